"""The skin's depth inside the probe is measured over its facets, not only its vertices.

The measure (:mod:`tissue.probe.surface_depth`) is checked against an exhaustive grid of
points on the triangles for every probe shape, on triangles placed across the probe's edges
and corners; the geometric allowance of a facet whose vertices lie outside is checked to
bound what such a facet can reach; and a step whose skin lies deeper than a method's bound
plus that allowance is ``penetrated``, never ``ok``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

import tissue
from tissue.contact import PenaltyContact, register_contact, unregister_contact
from tissue.mesh import TetMesh
from tissue.probe import (
    BoxProbe,
    CylinderProbe,
    MeshProbe,
    Probe,
    SphereProbe,
    linear_probe,
    matrix_to_quat,
)
from tissue.probe.surface_depth import facet_allowance_m, surface_depth

GRID_ORDER = 40


def _grid(order: int) -> np.ndarray:
    return np.array(
        [(i / order, j / order, 1 - (i + j) / order) for i in range(order + 1)
         for j in range(order + 1 - i)]
    )  # fmt: skip


def _exhaustive(probe: Probe, vertices: np.ndarray, triangles: np.ndarray) -> tuple[float, float]:
    """The deepest of a fine grid of points on the triangles [m], and how much deeper a point
    between them can be (a cell's circumradius, the distance being 1-Lipschitz) [m]."""
    corners = vertices[triangles]
    samples = np.einsum("sk,tkd->tsd", _grid(GRID_ORDER), corners).reshape(-1, 3)
    distance, _ = probe.signed_distance_world(samples)
    longest = float(np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2).max())
    return max(0.0, -float(distance.min())), longest / GRID_ORDER / np.sqrt(3.0)


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q @ np.diag(np.sign(np.diag(r)))
    return q if np.linalg.det(q) > 0 else -q


def _triangles_across(probe: Probe, rng: np.random.Generator, count: int, size_m: float):
    """``count`` triangles of about ``size_m`` [m] centred on random points of the probe's
    surface (its edges and corners included), randomly turned."""
    vertices, triangles = probe.surface_world()
    centres = vertices[rng.integers(0, vertices.shape[0], count)]
    corners = []
    for centre in centres:
        local = size_m * np.array([[1.0, 0.0, 0.0], [-0.5, 0.87, 0.0], [-0.5, -0.87, 0.0]])
        local *= rng.uniform(0.5, 1.0, (3, 1))
        corners.append(centre + (local @ _random_rotation(rng).T) + rng.normal(0, 0.3 * size_m, 3))
    points = np.concatenate(corners)
    return points, np.arange(points.shape[0]).reshape(-1, 3)


SHAPES = {
    "face": linear_probe(),
    "box": BoxProbe((0.04, 0.03, 0.012)),
    "sphere": SphereProbe(0.008),
    "cylinder": CylinderProbe(0.006, 0.03),
}


@pytest.mark.parametrize("name", sorted(SHAPES))
def test_the_measure_matches_an_exhaustive_grid_for_every_shape(name: str) -> None:
    rng = np.random.default_rng(11)
    probe = Probe(
        SHAPES[name], np.array([0.01, -0.02, 0.03]), matrix_to_quat(_random_rotation(rng))
    )
    for size in (0.002, 0.01):
        vertices, triangles = _triangles_across(probe, rng, 60, size)
        measured = surface_depth(probe, vertices, triangles)
        exhaustive, cell = _exhaustive(probe, vertices, triangles)
        # Never more than the truth, never less than a grid of points on the surface finds.
        assert exhaustive - 1e-9 <= measured.depth_m <= exhaustive + cell
        assert measured.vertex_depth_m <= measured.depth_m
        if measured.depth_m > 0.0:
            distance, _ = probe.signed_distance_world(measured.point_world)
            assert -distance[0] == pytest.approx(measured.depth_m, abs=1e-12)


def test_a_mesh_probe_is_measured_on_samples() -> None:
    """A shape without a compiled distance is sampled: within a grid cell of the truth."""
    face = SHAPES["box"]
    vertices, triangles = face.surface()
    probe = Probe(MeshProbe(vertices, triangles), np.zeros(3))
    exact = Probe(face, np.zeros(3))
    rng = np.random.default_rng(3)
    points, tris = _triangles_across(exact, rng, 30, 0.004)
    measured = surface_depth(probe, points, tris)
    exhaustive, cell = _exhaustive(exact, points, tris)
    assert abs(measured.depth_m - exhaustive) <= 4 * cell + 1e-6


def test_a_facet_across_the_rim_is_inside_while_its_vertices_are_not() -> None:
    """The issue's case: the probe's rounded edge between two skin vertices."""
    probe = Probe(linear_probe(), np.zeros(3))
    # A facet below the face (+y is out of the face), crossing the long edge at z = 6.6 mm.
    edge_z = 0.5 * 0.0132
    vertices = np.array(
        [
            [0.0, 0.0005, edge_z - 0.004],
            [0.004, -0.003, edge_z + 0.002],
            [-0.004, -0.003, edge_z + 0.002],
        ]
    )
    distance, _ = probe.signed_distance_world(vertices)
    assert np.all(distance > 0.0)
    measured = surface_depth(probe, vertices, np.array([[0, 1, 2]]))
    assert measured.vertex_depth_m == 0.0
    assert measured.depth_m > 0.5e-3
    assert measured.triangle == 0
    # Its vertices outside, it reaches no deeper than a facet of its size can.
    longest = float(np.linalg.norm(vertices - np.roll(vertices, 1, axis=0), axis=1).max())
    assert measured.depth_m <= facet_allowance_m(longest, probe.shape.edge_radius_m)
    assert measured.excess_m <= 0.0


@pytest.mark.parametrize("name", ["face", "sphere", "box"])
def test_no_facet_with_its_vertices_outside_exceeds_its_allowance(name: str) -> None:
    rng = np.random.default_rng(5)
    probe = Probe(SHAPES[name], np.zeros(3))
    worst = -np.inf
    for size in (0.0015, 0.002, 0.004, 0.01):
        vertices, triangles = _triangles_across(probe, rng, 400, size)
        distance, _ = probe.signed_distance_world(vertices)
        outside = (distance.reshape(-1, 3) > 0.0).all(axis=1)
        kept = triangles[outside]
        measured = surface_depth(probe, vertices, kept)
        worst = max(worst, measured.excess_m)
    assert worst <= 1e-12


def test_the_allowance_of_the_default_face() -> None:
    """The figures docs/contact.md quotes: a 2 mm facet against the 1.35 mm rim."""
    radius = linear_probe().edge_radius_m
    assert radius == pytest.approx(0.00135)
    assert facet_allowance_m(0.002, radius) == pytest.approx(0.65e-3, abs=0.01e-3)
    assert facet_allowance_m(0.0015, radius) == pytest.approx(0.31e-3, abs=0.01e-3)
    assert facet_allowance_m(0.0099, radius) == pytest.approx(0.0099 / np.sqrt(3.0))
    assert facet_allowance_m(0.004, 0.0) == pytest.approx(0.004 / np.sqrt(3.0))


class SoftPenalty(PenaltyContact):
    """Penalty with springs a thousand times softer: the skin sinks into the probe."""

    name = "toy_soft"
    label = "ToySoft"
    penetration_bound_m = 0.002

    def __init__(self, mesh: TetMesh, probe_shape: Any, **kwargs: Any) -> None:
        super().__init__(mesh, probe_shape, **kwargs)
        self.term.stiffness *= 1e-3


@pytest.fixture
def soft():
    register_contact(SoftPenalty)
    try:
        yield SoftPenalty.name
    finally:
        unregister_contact(SoftPenalty.name)


def test_a_skin_sunk_past_the_bound_is_penetrated_not_ok(soft: str) -> None:
    t = tissue.make_tissue(mesh=623, contact=soft, profile="paper", collision_edge_m=0.004)
    position, quat = t.touching_pose(t.lesions[0].rest_centre_m)
    pressing = tissue.pressing_direction(quat)
    t.reset(position, quat)
    statuses = []
    for k in range(1, 21):
        step = t.step(position + 0.0005 * k * pressing, quat)
        statuses.append(step.status)
        allowance = facet_allowance_m(0.004 * 4 / 3, t.probe_shape.edge_radius_m)
        vertex = step.diagnostics.details["skin_vertex_penetration_m"]
        if step.skin_penetration_m > SoftPenalty.penetration_bound_m + vertex + allowance:
            assert step.status is not tissue.StepStatus.OK
    assert tissue.StepStatus.PENETRATED in statuses
    assert step.skin_penetration_m > 0.004  # sunk, and said so
    assert np.all(np.isfinite(step.force_world_n))
