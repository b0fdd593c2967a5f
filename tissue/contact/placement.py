"""Placing the probe on the skin: where a ray meets the surface, and the first-contact pose."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from tissue.contact.base import SurfacePoints, contact_surface
from tissue.errors import TissueInputError
from tissue.mesh import TetMesh
from tissue.probe import Probe, ProbeShape

# Iterations of the first-contact search; each removes the overlap found at the last pose.
_CONTACT_SEARCH_ITERATIONS = 8
# Skin triangles within this distance of a skin point give its normal [m].
_NORMAL_RADIUS_M = 0.008


def ray_surface_hit(
    vertices: NDArray[np.float64],
    triangles: NDArray[np.int64],
    origin: NDArray[np.float64],
    direction: NDArray[np.float64],
) -> NDArray[np.float64] | None:
    """First point where the ray origin + t direction (t > 0) meets the triangles, or None.

    Möller & Trumbore (1997) ray-triangle intersection, vectorised over the triangles.
    """
    direction = direction / np.linalg.norm(direction)
    a, b, c = (vertices[triangles[:, i]] for i in range(3))
    edge1, edge2 = b - a, c - a
    p = np.cross(direction, edge2)
    det = np.einsum("ij,ij->i", edge1, p)
    ok = np.abs(det) > 1e-18
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = origin - a
    u = np.einsum("ij,ij->i", s, p) * inv
    q = np.cross(s, edge1)
    v = (q @ direction) * inv
    t = np.einsum("ij,ij->i", edge2, q) * inv
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
    if not np.any(hit):
        return None
    return origin + float(t[hit].min()) * direction


def first_contact_pose(
    surface: SurfacePoints,
    node_positions: NDArray[np.float64],
    shape: ProbeShape,
    target_point: NDArray[np.float64],
    direction: NDArray[np.float64],
    roll_rad: float = 0.0,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The pose at which the probe, pressing along ``direction``, first touches the surface.

    The probe's face centre is aimed at the skin point where the line through
    ``target_point`` along ``direction`` enters the surface; the probe is then backed off
    along ``direction`` until no surface point lies inside it and one touches it.

    Returns:
        (position [m] (3,), quaternion wxyz (4,)).
    """
    direction = np.asarray(direction, dtype=np.float64)
    norm = float(np.linalg.norm(direction))
    if not np.isfinite(norm) or norm == 0.0:
        raise TissueInputError(f"the pressing direction must be a non-zero vector; got {direction}")
    direction = direction / norm
    vertices = surface.positions(node_positions)
    extent = float(np.max(np.ptp(vertices, axis=0)))
    origin = np.asarray(target_point, dtype=np.float64) - 2.0 * extent * direction
    hit = ray_surface_hit(vertices, surface.triangles, origin, direction)
    if hit is None:
        raise TissueInputError(
            f"the line through {np.round(target_point, 4).tolist()} along "
            f"{np.round(direction, 3).tolist()} misses the tissue surface; choose a point "
            "above the tissue (--at X,Y within its footprint)"
        )
    probe = Probe.looking_along(shape, hit, direction, roll_rad=roll_rad)
    position = probe.position_world.copy()
    for _ in range(_CONTACT_SEARCH_ITERATIONS):
        probe.set_pose(position, probe.quat_wxyz)
        distance, _ = probe.signed_distance_world(vertices)
        closest = float(distance.min())
        if abs(closest) < 1e-9:
            break
        position = position + closest * direction  # back off by the overlap, or close the gap
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


def skin_normal_above(
    mesh: TetMesh, point: NDArray[np.float64], up: NDArray[np.float64] | None = None
) -> NDArray[np.float64]:
    """Outward unit normal of the skin (the collision surface, or the volume's boundary) at
    rest, where the line through ``point`` along ``up`` (default +z) leaves it, area-weighted
    over the triangles within 8 mm, shape (3,)."""
    surface = contact_surface(mesh)
    collision = mesh.collision_surface
    vertices = collision.rest_vertices if collision is not None else surface.positions(mesh.nodes)
    triangles = surface.triangles
    direction = np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, dtype=np.float64)
    hit = ray_surface_hit(vertices, triangles, np.asarray(point, dtype=np.float64), direction)
    if hit is None:
        raise TissueInputError(
            f"no skin above the point {np.round(point, 4).tolist()} along "
            f"{np.round(direction, 3).tolist()}; choose a point inside the tissue"
        )
    a, b, c = (vertices[triangles[:, i]] for i in range(3))
    area_normals = 0.5 * np.cross(b - a, c - a)
    near = np.linalg.norm((a + b + c) / 3.0 - hit, axis=1) < _NORMAL_RADIUS_M
    normal = area_normals[near].sum(axis=0)
    return normal / np.linalg.norm(normal)
