"""Node frames: Dirichlet conditions along a normal (frictionless planes) in any direction."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import scipy.sparse as sp

from tissue.errors import TissueInputError
from tissue.fem.material import NeoHookean, TissueMaterials
from tissue.mesh import node_dofs
from tissue.mesh.block import block_mesh
from tissue.mesh.io import nodes_on_plane
from tissue.sim.frames import NodeFrames
from tissue.sim.simulator import SimulationConfig, TissueSimulator
from tissue.sim.solvers import ConstrainedSystem, LinearSolver, LinearSolverConfig
from tissue.status import StepStatus

MATERIALS = TissueMaterials(tissue=NeoHookean(3000.0, 0.45))


def _rotation(axis: tuple[float, float, float], angle_rad: float) -> np.ndarray:
    """Rodrigues' rotation matrix about ``axis`` by ``angle_rad``."""
    k = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    cross = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle_rad) * cross + (1 - np.cos(angle_rad)) * cross @ cross


def test_rotating_a_tangent_in_place_is_q_a_qt() -> None:
    """The in-place rotation of a stiffness matrix equals Q A Q^T formed densely, and the
    vector maps are each other's inverse."""
    mesh = block_mesh((0.01, 0.01, 0.01), (3, 3, 3))
    sim = TissueSimulator(mesh, MATERIALS)
    rng = np.random.default_rng(3)
    positions = mesh.nodes + 2e-4 * rng.standard_normal(mesh.nodes.shape)
    stiffness = sim.elasticity.evaluate(positions, tangent=True).stiffness
    assert stiffness is not None
    nodes = rng.choice(mesh.node_count, 12, replace=False)
    frames = NodeFrames.from_normals(nodes, rng.standard_normal((12, 3)), mesh.node_count)
    q = np.eye(mesh.dof_count)
    for slot, node in enumerate(nodes):
        q[3 * node : 3 * node + 3, 3 * node : 3 * node + 3] = frames.axes[slot]
    expected = q @ stiffness.toarray() @ q.T
    rotated = stiffness.copy()
    frames.rotate_matrix(rotated)
    assert np.abs(rotated.toarray() - expected).max() <= 1e-12 * np.abs(expected).max()
    vector = rng.standard_normal(mesh.dof_count)
    np.testing.assert_allclose(frames.to_local(vector), q @ vector, atol=1e-15)
    np.testing.assert_allclose(frames.to_world(frames.to_local(vector)), vector, atol=1e-15)
    # Each frame is right-handed and orthonormal, its first axis the given normal.
    identity = np.broadcast_to(np.eye(3), (12, 3, 3))
    np.testing.assert_allclose(
        np.einsum("kij,klj->kil", frames.axes, frames.axes), identity, atol=1e-15
    )
    np.testing.assert_allclose(np.linalg.det(frames.axes), 1.0)


def test_a_matrix_without_whole_node_blocks_is_refused() -> None:
    frames = NodeFrames.from_normals(np.array([0]), np.array([[0.0, 0.0, 1.0]]), 2)
    diagonal = sp.identity(6, format="csr")
    with pytest.raises(ValueError, match="3 x 3 blocks"):
        frames.rotate_matrix(diagonal)


@pytest.mark.parametrize(
    ("mode", "quasi_static"), [("robust", True), ("robust", False), ("paper", False)]
)
def test_a_tilted_frictionless_platen_gives_the_rotated_answer(
    mode: str, quasi_static: bool
) -> None:
    """A block pressed 1.5 mm by a frictionless platen along z (its top held in z only),
    and the same block rotated by 40 degrees with its top held along the rotated normal
    (``prescribe_normal``): the material is isotropic, so the second answer is the first
    rotated, positions and reactions, to round-off (a direct solver on both sides)."""
    mesh = block_mesh((0.01, 0.01, 0.01), (3, 3, 3))
    top = nodes_on_plane(mesh.nodes, "z=max")
    config = SimulationConfig(
        mode=mode, quasi_static=quasi_static, linear_solver="direct", newton_tolerance=1e-10
    )
    flat = TissueSimulator(mesh, MATERIALS, config)
    press = mesh.nodes[top] - np.array([0.0, 0.0, 0.0015])
    flat.prescribe(top, press, axes=(2,))

    rotation = _rotation((1.0, 2.0, 3.0), np.radians(40.0))
    turned_mesh = dataclasses.replace(mesh, nodes=mesh.nodes @ rotation.T)
    turned = TissueSimulator(turned_mesh, MATERIALS, config)
    normal = np.broadcast_to(rotation[:, 2], (top.size, 3))
    turned.prescribe_normal(top, press @ rotation.T, normal)

    for _ in range(3):
        expected = flat.step()
        result = turned.step()
        assert expected.status is StepStatus.OK and result.status is StepStatus.OK
        scale = np.abs(expected.positions).max()
        np.testing.assert_allclose(
            result.positions, expected.positions @ rotation.T, atol=1e-9 * scale
        )
        force = np.abs(expected.reaction_forces).max()
        np.testing.assert_allclose(
            result.reaction_forces, expected.reaction_forces @ rotation.T, atol=1e-7 * force
        )
    # The top slid: held along the normal only, it spreads sideways like the flat one.
    spread = turned.positions[top] - turned_mesh.nodes[top]
    assert np.abs(spread - np.outer(spread @ rotation[:, 2], rotation[:, 2])).max() > 1e-5


def test_prescribe_normal_rejects_bad_input() -> None:
    mesh = block_mesh((0.01, 0.01, 0.01), (2, 2, 2))
    sim = TissueSimulator(mesh, MATERIALS)
    top = nodes_on_plane(mesh.nodes, "z=max")
    points = mesh.nodes[top]
    with pytest.raises(TissueInputError, match="normals"):
        sim.prescribe_normal(top, points, np.zeros((top.size, 3)))
    with pytest.raises(TissueInputError, match="points"):
        sim.prescribe_normal(top, points[:-1], np.ones((top.size, 3)))
    with pytest.raises(TissueInputError, match="fixed node"):
        sim.prescribe_normal(mesh.fixed_nodes[:2], points[:2], np.ones((2, 3)))
    with pytest.raises(TissueInputError, match="unique"):
        sim.prescribe_normal(np.r_[top[:1], top[:1]], points[:2], np.ones((2, 3)))


def _framed_system(stiffness, mesh, nodes, normals, rhs):
    """K (a copy) written in frames whose first axis is ``normals`` at ``nodes``, with the
    fixed base and those first axes constrained (to zero)."""
    frames = NodeFrames.from_normals(nodes, normals, mesh.node_count)
    matrix = stiffness.copy()
    frames.rotate_matrix(matrix)
    constrained = np.zeros(mesh.dof_count, dtype=bool)
    constrained[node_dofs(mesh.fixed_nodes)] = True
    constrained[3 * nodes] = True
    return ConstrainedSystem(
        matrix, frames.to_local(rhs), constrained, np.zeros(mesh.dof_count), frames=frames
    )


@pytest.mark.parametrize("turning", [True, False])
def test_a_kept_factor_preconditions_a_system_in_turned_frames(turning: bool) -> None:
    """``reuse`` keeps a factorisation of a system written in some node frames; the next
    system's frames have turned (by up to 15 degrees more) and more nodes are framed.

    When the frames were turning as it was factorised (each of its nodes' frames differs
    from the factorisation before), it holds their constrained axes free
    (``ConstrainedSystem.unframed``): turned into the new frames (``FrameChange``) and
    corrected for their constrained axes, it solves the new system in one or two CG
    iterations without refactorising. When they were not turning it holds those axes
    eliminated, and the turned axes cost CG more iterations (14-15 here)."""
    mesh = block_mesh((0.01, 0.01, 0.01), (4, 4, 4))
    sim = TissueSimulator(mesh, MATERIALS)
    stiffness = sim.elasticity.evaluate(mesh.nodes, tangent=True).stiffness
    assert stiffness is not None
    top = nodes_on_plane(mesh.nodes, "z=max")
    rhs = np.random.default_rng(7).standard_normal(mesh.dof_count)

    def tilted(count: int, degrees: float) -> np.ndarray:
        angle = np.radians(degrees) * np.linspace(0.2, 1.0, count)
        return np.stack([np.sin(angle), np.zeros(count), np.cos(angle)], axis=1)

    solver = LinearSolver(LinearSolverConfig(kind="reuse", reuse_refresh_factor=0.0))
    solver.refresh_kept_factorization(
        _framed_system(stiffness, mesh, top[:10], tilted(10, 5.0 if turning else 10.0), rhs)
    )
    solver.refresh_kept_factorization(
        _framed_system(stiffness, mesh, top[:10], tilted(10, 10.0), rhs)
    )
    exact, _ = LinearSolver(LinearSolverConfig(kind="direct")).solve(
        _framed_system(stiffness, mesh, top[:16], tilted(16, 25.0), rhs)
    )
    solution, report = solver.solve(
        _framed_system(stiffness, mesh, top[:16], tilted(16, 25.0), rhs), tolerance=1e-10
    )
    assert not report.factorized
    np.testing.assert_allclose(solution, exact, atol=1e-8 * np.abs(exact).max())
    if turning:
        assert report.iterations <= 2
    else:
        assert report.iterations >= 6
