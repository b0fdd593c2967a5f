"""What a robust step that does not converge falls back on: halves, then relaxation.

A robust step (:mod:`.newton`) that does not converge, or ends with an inverted tet, is
undone (its Newton iterations still count in the step's diagnostics) and taken as two half
steps with the probe half-way, as the integrator does for the tissue alone
(:meth:`RobustFallbacks._subdivided_robust_step`). A quasi-static step that
still fails at the deepest split has likely reached a limit of the static path, where no
nearby static solution exists; it is then relaxed to rest with the probe held
(:meth:`RobustFallbacks._relaxed_step`). Relaxation is tried only at the deepest split:
relaxing a whole increment from rest is far harder (relaxation steps absorbing a 1 mm
press did not converge at any pseudo time step, where at 1/16 mm they converge in a few
iterations).
"""

from __future__ import annotations

import numpy as np

from tissue.contact.lagrange.newton import RobustSteps
from tissue.sim.solvers import vector_norm
from tissue.status import StepStatus


class RobustFallbacks(RobustSteps):
    """Robust steps split, and quasi-static ones relaxed, where Newton does not converge."""

    def _subdivided_robust_step(self, h: float, depth: int):
        """A robust step of ``h`` [s]; if it does not converge or ends with an inverted tet
        (possible only with the inversion barrier off), the state is restored and two half
        steps are taken with the probe half-way, up to ``max_subdivisions`` deep (as the
        integrator does for the tissue alone). A quasi-static step that still fails there is
        relaxed to rest (:meth:`_relaxed_step`)."""
        sim = self.sim
        before = self._checkpoint()
        end = (self.probe.position_world.copy(), self.probe.quat_wxyz.copy())
        may_split = depth < sim.config.max_subdivisions and self._pose_before is not None
        quasi_static = sim.config.quasi_static
        outcome = self._robust_step(h, may_split or quasi_static)
        failed = outcome[0] in (StepStatus.NOT_CONVERGED, StepStatus.INVERTED)
        # Only at the deepest split: relaxing a whole increment from rest is far harder.
        if failed and quasi_static and not may_split:
            self._restore(before)
            outcome = _with_iterations_of(self._relaxed_step(h), outcome)
            failed = False
        if not failed or not may_split:
            outcome[3]["subdivisions"] = depth
            return outcome
        self._restore(before)
        undone = outcome
        begin = self._pose_before
        assert begin is not None  # may_split
        middle_quat = begin[1] + (end[1] if begin[1] @ end[1] >= 0 else -end[1])
        self.probe.set_pose(0.5 * (begin[0] + end[0]), middle_quat / np.linalg.norm(middle_quat))
        self._pose_before = begin
        first = self._subdivided_robust_step(0.5 * h, depth + 1)
        self._pose_before = (self.probe.position_world.copy(), self.probe.quat_wxyz.copy())
        self.probe.set_pose(*end)
        if first[0] in (StepStatus.DIVERGED, StepStatus.SOLVER_FAILED):
            return _with_iterations_of(first, undone)
        second = self._subdivided_robust_step(0.5 * h, depth + 1)
        second[3]["relaxation_steps"] = second[3].get("relaxation_steps", 0) + first[3].get(
            "relaxation_steps", 0
        )
        return _with_iterations_of(second, undone, first)

    def _relaxed_step(self, h: float):
        """A quasi-static step of ``h`` [s] that did not converge even when split, taken by
        relaxing the tissue to rest with the probe held at its pose.

        Where a deep press reaches a limit of the static path (a contact point on the
        probe's rounded rim pressed harder than the tissue round it can hold: the exact
        tangent, with the rim's curvature term, turns indefinite in the last part of an
        increment and stays so however the increment is split) there is no nearby static
        solution for Newton to converge to: the tissue snaps to another, as it would under
        any dissipative motion. Relaxation steps follow that motion: each is a dynamic step
        from rest (inertia m / tau^2, the velocity dropped after it: a proximal step, which
        descends the energy and cannot stop on an unstable equilibrium), tau starting at the
        tissue's time step and doubling while they converge (pseudo-transient continuation,
        up to :attr:`~LagrangeParams.max_relaxation_time_steps`), quartered when one does
        not. The step ends once one leaves the tissue in static equilibrium to the Newton
        tolerance (diagnostic ``static_residual``), or once the inertial force of the last
        is a small fraction (:attr:`~LagrangeParams.relaxed_inertia_fraction`) of the
        contact load and the static step, solved again from there, converges (each failed
        try divides that fraction by ten). Relaxation steps take no simulated time; the
        step's ``h`` is added at its end (diagnostic ``relaxation_steps``). After
        :attr:`~LagrangeParams.max_relaxation_steps`, or once tau falls below a thousandth
        of the tissue's time step, the step is reported not converged.
        """
        sim = self.sim
        tau = sim.config.tissue_dt
        mass = sim.integrator.mass_dof
        threshold = self.params.relaxed_inertia_fraction
        steps = 0
        outcome = None
        spent = 0  # Newton iterations of the relaxation steps and static tries so far
        for steps in range(1, self.params.max_relaxation_steps + 1):  # noqa: B007
            before = self._checkpoint()
            outcome = self._robust_step(h, relax_s=tau)
            spent += outcome[3].get("iterations", 0)
            if outcome[0] is not StepStatus.OK:
                self._restore(before)
                tau *= 0.25
                if tau < 1e-3 * sim.config.tissue_dt:
                    break
                continue
            if outcome[3]["static_residual"] <= sim.config.newton_tolerance:
                # At rest to the Newton tolerance: a static solution (the step's time is
                # added here: relaxation steps take none).
                sim.set_state(sim.positions, sim.velocities, time_s=sim.time_s + h)
                outcome[3]["relaxation_steps"] = steps
                outcome[3]["iterations"] = spent
                return outcome
            moved = (sim.positions - before[0]).reshape(-1)
            inertia = vector_norm(mass * moved) / tau**2
            if inertia <= threshold * vector_norm(self._warm):
                relaxed = self._checkpoint()
                settled = self._robust_step(h, True, exact_first_static=True)
                spent += settled[3].get("iterations", 0)
                if settled[0] is StepStatus.OK:
                    settled[3]["relaxation_steps"] = steps
                    settled[3]["iterations"] = spent
                    return settled
                self._restore(relaxed)
                threshold *= 0.1  # not yet: relax further before the next try
            tau = min(2.0 * tau, self.params.max_relaxation_time_steps * sim.config.tissue_dt)
        assert outcome is not None
        status = outcome[0] if outcome[0] is not StepStatus.OK else StepStatus.NOT_CONVERGED
        details = {**outcome[3], "relaxation_steps": steps, "iterations": spent}
        return status, outcome[1], outcome[2], details


def _with_iterations_of(outcome, *spent):
    """``outcome`` (a robust step's (status, points, forces, diagnostics)) with the Newton
    iterations of the attempts ``spent`` added to its own: an undone attempt and the halves
    or relaxation that replaced it are all the step's work
    (:attr:`tissue.StepDiagnostics.iterations` counts every re-solve)."""
    outcome[3]["iterations"] = outcome[3].get("iterations", 0) + sum(
        attempt[3].get("iterations", 0) for attempt in spent
    )
    return outcome
