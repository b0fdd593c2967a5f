"""The contact response: the forces that make the free step's gaps complementary.

Given a free step (the step's linear system solved with the contact forces fixed), the
response solves Signorini's conditions delta = delta_free + s W lambda >= 0, lambda >= 0,
delta . lambda = 0 for the forces lambda [N], with W = H A^-1 H^T the compliance of the
constraints H (Tagliabue et al. 2020, eq. 10; s = h^2 for a dynamic step's impulses, 1 for a
quasi-static step), and corrects the step by A^-1 H^T lambda (eq. 11). Two ways:

- :meth:`ContactResponses._exact_response`: W from a factorisation of A itself, as SOFA's
  ``LinearSolverConstraintCorrection`` (``paper`` mode, and ``robust`` mode on small
  systems). W is built from batches of columns A^-1 H^T, never all held at once (thousands
  of constraints on a fine mesh would take GBs).
- :meth:`ContactResponses._kept_response`: robust mode on larger systems keeps a
  single-precision factorisation F of an older matrix across Newton iterations and steps.
  Solves with A are CG preconditioned by F (``reuse`` solves, F refreshed when CG stalls),
  to the inexact-Newton tolerance and no further than the Newton tolerance needs;
  W~ = H F^-1 H^T is a submatrix of entries between surface points cached for F
  (:class:`~tissue.contact.compliance.KeptCompliance`: a point costs a column F^-1 H_p^T the
  first time it is seen under F, and again only once its contact normal has turned; the
  columns a Newton iteration will likely need are solved beside its free step's first
  solve, :meth:`ContactResponses._prefetch_compliance`). The response is iterated to the
  exact W: lambda' = LCP(W~, gaps(lambda) - W~ lambda), the gaps evaluated with A; with
  F = A one round is exact, and F is refreshed when a few rounds do not bring the gaps
  within the contact tolerance of the prediction. The free step carries the last forces as
  a load (:meth:`ContactResponses._loaded_solve`), so W~'s error acts only on their change,
  which takes fewer rounds and far fewer factorisations.

A small regularisation eps I on W keeps PGS well posed when several points of a flat face
are redundant constraints (background.md). Limitation: frictionless (normal forces only).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from tissue.contact.compliance import COLUMN_BATCH
from tissue.contact.fe_model import Contacts, dense_transpose, transpose_product
from tissue.contact.lagrange.pgs import projected_gauss_seidel
from tissue.contact.lagrange.state import LagrangeState
from tissue.sim.integrator import floored_tolerance
from tissue.sim.pardiso import PardisoFactorization
from tissue.sim.solvers import ConstrainedSystem, Factorization, LinearSolverKind, SolveReport


class ContactResponses(LagrangeState):
    """The contact LCP and its response, with a factorisation of A or a kept one."""

    def _lcp(
        self, compliance: NDArray[np.float64], offset: NDArray[np.float64], guess
    ) -> tuple[NDArray[np.float64], int]:
        """PGS on compliance (symmetrised, regularised) from ``guess``: (forces, sweeps)."""
        compliance = 0.5 * (compliance + compliance.T)
        diagonal = compliance.diagonal()
        epsilon = self.params.regularization * (float(diagonal.mean()) if diagonal.size else 0.0)
        compliance.flat[:: compliance.shape[0] + 1] += max(epsilon, 1e-300)  # the diagonal
        forces = np.array(guess, dtype=np.float64)
        sweeps, _ = projected_gauss_seidel(
            compliance, offset, forces, self.params.pgs_tolerance_m, self.params.pgs_max_iterations
        )
        return forces, int(sweeps)

    def _exact_response(
        self,
        factorization: Factorization,
        rows: sp.csr_matrix,
        offset: NDArray[np.float64],
        scale: float,
        contacts: Contacts,
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], dict[str, Any]]:
        """Forces lambda [N] with offset + scale W lambda complementary (eq. 10), W = H A^-1 H^T
        from ``factorization`` (of A itself), and c = A^-1 H^T lambda (eq. 11).

        W is built from batches of columns A^-1 H^T, never all held at once (thousands of
        constraints on a fine mesh would take GBs); c is those columns times lambda when they
        fit in one batch, else one more solve.
        """
        count = contacts.count
        if (
            isinstance(factorization, PardisoFactorization)
            and factorization.is_cholesky
            and count <= COLUMN_BATCH
        ):
            # As SOFA's LinearSolverConstraintCorrection: one forward substitution per
            # constraint row, Y = L^-1 H^T, then W = Y^T Y (A = L L^T), and the correction
            # A^-1 H^T lambda = L^-T (Y lambda) by one backward substitution.
            halves = factorization.forward(dense_transpose(rows))
            halves = halves.reshape(-1, count)
            guess = self._warm[contacts.points]
            forces, sweeps = self._lcp(scale * (halves.T @ halves), offset, guess)
            correction = factorization.backward(halves @ forces).reshape(-1)
            return forces, correction, {"pgs_sweeps": sweeps, "response_rounds": 1}
        compliance = np.empty((count, count))
        columns = np.zeros((rows.shape[1], 0))
        for start in range(0, count, COLUMN_BATCH):
            stop = min(count, start + COLUMN_BATCH)
            block = dense_transpose(rows[start:stop])
            columns = np.asarray(factorization.solve(block)).reshape(rows.shape[1], -1)
            compliance[:, start:stop] = rows @ columns
        forces, sweeps = self._lcp(scale * compliance, offset, self._warm[contacts.points])
        if count <= COLUMN_BATCH:
            correction = columns @ forces
        else:
            spread = transpose_product(rows, forces)
            correction = np.asarray(factorization.solve(spread)).reshape(-1)
        return forces, correction, {"pgs_sweeps": sweeps, "response_rounds": 1}

    def _kept_response(
        self,
        system: ConstrainedSystem,
        rows: sp.csr_matrix,
        offset: NDArray[np.float64],
        contacts: Contacts,
        fresh: bool,
        accuracy: float,
        start: NDArray[np.float64],
        under_kept_factor: bool = False,
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], dict[str, Any]]:
        """As :meth:`_exact_response` (quasi-static scale 1) with a kept factorisation F of
        an older matrix than ``system``'s A, starting from forces already applied.

        ``offset`` are the exact gaps with the forces ``start`` [N] already acting (the free
        step was solved with them as a load); the returned correction is the response to the
        change of the forces only. A^-1 is applied by ``reuse`` solves (CG preconditioned by
        F, to a residual of ``accuracy`` [N] over the free dofs); W~ = H F^-1 H^T comes from
        the compliance cache. Each round solves the LCP with W~ about the exact gaps of the
        current forces, lambda' = LCP(W~, gaps(lambda) - W~ lambda), whose fixed point is the
        exact solution; with F = A (``fresh``) the first round is exact. Its prediction
        misses the exact gaps by (W - W~)(lambda' - lambda): starting from the forces of the
        last iterate (or step) keeps that small. It stops once the exact gaps of the new
        forces are within the contact tolerance (:attr:`gap_tolerance_m`) of W~'s
        prediction; if they miss in ``max_response_iterations`` rounds, F is refactorised
        and one more (exact) round is taken.

        ``under_kept_factor``: take the response under F, F^-1 H^T dlambda from W~'s kept
        columns, as it is (no solve with A, one round unless points join). For the Newton
        iterations of a dynamic step after its first: the forces change little there, so F's
        error on their response is small, and the next KKT residual (exact gradient, gaps
        re-detected) judges the iterate anyway: a response short of A's costs an iteration
        now and then, not accuracy, and saves a solve every iteration.

        Constraints that carry no force and lie farther than
        :attr:`~LagrangeParams.lazy_gap_m` from the probe after the free step are left out of
        the LCP (no column of W~ is solved for them) until a round's exact gaps, which every
        round computes for all constraints, bring one within that distance; it then joins
        and the round is repeated. A left-out point ends with no force and a positive gap,
        which is its complementarity condition, so the solution is the full LCP's.
        """
        solver = self.sim.integrator.solver
        lazy_gap_m = self.params.lazy_gap_m
        forces = start.copy()
        correction = np.zeros(rows.shape[1])
        gaps = offset.copy()
        guess = start.copy()
        taking = (offset <= lazy_gap_m) | (start > 0.0)
        sweeps_total, rounds, missed = 0, 0, 0
        # With every constraint left out (none near, none pressing) the response is none.
        converged = not np.any(taking)
        limit = self.params.max_response_iterations
        # Joining points may each ask for a round more; the cap keeps a response finite.
        while not converged and rounds < 2 * (limit + 1):
            if missed >= limit and not fresh:
                solver.refresh_kept_factorization(system)
                fresh = True
            rounds += 1
            factorization = solver.kept_factorization
            assert factorization is not None
            chosen = np.flatnonzero(taking)
            compliance = self._compliance.matrix(
                factorization, contacts.points[chosen], contacts.normal[chosen], system.constrained
            )
            current = forces[chosen]
            new, sweeps = self._lcp(compliance, gaps[chosen] - compliance @ current, guess[chosen])
            sweeps_total += sweeps
            predicted = gaps[chosen] + compliance @ (new - current)
            delta = np.zeros_like(forces)
            delta[chosen] = new - current
            # Start from the change's response under F, a sum of W~'s kept columns (CG's
            # first iteration would have spent a solve with F on it).
            under_f = self._compliance.response(contacts.points[chosen], new - current)
            increment, taken, refactorized = self._response_increment(
                system, rows, delta, under_f, accuracy, under_kept_factor
            )
            correction += increment
            gaps = gaps + rows @ increment
            forces[chosen] = new
            guess = forces
            mismatch = float(np.max(np.abs(gaps[chosen] - predicted), initial=0.0))
            missed += int(mismatch > self.gap_tolerance_m and not fresh)
            joining = ~taking & (gaps <= lazy_gap_m)
            taking |= joining
            exact = fresh or taken or mismatch <= self.gap_tolerance_m
            converged = exact and not np.any(joining)
            fresh = fresh or refactorized
        if missed >= self.params.refresh_after_missed_rounds and not fresh:
            solver.refresh_kept_factorization(system)
        diagnostics = {"pgs_sweeps": sweeps_total, "response_rounds": rounds}
        return forces, correction, {**diagnostics, "response_converged": converged}

    def _response_increment(
        self,
        system: ConstrainedSystem,
        rows: sp.csr_matrix,
        delta: NDArray[np.float64],
        under_f: NDArray[np.float64] | None,
        accuracy: float,
        under_kept_factor: bool,
    ) -> tuple[NDArray[np.float64], bool, bool]:
        """The step's response to a change ``delta`` [N] of the forces (one per contact):
        ``under_f`` (F^-1 H^T delta, from W~'s columns) as it is when ``under_kept_factor``
        and the cache had it, else A^-1 H^T delta by a ``reuse`` solve started from it.

        The free step's own solve leaves a residual up to ``accuracy`` [N]: the response to
        the forces' change (mostly much smaller than the step's load) needs no smaller one,
        so its relative tolerance is that residual over its own load, capped at
        :attr:`~LagrangeParams.response_tolerance_cap`. Returns (the increment, whether it
        was taken under F, whether the solve refactorised F).
        """
        taken = under_kept_factor and under_f is not None
        refactorized = False
        if taken:
            assert under_f is not None
            increment = under_f
        else:
            cap = self.params.response_tolerance_cap
            change = system.with_rhs(transpose_product(rows, delta))
            load = change.free_rhs_norm()
            relative = cap if load == 0.0 else accuracy / load
            increment, report = self.sim.integrator.solver.solve(
                change,
                initial_guess=under_f,
                tolerance=min(cap, relative),
                kind=LinearSolverKind.REUSE,
            )
            refactorized = report.factorized
        return increment, taken, refactorized

    def _prefetch_compliance(
        self, contacts: Contacts, forces: NDArray[np.float64], constrained: NDArray[np.bool_]
    ) -> None:
        """Hand the kept factorisation's next solve (the free step's first) the W~ columns the
        response will likely need: those of the points pressing or within
        :attr:`~LagrangeParams.prefetch_gap_m` of the probe now (the response takes those
        within :attr:`~LagrangeParams.lazy_gap_m` after the free step, and solves what is
        missing itself)."""
        kept = self.sim.integrator.solver.kept_factorization
        if kept is None or not contacts.count:
            return
        gap = contacts.distance - self.params.contact_distance_m
        near = (gap <= self.params.prefetch_gap_m) | (forces > 0.0)
        if np.any(near):
            self._compliance.prefetch(
                kept, contacts.points[near], contacts.normal[near], constrained
            )

    def _loaded_solve(
        self,
        system: ConstrainedSystem,
        rows: sp.csr_matrix,
        forces: NDArray[np.float64],
        tolerance: float,
        enough: float,
    ) -> tuple[NDArray[np.float64], SolveReport, float]:
        """The free step by a ``reuse`` solve, carrying the last ``forces`` [N] as a load, so
        that the response (whose compliance W~ is approximate) only has to find their change.

        ``tolerance`` is the relative residual asked; ``enough`` [N] an absolute residual
        over the free dofs at which the solve may stop earlier (as the integrator's
        :meth:`~tissue.sim.integrator.IncrementalPotential.newton_direction`). Returns (step,
        report, the absolute residual asked [N]: what the response solves may leave too).
        """
        loaded = system.with_load(transpose_product(rows, forces)) if forces.size else system
        load = loaded.free_rhs_norm()
        tolerance = floored_tolerance(tolerance, enough, load)
        step, report = self.sim.integrator.solver.solve(
            loaded, tolerance=tolerance, kind=LinearSolverKind.REUSE
        )
        return step, report, tolerance * load
