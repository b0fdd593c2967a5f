"""Implicit integration: exact large-strain compression, Newton convergence, reactions, status."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import scipy.sparse as sp

from tissue.fem.material import NeoHookean, TissueMaterials
from tissue.mesh import node_dofs
from tissue.mesh.block import block_mesh
from tissue.mesh.io import nodes_on_plane
from tissue.sim.integrator import ChordHandOver, IntegratorConfig
from tissue.sim.simulator import SimulationConfig, TissueSimulator, settle
from tissue.sim.solvers import ConstrainedSystem
from tissue.status import StepStatus

E, NU = 3000.0, 0.45


def _uniaxial_closed_form(material: NeoHookean, stretch: float) -> tuple[float, float]:
    """Stable neo-Hookean, frictionless platens: (lateral stretch, axial nominal stress [Pa]).

    W = mu/2 (I_C - 3) + lam'/2 (J - alpha)^2 with F = diag(t, t, a):
    lateral P11 = mu t + lam' (J - alpha) t a = 0  =>  t^2 = (alpha - mu / (lam' a)) / a;
    axial P33 = mu a + lam' (J - alpha) t^2.
    """
    mu, lam = material.mu_pa, material.lambda_pa
    lam_p = lam + mu
    alpha = 1.0 + mu / lam_p
    a = stretch
    t2 = (alpha - mu / (lam_p * a)) / a
    p33 = mu * a + lam_p * (t2 * a - alpha) * t2
    return float(np.sqrt(t2)), float(p33)


def _platen_setup(mesh, height, axial_stretch):
    """Rollers on x=0, y=0, z=0 (symmetry, frictionless base) and the top platen at a·H."""
    x0 = nodes_on_plane(mesh.nodes, "x=min")
    y0 = nodes_on_plane(mesh.nodes, "y=min")
    z0 = nodes_on_plane(mesh.nodes, "z=min")
    top = nodes_on_plane(mesh.nodes, "z=max")
    dofs = np.concatenate(
        [node_dofs(x0, (0,)), node_dofs(y0, (1,)), node_dofs(z0, (2,)), node_dofs(top, (2,))]
    )
    targets = np.concatenate(
        [
            np.zeros(x0.size),
            np.zeros(y0.size),
            np.zeros(z0.size),
            np.full(top.size, axial_stretch * height),
        ]
    )
    return dofs, targets, top


@pytest.mark.parametrize("mode", ["robust", "paper"])
def test_uniaxial_compression_matches_closed_form_at_30_percent(mode: str) -> None:
    size = 0.01
    mesh = block_mesh((size, size, size), (3, 3, 3), fix=None)
    material = NeoHookean(E, NU)
    config = SimulationConfig(mode=mode, quasi_static=True, linear_solver="direct")
    sim = TissueSimulator(mesh, TissueMaterials(tissue=material), config)
    steps = 6 if mode == "robust" else 60  # the linearised paper step needs small increments
    for i in range(1, steps + 1):
        dofs, targets, top = _platen_setup(mesh, size, 1.0 - 0.3 * i / steps)
        sim.prescribe_dofs(dofs, targets)
        result = sim.step()
    if mode == "paper":  # let the linearised steps settle onto equilibrium
        for _ in range(5):
            result = sim.step()
    assert result.status is StepStatus.OK
    lateral, p33 = _uniaxial_closed_form(material, 0.7)
    force = result.reaction_forces[top, 2].sum()
    expected = p33 * size * size
    assert force == pytest.approx(expected, rel=5e-3)
    # The lateral stretch emerges from equilibrium, it is not imposed.
    width = sim.positions[:, 0].max() - sim.positions[:, 0].min()
    assert width / size == pytest.approx(lateral, rel=5e-3)


def test_newton_converges_quadratically_under_prescribed_top() -> None:
    size = 0.02
    mesh = block_mesh((size, size, size / 2), (4, 4, 2), fix="z=min")
    config = SimulationConfig(
        mode="robust", quasi_static=True, linear_solver="direct", newton_tolerance=1e-11
    )
    sim = TissueSimulator(mesh, TissueMaterials(tissue=NeoHookean(E, NU)), config)
    top = nodes_on_plane(mesh.nodes, "z=max")
    sim.prescribe(top, mesh.nodes[top] + [0.001, 0.0, -0.004])  # 40 % squeeze and shear
    result = sim.step()
    assert result.status is StepStatus.OK, result
    # The first entry is measured before the prescribed nodes reach their targets.
    history = np.array(result.newton_residuals)[1:]
    assert history[-1] <= 1e-11
    # Near the solution (where robust mode uses the exact tangent, below a relative residual
    # of 0.1, after any fallback to projection) each residual is at most about the square
    # of the previous one.
    tail = [
        (a, b)
        for a, b in zip(history[:-1], history[1:], strict=False)
        if a < 2e-3 and b > 1e-13  # below: round-off
    ]
    assert tail, history
    for previous, current in tail:
        assert current <= 50.0 * previous**2, history


def test_prescribed_reaction_balances_fixed_base_at_equilibrium() -> None:
    size = 0.02
    mesh = block_mesh((size, size, size / 2), (4, 4, 2), fix="z=min")
    config = SimulationConfig(mode="robust", quasi_static=True)
    sim = TissueSimulator(mesh, TissueMaterials(tissue=NeoHookean(E, NU)), config)
    top = nodes_on_plane(mesh.nodes, "z=max")
    sim.prescribe(top, mesh.nodes[top] + [0.0, 0.0, -0.002])
    result = sim.step()
    on_top = result.reaction_force_n(top)
    on_base = result.reaction_force_n(mesh.fixed_nodes)
    assert on_top[2] < 0  # the platen pushes down on the tissue
    np.testing.assert_allclose(on_top + on_base, 0.0, atol=1e-6 * abs(on_top[2]))


@pytest.mark.parametrize("mode", ["paper", "robust"])
def test_dynamic_compression_settles_to_quasi_static_answer(mode: str) -> None:
    size = 0.02
    mesh = block_mesh((size, size, size / 2), (4, 4, 2), fix="z=min")
    materials = TissueMaterials(tissue=NeoHookean(E, NU))
    top = nodes_on_plane(mesh.nodes, "z=max")
    target = mesh.nodes[top] + [0.0, 0.0, -0.001]

    static = TissueSimulator(mesh, materials, SimulationConfig(mode="robust", quasi_static=True))
    static.prescribe(top, target)
    reference = static.step()

    dynamic = TissueSimulator(mesh, materials, SimulationConfig(mode=mode, linear_solver="direct"))
    for i in range(1, 11):
        dynamic.prescribe(top, mesh.nodes[top] + [0.0, 0.0, -0.0001 * i])
        dynamic.step()
    result = settle(dynamic, max_steps=400, speed_tol_m_s=1e-7)
    assert result.status is StepStatus.OK
    np.testing.assert_allclose(result.positions, reference.positions, atol=1e-7)
    force, expected = result.reaction_force_n(top)[2], reference.reaction_force_n(top)[2]
    assert force == pytest.approx(expected, rel=1e-3)


def test_capped_cg_reports_its_residual_honestly() -> None:
    mesh = block_mesh((0.04, 0.04, 0.02), (8, 8, 4), fix="z=min")
    config = SimulationConfig(mode="paper", cg_max_iterations=3)
    sim = TissueSimulator(mesh, TissueMaterials(tissue=NeoHookean(E, 0.49)), config)
    top = nodes_on_plane(mesh.nodes, "z=max")
    sim.prescribe(top, mesh.nodes[top] + [0.0, 0.0, -0.0005])
    result = sim.step()
    assert result.linear_iterations == 3
    assert result.linear_residual > 1e-3  # three iterations cannot converge this system


def test_inverting_step_in_classic_law_is_reported_not_raised() -> None:
    mesh = block_mesh((0.01, 0.01, 0.01), (2, 2, 2), fix="z=min")
    materials = TissueMaterials(tissue=NeoHookean(E, NU), law="classic")
    sim = TissueSimulator(mesh, materials, SimulationConfig(mode="paper", linear_solver="direct"))
    top = nodes_on_plane(mesh.nodes, "z=max")
    sim.prescribe(top, mesh.nodes[top] + [0.0, 0.0, -0.015])  # through the base in one step
    result = sim.step()
    assert result.status in (StepStatus.INVERTED, StepStatus.DIVERGED, StepStatus.SOLVER_FAILED)
    assert np.all(np.isfinite(result.positions))
    assert np.all(np.isfinite(sim.positions))


def test_a_blown_up_step_is_reported_without_a_numpy_warning() -> None:
    """Positions finite but astronomically far out (a paper-mode LM cell of the quick study
    diverged so) are a divergence, said by the status alone: before, squaring them in the
    blow-up check printed numpy's "overflow encountered in multiply" to the user."""
    mesh = block_mesh((0.01, 0.01, 0.01), (2, 2, 2), fix="z=min")
    sim = TissueSimulator(mesh, TissueMaterials(tissue=NeoHookean(E, NU)), SimulationConfig())
    top = nodes_on_plane(mesh.nodes, "z=max")
    sim.prescribe(top, mesh.nodes[top] + [0.0, 0.0, 1e156])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        result = sim.step()
    assert result.status is StepStatus.DIVERGED
    assert np.all(np.isfinite(result.positions)) and np.all(np.isfinite(sim.positions))


def test_robust_mode_survives_the_same_violent_step() -> None:
    mesh = block_mesh((0.01, 0.01, 0.01), (2, 2, 2), fix="z=min")
    sim = TissueSimulator(
        mesh, TissueMaterials(tissue=NeoHookean(E, NU)), SimulationConfig(mode="robust")
    )
    top = nodes_on_plane(mesh.nodes, "z=max")
    sim.prescribe(top, mesh.nodes[top] + [0.0, 0.0, -0.006])  # 60 % in one step
    result = sim.step()
    assert np.all(np.isfinite(result.positions))
    assert result.status in (StepStatus.OK, StepStatus.NOT_CONVERGED)
    assert result.min_volume_ratio > 0.0


@pytest.mark.parametrize("barrier", [0.0, None])
def test_robust_inversion_barrier_carries_a_point_push_the_plain_law_cannot(barrier) -> None:
    """One top node pushed through 90 % of a coarse block's height in 20 steps (as a
    prescribed-displacement probe touching a single node of a coarse mesh does): without
    the barrier the robust solve fails near the bottom (a tet at J ~ 0.01 or below); with
    robust mode's default barrier every step converges with every tet uninverted."""
    mesh = block_mesh((0.02, 0.02, 0.01), (2, 2, 2), fix="z=min")
    config = SimulationConfig(mode="robust", inversion_barrier=barrier)
    sim = TissueSimulator(mesh, TissueMaterials(tissue=NeoHookean(E, 0.49)), config)
    top = nodes_on_plane(mesh.nodes, "z=max")
    centre = top[np.argmin(np.linalg.norm(mesh.nodes[top, :2] - 0.01, axis=1))]
    statuses = []
    for k in range(1, 21):
        sim.prescribe([centre], mesh.nodes[centre] + [0.0, 0.0, -0.009 * k / 20])
        result = sim.step()
        statuses.append(result.status)
        assert np.all(np.isfinite(result.positions))
        if result.status.is_failure:
            break
    if barrier == 0.0:
        assert statuses[-1].is_failure, "the plain law no longer fails here: the case is too easy"
    else:
        assert config.inversion_barrier == 0.1
        assert statuses == [StepStatus.OK] * 20
        assert 0.0 < result.min_volume_ratio < 0.1  # the barrier was what held it


def test_continued_steps_start_from_extrapolation_and_converge_to_the_same_state() -> None:
    size = 0.02
    mesh = block_mesh((size, size, size / 2), (4, 4, 2), fix="z=min")
    materials = TissueMaterials(tissue=NeoHookean(E, NU))
    top = nodes_on_plane(mesh.nodes, "z=max")
    config = SimulationConfig(mode="robust", newton_tolerance=1e-6)
    continued = TissueSimulator(mesh, materials, config)
    restarted = TissueSimulator(mesh, materials, config)
    iterations = np.zeros(2, dtype=int)
    for i in range(1, 9):
        target = mesh.nodes[top] + [0.0, 0.0, -0.0002 * i]
        continued.prescribe(top, target)
        first = continued.step()
        restarted.prescribe(top, target)
        # A state set from outside is not the last step's: no extrapolation.
        restarted.set_state(restarted.positions, restarted.velocities)
        second = restarted.step()
        for result in (first, second):
            assert result.status is StepStatus.OK
            assert result.newton_residual <= 1e-6
        if i > 2:  # steadier motion: the extrapolated start is closer to the solution
            assert first.newton_residuals[0] < 0.5 * second.newton_residuals[0]
            iterations += [first.newton_iterations, second.newton_iterations]
    # Never more Newton iterations in steady motion (the first residual of each step is
    # what the start changes; each step here needs one or two either way). The second
    # step, extrapolated from a first one that started at rest, may take one more: its
    # start is no closer (3.1e-2 against 2.1e-2 here), and the chord step its second
    # iteration takes (see ImplicitIntegrator._newton) converges only linearly.
    assert iterations[0] <= iterations[1]
    np.testing.assert_allclose(continued.positions, restarted.positions, atol=1e-9)


def test_a_step_handed_a_start_near_its_solution_starts_there_once() -> None:
    size = 0.02
    mesh = block_mesh((size, size, size / 2), (4, 4, 2), fix="z=min")
    materials = TissueMaterials(tissue=NeoHookean(E, NU))
    top = nodes_on_plane(mesh.nodes, "z=max")
    sim = TissueSimulator(mesh, materials, SimulationConfig(mode="robust", newton_tolerance=1e-6))
    sim.prescribe(top, mesh.nodes[top] + [0.0, 0.0, -0.001])
    x0, v0 = sim.positions.copy(), sim.velocities.copy()
    plain = sim.step()
    solution = sim.positions.copy()
    sim.set_state(x0, v0)
    sim.integrator.start_next_step_near(solution)
    near = sim.step()
    for result in (plain, near):
        assert result.status is StepStatus.OK
    # Started at its own solution: converged at once, to the same state (a plain start
    # has the prescribed nodes off their targets and takes Newton iterations).
    assert plain.newton_iterations >= 2
    assert near.newton_iterations == 0
    assert near.newton_residuals[0] <= 1e-6
    np.testing.assert_allclose(sim.positions, solution, atol=1e-9)
    # Handed over for one step: the next solve from the same state starts as a plain one.
    sim.set_state(x0, v0)
    assert sim.step().newton_residuals == plain.newton_residuals
    # A state set from outside forgets a start handed over before it.
    sim.set_state(x0, v0)
    sim.integrator.start_next_step_near(solution)
    sim.set_state(x0, v0)
    assert sim.step().newton_residuals == plain.newton_residuals
    with pytest.raises(ValueError, match=r"shape \(\d+, 3\).*got \(3,\)"):
        sim.integrator.start_next_step_near(np.zeros(3))


def _count_calls(owner: object, name: str) -> list[int]:
    """Wrap ``owner.name`` so that each call adds one to the returned one-item list."""
    calls = [0]
    method = getattr(owner, name)

    def counted(*args, **kwargs):
        calls[0] += 1
        return method(*args, **kwargs)

    setattr(owner, name, counted)
    return calls


def test_paper_step_reuses_its_end_evaluation_only_where_it_starts() -> None:
    """A paper step keeps its end-of-step evaluation (with the tangent) for the next step;
    the next step takes it only if it starts at exactly those positions, and the trajectory
    is the same, bit for bit, as one that evaluates afresh every step."""
    size = 0.02
    mesh = block_mesh((size, size, size / 2), (4, 4, 2), fix="z=min")
    materials = TissueMaterials(tissue=NeoHookean(E, NU))
    top = nodes_on_plane(mesh.nodes, "z=max")
    config = SimulationConfig(mode="paper", linear_solver="direct")
    kept = TissueSimulator(mesh, materials, config)
    fresh = TissueSimulator(mesh, materials, config)
    calls = _count_calls(kept.integrator.elasticity, "evaluate")
    for i in range(1, 6):
        target = mesh.nodes[top] + [0.0, 0.0, -0.0002 * i]
        kept.prescribe(top, target)
        first = kept.step()
        fresh.prescribe(top, target)
        fresh.integrator._end_state = None  # nothing kept: evaluates at the start
        second = fresh.step()
        np.testing.assert_array_equal(first.positions, second.positions)
        # The energy and det F it reports are those of the energy-only pass it replaced.
        energy, ratio = kept.integrator.elasticity.energy_and_min_volume_ratio(first.positions)
        assert (first.elastic_energy_j, first.min_volume_ratio) == (energy, ratio)
    assert calls[0] == 5  # one a step (the model's first: at rest, when it was built)
    # Moved from outside: the kept evaluation is of other positions and is not used.
    moved = kept.positions + 1e-5
    kept.set_state(moved, kept.velocities)
    fresh.set_state(moved, fresh.velocities)
    fresh.integrator._end_state = None
    np.testing.assert_array_equal(kept.step().positions, fresh.step().positions)
    assert calls[0] == 7


class _Quadratic:
    """E(y) = 1/2 y^T A y - b^T y with a record of the points evaluated (the line search's
    ``evaluate``: energy [J], gradient [N], force scale [N])."""

    def __init__(self, energy_offset: float = 0.0) -> None:
        rng = np.random.default_rng(3)
        q = rng.standard_normal((6, 6))
        self.a = q @ q.T + 6.0 * np.eye(6)
        self.b = rng.standard_normal(6)
        self.offset = energy_offset
        self.evaluated: list[np.ndarray] = []

    def __call__(self, y: np.ndarray) -> tuple[float, np.ndarray, float]:
        self.evaluated.append(y.copy())
        gradient = self.a @ y - self.b
        return 0.5 * y @ self.a @ y - self.b @ y + self.offset, gradient, 1.0


@pytest.mark.parametrize("fraction", [0.25, 0.3, 0.4, 0.6])
def test_line_search_extrapolates_a_full_step_that_falls_short(fraction: float) -> None:
    """A step a fraction of Newton's (as when Newton converges only linearly) is lengthened
    to the secant's zero of the directional derivative: exact on a quadratic, capped at 4.
    Past half of Newton's step (the energy falling at under half its initial rate at its end)
    the step is kept as it is."""
    from tissue.sim.integrator.line_search import line_search

    energy = _Quadratic()
    y = np.zeros(6)
    e0, g0, _ = energy(y)
    newton = -np.linalg.solve(energy.a, g0)
    found = line_search(y, fraction * newton, g0, 0.0, energy, e0, config=IntegratorConfig())
    assert found is not None
    point, point_energy, point_gradient, _ = found
    expected = (min(4.0, 1.0 / fraction) if fraction < 0.5 else 1.0) * fraction * newton
    np.testing.assert_allclose(point, expected, rtol=1e-12, atol=1e-15)
    if fraction < 0.5:
        assert point_energy < energy(y + fraction * newton)[0]
    np.testing.assert_allclose(point_gradient, energy.a @ point - energy.b, atol=1e-12)


def test_line_search_keeps_a_good_full_step_and_evaluates_last_where_it_ends() -> None:
    """Newton's own step is kept without a further evaluation; a step whose extrapolation
    does not lower the energy is kept too, evaluated again (contact terms report the last
    evaluation's forces)."""
    from tissue.sim.integrator.line_search import line_search

    config = IntegratorConfig()
    energy = _Quadratic()
    y = np.zeros(6)
    e0, g0, _ = energy(y)
    newton = -np.linalg.solve(energy.a, g0)
    evaluations = len(energy.evaluated)
    point, *_ = line_search(y, newton, g0, 0.0, energy, e0, config=config)
    np.testing.assert_allclose(point, newton, rtol=1e-12)
    assert len(energy.evaluated) == evaluations + 1

    class _RisesBeyondOne(_Quadratic):
        def __call__(self, y: np.ndarray) -> tuple[float, np.ndarray, float]:
            e, g, s = super().__call__(y)
            beyond = np.linalg.norm(y) > 1.5 * np.linalg.norm(0.3 * newton)
            return (e + 1.0 if beyond else e), g, s

    rising = _RisesBeyondOne()
    point, point_energy, *_ = line_search(y, 0.3 * newton, g0, 0.0, rising, e0, config=config)
    np.testing.assert_allclose(point, 0.3 * newton, rtol=1e-12)
    assert len(rising.evaluated) == 3  # the step, its extrapolation, the step again
    np.testing.assert_array_equal(rising.evaluated[-1], point)
    assert point_energy == rising(point)[0]


def test_start_evaluation_with_tangent_serves_the_hessian_there_only() -> None:
    """``evaluate(z, with_tangent=True)`` keeps its exact tangent for the next Hessian at
    that very z: the same system, bit for bit, as a fresh assembly, and one element pass
    fewer. A Hessian elsewhere, or projected, or after z changed in place, assembles anew."""
    size = 0.02
    mesh = block_mesh((size, size, size / 2), (4, 4, 2), fix="z=min")
    sim = TissueSimulator(mesh, TissueMaterials(tissue=NeoHookean(E, NU)))
    dofs, targets = sim.constraints()
    rng = np.random.default_rng(4)
    v = rng.normal(0.0, 0.01, sim.velocities.shape)
    potential = sim.integrator.incremental_potential(sim.positions, v, 0.02, dofs, targets)
    z = potential.start()
    passes = _count_calls(sim.integrator.elasticity, "evaluate")
    plain = potential.evaluate(z)
    expected = potential.hessian_system(z, -plain[1], project=False).matrix.data.copy()
    assert passes[0] == 2
    kept = potential.evaluate(z, with_tangent=True)
    assert kept[0] == plain[0] and np.array_equal(kept[1], plain[1])
    system = potential.hessian_system(z, -kept[1], project=False)
    assert passes[0] == 3  # the Hessian took the kept tangent
    np.testing.assert_array_equal(system.matrix.data, expected)
    potential.hessian_system(z, -kept[1], project=False)
    assert passes[0] == 4  # used once: its matrix is the system's
    potential.evaluate(z, with_tangent=True)
    z[0] += 1e-6  # moved in place since
    potential.hessian_system(z, -kept[1], project=False)
    assert passes[0] == 6
    potential.evaluate(z, with_tangent=True)
    potential.hessian_system(z, -kept[1], project=True)  # projected: not the kept tangent
    assert passes[0] == 8


def test_term_stiffness_outside_the_mesh_pattern_is_an_error() -> None:
    """A term coupling two nodes of no common tet cannot enter the elastic pattern: named."""
    from tissue.sim.integrator import TermEvaluation

    size = 0.02
    mesh = block_mesh((size, size, size / 2), (4, 4, 2), fix="z=min")
    sim = TissueSimulator(
        mesh, TissueMaterials(tissue=NeoHookean(E, NU)), SimulationConfig(mode="paper")
    )
    far = int(np.argmax(np.linalg.norm(mesh.nodes - mesh.nodes[0], axis=1)))

    class Spring:
        def evaluate(self, positions):
            return TermEvaluation(
                energy_j=0.0,
                forces=np.zeros_like(positions),
                stiffness_rows=np.array([0, 3 * far]),
                stiffness_cols=np.array([3 * far, 0]),
                stiffness_values=np.array([1.0, 1.0]),
            )

    with pytest.raises(ValueError, match="outside the mesh's pattern"):
        sim.step(terms=(Spring(),))


def test_chord_hand_over_backs_off_after_chords_that_needed_more_iterations() -> None:
    """ChordHandOver: a step converged in one full exact iteration hands its matrix on; a
    handed matrix is taken once and only for the same time step and constraints; a handed
    chord that needed a second iteration pauses the hand-over for 1, then 2, 4, ... steps
    (capped), and one that converged at once halves the pause."""
    dofs = 12
    constrained = np.zeros(dofs, dtype=bool)
    system = ConstrainedSystem(
        sp.identity(dofs, format="csr"), np.zeros(dofs), constrained, np.zeros(dofs)
    )
    cap = IntegratorConfig().chord_backoff_max_steps
    chords = ChordHandOver(cap)

    def step(took: bool, iterations: int, full_exact: bool = True) -> bool:
        """A converged step; whether the next step is handed a matrix."""
        chords.record(system, 0.02, took, iterations, full_exact)
        return chords.take(0.02, constrained) is system

    assert step(False, 1)  # converged at once: handed on
    assert not step(False, 2)  # two iterations: nothing to hand on
    assert not step(False, 1, full_exact=False)  # projected or shortened: nothing
    chords.record(system, 0.02, False, 1, True)
    assert chords.take(0.01, constrained) is None  # another time step
    assert chords.take(0.02, constrained) is None  # taken (dropped) once
    chords.record(system, 0.02, False, 1, True)
    assert chords.take(0.02, ~constrained) is None  # other constraints
    assert not step(True, 2)  # a handed chord needed two: paused for one more step
    assert not step(False, 1)  # the paused step
    assert step(False, 1)
    assert not step(True, 2) and not step(False, 1) and not step(False, 1)  # paused for 2
    assert step(False, 1)
    for _ in range(10):
        step(True, 2)
    assert chords._backoff == cap
    chords.reset()
    assert step(False, 1)
    chords._backoff = 8
    assert step(True, 1) and chords._backoff == 4  # a chord that converged halves it


@pytest.mark.parametrize("mode", ["paper", "robust"])
def test_mass_damping_slows_a_rigid_translation_as_backward_euler_says(mode: str) -> None:
    """A free block translating rigidly feels no elastic force and no stiffness damping, only
    r_M: backward Euler gives v_{n+1} = v_n / (1 + h r_M) exactly, and the robust Newton,
    whose Hessian carries the same r_M M / h, gets it in one iteration."""
    from tissue.mesh import TetMesh

    block = block_mesh((0.02, 0.02, 0.01), (2, 2, 1))
    free = TetMesh(block.nodes, block.tets, block.region, np.zeros(0, dtype=np.int64))
    config = SimulationConfig(mode=mode, rayleigh_mass=2.0, rayleigh_stiffness=0.1)
    sim = TissueSimulator(free, TissueMaterials(tissue=NeoHookean(E, NU)), config)
    velocity = np.array([0.01, -0.02, 0.005])
    sim.set_state(free.nodes, np.tile(velocity, (free.node_count, 1)))
    h = config.tissue_dt
    for step in range(1, 6):
        result = sim.step()
        expected = velocity / (1.0 + h * config.rayleigh_mass) ** step
        np.testing.assert_allclose(
            sim.velocities, np.tile(expected, (free.node_count, 1)), rtol=1e-4
        )
        if mode == "robust":
            assert result.newton_iterations == 1
