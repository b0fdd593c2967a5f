"""``direct``: sparse factorisations of symmetric matrices, MKL Pardiso or scipy's SuperLU.

Intel MKL Pardiso (:mod:`tissue.sim.pardiso`: located through ``pypardiso``, which installs
from wheels with pip alone, and called directly) factorises in SPD mode (Cholesky-type), with a
symmetric-indefinite factorisation (Bunch-Kaufman pivoting) as fallback when the matrix is not
positive definite; scipy's SuperLU (an LU that ignores symmetry, slower) stands in where MKL
is unavailable. The same factoriser serves ``reuse``'s kept preconditioner, in single
precision (:meth:`DirectFactorizer.factorize_preconditioner`).
"""

from __future__ import annotations

from typing import Protocol

import numba
import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from tissue.sim.pardiso import (
    PardisoError,
    PardisoFactorization,
    PardisoInstance,
    pardiso_available,
)
from tissue.sim.solvers.settings import DirectBackend
from tissue.threads import parallel_kernel


class Factorization(Protocol):
    """A factorised matrix (n, n) that solves for one right-hand side (n,) or several
    (n, k), returning the solutions in the same shape."""

    def solve(self, rhs: NDArray[np.float64]) -> NDArray[np.float64]: ...


@parallel_kernel
def _gather(source, positions, out):  # pragma: no cover - compiled
    """out[i] = source[positions[i]] (converting to out's type)."""
    for i in numba.prange(positions.shape[0]):
        out[i] = source[positions[i]]


class _SuperLUFactorization:
    """scipy's SuperLU factorisation of a CSR matrix (n, n), where Pardiso is unavailable."""

    def __init__(self, matrix: sp.csr_matrix) -> None:
        import scipy.sparse.linalg as spla

        self._lu = spla.splu(matrix.tocsc(), permc_spec="MMD_AT_PLUS_A")

    def solve(self, rhs: NDArray[np.float64]) -> NDArray[np.float64]:
        """The solution for ``rhs``, (n,) or (n, k)."""
        return self._lu.solve(rhs)


class DirectFactorizer:
    """Factorises symmetric matrices of one fixed sparsity pattern, reusing the analysis.

    With Pardiso, the upper-triangle positions are found once and the symbolic analysis
    (reordering) is computed once per matrix type and precision; each factorisation then
    runs only the numerical phase. A matrix that is not positive definite (a zero or
    negative pivot in the SPD mode) is refactorised in symmetric-indefinite mode
    (Bunch-Kaufman pivoting) instead of failing.

    Rows and columns of eliminated dofs (``constrained``: identity rows and columns, as
    :class:`~tissue.sim.solvers.constrained_system.ConstrainedSystem` leaves them) are handed
    to Pardiso as their diagonal alone, not as the zeros the pattern still holds there, which
    it would otherwise factorise as nonzeros (about a fifth fewer factor nonzeros and a fifth
    less time with the fixed base left out). The dofs so left out are those constrained in
    every matrix factorised since the pattern was analysed (the fixed base, in practice): the
    analysis is redone only when one of them is found free.

    Args:
        backend: ``auto`` (Pardiso where available, else SuperLU), ``pardiso`` or ``superlu``.
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
        :meth:`~tissue.sim.solvers.linear_solver.LinearSolver.analyse`). Nothing to do with
        SuperLU."""
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
