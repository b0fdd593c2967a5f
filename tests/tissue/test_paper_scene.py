"""The published scene of Tagliabue et al. (read from ../shared/paper-scene, never copied)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tissue.errors import ConfigError, MeshError
from tissue.mesh.paper_scene import load_paper_scene, read_stl, remesh_paper_scene
from tissue.mesh.phantom import CACHE_ENV_VAR, PHANTOM_LEVELS

SCENE = Path(__file__).resolve().parents[3] / "shared" / "paper-scene"

pytestmark = pytest.mark.skipif(
    not (SCENE / "breast_13k.msh").is_file(),
    reason=f"the published scene is not present at {SCENE} (test data, not shipped)",
)


@pytest.fixture(autouse=True)
def _temporary_cache(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv(CACHE_ENV_VAR, str(tmp_path / "cache"))


@pytest.fixture(scope="module")
def scene():
    return load_paper_scene(SCENE)


def _closed_and_outward(vertices: np.ndarray, triangles: np.ndarray) -> float:
    directed = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    edges = {tuple(edge) for edge in directed.tolist()}
    assert len(edges) == directed.shape[0]
    assert all((b, a) in edges for a, b in edges)
    corners = vertices[triangles]
    return float(np.einsum("ij,ij->i", corners[:, 0], np.cross(corners[:, 1], corners[:, 2])).sum())


def test_counts_as_published(scene) -> None:
    mesh = scene.mesh
    assert (mesh.node_count, mesh.tet_count) == (2469, 9295)
    assert mesh.fixed_nodes.size == 822
    assert mesh.collision_surface.triangle_count == 1004
    assert mesh.collision_surface.vertex_count == 504
    assert mesh.region_names == ("tissue",)
    assert np.all(mesh.tet_volumes() > 0)
    assert mesh.tet_volumes().sum() == pytest.approx(540.6e-6, rel=0.01)
    np.testing.assert_allclose(np.ptp(mesh.nodes, axis=0), [0.142, 0.123, 0.079], atol=0.001)


def test_fixed_nodes_are_the_base_at_largest_z(scene) -> None:
    z = scene.mesh.nodes[:, 2]
    assert z[scene.mesh.fixed_nodes].min() >= z.max() - 0.003


def test_collision_surface_closed_outward_and_embedded(scene) -> None:
    surface = scene.mesh.collision_surface
    volume = _closed_and_outward(surface.rest_vertices, surface.triangles) / 6.0
    assert volume == pytest.approx(540.6e-6, rel=0.01)
    np.testing.assert_allclose(surface.vertices(scene.mesh.nodes), surface.rest_vertices, atol=1e-9)


def test_lesions_poses_and_spring_nodes(scene) -> None:
    assert scene.tumour_ids == (1, 2)
    assert scene.mesh.landmarks.names == ("tumor1", "tumor2")
    np.testing.assert_allclose(
        scene.mesh.landmarks.rest_positions[0], [-0.065673, 0.169330, -0.105975]
    )
    for number in (1, 2):
        poses = scene.probe_poses[number]
        assert poses.shape == (5, 4, 4)
        np.testing.assert_allclose(poses[:, 3], np.tile([0, 0, 0, 1.0], (5, 1)))
        rotations = poses[:, :3, :3]
        np.testing.assert_allclose(
            rotations @ rotations.transpose(0, 2, 1), np.tile(np.eye(3), (5, 1, 1)), atol=1e-3
        )
        nodes = scene.spring_nodes[number]
        assert nodes.size >= 3 and nodes.max() < 504
        # The spring nodes lie under the probe at rest: within a few cm of its origin.
        distance = np.linalg.norm(
            scene.mesh.collision_surface.rest_vertices[nodes] - poses[0, :3, 3], axis=1
        )
        assert distance.max() < 0.03
    np.testing.assert_array_equal(scene.spring_nodes[1], [232, 253, 255, 371, 430, 492])


def test_probe_geometry(scene) -> None:
    assert scene.probe_triangles.shape == (70, 3)
    extent = np.ptp(scene.probe_vertices, axis=0)
    np.testing.assert_allclose(extent, [0.053, 0.0027, 0.0132], atol=0.001)


def test_stl_vertices_merge_in_first_appearance_order() -> None:
    vertices, triangles = read_stl(SCENE / "breast_500.stl")
    assert vertices.shape == (504, 3) and triangles.shape == (1004, 3)
    assert triangles[0].tolist() == [0, 1, 2]
    assert np.all(np.diff(np.maximum.accumulate(triangles.reshape(-1))) <= 1)


def test_incomplete_directory_names_the_missing_file(tmp_path: Path) -> None:
    # Links, not copies: nothing of the published data is duplicated.
    for item in SCENE.iterdir():
        if item.name != "breast_500.stl":
            (tmp_path / item.name).symlink_to(item)
    with pytest.raises(MeshError, match="breast_500.stl"):
        load_paper_scene(tmp_path)
    with pytest.raises(MeshError, match="does not exist"):
        load_paper_scene(tmp_path / "absent")
    partial = tmp_path / "partial"
    partial.mkdir()
    for item in SCENE.iterdir():
        if item.name != "ground_truth":
            (partial / item.name).symlink_to(item)
    with pytest.raises(MeshError, match="ground_truth"):
        load_paper_scene(partial)


def _check_remesh(level: int) -> None:
    mesh = remesh_paper_scene(SCENE, level)
    assert abs(mesh.tet_count / level - 1.0) <= 0.10, (level, mesh.tet_count)
    assert mesh.collision_surface.triangle_count == 1004
    assert mesh.landmarks.names == ("tumor1", "tumor2")
    z = mesh.nodes[:, 2]
    assert mesh.fixed_nodes.size >= 3
    assert z[mesh.fixed_nodes].min() >= z.max() - 0.003
    # Coarse levels cut the curved skin with chords: up to about 4 % of volume at 623.
    assert mesh.tet_volumes().sum() == pytest.approx(540.6e-6, rel=0.06)


def test_remesh_at_4126() -> None:
    _check_remesh(4126)
    with pytest.raises(ConfigError, match="valid levels"):
        remesh_paper_scene(SCENE, 5000)


def test_remesh_is_cached(tmp_path: Path) -> None:
    first = remesh_paper_scene(SCENE, 623, cache_dir=tmp_path)
    assert len(list(tmp_path.glob("paper-scene-*.npz"))) == 1
    second = remesh_paper_scene(SCENE, 623, cache_dir=tmp_path)
    np.testing.assert_array_equal(first.nodes, second.nodes)
    np.testing.assert_array_equal(first.tets, second.tets)


@pytest.mark.slow
@pytest.mark.parametrize("level", [level for level in PHANTOM_LEVELS if level != 4126])
def test_remesh_every_level(level: int) -> None:
    _check_remesh(level)
