"""A kept factorisation corrected, in capacitance (Woodbury) form, for rank-one terms changed
since it was computed.

The robust penalty method's tangent holds one stiff spring term s v v^T per contact point
(:class:`~tissue.sim.solvers.constrained_system.RankOneTerms`). As points enter and leave
contact between steps, ``reuse``'s kept factorisation F falls behind by a few such terms,
each costing CG about an iteration; :class:`RankOneSince` corrects F for them exactly, from a
column F^-1 v per changed term solved once and kept while F is. Up to
:data:`~tissue.sim.solvers.limits.MAX_RANK_ONE_SINCE` columns; beyond, ``reuse``
refactorises.

Reference: Woodbury's identity for a low-rank update (e.g. Hager, "Updating the inverse of a
matrix", SIAM Review 31, 1989). Limitation: a term whose vector turned by less than 2 degrees
keeps its old column, so the correction is then of a nearby matrix (a preconditioner only).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.linalg
from numpy.typing import NDArray

import tissue.sim.solvers as solvers
from tissue.sim.solvers.constrained_system import RankOneTerms
from tissue.sim.solvers.direct_factorization import Factorization
from tissue.sim.solvers.vector_kernels import subtract_columns

# A term whose vector has turned by less than this (cos 2 degrees) from the one its column was
# solved for keeps that column: the correction is then of a nearby matrix, which only a
# preconditioner's quality notices.
_RANK_ONE_TURN_COS = float(np.cos(np.radians(2.0)))


class RankOneSince:
    """A kept factorisation F corrected for rank-one terms changed since it was computed.

    F factorised A_F, which held the terms T_F = sum s_i v_i v_i^T; the system now holds T
    (penalty springs: points entering and leaving contact, the probe's normal turning at its
    rim). Each change is a stiff rank-one term F knows nothing of, and CG pays about one
    iteration for each: between factorisations it is the springs' change, more than the
    elastic tangent's, that costs CG its iterations. With the change written as
    U S U^T (a column per term added, one per term removed with -s, both for a term that
    changed), the capacitance (Woodbury) form

        z = F^-1 r - Y C^-1 U^T F^-1 r,  Y = F^-1 U,  C = S^-1 + U^T Y,

    inverts F + U S U^T exactly: one solve with F per application, plus a column of Y per
    term, solved once while F is kept (in the same multi-RHS call as the next application)
    and reused as long as the term's vector has not turned by 2 degrees.

    Args:
        base: F, the kept factorisation.
        size: n, the system's size.
        at_factor: the terms T_F of the matrix F factorised.

    Attributes:
        columns: the kept columns F^-1 v, (n, m) column-major, the first ``count`` used.
        solved_columns: how many columns were solved in all (``reuse`` counts their cost).
    """

    def __init__(self, base: Factorization, size: int, at_factor: RankOneTerms) -> None:
        self.base = base
        self.size = size
        self.at_factor = at_factor
        self._factor_order = np.argsort(at_factor.keys, kind="stable")
        self.columns = np.empty((size, solvers.MAX_RANK_ONE_SINCE), order="F")
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
        columns than :data:`~tissue.sim.solvers.limits.MAX_RANK_ONE_SINCE` (refactorise). New
        columns are solved with the next right-hand side (:meth:`solve`). ``constrained`` (n,)
        bool: the system's known dofs, where the terms' vectors count as 0."""
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
        if self.count + len(pending) > solvers.MAX_RANK_ONE_SINCE:
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
        """The corrected preconditioner applied to ``rhs`` (n,)."""
        if self._pending:
            # The new columns and this right-hand side in one multi-RHS call (Pardiso reads
            # the factor once for all of them, as in ConstrainedSince.solve).
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
        subtract_columns(z, self.columns, self._slots, weights)
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


def _turned_less(held: NDArray[np.float64], vectors: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Row by row, whether ``vectors`` point within 2 degrees of ``held`` with the same
    length to 1e-12 (both zero counts as the same), shapes (k, m) -> (k,)."""
    held_square = np.einsum("im,im->i", held, held)
    square = np.einsum("im,im->i", vectors, vectors)
    cross = np.einsum("im,im->i", held, vectors)
    same_length = np.abs(held_square - square) <= 1e-12 * np.maximum(held_square, square)
    aligned = cross >= _RANK_ONE_TURN_COS * np.sqrt(held_square * square)
    return same_length & (aligned | (square == 0.0))
