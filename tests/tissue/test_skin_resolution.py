"""The skin's resolution is a choice of the tissue (``TissueSpec.collision_edge_m``): the
phantom's dome meshed again at an edge length, any other surface refined by edge bisection,
both embedded in the volume; a resolution outside the volume's range, or a surface outside the
volume, is refused with the numbers. At the probe's scale the skin's facets stay out of the
probe where the paper's 1,004 triangles let its edge through."""

from __future__ import annotations

import numpy as np
import pytest

import tissue
from tissue.errors import ConfigError, MeshError
from tissue.mesh import TetMesh
from tissue.mesh.phantom import breast_phantom
from tissue.mesh.skin import (
    SPLIT_FRACTION,
    boundary_edge_m,
    collision_edge_range_m,
    refine_surface,
    with_collision_edge,
)
from tissue.probe import FACE_WIDTH_M, matrix_to_quat, quat_to_matrix
from tissue.spec import published_scene_dir


def _edges(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    corners = vertices[triangles]
    return np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2).reshape(-1)


def _closed_and_oriented(triangles: np.ndarray) -> bool:
    """Every directed edge appears once and its reverse once: a closed, consistently wound
    surface."""
    directed = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    forward = {tuple(e) for e in directed.tolist()}
    return len(forward) == directed.shape[0] and all((b, a) in forward for a, b in forward)


def _enclosed_volume(vertices: np.ndarray, triangles: np.ndarray) -> float:
    a, b, c = (vertices[triangles[:, k]] for k in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def test_the_phantom_skin_is_meshed_at_the_edge_asked() -> None:
    mesh = breast_phantom(1363, collision_edge_m=0.002)
    surface = mesh.collision_surface
    assert surface is not None
    assert mesh.metadata["collision_edge_m"] == 0.002
    vertices, triangles = surface.rest_vertices, surface.triangles
    on_dome = (vertices[triangles][:, :, 2] > 1e-6).any(axis=1)
    dome_edges = _edges(vertices, triangles[on_dome])
    assert np.median(dome_edges) == pytest.approx(0.002, rel=0.05)
    # The probe's 13.2 mm face spans at least four edges anywhere on the dome.
    assert np.percentile(dome_edges, 99) < FACE_WIDTH_M / 4
    assert _closed_and_oriented(triangles)
    # The paper's surface is what the level keeps without a resolution.
    paper = breast_phantom(1363).collision_surface
    assert paper is not None and paper.vertex_count == 512
    assert surface.vertex_count > 10 * paper.vertex_count
    # The same surface from the cache, and as the spec builds it.
    again = tissue.make_tissue(mesh=1363, collision_edge_m=0.002).contact_model.mesh
    assert again.collision_surface is not None
    np.testing.assert_array_equal(again.collision_surface.rest_vertices, vertices)


def test_a_resolution_outside_the_volumes_range_is_refused_with_the_numbers() -> None:
    mesh = breast_phantom(623)
    shortest, longest = collision_edge_range_m(mesh)
    assert longest == pytest.approx(boundary_edge_m(mesh))
    assert 0.0 < shortest < 0.001 < 0.01 < longest
    with pytest.raises(ConfigError, match=r"coarser than the volume's boundary .*choose"):
        tissue.make_tissue(mesh=623, collision_edge_m=1.5 * longest)
    with pytest.raises(ConfigError, match=r"vertices, more than 200,000.*choose"):
        tissue.make_tissue(mesh=623, collision_edge_m=0.5 * shortest)
    for bad in ("2mm", -0.002, float("nan"), True, 0.0):
        with pytest.raises(ConfigError, match="collision_edge_m"):
            tissue.TissueSpec(mesh=623, collision_edge_m=bad)  # type: ignore[arg-type]


def test_refinement_keeps_a_closed_surface_and_its_shape() -> None:
    vertices = (
        np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=float)
        * 0.01
    )
    triangles = np.array(
        [[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]]
    )
    assert _enclosed_volume(vertices, triangles) > 0.0
    refined, pieces = refine_surface(vertices, triangles, 0.002)
    assert _closed_and_oriented(pieces)
    assert _edges(refined, pieces).max() <= SPLIT_FRACTION * 0.002
    np.testing.assert_array_equal(refined[: vertices.shape[0]], vertices)
    # Flat refinement: the same solid, every new vertex on an old facet.
    assert _enclosed_volume(refined, pieces) == pytest.approx(
        _enclosed_volume(vertices, triangles), rel=1e-12
    )
    assert np.allclose(np.abs(refined).sum(axis=1), 0.01)


def test_a_surface_outside_the_volume_is_refused_naming_its_points() -> None:
    mesh = breast_phantom(623)
    surface = mesh.collision_surface
    assert surface is not None
    wrong_units = TetMesh(
        nodes=mesh.nodes,
        tets=mesh.tets,
        region=mesh.region,
        fixed_nodes=mesh.fixed_nodes,
        region_names=mesh.region_names,
        name="scaled",
    ).with_collision_surface(surface.rest_vertices * 1.6, surface.triangles)
    with pytest.raises(MeshError, match=r"points of scaled fall outside its volume .* at \["):
        with_collision_edge(wrong_units, 0.01)


def test_the_published_scene_is_refined_by_bisection() -> None:
    try:
        directory = published_scene_dir("paper-scene")
    except ConfigError:
        pytest.skip("the published scene (../shared/paper-scene) is not here")
    t = tissue.make_tissue(mesh=str(directory), collision_edge_m=0.003)
    surface = t.contact_model.mesh.collision_surface
    assert surface is not None
    assert _edges(surface.rest_vertices, surface.triangles).max() <= SPLIT_FRACTION * 0.003
    assert surface.vertex_count > 4 * 504


def _press_and_rock(edge: float | None) -> tuple[list[tissue.TissueStep], float]:
    """The issue's scenario at 623 tets: press 10 mm over lesion 1, rock 20 degrees about the
    probe's long axis. Returns the steps and the skin's rest median edge [m]."""
    t = tissue.make_tissue(mesh=623, contact="lm", collision_edge_m=edge)
    position, quat = t.touching_pose(t.lesions[0].rest_centre_m)
    pressing = tissue.pressing_direction(quat)
    t.reset(position, quat)
    steps = [t.step(position + 0.0005 * k * pressing, quat) for k in range(1, 21)]
    rotation = quat_to_matrix(quat)
    pressed = position + 0.01 * pressing
    for k in range(1, 41):
        angle = np.radians(0.5 * k)
        about_x = np.array(
            [[1, 0, 0], [0, np.cos(angle), -np.sin(angle)], [0, np.sin(angle), np.cos(angle)]]
        )
        steps.append(t.step(pressed, matrix_to_quat(rotation @ about_x)))
    surface = t.contact_model.skin
    median = float(np.median(_edges(surface.positions(t.rest_nodes_m), surface.triangles)))
    return steps, median


def test_at_the_probes_scale_the_skin_stays_out_of_the_probe() -> None:
    fine, median = _press_and_rock(0.002)
    assert median == pytest.approx(0.002, rel=0.1)
    assert {step.status for step in fine} == {tissue.StepStatus.OK}
    assert max(step.skin_penetration_m for step in fine) < 0.5e-3
    # The paper's triangles, held out at their vertices as exactly, let the rim through.
    coarse, _ = _press_and_rock(None)
    vertex = max(step.diagnostics.details["skin_vertex_penetration_m"] for step in coarse)
    assert vertex < 1e-5
    assert max(step.skin_penetration_m for step in coarse) > 1.5e-3
