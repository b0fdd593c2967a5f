"""Linear solvers: agreement with a dense solve, constraints, indefinite fallback, reuse."""

from __future__ import annotations

import threading

import numba
import numpy as np
import pytest
import scipy.sparse as sp

from tissue.errors import ConfigError
from tissue.fem.elasticity import Elasticity
from tissue.fem.material import TissueMaterials
from tissue.mesh.block import block_mesh
from tissue.sim.pardiso import pardiso_available
from tissue.sim.solvers import (
    NO_BLOCKS,
    ConstrainedSystem,
    DirectFactorizer,
    LinearSolver,
    LinearSolverConfig,
    NodeBlocks,
    RankOneTerms,
    SymmetricProduct,
    jacobi_pcg,
)
from tissue.threads import one_thread_below, parallel_kernel, running_on_one_thread


@parallel_kernel
def _doubled_sum(values):  # pragma: no cover - compiled
    total = 0.0
    for i in numba.prange(values.shape[0]):
        total += 2.0 * values[i]
    return total


def _laplacian_3d(n: int, shift: float) -> sp.csr_matrix:
    one = sp.diags([-1.0, 2.0, -1.0], [-1, 0, 1], shape=(n, n))
    eye = sp.eye(n)
    matrix = (
        sp.kron(sp.kron(one, eye), eye)
        + sp.kron(sp.kron(eye, one), eye)
        + sp.kron(sp.kron(eye, eye), one)
    )
    matrix = (matrix + shift * sp.eye(n**3)).tocsr()
    matrix.sort_indices()
    return matrix


def _record_kept_solves(solver: LinearSolver) -> list[tuple[int, ...]]:
    """Wrap the solver's kept factorisation so that each of its solves appends its
    right-hand side's shape to the returned list."""
    kept = solver.kept_factorization
    assert kept is not None
    shapes: list[tuple[int, ...]] = []
    solve = kept.solve

    def counted(rhs):
        shapes.append(np.shape(rhs))
        return solve(rhs)

    kept.solve = counted  # type: ignore[method-assign]
    return shapes


def _reference(matrix: sp.csr_matrix, rhs, constrained, values):
    free = ~constrained
    dense = matrix.toarray()
    x = np.where(constrained, values, 0.0)
    x[free] = np.linalg.solve(
        dense[np.ix_(free, free)],
        rhs[free] - dense[np.ix_(free, constrained)] @ values[constrained],
    )
    return x


@pytest.mark.parametrize("kind", ["cg", "direct", "reuse"])
def test_constrained_solution_matches_dense_reference(kind: str) -> None:
    rng = np.random.default_rng(1)
    matrix = _laplacian_3d(6, 0.05)
    rhs = rng.standard_normal(matrix.shape[0])
    constrained = rng.random(matrix.shape[0]) < 0.1
    values = rng.standard_normal(matrix.shape[0])
    expected = _reference(matrix, rhs, constrained, values)
    solver = LinearSolver(LinearSolverConfig(kind=kind, cg_max_iterations=2000, cg_tolerance=1e-12))
    for _ in range(2):  # the second solve reuses analysis / factorisation
        x, report = solver.solve(
            ConstrainedSystem(matrix.copy(), rhs, constrained, values), tolerance=1e-12
        )
        np.testing.assert_allclose(x, expected, rtol=1e-8, atol=1e-8)
        assert report.converged


def test_direct_solver_falls_back_on_an_indefinite_matrix() -> None:
    matrix = _laplacian_3d(5, -1.3)  # shifted so some eigenvalues are negative
    assert np.linalg.eigvalsh(matrix.toarray()).min() < 0
    rhs = np.ones(matrix.shape[0])
    constrained = np.zeros(matrix.shape[0], dtype=bool)
    solver = LinearSolver(LinearSolverConfig(kind="direct"))
    x, report = solver.solve(ConstrainedSystem(matrix.copy(), rhs, constrained, np.zeros_like(rhs)))
    assert report.indefinite
    np.testing.assert_allclose(matrix @ x, rhs, atol=1e-8)


@pytest.mark.skipif(not pardiso_available(), reason="the left-out dofs are Pardiso's pattern")
def test_direct_factorization_leaves_out_eliminated_dofs_until_one_is_freed() -> None:
    """Constrained dofs' rows and columns (identity after elimination) go to Pardiso as their
    diagonal alone: fewer factor nonzeros, the same solution. A later system in which some of
    them are free is factorised on a new analysis without them, not as if still fixed."""
    rng = np.random.default_rng(5)
    matrix = _laplacian_3d(7, 0.05)
    n = matrix.shape[0]
    first = rng.random(n) < 0.15
    values = rng.standard_normal(n)
    solver = LinearSolver(LinearSolverConfig(kind="direct"))
    rhs = rng.standard_normal(n)
    x, _ = solver.solve(ConstrainedSystem(matrix.copy(), rhs, first, values))
    np.testing.assert_allclose(x, _reference(matrix, rhs, first, values), rtol=1e-10, atol=1e-10)
    eliminated = ConstrainedSystem(matrix.copy(), rhs, first, values).matrix
    whole = DirectFactorizer()
    whole.factorize(eliminated)  # no dofs named: every structural entry factorised
    assert solver.factorizer.factor_nonzeros() < 0.9 * whole.factor_nonzeros()

    freed = first & (rng.random(n) < 0.5)
    later = (first & ~freed) | (rng.random(n) < 0.05)
    assert np.count_nonzero(freed & ~later) > 5
    rhs = rng.standard_normal(n)
    x, _ = solver.solve(ConstrainedSystem(matrix.copy(), rhs, later, values))
    np.testing.assert_allclose(x, _reference(matrix, rhs, later, values), rtol=1e-10, atol=1e-10)
    left_out = solver.factorizer._left_out
    assert left_out is not None and np.array_equal(left_out, first & later)


@pytest.mark.skipif(not pardiso_available(), reason="the substitution phases are Pardiso's")
def test_cholesky_halves_give_the_compliance_and_the_solve() -> None:
    """Forward substitution alone, Y = L^-1 P B, gives B^T A^-1 B as Y^T Y (the paper LM's
    compliance), and backward(forward(b)) is A^-1 b; an indefinite factor refuses both."""
    rng = np.random.default_rng(7)
    matrix = _laplacian_3d(6, 0.05)
    n = matrix.shape[0]
    factorization, indefinite = DirectFactorizer().factorize(matrix)
    assert not indefinite and factorization.is_cholesky
    columns = rng.standard_normal((n, 5))
    halves = factorization.forward(np.asfortranarray(columns))
    expected = columns.T @ np.linalg.solve(matrix.toarray(), columns)
    np.testing.assert_allclose(halves.T @ halves, expected, rtol=1e-10, atol=1e-12)
    rhs = rng.standard_normal(n)
    np.testing.assert_allclose(
        factorization.backward(factorization.forward(rhs)),
        np.linalg.solve(matrix.toarray(), rhs),
        rtol=1e-10,
        atol=1e-12,
    )
    indefinite_factor, indefinite = DirectFactorizer().factorize(_laplacian_3d(5, -1.3))
    assert indefinite and not indefinite_factor.is_cholesky
    with pytest.raises(ValueError, match="Cholesky"):
        indefinite_factor.forward(np.ones(125))


def test_cg_cap_is_respected_and_reported() -> None:
    matrix = _laplacian_3d(10, 1e-4)
    rhs = np.ones(matrix.shape[0])
    solver = LinearSolver(LinearSolverConfig(kind="cg", cg_max_iterations=25, cg_tolerance=1e-12))
    _, report = solver.solve(
        ConstrainedSystem(matrix, rhs, np.zeros_like(rhs, dtype=bool), np.zeros_like(rhs))
    )
    assert report.iterations == 25
    assert not report.converged
    assert report.relative_residual > 1e-12


@pytest.mark.parametrize(
    "settings",
    [
        {"kind": "cholesky"},
        {"cg_max_iterations": 0},
        {"cg_tolerance": 2.0},
        {"direct_backend": "mumps"},
    ],
)
def test_bad_solver_settings_are_named(settings: dict) -> None:
    with pytest.raises(ConfigError) as error:
        LinearSolverConfig(**settings)
    assert str(next(iter(settings.values()))) in str(error.value)


def test_cg_on_node_blocks_matches_the_dense_reference() -> None:
    """Elasticity matrices are node-blocked: CG then multiplies with the upper blocks only."""
    mesh = block_mesh((0.02, 0.02, 0.01), (4, 4, 2), fix="z=min")
    rng = np.random.default_rng(3)
    positions = mesh.nodes + 1e-4 * rng.standard_normal(mesh.nodes.shape)
    stiffness = Elasticity(mesh, TissueMaterials()).evaluate(positions).stiffness
    assert stiffness is not None
    matrix = (stiffness + 10.0 * sp.eye(stiffness.shape[0], format="csr")).tocsr()
    matrix.sort_indices()
    assert NodeBlocks.of(matrix) is not None
    assert NodeBlocks.of(_laplacian_3d(6, 0.05)) is None  # scalar pattern: plain CSR products
    n = matrix.shape[0]
    rhs = rng.standard_normal(n)
    constrained = rng.random(n) < 0.1
    values = rng.standard_normal(n)
    expected = _reference(matrix, rhs, constrained, values)
    solver = LinearSolver(LinearSolverConfig(kind="cg", cg_max_iterations=5000, cg_tolerance=1e-12))
    found = []
    for _ in range(2):  # the second solve, on the same pattern arrays, reuses the blocks
        same_pattern = matrix.copy()
        same_pattern.indices, same_pattern.indptr = matrix.indices, matrix.indptr
        x, report = solver.solve(ConstrainedSystem(same_pattern, rhs, constrained, values))
        assert solver._blocks is not None and solver._blocks[2] is not None
        found.append(solver._blocks[2])
        np.testing.assert_allclose(x, expected, rtol=1e-8, atol=1e-8)
        assert report.converged
    assert found[0] is found[1]


def test_kept_factorization_is_corrected_for_dofs_constrained_since() -> None:
    """A reuse solve after more dofs became constrained (prescribed displacement's online
    node set growing) converges as if the factorisation were fresh: the capacitance
    correction makes the kept factor the exact inverse on the remaining free dofs."""
    rng = np.random.default_rng(3)
    matrix = _laplacian_3d(7, 0.05)
    n = matrix.shape[0]
    before = rng.random(n) < 0.05
    later = before | (rng.random(n) < 0.05)
    assert 10 < np.count_nonzero(later & ~before) < 40
    values = rng.standard_normal(n)
    solver = LinearSolver(LinearSolverConfig(kind="reuse"))
    solver.single_precision_preconditioner = False  # an exact kept factor, to test exactly
    solver.solve(ConstrainedSystem(matrix.copy(), rng.standard_normal(n), before, values))
    rhs = rng.standard_normal(n)
    x, report = solver.solve(ConstrainedSystem(matrix.copy(), rhs, later, values), tolerance=1e-10)
    np.testing.assert_allclose(x, _reference(matrix, rhs, later, values), rtol=1e-8, atol=1e-8)
    assert report.converged and not report.factorized and report.iterations <= 2


def test_columns_for_newly_constrained_dofs_share_the_first_solve() -> None:
    """The columns F^-1 e_d of dofs constrained since the kept factor are solved in the same
    multi-RHS call as CG's first preconditioner solve: one call of the factor per CG
    iteration, the first with one column per new dof plus the residual (Pardiso reads the
    factor once per call: on the finest mesh one right-hand side took 45 ms, six 139 ms)."""
    rng = np.random.default_rng(3)
    matrix = _laplacian_3d(7, 0.05)
    n = matrix.shape[0]
    before = rng.random(n) < 0.05
    later = before | (rng.random(n) < 0.05)
    added = int(np.count_nonzero(later & ~before))
    values = rng.standard_normal(n)
    solver = LinearSolver(LinearSolverConfig(kind="reuse"))
    solver.single_precision_preconditioner = False
    solver.solve(ConstrainedSystem(matrix.copy(), rng.standard_normal(n), before, values))
    shapes = _record_kept_solves(solver)
    rhs = rng.standard_normal(n)
    x, report = solver.solve(ConstrainedSystem(matrix.copy(), rhs, later, values), tolerance=1e-10)
    np.testing.assert_allclose(x, _reference(matrix, rhs, later, values), rtol=1e-8, atol=1e-8)
    assert report.converged and not report.factorized
    assert shapes[0] == (n, added + 1)
    assert shapes[1:] == [(n,)] * (report.iterations - 1)
    # The columns are kept: a later solve with the same dofs calls the factor once per
    # iteration, with the right-hand side alone.
    shapes.clear()
    _, report = solver.solve(
        ConstrainedSystem(matrix.copy(), rng.standard_normal(n), later, values), tolerance=1e-10
    )
    assert shapes == [(n,)] * report.iterations


def _rank_one_scene(seed: int):
    """A matrix, its rank-one terms when a factor was kept (keys 3, 8, 11, 20) and now: 8 as
    it was, 11 turned, 20 re-scaled, 31 and 40 new (40 on a constrained dof), 3 gone."""
    rng = np.random.default_rng(seed)
    base = _laplacian_3d(6, 0.05)
    n = base.shape[0]
    dofs = np.array([rng.choice(n, 6, replace=False) for _ in range(6)])
    vectors = rng.standard_normal((6, 6))
    old = RankOneTerms(np.array([3, 8, 11, 20]), dofs[:4], vectors[:4], np.full(4, 50.0))
    now = RankOneTerms(
        np.array([8, 11, 20, 31, 40]),
        dofs[1:],
        np.vstack([vectors[1], rng.standard_normal(6), vectors[3], vectors[4:]]),
        np.array([50.0, 50.0, 80.0, 50.0, 50.0]),
    )
    constrained = rng.random(n) < 0.05
    constrained[now.dofs[4, 0]] = True
    return rng, base, old, now, constrained, rng.standard_normal(n)


def _with_terms(base: sp.csr_matrix, terms: RankOneTerms) -> sp.csr_matrix:
    n = base.shape[0]
    rows = np.repeat(terms.dofs, terms.dofs.shape[1], axis=1)
    cols = np.tile(terms.dofs, (1, terms.dofs.shape[1]))
    values = terms.scales[:, None, None] * np.einsum("ka,kb->kab", terms.vectors, terms.vectors)
    added = sp.csr_matrix((values.reshape(-1), (rows.reshape(-1), cols.reshape(-1))), (n, n))
    matrix = (base + added).tocsr()
    matrix.sort_indices()
    return matrix


@pytest.mark.parametrize("declared", [True, False])
def test_kept_factor_is_corrected_for_rank_one_terms_changed_since(declared: bool) -> None:
    """Terms added, removed, re-scaled and turned since the kept factorisation (penalty
    springs entering and leaving contact): the capacitance correction makes the
    preconditioner the current matrix's inverse, so CG converges in one iteration; undeclared,
    the same changes cost CG an iteration each. The 7 new columns (two new terms, the old
    and new forms of two changed ones, one gone) share the first solve and are kept."""
    rng, base, old, now, constrained, values = _rank_one_scene(11)
    n = base.shape[0]
    # No amortised refresh: on a system this small the 7 columns alone (2.8 iterations'
    # worth) would pay for a new factorisation.
    solver = LinearSolver(LinearSolverConfig(kind="reuse", reuse_refresh_factor=0.0))
    solver.single_precision_preconditioner = False
    first = ConstrainedSystem(
        _with_terms(base, old),
        rng.standard_normal(n),
        constrained,
        values,
        old if declared else None,
    )
    assert solver.solve(first)[1].factorized
    shapes = _record_kept_solves(solver)
    matrix = _with_terms(base, now)
    rhs = rng.standard_normal(n)
    system = ConstrainedSystem(matrix.copy(), rhs, constrained, values, now if declared else None)
    x, report = solver.solve(system, tolerance=1e-10)
    np.testing.assert_allclose(
        x, _reference(matrix, rhs, constrained, values), rtol=1e-8, atol=1e-8
    )
    assert report.converged and not report.factorized
    if not declared:
        assert report.iterations >= 4
        return
    assert report.iterations == 1
    assert shapes == [(n, 8)]
    shapes.clear()
    again = ConstrainedSystem(matrix.copy(), rng.standard_normal(n), constrained, values, now)
    _, report = solver.solve(again, tolerance=1e-10)
    assert report.iterations == 1 and shapes == [(n,)]


def test_too_many_rank_one_changes_refactorise(monkeypatch) -> None:
    """More changed terms than the cap on held columns: the kept factor is refreshed (and
    the solve is exact)."""
    import tissue.sim.solvers as solvers

    monkeypatch.setattr(solvers, "MAX_RANK_ONE_SINCE", 6)
    rng, base, old, now, constrained, values = _rank_one_scene(12)
    n = base.shape[0]
    solver = LinearSolver(LinearSolverConfig(kind="reuse"))
    first = ConstrainedSystem(
        _with_terms(base, old), rng.standard_normal(n), constrained, values, old
    )
    solver.solve(first)
    matrix = _with_terms(base, now)
    rhs = rng.standard_normal(n)
    x, report = solver.solve(
        ConstrainedSystem(matrix.copy(), rhs, constrained, values, now), tolerance=1e-10
    )
    assert report.factorized
    np.testing.assert_allclose(
        x, _reference(matrix, rhs, constrained, values), rtol=1e-8, atol=1e-8
    )


def test_kept_factorization_correction_outgrows_its_column_cap(monkeypatch) -> None:
    """Dofs constrained, released and others constrained under one kept factor: the columns
    held outnumber the cap on the active set (the column array grows), and each solve stays
    exact without a refactorisation."""
    import tissue.sim.solvers as solvers

    monkeypatch.setattr(solvers, "MAX_CONSTRAINED_SINCE", 30)
    rng = np.random.default_rng(5)
    matrix = _laplacian_3d(7, 0.05)
    n = matrix.shape[0]
    before = np.zeros(n, dtype=bool)
    before[:20] = True
    first, second = before.copy(), before.copy()
    first[40:65] = True  # 25 dofs each, 50 columns in all against a cap of 30
    second[100:125] = True
    values = rng.standard_normal(n)
    solver = LinearSolver(LinearSolverConfig(kind="reuse"))
    solver.single_precision_preconditioner = False
    solver.solve(ConstrainedSystem(matrix.copy(), rng.standard_normal(n), before, values))
    for constrained in (first, second, first):
        rhs = rng.standard_normal(n)
        x, report = solver.solve(
            ConstrainedSystem(matrix.copy(), rhs, constrained, values), tolerance=1e-10
        )
        np.testing.assert_allclose(
            x, _reference(matrix, rhs, constrained, values), rtol=1e-8, atol=1e-8
        )
        assert report.converged and not report.factorized and report.iterations <= 2
    assert solver._since is not None and solver._since.count == 50


def test_reuse_refactorises_once_extra_cg_iterations_cost_a_factorisation() -> None:
    """On a drifting matrix (a Newton run's tangents), ``reuse`` refactorises once the CG
    iterations beyond one per solve add up to ``reuse_refresh_factor`` sqrt(n), before CG
    stalls at its cap: fewer iterations in all than refreshing only on a stall, the same
    solutions, and the same schedule on every run (counted in iterations, not wall time)."""
    rng = np.random.default_rng(5)
    matrix = _laplacian_3d(7, 0.05)
    n = matrix.shape[0]
    constrained = np.zeros(n, dtype=bool)
    values = np.zeros(n)
    # Each solve's matrix is scaled and shifted a little from the last one.
    drifted = [(matrix * (1.0 + 0.03 * k) + 0.01 * k * sp.eye(n)).tocsr() for k in range(30)]
    right_hand_sides = [rng.standard_normal(n) for _ in drifted]

    def run(factor: float) -> tuple[list[int], list[bool], list[np.ndarray]]:
        solver = LinearSolver(LinearSolverConfig(kind="reuse", reuse_refresh_factor=factor))
        solver.single_precision_preconditioner = False
        iterations, factorized, solutions = [], [], []
        for a, rhs in zip(drifted, right_hand_sides, strict=True):
            x, report = solver.solve(ConstrainedSystem(a, rhs, constrained, values), tolerance=1e-8)
            assert report.converged
            np.testing.assert_allclose(x, _reference(a, rhs, constrained, values), atol=1e-7)
            iterations.append(report.iterations)
            factorized.append(report.factorized)
            solutions.append(x)
        return iterations, factorized, solutions

    on_stall, _, _ = run(0.0)
    amortised, refreshed, solutions = run(0.15)
    cap = LinearSolverConfig().reuse_max_iterations
    # Only stalls refactorise without the rule (each after a capped CG run); with it, the
    # refreshes come earlier, after solves well under the cap.
    assert sum(refreshed[1:]) >= 2
    assert all(count <= cap for count in amortised)
    assert sum(amortised) < sum(on_stall), (amortised, on_stall)
    again, refreshed_again, solutions_again = run(0.15)
    assert again == amortised and refreshed_again == refreshed
    for first, second in zip(solutions, solutions_again, strict=True):
        np.testing.assert_array_equal(first, second)


def test_symmetric_product_matches_the_csr_product() -> None:
    """The upper-node-block product equals A x (node-blocked stiffness), and a pattern that
    is not node-blocked falls back to CSR."""
    mesh = block_mesh((0.02, 0.02, 0.01), (3, 3, 2), fix="z=min")
    stiffness = Elasticity(mesh, TissueMaterials()).evaluate(mesh.nodes).stiffness
    x = np.random.default_rng(2).standard_normal(stiffness.shape[0])
    product = SymmetricProduct(stiffness)
    assert product.blocks is not None
    out = np.empty_like(x)
    assert product(x, out) == pytest.approx(x @ (stiffness @ x), rel=1e-12)
    np.testing.assert_allclose(out, stiffness @ x, rtol=1e-12, atol=1e-12 * np.abs(out).max())
    solver = LinearSolver(LinearSolverConfig(kind="cg"))
    by_solver = np.empty_like(x)
    solver.product(stiffness, x, by_solver)  # through the solver's own blocks
    np.testing.assert_array_equal(by_solver, out)
    laplacian = _laplacian_3d(4, 0.1)
    plain = SymmetricProduct(laplacian)
    assert plain.blocks is None
    y = np.ones(laplacian.shape[0])
    out = np.empty_like(y)
    plain(y, out)
    np.testing.assert_array_equal(out, laplacian @ y)


@pytest.mark.skipif(not pardiso_available(), reason="the analysis is Pardiso's")
def test_pattern_analysed_ahead_serves_the_first_kept_factorisation() -> None:
    """``analyse`` runs the symbolic phase when a model is built; the first ``reuse`` solve
    then only factorises (no phase 11) and solves correctly."""
    import tissue.sim.pardiso as pardiso

    rng = np.random.default_rng(8)
    matrix = _laplacian_3d(6, 0.05)
    n = matrix.shape[0]
    fixed = np.zeros(n, dtype=bool)
    fixed[:20] = True
    solver = LinearSolver(LinearSolverConfig(kind="reuse"))
    phases: list[int] = []
    call = pardiso._pardiso_call

    def counted(*args):
        phases.append(args[4])
        return call(*args)

    pardiso._pardiso_call = counted
    try:
        solver.analyse(matrix, fixed)
        assert phases == [11]
        rhs = rng.standard_normal(n)
        values = rng.standard_normal(n)
        x, report = solver.solve(
            ConstrainedSystem(matrix.copy(), rhs, fixed, values), tolerance=1e-10
        )
    finally:
        pardiso._pardiso_call = call
    assert 11 not in phases[1:] and 22 in phases
    np.testing.assert_allclose(x, _reference(matrix, rhs, fixed, values), rtol=1e-8, atol=1e-8)


def test_reuse_products_follow_a_matrix_modified_in_place() -> None:
    """Systems sharing a matrix share its filled node blocks (one fill for the three solves
    of a robust LM step); a matrix changed in place and declared with ``matrix_modified``
    is filled again, so the next solve is of the new matrix."""
    rng = np.random.default_rng(9)
    mesh = block_mesh((0.02, 0.02, 0.01), (4, 4, 2), fix="z=min")
    stiffness = Elasticity(mesh, TissueMaterials()).evaluate(mesh.nodes).stiffness
    matrix = stiffness.copy()  # the node-blocked pattern kept (a sparse sum prunes zeros)
    n = matrix.shape[0]
    row_of_entry = np.repeat(np.arange(n), np.diff(matrix.indptr))
    matrix.data[matrix.indices == row_of_entry] += 50.0
    constrained = np.zeros(n, dtype=bool)
    constrained[:12] = True
    values = rng.standard_normal(n)
    solver = LinearSolver(LinearSolverConfig(kind="reuse"))
    system = ConstrainedSystem(matrix.copy(), rng.standard_normal(n), constrained, values)
    fills = 0
    fill = NodeBlocks.fill

    def counted(self, data):
        nonlocal fills
        fills += 1
        return fill(self, data)

    NodeBlocks.fill = counted  # type: ignore[method-assign]
    try:
        solver.solve(system, tolerance=1e-10)  # keeps a factor of this matrix
        shifted = matrix.copy()
        shifted.data[shifted.indices == row_of_entry] += 5.0
        for rhs in rng.standard_normal((2, n)):
            x, _ = solver.solve(system.with_rhs(rhs), initial_guess=rhs, tolerance=1e-10)
            np.testing.assert_allclose(
                x, _reference(matrix, rhs, constrained, np.zeros(n)), rtol=1e-7, atol=1e-9
            )
        assert fills == 1
        # Change the eliminated matrix in place (the diagonal of the free dofs), and say so.
        system.matrix.data[
            (system.matrix.indices == row_of_entry) & ~constrained[row_of_entry]
        ] += 5.0
        system.matrix_modified()
        rhs = rng.standard_normal(n)
        x, _ = solver.solve(system.with_rhs(rhs), initial_guess=rhs, tolerance=1e-10)
        np.testing.assert_allclose(
            x, _reference(shifted, rhs, constrained, np.zeros(n)), rtol=1e-7, atol=1e-9
        )
        assert fills == 2
    finally:
        NodeBlocks.fill = fill  # type: ignore[method-assign]


def test_parallel_kernels_serial_builds_give_the_parallel_builds_bits_on_one_thread() -> None:
    """Inside a one-thread ``one_thread_below`` the kernels run their serial builds (no
    OpenMP region a call): the same bits as the parallel builds on one thread, for the
    element kernels and for CG, whose serial loop calls the serial products."""
    mesh = block_mesh((0.02, 0.02, 0.01), (4, 4, 2), fix="z=min")
    rng = np.random.default_rng(5)
    positions = mesh.nodes + 1e-3 * rng.standard_normal(mesh.nodes.shape)
    elasticity = Elasticity(mesh, TissueMaterials())
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        assert not running_on_one_thread()
        parallel = elasticity.evaluate(positions, project_psd=True)
    finally:
        numba.set_num_threads(threads)
    with one_thread_below(10, 11):
        assert running_on_one_thread() and numba.get_num_threads() == 1
        with one_thread_below(10, 5):  # nested above its threshold: still one thread
            assert running_on_one_thread() and numba.get_num_threads() == 1
        assert running_on_one_thread()
        serial = elasticity.evaluate(positions, project_psd=True)
    assert not running_on_one_thread() and numba.get_num_threads() == threads
    # Which build ran: each compiles (or loads) a specialisation when first called.
    values = np.arange(5.0)
    with one_thread_below(10, 11):
        assert _doubled_sum(values) == 20.0
    assert len(_doubled_sum.serial.signatures) == 1 and not _doubled_sum.parallel.signatures
    assert _doubled_sum(values) == 20.0
    assert len(_doubled_sum.parallel.signatures) == 1
    # Per Python thread, as numba's thread count is: another thread keeps its own.
    seen_elsewhere = []
    with one_thread_below(10, 11):
        other = threading.Thread(target=lambda: seen_elsewhere.append(running_on_one_thread()))
        other.start()
        other.join()
    assert seen_elsewhere == [False]
    assert parallel.stiffness is not None and serial.stiffness is not None
    assert serial.energy_j == parallel.energy_j
    np.testing.assert_array_equal(serial.forces, parallel.forces)
    np.testing.assert_array_equal(serial.stiffness.data, parallel.stiffness.data)

    matrix = (parallel.stiffness + 10.0 * sp.eye(parallel.stiffness.shape[0])).tocsr()
    matrix.sort_indices()
    rhs = rng.standard_normal(matrix.shape[0])
    inverse_diagonal = 1.0 / matrix.diagonal()
    results = []
    for build in (jacobi_pcg.parallel, jacobi_pcg.serial):
        x = np.zeros_like(rhs)
        numba.set_num_threads(1)
        try:
            iterations, residual = build(
                matrix.indptr, matrix.indices, matrix.data, *NO_BLOCKS, rhs, x,
                inverse_diagonal, 25, 0.0,
            )  # fmt: skip
        finally:
            numba.set_num_threads(threads)
        results.append((iterations, residual, x))
    assert results[0][0] == results[1][0] == 25
    assert results[0][1] == results[1][1]
    np.testing.assert_array_equal(results[0][2], results[1][2])
    # Cached in files of their own (numba's cache index does not key on ``parallel``).
    assert jacobi_pcg.serial.py_func.__qualname__ == "jacobi_pcg__serial"
