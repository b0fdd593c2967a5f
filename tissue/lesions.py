"""The lesions of a tissue: where they are at rest, and their deformed centroids.

A lesion is a region of the mesh (label k >= 1, its own stiffer material) or, on meshes that
carry lesions only as tracked points (the published scene: one point per tumour, the contour
point closest to the probe, no lesion sub-volume), a point lesion with no tets.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from numpy.typing import NDArray

from tissue.mesh import TetMesh


@dataclass(frozen=True)
class Lesion:
    """One lesion.

    Attributes:
        label: its number, 1-based (its region label where it has tets).
        name: its name (``lesion_3``, ``tumor1``).
        rest_centre_m: its centre at rest [m], (3,): the volume-weighted centroid of its
            tets (what :meth:`LesionTracker.centroids` gives at rest), or a point lesion's
            tracked point.
        radius_m: its radius [m]: the phantom's specified radius (its tets keep that
            sphere's volume), else the radius of the sphere of its tets' volume; 0 for a
            point lesion.
        tets: indices of its tets, (k,) (empty for a point lesion).
    """

    label: int
    name: str
    rest_centre_m: NDArray[np.float64]
    radius_m: float
    tets: NDArray[np.int64]


class LesionTracker:
    """The lesions of a mesh and their deformed centroids.

    A lesion with tets moves with their volume-weighted centroid (exact for the deformed
    piecewise-linear geometry); a point lesion with its landmark (barycentric embedding).

    Args:
        mesh: the tissue mesh.
    """

    def __init__(self, mesh: TetMesh) -> None:
        self._mesh = mesh
        lesions: list[Lesion] = []
        given = mesh.metadata.get("lesion_radii_m")
        radii = None if given is None else np.asarray(given, dtype=np.float64).reshape(-1)
        volumes = mesh.tet_volumes()
        for label in range(1, len(mesh.region_names)):
            tets = np.flatnonzero(mesh.region == label)
            if tets.size == 0:
                continue
            weight = volumes[tets]
            centroid = (weight[:, None] * mesh.nodes[mesh.tets[tets]].mean(axis=1)).sum(
                axis=0
            ) / weight.sum()
            radius = float((3.0 * weight.sum() / (4.0 * np.pi)) ** (1.0 / 3.0))
            if radii is not None and radii.size >= label:
                radius = float(radii[label - 1])
            lesions.append(Lesion(label, mesh.region_names[label], centroid, radius, tets))
        self._point_landmarks = np.zeros(0, dtype=np.int64)
        if not lesions and mesh.landmarks is not None:
            # Lesions known only as tracked points.
            for index, name in enumerate(mesh.landmarks.names):
                rest = mesh.landmarks.rest_positions[index].copy()
                lesions.append(Lesion(index + 1, name, rest, 0.0, np.zeros(0, dtype=np.int64)))
            self._point_landmarks = np.arange(len(lesions), dtype=np.int64)
        self.lesions: tuple[Lesion, ...] = tuple(lesions)
        # All lesion tets in one array, and which lesion each belongs to.
        if lesions and self._point_landmarks.size == 0:
            self._tets = mesh.tets[np.concatenate([lesion.tets for lesion in lesions])]
            self._owner = np.repeat(
                np.arange(len(lesions)), [lesion.tets.size for lesion in lesions]
            )
        else:
            self._tets = np.zeros((0, 4), dtype=np.int64)
            self._owner = np.zeros(0, dtype=np.int64)
        # Lesion k's tets are self._tets[self._starts[k]:self._starts[k + 1]].
        self._starts = np.searchsorted(self._owner, np.arange(len(lesions) + 1)).astype(np.int64)

    @property
    def count(self) -> int:
        return len(self.lesions)

    def centroids(
        self, node_positions: NDArray[np.float64], which: NDArray[np.int64] | None = None
    ) -> NDArray[np.float64]:
        """Deformed lesion centroids [m] from node positions [m]: every lesion's,
        (lesion_count, 3), or those of the lesions ``which`` (indices into
        :attr:`lesions`), (len(which), 3), and no other lesion's tets are read."""
        if self._point_landmarks.size:
            landmarks = self._mesh.landmarks
            assert landmarks is not None
            points = landmarks.positions(node_positions)[self._point_landmarks]
            return points if which is None else points[which]
        if which is None:
            which = np.arange(len(self.lesions), dtype=np.int64)
        if which.size == 0:
            return np.zeros((0, 3))
        return _volume_centroids(
            np.ascontiguousarray(node_positions), self._tets, self._starts, which
        )


@numba.njit(cache=True)
def _volume_centroids(
    positions: NDArray[np.float64],
    tets: NDArray[np.int64],
    starts: NDArray[np.int64],
    which: NDArray[np.int64],
) -> NDArray[np.float64]:  # pragma: no cover - compiled
    """The volume-weighted centroids of lesions ``which`` [m], (len(which), 3): for each,
    the sum over its tets (``tets[starts[k]:starts[k + 1]]``) of signed volume x corner
    mean, over its volume. Compiled: it runs every tissue step (about 100 us as NumPy for
    the 1,363 level's 10 lesions, 11 us here)."""
    out = np.zeros((which.size, 3))
    for row in range(which.size):
        k = which[row]
        total = 0.0
        for t in range(starts[k], starts[k + 1]):
            a, b, c, d = tets[t, 0], tets[t, 1], tets[t, 2], tets[t, 3]
            e1 = positions[b] - positions[a]
            e2 = positions[c] - positions[a]
            e3 = positions[d] - positions[a]
            volume = (
                e1[0] * (e2[1] * e3[2] - e2[2] * e3[1])
                + e1[1] * (e2[2] * e3[0] - e2[0] * e3[2])
                + e1[2] * (e2[0] * e3[1] - e2[1] * e3[0])
            ) / 6.0
            total += volume
            for axis in range(3):
                mean = 0.25 * (
                    positions[a, axis]
                    + positions[b, axis]
                    + positions[c, axis]
                    + positions[d, axis]
                )
                out[row, axis] += volume * mean
        for axis in range(3):
            out[row, axis] /= total
    return out
