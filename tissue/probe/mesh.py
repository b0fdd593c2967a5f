"""Probes from closed triangle meshes: exact point-triangle distance, sign by winding.

For small tool meshes (tens to a few thousand triangles), such as the published
``us_probe_collision.stl``: brute force over triangles in numba, O(points x triangles).
"""

from __future__ import annotations

import math
from pathlib import Path

import numba as nb
import numpy as np
from numpy.typing import ArrayLike, NDArray

from tissue.errors import ConfigError, MeshError
from tissue.probe.shape import (
    LARGEST_PLAUSIBLE_SIZE_M,
    PROBE_SPEC_FORMS,
    ProbeShape,
    as_points,
)
from tissue.probe.triangle import closest_point_on_triangle
from tissue.threads import parallel_kernel


@nb.njit(cache=True, inline="always")
def _solid_angle(px, py, pz, t, corners):  # pragma: no cover - compiled
    """Signed solid angle of triangle t seen from p (Van Oosterom and Strackee, 1983)."""
    ax, ay, az = corners[t, 0, 0] - px, corners[t, 0, 1] - py, corners[t, 0, 2] - pz
    bx, by, bz = corners[t, 1, 0] - px, corners[t, 1, 1] - py, corners[t, 1, 2] - pz
    cx, cy, cz = corners[t, 2, 0] - px, corners[t, 2, 1] - py, corners[t, 2, 2] - pz
    la = math.sqrt(ax * ax + ay * ay + az * az)
    lb = math.sqrt(bx * bx + by * by + bz * bz)
    lc = math.sqrt(cx * cx + cy * cy + cz * cz)
    triple = ax * (by * cz - bz * cy) - ay * (bx * cz - bz * cx) + az * (bx * cy - by * cx)
    below = (
        la * lb * lc
        + (ax * bx + ay * by + az * bz) * lc
        + (ax * cx + ay * cy + az * cz) * lb
        + (bx * cx + by * cy + bz * cz) * la
    )
    return 2.0 * math.atan2(triple, below)


@parallel_kernel
def _mesh_signed_distance(
    points, corners, face_normals, lower, upper, distance, normal
):  # pragma: no cover
    """Exact unsigned distance by brute force over triangles; sign by winding number.

    ``corners`` is (t, 3, 3). The winding number (sum of signed solid angles over 4 pi) is
    1 inside a closed outward mesh and 0 outside; unlike a pseudo-normal test it does not
    depend on which feature (face, edge, vertex) the closest point lies on. It is only
    needed for points nearest an edge or a vertex and inside the bounding box
    [lower, upper]: the solid angles cost as much as the distances.
    """
    triangle_count = corners.shape[0]
    for i in nb.prange(points.shape[0]):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        best = np.inf
        qx, qy, qz = px, py, pz
        best_triangle = 0
        best_in_face = False
        solid_angle = 0.0
        for t in range(triangle_count):
            cx, cy, cz, in_face = closest_point_on_triangle(px, py, pz, t, corners)
            squared = (px - cx) ** 2 + (py - cy) ** 2 + (pz - cz) ** 2
            if squared < best:
                best = squared
                qx, qy, qz = cx, cy, cz
                best_triangle = t
                best_in_face = in_face
        inside = False
        if best_in_face:
            # Nearest to a face's interior: the segment to it crosses no surface, so that
            # face's normal gives the side exactly and the winding number is not needed.
            inside = (
                (px - qx) * face_normals[best_triangle, 0]
                + (py - qy) * face_normals[best_triangle, 1]
                + (pz - qz) * face_normals[best_triangle, 2]
            ) < 0.0
        elif (
            lower[0] <= px <= upper[0] and lower[1] <= py <= upper[1] and lower[2] <= pz <= upper[2]
        ):
            for t in range(triangle_count):
                solid_angle += _solid_angle(px, py, pz, t, corners)
            inside = solid_angle > 2.0 * math.pi
        length = math.sqrt(best)
        distance[i] = -length if inside else length
        # The SDF's gradient: away from the closest point outside, towards it inside. On
        # the surface itself that direction is undefined, so take the triangle's normal.
        if length > 1e-12:
            scale = (-1.0 if inside else 1.0) / length
            normal[i, 0] = scale * (px - qx)
            normal[i, 1] = scale * (py - qy)
            normal[i, 2] = scale * (pz - qz)
        else:
            normal[i, 0] = face_normals[best_triangle, 0]
            normal[i, 1] = face_normals[best_triangle, 1]
            normal[i, 2] = face_normals[best_triangle, 2]


class MeshProbe(ProbeShape):
    """Any closed (watertight) triangle mesh, given in the probe frame.

    The mesh is used in its own coordinates: it should follow the frame convention (contact
    face at y = 0, body at y < 0, pressing along +y), as ``us_probe_collision.stl`` does.
    An inside-out mesh (negative volume) is flipped. Signed distance is exact: the distance
    to the nearest triangle (brute force, O(points x triangles), meant for small tool
    meshes of tens to a few thousand triangles) signed by the winding number.

    Args:
        vertices: positions [m], shape (v, 3).
        triangles: vertex indices, shape (t, 3).
        name: description for messages; defaults to the triangle count.

    Raises:
        MeshError: wrong shapes, non-finite values, a mesh that is not closed or encloses
            no volume, or one far too large to be in metres.
    """

    def __init__(self, vertices: ArrayLike, triangles: ArrayLike, name: str | None = None) -> None:
        import trimesh

        v = np.asarray(vertices, dtype=np.float64)
        f = np.asarray(triangles)
        if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
            raise MeshError(
                f"a probe mesh needs vertices of shape (v, 3) and triangles of shape (t, 3); "
                f"got {v.shape} and {f.shape}"
            )
        if not np.all(np.isfinite(v)):
            raise MeshError("probe mesh vertices contain NaN or infinite values")
        if not np.issubdtype(f.dtype, np.integer) or f.min() < 0 or f.max() >= len(v):
            raise MeshError(
                f"probe mesh triangles must be integer indices in [0, {len(v) - 1}]; "
                f"got dtype {f.dtype} and range [{f.min()}, {f.max()}]"
            )
        label = name or f"mesh:{len(f)} triangles"
        # process=True merges the duplicated corners that STL files store per triangle, so
        # the watertightness test sees shared edges.
        mesh = trimesh.Trimesh(vertices=v, faces=f, process=True)
        if not mesh.is_watertight:
            open_edges = len(trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1))
            raise MeshError(
                f"probe mesh {label} is not closed: {open_edges} edges belong to a single "
                f"triangle (or edges are shared by more than two). A probe mesh must be "
                f"watertight so that inside and outside are defined; close it (for example "
                f"trimesh.repair.fill_holes) or use an analytic probe: "
                f"{', '.join(PROBE_SPEC_FORMS[:4])}"
            )
        if not mesh.is_winding_consistent:
            trimesh.repair.fix_winding(mesh)
        if abs(mesh.volume) <= 0.0:
            raise MeshError(f"probe mesh {label} encloses no volume")
        if mesh.volume < 0.0:
            mesh.invert()
        extent = float(np.max(mesh.extents))
        if extent > LARGEST_PLAUSIBLE_SIZE_M:
            raise MeshError(
                f"probe mesh {label} is {extent:g} units across; probe meshes are in metres "
                f"(a millimetre file needs scale=0.001)"
            )
        self.name = label
        self.vertices = np.ascontiguousarray(mesh.vertices, dtype=np.float64)
        self.triangles = np.ascontiguousarray(mesh.faces, dtype=np.int64)
        self._corners = np.ascontiguousarray(self.vertices[self.triangles])
        self._face_normals = np.ascontiguousarray(mesh.face_normals, dtype=np.float64)
        self.bounding_radius_m = float(np.max(np.linalg.norm(self.vertices, axis=1)))
        self._lower = self.vertices.min(axis=0)
        self._upper = self.vertices.max(axis=0)

    @property
    def triangle_count(self) -> int:
        return int(self.triangles.shape[0])

    def signed_distance(
        self, points: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        p = as_points(points)
        distance = np.empty(p.shape[0])
        normal = np.empty((p.shape[0], 3))
        if p.shape[0]:
            _mesh_signed_distance(
                p, self._corners, self._face_normals, self._lower, self._upper, distance, normal
            )
        return distance, normal

    def distance_hessian(self, points: NDArray[np.float64]) -> NDArray[np.float64]:
        """Zeros, shape (n, 3, 3): the normal is the nearest triangle's, constant over a face
        and jumping at edges, so a triangle mesh has no curvature to give (a contact on one
        of its edges converges linearly in Newton)."""
        return np.zeros((as_points(points).shape[0], 3, 3))

    def surface(self) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        return self.vertices, self.triangles


def load_probe_mesh(path: str | Path, scale: float = 1.0) -> MeshProbe:
    """Load a closed probe mesh (STL, OBJ, PLY, ...) with trimesh.

    Args:
        path: mesh file, coordinates in the probe frame.
        scale: factor to metres (0.001 for a file in millimetres).

    Returns:
        the mesh probe, vertices [m].

    Raises:
        ConfigError: the file is missing or is not a single triangle mesh.
        MeshError: the mesh is not closed or not in metres (see :class:`MeshProbe`).
    """
    import trimesh

    file = Path(path)
    if not file.is_file():
        raise ConfigError(f"probe mesh file {str(path)!r} does not exist")
    factor = float(scale)
    if not math.isfinite(factor) or factor <= 0.0:
        raise ConfigError(f"probe mesh scale must be a positive number; got {scale!r}")
    try:
        loaded = trimesh.load(file, force="mesh")
    except Exception as error:  # trimesh raises many types for unreadable files
        raise ConfigError(f"cannot read probe mesh {str(path)!r}: {error}") from error
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise ConfigError(f"probe mesh {str(path)!r} holds no triangles")
    return MeshProbe(loaded.vertices * factor, loaded.faces, name=f"mesh:{file.name}")
