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
  Elasticity matrices are made of 3x3 node blocks: CG then multiplies with the upper
  blocks only (half the memory traffic, in double precision).
* ``direct``: a sparse Cholesky-type factorisation. Intel MKL Pardiso (:mod:`tissue.sim.pardiso`:
  located through ``pypardiso``, which installs from wheels with pip alone, and called
  directly; SPD mode),
  with a symmetric-indefinite factorisation as fallback when the matrix is not positive
  definite, and scipy's SuperLU where MKL is unavailable.
* ``reuse``: CG preconditioned by the last factorisation, refactorising only when CG
  stalls. Consecutive implicit steps change the matrix little, so most steps cost a few
  triangular solves instead of a factorisation (Courtecuisse et al. 2014 use a one-step-old
  factorisation as preconditioner in the same spirit). The preconditioner is factorised
  in single precision (half the memory and time); CG itself runs in double precision on the
  exact matrix, and a system it cannot solve gets the double-precision direct solve. The
  kept factorisation is corrected in capacitance (Woodbury) form for what changes in low
  rank between solves: dofs constrained since it was computed, and rank-one terms a system
  declares (:class:`RankOneTerms`: penalty springs) changed since.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numba
import numpy as np
import scipy.linalg
import scipy.sparse as sp
from numpy.typing import NDArray

from tissue.choices import Choice
from tissue.errors import ConfigError
from tissue.mesh import node_dofs
from tissue.sim.frames import FrameChange, NodeFrames, find_column
from tissue.sim.pardiso import (
    PardisoError,
    PardisoFactorization,
    PardisoInstance,
    pardiso_available,
)
from tissue.threads import one_thread_below, parallel_kernel


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
#
# Vector reductions run in these compiled loops rather than through numpy's BLAS (``@`` and
# ``np.linalg.norm`` on 1-D arrays): OpenBLAS hands vectors of more than ~10^4 entries to its
# worker threads, and on a small busy machine waking them cost 3-8 ms per call (measured here
# on two shared cores: ``np.linalg.norm`` of 16,059 doubles took 4-8 ms against 8 us in a
# serial loop), more than the rest of a Newton step on the 26k-tet mesh.


@parallel_kernel
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


def vector_norm(x: NDArray[np.float64]) -> float:
    """Euclidean norm of a 1-D float64 array in a serial loop (not BLAS: see above)."""
    return math.sqrt(_dot(x, x))


@numba.njit(cache=True)
def _free_square_norm(x, constrained):  # pragma: no cover - compiled
    """Sum of x_i^2 over the free (not constrained) entries."""
    acc = 0.0
    for i in range(x.shape[0]):
        if not constrained[i]:
            acc += x[i] * x[i]
    return acc


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


@parallel_kernel
def _product(
    indptr, indices, data, upper_ptr, upper_cols, upper, bounds, partial, x, out
):  # pragma: no cover - compiled
    """out = A x; returns x . out.

    With node blocks (``upper_ptr`` longer than 1) only the upper 3x3 blocks are read (see
    :class:`_NodeBlocks`): block (b, c) adds B x_c to row b and, off the diagonal, B^T x_b to
    row c, each of the ``partial`` rows summing its own range of node rows. Else plain CSR.
    """
    n = out.shape[0]
    if upper_ptr.shape[0] > 1:
        parts = partial.shape[0]
        for part in numba.prange(parts):
            y = partial[part]
            y[:] = 0.0
            for b in range(bounds[part], bounds[part + 1]):
                xb0 = x[3 * b]
                xb1 = x[3 * b + 1]
                xb2 = x[3 * b + 2]
                a0 = 0.0
                a1 = 0.0
                a2 = 0.0
                for q in range(upper_ptr[b], upper_ptr[b + 1]):
                    c = upper_cols[q]
                    o = 9 * q
                    x0 = x[c]
                    x1 = x[c + 1]
                    x2 = x[c + 2]
                    a0 += upper[o] * x0 + upper[o + 1] * x1 + upper[o + 2] * x2
                    a1 += upper[o + 3] * x0 + upper[o + 4] * x1 + upper[o + 5] * x2
                    a2 += upper[o + 6] * x0 + upper[o + 7] * x1 + upper[o + 8] * x2
                    if c != 3 * b:
                        y[c] += upper[o] * xb0 + upper[o + 3] * xb1 + upper[o + 6] * xb2
                        y[c + 1] += upper[o + 1] * xb0 + upper[o + 4] * xb1 + upper[o + 7] * xb2
                        y[c + 2] += upper[o + 2] * xb0 + upper[o + 5] * xb1 + upper[o + 8] * xb2
                y[3 * b] += a0
                y[3 * b + 1] += a1
                y[3 * b + 2] += a2
        total = 0.0
        for i in numba.prange(n):
            acc = 0.0
            for part in range(parts):
                acc += partial[part, i]
            out[i] = acc
            total += x[i] * acc
        return total
    total = 0.0
    for row in numba.prange(n):
        acc = 0.0
        for k in range(indptr[row], indptr[row + 1]):
            acc += data[k] * x[indices[k]]
        out[row] = acc
        total += x[row] * acc
    return total


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
def _jacobi_pcg(
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

    Returns (iterations, relative residual). x holds the initial guess and the result. The
    products use the upper node blocks where given (see :func:`_product`). One iteration is
    three parallel passes: A p with p . A p, the updates of x and r with their dot products,
    and the new direction (z = r / diag is never stored).
    """
    n = b.shape[0]
    r = np.empty(n)
    p = np.empty(n)
    ap = np.empty(n)
    _product(indptr, indices, data, upper_ptr, upper_cols, upper, bounds, partial, x, ap)
    b_square, r_square, rz = _jacobi_start(b, ap, inv_diag, r, p)
    b_norm = np.sqrt(b_square)
    if b_norm == 0.0:
        b_norm = 1.0
    residual = np.sqrt(r_square) / b_norm
    iterations = 0
    while iterations < max_iterations and residual > tolerance:
        pap = _product(indptr, indices, data, upper_ptr, upper_cols, upper, bounds, partial, p, ap)
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


@numba.njit(cache=True)
def _node_block_columns(indptr, indices, columns):  # pragma: no cover - compiled
    """Whether the pattern is node-blocked (layout of :mod:`tissue.fem.kernels`).

    That is: rows 3b, 3b+1, 3b+2 share one column list made of whole triples 3c, 3c+1,
    3c+2 (c ascending). Writes the first column 3c of each block to ``columns`` (nnz / 9,).
    """
    n = indptr.shape[0] - 1
    if n % 3 != 0 or indices.shape[0] != 9 * columns.shape[0]:
        return False
    for b in range(n // 3):
        start = indptr[3 * b]
        width = indptr[3 * b + 1] - start
        if (
            width % 3 != 0
            or indptr[3 * b + 2] - indptr[3 * b + 1] != width
            or indptr[3 * b + 3] - indptr[3 * b + 2] != width
        ):
            return False
        for block in range(width // 3):
            c = indices[start + 3 * block]
            if c % 3 != 0:
                return False
            for i in range(3):
                for k in range(3):
                    if indices[start + i * width + 3 * block + k] != c + k:
                        return False
            columns[start // 9 + block] = c
    return True


@numba.njit(cache=True)
def _count_upper_blocks(indptr, columns, upper_ptr):  # pragma: no cover - compiled
    """upper_ptr[b]: first upper block (column >= row) of node row b; returns their count."""
    count = 0
    for b in range(upper_ptr.shape[0] - 1):
        start = indptr[3 * b]
        upper_ptr[b] = count
        for block in range((indptr[3 * b + 1] - start) // 3):
            if columns[start // 9 + block] >= 3 * b:
                count += 1
    upper_ptr[upper_ptr.shape[0] - 1] = count
    return count


@parallel_kernel
def _fill_upper_blocks(
    indptr, columns, data, upper_ptr, upper_cols, upper
):  # pragma: no cover - compiled
    """Copy the upper 3x3 blocks of node row b, row-major, to upper[9 q : 9 q + 9]."""
    for b in numba.prange(upper_ptr.shape[0] - 1):
        start = indptr[3 * b]
        width = indptr[3 * b + 1] - start
        q = upper_ptr[b]
        for block in range(width // 3):
            c = columns[start // 9 + block]
            if c < 3 * b:
                continue
            upper_cols[q] = c
            for i in range(3):
                for k in range(3):
                    upper[9 * q + 3 * i + k] = data[start + i * width + 3 * block + k]
            q += 1


@parallel_kernel
def _eliminate(indptr, indices, data, constrained):  # pragma: no cover - compiled
    """Identity rows and columns at constrained dofs, in place."""
    for row in numba.prange(indptr.shape[0] - 1):
        row_constrained = constrained[row]
        for k in range(indptr[row], indptr[row + 1]):
            col = indices[k]
            if row_constrained or constrained[col]:
                data[k] = 1.0 if col == row else 0.0


@numba.njit(cache=True)
def _entries_touching(indptr, indices, dofs):  # pragma: no cover - compiled
    """Positions in a symmetric CSR pattern (sorted rows) of every entry in the rows and
    columns of ``dofs``, with repeats (-1 where a mirror entry is missing)."""
    count = 0
    for d in dofs:
        count += 2 * (indptr[d + 1] - indptr[d])
    out = np.empty(count, dtype=np.int64)
    q = 0
    for d in dofs:
        for k in range(indptr[d], indptr[d + 1]):
            out[q] = k
            q += 1
            # The mirror entry (column, d) in the column's row.
            out[q] = find_column(indices, indptr[indices[k]], indptr[indices[k] + 1], d)
            q += 1
    return out


@numba.njit(cache=True)
def _add_known_columns(indptr, indices, data, values, out):  # pragma: no cover - compiled
    """out += A values for a symmetric CSR A, visiting only the rows of nonzero values.

    Row j of A is its column j, and rows are visited in increasing j: each out[i] receives
    the nonzero terms in the order of a row-wise product (bitwise the same sums).
    """
    for j in range(values.shape[0]):
        value = values[j]
        if value == 0.0:
            continue
        for k in range(indptr[j], indptr[j + 1]):
            out[indices[k]] += data[k] * value


@parallel_kernel
def _block_inverse_diagonal(upper_ptr, upper_cols, upper, out):  # pragma: no cover - compiled
    """1 / A_ii where positive, else 1, from the diagonal blocks of node blocks; returns
    False if some node row has no diagonal block (then use :func:`_inverse_diagonal`)."""
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
def _inverse_diagonal(indptr, indices, data, out):  # pragma: no cover - compiled
    """1 / A_ii where positive, else 1 (Jacobi preconditioner; sorted CSR rows)."""
    for row in numba.prange(indptr.shape[0] - 1):
        value = 0.0
        for k in range(indptr[row], indptr[row + 1]):
            if indices[k] == row:
                value = data[k]
                break
        out[row] = 1.0 / value if value > 0.0 else 1.0


@parallel_kernel
def _gather(source, positions, out):  # pragma: no cover - compiled
    """out[i] = source[positions[i]] (converting to out's type)."""
    for i in numba.prange(positions.shape[0]):
        out[i] = source[positions[i]]


# ----------------------------------------------------------------------------- systems


@dataclass(frozen=True)
class RankOneTerms:
    """Part of a system matrix written as sum_i s_i v_i v_i^T, terms that come and go between
    solves (penalty springs: one per contact point), so that a kept factorisation can be
    corrected for them in low rank (see ``_RankOneSince``).

    Attributes:
        keys: what each term stands for, unique (a contact point's index), shape (k,).
        dofs: the dofs each v_i touches, shape (k, m), distinct within a row.
        vectors: v_i's entries at those dofs, shape (k, m).
        scales: s_i > 0 [the matrix's units], shape (k,).
    """

    keys: NDArray[np.int64]
    dofs: NDArray[np.int64]
    vectors: NDArray[np.float64]
    scales: NDArray[np.float64]


class ConstrainedSystem:
    """A symmetric system A x = b with some dofs of x known, eliminated in place.

    Args:
        matrix: the full symmetric matrix, CSR with sorted indices, shape (n, n). Its data is
            modified in place (identity rows and columns at constrained dofs).
        rhs: the full right-hand side, shape (n,).
        constrained: mask of known dofs, shape (n,), bool.
        values: the known values at constrained dofs (other entries ignored), shape (n,).
        rank_one: the terms of ``matrix`` that change in low rank between solves (already
            included in it), or None; ``reuse`` corrects its kept factorisation for them.
        frames: the node frames the system is written in (None: world coordinates); ``reuse``
            turns its kept factorisation into them.
    """

    def __init__(
        self,
        matrix: sp.csr_matrix,
        rhs: NDArray[np.float64],
        constrained: NDArray[np.bool_],
        values: NDArray[np.float64],
        rank_one: RankOneTerms | None = None,
        frames: NodeFrames | None = None,
    ) -> None:
        self.rank_one = rank_one
        self.frames = frames
        # Names the matrix's current values (systems derived with ``with_rhs`` / ``with_load``
        # share it): a solver keeps what it derived from them, such as CG's node blocks,
        # until :meth:`matrix_modified` says they changed.
        self.values_token = object()
        values = np.where(constrained, values, 0.0)
        # Move the known columns to the right-hand side before eliminating them (by symmetry,
        # the rows of the nonzero known values: a few probe nodes instead of the whole matrix).
        known = np.zeros_like(rhs)
        _add_known_columns(matrix.indptr, matrix.indices, matrix.data, values, known)
        self.original_rhs = rhs
        self.rhs = np.where(constrained, values, rhs - known)
        self.constrained = constrained
        self.values = values
        self._full_times_values = known
        # A framed node's constrained axis turns with its frame from step to step; a kept
        # factorisation must not hold it eliminated (see ``unframed``): keep its entries.
        self._framed_entries: (
            tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.bool_]] | None
        ) = None
        if frames is not None:
            framed = np.zeros(constrained.size, dtype=bool)
            framed[node_dofs(frames.nodes)] = True
            framed &= constrained
            positions = np.unique(
                _entries_touching(matrix.indptr, matrix.indices, np.flatnonzero(framed))
            )
            if positions.size and positions[0] < 0:
                raise ValueError("node frames need a matrix with a symmetric sparsity pattern")
            self._framed_entries = (positions, matrix.data[positions].copy(), framed)
        _eliminate(matrix.indptr, matrix.indices, matrix.data, constrained)
        self.matrix = matrix

    def unframed(self) -> tuple[sp.csr_matrix, NDArray[np.bool_]]:
        """The matrix with the constrained axes of framed nodes not eliminated (a copy), and
        the dofs still eliminated in it: what a kept factorisation factorises, so that the
        later systems' turned frames find those axes in it (their constraints are then
        corrected for, :class:`_ConstrainedSince`). The system's own when it has no frames,
        or more framed constraints than such a correction takes
        (:data:`MAX_CONSTRAINED_SINCE`)."""
        if self._framed_entries is None:
            return self.matrix, self.constrained
        positions, values, framed = self._framed_entries
        if np.count_nonzero(framed) > MAX_CONSTRAINED_SINCE:
            return self.matrix, self.constrained
        matrix = self.matrix.copy()
        matrix.data[positions] = values
        return matrix, self.constrained & ~framed

    def matrix_modified(self) -> None:
        """Say that the matrix's values were changed in place (after construction): what a
        solver derived from the old ones is not used again. Systems derived later share
        the new token; those derived before keep the old one and must not be solved."""
        self.values_token = object()

    def with_rhs(self, rhs: NDArray[np.float64]) -> ConstrainedSystem:
        """The same (already eliminated) matrix with right-hand side ``rhs`` and the known
        dofs held at zero, shape (n,): A x = rhs for the increment a load adds."""
        other = object.__new__(ConstrainedSystem)
        other.matrix = self.matrix
        other.values_token = self.values_token
        other.rank_one = self.rank_one
        other.frames = self.frames
        other._framed_entries = self._framed_entries
        other.constrained = self.constrained
        other.values = np.zeros_like(rhs)
        other.original_rhs = rhs
        other.rhs = np.where(self.constrained, 0.0, rhs)
        other._full_times_values = np.zeros_like(rhs)
        return other

    def with_load(self, load: NDArray[np.float64]) -> ConstrainedSystem:
        """The same system with ``load`` added to its right-hand side at the free dofs and
        the known dofs kept at their values, shape (n,)."""
        other = object.__new__(ConstrainedSystem)
        other.matrix = self.matrix
        other.values_token = self.values_token
        other.rank_one = self.rank_one
        other.frames = self.frames
        other._framed_entries = self._framed_entries
        other.constrained = self.constrained
        other.values = self.values
        other.original_rhs = self.original_rhs + load
        other.rhs = np.where(self.constrained, self.rhs, self.rhs + load)
        other._full_times_values = self._full_times_values
        return other

    def residual_norm(self, x: NDArray[np.float64]) -> float:
        """||b - A x|| / ||b|| of the eliminated system."""
        ax = np.empty_like(x)
        _spmv(self.matrix.indptr, self.matrix.indices, self.matrix.data, x, ax)
        difference = self.rhs - ax
        denominator = math.sqrt(_dot(self.rhs, self.rhs)) or 1.0
        return math.sqrt(_dot(difference, difference)) / denominator

    def free_rhs_norm(self) -> float:
        """||b|| over the free dofs."""
        return math.sqrt(_free_square_norm(self.rhs, self.constrained))


class _NodeBlocks:
    """The upper 3x3 blocks of a symmetric node-blocked matrix, for the products of CG.

    A product then reads half the matrix (each off-diagonal block serves both triangles): on
    the 176k-tet phantom 2.5x faster than CSR here, as the upper blocks (18 MB) stay in the
    32 MB L3 cache and the whole CSR matrix (50 MB) does not. Built once per pattern; the
    values are copied from the CSR data before each solve (about one CSR product).
    """

    def __init__(self, indptr: NDArray[np.integer], columns: NDArray[np.int32]) -> None:
        node_count = (indptr.shape[0] - 1) // 3
        self.indptr = indptr
        self.columns = columns
        self.upper_ptr = np.empty(node_count + 1, dtype=np.int64)
        count = _count_upper_blocks(indptr, columns, self.upper_ptr)
        self.upper_cols = np.empty(count, dtype=np.int32)
        self.upper = np.empty(9 * count)
        # One partial result per part; parts hold about the same number of blocks.
        parts = max(1, min(numba.get_num_threads(), node_count))
        self.bounds = np.searchsorted(self.upper_ptr, np.linspace(0, count, parts + 1))
        self.bounds = np.clip(self.bounds, 0, node_count).astype(np.int64)
        self.bounds[0], self.bounds[-1] = 0, node_count
        self.partial = np.empty((parts, 3 * node_count))

    @classmethod
    def of(cls, matrix: sp.csr_matrix) -> _NodeBlocks | None:
        """The blocks of ``matrix``'s pattern, or None if it is not node-blocked."""
        if matrix.indices.shape[0] % 9 != 0:
            return None
        columns = np.empty(matrix.indices.shape[0] // 9, dtype=np.int32)
        if not _node_block_columns(matrix.indptr, matrix.indices, columns):
            return None
        return cls(matrix.indptr, columns)

    def fill(self, data: NDArray[np.float64]) -> None:
        _fill_upper_blocks(
            self.indptr, self.columns, data, self.upper_ptr, self.upper_cols, self.upper
        )

    def arguments(self) -> tuple[NDArray, NDArray, NDArray, NDArray, NDArray]:
        return self.upper_ptr, self.upper_cols, self.upper, self.bounds, self.partial


class SymmetricProduct:
    """y = A x for a symmetric CSR matrix whose values do not change after this is built,
    through its upper node blocks where it is node-blocked (3x faster than a CSR product
    here on one thread: 34 against 105 us at 4,126 tets, 245 against 730 us at 26,220),
    else as CSR.

    Args:
        matrix: the matrix, (n, n), sorted indices; its values are copied now.
    """

    def __init__(self, matrix: sp.csr_matrix) -> None:
        self.matrix = matrix
        self.blocks = _NodeBlocks.of(matrix)
        if self.blocks is not None:
            self.blocks.fill(matrix.data)

    def __call__(self, x: NDArray[np.float64], out: NDArray[np.float64]) -> float:
        """Write A x to ``out`` (n,); returns x . A x."""
        return _matrix_product(self.matrix, self.blocks, x, out)


def _matrix_product(
    matrix: sp.csr_matrix,
    blocks: _NodeBlocks | None,
    x: NDArray[np.float64],
    out: NDArray[np.float64],
) -> float:
    """out = A x through ``blocks`` (holding A's values) where given, else as CSR; x . A x."""
    upper_ptr, upper_cols, upper, bounds, partial = (
        blocks.arguments() if blocks is not None else _NO_BLOCKS
    )
    return float(
        _product(
            matrix.indptr,
            matrix.indices,
            matrix.data,
            upper_ptr,
            upper_cols,
            upper,
            bounds,
            partial,
            x,
            out,
        )
    )


# The block arguments of _product when there are no blocks (plain CSR products).
_NO_BLOCKS = (
    np.zeros(1, dtype=np.int64),
    np.zeros(0, dtype=np.int32),
    np.zeros(0),
    np.zeros(1, dtype=np.int64),
    np.zeros((1, 1)),
)


class _SuperLUFactorization:
    def __init__(self, matrix: sp.csr_matrix) -> None:
        import scipy.sparse.linalg as spla

        self._lu = spla.splu(matrix.tocsc(), permc_spec="MMD_AT_PLUS_A")

    def solve(self, rhs: NDArray[np.float64]) -> NDArray[np.float64]:
        return self._lu.solve(rhs)


class DirectFactorizer:
    """Factorises symmetric matrices of one fixed sparsity pattern, reusing the analysis.

    With Pardiso, the upper-triangle positions are found once and the symbolic analysis
    (reordering) is computed once per matrix type and precision; each factorisation then
    runs only the numerical phase. A matrix that is not positive definite (a zero or
    negative pivot in the SPD mode) is refactorised in symmetric-indefinite mode
    (Bunch-Kaufman pivoting) instead of failing.

    Rows and columns of eliminated dofs (``constrained``: identity rows and columns, as
    :class:`ConstrainedSystem` leaves them) are handed to Pardiso as their diagonal alone, not
    as the zeros the pattern still holds there, which it would otherwise factorise as
    nonzeros. The dofs so left out are those constrained in every matrix factorised since
    the pattern was analysed (the fixed base, in practice): the analysis is redone only when
    one of them is found free. Measured on the phantom's paper-mode matrix (fixed base
    eliminated): factor nonzeros 436,694 -> 355,723 at 4,126 tets and 6.36 -> 5.12 M at
    26,220; double-precision factorisation 4.96 -> 4.11 ms and 131 -> 108 ms, single 3.42 ->
    2.75 ms and 75.8 -> 57.0 ms, a solve 15-25 % faster (median of 5-7 each, one process).
    """

    def __init__(self, backend: DirectBackend | str = DirectBackend.AUTO) -> None:
        self.backend = DirectBackend.parse(backend)
        if self.backend is DirectBackend.AUTO:
            self.backend = DirectBackend.PARDISO if pardiso_available() else DirectBackend.SUPERLU
        self._pattern: tuple[NDArray[np.integer], NDArray[np.integer]] | None = None
        self._upper_positions: NDArray[np.int64] | None = None
        self._upper_structure: tuple[NDArray[np.int32], NDArray[np.int32]] | None = None
        self._instances: dict[tuple[int, bool], PardisoInstance] = {}
        # The dofs whose rows and columns the analysed pattern holds as the diagonal alone.
        self._left_out: NDArray[np.bool_] | None = None

    def factorize(
        self, matrix: sp.csr_matrix, constrained: NDArray[np.bool_] | None = None
    ) -> tuple[Factorization, bool]:
        """Factorise ``matrix`` (CSR, symmetric). Returns (factorisation, used_indefinite).

        ``constrained`` (n,) bool, optional: dofs whose rows and columns in ``matrix`` are
        the identity's (eliminated), which the factorisation may leave out.
        """
        if self.backend is DirectBackend.SUPERLU:
            return _SuperLUFactorization(matrix), False
        for mtype in (2, -2):  # SPD first, then symmetric indefinite
            try:
                return self._factorize_pardiso(matrix, mtype, False, constrained), mtype == -2
            except PardisoError:
                continue
        # Both failed (a truly singular matrix): fall back to SuperLU, which may still cope.
        return _SuperLUFactorization(matrix), True

    def factorize_preconditioner(
        self,
        matrix: sp.csr_matrix,
        single: bool = True,
        constrained: NDArray[np.bool_] | None = None,
    ) -> Factorization | None:
        """An SPD factorisation good enough to precondition CG, or None if not SPD.

        With Pardiso and ``single`` it is computed in single precision: half the memory and
        about half the time of a double one, enough for the loose solves of inexact Newton
        (CG runs in double precision on the exact matrix). Its solves are only accurate to
        about cond(A) x 6e-8, though: for tight solves (contact compliances) ask for double.
        """
        if self.backend is DirectBackend.SUPERLU:
            factorization, indefinite = self.factorize(matrix)
            return None if indefinite else factorization
        try:
            return self._factorize_pardiso(matrix, 2, single, constrained)
        except PardisoError:
            return None

    def factor_nonzeros(self) -> int:
        """Nonzeros of the largest factor held (0 for SuperLU), for memory accounting."""
        return max((i.factor_nonzeros for i in self._instances.values()), default=0)

    def analyse(
        self, matrix: sp.csr_matrix, constrained: NDArray[np.bool_], mtype: int, single: bool
    ) -> None:
        """The symbolic analysis of ``matrix``'s pattern for a later factorisation of matrix
        type ``mtype`` and precision ``single`` with ``constrained`` dofs left out, now (see
        :meth:`LinearSolver.analyse`). Nothing to do with SuperLU."""
        if self.backend is DirectBackend.PARDISO:
            self._instance(matrix, mtype, single, constrained)

    def _instance(
        self,
        matrix: sp.csr_matrix,
        mtype: int,
        single: bool,
        constrained: NDArray[np.bool_] | None,
    ) -> tuple[PardisoInstance, bool]:
        """The Pardiso instance for ``matrix``'s pattern, type and precision, and whether it
        is new (its values then already gathered from ``matrix``)."""
        self._refresh_pattern(matrix, constrained)
        assert self._upper_positions is not None and self._upper_structure is not None
        instance = self._instances.get((mtype, single))
        if instance is not None:
            return instance, False
        indptr, indices = self._upper_structure
        data: NDArray[np.floating] = np.empty(
            indices.shape[0], dtype=np.float32 if single else np.float64
        )
        _gather(matrix.data, self._upper_positions, data)
        instance = PardisoInstance(mtype, single, indptr, indices, data)
        self._instances[(mtype, single)] = instance
        return instance, True

    def _factorize_pardiso(
        self,
        matrix: sp.csr_matrix,
        mtype: int,
        single: bool,
        constrained: NDArray[np.bool_] | None,
    ) -> PardisoFactorization:
        instance, new = self._instance(matrix, mtype, single, constrained)
        if not new:
            assert self._upper_positions is not None
            _gather(matrix.data, self._upper_positions, instance.data)
        instance.factorize()
        return PardisoFactorization(instance)

    def _refresh_pattern(
        self, matrix: sp.csr_matrix, constrained: NDArray[np.bool_] | None
    ) -> None:
        """Upper-triangle positions and structure of a new pattern, or of fewer dofs left out
        (instances dropped: a new analysis)."""
        n = matrix.shape[0]
        eliminated = np.zeros(n, dtype=bool) if constrained is None else constrained
        if self._same_pattern(matrix):
            assert self._left_out is not None
            if not np.any(self._left_out & ~eliminated):
                return
            left_out = self._left_out & eliminated  # one of them is free now
        else:
            left_out = eliminated.copy()
        rows = np.repeat(np.arange(n), np.diff(matrix.indptr))
        columns = matrix.indices
        upper = np.flatnonzero(
            (columns > rows) & ~left_out[rows] & ~left_out[columns] | (columns == rows)
        )
        self._left_out = left_out
        counts = np.bincount(rows[upper], minlength=matrix.shape[0])
        indptr = np.zeros(matrix.shape[0] + 1, dtype=np.int32)
        np.cumsum(counts, out=indptr[1:])
        self._upper_positions = upper
        self._upper_structure = (indptr, matrix.indices[upper].astype(np.int32))
        self._pattern = (matrix.indptr.copy(), matrix.indices.copy())
        self._instances = {}  # their memory is released as they are collected

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


@dataclass(frozen=True)
class LinearSolverConfig:
    """Settings of the linear solver.

    Attributes:
        kind: ``cg``, ``direct`` or ``reuse``.
        cg_max_iterations: iteration cap of ``cg`` (25 as in the paper).
        cg_tolerance: relative residual at which ``cg`` stops early.
        direct_backend: ``auto`` (Pardiso where available, else SuperLU), ``pardiso``, ``superlu``.
        reuse_max_iterations: preconditioned-CG iterations after which ``reuse`` refactorises.
        reuse_refresh_factor: ``reuse`` also refactorises once the CG iterations beyond the
            first of each solve since the kept factorisation add up to this times the square
            root of the free unknowns: what a (numeric) refactorisation costs in CG
            iterations, measured here (robust penalty pressing the phantom, single-precision
            Pardiso, 2 cores) as 6.3 / 8.5 / 14.6 / 19.3 iterations at 2,025 / 3,123 / 8,970 /
            16,239 free unknowns (2,539 / 4,126 / 12,861 / 26,220 tets): 0.14-0.15 sqrt(n).
            0 refreshes only when CG stalls.
    """

    kind: LinearSolverKind | str = LinearSolverKind.CG
    cg_max_iterations: int = 25
    cg_tolerance: float = 1e-5
    direct_backend: DirectBackend | str = DirectBackend.AUTO
    reuse_max_iterations: int = 12
    reuse_refresh_factor: float = 0.15

    def __post_init__(self) -> None:
        object.__setattr__(self, "kind", LinearSolverKind.parse(self.kind))
        object.__setattr__(self, "direct_backend", DirectBackend.parse(self.direct_backend))
        if self.cg_max_iterations < 1:
            raise ConfigError(f"cg_max_iterations must be >= 1; got {self.cg_max_iterations}")
        if not 0 < self.cg_tolerance < 1:
            raise ConfigError(f"cg_tolerance must lie in (0, 1); got {self.cg_tolerance}")
        if self.reuse_max_iterations < 1:
            raise ConfigError(f"reuse_max_iterations must be >= 1; got {self.reuse_max_iterations}")
        if not (math.isfinite(self.reuse_refresh_factor) and self.reuse_refresh_factor >= 0.0):
            raise ConfigError(
                "reuse_refresh_factor must be a finite number >= 0 (0: refactorise only when CG "
                f"stalls); got {self.reuse_refresh_factor}"
            )


class LinearSolver:
    """Solves constrained systems with the configured method, keeping state across steps."""

    def __init__(self, config: LinearSolverConfig | None = None) -> None:
        self.config = config or LinearSolverConfig()
        self._factorizer: DirectFactorizer | None = None
        self._reuse: Factorization | None = None
        # Dofs constrained when the kept factorisation was computed, and its corrections for
        # dofs constrained since (see _ConstrainedSince).
        self._reuse_constrained: NDArray[np.bool_] | None = None
        self._since: _ConstrainedSince | None = None
        # The node frames the kept factorisation's matrix was written in.
        self._reuse_frames: NodeFrames | None = None
        # The rank-one terms of the kept factorisation's matrix (None: unknown, so never
        # corrected), and its corrections for the terms changed since (see _RankOneSince).
        self._reuse_rank_one: RankOneTerms | None = None
        self._rank_one_since: _RankOneSince | None = None
        self.last_factorization: Factorization | None = None
        # Kept factorisations in single precision (see DirectFactorizer.factorize_preconditioner);
        # False keeps them in double (twice the memory and time per triangular solve).
        self.single_precision_preconditioner = True
        # Whether the last refresh_kept_factorization found its matrix not SPD.
        self.kept_indefinite = False
        # (indices, indptr) of the last pattern CG saw, and its node blocks (or None).
        self._blocks: tuple[NDArray, NDArray, _NodeBlocks | None] | None = None
        # (those blocks, the values token of the system they were last filled from).
        self._filled_for: tuple[_NodeBlocks, object] | None = None
        # Amortised refresh of the kept factorisation (``reuse``, see _solve_reuse): the CG
        # iterations beyond the first of each solve since it was computed, plus what its
        # rank-one corrections' columns cost (in iterations).
        self._excess_iterations = 0.0

    @property
    def factorizer(self) -> DirectFactorizer:
        if self._factorizer is None:
            self._factorizer = DirectFactorizer(self.config.direct_backend)
        return self._factorizer

    def analyse(self, matrix: sp.csr_matrix, constrained: NDArray[np.bool_]) -> None:
        """Analyse ``matrix``'s pattern (symmetric, CSR) ahead of the kept factorisation a
        ``reuse`` solver will compute, with ``constrained`` (n,) bool left out: a one-time
        cost (5.3 of the first robust step's 19 ms at 4,126 tets) paid when a model is built.
        The values are not factorised. Nothing to do for other kinds or without Pardiso."""
        if self.config.kind is LinearSolverKind.REUSE:
            self.factorizer.analyse(matrix, constrained, 2, self.single_precision_preconditioner)

    def forget(self) -> None:
        """Drop any factorisation kept across steps (after a reset or a large change)."""
        self._keep(None, None)
        self.last_factorization = None

    def _keep(
        self,
        factorization: Factorization | None,
        constrained: NDArray[np.bool_] | None,
        rank_one: RankOneTerms | None = None,
        frames: NodeFrames | None = None,
    ) -> None:
        self._excess_iterations = 0.0
        self._reuse = factorization
        self._reuse_constrained = None if constrained is None else constrained.copy()
        self._reuse_frames = frames
        self._since = None
        self._reuse_rank_one = rank_one
        self._rank_one_since = None

    def _preconditioner(
        self, constrained: NDArray[np.bool_], frames: NodeFrames | None = None
    ) -> Factorization | None:
        """The kept factorisation as a preconditioner for a system with ``constrained``
        dofs written in ``frames``: itself, or corrected for the dofs constrained since it
        was computed and turned into the system's frames (None when there are too many of
        those dofs: refactorise)."""
        if self._reuse is None or self._reuse_constrained is None:
            return self._reuse
        change = FrameChange.between(self._reuse_frames, frames)
        if change is None:
            added = np.flatnonzero(constrained & ~self._reuse_constrained)
        else:
            # A framed node whose frame turned: every dof it has constrained is corrected for
            # (along its new axis); the other dofs as usual.
            turned = np.zeros(constrained.size, dtype=bool)
            turned[node_dofs(change.nodes)] = True
            added = np.flatnonzero(constrained & (turned | ~self._reuse_constrained))
        if added.size == 0 and change is None:
            return self._reuse
        if added.size > MAX_CONSTRAINED_SINCE:
            return None
        if self._since is None:
            self._since = _ConstrainedSince(self._reuse, constrained.size)
        return self._since.for_dofs(added, change)

    def _corrected_for_rank_one(
        self, kept: Factorization, system: ConstrainedSystem
    ) -> Factorization | None:
        """``kept`` corrected for the rank-one terms changed since it was computed (itself
        when there are none, or they are not known; None when there are too many:
        refactorise)."""
        if system.rank_one is None or self._reuse_rank_one is None:
            return kept
        if self._rank_one_since is None:
            self._rank_one_since = _RankOneSince(kept, system.rhs.size, self._reuse_rank_one)
        return self._rank_one_since.for_terms(system.rank_one, system.constrained)

    @property
    def kept_factorization(self) -> Factorization | None:
        """The factorisation ``reuse`` solves precondition with (kept across steps), or None.

        A new object whenever it is refactorised, so callers may cache what they derive
        from it keyed on its identity.
        """
        return self._reuse

    def refresh_kept_factorization(self, system: ConstrainedSystem) -> Factorization:
        """Refactorise ``system``'s matrix now and keep it for later ``reuse`` solves
        (:attr:`kept_indefinite` says whether the matrix was not SPD)."""
        preconditioner = self._refactorize(system)
        self.kept_indefinite = preconditioner is None
        if preconditioner is None:  # not SPD: an exact (indefinite) factorisation
            preconditioner, _ = self.factorize(system)
            self._keep(preconditioner, system.constrained, system.rank_one, system.frames)
        return preconditioner

    def _refactorize(self, system: ConstrainedSystem) -> Factorization | None:
        """A fresh SPD factorisation of ``system``'s matrix, kept; None if not SPD.

        With node frames, where most framed nodes' frames turned since the last kept
        factorisation, their constrained axes are left free in it
        (:meth:`ConstrainedSystem.unframed`) and corrected for in every later solve: a
        turned axis the factor held eliminated costs CG about an iteration each (a sphere
        pressed into a block: 14 CG iterations a step against 3-5). Where few turned (a flat
        face: only the rim's nodes turn) they stay eliminated: the corrections' columns,
        one solve per framed node after each factorisation, would cost more than they save
        (173,229 tets, 93 sliding nodes under the face: 1.20-1.37 s against 1.10-1.11 s a
        step, the same CG iterations).
        """
        matrix, eliminated = system.matrix, system.constrained
        if system.frames is not None and _mostly_turned(self._reuse_frames, system.frames):
            matrix, eliminated = system.unframed()
        preconditioner = self.factorizer.factorize_preconditioner(
            matrix, self.single_precision_preconditioner, eliminated
        )
        if preconditioner is not None:
            self._keep(preconditioner, eliminated, system.rank_one, system.frames)
        return preconditioner

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
        factorization, indefinite = self.factorizer.factorize(system.matrix, system.constrained)
        self.last_factorization = factorization
        self._reuse = factorization
        self._reuse_frames = system.frames
        self._reuse_rank_one = None
        self._rank_one_since = None
        return factorization, indefinite

    def _node_blocks(self, matrix: sp.csr_matrix) -> _NodeBlocks | None:
        """Node blocks of ``matrix``'s pattern, found once per pattern (the same arrays)."""
        cached = self._blocks
        if (
            cached is None
            or not _same_buffer(cached[0], matrix.indices)
            or not _same_buffer(cached[1], matrix.indptr)
        ):
            cached = (matrix.indices, matrix.indptr, _NodeBlocks.of(matrix))
            self._blocks = cached
        return cached[2]

    def product(
        self, matrix: sp.csr_matrix, x: NDArray[np.float64], out: NDArray[np.float64]
    ) -> None:
        """out = A x for a symmetric CSR ``matrix`` (n, n) about to become a system's: through
        the node blocks CG keeps for its pattern (filled from it now; with the product, 62
        against 105 us for CSR at 4,126 tets), else as CSR."""
        blocks = self._node_blocks(matrix)
        if blocks is not None:
            blocks.fill(matrix.data)
            self._filled_for = None  # holding this matrix's values, not a system's
        _matrix_product(matrix, blocks, x, out)

    def _filled_blocks(self, system: ConstrainedSystem) -> _NodeBlocks | None:
        """The node blocks of ``system``'s matrix holding its values (filled once for the
        systems sharing its values token: a robust LM step solves three with one matrix,
        and filling them each time took more than the products they served), or None if
        its pattern is not node-blocked."""
        blocks = self._node_blocks(system.matrix)
        if blocks is None:
            return None
        filled = self._filled_for
        if filled is None or filled[0] is not blocks or filled[1] is not system.values_token:
            blocks.fill(system.matrix.data)
            self._filled_for = (blocks, system.values_token)
        return blocks

    def _solve_cg(self, system, initial_guess, tolerance):
        x = _start(system, initial_guess)
        matrix = system.matrix
        inv_diag = np.empty(matrix.shape[0])
        blocks = self._filled_blocks(system)
        if blocks is None or not _block_inverse_diagonal(
            blocks.upper_ptr, blocks.upper_cols, blocks.upper, inv_diag
        ):
            _inverse_diagonal(matrix.indptr, matrix.indices, matrix.data, inv_diag)
        with _threads_for(x.shape[0]):
            iterations, residual = _jacobi_pcg(
                matrix.indptr,
                matrix.indices,
                matrix.data,
                *(blocks.arguments() if blocks is not None else _NO_BLOCKS),
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
        cap = self.config.reuse_max_iterations
        spent = 0
        kept = self._preconditioner(system.constrained, system.frames)
        if kept is not None and kept is self._reuse:
            kept = self._corrected_for_rank_one(kept, system)
        corrected = self._rank_one_since if kept is self._rank_one_since else None
        # Ski rental: a fresh factor solves in about one CG iteration, so the iterations
        # beyond the first of each solve are what keeping the old factor costs; once they
        # add up to what a factorisation costs, refactorising now pays at worst twice the
        # best schedule. The cost is counted in iterations (deterministic, unlike wall time)
        # from the model of ``LinearSolverConfig.reuse_refresh_factor``.
        if kept is not None and self.config.reuse_refresh_factor > 0:
            free = system.rhs.size - int(np.count_nonzero(system.constrained))
            if self._excess_iterations >= self.config.reuse_refresh_factor * math.sqrt(free):
                kept = None
        if kept is not None:
            solved_before = corrected.solved_columns if corrected is not None else 0
            x = _start(system, initial_guess)
            with _threads_for(x.shape[0]):
                iterations, residual = _factor_pcg(
                    system, kept, x, cap, tolerance, lambda: self._filled_blocks(system)
                )
            self._excess_iterations += max(iterations - 1, 0)
            if corrected is not None:
                new_columns = corrected.solved_columns - solved_before
                self._excess_iterations += RANK_ONE_COLUMN_COST * new_columns
            if residual <= tolerance:
                return x, SolveReport(iterations, residual, True)
            spent = iterations
        # CG stalled, or refreshing pays (or nothing to reuse): a fresh factorisation.
        preconditioner = self._refactorize(system)
        if preconditioner is not None and system.frames is not None:
            # Factorised with the framed nodes' constrained axes free: corrected for them.
            preconditioner = self._preconditioner(system.constrained, system.frames)
        if preconditioner is not None:
            x = _start(system, initial_guess)
            with _threads_for(x.shape[0]):
                iterations, residual = _factor_pcg(
                    system, preconditioner, x, cap, tolerance, lambda: self._filled_blocks(system)
                )
            if residual <= tolerance:
                return x, SolveReport(spent + iterations, residual, True, True)
        # Not positive definite, or CG still short of the tolerance: an exact factorisation
        # (symmetric indefinite where needed, which the report says).
        x, report = self._solve_direct(system)
        return x, SolveReport(
            spent + report.iterations,
            report.relative_residual,
            report.converged,
            True,
            report.indefinite,
        )


# A kept factorisation is corrected for at most this many dofs constrained since it was
# computed (their columns of F^-1 are held: 192 x 95k doubles = 146 MB on the finest level);
# beyond, it is refactorised.
MAX_CONSTRAINED_SINCE = 192


class _ConstrainedSince:
    """A kept factorisation F corrected for dofs D constrained since it was computed.

    F factorised a matrix in which D were free; the system now holds them fixed (identity
    rows and columns), so F^-1 differs from the wanted inverse by a term of rank |D| and CG
    needs about |D| more iterations (prescribed displacement with an online node set: 11-22
    CG iterations a step on 26,220 tets while nodes joined the set, 1-3 while it stood
    still). The exact inverse on the other free dofs is the capacitance (Woodbury) form

        z = F^-1 r - Y S^-1 Y^T r,  Y = F^-1 E_D,  S = E_D^T F^-1 E_D,

    E_D the unit columns of D: one solve with F per application, plus |D| columns of F^-1
    solved once per dof (cached while F is kept), in the same multi-RHS call as the first
    application after the dof joined. Dofs released since F (identity in F, free now) are
    not corrected: CG absorbs them.

    A system written in other node frames than F's matrix (prescribed nodes sliding on the
    probe: :mod:`tissue.sim.frames`) is preconditioned by G = P F^-1 P^T, P the change of
    coordinates (:class:`tissue.sim.frames.FrameChange`), corrected in the same form with
    Y = G E_D. A dof d of a node whose frame turned is the direction P^T e_d in F's
    coordinates: its column of Y combines the node's three columns of F^-1 (kept like the
    others, so a frame that turns every step costs no new solves; Y itself is formed again,
    O(n |D|)). Kept factorisations hold the framed nodes' constrained axes free
    (:meth:`ConstrainedSystem.unframed`), so that every such constraint is corrected for; a
    direction F did hold eliminated (too many framed constraints, or an indefinite matrix
    factorised exactly) and the system's frame has turned away from is not (as a released
    dof).
    """

    def __init__(self, base: Factorization, size: int) -> None:
        self.base = base
        self.size = size
        self.slot: dict[int, int] = {}
        # Column-major and filled in place: a column's pages are touched only once it is
        # solved, and nothing is copied as columns join (an hstack per new batch and a
        # gather of the active columns per change of the set copied up to 146 MB each time
        # on the finest level: 19 % of a 176k press's time).
        self.columns = np.empty((size, MAX_CONSTRAINED_SINCE), order="F")
        self.count = 0
        self._active: NDArray[np.int64] | None = None
        self._active_slots = np.zeros(0, dtype=np.int64)
        self._factor: Any = None
        # The dofs to correct for (set by for_dofs), and those of them without a column yet.
        self._wanted: NDArray[np.int64] | None = None
        self._pending: list[int] = []
        # The change of frames from F's matrix to the system's (None: the same), the one the
        # active correction was formed for, and (when one applies) each wanted dof's kept
        # columns and their weights in F^-1 P^T e_d, shape (|D|, 3) each.
        self._change: FrameChange | None = None
        self._active_change: FrameChange | None = None
        self._turned: tuple[NDArray[np.int64], NDArray[np.float64]] | None = None

    def for_dofs(self, dofs: NDArray[np.int64], change: FrameChange | None = None) -> Factorization:
        """Correct for ``dofs`` (every dof constrained since F, sorted), in the coordinates
        ``change`` turns F's into (None: F's own). The columns of dofs not seen before are
        solved together with the next right-hand side (:meth:`solve`)."""
        needed = [int(d) for d in dofs]
        if change is not None:  # every dof of a turned node: its columns combine
            turned = set(change.nodes.tolist())
            needed += [3 * (d // 3) + axis for d in needed if d // 3 in turned for axis in range(3)]
        self._pending = list(dict.fromkeys(d for d in needed if d not in self.slot))
        self._wanted = dofs
        self._change = change
        return self

    def solve(self, rhs: NDArray[np.float64]) -> NDArray[np.float64]:
        assert self._wanted is not None
        change = self._change
        if change is not None:
            rhs = change.apply(rhs, transpose=True)
        if self._pending:
            # The new columns and this right-hand side in one multi-RHS call: Pardiso reads
            # the factor once for all of them (at 176,506 tets one right-hand side took 45
            # ms, six together 139 ms), which saves one solve in every step whose node set
            # grew.
            new, self._pending = self._pending, []
            block = np.zeros((self.size, len(new) + 1), order="F")
            block[new, np.arange(len(new))] = 1.0
            block[:, -1] = rhs
            solved = np.asarray(self.base.solve(block)).reshape(self.size, -1)
            self._store(new, solved[:, :-1])
            z = np.array(solved[:, -1], dtype=np.float64)
        else:
            z = np.array(self.base.solve(rhs), dtype=np.float64).reshape(-1)
        if change is not None:
            z = change.apply(z)
        if (
            self._active is None
            or not np.array_equal(self._active, self._wanted)
            or change is not self._active_change
        ):
            self._form_correction(change)
        if self._factor is None or self._active is None or self._active.size == 0:
            return z
        weights = scipy.linalg.cho_solve(self._factor, z[self._active])
        if self._turned is not None and change is not None:
            # Y w = P F^-1 P^T E_D w: the kept columns weighted, then turned (a few rows).
            slots, combination = self._turned
            scaled = (combination * weights[:, None]).ravel()
            used = scaled != 0.0  # an unturned dof has one column; its row holds two zeros
            response = np.zeros_like(z)
            _subtract_columns(response, self.columns, slots.ravel()[used], scaled[used])
            z += change.apply(response)
        else:
            _subtract_columns(z, self.columns, self._active_slots, weights)
        return z

    def _form_correction(self, change: FrameChange | None) -> None:
        """The Cholesky factor of S = E_D^T G E_D for the wanted dofs D (G = P F^-1 P^T),
        and with a change of frames the kept columns that make up G E_D."""
        assert self._wanted is not None
        self._active = self._wanted.copy()
        self._active_change = change
        self._active_slots = np.array([self.slot[int(d)] for d in self._active], dtype=np.int64)
        self._turned = None
        if self._active.size == 0:
            self._factor = None
            return
        if change is None:
            capacitance = self.columns[np.ix_(self._active, self._active_slots)]
        else:
            # Column d of F^-1 P^T E_D is e_d's own kept column, or for a dof (node a,
            # axis j) whose frame turned sum_i P_a[j, i] F^-1 e_(3a+i) (P^T e_d is row j of
            # P's block); row d' of P x likewise. So G E_D and S need no column of n rows.
            block_of = {int(node): k for k, node in enumerate(change.nodes)}
            dofs = np.repeat(self._active[:, None], 3, axis=1)
            combination = np.zeros((self._active.size, 3))
            combination[:, 0] = 1.0
            for index, dof in enumerate(self._active):
                node, axis = divmod(int(dof), 3)
                k = block_of.get(node)
                if k is not None:
                    dofs[index] = 3 * node + np.arange(3)
                    combination[index] = change.blocks[k, axis]
            slots = np.array([[self.slot[int(d)] for d in row] for row in dofs], dtype=np.int64)
            entries = self.columns[np.ix_(dofs.reshape(-1), slots.reshape(-1))]
            entries = entries.reshape(dofs.shape[0], 3, dofs.shape[0], 3)
            capacitance = np.einsum("pr,prqc,qc->pq", combination, entries, combination)
            self._turned = (slots, combination)
        try:
            self._factor = scipy.linalg.cho_factor(0.5 * (capacitance + capacitance.T))
        except np.linalg.LinAlgError:  # not positive definite (round-off): uncorrected
            self._factor = None

    def _store(self, dofs: list[int], solved: NDArray[np.float64]) -> None:
        """Keep the columns F^-1 e_d of ``dofs``, shape (size, len(dofs))."""
        if self.count + len(dofs) > self.columns.shape[1]:
            # Dofs released and others constrained since F: more columns than the cap on
            # the active set (rare; the array doubles, copied once).
            grown = np.empty((self.size, 2 * (self.count + len(dofs))), order="F")
            grown[:, : self.count] = self.columns[:, : self.count]
            self.columns = grown
        self.columns[:, self.count : self.count + len(dofs)] = solved
        for index, dof in enumerate(dofs):
            self.slot[dof] = self.count + index
        self.count += len(dofs)


# A kept factorisation is corrected for at most this many rank-one terms changed since it was
# computed (their columns F^-1 v are held, as for constrained dofs); beyond, it is refactorised.
MAX_RANK_ONE_SINCE = 192
# What one column F^-1 v solved beside a right-hand side costs, in CG iterations (single
# solves): measured 0.42 at 176,506 tets (one right-hand side 45 ms, six together 139 ms) and
# 0.32 at 26,220 (4.3 ms, 6.4 together 11.7 ms). Counted into ``reuse``'s refresh rule.
RANK_ONE_COLUMN_COST = 0.4
# A term whose vector has turned by less than this (cos 2 degrees) from the one its column was
# solved for keeps that column: the correction is then of a nearby matrix, which only a
# preconditioner's quality notices.
_RANK_ONE_TURN_COS = float(np.cos(np.radians(2.0)))


class _RankOneSince:
    """A kept factorisation F corrected for rank-one terms changed since it was computed.

    F factorised A_F, which held the terms T_F = sum s_i v_i v_i^T; the system now holds T
    (penalty springs: points entering and leaving contact, the probe's normal turning at its
    rim). Each change is a stiff rank-one term F knows nothing of, and CG pays about one
    iteration for each: robust penalty pressing the 26,220-tet phantom needed 7-9 CG
    iterations to 1e-6 four steps after a factorisation, 7-9 with only the springs' change
    added to A_F, and 3-4 with only the elastic tangent's change. With the change written as
    U S U^T (a column per term added, one per term removed with -s, both for a term that
    changed), the capacitance (Woodbury) form

        z = F^-1 r - Y C^-1 U^T F^-1 r,  Y = F^-1 U,  C = S^-1 + U^T Y,

    inverts F + U S U^T exactly: one solve with F per application, plus a column of Y per
    term, solved once while F is kept (in the same multi-RHS call as the next application)
    and reused as long as the term's vector has not turned by 2 degrees.
    """

    def __init__(self, base: Factorization, size: int, at_factor: RankOneTerms) -> None:
        self.base = base
        self.size = size
        self.at_factor = at_factor
        self._factor_order = np.argsort(at_factor.keys, kind="stable")
        self.columns = np.empty((size, MAX_RANK_ONE_SINCE), order="F")
        self.count = 0
        self.solved_columns = 0
        # (key, whether it is the factor's term) -> (slot, dofs, vector) of a solved column.
        self._held: dict[tuple[int, bool], tuple[int, NDArray, NDArray]] = {}
        self._pending: list[tuple[tuple[int, bool], NDArray, NDArray]] = []
        # The correction: its terms, the slots of their columns, scales, dofs and vectors.
        self._wanted: list[tuple[int, bool]] = []
        self._slots = np.zeros(0, dtype=np.int64)
        self._scales = np.zeros(0)
        self._dofs = np.zeros((0, 0), dtype=np.int64)
        self._vectors = np.zeros((0, 0))
        self._capacitance: Any = None
        self._stale = True

    def for_terms(self, now: RankOneTerms, constrained: NDArray[np.bool_]) -> Factorization | None:
        """Correct for the terms ``now`` against the factor's; None when that needs more
        columns than :data:`MAX_RANK_ONE_SINCE` (refactorise). New columns are solved with
        the next right-hand side (:meth:`solve`)."""
        old = self.at_factor
        old_vectors = np.where(constrained[old.dofs], 0.0, old.vectors)
        now_vectors = np.where(constrained[now.dofs], 0.0, now.vectors)
        match = np.full(now.keys.size, -1, dtype=np.int64)
        if old.keys.size and now.keys.size:
            where = np.searchsorted(old.keys, now.keys, sorter=self._factor_order)
            where = self._factor_order[np.minimum(where, old.keys.size - 1)]
            match = np.where(old.keys[where] == now.keys, where, -1)
        both = np.flatnonzero(match >= 0)
        same = np.zeros(now.keys.size, dtype=bool)
        same[both] = (old.scales[match[both]] == now.scales[both]) & _turned_less(
            old_vectors[match[both]], now_vectors[both]
        )
        added = np.flatnonzero(~same)  # new terms, and changed ones (their new form)
        kept_old = np.zeros(old.keys.size, dtype=bool)
        kept_old[match[same]] = True
        removed = np.flatnonzero(~kept_old)  # gone, and changed ones (their old form)
        pending: list[tuple[tuple[int, bool], NDArray, NDArray]] = []
        slot_keys: list[tuple[int, bool]] = []
        for i in added:
            slot_key = (int(now.keys[i]), False)
            held = self._held.get(slot_key)
            if held is None or not _turned_less(held[2][None], now_vectors[i][None])[0]:
                pending.append((slot_key, now.dofs[i], now_vectors[i]))
            slot_keys.append(slot_key)
        for j in removed:
            slot_key = (int(old.keys[j]), True)
            if slot_key not in self._held:  # a term of the factor never turns
                pending.append((slot_key, old.dofs[j], old_vectors[j]))
            slot_keys.append(slot_key)
        if self.count + len(pending) > MAX_RANK_ONE_SINCE:
            return None
        scales = np.concatenate([now.scales[added], -old.scales[removed]])
        self._stale = (
            self._stale
            or bool(pending)
            or slot_keys != self._wanted
            or not np.array_equal(scales, self._scales)
        )
        self._pending = pending
        self._wanted = slot_keys
        self._scales = scales
        return self

    def solve(self, rhs: NDArray[np.float64]) -> NDArray[np.float64]:
        if self._pending:
            # The new columns and this right-hand side in one multi-RHS call (see
            # _ConstrainedSince.solve).
            new, self._pending = self._pending, []
            block = np.zeros((self.size, len(new) + 1), order="F")
            for index, (_, dofs, vector) in enumerate(new):
                block[dofs, index] = vector
            block[:, -1] = rhs
            solved = np.asarray(self.base.solve(block)).reshape(self.size, -1)
            self.columns[:, self.count : self.count + len(new)] = solved[:, :-1]
            for index, (slot_key, dofs, vector) in enumerate(new):
                self._held[slot_key] = (self.count + index, dofs, vector)
            self.count += len(new)
            self.solved_columns += len(new)
            z = np.array(solved[:, -1], dtype=np.float64)
        else:
            z = np.array(self.base.solve(rhs), dtype=np.float64).reshape(-1)
        if self._stale:
            self._stale = False
            self._assemble_correction()
        if self._capacitance is None or self._slots.size == 0:
            return z
        projected = np.einsum("im,im->i", self._vectors, z[self._dofs])
        weights = scipy.linalg.lu_solve(self._capacitance, projected, check_finite=False)
        _subtract_columns(z, self.columns, self._slots, weights)
        return z

    def _assemble_correction(self) -> None:
        """U's columns as held, and the LU of C = S^-1 + U^T Y (symmetric; indefinite where
        terms were removed). A singular C (round-off) leaves the solves uncorrected."""
        held = [self._held[k] for k in self._wanted]
        self._capacitance = None
        if not held:
            self._slots = np.zeros(0, dtype=np.int64)
            return
        self._slots = np.array([h[0] for h in held], dtype=np.int64)
        self._dofs = np.stack([h[1] for h in held])
        self._vectors = np.stack([h[2] for h in held])
        at_dofs = self.columns[self._dofs.reshape(-1)][:, self._slots]
        at_dofs = at_dofs.reshape(*self._dofs.shape, self._slots.size)
        capacitance = np.einsum("im,imj->ij", self._vectors, at_dofs)
        capacitance = 0.5 * (capacitance + capacitance.T) + np.diag(1.0 / self._scales)
        if not np.all(np.isfinite(capacitance)):
            return
        factor = scipy.linalg.lu_factor(capacitance, check_finite=False)
        if np.all(np.isfinite(factor[0])) and np.all(np.diag(factor[0]) != 0.0):
            self._capacitance = factor


def _mostly_turned(old: NodeFrames | None, new: NodeFrames) -> bool:
    """Whether more than half of the nodes framed in ``new`` were framed in ``old`` with
    another frame."""
    change = FrameChange.between(old, new)
    if old is None or change is None:
        return False
    turned = np.intersect1d(np.intersect1d(change.nodes, old.nodes), new.nodes)
    return 2 * turned.size > new.nodes.size


def _turned_less(held: NDArray[np.float64], vectors: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Row by row, whether ``vectors`` point within 2 degrees of ``held`` with the same
    length to 1e-12 (both zero counts as the same), shapes (k, m) -> (k,)."""
    held_square = np.einsum("im,im->i", held, held)
    square = np.einsum("im,im->i", vectors, vectors)
    cross = np.einsum("im,im->i", held, vectors)
    same_length = np.abs(held_square - square) <= 1e-12 * np.maximum(held_square, square)
    aligned = cross >= _RANK_ONE_TURN_COS * np.sqrt(held_square * square)
    return same_length & (aligned | (square == 0.0))


@numba.njit(cache=True)
def _subtract_columns(z, columns, slots, weights):  # pragma: no cover - compiled
    """z -= columns[:, slots] @ weights, column by column (contiguous in a column-major
    array), in one serial loop: a BLAS product of a tall matrix woke OpenBLAS's threads (17 ms
    per application on 26,220 tets, two busy cores), and the gather would copy the columns."""
    for j in range(slots.shape[0]):
        column = slots[j]
        weight = weights[j]
        for i in range(z.shape[0]):
            z[i] -= columns[i, column] * weight


# Below this many unknowns CG runs on one thread (its kernels' serial builds, see
# tissue.threads). Each CG iteration is three or four parallel
# regions; starting and joining the worker threads costs ~0.1 ms on two shared cores, so 25
# iterations paid 5-10 ms of synchronisation on the small phantom levels (measured here on
# 4.1k tets: a paper step 2.3 ms on one thread, 8-12 ms on two) while saving little work.
SERIAL_CG_UNKNOWNS = 40_000
# Below this many unknowns (3 per node) a whole step runs its compiled kernels on one thread
# (``ContactModel.step``, ``TissueSimulator.step``): its assembly, element and contact
# kernels are a dozen parallel regions a step besides CG's, each paying the workers' start
# and join for little work. Measured here (`probegym bench contact`, two alternating runs of
# NUMBA_NUM_THREADS=2 and 1, two idle cores), median step two threads -> one: 571 tets (417
# unknowns) paper prescribed 1.75 / 1.59 -> 0.92 / 0.90 ms, paper penalty 2.13 / 1.91 -> 1.29 /
# 1.24, robust LM 3.41 / 3.26 -> 2.44 / 2.23 (28-48 % less for every FE method and mode);
# 1,303 tets 16-40 % less, 2,549 tets 5-26 %; 4,141 tets (2,406) paper penalty 4.12 / 4.19 ->
# 3.78 / 3.66, robust penalty 7.86 / 7.95 -> 6.98 / 6.98, the others within the noise; from
# 6,966 tets mixed (robust LM 12.6 / 13.3 -> 14.8 / 14.1), and at 12,971 and 26,854 one thread
# is 10-40 % slower.
SERIAL_STEP_UNKNOWNS = 3_000


def _threads_for(unknowns: int) -> contextlib.AbstractContextManager[None]:
    """CG's kernels on one thread below :data:`SERIAL_CG_UNKNOWNS`."""
    return one_thread_below(unknowns, SERIAL_CG_UNKNOWNS)


def _factor_pcg(
    system: ConstrainedSystem,
    preconditioner: Factorization,
    x: NDArray[np.float64],
    max_iterations: int,
    tolerance: float,
    filled_blocks: Callable[[], _NodeBlocks | None] = lambda: None,
) -> tuple[int, float]:
    """CG preconditioned by an (older) factorisation; constrained dofs stay fixed.

    The preconditioner may be a single-precision factorisation, whose solves are not exactly
    a symmetric operator: the flexible (Polak-Ribiere) beta keeps CG converging regardless.
    The residual is checked before each preconditioner solve, so a converged CG never pays
    for one more. ``filled_blocks`` gives the matrix's node blocks holding its values (None
    if it has none), asked for at the first product only: block products cost a third of
    CSR ones, and a solve that needs no product needs no filling.
    """
    matrix, constrained = system.matrix, system.constrained
    indptr, indices, data = matrix.indptr, matrix.indices, matrix.data
    b_square = _free_square_norm(system.rhs, constrained)
    b_norm = math.sqrt(b_square) or 1.0
    upper_ptr, upper_cols, upper, bounds, partial = _NO_BLOCKS
    ap = np.empty_like(x)
    if _free_entries_zero(x, constrained):
        # x = 0 at the unknowns and the known columns eliminated: r = b there, without a
        # product with the whole matrix (0.1 ms at 4,126 tets, three solves a robust step).
        r = np.where(constrained, 0.0, system.rhs)
        r_square = b_square
    else:
        blocks = filled_blocks()
        if blocks is not None:
            upper_ptr, upper_cols, upper, bounds, partial = blocks.arguments()
        _product(indptr, indices, data, upper_ptr, upper_cols, upper, bounds, partial, x, ap)
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
        if iterations == 0 and upper_ptr is _NO_BLOCKS[0]:
            blocks = filled_blocks()
            if blocks is not None:
                upper_ptr, upper_cols, upper, bounds, partial = blocks.arguments()
        pap = _product(indptr, indices, data, upper_ptr, upper_cols, upper, bounds, partial, p, ap)
        if pap <= 0.0 or not math.isfinite(pap):
            break
        r_square = _cg_update(x, r, r_old, p, ap, rz / pap, constrained)
        iterations += 1
        residual = math.sqrt(r_square) / b_norm
    return iterations, residual


def _same_buffer(kept: NDArray, other: NDArray) -> bool:
    """``other`` is ``kept`` or a view of all of its memory (scipy wraps a matrix built from
    another's index arrays in new array objects). ``kept`` is held by the caller, so its
    memory cannot have been reused by another array."""
    return kept is other or (
        kept.ctypes.data == other.ctypes.data
        and kept.shape == other.shape
        and kept.dtype == other.dtype
    )


def _start(
    system: ConstrainedSystem, initial_guess: NDArray[np.float64] | None
) -> NDArray[np.float64]:
    if initial_guess is None:
        x = np.zeros_like(system.rhs)
    else:
        x = np.array(initial_guess, dtype=np.float64)
    x[system.constrained] = system.values[system.constrained]
    return x


def _with_seconds(report: SolveReport, seconds: float) -> SolveReport:
    return SolveReport(
        report.iterations,
        report.relative_residual,
        report.converged,
        report.factorized,
        report.indefinite,
        seconds,
    )
