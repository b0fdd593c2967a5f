"""Bad input raises a clear error naming the value, what was expected and how to fix it."""

from __future__ import annotations

import numpy as np
import pytest

from tissue.errors import ConfigError, MaterialError, MeshError
from tissue.fem.material import NeoHookean, TissueMaterials
from tissue.mesh import TetMesh
from tissue.mesh.block import block_mesh
from tissue.sim.simulator import SimulationConfig, TissueSimulator


@pytest.mark.parametrize(
    ("kwargs", "named"),
    [
        ({"young_pa": 0.0}, "0.0"),
        ({"young_pa": -5.0}, "-5.0"),
        ({"poisson": 0.5}, "0.5"),
        ({"poisson": -1.0}, "-1.0"),
        ({"poisson": float("nan")}, "nan"),
        ({"density_kg_m3": 0.0}, "density"),
    ],
)
def test_material_out_of_range(kwargs: dict, named: str) -> None:
    with pytest.raises(MaterialError) as error:
        NeoHookean(**kwargs)
    assert named in str(error.value)


def test_unknown_material_law_lists_valid_ones() -> None:
    with pytest.raises(MaterialError, match="'stable'"):
        TissueMaterials(law="mooney")


def _unit_tet_mesh(nodes: np.ndarray, tets: np.ndarray) -> TetMesh:
    return TetMesh(
        nodes=nodes, tets=tets, region=np.zeros(len(tets), np.int64), fixed_nodes=np.array([0])
    )


def test_inverted_tet_is_rejected_with_its_index() -> None:
    nodes = np.array([[0, 0, 0], [0.01, 0, 0], [0, 0.01, 0], [0, 0, 0.01]], dtype=float)
    with pytest.raises(MeshError, match="inverted.*\\[0\\]"):
        _unit_tet_mesh(nodes, np.array([[0, 2, 1, 3]]))


def test_degenerate_tet_is_rejected() -> None:
    nodes = np.array(
        [[0, 0, 0], [0.01, 0, 0], [0, 0.01, 0], [0.01, 0.01, 0], [0, 0, 0.01]], dtype=float
    )
    with pytest.raises(MeshError, match="degenerate"):
        _unit_tet_mesh(nodes, np.array([[0, 1, 2, 4], [0, 1, 2, 3]]))


def test_mesh_in_millimetres_is_caught() -> None:
    mesh = block_mesh((0.14, 0.12, 0.08), (2, 2, 2))
    with pytest.raises(MeshError, match="millimetres"):
        TetMesh(
            nodes=mesh.nodes * 1000.0,
            tets=mesh.tets,
            region=mesh.region,
            fixed_nodes=mesh.fixed_nodes,
        )


def test_quasi_static_without_enough_fixed_nodes_is_rejected() -> None:
    mesh = block_mesh((0.01, 0.01, 0.01), (2, 2, 2), fix=None)
    sim = TissueSimulator(mesh, config=SimulationConfig(quasi_static=True))
    with pytest.raises(MeshError, match="rigid motion"):
        sim.step()


@pytest.mark.parametrize(
    ("overrides", "named"),
    [
        ({"mode": "fast"}, "'fast'"),
        ({"linear_solver": "cholmod"}, "'cholmod'"),
        ({"anti_locking": "fbar2"}, "'fbar2'"),
        ({"tissue_dt": 0.0}, "0.0"),
        ({"newton_tolerance": 0.0}, "0.0"),
        ({"tissue_timestep": 0.01}, "tissue_timestep"),
    ],
)
def test_bad_simulation_settings_are_named(overrides: dict, named: str) -> None:
    with pytest.raises(ConfigError) as error:
        SimulationConfig.from_overrides(**overrides)
    assert named in str(error.value)


def test_unknown_level_lists_valid_levels() -> None:
    from tissue.mesh.phantom import parse_level

    with pytest.raises(ConfigError, match="4126"):
        parse_level(5000)
