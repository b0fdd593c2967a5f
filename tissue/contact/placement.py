"""Placing the probe on the skin: where a ray meets the surface, and the first-contact pose."""

from __future__ import annotations

import numba as nb
import numpy as np
from numpy.typing import NDArray

from tissue.contact.ray_grid import TriangleGrid, triangle_hit
from tissue.contact.surface_points import SurfacePoints, contact_surface
from tissue.errors import TissueInputError
from tissue.mesh import TetMesh
from tissue.probe import Probe, ProbeShape

# Iterations of the first-contact search; each removes the overlap found at the last pose.
_CONTACT_SEARCH_ITERATIONS = 8
# The first-contact search looks first at the skin points this close to the probe's box
# across its pressing axis [m] (a fine skin has thousands; those beside the probe cannot
# touch it as it moves along the axis).
_SEARCH_MARGIN_M = 0.002
# The first-contact search's step divides the gap by the probe normal's share along the
# pressing direction at the nearest point, at least this (past 60 degrees it moves by twice
# the gap and converges linearly, as on the probe's side).
_LEAST_FACING = 0.5
# Skin triangles within this distance of a skin point give its normal [m].
_NORMAL_RADIUS_M = 0.008


def ray_surface_hit(
    vertices: NDArray[np.float64],
    triangles: NDArray[np.int64],
    origin: NDArray[np.float64],
    direction: NDArray[np.float64],
) -> NDArray[np.float64] | None:
    """First point where the ray origin + t direction (t > 0) meets the triangles, or None.

    Möller & Trumbore (1997) ray-triangle intersection, in one compiled pass over the
    triangles.
    """
    direction = np.ascontiguousarray(direction / np.linalg.norm(direction), dtype=np.float64)
    origin = np.ascontiguousarray(origin, dtype=np.float64)
    t = _nearest_hit_indexed(
        np.ascontiguousarray(vertices, dtype=np.float64),
        np.ascontiguousarray(triangles, dtype=np.int64),
        origin,
        direction,
    )
    if not np.isfinite(t):
        return None
    return origin + t * direction


@nb.njit(cache=True)
def _area_normal_within(centroids, area_normals, point, radius):  # pragma: no cover
    """The sum of ``area_normals`` (t, 3) over the triangles whose ``centroids`` (t, 3) lie
    closer than ``radius`` [m] to ``point`` (3,), in one compiled pass (the NumPy mask over
    the 2 mm skin's 16,710 triangles took most of a ForceScan step's observation)."""
    reach = radius * radius
    total = np.zeros(3)
    for k in range(centroids.shape[0]):
        dx = centroids[k, 0] - point[0]
        dy = centroids[k, 1] - point[1]
        dz = centroids[k, 2] - point[2]
        if dx * dx + dy * dy + dz * dz < reach:
            for axis in range(3):
                total[axis] += area_normals[k, axis]
    return total


@nb.njit(cache=True)
def _nearest_hit_indexed(vertices, triangles, origin, direction):  # pragma: no cover
    """:func:`_nearest_hit_distance` over ``triangles`` (t, 3) of ``vertices`` (v, 3)."""
    best = np.inf
    corner = np.empty((1, 3))
    edge1 = np.empty((1, 3))
    edge2 = np.empty((1, 3))
    for k in range(triangles.shape[0]):
        a, b, c = triangles[k, 0], triangles[k, 1], triangles[k, 2]
        for axis in range(3):
            corner[0, axis] = vertices[a, axis]
            edge1[0, axis] = vertices[b, axis] - vertices[a, axis]
            edge2[0, axis] = vertices[c, axis] - vertices[a, axis]
        best = min(best, _nearest_hit_distance(corner, edge1, edge2, origin, direction))
    return best


@nb.njit(cache=True)
def _nearest_hit_distance(
    a: NDArray[np.float64],
    edge1: NDArray[np.float64],
    edge2: NDArray[np.float64],
    origin: NDArray[np.float64],
    direction: NDArray[np.float64],
) -> float:
    """The smallest t > 0 with origin + t direction on a triangle (Möller-Trumbore), inf if
    none: every triangle tested."""
    best = np.inf
    for k in range(a.shape[0]):
        best = min(best, triangle_hit(a, edge1, edge2, k, origin, direction))
    return best


def first_contact_pose(
    surface: SurfacePoints,
    node_positions: NDArray[np.float64],
    shape: ProbeShape,
    target_point: NDArray[np.float64],
    direction: NDArray[np.float64],
    roll_rad: float = 0.0,
    rest_skin: RestSkin | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The pose at which the probe, pressing along ``direction``, first touches the surface.

    The probe's face centre is aimed at the skin point where the line through
    ``target_point`` along ``direction`` enters the surface; the probe is then backed off
    along ``direction`` until no surface point lies inside it and one touches it.
    ``rest_skin``: the same surface at rest, whose grid finds that point (for
    ``node_positions`` at rest; None: every triangle is tested).

    Returns:
        (position [m] (3,), quaternion wxyz (4,)).
    """
    direction = np.asarray(direction, dtype=np.float64)
    norm = float(np.linalg.norm(direction))
    if not np.isfinite(norm) or norm == 0.0:
        raise TissueInputError(f"the pressing direction must be a non-zero vector; got {direction}")
    direction = direction / norm
    vertices = surface.positions(node_positions)
    extent = float(np.max(np.ptp(node_positions, axis=0)))
    origin = np.asarray(target_point, dtype=np.float64) - 2.0 * extent * direction
    if rest_skin is None:
        hit = ray_surface_hit(vertices, surface.triangles, origin, direction)
    else:
        t = rest_skin.nearest_hit(origin, direction)
        hit = origin + t * direction if np.isfinite(t) else None
    if hit is None:
        raise TissueInputError(
            f"the line through {np.round(target_point, 4).tolist()} along "
            f"{np.round(direction, 3).tolist()} misses the tissue surface; choose a point "
            "above the tissue (--at X,Y within its footprint)"
        )
    probe = Probe.looking_along(shape, hit, direction, roll_rad=roll_rad)
    position = probe.position_world.copy()
    # The search moves the probe along its pressing axis (the probe frame's y) by the
    # overlap each time: the skin points that can set it lie across that axis from the
    # probe's box, within a margin, at any height. The others are checked at the end, and
    # the search goes on over all points should one of them be closest.
    across = probe.to_probe_frame(vertices)[:, [0, 2]]
    bounds = probe.shape.local_bounds_m()[:, [0, 2]]
    candidates = vertices[
        np.all(
            (across >= bounds[0] - _SEARCH_MARGIN_M) & (across <= bounds[1] + _SEARCH_MARGIN_M),
            axis=1,
        )
    ]
    for points in (candidates, vertices):
        if points.shape[0] == 0:
            continue
        for _ in range(_CONTACT_SEARCH_ITERATIONS):
            probe.set_pose(position, probe.quat_wxyz)
            distance, normals = probe.signed_distance_world(points)
            nearest = int(np.argmin(distance))
            closest = float(distance[nearest])
            if abs(closest) < 1e-9:
                break
            # Back off by the overlap, or close the gap: moved along the direction, the
            # probe's surface meets the point at the rate its normal faces the direction
            # (1 on the face, less on the rounded rim; a Newton step), at least half.
            facing = max(float(normals[nearest] @ direction), _LEAST_FACING)
            position = position + (closest / facing) * direction
        probe.set_pose(position, probe.quat_wxyz)
        if points is not vertices:
            distance, _ = probe.signed_distance_world(vertices)
            if abs(float(distance.min())) < 1e-9:
                break
    return position, probe.quat_wxyz.copy()


def radial_roll_rad(shape: ProbeShape, direction: NDArray[np.float64]) -> float:
    """Roll that lays the probe's long axis down the skin's slope (a radial scan plane).

    Breast sonographers scan radially; on the dome's flanks it also gives frictionless
    tissue 53 mm of face to cross, not 13 mm, before it can slip out downhill. Zero where
    the skin is level.
    """
    probe = Probe.looking_along(shape, np.zeros(3), direction)
    rotation = probe.rotation_world()
    x_axis, z_axis = rotation[:, 0], rotation[:, 2]
    down = np.array([0.0, 0.0, -1.0])
    downhill = down - (down @ direction) * direction
    if np.linalg.norm(downhill) < 1e-6:
        return 0.0
    # looking_along rolls x towards -z: the roll taking x onto the downhill direction.
    return float(np.arctan2(-(downhill @ z_axis), downhill @ x_axis))


class RestSkin:
    """The skin at rest (the collision surface, or the volume's boundary) for ray queries,
    its triangles' corners and area normals, and a grid over them
    (:class:`tissue.contact.ray_grid.TriangleGrid`), computed once.

    Args:
        mesh: the tissue mesh.
    """

    def __init__(self, mesh: TetMesh) -> None:
        surface = contact_surface(mesh)
        collision = mesh.collision_surface
        vertices = (
            collision.rest_vertices if collision is not None else surface.positions(mesh.nodes)
        )
        self.vertices = vertices
        self.triangles = surface.triangles
        a, b, c = (vertices[surface.triangles[:, i]] for i in range(3))
        self._grid = TriangleGrid(a, b - a, c - a)
        self._area_normals = 0.5 * np.cross(b - a, c - a)
        self._centroids = (a + b + c) / 3.0

    def nearest_hit(self, origin: NDArray[np.float64], direction: NDArray[np.float64]) -> float:
        """The smallest t > 0 with ``origin`` + t ``direction`` on the skin at rest, inf if
        none (:meth:`tissue.contact.ray_grid.TriangleGrid.nearest_hit`)."""
        return self._grid.nearest_hit(origin, direction)

    def normal_where_leaving(
        self, point: NDArray[np.float64], up: NDArray[np.float64] | None = None
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Where the line through ``point`` along ``up`` (default +z) leaves the skin [m],
        (3,), and the outward unit normal there, area-weighted over the triangles within 8 mm,
        (3,).

        Raises:
            TissueInputError: the ray from ``point`` along ``up`` meets no skin.
        """
        direction = np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, dtype=np.float64)
        direction = direction / np.linalg.norm(direction)
        origin = np.asarray(point, dtype=np.float64)
        t = self.nearest_hit(origin, direction)
        if not np.isfinite(t):
            raise TissueInputError(
                f"no skin above the point {np.round(origin, 4).tolist()} along "
                f"{np.round(direction, 3).tolist()}; choose a point inside the tissue"
            )
        hit = origin + t * direction
        normal = _area_normal_within(self._centroids, self._area_normals, hit, _NORMAL_RADIUS_M)
        return hit, normal / np.linalg.norm(normal)


def skin_normal_above(
    mesh: TetMesh, point: NDArray[np.float64], up: NDArray[np.float64] | None = None
) -> NDArray[np.float64]:
    """Outward unit normal of the skin (the collision surface, or the volume's boundary) at
    rest, where the line through ``point`` along ``up`` (default +z) leaves it, area-weighted
    over the triangles within 8 mm, shape (3,) (:meth:`RestSkin.normal_where_leaving`)."""
    return RestSkin(mesh).normal_where_leaving(point, up)[1]
