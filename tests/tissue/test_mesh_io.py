"""Loading and writing tet meshes with meshio, and the mesh archive format."""

from __future__ import annotations

from pathlib import Path

import meshio
import numpy as np
import pytest

from tissue.errors import ConfigError, MeshError
from tissue.mesh import TetMesh
from tissue.mesh.io import (
    load_mesh_npz,
    load_tet_mesh,
    nodes_on_plane,
    save_mesh_npz,
    write_mesh,
)


def _box_mesh(size_m: float = 0.05) -> TetMesh:
    """A cube of side ``size_m`` [m] split into 6 positively oriented tets (Kuhn split),
    two regions."""
    corners = np.array(
        [[(i >> 0) & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], dtype=np.float64
    )
    tets = np.array(
        [[0, 1, 3, 7], [0, 1, 7, 5], [0, 2, 7, 3], [0, 2, 6, 7], [0, 4, 5, 7], [0, 4, 7, 6]]
    )
    nodes = corners * size_m
    volume = np.einsum(
        "ij,ij->i",
        nodes[tets[:, 1]] - nodes[tets[:, 0]],
        np.cross(nodes[tets[:, 2]] - nodes[tets[:, 0]], nodes[tets[:, 3]] - nodes[tets[:, 0]]),
    )
    tets[volume < 0] = tets[volume < 0][:, [0, 1, 3, 2]]
    return TetMesh(
        nodes=nodes,
        tets=tets,
        region=np.array([0, 0, 0, 1, 1, 0]),
        fixed_nodes=np.array([0, 1, 2, 3]),
        region_names=("tissue", "lesion_1"),
        name="box",
    )


def _write_raw(path: Path, points, tets, **kwargs) -> Path:
    meshio.write(path, meshio.Mesh(points, [("tetra", np.asarray(tets))], **kwargs))
    return path


@pytest.mark.parametrize("suffix", [".vtu", ".msh", ".vtk"])
def test_round_trip(tmp_path: Path, suffix: str) -> None:
    mesh = _box_mesh()
    path = write_mesh(mesh, tmp_path / f"box{suffix}")
    loaded = load_tet_mesh(path, fixed_plane="z=min")
    np.testing.assert_allclose(loaded.nodes, mesh.nodes, atol=1e-15)
    np.testing.assert_array_equal(loaded.tets, mesh.tets)
    np.testing.assert_array_equal(loaded.region, mesh.region)
    np.testing.assert_array_equal(loaded.fixed_nodes, mesh.fixed_nodes)
    assert loaded.region_names[0] == "tissue" and len(loaded.region_names) == 2
    if suffix == ".msh":
        assert loaded.region_names == mesh.region_names


def test_write_deformed_mesh_with_displacement(tmp_path: Path) -> None:
    mesh = _box_mesh()
    moved = mesh.nodes + [0.0, 0.0, -0.001]
    stress = np.arange(mesh.node_count, dtype=np.float64)
    path = write_mesh(mesh, tmp_path / "moved.vtu", positions=moved, point_data={"s": stress})
    data = meshio.read(path)
    np.testing.assert_allclose(data.points, moved)
    np.testing.assert_allclose(data.point_data["displacement"][:, 2], -0.001)
    np.testing.assert_array_equal(data.point_data["fixed"][:4], 1)
    np.testing.assert_array_equal(data.cell_data["region"][0], mesh.region)
    with pytest.raises(MeshError, match="shape"):
        write_mesh(mesh, tmp_path / "bad.vtu", positions=moved[:3])


def test_fixed_planes(tmp_path: Path) -> None:
    path = write_mesh(_box_mesh(), tmp_path / "box.vtu")
    top = load_tet_mesh(path, fixed_plane="z=max")
    np.testing.assert_array_equal(top.fixed_nodes, [4, 5, 6, 7])
    side = load_tet_mesh(path, fixed_plane=" x = max ")
    np.testing.assert_array_equal(side.fixed_nodes, [1, 3, 5, 7])
    by_value = load_tet_mesh(path, fixed_plane="y=0.0")
    np.testing.assert_array_equal(by_value.fixed_nodes, [0, 1, 4, 5])
    nodes = np.array([[0, 0, 0.0], [0, 0, 0.001], [0, 0, 0.05]])
    np.testing.assert_array_equal(nodes_on_plane(nodes, "z=min", tolerance=0.002), [0, 1])
    for bad in ("w=min", "z=middle", "z<0", "min"):
        with pytest.raises(ConfigError, match="fixed_plane"):
            load_tet_mesh(path, fixed_plane=bad)


def test_fixed_nodes_file(tmp_path: Path) -> None:
    path = write_mesh(_box_mesh(), tmp_path / "box.vtu")
    (tmp_path / "fixed.txt").write_text("0 2\n4 6\n")
    mesh = load_tet_mesh(path, fixed_nodes_file=tmp_path / "fixed.txt")
    np.testing.assert_array_equal(mesh.fixed_nodes, [0, 2, 4, 6])
    both = load_tet_mesh(path, fixed_nodes_file=tmp_path / "fixed.txt", fixed_plane="x=max")
    np.testing.assert_array_equal(both.fixed_nodes, [0, 1, 2, 3, 4, 5, 6, 7])
    (tmp_path / "out.txt").write_text("0 8")
    with pytest.raises(MeshError, match="0..7"):
        load_tet_mesh(path, fixed_nodes_file=tmp_path / "out.txt")
    (tmp_path / "text.txt").write_text("zero one")
    with pytest.raises(MeshError, match="integer"):
        load_tet_mesh(path, fixed_nodes_file=tmp_path / "text.txt")
    with pytest.raises(MeshError, match="does not exist"):
        load_tet_mesh(path, fixed_nodes_file=tmp_path / "absent.txt")


def test_millimetre_file_is_caught_and_scale_fixes_it(tmp_path: Path) -> None:
    mesh = _box_mesh(size_m=140.0 * 0.001)
    path = _write_raw(tmp_path / "mm.vtu", mesh.nodes * 1000.0, mesh.tets)
    with pytest.raises(MeshError, match="millimetres"):
        load_tet_mesh(path)
    loaded = load_tet_mesh(path, scale=0.001)
    np.testing.assert_allclose(loaded.nodes, mesh.nodes)
    with pytest.raises(ConfigError, match="scale"):
        load_tet_mesh(path, scale=-1.0)


def test_missing_file_and_no_tets(tmp_path: Path) -> None:
    with pytest.raises(MeshError, match="does not exist"):
        load_tet_mesh(tmp_path / "absent.msh")
    surface = tmp_path / "surface.vtu"
    meshio.write(surface, meshio.Mesh(np.eye(3) * 0.01, [("triangle", np.array([[0, 1, 2]]))]))
    with pytest.raises(MeshError, match="no linear tetrahedra.*triangle"):
        load_tet_mesh(surface)
    (tmp_path / "garbage.msh").write_text("not a mesh")
    with pytest.raises(MeshError, match="cannot read"):
        load_tet_mesh(tmp_path / "garbage.msh")


def test_orientation_and_unused_nodes(tmp_path: Path) -> None:
    mesh = _box_mesh()
    flipped = mesh.tets[:, [0, 1, 3, 2]]
    # An extra node used by no tet is dropped; fixed indices from a file are renumbered.
    points = np.vstack([[0.5, 0.5, 0.5], mesh.nodes])
    path = _write_raw(tmp_path / "flipped.vtu", points, flipped + 1)
    (tmp_path / "fixed.txt").write_text("1 2")
    loaded = load_tet_mesh(path, fixed_nodes_file=tmp_path / "fixed.txt")
    assert loaded.node_count == 8
    assert np.all(loaded.tet_volumes() > 0)
    np.testing.assert_array_equal(loaded.fixed_nodes, [0, 1])
    with pytest.raises(MeshError, match="inverted"):
        load_tet_mesh(path, orient=False)
    (tmp_path / "unused.txt").write_text("0")
    with pytest.raises(MeshError, match="no tet"):
        load_tet_mesh(path, fixed_nodes_file=tmp_path / "unused.txt")


def test_gmsh_physical_groups_become_regions(tmp_path: Path) -> None:
    mesh = _box_mesh()
    path = tmp_path / "groups.msh"
    physical = np.array([7, 7, 7, 9, 9, 7])
    meshio.write(
        path,
        meshio.Mesh(
            mesh.nodes,
            [("tetra", mesh.tets)],
            cell_data={"gmsh:physical": [physical], "gmsh:geometrical": [physical]},
        ),
        file_format="gmsh22",
        binary=False,
    )
    loaded = load_tet_mesh(path)
    np.testing.assert_array_equal(loaded.region, [0, 0, 0, 1, 1, 0])
    assert loaded.region_names == ("tissue", "region_9")


def test_npz_archive_round_trip(tmp_path: Path) -> None:
    mesh = _box_mesh()
    mesh = mesh.with_collision_surface(mesh.nodes[:3] * 0.5, np.array([[0, 1, 2]]))
    mesh = mesh.with_landmarks(("centre",), np.full((1, 3), 0.025))
    mesh = TetMesh(**{**mesh.__dict__, "metadata": {"radii_m": np.array([0.1, 0.2]), "n": 3}})
    path = save_mesh_npz(mesh, tmp_path / "m.npz")
    loaded = load_mesh_npz(path)
    np.testing.assert_array_equal(loaded.tets, mesh.tets)
    np.testing.assert_array_equal(loaded.collision_surface.triangles, [[0, 1, 2]])
    assert loaded.landmarks.names == ("centre",)
    np.testing.assert_array_equal(loaded.metadata["radii_m"], [0.1, 0.2])
    assert loaded.metadata["n"] == 3
    assert [p.name for p in tmp_path.iterdir()] == ["m.npz"]  # no temporary left behind
    (tmp_path / "bad.npz").write_bytes(b"nope")
    with pytest.raises(MeshError, match="cannot read"):
        load_mesh_npz(tmp_path / "bad.npz")


@pytest.mark.parametrize("divisions", [1, 2, 3, 6])
def test_triangle_grid_covers_the_triangle_once(divisions: int) -> None:
    from tissue.mesh import triangle_grid

    every, inside = triangle_grid(divisions), triangle_grid(divisions, interior=True)
    assert len(every) == (divisions + 1) * (divisions + 2) // 2
    assert len(inside) == (divisions - 1) * (divisions - 2) // 2
    for weights in (every, inside):
        np.testing.assert_allclose(weights.sum(axis=1), 1.0)
        assert len(np.unique(np.round(weights, 12), axis=0)) == len(weights)
    assert np.all(every >= 0.0) and np.all(inside > 0.0)
