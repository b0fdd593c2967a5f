"""The linear solver of the implicit step: one object that solves constrained systems by
``cg``, ``direct`` or ``reuse`` and keeps what it may reuse across steps.

* ``cg`` (:mod:`~tissue.sim.solvers.jacobi_cg`): Jacobi-preconditioned CG with an iteration
  cap, as in the paper. Fast, but short of convergence on fine meshes (the report says how
  far: ``relative_residual``).
* ``direct`` (:mod:`~tissue.sim.solvers.direct_factorization`): a factorisation per solve.
* ``reuse``: CG preconditioned by the last factorisation (:mod:`~tissue.sim.solvers.factor_cg`),
  kept across steps and refactorised only when CG stalls or when the extra CG iterations
  since add up to what a factorisation costs (a ski-rental rule, counted in iterations so
  that the schedule is deterministic). The kept factorisation is in single precision (half
  the memory and time); CG runs in double precision on the exact matrix, and a system it
  cannot solve gets the double-precision direct solve. It is corrected in capacitance
  (Woodbury) form for what changes in low rank between solves: dofs constrained since it
  was computed (:mod:`~tissue.sim.solvers.constrained_correction`, also for turned node
  frames) and rank-one terms a system declares
  (:mod:`~tissue.sim.solvers.rank_one_correction`).

CG's kernels run on one thread below :data:`~tissue.sim.solvers.limits.SERIAL_CG_UNKNOWNS`
unknowns.
"""

from __future__ import annotations

import contextlib
import math
import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

import tissue.sim.solvers as solvers
from tissue.mesh import node_dofs
from tissue.sim.frames import FrameChange, NodeFrames
from tissue.sim.solvers.constrained_correction import ConstrainedSince
from tissue.sim.solvers.constrained_system import ConstrainedSystem, RankOneTerms
from tissue.sim.solvers.direct_factorization import DirectFactorizer, Factorization
from tissue.sim.solvers.factor_cg import factor_pcg
from tissue.sim.solvers.jacobi_cg import block_inverse_diagonal, inverse_diagonal, jacobi_pcg
from tissue.sim.solvers.node_blocks import NO_BLOCKS, NodeBlocks, matrix_product
from tissue.sim.solvers.rank_one_correction import RankOneSince
from tissue.sim.solvers.settings import LinearSolverConfig, LinearSolverKind
from tissue.threads import one_thread_below


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


class LinearSolver:
    """Solves constrained systems with the configured method, keeping state across steps.

    Args:
        config: the solver's settings (None: the defaults, ``cg``).

    Attributes:
        last_factorization: the factorisation of the last :meth:`factorize` (compliance
            computations read it), or None.
        single_precision_preconditioner: whether kept factorisations are in single
            precision (True; False keeps them in double, twice the memory and time).
        kept_indefinite: whether the last :meth:`refresh_kept_factorization` found its
            matrix not SPD.
    """

    def __init__(self, config: LinearSolverConfig | None = None) -> None:
        self.config = config or LinearSolverConfig()
        self._factorizer: DirectFactorizer | None = None
        self._reuse: Factorization | None = None
        # Dofs constrained when the kept factorisation was computed, and its corrections for
        # dofs constrained since (see ConstrainedSince).
        self._reuse_constrained: NDArray[np.bool_] | None = None
        self._since: ConstrainedSince | None = None
        # The node frames the kept factorisation's matrix was written in.
        self._reuse_frames: NodeFrames | None = None
        # The rank-one terms of the kept factorisation's matrix (None: unknown, so never
        # corrected), and its corrections for the terms changed since (see RankOneSince).
        self._reuse_rank_one: RankOneTerms | None = None
        self._rank_one_since: RankOneSince | None = None
        self.last_factorization: Factorization | None = None
        # Kept factorisations in single precision (see DirectFactorizer.factorize_preconditioner);
        # False keeps them in double (twice the memory and time per triangular solve).
        self.single_precision_preconditioner = True
        # Whether the last refresh_kept_factorization found its matrix not SPD.
        self.kept_indefinite = False
        # (indices, indptr) of the last pattern CG saw, and its node blocks (or None).
        self._blocks: tuple[NDArray, NDArray, NodeBlocks | None] | None = None
        # (those blocks, the values token of the system they were last filled from).
        self._filled_for: tuple[NodeBlocks, object] | None = None
        # Amortised refresh of the kept factorisation (``reuse``, see _solve_reuse): the CG
        # iterations beyond the first of each solve since it was computed, plus what its
        # rank-one corrections' columns cost (in iterations).
        self._excess_iterations = 0.0

    @property
    def factorizer(self) -> DirectFactorizer:
        """The direct factoriser (made on first use, keeping its analysis across steps)."""
        if self._factorizer is None:
            self._factorizer = DirectFactorizer(self.config.direct_backend)
        return self._factorizer

    def analyse(self, matrix: sp.csr_matrix, constrained: NDArray[np.bool_]) -> None:
        """Analyse ``matrix``'s pattern (symmetric, CSR) ahead of the kept factorisation a
        ``reuse`` solver will compute, with ``constrained`` (n,) bool left out: a one-time
        cost (a sizeable part of the first step's) paid when a model is built instead. The
        values are not factorised. Nothing to do for other kinds or without Pardiso."""
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
        if added.size > solvers.MAX_CONSTRAINED_SINCE:
            return None
        if self._since is None:
            self._since = ConstrainedSince(self._reuse, constrained.size)
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
            self._rank_one_since = RankOneSince(kept, system.rhs.size, self._reuse_rank_one)
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
        (:meth:`~.ConstrainedSystem.unframed`) and corrected for in every later solve: a
        turned axis the factor held eliminated costs CG about an iteration each (a sphere
        pressed into a block). Where few turned (a flat face: only the rim's nodes turn) they
        stay eliminated: the corrections' columns, one solve per framed node after each
        factorisation, would cost more than they save.
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
        """Solve ``system``. Returns the full solution (n,), constrained dofs at their
        values, and a report.

        Args:
            system: the system.
            initial_guess: CG's starting point (n,) (None: zeros); ``direct`` ignores it.
            tolerance: the relative residual to reach (None: ``cg_tolerance`` for ``cg``,
                1e-8 for ``reuse``).
            kind: the solver for this solve (None: the configured one).
        """
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

    def _node_blocks(self, matrix: sp.csr_matrix) -> NodeBlocks | None:
        """Node blocks of ``matrix``'s pattern, found once per pattern (the same arrays)."""
        cached = self._blocks
        if (
            cached is None
            or not _same_buffer(cached[0], matrix.indices)
            or not _same_buffer(cached[1], matrix.indptr)
        ):
            cached = (matrix.indices, matrix.indptr, NodeBlocks.of(matrix))
            self._blocks = cached
        return cached[2]

    def product(
        self, matrix: sp.csr_matrix, x: NDArray[np.float64], out: NDArray[np.float64]
    ) -> None:
        """out = A x for a symmetric CSR ``matrix`` (n, n) about to become a system's: through
        the node blocks CG keeps for its pattern (filled from it now: filling and the block
        product together still beat a CSR product), else as CSR. x, out: (n,)."""
        blocks = self._node_blocks(matrix)
        if blocks is not None:
            blocks.fill(matrix.data)
            self._filled_for = None  # holding this matrix's values, not a system's
        matrix_product(matrix, blocks, x, out)

    def _filled_blocks(self, system: ConstrainedSystem) -> NodeBlocks | None:
        """The node blocks of ``system``'s matrix holding its values (filled once for the
        systems sharing its values token: a robust LM step solves three with one matrix,
        and filling them for each would cost more than the products they serve), or None
        if its pattern is not node-blocked."""
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
        if blocks is None or not block_inverse_diagonal(
            blocks.upper_ptr, blocks.upper_cols, blocks.upper, inv_diag
        ):
            inverse_diagonal(matrix.indptr, matrix.indices, matrix.data, inv_diag)
        with _threads_for(x.shape[0]):
            iterations, residual = jacobi_pcg(
                matrix.indptr,
                matrix.indices,
                matrix.data,
                *(blocks.arguments() if blocks is not None else NO_BLOCKS),
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
                iterations, residual = factor_pcg(
                    system, kept, x, cap, tolerance, lambda: self._filled_blocks(system)
                )
            self._excess_iterations += max(iterations - 1, 0)
            if corrected is not None:
                new_columns = corrected.solved_columns - solved_before
                self._excess_iterations += solvers.RANK_ONE_COLUMN_COST * new_columns
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
                iterations, residual = factor_pcg(
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


def _threads_for(unknowns: int) -> contextlib.AbstractContextManager[None]:
    """CG's kernels on one thread below
    :data:`~tissue.sim.solvers.limits.SERIAL_CG_UNKNOWNS` unknowns."""
    return one_thread_below(unknowns, solvers.SERIAL_CG_UNKNOWNS)


def _mostly_turned(old: NodeFrames | None, new: NodeFrames) -> bool:
    """Whether more than half of the nodes framed in ``new`` were framed in ``old`` with
    another frame."""
    change = FrameChange.between(old, new)
    if old is None or change is None:
        return False
    turned = np.intersect1d(np.intersect1d(change.nodes, old.nodes), new.nodes)
    return 2 * turned.size > new.nodes.size


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
    """CG's starting point (n,): ``initial_guess`` (a copy) or zeros, the known dofs at
    their values."""
    if initial_guess is None:
        x = np.zeros_like(system.rhs)
    else:
        x = np.array(initial_guess, dtype=np.float64)
    x[system.constrained] = system.values[system.constrained]
    return x


def _with_seconds(report: SolveReport, seconds: float) -> SolveReport:
    """``report`` with its wall time [s] set."""
    return SolveReport(
        report.iterations,
        report.relative_residual,
        report.converged,
        report.factorized,
        report.indefinite,
        seconds,
    )
