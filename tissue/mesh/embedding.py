"""Barycentric embedding of points (collision-surface vertices, landmarks) in a tet mesh."""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

# Candidate tets tried per point, nearest by centroid.
_CANDIDATE_COUNT = 48


@dataclass(frozen=True)
class BarycentricEmbedding:
    """Points expressed as barycentric combinations of the nodes of one tet each.

    Attributes:
        tet_nodes: node indices of each point's tet, shape (point_count, 4).
        weights: barycentric weights, shape (point_count, 4), summing to 1. Points just
            outside the mesh get the least-extrapolating tet (some weights slightly < 0).
    """

    tet_nodes: NDArray[np.int64]
    weights: NDArray[np.float64]

    def interpolate(self, node_values: NDArray[np.float64]) -> NDArray[np.float64]:
        """Values at the points, shape (point_count, k), from node values (node_count, k)."""
        values = np.asarray(node_values)
        if values.dtype != np.float64 or values.ndim != 2:
            return np.einsum("pk,pkd->pd", self.weights, values[self.tet_nodes])
        # A compiled loop: a step interpolates the collision surface several times, and
        # gathering (points, 4, k) for einsum cost 15-27 us a call at ~500 points, ~5 here.
        out = np.empty((self.tet_nodes.shape[0], values.shape[1]))
        _interpolate(self.tet_nodes, self.weights, values, out)
        return out

    def spread(self, point_values: NDArray[np.float64], node_count: int) -> NDArray[np.float64]:
        """Transpose of :meth:`interpolate`: distribute point forces (point_count, 3) to nodes.

        Returns:
            node values, shape (node_count, 3). Forces spread this way do the same virtual
            work as the point forces.
        """
        out = np.zeros((node_count, point_values.shape[1]))
        np.add.at(out, self.tet_nodes, self.weights[:, :, None] * point_values[:, None, :])
        return out


def barycentric_coordinates(
    positions: NDArray[np.float64], tets: NDArray[np.int64], points: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Barycentric coordinates of points[i] in tets[i]: shape (count, 4)."""
    x0 = positions[tets[:, 0]]
    basis = np.stack(
        [positions[tets[:, 1]] - x0, positions[tets[:, 2]] - x0, positions[tets[:, 3]] - x0], axis=2
    )
    local = np.linalg.solve(basis, (points - x0)[:, :, None])[:, :, 0]
    return np.column_stack([1.0 - local.sum(axis=1), local])


def embed_points(
    node_positions: NDArray[np.float64], tets: NDArray[np.int64], points: NDArray[np.float64]
) -> BarycentricEmbedding:
    """Embed points [m], shape (point_count, 3), in the tets of a mesh.

    Each point gets the tet, among those with the nearest centroids, whose smallest
    barycentric coordinate is largest: the containing tet when there is one, otherwise the
    one that extrapolates least (for surface points lying just outside a coarse volume).
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if points.shape[0] == 0:
        return BarycentricEmbedding(np.zeros((0, 4), np.int64), np.zeros((0, 4)))
    centroids = node_positions[tets].mean(axis=1)
    k = min(_CANDIDATE_COUNT, tets.shape[0])
    _, candidates = cKDTree(centroids).query(points, k=k)
    candidates = np.asarray(candidates).reshape(points.shape[0], k)
    flat_tets = candidates.reshape(-1)
    flat_points = np.repeat(points, k, axis=0)
    bary = barycentric_coordinates(node_positions, tets[flat_tets], flat_points)
    worst = bary.min(axis=1).reshape(points.shape[0], k)
    best = np.argmax(worst, axis=1)
    rows = np.arange(points.shape[0])
    chosen = candidates[rows, best]
    weights = bary.reshape(points.shape[0], k, 4)[rows, best]
    return BarycentricEmbedding(tet_nodes=tets[chosen].astype(np.int64), weights=weights)


@numba.njit(cache=True)
def _interpolate(tet_nodes, weights, values, out):  # pragma: no cover - compiled
    """out[p] = sum_a weights[p, a] values[tet_nodes[p, a]]."""
    for p in range(tet_nodes.shape[0]):
        for d in range(values.shape[1]):
            acc = 0.0
            for a in range(4):
                acc += weights[p, a] * values[tet_nodes[p, a], d]
            out[p, d] = acc
