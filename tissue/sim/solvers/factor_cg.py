"""CG preconditioned by a factorisation: the iteration of ``reuse`` solves.

A factorisation F of a recent matrix (kept across steps, possibly in single precision, and
corrected in low rank: :mod:`~tissue.sim.solvers.constrained_correction`,
:mod:`~tissue.sim.solvers.rank_one_correction`) preconditions CG on the exact current matrix.
While the matrix has changed little since F, CG converges in a few iterations, each one
triangular solve with F and one product with A: far cheaper than a factorisation
(Courtecuisse et al. 2014 precondition with a one-step-old factorisation in the same
spirit). The loop runs in Python (a preconditioner solve is a library call), its vector
updates in the compiled kernels here.

Arrays are float64 of the system's size n unless said otherwise; ``constrained`` is the (n,)
bool mask of known dofs, where residuals and preconditioned residuals are held at 0.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numba
import numpy as np
from numpy.typing import NDArray

from tissue.sim.solvers.constrained_system import ConstrainedSystem
from tissue.sim.solvers.direct_factorization import Factorization
from tissue.sim.solvers.node_blocks import NO_BLOCKS, NodeBlocks, node_block_product
from tissue.sim.solvers.vector_kernels import free_square_norm


@numba.njit(cache=True)
def _free_difference(b, ax, constrained, r):  # pragma: no cover - compiled
    """r = b - ax at free dofs, 0 at constrained ones; returns ||r||^2."""
    total = 0.0
    for i in range(b.shape[0]):
        if constrained[i]:
            r[i] = 0.0
        else:
            value = b[i] - ax[i]
            r[i] = value
            total += value * value
    return total


@numba.njit(cache=True)
def _free_entries_zero(x, constrained):  # pragma: no cover - compiled
    """Whether x is 0 at every dof not constrained."""
    for i in range(x.shape[0]):  # noqa: SIM110 - numba compiles this loop, not all()
        if not constrained[i] and x[i] != 0.0:
            return False
    return True


@numba.njit(cache=True)
def _preconditioned_dots(z, r, r_old, constrained):  # pragma: no cover - compiled
    """Zero z at constrained dofs; return (z . r, z . r_old)."""
    zr = 0.0
    zr_old = 0.0
    for i in range(z.shape[0]):
        if constrained[i]:
            z[i] = 0.0
        else:
            zr += z[i] * r[i]
            zr_old += z[i] * r_old[i]
    return zr, zr_old


@numba.njit(cache=True)
def _update_direction(p, z, beta):  # pragma: no cover - compiled
    for i in range(p.shape[0]):
        p[i] = z[i] + beta * p[i]


@numba.njit(cache=True)
def _cg_update(x, r, r_old, p, ap, alpha, constrained):  # pragma: no cover - compiled
    """x += alpha p; r_old = r; r -= alpha A p (0 at constrained dofs); returns ||r||^2."""
    total = 0.0
    for i in range(x.shape[0]):
        x[i] += alpha * p[i]
        r_old[i] = r[i]
        if constrained[i]:
            r[i] = 0.0
        else:
            value = r[i] - alpha * ap[i]
            r[i] = value
            total += value * value
    return total


def factor_pcg(
    system: ConstrainedSystem,
    preconditioner: Factorization,
    x: NDArray[np.float64],
    max_iterations: int,
    tolerance: float,
    filled_blocks: Callable[[], NodeBlocks | None] = lambda: None,
) -> tuple[int, float]:
    """CG preconditioned by an (older) factorisation; constrained dofs stay fixed.

    Args:
        system: the (eliminated) system to solve.
        preconditioner: solves with an approximation of the system's matrix.
        x: the initial guess (n,), known dofs at their values; overwritten with the result.
        max_iterations: the iteration cap.
        tolerance: the relative residual ||b - A x|| / ||b|| over the free dofs to reach.
        filled_blocks: see below.

    Returns:
        (iterations, relative residual reached).

    The preconditioner may be a single-precision factorisation, whose solves are not exactly
    a symmetric operator: the flexible (Polak-Ribiere) beta keeps CG converging regardless.
    The residual is checked before each preconditioner solve, so a converged CG never pays
    for one more. ``filled_blocks`` gives the matrix's node blocks holding its values (None
    if it has none), asked for at the first product only: block products cost a third of
    CSR ones, and a solve that needs no product needs no filling.
    """
    matrix, constrained = system.matrix, system.constrained
    indptr, indices, data = matrix.indptr, matrix.indices, matrix.data
    b_square = free_square_norm(system.rhs, constrained)
    b_norm = math.sqrt(b_square) or 1.0
    upper_ptr, upper_cols, upper, bounds, partial = NO_BLOCKS
    ap = np.empty_like(x)
    if _free_entries_zero(x, constrained):
        # x = 0 at the unknowns and the known columns eliminated: r = b there, without a
        # product with the whole matrix.
        r = np.where(constrained, 0.0, system.rhs)
        r_square = b_square
    else:
        blocks = filled_blocks()
        if blocks is not None:
            upper_ptr, upper_cols, upper, bounds, partial = blocks.arguments()
        node_block_product(
            indptr, indices, data, upper_ptr, upper_cols, upper, bounds, partial, x, ap
        )
        r = np.empty_like(x)
        r_square = _free_difference(system.rhs, ap, constrained, r)
    residual = math.sqrt(r_square) / b_norm
    r_old = np.zeros_like(x)
    p = np.zeros_like(x)
    rz = 0.0
    iterations = 0
    while iterations < max_iterations and residual > tolerance:
        z = np.asarray(preconditioner.solve(r), dtype=np.float64).reshape(-1)
        rz_new, rz_cross = _preconditioned_dots(z, r, r_old, constrained)
        if rz_new <= 0.0 or not math.isfinite(rz_new):
            break
        _update_direction(p, z, 0.0 if iterations == 0 else (rz_new - rz_cross) / rz)
        rz = rz_new
        if iterations == 0 and upper_ptr is NO_BLOCKS[0]:
            blocks = filled_blocks()
            if blocks is not None:
                upper_ptr, upper_cols, upper, bounds, partial = blocks.arguments()
        pap = node_block_product(
            indptr, indices, data, upper_ptr, upper_cols, upper, bounds, partial, p, ap
        )
        if pap <= 0.0 or not math.isfinite(pap):
            break
        r_square = _cg_update(x, r, r_old, p, ap, rz / pap, constrained)
        iterations += 1
        residual = math.sqrt(r_square) / b_norm
    return iterations, residual
