"""The points contact acts on: a collision surface embedded in the volume, found near the
probe without placing the whole surface.

:func:`contact_surface` gives a mesh's collision surface (or its volume's boundary), each
point a barycentric combination of one tet's nodes (:class:`SurfacePoints`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numba as nb
import numpy as np
from numpy.typing import NDArray

from tissue.mesh import TetMesh, boundary_faces
from tissue.mesh.embedding import BarycentricEmbedding
from tissue.probe import Probe


@dataclass(frozen=True)
class SurfacePoints:
    """The tissue points contact acts on: collision-surface vertices embedded in the volume.

    A collision surface at the probe's scale has thousands of points (8,357 at a 2 mm edge on
    the phantom) of which a step's contact concerns a few dozen: :meth:`near` finds those
    without placing the others. The points are grouped by the tet that holds them; a point
    is an affine combination of its tet's four nodes, so it lies within (the sum of its
    weights' magnitudes) x (the largest distance of a node from the nodes' centroid) of that
    centroid, and a tet whose ball so bounded misses the probe's box holds no point near it.

    Attributes:
        embedding: barycentric map from volume nodes to the points.
        triangles: the surface's triangles over the points (outward), (t, 3).
    """

    embedding: BarycentricEmbedding
    triangles: NDArray[np.int64]
    _hosts: _Hosts = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "_hosts", _Hosts.of(self.embedding))

    @property
    def count(self) -> int:
        return int(self.embedding.weights.shape[0])

    def positions(self, node_positions: NDArray[np.float64]) -> NDArray[np.float64]:
        """Every point's position [m], (count, 3), from node positions [m] (n, 3)."""
        return self.embedding.interpolate(node_positions)

    def positions_of(
        self, node_positions: NDArray[np.float64], points: NDArray[np.int64]
    ) -> NDArray[np.float64]:
        """The positions [m] (k, 3) of the points ``points`` (k,) alone."""
        out = np.empty((points.size, 3))
        _interpolate_some(
            self.embedding.tet_nodes,
            self.embedding.weights,
            np.ascontiguousarray(node_positions, dtype=np.float64),
            np.ascontiguousarray(points, dtype=np.int64),
            out,
        )
        return out

    def near(
        self, node_positions: NDArray[np.float64], probe: Probe, margin_m: float
    ) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """The points within the probe's local bounding box widened by ``margin_m`` [m]
        (:meth:`tissue.probe.Probe.near`), in increasing order, and their positions [m]:
        ((k,), (k, 3)). Only the points of tets near the probe are placed."""
        hosts = self._hosts
        indices = np.empty(self.count, dtype=np.int64)
        positions = np.empty((self.count, 3))
        count = _near_points(
            np.ascontiguousarray(node_positions, dtype=np.float64),
            hosts.nodes,
            hosts.spread,
            hosts.offsets,
            hosts.points,
            self.embedding.tet_nodes,
            self.embedding.weights,
            probe.position_world,
            probe.rotation_world(),
            probe.local_bounds_m(),
            float(margin_m),
            indices,
            positions,
        )
        order = np.argsort(indices[:count], kind="stable")
        return indices[:count][order], positions[:count][order]


@dataclass(frozen=True)
class _Hosts:
    """The points of a :class:`SurfacePoints` grouped by the tet holding them.

    Attributes:
        nodes: each holding tet's four nodes, (h, 4).
        spread: the largest sum of weight magnitudes of its points (>= 1), (h,).
        offsets: tet j holds ``points[offsets[j]:offsets[j + 1]]``, (h + 1,).
        points: point indices grouped by tet, (point_count,).
    """

    nodes: NDArray[np.int64]
    spread: NDArray[np.float64]
    offsets: NDArray[np.int64]
    points: NDArray[np.int64]

    @classmethod
    def of(cls, embedding: BarycentricEmbedding) -> _Hosts:
        tet_nodes = np.ascontiguousarray(embedding.tet_nodes, dtype=np.int64)
        if tet_nodes.shape[0] == 0:
            empty = np.zeros(0, dtype=np.int64)
            return cls(np.zeros((0, 4), np.int64), np.zeros(0), np.zeros(1, np.int64), empty)
        nodes, host = np.unique(tet_nodes, axis=0, return_inverse=True)
        host = host.reshape(-1)
        points = np.argsort(host, kind="stable").astype(np.int64)
        offsets = np.zeros(nodes.shape[0] + 1, dtype=np.int64)
        np.cumsum(np.bincount(host, minlength=nodes.shape[0]), out=offsets[1:])
        spread = np.zeros(nodes.shape[0])
        np.maximum.at(spread, host, np.abs(embedding.weights).sum(axis=1))
        return cls(np.ascontiguousarray(nodes), spread, offsets, points)


def contact_surface(mesh: TetMesh) -> SurfacePoints:
    """The mesh's collision surface, or its boundary faces (identity embedding) if it has none."""
    if mesh.collision_surface is not None:
        surface = mesh.collision_surface
        return SurfacePoints(surface.embedding, surface.triangles)
    return boundary_surface(mesh)


def boundary_surface(mesh: TetMesh) -> SurfacePoints:
    """The volume's boundary faces as contact points (each node embedded with weight 1)."""
    faces = boundary_faces(mesh.tets)
    vertices = np.unique(faces)
    # Each boundary node is "embedded" in one tet that contains it, with weight 1 on itself.
    owner = np.full(mesh.node_count, -1, dtype=np.int64)
    corner = np.zeros(mesh.node_count, dtype=np.int64)
    for local in range(4):
        owner[mesh.tets[:, local]] = np.arange(mesh.tet_count)
        corner[mesh.tets[:, local]] = local
    tet_nodes = mesh.tets[owner[vertices]]
    weights = np.zeros((vertices.size, 4))
    weights[np.arange(vertices.size), corner[vertices]] = 1.0
    remap = np.full(mesh.node_count, -1, dtype=np.int64)
    remap[vertices] = np.arange(vertices.size)
    return SurfacePoints(BarycentricEmbedding(tet_nodes, weights), remap[faces])


@nb.njit(cache=True)
def _interpolate_some(tet_nodes, weights, x, points, out):  # pragma: no cover - compiled
    """out[i] = the position of point ``points[i]`` from node positions ``x``."""
    for i in range(points.shape[0]):
        p = points[i]
        for d in range(3):
            acc = 0.0
            for a in range(4):
                acc += weights[p, a] * x[tet_nodes[p, a], d]
            out[i, d] = acc


@nb.njit(cache=True)
def _near_points(
    x,
    host_nodes,
    spread,
    offsets,
    host_points,
    tet_nodes,
    weights,
    origin,
    rotation,
    bounds,
    margin,
    out_indices,
    out_positions,
):  # pragma: no cover - compiled
    """Writes the points within ``bounds`` (the probe-frame box, (2, 3)) widened by
    ``margin`` and their positions to the outputs, tet by tet; returns their count."""
    found = 0
    for h in range(host_nodes.shape[0]):
        cx = 0.0
        cy = 0.0
        cz = 0.0
        for a in range(4):
            n = host_nodes[h, a]
            cx += 0.25 * x[n, 0]
            cy += 0.25 * x[n, 1]
            cz += 0.25 * x[n, 2]
        radius2 = 0.0
        for a in range(4):
            n = host_nodes[h, a]
            dx = x[n, 0] - cx
            dy = x[n, 1] - cy
            dz = x[n, 2] - cz
            radius2 = max(radius2, dx * dx + dy * dy + dz * dz)
        reach = margin + spread[h] * np.sqrt(radius2)
        missed = False
        for axis in range(3):
            value = (
                (cx - origin[0]) * rotation[0, axis]
                + (cy - origin[1]) * rotation[1, axis]
                + (cz - origin[2]) * rotation[2, axis]
            )
            if value < bounds[0, axis] - reach or value > bounds[1, axis] + reach:
                missed = True
                break
        if missed:
            continue
        for k in range(offsets[h], offsets[h + 1]):
            p = host_points[k]
            px = 0.0
            py = 0.0
            pz = 0.0
            for a in range(4):
                n = tet_nodes[p, a]
                w = weights[p, a]
                px += w * x[n, 0]
                py += w * x[n, 1]
                pz += w * x[n, 2]
            inside = True
            for axis in range(3):
                value = (
                    (px - origin[0]) * rotation[0, axis]
                    + (py - origin[1]) * rotation[1, axis]
                    + (pz - origin[2]) * rotation[2, axis]
                )
                if value < bounds[0, axis] - margin or value > bounds[1, axis] + margin:
                    inside = False
                    break
            if inside:
                out_indices[found] = p
                out_positions[found, 0] = px
                out_positions[found, 1] = py
                out_positions[found, 2] = pz
                found += 1
    return found
