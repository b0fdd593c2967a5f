"""The systems the solvers solve: symmetric, with known dofs eliminated in place.

Every system here is symmetric, of size n = 3 node_count, with some degrees of freedom
*constrained* (fixed base, prescribed surface nodes). Constrained rows and columns are
eliminated in place: the right-hand side is corrected with their known values and the matrix
gets identity rows and columns there, so the sparsity pattern never changes and a symbolic
factorisation is computed once per mesh.

A system may also declare what changes in low rank from one solve to the next, for ``reuse``
to correct its kept factorisation rather than refactorise: rank-one terms
(:class:`RankOneTerms`, penalty springs) and node frames (:class:`~tissue.sim.frames.NodeFrames`,
prescribed nodes sliding on the probe).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

import tissue.sim.solvers as solvers
from tissue.mesh import node_dofs
from tissue.sim.frames import NodeFrames, find_column
from tissue.sim.solvers.vector_kernels import dot, free_square_norm, spmv
from tissue.threads import parallel_kernel


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


@dataclass(frozen=True)
class RankOneTerms:
    """Part of a system matrix written as sum_i s_i v_i v_i^T, terms that come and go between
    solves (penalty springs: one per contact point), so that a kept factorisation can be
    corrected for them in low rank
    (:class:`~tissue.sim.solvers.rank_one_correction.RankOneSince`).

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
        corrected for,
        :class:`~tissue.sim.solvers.constrained_correction.ConstrainedSince`). The system's
        own when it has no frames, or more framed constraints than such a correction takes
        (:data:`~tissue.sim.solvers.limits.MAX_CONSTRAINED_SINCE`)."""
        if self._framed_entries is None:
            return self.matrix, self.constrained
        positions, values, framed = self._framed_entries
        if np.count_nonzero(framed) > solvers.MAX_CONSTRAINED_SINCE:
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
        spmv(self.matrix.indptr, self.matrix.indices, self.matrix.data, x, ax)
        difference = self.rhs - ax
        denominator = math.sqrt(dot(self.rhs, self.rhs)) or 1.0
        return math.sqrt(dot(difference, difference)) / denominator

    def free_rhs_norm(self) -> float:
        """||b|| over the free dofs."""
        return math.sqrt(free_square_norm(self.rhs, self.constrained))
