"""``robust`` mode's step: Newton on the nonlinear incremental potential, contact as an LCP.

Each iteration linearises the potential (Newton) and the gaps (contact normals re-detected
at the iterate), solves that linear complementarity problem (:mod:`.response`), and repeats
until the KKT residual (force balance on the free dofs) is below the Newton tolerance and no
point penetrates beyond the contact tolerance. The pieces of one iteration, in order:

1. the accuracy its linear solves need (:meth:`RobustSteps._solve_accuracy`) and the
   tangent it takes (:meth:`RobustSteps._projects`);
2. the Newton system and the free step (:meth:`RobustSteps._linearised_free_step`): the
   exact tangent, completed in quasi-static steps with the contact's own terms
   (:mod:`.tangent`), or the projected (PSD) one where the exact one is not definite;
3. the contact response and the unaugmented forces (:meth:`RobustSteps._responded_step`);
4. the step, halved while it would invert a tet (:meth:`RobustSteps._feasible_trial`);
5. the new iterate: contacts re-detected, KKT residual and penetration
   (:meth:`RobustSteps._next_iterate`), an exact step that does not reduce the residual
   undone (the step then goes on projected, or is retried by its caller);
6. the convergence test (:meth:`RobustSteps._converged`).

Quasi-static steps complete the exact tangent near the solution with the contact terms, so
that Newton converges quadratically where the probe's rounded rim presses. Dynamic steps
with stiffness damping take the exact element tangent from their first iteration (their
Hessian holds M / h^2 + (r_K / h) K_rest beside it), the projected one where that is not
definite or does not reduce the residual. On all but the smallest systems
(:attr:`~LagrangeParams.keep_factorization_unknowns`) a factorisation is kept across
iterations and steps (:mod:`.response`), and a dynamic step's converged matrix serves the
next iteration, or the next step, as a chord.

Limitations: frictionless; Newton takes full steps (no merit function to search on),
shortened only to keep tets from inverting, so a step that does not converge is split or
relaxed by the caller (:mod:`.fallbacks`).
"""

from __future__ import annotations

import math
import time

import numpy as np
from numpy.typing import NDArray

from tissue.contact.fe_model import constraint_rows, transpose_product
from tissue.contact.lagrange.iterate import FreeStep, Iterate, NewtonRun
from tissue.contact.lagrange.response import ContactResponses
from tissue.contact.lagrange.state import solve_report
from tissue.contact.lagrange.tangent import ContactTangent
from tissue.sim.integrator import IncrementalPotential
from tissue.sim.solvers import ConstrainedSystem, vector_norm
from tissue.status import StepStatus

#: A robust Newton step that would invert a tet (the inversion barrier makes its energy
#: infinite) is halved until none inverts, down to this fraction of the step.
_MIN_FEASIBLE_FRACTION = 2.0**-10


class RobustSteps(ContactResponses, ContactTangent):
    """``robust`` mode's Newton-LCP step."""

    def _robust_step(
        self,
        h: float,
        may_retry: bool = False,
        relax_s: float = 0.0,
        exact_first_static: bool = False,
    ):
        """One robust step of ``h`` [s]: (status, contact points, forces on the probe,
        diagnostics).

        ``may_retry``: the caller will retry a step that does not converge (as two halves,
        or relaxed), so a quasi-static step whose exact tangent failed gives up at once
        rather than crawl on the projected one (the halves converge in a few iterations
        where the projected tangent does not in sixty). ``relax_s`` > 0 (quasi-static only):
        a relaxation step of :meth:`_relaxed_step`, a dynamic step from rest with that time
        step [s] that takes no simulated time. ``exact_first_static`` (quasi-static): the
        exact tangent with the contact terms from the first iteration (the static solve
        after a relaxation)."""
        start = time.perf_counter()
        run = self._start_newton(h, may_retry, relax_s, exact_first_static)
        for iterations in range(1, run.limit + 1):
            run.iterations = iterations
            if not self._newton_iteration(run):
                break
        return self._end_robust_step(run, start)

    # ------------------------------------------------------------------ the start

    def _start_newton(
        self, h: float, may_retry: bool, relax_s: float, exact_first_static: bool
    ) -> NewtonRun:
        """The step's potential, its first iterate with the contacts there (their forces the
        warm start's), and the rules its iterations follow."""
        sim = self.sim
        integrator, cfg = sim.integrator, sim.integrator.config
        x, v = sim.positions.copy(), sim.velocities.copy()
        dofs, targets = sim.constraints()
        potential = self._step_potential(x, v, h, dofs, targets, relax_s)
        constrained = potential.constrained
        free = ~constrained
        y, (energy, gradient, scale), handed, started_at_x = self._starting_point(
            potential, x, v, h, relax_s
        )
        contacts = self._detect_contacts(y.reshape(-1, 3))
        rows = constraint_rows(self.surface, contacts, y.size, constrained)
        # The forces of the start, one per contact: what the step reports if it gives up in
        # its first iteration (a retry-able exact tangent found indefinite at once).
        forces = self._warm[contacts.points]
        at = Iterate(y, energy, gradient, scale, contacts, rows, forces, np.inf, 0.0)
        dynamic = not cfg.quasi_static and relax_s == 0.0
        limit = self.params.max_iterations
        if relax_s > 0.0:
            limit = min(limit, self.params.relaxation_iterations)
        return NewtonRun(
            h=h,
            may_retry=may_retry,
            relax_s=relax_s,
            exact_first_static=exact_first_static,
            x=x,
            v=v,
            dofs=dofs,
            targets=targets,
            potential=potential,
            constrained=constrained,
            free=free,
            scale_floor=integrator.config.residual_scale_floor * integrator._force_unit,
            keep=y.size >= self.params.keep_factorization_unknowns,
            dynamic=dynamic,
            # Dynamic steps with stiffness damping try the exact tangent first, as the
            # integrator's do (ImplicitIntegrator._newton): their Hessian adds M / h^2 +
            # (r_K / h) K_rest (5 K_rest at the defaults), which covers what the projection
            # would clamp; the projected tangent is what Newton's first iteration misses by.
            exact_first=dynamic and cfg.rayleigh_stiffness > 0.0,
            contact_terms=bool(cfg.quasi_static) and relax_s == 0.0,
            # A static solve from a relaxed state (``exact_first_static``) is near its
            # solution or nowhere near one: exact from the start, so that a failure costs
            # one try.
            projected_iterations=(
                0 if exact_first_static else self.params.kept_projected_iterations
            ),
            limit=limit,
            handed=handed,
            started_at_x=started_at_x,
            at=at,
            chord=handed,
        )

    def _step_potential(
        self,
        x: NDArray[np.float64],
        v: NDArray[np.float64],
        h: float,
        dofs: NDArray[np.int64],
        targets: NDArray[np.float64],
        relax_s: float,
    ) -> IncrementalPotential:
        """The step's incremental potential; for a relaxation step (``relax_s`` > 0 [s]) the
        inertia about x with that time step and no damping."""
        integrator = self.sim.integrator
        if relax_s > 0.0:
            potential = integrator.incremental_potential(
                x, np.zeros_like(v), relax_s, dofs, targets
            )
            potential.quasi = False  # inertia about x, no damping (built for quasi-static)
        else:
            potential = integrator.incremental_potential(x, v, h, dofs, targets)
        return potential

    def _starting_point(
        self,
        potential: IncrementalPotential,
        x: NDArray[np.float64],
        v: NDArray[np.float64],
        h: float,
        relax_s: float,
    ) -> tuple[
        NDArray[np.float64],
        tuple[float, NDArray[np.float64], float],
        ConstrainedSystem | None,
        bool,
    ]:
        """The first iterate and its evaluation (energy, gradient, scale), the last step's
        matrix when this step takes it as a chord, and whether the step starts at x.

        A dynamic step continuing the last one starts from x + h v + h^2 a, a the last
        step's acceleration, as the integrator's Newton does (fewer Newton and CG
        iterations, the same force). It then takes the last step's matrix for its first
        iteration (:class:`~tissue.sim.integrator.ChordHandOver`), where a factorisation is
        kept: a large saving where the contact set changes little from step to step, none
        where it changes in most. A start that inverts a tet starts from x instead."""
        cfg = self.sim.integrator.config
        y = potential.start()
        constrained = potential.constrained
        evaluated = None
        # A dynamic step with stiffness damping takes the exact tangent first: the start's
        # evaluation assembles it too.
        tangent_first = not cfg.quasi_static and relax_s == 0.0 and cfg.rayleigh_stiffness > 0.0
        guess = self._extrapolated_start(x, v, h) if relax_s == 0.0 else None
        handed = self._chords.take(h, constrained)
        if guess is None or not tangent_first or y.size < self.params.keep_factorization_unknowns:
            handed = None
        if handed is not None:
            tangent_first = False  # the first iteration assembles no tangent
        if guess is not None:
            guess[constrained] = y[constrained]
            evaluated = potential.evaluate(guess, tangent_first)
            if math.isfinite(evaluated[0]):
                y = guess
            else:
                evaluated = None
        if evaluated is None:
            evaluated = potential.evaluate(y, tangent_first)
        energy, gradient, scale = evaluated
        # (A quasi-static step already starts from x.)
        started_at_x = not cfg.quasi_static and not math.isfinite(energy)
        if started_at_x:
            # The inertial prediction x + h v inverts a tet (it can where the probe's face
            # presses near its end): Newton started there may converge inverted. Start from
            # x instead (the constrained dofs where the potential puts them).
            predicted, y = y, x.reshape(-1).copy()
            y[constrained] = predicted[constrained]
            energy, gradient, scale = potential.evaluate(y)
        return y, (energy, gradient, scale), handed, started_at_x

    # ------------------------------------------------------------------ one iteration

    def _newton_iteration(self, run: NewtonRun) -> bool:
        """One Newton-LCP iteration from ``run.at``; False once the step is done (converged,
        failed, or to be retried by the caller)."""
        before = run.at
        tolerance, enough = self._solve_accuracy(run)
        project = self._projects(run)
        if run.iterations > 1 and before.contacts.count:
            self._warm[before.contacts.points] = before.forces  # total forces of the last iterate
        start_forces = self._warm[before.contacts.points]
        try:
            free = self._linearised_free_step(run, project, start_forces, tolerance, enough)
        except Exception:  # noqa: BLE001 - a status, not a crash
            run.status = StepStatus.SOLVER_FAILED
            return False
        if not run.exact_trusted and run.may_retry and run.contact_terms:
            return False  # no definite exact tangent: the caller retries (not converged)
        project = free.project
        forces, step = self._responded_step(run, free, start_forces)
        finite = bool(np.all(np.isfinite(step)) and np.all(np.isfinite(forces)))
        if not finite and not project and (run.contact_terms or run.exact_first):
            # The exact tangent failed numerically (its forces were not finite): drop its
            # factorisation and go on projected, as for an exact step that does not descend.
            self.sim.integrator.solver.forget()
            return self._distrust_exact_tangent(run)
        if not finite:
            run.status = StepStatus.DIVERGED
            return False
        run.exact_iterations += int(not project)
        fraction, trial, evaluated = self._feasible_trial(run.potential, before.y, step)
        if not math.isfinite(evaluated[0]):
            # No feasible fraction: not converged, from the last feasible iterate (the
            # caller splits the step).
            return False
        run.shortened += int(fraction < 1.0)
        # The next iteration of a dynamic step keeps this one's matrix (a chord step): one
        # iteration on (the constrained dofs at their targets) the matrix has barely
        # changed; the residual is still that of the true gradient, and a step needing a
        # third iteration assembles afresh. The same iterations and force, one Hessian and
        # factorisation fewer a step.
        if (
            run.keep
            and (project or run.exact_first)
            and run.dynamic
            and fraction == 1.0
            and not run.chord_step
        ):
            run.chord = free.system
        after = self._next_iterate(run, trial, evaluated, forces)
        if not np.isfinite(after.residual):
            run.status = StepStatus.DIVERGED
            return False
        exact = not project and (run.contact_terms or run.exact_first)
        if exact and after.residual >= before.residual:
            # Near a bifurcation of a deep press (the tissue could slide either way under the
            # frictionless probe) the exact tangent is nearly singular and its full step can
            # jump millimetres; an exact step that does not reduce the KKT residual is
            # undone, and the step is retried (``may_retry``: split or relaxed) or goes on
            # with the projected tangent (and does not reuse this matrix as a chord).
            run.chord = None
            return self._distrust_exact_tangent(run)
        run.at = after
        return not self._converged(run)

    def _distrust_exact_tangent(self, run: NewtonRun) -> bool:
        """Undo an exact step (the iterate stays ``run.at``) and take the projected tangent
        for the rest of the step; False when the caller retries the step instead."""
        run.exact_trusted = False
        run.rejected += 1
        return not (run.may_retry and run.contact_terms)

    def _solve_accuracy(self, run: NewtonRun) -> tuple[float, float]:
        """The relative tolerance of this iteration's linear solves and the absolute residual
        [N] at which they may stop earlier.

        With a kept factorisation the solves are inexact Newton: each to a tenth of the last
        KKT residual, as the integrator's own Newton does, and, as there, never more
        accurately than what brings the KKT residual well under the Newton tolerance: the
        free step and the response solves each get half of the integrator's share (their
        residuals add). The relative tolerance alone asked a steady press's second
        iteration for far more accuracy than its chord step keeps.
        """
        cfg = self.sim.integrator.config
        share = cfg.linear_share_of_tolerance
        tolerance = min(1e-2, max(0.1 * run.at.residual, 1e-10))
        enough = 0.5 * share * cfg.newton_tolerance
        enough *= max(run.at.scale, run.scale_floor)
        return tolerance, enough

    def _projects(self, run: NewtonRun) -> bool:
        """Whether this iteration starts from the projected (PSD) element tangent.

        As the integrator: projected far from the solution, exact near it (projection costs
        quadratic convergence), projected again where that is not definite (W = H A^-1 H^T
        must be positive for PGS). Quasi-static steps complete the exact tangent with the
        contact terms and, with a kept factorisation, take it after
        :attr:`~LagrangeParams.kept_projected_iterations`: with no inertia the projected
        tangent crawls. Dynamic steps take the exact tangent without the contact terms, from
        the first iteration (``exact_first``): with them, a full step can leave the step's
        own solution for another (a tilted press where the tissue creeps sideways under the
        frictionless probe ended on the slid equilibrium, at half the force).
        """
        cfg = self.sim.integrator.config
        far = bool(cfg.project_psd) and run.at.residual > cfg.projection_switch
        if run.exact_first:
            return not run.exact_trusted
        return (
            not run.exact_trusted
            or (far and not (run.exact_first_static and run.contact_terms))
            or (run.keep and (not run.contact_terms or run.iterations <= run.projected_iterations))
        )

    def _linearised_free_step(
        self,
        run: NewtonRun,
        project: bool,
        start_forces: NDArray[np.float64],
        tolerance: float,
        enough: float,
    ) -> FreeStep:
        """The iteration's Newton system and its free step (the last forces as a load where a
        factorisation is kept).

        Unless ``project``, the exact tangent with the contact terms, its augmentation raised
        if that is not definite (:attr:`~LagrangeParams.augmentation_stiffnesses`), then the
        projected tangent; an exact tangent found indefinite is not trusted for the rest of
        the step (and a retry-able quasi-static step gives up at once)."""
        stiffnesses = self.params.augmentation_stiffnesses if run.contact_terms else (0.0,)
        tangents = [None] if project else [*stiffnesses, None]
        free = None
        for attempt, stiffness in enumerate(tangents):
            project = stiffness is None
            if project and attempt and (run.contact_terms or run.exact_first):
                run.exact_trusted = False  # not definite: projected for the rest of the step
                if run.may_retry and run.contact_terms:
                    break
            system, augmented = self._newton_system(run, project, stiffness, start_forces)
            if run.keep:
                free = self._kept_free_step(
                    run, system, augmented, project, attempt, start_forces, tolerance, enough
                )
            else:
                factorization, indefinite = self.sim.integrator.solver.factorize(system)
                free = FreeStep(system, augmented, project, indefinite)
                free.factorization = factorization
            if project or not free.indefinite:
                break
        assert free is not None  # the first attempt is never skipped
        free.project = project
        if not run.keep:
            assert free.factorization is not None
            free_step = np.asarray(free.factorization.solve(free.system.rhs)).reshape(-1)
            free.step = np.where(run.constrained, free.system.values, free_step)
        return free

    def _newton_system(
        self,
        run: NewtonRun,
        project: bool,
        stiffness: float | None,
        start_forces: NDArray[np.float64],
    ) -> tuple[ConstrainedSystem, tuple[NDArray[np.bool_], float] | None]:
        """The Newton system at ``run.at``: the chord when one is kept and fits this tangent,
        else the (projected or exact) Hessian, with the contact terms of ``stiffness`` (0:
        none) added. Returns (system, the augmentation as
        :meth:`~ContactTangent._add_contact_tangent` returns it)."""
        at = run.at
        run.chord_step = run.chord is not None and (project or run.exact_first)
        if run.chord is not None and run.chord_step:
            system = run.chord.with_rhs(-at.gradient)
        else:
            system = run.potential.hessian_system(at.y, -at.gradient, project=project)
        run.chord = None
        run.system = system
        augmented = None
        if stiffness and at.contacts.count:  # 0.0: the exact tangent without them
            augmented = self._add_contact_tangent(system, at.contacts, start_forces, stiffness)
        return system, augmented

    def _kept_free_step(
        self,
        run: NewtonRun,
        system: ConstrainedSystem,
        augmented: tuple[NDArray[np.bool_], float] | None,
        project: bool,
        attempt: int,
        start_forces: NDArray[np.float64],
        tolerance: float,
        enough: float,
    ) -> FreeStep:
        """The free step with the kept factorisation, refreshed for a new kind of tangent:
        W~ = H F^-1 H^T of a projected F misses the exact compliance by more than the contact
        tolerance can see near convergence. (Quasi-static steps turn exact within a step;
        dynamic ones keep the exact F across steps.) The W~ columns the response will likely
        need are solved in the same call."""
        solver = self.sim.integrator.solver
        refreshed = attempt > 0 or (run.contact_terms and not project and not run.exact_iterations)
        if refreshed:
            solver.refresh_kept_factorization(system)
        self._prefetch_compliance(run.at.contacts, start_forces, run.constrained)
        free_step, report, accuracy = self._loaded_solve(
            system, run.at.rows, start_forces, tolerance, enough
        )
        fresh = report.factorized or refreshed
        indefinite = report.indefinite or (refreshed and solver.kept_indefinite)
        return FreeStep(system, augmented, project, indefinite, free_step, None, fresh, accuracy)

    def _responded_step(
        self, run: NewtonRun, free: FreeStep, start_forces: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The contact response to the free step: (forces [N] of the true linearisation, one
        per contact of ``run.at``; the whole step (3N,) [m]).

        With a kept factorisation the Newton iterations of a dynamic step after its first
        take the response under F (:meth:`_kept_response`'s ``under_kept_factor``)."""
        at = run.at
        assert free.step is not None
        if at.contacts.count:
            offset = at.contacts.distance + at.rows @ free.step - self.params.contact_distance_m
            if run.keep:
                forces, correction, response = self._kept_response(
                    free.system,
                    at.rows,
                    offset,
                    at.contacts,
                    free.fresh,
                    free.accuracy,
                    start_forces,
                    under_kept_factor=run.exact_first and run.iterations > 1,
                )
            else:
                assert free.factorization is not None
                forces, correction, response = self._exact_response(
                    free.factorization, at.rows, offset, 1.0, at.contacts
                )
            run.sweeps_total += response["pgs_sweeps"]
            run.rounds += response["response_rounds"]
            step = free.step + correction
            forces = self._unaugmented(forces, at.rows, step, free.augmented)
        else:
            forces = np.zeros(0)
            step = free.step
        return forces, step

    @staticmethod
    def _feasible_trial(
        potential: IncrementalPotential, y: NDArray[np.float64], step: NDArray[np.float64]
    ) -> tuple[float, NDArray[np.float64], tuple[float, NDArray[np.float64], float]]:
        """(fraction, y + fraction step, its evaluation): the step halved until no tet
        inverts, down to :data:`_MIN_FEASIBLE_FRACTION` (the energy is then still infinite).

        Robust mode's inversion barrier makes an inverted tet's energy infinite, but this
        Newton takes full steps and the barrier only acts through the tangent: a step may
        jump past J = 0, where the inverted tet exerts no force, and converge there (a box
        pressed 9-11 mm into a coarse block). The next iteration re-linearises from the
        shortened step."""
        fraction = 1.0
        trial = y + step
        energy, gradient, scale = potential.evaluate(trial)
        while not math.isfinite(energy) and fraction > _MIN_FEASIBLE_FRACTION:
            fraction *= 0.5
            trial = y + fraction * step
            energy, gradient, scale = potential.evaluate(trial)
        return fraction, trial, (energy, gradient, scale)

    def _next_iterate(
        self,
        run: NewtonRun,
        y: NDArray[np.float64],
        evaluated: tuple[float, NDArray[np.float64], float],
        forces: NDArray[np.float64],
    ) -> Iterate:
        """The iterate at ``y`` (evaluated there): contacts re-detected, the ``forces`` [N]
        (one per contact of ``run.at``) carried over to them by surface point, the KKT
        residual and the penetration."""
        energy, gradient, scale = evaluated
        contacts = run.at.contacts
        contacts_new = self._detect_contacts(y.reshape(-1, 3))
        # Carry the forces over to the re-detected contacts (same surface points).
        carried = np.zeros(self.surface.count)
        if contacts.count:
            carried[contacts.points] = forces
        contacts = contacts_new
        rows = constraint_rows(self.surface, contacts, y.size, run.constrained)
        forces = carried[contacts.points]
        kkt = gradient - transpose_product(rows, forces)
        # The integrator's floor on the force scale: a tissue at rest with no load has
        # scale ~ 0, and its round-off gradient must not read as a large relative residual.
        residual = vector_norm(kkt[run.free]) / max(scale, run.scale_floor)
        penetration = float(max(0.0, -(contacts.distance.min() if contacts.count else 0.0)))
        return Iterate(y, energy, gradient, scale, contacts, rows, forces, residual, penetration)

    def _converged(self, run: NewtonRun) -> bool:
        """Whether the step ends at ``run.at`` (setting ``run.status``): converged when the
        KKT residual is below the Newton tolerance and no point penetrates beyond the
        contact tolerance; ended when the penetration stalls (see
        :attr:`~LagrangeParams.stalled_penetration_m`), OK if it is shallow enough."""
        at = run.at
        if at.residual <= self.sim.integrator.config.newton_tolerance:
            if at.penetration <= self.gap_tolerance_m:
                run.status = StepStatus.OK
                return True
            run.stalled = run.stalled + 1 if at.penetration > 0.5 * run.deepest else 0
            run.deepest = min(run.deepest, at.penetration)
            if run.stalled >= self.params.stalled_iterations:
                if at.penetration <= self.params.stalled_penetration_m:
                    run.status = StepStatus.OK
                return True
        return False

    # ------------------------------------------------------------------ the end

    def _end_robust_step(self, run: NewtonRun, start: float):
        """Commit the step's end (``run.at``) and report it; a step that diverged or whose
        solver failed commits nothing and drops the kept factorisation."""
        sim = self.sim
        integrator = sim.integrator
        cfg = integrator.config
        status = run.status
        if status in (StepStatus.DIVERGED, StepStatus.SOLVER_FAILED):
            integrator.solver.forget()
            return status, np.zeros((0, 3)), np.zeros((0, 3)), {"iterations": run.iterations}
        at, x, v, h = run.at, run.x, run.v, run.h
        new_x = at.y.reshape(-1, 3)
        new_v = np.zeros_like(v) if cfg.quasi_static else (new_x - x) / h
        reaction = np.zeros(at.y.size)
        reaction[run.dofs] = (at.gradient - transpose_product(at.rows, at.forces))[run.dofs]
        # The last evaluation was at y (unless an exact step was undone): its elastic energy
        # and smallest det F serve the step's end, which saves an element pass a step.
        elastic = run.potential.last_elastic
        known = elastic[1:] if elastic is not None and elastic[0] is at.y else None
        outcome = integrator._finish(
            x,
            v,
            new_x,
            new_v,
            reaction,
            solve_report(False),
            newton_iterations=run.iterations,
            newton_residual=at.residual,
            known=known,
        )
        if status is StepStatus.NOT_CONVERGED and outcome.status is StepStatus.OK:
            outcome.status = StepStatus.NOT_CONVERGED
        status = sim.commit(outcome, 0.0 if run.relax_s else h, start).status
        continues = status is StepStatus.OK and run.relax_s == 0.0 and not cfg.quasi_static
        self._last_step = (new_x, new_v, v, h) if continues else None
        if continues and run.exact_first and at.y.size >= self.params.keep_factorization_unknowns:
            full_exact = run.exact_iterations == run.iterations and run.shortened == 0
            assert run.system is not None
            self._chords.record(run.system, h, run.handed is not None, run.iterations, full_exact)
        points, on_probe = self._finish(at.contacts, at.forces)
        diagnostics = {
            "constraints": at.contacts.count,
            "active": int(np.sum(at.forces > 0)),
            "iterations": run.iterations,
            "exact_iterations": run.exact_iterations,
            "exact_rejected": run.rejected,
            "shortened_steps": run.shortened,
            "chord_from_last_step": run.handed is not None,
            "started_at_x": run.started_at_x,
            "pgs_sweeps": run.sweeps_total,
            "kkt_residual": at.residual,
            "response_rounds": run.rounds,
            "min_volume_ratio": outcome.min_volume_ratio,
            "relaxation_steps": 0,
            "static_residual": self._static_residual(run),
        }
        return status, points, on_probe, diagnostics

    def _static_residual(self, run: NewtonRun) -> float:
        """The KKT residual of the step's end; for a relaxation step, how far the relaxed
        state is from static equilibrium (no inertia)."""
        if run.relax_s <= 0.0:
            return run.at.residual
        at = run.at
        integrator = self.sim.integrator
        static = integrator.incremental_potential(run.x, run.v, run.h, run.dofs, run.targets)
        _, static_gradient, static_scale = static.evaluate(at.y)
        unbalanced = (static_gradient - transpose_product(at.rows, at.forces))[run.free]
        return vector_norm(unbalanced) / max(static_scale, run.scale_floor)
