"""``cg``: conjugate gradient with a Jacobi (diagonal) preconditioner and an iteration cap.

The paper's solver (SOFA's ``CGLinearSolver``, 25 iterations). The whole loop is compiled
(:func:`jacobi_pcg`), on a system whose constrained rows and columns are identity's (see
:class:`~tissue.sim.solvers.constrained_system.ConstrainedSystem`), so no mask is needed:
identity rows keep the known values where the initial guess put them. Limitation: on fine
meshes 25 iterations are far from converged; the caller reports how far (the relative
residual).

Arrays are float64 of the system's size n unless said otherwise; ``inv_diag`` (n,) holds the
preconditioner, 1 / A_ii (1 where A_ii is not positive).
"""

from __future__ import annotations

import numba
import numpy as np

from tissue.sim.solvers.node_blocks import node_block_product
from tissue.threads import parallel_kernel


@parallel_kernel
def block_inverse_diagonal(upper_ptr, upper_cols, upper, out):  # pragma: no cover - compiled
    """1 / A_ii where positive, else 1, from the diagonal blocks of node blocks; returns
    False if some node row has no diagonal block (then use :func:`inverse_diagonal`)."""
    missing = 0
    for b in numba.prange(upper_ptr.shape[0] - 1):
        q = upper_ptr[b]
        if q == upper_ptr[b + 1] or upper_cols[q] != 3 * b:
            missing += 1
            continue
        for i in range(3):
            value = upper[9 * q + 4 * i]
            out[3 * b + i] = 1.0 / value if value > 0.0 else 1.0
    return missing == 0


@parallel_kernel
def inverse_diagonal(indptr, indices, data, out):  # pragma: no cover - compiled
    """1 / A_ii where positive, else 1 (Jacobi preconditioner; sorted CSR rows)."""
    for row in numba.prange(indptr.shape[0] - 1):
        value = 0.0
        for k in range(indptr[row], indptr[row + 1]):
            if indices[k] == row:
                value = data[k]
                break
        out[row] = 1.0 / value if value > 0.0 else 1.0


@parallel_kernel
def _jacobi_start(b, ax, inv_diag, r, p):  # pragma: no cover - compiled
    """r = b - A x, p = r / diag; returns (b . b, r . r, r . p)."""
    b_square = 0.0
    r_square = 0.0
    rz = 0.0
    for i in numba.prange(b.shape[0]):
        value = b[i] - ax[i]
        r[i] = value
        z = value * inv_diag[i]
        p[i] = z
        b_square += b[i] * b[i]
        r_square += value * value
        rz += value * z
    return b_square, r_square, rz


@parallel_kernel
def _jacobi_update(x, r, p, ap, alpha, inv_diag):  # pragma: no cover - compiled
    """x += alpha p, r -= alpha A p; returns (r . r / diag, r . r)."""
    rz = 0.0
    r_square = 0.0
    for i in numba.prange(x.shape[0]):
        x[i] += alpha * p[i]
        value = r[i] - alpha * ap[i]
        r[i] = value
        rz += value * value * inv_diag[i]
        r_square += value * value
    return rz, r_square


@parallel_kernel
def _jacobi_direction(p, r, inv_diag, beta):  # pragma: no cover - compiled
    for i in numba.prange(p.shape[0]):
        p[i] = r[i] * inv_diag[i] + beta * p[i]


@parallel_kernel(prange=False)
def jacobi_pcg(
    indptr,
    indices,
    data,
    upper_ptr,
    upper_cols,
    upper,
    bounds,
    partial,
    b,
    x,
    inv_diag,
    max_iterations,
    tolerance,
):  # pragma: no cover - compiled
    """Jacobi-preconditioned CG on a system whose constrained rows are identity rows.

    Returns (iterations, relative residual). x (n,) holds the initial guess and the result;
    b (n,) is the right-hand side. The products use the upper node blocks where given (see
    :func:`~tissue.sim.solvers.node_blocks.node_block_product`). One iteration is three parallel
    passes: A p with p . A p, the updates of x and r with their dot products, and the new
    direction (z = r / diag is never stored).
    """
    n = b.shape[0]
    r = np.empty(n)
    p = np.empty(n)
    ap = np.empty(n)
    node_block_product(indptr, indices, data, upper_ptr, upper_cols, upper, bounds, partial, x, ap)
    b_square, r_square, rz = _jacobi_start(b, ap, inv_diag, r, p)
    b_norm = np.sqrt(b_square)
    if b_norm == 0.0:
        b_norm = 1.0
    residual = np.sqrt(r_square) / b_norm
    iterations = 0
    while iterations < max_iterations and residual > tolerance:
        pap = node_block_product(
            indptr, indices, data, upper_ptr, upper_cols, upper, bounds, partial, p, ap
        )
        if pap <= 0.0 or not np.isfinite(pap):
            break  # indefinite direction or breakdown: stop with what we have
        alpha = rz / pap
        rz_new, r_square = _jacobi_update(x, r, p, ap, alpha, inv_diag)
        beta = rz_new / rz
        rz = rz_new
        _jacobi_direction(p, r, inv_diag, beta)
        iterations += 1
        residual = np.sqrt(r_square) / b_norm
    return iterations, residual
