"""Sparse linear solvers for the implicit step: capped Jacobi-CG, direct factorisation, reuse.

Every system here is symmetric, of size 3·node_count, with some degrees of freedom
*constrained* (fixed base, prescribed surface nodes). Constrained rows and columns are
eliminated in place: the right-hand side is corrected with their known values and the
matrix gets identity rows and columns there, so the sparsity pattern never changes and a
symbolic factorisation is computed once per mesh.

Solvers:

* ``cg``: conjugate gradient with a Jacobi preconditioner and an iteration cap (25 by
  default, as SOFA's ``CGLinearSolver`` in the paper). Fast, but on fine meshes 25
  iterations are far from converged; the report says how far (``relative_residual``).
* ``direct``: a sparse Cholesky-type factorisation. Intel MKL Pardiso through ``pypardiso``
  (installs from wheels with pip alone, multithreaded; SPD mode), with a symmetric-
  indefinite factorisation as fallback when the matrix is not positive definite, and
  scipy's SuperLU where MKL is unavailable.
* ``reuse``: CG preconditioned by the last factorisation, refactorising only when CG
  stalls. Consecutive implicit steps change the matrix little, so most steps cost a few
  triangular solves instead of a factorisation (Courtecuisse et al. 2014 use a one-step-old
  factorisation as preconditioner in the same spirit).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Protocol

import numba
import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from tissue.choices import Choice
from tissue.errors import ConfigError


class LinearSolverKind(Choice):
    """The linear solver used for each implicit step."""

    CG = "cg"
    DIRECT = "direct"
    REUSE = "reuse"

    @classmethod
    def noun(cls) -> str:
        return "linear solver"


class DirectBackend(Choice):
    """The library behind direct factorisations."""

    AUTO = "auto"
    PARDISO = "pardiso"
    SUPERLU = "superlu"

    @classmethod
    def noun(cls) -> str:
        return "direct solver backend"


@dataclass(frozen=True)
class SolveReport:
    """What one linear solve did.

    Attributes:
        iterations: CG iterations (0 for a pure direct solve).
        relative_residual: ||b - A x|| / ||b|| over free dofs, as measured after the solve.
        converged: whether the requested tolerance was reached.
        factorized: whether a numerical factorisation was computed in this solve.
        indefinite: whether the SPD factorisation failed and a symmetric-indefinite one was used.
        seconds: wall time of the solve [s].
    """

    iterations: int
    relative_residual: float
    converged: bool
    factorized: bool = False
    indefinite: bool = False
    seconds: float = 0.0


class Factorization(Protocol):
    """A factorised matrix that solves for one or several right-hand sides."""

    def solve(self, rhs: NDArray[np.float64]) -> NDArray[np.float64]: ...


# ----------------------------------------------------------------------------- kernels


@numba.njit(parallel=True, cache=True)
def _spmv(indptr, indices, data, x, out):  # pragma: no cover - compiled
    for row in numba.prange(indptr.shape[0] - 1):
        acc = 0.0
        for k in range(indptr[row], indptr[row + 1]):
            acc += data[k] * x[indices[k]]
        out[row] = acc


@numba.njit(cache=True)
def _dot(a, b):  # pragma: no cover - compiled
    acc = 0.0
    for i in range(a.shape[0]):
        acc += a[i] * b[i]
    return acc


@numba.njit(cache=True)
def _jacobi_pcg(
    indptr, indices, data, b, x, inv_diag, max_iterations, tolerance
):  # pragma: no cover
    """Jacobi-preconditioned CG on a system whose constrained rows are identity rows.

    Returns (iterations, relative residual). x holds the initial guess and the result.
    """
    n = b.shape[0]
    r = np.empty(n)
    _spmv(indptr, indices, data, x, r)
    for i in range(n):
        r[i] = b[i] - r[i]
    b_norm = np.sqrt(_dot(b, b))
    if b_norm == 0.0:
        b_norm = 1.0
    z = r * inv_diag
    p = z.copy()
    rz = _dot(r, z)
    ap = np.empty(n)
    residual = np.sqrt(_dot(r, r)) / b_norm
    iterations = 0
    while iterations < max_iterations and residual > tolerance:
        _spmv(indptr, indices, data, p, ap)
        pap = _dot(p, ap)
        if pap <= 0.0 or not np.isfinite(pap):
            break  # indefinite direction or breakdown: stop with what we have
        alpha = rz / pap
        for i in range(n):
            x[i] += alpha * p[i]
            r[i] -= alpha * ap[i]
        for i in range(n):
            z[i] = r[i] * inv_diag[i]
        rz_new = _dot(r, z)
        beta = rz_new / rz
        rz = rz_new
        for i in range(n):
            p[i] = z[i] + beta * p[i]
        iterations += 1
        residual = np.sqrt(_dot(r, r)) / b_norm
    return iterations, residual


@numba.njit(parallel=True, cache=True)
def _eliminate(indptr, indices, data, constrained):  # pragma: no cover - compiled
    """Identity rows and columns at constrained dofs, in place."""
    for row in numba.prange(indptr.shape[0] - 1):
        row_constrained = constrained[row]
        for k in range(indptr[row], indptr[row + 1]):
            col = indices[k]
            if row_constrained or constrained[col]:
                data[k] = 1.0 if col == row else 0.0


# ----------------------------------------------------------------------------- systems


class ConstrainedSystem:
    """A symmetric system A x = b with some dofs of x known, eliminated in place.

    Args:
        matrix: the full symmetric matrix, CSR with sorted indices, shape (n, n). Its data is
            modified in place (identity rows and columns at constrained dofs).
        rhs: the full right-hand side, shape (n,).
        constrained: mask of known dofs, shape (n,), bool.
        values: the known values at constrained dofs (other entries ignored), shape (n,).
    """

    def __init__(
        self,
        matrix: sp.csr_matrix,
        rhs: NDArray[np.float64],
        constrained: NDArray[np.bool_],
        values: NDArray[np.float64],
    ) -> None:
        values = np.where(constrained, values, 0.0)
        # Move the known columns to the right-hand side before eliminating them.
        known = np.empty_like(rhs)
        _spmv(matrix.indptr, matrix.indices, matrix.data, values, known)
        self.original_rhs = rhs
        self.rhs = np.where(constrained, values, rhs - known)
        self.constrained = constrained
        self.values = values
        self._full_times_values = known
        _eliminate(matrix.indptr, matrix.indices, matrix.data, constrained)
        self.matrix = matrix

    def residual_norm(self, x: NDArray[np.float64]) -> float:
        """||b - A x|| / ||b|| of the eliminated system."""
        ax = np.empty_like(x)
        _spmv(self.matrix.indptr, self.matrix.indices, self.matrix.data, x, ax)
        denominator = float(np.linalg.norm(self.rhs)) or 1.0
        return float(np.linalg.norm(self.rhs - ax)) / denominator


class _PardisoFactorization:
    """An MKL Pardiso factorisation of a symmetric matrix, symbolic analysis kept per pattern."""

    def __init__(self, upper: sp.csr_matrix, solver: object) -> None:
        self._upper = upper
        self._solver = solver

    def solve(self, rhs: NDArray[np.float64]) -> NDArray[np.float64]:
        solver = self._solver
        solver.set_phase(33)  # type: ignore[attr-defined]
        b = np.asfortranarray(rhs, dtype=np.float64)
        return solver._call_pardiso(self._upper, b)  # type: ignore[attr-defined]


class _SuperLUFactorization:
    def __init__(self, matrix: sp.csr_matrix) -> None:
        import scipy.sparse.linalg as spla

        self._lu = spla.splu(matrix.tocsc(), permc_spec="MMD_AT_PLUS_A")

    def solve(self, rhs: NDArray[np.float64]) -> NDArray[np.float64]:
        return self._lu.solve(rhs)


class DirectFactorizer:
    """Factorises symmetric matrices of one fixed sparsity pattern, reusing the analysis.

    With Pardiso, the upper-triangle positions are found once and the symbolic analysis
    (reordering) is computed once; each factorisation then runs only the numerical phase.
    A matrix that is not positive definite (a zero or negative pivot in the SPD mode) is
    refactorised in symmetric-indefinite mode (Bunch-Kaufman pivoting) instead of failing.
    """

    def __init__(self, backend: DirectBackend | str = DirectBackend.AUTO) -> None:
        self.backend = DirectBackend.parse(backend)
        if self.backend is DirectBackend.AUTO:
            self.backend = DirectBackend.PARDISO if _pardiso_available() else DirectBackend.SUPERLU
        self._pattern: tuple[NDArray[np.int32], NDArray[np.int32]] | None = None
        self._upper_positions: NDArray[np.int64] | None = None
        self._upper_template: sp.csr_matrix | None = None
        self._solvers: dict[int, object] = {}

    def factorize(self, matrix: sp.csr_matrix) -> tuple[Factorization, bool]:
        """Factorise ``matrix`` (CSR, symmetric). Returns (factorisation, used_indefinite)."""
        if self.backend is DirectBackend.SUPERLU:
            return _SuperLUFactorization(matrix), False
        upper = self._upper_of(matrix)
        for mtype in (2, -2):  # SPD first, then symmetric indefinite
            solver = self._solver_for(mtype, upper)
            solver.set_phase(22)  # type: ignore[attr-defined]
            try:
                solver._call_pardiso(upper, np.zeros((upper.shape[0], 1), order="F"))  # type: ignore[attr-defined]
            except Exception:  # noqa: BLE001 - Pardiso reports non-SPD as an error code
                continue
            return _PardisoFactorization(upper, solver), mtype == -2
        # Both failed (a truly singular matrix): fall back to SuperLU, which may still cope.
        return _SuperLUFactorization(matrix), True

    def _upper_of(self, matrix: sp.csr_matrix) -> sp.csr_matrix:
        if not self._same_pattern(matrix) or self._upper_template is None:
            rows = np.repeat(np.arange(matrix.shape[0]), np.diff(matrix.indptr))
            self._upper_positions = np.flatnonzero(matrix.indices >= rows)
            template = sp.csr_matrix(
                (
                    matrix.data[self._upper_positions].copy(),
                    matrix.indices[self._upper_positions].copy(),
                    np.concatenate(
                        [
                            [0],
                            np.cumsum(
                                np.bincount(rows[self._upper_positions], minlength=matrix.shape[0])
                            ),
                        ]
                    ),
                ),
                shape=matrix.shape,
            )
            self._upper_template = template
            self._pattern = (matrix.indptr.copy(), matrix.indices.copy())
            self._solvers = {}
        assert self._upper_positions is not None
        upper = self._upper_template
        upper.data[:] = matrix.data[self._upper_positions]
        return upper

    def _same_pattern(self, matrix: sp.csr_matrix) -> bool:
        # Comparing the pattern costs O(nnz), far less than a new symbolic analysis.
        if self._pattern is None:
            return False
        indptr, indices = self._pattern
        return (
            indices.shape == matrix.indices.shape
            and np.array_equal(indptr, matrix.indptr)
            and np.array_equal(indices, matrix.indices)
        )

    def _solver_for(self, mtype: int, upper: sp.csr_matrix) -> object:
        solver = self._solvers.get(mtype)
        if solver is None:
            import pypardiso

            solver = pypardiso.PyPardisoSolver(mtype=mtype)
            solver.set_phase(11)  # symbolic analysis, once per pattern
            solver._call_pardiso(upper, np.zeros((upper.shape[0], 1), order="F"))  # type: ignore[attr-defined]
            self._solvers[mtype] = solver
        return solver


def _pardiso_available() -> bool:
    try:
        import pypardiso

        pypardiso.PyPardisoSolver()
    except Exception:  # noqa: BLE001 - no MKL runtime on this platform
        return False
    return True


@dataclass(frozen=True)
class LinearSolverConfig:
    """Settings of the linear solver.

    Attributes:
        kind: ``cg``, ``direct`` or ``reuse``.
        cg_max_iterations: iteration cap of ``cg`` (25 as in the paper).
        cg_tolerance: relative residual at which ``cg`` stops early.
        direct_backend: ``auto`` (Pardiso where available, else SuperLU), ``pardiso``, ``superlu``.
        reuse_max_iterations: preconditioned-CG iterations after which ``reuse`` refactorises.
    """

    kind: LinearSolverKind | str = LinearSolverKind.CG
    cg_max_iterations: int = 25
    cg_tolerance: float = 1e-5
    direct_backend: DirectBackend | str = DirectBackend.AUTO
    reuse_max_iterations: int = 12

    def __post_init__(self) -> None:
        object.__setattr__(self, "kind", LinearSolverKind.parse(self.kind))
        object.__setattr__(self, "direct_backend", DirectBackend.parse(self.direct_backend))
        if self.cg_max_iterations < 1:
            raise ConfigError(f"cg_max_iterations must be >= 1; got {self.cg_max_iterations}")
        if not 0 < self.cg_tolerance < 1:
            raise ConfigError(f"cg_tolerance must lie in (0, 1); got {self.cg_tolerance}")
        if self.reuse_max_iterations < 1:
            raise ConfigError(f"reuse_max_iterations must be >= 1; got {self.reuse_max_iterations}")


class LinearSolver:
    """Solves constrained systems with the configured method, keeping state across steps."""

    def __init__(self, config: LinearSolverConfig | None = None) -> None:
        self.config = config or LinearSolverConfig()
        self._factorizer: DirectFactorizer | None = None
        self._reuse: Factorization | None = None
        self.last_factorization: Factorization | None = None

    @property
    def factorizer(self) -> DirectFactorizer:
        if self._factorizer is None:
            self._factorizer = DirectFactorizer(self.config.direct_backend)
        return self._factorizer

    def forget(self) -> None:
        """Drop any factorisation kept across steps (after a reset or a large change)."""
        self._reuse = None
        self.last_factorization = None

    def solve(
        self,
        system: ConstrainedSystem,
        initial_guess: NDArray[np.float64] | None = None,
        tolerance: float | None = None,
        kind: LinearSolverKind | None = None,
    ) -> tuple[NDArray[np.float64], SolveReport]:
        """Solve ``system``. Returns the full solution (constrained dofs at their values)."""
        kind = LinearSolverKind.parse(kind or self.config.kind)
        start = time.perf_counter()
        if kind is LinearSolverKind.CG:
            x, report = self._solve_cg(system, initial_guess, tolerance)
        elif kind is LinearSolverKind.DIRECT:
            x, report = self._solve_direct(system)
        else:
            x, report = self._solve_reuse(system, initial_guess, tolerance)
        return x, _with_seconds(report, time.perf_counter() - start)

    def factorize(self, system: ConstrainedSystem) -> tuple[Factorization, bool]:
        """Factorise the eliminated matrix of ``system`` (for compliance computations)."""
        factorization, indefinite = self.factorizer.factorize(system.matrix)
        self.last_factorization = factorization
        self._reuse = factorization
        return factorization, indefinite

    def _solve_cg(self, system, initial_guess, tolerance):
        x = _start(system, initial_guess)
        matrix = system.matrix
        inv_diag = 1.0 / _safe_diagonal(matrix)
        iterations, residual = _jacobi_pcg(
            matrix.indptr,
            matrix.indices,
            matrix.data,
            system.rhs,
            x,
            inv_diag,
            self.config.cg_max_iterations,
            tolerance or self.config.cg_tolerance,
        )
        converged = residual <= (tolerance or self.config.cg_tolerance)
        return x, SolveReport(int(iterations), float(residual), bool(converged))

    def _solve_direct(self, system):
        factorization, indefinite = self.factorize(system)
        x = factorization.solve(system.rhs)
        x = np.where(system.constrained, system.values, x)
        residual = system.residual_norm(x)
        return x, SolveReport(0, residual, bool(np.isfinite(residual)), True, indefinite)

    def _solve_reuse(self, system, initial_guess, tolerance):
        tolerance = tolerance or 1e-8
        if self._reuse is not None:
            x = _start(system, initial_guess)
            iterations, residual = _factor_pcg(
                system, self._reuse, x, self.config.reuse_max_iterations, tolerance
            )
            if residual <= tolerance:
                return x, SolveReport(iterations, residual, True)
        x, report = self._solve_direct(system)
        return x, report


def _factor_pcg(
    system: ConstrainedSystem,
    preconditioner: Factorization,
    x: NDArray[np.float64],
    max_iterations: int,
    tolerance: float,
) -> tuple[int, float]:
    """CG preconditioned by an (older) factorisation; constrained dofs stay fixed."""
    matrix, free = system.matrix, ~system.constrained
    b_norm = float(np.linalg.norm(system.rhs[free])) or 1.0
    r = system.rhs - matrix @ x
    r[system.constrained] = 0.0
    z = preconditioner.solve(r)
    z[system.constrained] = 0.0
    p = z.copy()
    rz = float(r @ z)
    residual = float(np.linalg.norm(r)) / b_norm
    iterations = 0
    while iterations < max_iterations and residual > tolerance:
        ap = matrix @ p
        pap = float(p @ ap)
        if pap <= 0.0 or not np.isfinite(pap) or rz <= 0.0:
            break
        alpha = rz / pap
        x += alpha * p
        r -= alpha * ap
        r[system.constrained] = 0.0
        z = preconditioner.solve(r)
        z[system.constrained] = 0.0
        rz_new = float(r @ z)
        p = z + (rz_new / rz) * p
        rz = rz_new
        iterations += 1
        residual = float(np.linalg.norm(r)) / b_norm
    return iterations, residual


def _start(
    system: ConstrainedSystem, initial_guess: NDArray[np.float64] | None
) -> NDArray[np.float64]:
    if initial_guess is None:
        x = np.zeros_like(system.rhs)
    else:
        x = np.array(initial_guess, dtype=np.float64)
    x[system.constrained] = system.values[system.constrained]
    return x


def _safe_diagonal(matrix: sp.csr_matrix) -> NDArray[np.float64]:
    diag = matrix.diagonal()
    return np.where(diag > 0.0, diag, 1.0)


def _with_seconds(report: SolveReport, seconds: float) -> SolveReport:
    return SolveReport(
        report.iterations,
        report.relative_residual,
        report.converged,
        report.factorized,
        report.indefinite,
        seconds,
    )
