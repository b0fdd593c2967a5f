"""The tissue's surfaces for drawing: the skin and each lesion's boundary, as they deform."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from tissue.contact.surface_points import SurfacePoints
from tissue.lesions import LesionTracker
from tissue.mesh import TetMesh, boundary_faces


@dataclass(frozen=True)
class SurfaceMesh:
    """Triangles to draw, with a region per vertex and per triangle.

    Attributes:
        vertices_m: vertex positions [m], (vertex_count, 3).
        triangles: vertex indices, (triangle_count, 3), counter-clockwise seen from outside
            the region they bound (outward normals).
        vertex_region: region label per vertex, (vertex_count,): 0 the skin, k lesion k.
        triangle_region: region label per triangle, (triangle_count,).
    """

    vertices_m: NDArray[np.float64]
    triangles: NDArray[np.int64]
    vertex_region: NDArray[np.int64]
    triangle_region: NDArray[np.int64]


class SurfaceView:
    """Builds :class:`SurfaceMesh` es of a mesh's skin and lesions at any node positions.

    The skin is the collision surface (embedded in the volume: it moves with it), or the
    volume's boundary where the mesh has none; each lesion with tets adds the boundary of
    its tets (its vertices are mesh nodes). Point lesions add nothing.

    Args:
        mesh: the tissue mesh.
        skin: the skin's points and triangles.
        lesions: the mesh's lesions.
    """

    def __init__(self, mesh: TetMesh, skin: SurfacePoints, lesions: LesionTracker) -> None:
        self._skin = skin
        triangles = [skin.triangles]
        regions = [np.zeros(skin.triangles.shape[0], dtype=np.int64)]
        vertex_regions = [np.zeros(skin.count, dtype=np.int64)]
        nodes: list[NDArray[np.int64]] = []
        offset = skin.count
        for lesion in lesions.lesions:
            if lesion.tets.size == 0:
                continue
            faces = boundary_faces(mesh.tets[lesion.tets])
            used, local = np.unique(faces, return_inverse=True)
            triangles.append(local.reshape(-1, 3) + offset)
            regions.append(np.full(faces.shape[0], lesion.label, dtype=np.int64))
            vertex_regions.append(np.full(used.size, lesion.label, dtype=np.int64))
            nodes.append(used)
            offset += used.size
        self._nodes = np.concatenate(nodes) if nodes else np.zeros(0, dtype=np.int64)
        self._triangles = np.concatenate(triangles).astype(np.int64)
        self._triangle_region = np.concatenate(regions)
        self._vertex_region = np.concatenate(vertex_regions)

    def at(self, node_positions: NDArray[np.float64]) -> SurfaceMesh:
        """The surfaces with the nodes at ``node_positions`` [m] (node_count, 3)."""
        vertices = np.concatenate(
            [self._skin.positions(node_positions), node_positions[self._nodes]]
        )
        return SurfaceMesh(
            vertices,
            self._triangles.copy(),
            self._vertex_region.copy(),
            self._triangle_region.copy(),
        )
