"""A kept factorisation corrected, in capacitance (Woodbury) form, for dofs constrained since.

``reuse`` keeps a factorisation F across steps as CG's preconditioner. When dofs become
constrained after F was computed (prescribed displacement's online node set growing under
the probe), F^-1 is a worse preconditioner by a term of rank |D|, which costs CG about an
iteration per dof; :class:`ConstrainedSince` removes that term exactly, from |D| columns
of F^-1 solved once and kept while F is. The same form handles node frames that have turned
since F (prescribed nodes sliding on the probe). Up to
:data:`~tissue.sim.solvers.limits.MAX_CONSTRAINED_SINCE` dofs; beyond, ``reuse``
refactorises.

Reference: Woodbury's identity; the capacitance-matrix form of a low-rank update of a
factorised matrix (e.g. Hager, "Updating the inverse of a matrix", SIAM Review 31, 1989).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.linalg
from numpy.typing import NDArray

import tissue.sim.solvers as solvers
from tissue.sim.frames import FrameChange
from tissue.sim.solvers.direct_factorization import Factorization
from tissue.sim.solvers.vector_kernels import subtract_columns


class ConstrainedSince:
    """A kept factorisation F corrected for dofs D constrained since it was computed.

    F factorised a matrix in which D were free; the system now holds them fixed (identity
    rows and columns), so F^-1 differs from the wanted inverse by a term of rank |D| and CG
    needs about |D| more iterations. The exact inverse on the other free dofs is the
    capacitance (Woodbury) form

        z = F^-1 r - Y S^-1 Y^T r,  Y = F^-1 E_D,  S = E_D^T F^-1 E_D,

    E_D the unit columns of D: one solve with F per application, plus |D| columns of F^-1
    solved once per dof (cached while F is kept), in the same multi-RHS call as the first
    application after the dof joined. Dofs released since F (identity in F, free now) are
    not corrected: CG absorbs them.

    A system written in other node frames than F's matrix (prescribed nodes sliding on the
    probe: :mod:`tissue.sim.frames`) is preconditioned by G = P F^-1 P^T, P the change of
    coordinates (:class:`~tissue.sim.frames.FrameChange`), corrected in the same form with
    Y = G E_D. A dof d of a node whose frame turned is the direction P^T e_d in F's
    coordinates: its column of Y combines the node's three columns of F^-1 (kept like the
    others, so a frame that turns every step costs no new solves; Y itself is formed again,
    O(n |D|)). Kept factorisations hold the framed nodes' constrained axes free
    (:meth:`~tissue.sim.solvers.constrained_system.ConstrainedSystem.unframed`), so that
    every such constraint is corrected for; a direction F did hold eliminated (too many
    framed constraints, or an indefinite matrix factorised exactly) and the system's frame
    has turned away from is not (as a released dof).

    Args:
        base: F, the kept factorisation.
        size: n, the system's size.

    Attributes:
        columns: the kept columns F^-1 e_d, (n, m) column-major, the first ``count`` used;
            ``slot`` maps a dof d to its column.
    """

    def __init__(self, base: Factorization, size: int) -> None:
        self.base = base
        self.size = size
        self.slot: dict[int, int] = {}
        # Column-major and filled in place: a column's pages are touched only once it is
        # solved, and nothing is copied as columns join (stacking them, up to 146 MB on the
        # finest mesh, took a large share of a step).
        self.columns = np.empty((size, solvers.MAX_CONSTRAINED_SINCE), order="F")
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
        """The corrected preconditioner applied to ``rhs`` (n,), in the system's frames."""
        assert self._wanted is not None
        change = self._change
        if change is not None:
            rhs = change.apply(rhs, transpose=True)
        if self._pending:
            # The new columns and this right-hand side in one multi-RHS call: Pardiso reads
            # the factor once for all of them, which saves one solve in every step whose
            # node set grew.
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
            subtract_columns(response, self.columns, slots.ravel()[used], scaled[used])
            z += change.apply(response)
        else:
            subtract_columns(z, self.columns, self._active_slots, weights)
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
