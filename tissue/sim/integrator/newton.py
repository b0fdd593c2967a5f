"""``robust`` mode's step: Newton's method on the step's incremental potential, with a line
search, PSD-projected tangents far from the solution, chord steps, and a failed step retried
as two half steps, recursively (automatic subdivision)."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from tissue.sim.integrator.core import IntegratorCore
from tissue.sim.integrator.line_search import extrapolated_positions, line_search
from tissue.sim.integrator.outcome import StepOutcome, merge, rank
from tissue.sim.integrator.potential import IncrementalPotential
from tissue.sim.solvers import (
    ConstrainedSystem,
    LinearSolverKind,
    SolveReport,
    dot,
    free_square_norm,
)
from tissue.status import StepStatus


class NewtonSteps(IntegratorCore):
    """``robust`` mode's Newton step and its subdivision."""

    def _robust_step(
        self, x, v, h, dofs, targets, terms, subdivisions_left, frames=None
    ) -> StepOutcome:
        outcome = self._newton(x, v, h, dofs, targets, terms, frames)
        if not outcome.status.is_failure or subdivisions_left == 0:
            return outcome
        # Retry as two half steps, the prescribed targets interpolated linearly.
        start = (x.reshape(-1) if frames is None else frames.to_local(x.reshape(-1)))[dofs]
        middle = start + 0.5 * (targets - start)
        left = subdivisions_left - 1
        first = self._robust_step(x, v, 0.5 * h, dofs, middle, terms, left, frames)
        if first.status in (StepStatus.DIVERGED, StepStatus.SOLVER_FAILED):
            return outcome  # halving found nothing better: the undivided attempt stands
        second = self._robust_step(
            first.positions,
            first.velocities,
            0.5 * h,
            dofs,
            targets,
            terms,
            left,
            frames,
        )
        merged = merge(first, second)
        merged.subdivisions += 1
        return merged if rank(merged) <= rank(outcome) else outcome

    def incremental_potential(
        self, x0, v0, h, dofs, targets, terms=(), frames=None
    ) -> IncrementalPotential:
        """The step's incremental potential (robust mode), for Newton and constrained solvers."""
        return IncrementalPotential(self, x0, v0, h, dofs, targets, terms, frames)

    def _newton(self, x0, v0, h, dofs, targets, terms, frames=None) -> StepOutcome:
        cfg = self.config
        quasi = cfg.quasi_static
        potential = self.incremental_potential(x0, v0, h, dofs, targets, terms, frames)
        free = ~potential.constrained
        evaluate, direction = potential.evaluate, potential.newton_direction

        # Start from the inertial prediction x + h v: for a probe moving steadily the free
        # nodes keep moving much as they did, which saves Newton iterations. Continuing the
        # last step, add its velocity change too (x + h v + h^2 a, a = dv / h_last): about
        # fifty times closer to the solution in a steady compression.
        y = potential.start()
        guess = self._extrapolated_start(x0, v0, h)
        if guess is not None:
            guess = potential.local(guess)
        # See the projection rule in the loop: dynamic steps with stiffness damping take the
        # exact tangent first, so the start's evaluation assembles it too.
        exact_first = not quasi and cfg.rayleigh_stiffness > 0.0
        evaluated = evaluate(guess, exact_first) if guess is not None else None
        if guess is not None and evaluated is not None and _finite(evaluated[0], evaluated[1]):
            y = guess
        else:
            evaluated = evaluate(y, exact_first)
        energy, gradient, scale = evaluated
        # Forces below this are round-off (at rest the residual is pure noise): a fraction of
        # what the stiffest material's moduli exert over the mesh's extent squared.
        scale_floor = cfg.residual_scale_floor * self._force_unit
        total_linear = 0
        worst_linear = 0.0
        factorizations = 0
        relative = math.inf
        history: list[float] = []
        converged = False
        iterations = 0
        # A dynamic step's second iteration keeps the first's matrix (a chord step), as
        # LM's robust steps do (see there): after a full step from the extrapolated start
        # the matrix has barely changed, and the residual stays the true gradient's, so a
        # chord that falls short costs an iteration, not accuracy. Only with a kept
        # factorisation (``reuse``), which solves it without refactorising (measurements:
        # docs/design-decisions.md). At a tight tolerance (1e-6) a chord may cost an
        # iteration where the start was poor (tests/test_integrator.py).
        chord_allowed = exact_first and self.solver.config.kind is LinearSolverKind.REUSE
        chord: ConstrainedSystem | None = None
        while True:
            mismatch = float(np.max(np.abs(targets - y[dofs]))) if dofs.size else 0.0
            relative = math.sqrt(free_square_norm(gradient, ~free)) / max(scale, scale_floor)
            history.append(relative)
            if not (np.isfinite(relative) and math.isfinite(energy)):
                return self._failed(x0, v0, StepStatus.DIVERGED)
            converged = mismatch == 0.0 and relative <= cfg.newton_tolerance
            if converged or iterations == cfg.newton_max_iterations:
                break
            iterations += 1
            # Projected tangents make every direction descend but cost quadratic convergence
            # (the clamped Hessian is not the true one): far from the solution we project,
            # near it we use the exact tangent, falling back to projection whenever the exact
            # one does not give a descent direction.
            # A dynamic step with stiffness damping tries the exact tangent first even far
            # from its solution: its Hessian adds M / h^2 + (r_K / h) K_rest (5 K_rest at the
            # defaults) to the elastic one, which covers what the projection would clamp in
            # all but the most compressed tets, and the fallback below projects where it
            # does not. The projection costs 2.5 x a plain assembly, and skipping it left
            # Newton and CG iterations and forces as they were (docs/design-decisions.md).
            project = bool(cfg.project_psd) and relative > cfg.projection_switch and not exact_first
            # Inexact Newton: solve only as accurately as the current residual deserves, and
            # never beyond what brings the residual well under the Newton tolerance.
            tolerance = min(1e-2, max(0.1 * relative, 1e-10))
            enough = cfg.linear_share_of_tolerance * cfg.newton_tolerance * max(scale, scale_floor)
            chord_step = chord is not None and mismatch == 0.0
            fell_back = False
            try:
                step, report, system = direction(
                    y,
                    gradient,
                    project,
                    tolerance,
                    enough,
                    chord if chord_step else None,
                )
                descends = mismatch > 0.0 or dot(gradient, step) < 0.0
                if chord_step and not descends:  # the chord misled: the Hessian here
                    total_linear += report.iterations
                    factorizations += int(report.factorized)
                    chord_step = False
                    step, report, system = direction(y, gradient, project, tolerance, enough)
                    descends = mismatch > 0.0 or dot(gradient, step) < 0.0
                if cfg.project_psd and not project and (report.indefinite or not descends):
                    total_linear += report.iterations
                    factorizations += int(report.factorized)
                    fell_back = True
                    step, report, system = direction(y, gradient, True, tolerance, enough)
            except Exception:  # noqa: BLE001 - report, don't crash
                return self._failed(x0, v0, StepStatus.SOLVER_FAILED)
            total_linear += report.iterations
            worst_linear = max(worst_linear, report.relative_residual)
            factorizations += int(report.factorized)
            if not np.all(np.isfinite(step)):
                return self._failed(x0, v0, StepStatus.SOLVER_FAILED)
            found = line_search(
                y, step, gradient, mismatch, evaluate, energy, dofs, targets, config=cfg
            )
            if found is None:
                return self._failed(x0, v0, StepStatus.DIVERGED)
            # The next iteration may keep this matrix if this one was assembled here (not a
            # chord, not the projected fallback) and its full step was taken as it is.
            chord = None
            if chord_allowed and not chord_step and not fell_back:
                full = y + step
                if mismatch > 0.0:
                    full[dofs] = targets
                chord = system if np.array_equal(found[0], full) else None
            y, energy, gradient, scale = found
        new_x = potential.world(y).reshape(-1, 3)
        new_v = np.zeros_like(v0) if quasi else (new_x - x0) / h
        # Reaction at constrained dofs: the constraint force balancing the residual there.
        reaction = np.zeros_like(y)
        reaction[dofs] = gradient[dofs]
        reaction = potential.world(reaction)
        report = SolveReport(total_linear, worst_linear, True, factorizations > 0)
        # The last evaluation was at y (the accepted point): its energy and det F serve.
        elastic = potential.last_elastic
        known = elastic[1:] if elastic is not None and elastic[0] is y else None
        outcome = self._finish(
            x0,
            v0,
            new_x,
            new_v,
            reaction,
            report,
            newton_iterations=iterations,
            newton_residual=relative,
            known=known,
        )
        outcome.factorizations = factorizations
        outcome.newton_residuals = history
        if not converged and outcome.status is StepStatus.OK:
            outcome.status = StepStatus.NOT_CONVERGED
        return outcome

    def _extrapolated_start(self, x0, v0, h) -> NDArray[np.float64] | None:
        """The positions :meth:`start_next_step_near` handed over, once; else x + h v + h^2
        (v - v_last) / h_last when (x0, v0) are what the last step returned (equal in value:
        a caller may hand a copy of the state it adopted)."""
        near, self._start_near = self._start_near, None
        if near is not None and not self.config.quasi_static:
            return near
        last = self._last_step
        if last is None or self.config.quasi_static:
            return None
        positions, velocities, previous, last_h = last
        if not (_same(positions, x0) and _same(velocities, v0)):
            return None
        return extrapolated_positions(x0, v0, h, previous, last_h)


def _same(a: NDArray[np.float64], b: NDArray[np.float64]) -> bool:
    """Whether two states are the same: one array, or equal in value."""
    return a is b or (a.shape == b.shape and bool(np.array_equal(a, b)))


def _finite(energy: float, gradient: NDArray[np.float64]) -> bool:
    return math.isfinite(energy) and bool(np.all(np.isfinite(gradient)))
