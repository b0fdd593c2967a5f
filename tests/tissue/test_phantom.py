"""The parametric breast phantom and its mesh ladder."""

from __future__ import annotations

import math
import signal
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import Delaunay

from tissue.errors import ConfigError
from tissue.mesh import TetMesh, phantom
from tissue.mesh.phantom import (
    PHANTOM_LEVELS,
    LesionSpec,
    PhantomSpec,
    breast_phantom,
    describe_mesh,
    mesh_cache_dir,
    parse_level,
)

FAST_LEVELS = (623, 1363, 2539, 4126, 7369, 12861, 26220)
SLOW_LEVELS = (105004, 176506)
SPHERE_LEVELS = (4126, 7369, 12861, 26220)


@pytest.fixture(autouse=True)
def _temporary_cache(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv(phantom.CACHE_ENV_VAR, str(tmp_path / "env-cache"))


@pytest.fixture(scope="module")
def ladder(tmp_path_factory: pytest.TempPathFactory):
    """Meshes by level, generated once per module into a temporary cache."""
    cache = tmp_path_factory.mktemp("ladder-cache")
    meshes: dict[int, TetMesh] = {}

    def get(level: int) -> TetMesh:
        if level not in meshes:
            meshes[level] = breast_phantom(level, cache_dir=cache)
        return meshes[level]

    return get


def _assert_count(mesh: TetMesh, level: int) -> None:
    assert abs(mesh.tet_count / level - 1.0) <= 0.10, (level, mesh.tet_count)


@pytest.mark.parametrize("level", FAST_LEVELS)
def test_level_tet_count_within_ten_percent(ladder, level: int) -> None:
    mesh = ladder(level)
    _assert_count(mesh, level)
    assert mesh.metadata["level"] == level
    assert np.all(mesh.tet_volumes() > 0)


@pytest.mark.slow
@pytest.mark.parametrize("level", SLOW_LEVELS)
def test_fine_level_tet_count_within_ten_percent(tmp_path: Path, level: int) -> None:
    mesh = breast_phantom(level, cache_dir=tmp_path)
    _assert_count(mesh, level)
    assert mesh.lesion_count == 10
    assert np.bincount(mesh.region, minlength=11)[1:].min() > 0


def test_shape_size_and_volume(ladder) -> None:
    mesh = ladder(4126)
    extent = np.ptp(mesh.nodes, axis=0)
    np.testing.assert_allclose(extent, [0.140, 0.120, 0.080], rtol=0.03)
    assert mesh.nodes[:, 2].min() == pytest.approx(0.0, abs=1e-12)
    assert mesh.tet_volumes().sum() == pytest.approx(541e-6, rel=0.04)
    assert PhantomSpec().volume_m3 == pytest.approx(541e-6, rel=0.005)


@pytest.mark.parametrize("level", FAST_LEVELS)
def test_every_level_has_ten_labelled_lesions(ladder, level: int) -> None:
    mesh = ladder(level)
    assert mesh.region_names == ("tissue",) + tuple(f"lesion_{k}" for k in range(1, 11))
    assert mesh.lesion_count == 10
    assert np.bincount(mesh.region, minlength=11)[1:].min() >= 1


@pytest.mark.parametrize("level", (2539, *SPHERE_LEVELS))
def test_lesion_volumes_match_spheres(ladder, level: int) -> None:
    mesh = ladder(level)
    radii = np.asarray(mesh.metadata["lesion_radii_m"])
    expected = 4.0 / 3.0 * math.pi * radii**3
    volumes = np.bincount(mesh.region, weights=mesh.tet_volumes(), minlength=11)[1:]
    np.testing.assert_allclose(volumes, expected, rtol=0.15)


@pytest.mark.parametrize("level", FAST_LEVELS)
def test_lesions_are_conforming_sub_volumes_around_their_centres(ladder, level: int) -> None:
    mesh = ladder(level)
    centres = np.asarray(mesh.metadata["lesion_centres_m"])
    radii = np.asarray(mesh.metadata["lesion_radii_m"])
    for k in range(1, 11):
        lesion_nodes = mesh.nodes[np.unique(mesh.tets[mesh.region == k])]
        distance = np.linalg.norm(lesion_nodes - centres[k - 1], axis=1)
        # Polyhedra reach 2.02 radii (tetrahedron vertices); spheres about 1.2.
        assert distance.max() <= 2.1 * radii[k - 1]


def test_spec_lesions_lie_in_the_requested_ranges() -> None:
    spec = PhantomSpec()
    assert len(spec.lesions) == 10
    diameters = np.array([lesion.diameter_m for lesion in spec.lesions])
    depths = np.array([lesion.depth_m for lesion in spec.lesions])
    assert diameters.min() >= 0.005 and diameters.max() <= 0.010
    assert depths.min() >= 0.010 and depths.max() <= 0.045
    centres = spec.lesion_centres_m()
    skin = spec.skin_height_m(centres[:, 0], centres[:, 1])
    np.testing.assert_allclose(skin - centres[:, 2], depths, atol=1e-12)


@pytest.mark.parametrize("level", FAST_LEVELS)
def test_landmarks_are_lesion_tops_inside_the_lesions(ladder, level: int) -> None:
    mesh = ladder(level)
    assert mesh.landmarks is not None
    assert mesh.landmarks.names == tuple(f"lesion_{k}" for k in range(1, 11))
    centres = np.asarray(mesh.metadata["lesion_centres_m"])
    radii = np.asarray(mesh.metadata["lesion_radii_m"])
    points = mesh.landmarks.rest_positions
    np.testing.assert_allclose(points, centres + radii[:, None] * [0, 0, 1], atol=1e-12)
    # Embedded inside the volume, and inside (or within 10 % of a radius of) the lesion.
    assert mesh.landmarks.embedding.weights.min() >= -1e-9
    np.testing.assert_allclose(mesh.landmarks.positions(mesh.nodes), points, atol=1e-12)
    for k in range(1, 11):
        lesion_nodes = mesh.nodes[np.unique(mesh.tets[mesh.region == k])]
        hull = Delaunay(lesion_nodes)
        inside = hull.find_simplex(points[k - 1]) >= 0
        below_top = points[k - 1, 2] <= lesion_nodes[:, 2].max() + 0.1 * radii[k - 1]
        lowered = points[k - 1] - [0, 0, 0.1 * radii[k - 1]]
        assert below_top and (inside or hull.find_simplex(lowered) >= 0), k


@pytest.mark.parametrize("level", (623, 4126))
def test_fixed_nodes_are_the_base(ladder, level: int) -> None:
    mesh = ladder(level)
    on_base = np.flatnonzero(np.abs(mesh.nodes[:, 2]) <= 1e-12)
    np.testing.assert_array_equal(mesh.fixed_nodes, on_base)
    assert mesh.fixed_nodes.size >= 3
    base_faces = mesh.boundary_triangles()
    flat = np.all(np.abs(mesh.nodes[base_faces][:, :, 2]) <= 1e-12, axis=1)
    assert np.setdiff1d(np.unique(base_faces[flat]), mesh.fixed_nodes).size == 0


@pytest.mark.parametrize("level", (623, 4126))
def test_collision_surface_is_closed_outward_and_about_1000_triangles(ladder, level) -> None:
    mesh = ladder(level)
    surface = mesh.collision_surface
    assert surface is not None
    assert 900 <= surface.triangle_count <= 1100
    triangles = surface.triangles
    # Closed and consistently wound: each directed edge appears once, its reverse once.
    directed = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    as_set = {tuple(edge) for edge in directed.tolist()}
    assert len(as_set) == directed.shape[0]
    assert all((b, a) in as_set for a, b in as_set)
    corners = surface.rest_vertices[triangles]
    volume = np.einsum("ij,ij->i", corners[:, 0], np.cross(corners[:, 1], corners[:, 2])).sum()
    assert volume / 6.0 == pytest.approx(PhantomSpec().volume_m3, rel=0.02)
    # Embedded in the volume: the rest vertices are reproduced from the nodes.
    np.testing.assert_allclose(surface.vertices(mesh.nodes), surface.rest_vertices, atol=1e-12)


def test_generation_is_deterministic(tmp_path: Path) -> None:
    first = breast_phantom(623, cache_dir=tmp_path / "a")
    second = breast_phantom(623, cache_dir=tmp_path / "b")
    for name in ("nodes", "tets", "region", "fixed_nodes"):
        np.testing.assert_array_equal(getattr(first, name), getattr(second, name))
    np.testing.assert_array_equal(
        first.collision_surface.rest_vertices, second.collision_surface.rest_vertices
    )
    np.testing.assert_array_equal(
        first.collision_surface.triangles, second.collision_surface.triangles
    )


def test_cache_hit_returns_identical_arrays(tmp_path: Path, monkeypatch) -> None:
    fresh = breast_phantom(623, cache_dir=tmp_path)
    files = list(tmp_path.glob("*.npz"))
    assert len(files) == 1 and f"g{phantom.GENERATOR_VERSION}" in files[0].name

    def must_not_generate(*args, **kwargs):
        raise AssertionError("the cache was not used")

    monkeypatch.setattr(phantom, "generate_phantom", must_not_generate)
    cached = breast_phantom("623", cache_dir=tmp_path)
    for name in ("nodes", "tets", "region", "fixed_nodes"):
        np.testing.assert_array_equal(getattr(fresh, name), getattr(cached, name))
    np.testing.assert_array_equal(
        fresh.landmarks.embedding.weights, cached.landmarks.embedding.weights
    )
    np.testing.assert_array_equal(
        fresh.metadata["lesion_centres_m"], cached.metadata["lesion_centres_m"]
    )


def test_cache_key_depends_on_the_spec(tmp_path: Path) -> None:
    spec = PhantomSpec(lesions=PhantomSpec().lesions[:3])
    mesh = breast_phantom(623, spec=spec, cache_dir=tmp_path)
    assert mesh.lesion_count == 3
    _assert_count(mesh, 623)
    assert len(list(tmp_path.glob("*.npz"))) == 1


def test_cache_directory_comes_from_the_environment(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setenv(phantom.CACHE_ENV_VAR, str(tmp_path / "here"))
    assert mesh_cache_dir() == tmp_path / "here"
    assert mesh_cache_dir(tmp_path / "explicit") == tmp_path / "explicit"
    breast_phantom(623)
    assert len(list((tmp_path / "here").glob("phantom-*.npz"))) == 1


def test_gmsh_is_left_finalised_and_silent(tmp_path: Path, capfd) -> None:
    import gmsh

    breast_phantom(623, cache_dir=tmp_path)
    assert not gmsh.isInitialized()
    captured = capfd.readouterr()
    assert captured.out == "" and captured.err == ""


def _sigpipe_ignored() -> bool:
    """SIGPIPE's action as the OS has it (Python's ``signal.getsignal`` only remembers)."""
    with open("/proc/self/status") as status:
        line = next(line for line in status if line.startswith("SigIgn:"))
    return bool(int(line.split()[1], 16) >> (signal.SIGPIPE - 1) & 1)


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="reads Linux's /proc")
def test_meshing_leaves_sigpipe_ignored(tmp_path: Path) -> None:
    """gmsh's initialisation resets SIGPIPE to its default; a study's Ctrl-C then died of
    SIGPIPE on its workers' closed pipes instead of saying what it kept."""
    assert _sigpipe_ignored()  # Python's start-up action
    breast_phantom(623, cache_dir=tmp_path)
    assert _sigpipe_ignored()


def test_parse_level() -> None:
    assert parse_level(4126) == 4126
    assert parse_level("4,126") == 4126
    assert parse_level(" 176506 ") == 176506
    assert set(PHANTOM_LEVELS) == {623, 1363, 2539, 4126, 7369, 12861, 26220, 105004, 176506}
    for bad in (4000, "coarse", True, 4126.0, None):
        with pytest.raises(ConfigError, match="623, 1363, 2539"):
            parse_level(bad)  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="4000"):
        breast_phantom(4000)


def test_bad_specs_are_rejected() -> None:
    with pytest.raises(ConfigError, match="metres"):
        PhantomSpec(length_m=140.0)
    with pytest.raises(ConfigError, match="footprint"):
        PhantomSpec(lesions=(LesionSpec(0.09, 0.0, 0.01, 0.006),))
    with pytest.raises(ConfigError, match="apart"):
        PhantomSpec(lesions=(LesionSpec(0, 0, 0.02, 0.008), LesionSpec(0.005, 0, 0.02, 0.008)))
    with pytest.raises(ConfigError, match="base"):
        PhantomSpec(lesions=(LesionSpec(0, 0, 0.078, 0.008),))
    with pytest.raises(ConfigError, match="skin"):
        PhantomSpec(lesions=(LesionSpec(0, 0, 0.004, 0.006),))
    with pytest.raises(ConfigError, match="diameter"):
        LesionSpec(0, 0, 0.02, 8.0)
    with pytest.raises(ConfigError, match="PhantomSpec"):
        breast_phantom(623, spec="default")  # type: ignore[arg-type]


def test_describe_mesh(ladder) -> None:
    mesh = ladder(623)
    text = describe_mesh(mesh)
    assert f"{mesh.node_count} nodes" in text
    assert f"{mesh.tet_count} tets" in text
    assert "10 lesions" in text
    assert f"{mesh.collision_surface.triangle_count} collision triangles" in text
