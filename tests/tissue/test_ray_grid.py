"""The triangle grid's first hit is the full pass's, bit for bit, for any ray; the touching poses
found with it touch."""

from __future__ import annotations

import numpy as np
import pytest

from tissue.contact.placement import _nearest_hit_distance
from tissue.contact.ray_grid import TriangleGrid


def _soup(rng: np.random.Generator, count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``count`` triangles of 1-5 mm scattered in a 60 mm box, some of them long and thin."""
    corner = rng.uniform(-0.03, 0.03, size=(count, 3))
    edge1 = rng.normal(scale=0.003, size=(count, 3))
    edge2 = rng.normal(scale=0.003, size=(count, 3))
    edge2[: count // 10] *= 0.01  # slivers
    edge1[count // 10 : count // 5] *= 8.0  # a few spanning many cells
    return corner, edge1, edge2


def _rays(rng: np.random.Generator, count: int) -> list[tuple[np.ndarray, np.ndarray]]:
    rays = []
    for _ in range(count):
        origin = rng.uniform(-0.05, 0.05, size=3)  # inside and outside the grid's box
        direction = rng.normal(size=3)
        rays.append((origin, direction))
    # Along the axes (zero components), from outside the box, and missing it.
    for axis in range(3):
        for sign in (1.0, -1.0):
            direction = np.zeros(3)
            direction[axis] = sign
            rays.append((rng.uniform(-0.03, 0.03, size=3), direction))
            rays.append((-0.2 * direction + rng.uniform(-0.01, 0.01, size=3), direction))
            rays.append((0.2 * direction, direction))  # starts beyond the box, leaving it
    rays.append((np.array([0.5, 0.5, 0.5]), np.array([1.0, 0.0, 0.0])))
    return rays


def test_the_grid_finds_the_full_pass_hit_for_every_ray() -> None:
    rng = np.random.default_rng(7)
    corner, edge1, edge2 = _soup(rng, 3000)
    grid = TriangleGrid(corner, edge1, edge2)
    assert grid.items.size >= corner.shape[0]
    hits = 0
    for origin, direction in _rays(rng, 400):
        full = _nearest_hit_distance(corner, edge1, edge2, origin, direction)
        assert grid.nearest_hit(origin, direction) == full
        hits += bool(np.isfinite(full))
    assert hits > 100  # the comparison covers hits, not only misses


def test_rays_from_cell_faces_and_corners_find_the_same_hit() -> None:
    """Origins on the grid's own cell boundaries, where rounding picks a cell."""
    rng = np.random.default_rng(3)
    corner, edge1, edge2 = _soup(rng, 800)
    grid = TriangleGrid(corner, edge1, edge2)
    for _ in range(200):
        cell = rng.integers(0, grid.dims)
        origin = grid.low + cell * grid.side
        direction = rng.normal(size=3)
        if rng.uniform() < 0.5:
            direction[rng.integers(0, 3)] = 0.0
        full = _nearest_hit_distance(corner, edge1, edge2, origin, direction)
        assert grid.nearest_hit(origin, direction) == full


def test_the_rest_skin_queries_hit_the_skin_the_full_pass_hits() -> None:
    """The 2 mm skin (16,710 triangles): rays up from under the dome and back along -z."""
    import tissue

    model = tissue.make_tissue(mesh=623, contact="penalty", collision_edge_m=0.002)
    skin = model._rest_skin_query()
    assert skin.triangles.shape[0] > 10_000
    a, b, c = (skin.vertices[skin.triangles[:, i]] for i in range(3))
    rng = np.random.default_rng(0)
    for x, y in rng.uniform(-0.04, 0.04, size=(60, 2)):
        for origin, direction in (
            (np.array([x, y, 0.005]), np.array([0.1, -0.2, 1.0])),
            (np.array([x, y, 0.2]), np.array([0.0, 0.0, -1.0])),
        ):
            unit = direction / np.linalg.norm(direction)
            full = _nearest_hit_distance(a, b - a, c - a, origin, unit)
            assert skin._grid.nearest_hit(origin, unit) == full
    with pytest.raises(tissue.TissueInputError, match="no skin"):
        skin.normal_where_leaving(np.array([0.0, 0.0, 0.5]))


def test_touching_poses_touch_the_fine_skin_with_nothing_inside() -> None:
    """The first-contact search (its candidates across the pressing axis, its Newton
    back-off at the rim) ends touching: the nearest of all the skin's points lies on the
    probe's surface to within the search's 1e-9 m, for oblique directions and rolls."""
    import tissue
    from tissue.probe import Probe

    model = tissue.make_tissue(mesh=623, contact="penalty", collision_edge_m=0.002)
    vertices = model._rest_skin_query().vertices
    shape = model._resolved.probe_shape
    rng = np.random.default_rng(1)
    for lesion in model.lesions:
        for _ in range(3):
            direction = rng.normal(size=3)
            direction[2] = -abs(direction[2]) - 1.0
            position, quat = model.touching_pose(
                lesion.rest_centre_m, direction, roll_rad=rng.uniform(-1.0, 1.0)
            )
            probe = Probe(shape)
            probe.set_pose(position, quat)
            distance, _ = probe.signed_distance_world(vertices)
            assert abs(float(distance.min())) < 1e-9
