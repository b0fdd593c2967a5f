"""``paper`` mode's step: the three phases of Tagliabue et al. 2020, section 2.1.2, as written.

1. free motion: the step's linear system (eq. 8) solved with lambda = 0, exactly (the paper
   used Pardiso's direct solver);
2. collision detection at the free positions: the constraint Jacobian H (one row per
   collision-surface point within the alarm distance: the probe's normal times the point's
   barycentric embedding) and the free gaps delta_free;
3. collision response: compliance W = H A^-1 H^T, projected Gauss-Seidel on Signorini's
   conditions delta = delta_free + h^2 W lambda >= 0, lambda >= 0, delta . lambda = 0
   (eq. 10, with lambda a force in newtons, so the impulse per step is h lambda),
   warm-started from the previous step's forces; then the correction
   dv = dv_free + A^-1 H^T h lambda (eq. 11).

A is factorised every step, as the paper did (SOFA's ``FreeMotionAnimationLoop`` with
``LinearSolverConstraintCorrection``). Robust mode's kept factorisation was tried here and
left: what it saves in factorisations comes back as refreshes and triangular solves, for a
step about a quarter faster, still an order of magnitude above paper penalty's. One
linearised response freezes the normals of a curved probe, which leaves gaps of order
(tangential motion)^2 / radius; robust mode iterates them away.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from tissue.contact.fe_model import constraint_rows, transpose_product
from tissue.contact.lagrange.response import ContactResponses
from tissue.contact.lagrange.state import solve_report
from tissue.status import StepStatus


class PaperSteps(ContactResponses):
    """``paper`` mode's linearised step with one exact contact response."""

    def _paper_step(self, h: float):
        """One step of ``h`` [s]: (status, contact points, forces on the probe, diagnostics)."""
        sim = self.sim
        start = time.perf_counter()
        integrator = sim.integrator
        x, v = sim.positions.copy(), sim.velocities.copy()
        dofs, targets = sim.constraints()
        linear = integrator.paper_system(x, v, h, dofs, targets)
        try:
            factorization, indefinite = integrator.solver.factorize(linear.system)
            free_dv = np.asarray(factorization.solve(linear.system.rhs)).reshape(-1)
        except Exception:  # noqa: BLE001 - a failed factorisation is a status
            return StepStatus.SOLVER_FAILED, np.zeros((0, 3)), np.zeros((0, 3)), {}
        free_dv = np.where(linear.system.constrained, linear.system.values, free_dv)
        # Dynamic steps solve for dv (x' = x + h (v + dv), the impulse per step is h lambda);
        # quasi-static ones for dx directly (x' = x + dx, lambda itself balances).
        quasi = integrator.config.quasi_static
        free_x = x + free_dv.reshape(-1, 3) if quasi else x + h * (v + free_dv.reshape(-1, 3))
        impulse_per_force = 1.0 if quasi else h
        contacts = self._detect_contacts(free_x)
        forces = np.zeros(0)
        dv = free_dv
        response: dict[str, Any] = {}
        if contacts.count:
            rows = constraint_rows(self.surface, contacts, x.size, linear.system.constrained)
            # delta = delta_free + h H dv_corr, dv_corr = A^-1 H^T (h lambda)  =>  scale h^2
            # (quasi-static: delta = delta_free + H A^-1 H^T lambda, scale 1).
            forces, correction, response = self._exact_response(
                factorization,
                rows,
                contacts.distance - self.params.contact_distance_m,
                impulse_per_force**2,
                contacts,
            )
            dv = free_dv + impulse_per_force * correction
            # The multipliers act as extra right-hand side: include them in the reactions.
            linear.rhs[:] = linear.rhs + transpose_product(rows, impulse_per_force * forces)
        outcome = integrator.paper_finish(x, v, h, linear, dv, solve_report(indefinite))
        status = sim.commit(outcome, h, start).status
        points, on_probe = self._finish(contacts, forces)
        diagnostics = {
            "constraints": contacts.count,
            "active": int(np.sum(forces > 0)),
            "min_volume_ratio": outcome.min_volume_ratio,
            **response,
        }
        return status, points, on_probe, diagnostics
