"""Lagrange-multiplier contact (Tagliabue et al. 2020, section 2.1.2; SOFA's
``FreeMotionAnimationLoop`` with a Gauss-Seidel constraint solver and
``LinearSolverConstraintCorrection``).

``paper`` mode follows the three phases as written:

1. free motion: the step's linear system (eq. 8) solved with lambda = 0, by a direct
   factorisation (the paper used Pardiso; so do we);
2. collision detection at the free positions: the constraint Jacobian H (one row per
   collision-surface point within the alarm distance: the probe's normal times the point's
   barycentric embedding) and the free gaps delta_free;
3. collision response: compliance W = H A^-1 H^T from the same factorisation (one solve per
   constraint row, all at once), projected Gauss-Seidel on Signorini's conditions
   delta = delta_free + h^2 W lambda >= 0, lambda >= 0, delta . lambda = 0 (eq. 10, with lambda a
   force in newtons, so the impulse per step is h lambda), warm-started from the previous
   step's forces; then the correction dv = dv_free + A^-1 H^T h lambda (eq. 11).

``robust`` mode solves the same Signorini problem on the nonlinear incremental potential:
each iteration linearises the potential (Newton) and the gaps (contact normals re-detected
at the iterate), solves that linear complementarity problem exactly as above, and repeats
until the KKT residual (force balance on the free dofs) is below the Newton tolerance.

lambda are the contact forces. A small regularisation eps I on W keeps PGS well posed when
several points of a flat face are redundant constraints (background.md).

Limitations: the compliance costs one triangular solve per active constraint; frictionless.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numba
import numpy as np
from numpy.typing import NDArray

from tissue.contact.base import ContactMethod
from tissue.contact.fe_model import Contacts, FEContactModel, constraint_rows, detect_contacts
from tissue.errors import ConfigError
from tissue.integrator import RESIDUAL_SCALE_FLOOR, IntegrationMode
from tissue.solvers import SolveReport
from tissue.status import StepStatus


@dataclass(frozen=True)
class LagrangeParams:
    """Lagrange-multiplier contact settings.

    Attributes:
        alarm_distance_m: points closer than this to the probe become constraints [m]
            (the published scene used 2 mm).
        contact_distance_m: the gap kept between tissue and probe [m] (0: touching).
        pgs_tolerance_m: PGS stops when no gap or force changes by more than this
            (expressed as a gap) [m].
        pgs_max_iterations: PGS sweep cap (1000 as SOFA's default).
        regularization: eps on W's diagonal, relative to its mean diagonal.
        max_iterations: (robust mode) Newton-LCP iterations before giving up.
    """

    alarm_distance_m: float = 0.002
    contact_distance_m: float = 0.0
    pgs_tolerance_m: float = 1e-8
    pgs_max_iterations: int = 1000
    regularization: float = 1e-8
    max_iterations: int = 30

    def __post_init__(self) -> None:
        for name in ("alarm_distance_m", "contact_distance_m", "pgs_tolerance_m"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise ConfigError(f"{name} must be >= 0; got {value!r}")
        if self.alarm_distance_m < self.contact_distance_m:
            raise ConfigError(
                f"alarm_distance_m ({self.alarm_distance_m}) must be >= contact_distance_m "
                f"({self.contact_distance_m})"
            )
        if self.pgs_max_iterations < 1 or self.max_iterations < 1:
            raise ConfigError("pgs_max_iterations and max_iterations must be >= 1")
        if not (np.isfinite(self.regularization) and self.regularization >= 0):
            raise ConfigError(f"regularization must be >= 0; got {self.regularization!r}")


@numba.njit(cache=True)
def projected_gauss_seidel(matrix, offset, force, tolerance, max_iterations):  # pragma: no cover
    """Solve gap = offset + matrix @ force >= 0, force >= 0, gap . force = 0 in place.

    Returns (sweeps, largest change of the last sweep expressed as a gap).
    """
    count = offset.shape[0]
    change = 0.0
    for sweep in range(1, max_iterations + 1):
        change = 0.0
        for i in range(count):
            gap = offset[i]
            for j in range(count):
                gap += matrix[i, j] * force[j]
            new = force[i] - gap / matrix[i, i]
            if new < 0.0:
                new = 0.0
            delta = abs(new - force[i]) * matrix[i, i]
            if delta > change:
                change = delta
            force[i] = new
        if change <= tolerance:
            return sweep, change
    return max_iterations, change


class LagrangeContact(FEContactModel):
    """Frictionless contact as constraints, solved for their Lagrange multipliers."""

    method = ContactMethod.LM

    params_type = LagrangeParams
    params: LagrangeParams

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        # Warm start: last forces by surface point.
        self._warm = np.zeros(self.surface.count)
        # The probe pose of the last step (a failed robust step is retried from it).
        self._pose_before: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None

    def _reset_tissue(self) -> None:
        super()._reset_tissue()
        self._warm = np.zeros(self.surface.count)
        self._pose_before = None

    def _advance(
        self,
    ) -> tuple[StepStatus, NDArray[np.float64], NDArray[np.float64], dict[str, Any]]:
        if self.sim.config.mode is IntegrationMode.PAPER:
            outcome = self._paper_step()
        else:
            outcome = self._subdivided_robust_step(self.sim.config.tissue_dt, 0)
        self._pose_before = (self.probe.position_world.copy(), self.probe.quat_wxyz.copy())
        return outcome

    def _subdivided_robust_step(self, h: float, depth: int):
        """A robust step of ``h`` [s]; if it does not converge, the state is restored and
        two half steps are taken with the probe half-way, up to ``max_subdivisions`` deep
        (as the integrator does for the tissue alone)."""
        sim = self.sim
        x0, v0, t0 = sim.positions.copy(), sim.velocities.copy(), sim.time_s
        warm0 = self._warm.copy()
        end = (self.probe.position_world.copy(), self.probe.quat_wxyz.copy())
        outcome = self._robust_step(h)
        if (
            outcome[0] is not StepStatus.NOT_CONVERGED
            or depth >= sim.config.max_subdivisions
            or self._pose_before is None
        ):
            outcome[3]["subdivisions"] = depth
            return outcome
        sim.set_state(x0, v0, time_s=t0)
        self._warm[:] = warm0
        begin = self._pose_before
        middle_quat = begin[1] + (end[1] if begin[1] @ end[1] >= 0 else -end[1])
        self.probe.set_pose(0.5 * (begin[0] + end[0]), middle_quat / np.linalg.norm(middle_quat))
        self._pose_before = begin
        first = self._subdivided_robust_step(0.5 * h, depth + 1)
        self._pose_before = (self.probe.position_world.copy(), self.probe.quat_wxyz.copy())
        self.probe.set_pose(*end)
        if first[0] in (StepStatus.DIVERGED, StepStatus.SOLVER_FAILED):
            return first
        return self._subdivided_robust_step(0.5 * h, depth + 1)

    # ------------------------------------------------------------------ shared

    def _solve_lcp(
        self, factorization, rows, gaps: NDArray[np.float64], scale: float, contacts: Contacts
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], int, float]:
        """Forces lambda [N] with gaps + scale * W lambda complementary; and A^-1 H^T."""
        dense_rows = rows.toarray()
        compliance_columns = factorization.solve(np.asfortranarray(dense_rows.T))
        compliance_columns = np.asarray(compliance_columns).reshape(rows.shape[1], -1)
        compliance = scale * (rows @ compliance_columns)
        compliance = 0.5 * (compliance + compliance.T)
        diagonal = np.diag(compliance)
        epsilon = self.params.regularization * (float(diagonal.mean()) if diagonal.size else 0.0)
        compliance[np.diag_indices_from(compliance)] += max(epsilon, 1e-300)
        forces = self._warm[contacts.points].copy()
        sweeps, change = projected_gauss_seidel(
            compliance,
            gaps - self.params.contact_distance_m,
            forces,
            self.params.pgs_tolerance_m,
            self.params.pgs_max_iterations,
        )
        return forces, compliance_columns, int(sweeps), float(change)

    def _finish(
        self, contacts: Contacts, forces: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Keep the forces for the next warm start; contact points and forces on the probe."""
        self._warm[:] = 0.0
        self._warm[contacts.points] = forces
        positions = self.surface.positions(self.sim.positions)[contacts.points]
        active = forces > 0.0
        if not np.any(active):
            return np.zeros((0, 3)), np.zeros((0, 3))
        _, normal = self.probe.signed_distance_world(positions[active])
        return positions[active], -forces[active, None] * normal

    # ------------------------------------------------------------------ paper

    def _paper_step(self):
        sim, h = self.sim, self.sim.config.tissue_dt
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
        contacts = detect_contacts(self.surface, free_x, self.probe, self.params.alarm_distance_m)
        sweeps, change = 0, 0.0
        forces = np.zeros(0)
        dv = free_dv
        if contacts.count:
            rows = constraint_rows(self.surface, contacts, x.size, linear.system.constrained)
            # delta = delta_free + h H dv_corr, dv_corr = A^-1 H^T (h lambda)  =>  scale h^2
            # (quasi-static: delta = delta_free + H A^-1 H^T lambda, scale 1).
            forces, columns, sweeps, change = self._solve_lcp(
                factorization, rows, contacts.distance, impulse_per_force**2, contacts
            )
            dv = free_dv + columns @ (impulse_per_force * forces)
            # The multipliers act as extra right-hand side: include them in the reactions.
            linear.rhs[:] = linear.rhs + rows.T @ (impulse_per_force * forces)
        report = _report(indefinite)
        outcome = integrator.paper_finish(x, v, h, linear, dv, report)
        status = sim.commit(outcome, h, start).status
        points, on_probe = self._finish(contacts, forces)
        diagnostics = {
            "constraints": contacts.count,
            "active": int(np.sum(forces > 0)),
            "pgs_sweeps": sweeps,
            "pgs_change_m": change,
            "min_volume_ratio": outcome.min_volume_ratio,
        }
        return status, points, on_probe, diagnostics

    # ------------------------------------------------------------------ robust

    def _robust_step(self, h: float):
        sim = self.sim
        start = time.perf_counter()
        integrator, cfg = sim.integrator, sim.integrator.config
        x, v = sim.positions.copy(), sim.velocities.copy()
        dofs, targets = sim.constraints()
        potential = integrator.incremental_potential(x, v, h, dofs, targets)
        y = potential.start()
        constrained = potential.constrained
        free = ~constrained
        energy, gradient, scale = potential.evaluate(y)
        forces = np.zeros(0)
        contacts = detect_contacts(
            self.surface, y.reshape(-1, 3), self.probe, self.params.alarm_distance_m
        )
        rows = constraint_rows(self.surface, contacts, y.size, constrained)
        scale_floor = RESIDUAL_SCALE_FLOOR * integrator._force_unit
        status = StepStatus.NOT_CONVERGED
        iterations, sweeps_total = 0, 0
        residual = np.inf
        for iterations in range(1, self.params.max_iterations + 1):  # noqa: B007
            system = potential.hessian_system(y, -gradient, project=True)
            try:
                factorization, _ = integrator.solver.factorize(system)
                free_step = np.asarray(factorization.solve(system.rhs)).reshape(-1)
            except Exception:  # noqa: BLE001 - a status, not a crash
                status = StepStatus.SOLVER_FAILED
                break
            free_step = np.where(constrained, system.values, free_step)
            if contacts.count:
                gaps = contacts.distance + rows @ free_step
                if iterations > 1:
                    self._warm[contacts.points] = forces  # total forces of the last iterate
                forces, columns, sweeps, _ = self._solve_lcp(
                    factorization, rows, gaps, 1.0, contacts
                )
                sweeps_total += sweeps
                step = free_step + columns @ forces
            else:
                forces = np.zeros(0)
                step = free_step
            if not np.all(np.isfinite(step)):
                status = StepStatus.DIVERGED
                break
            y = y + step
            energy, gradient, scale = potential.evaluate(y)
            contacts_new = detect_contacts(
                self.surface, y.reshape(-1, 3), self.probe, self.params.alarm_distance_m
            )
            # Carry the forces over to the re-detected contacts (same surface points).
            carried = np.zeros(self.surface.count)
            if contacts.count:
                carried[contacts.points] = forces
            contacts = contacts_new
            rows = constraint_rows(self.surface, contacts, y.size, constrained)
            forces = carried[contacts.points]
            kkt = gradient - rows.T @ forces
            # The integrator's floor on the force scale: a tissue at rest with no load has
            # scale ~ 0, and its round-off gradient must not read as a large relative residual.
            residual = float(np.linalg.norm(kkt[free])) / max(scale, scale_floor)
            penetration = float(max(0.0, -(contacts.distance.min() if contacts.count else 0.0)))
            if not np.isfinite(residual):
                status = StepStatus.DIVERGED
                break
            if (
                residual <= cfg.newton_tolerance
                and penetration <= 10 * self.params.pgs_tolerance_m + 1e-9
            ):
                status = StepStatus.OK
                break
        if status in (StepStatus.DIVERGED, StepStatus.SOLVER_FAILED):
            integrator.solver.forget()
            return status, np.zeros((0, 3)), np.zeros((0, 3)), {"iterations": iterations}
        new_x = y.reshape(-1, 3)
        new_v = np.zeros_like(v) if cfg.quasi_static else (new_x - x) / h
        reaction = np.zeros(y.size)
        reaction[dofs] = (gradient - rows.T @ forces)[dofs]
        outcome = integrator._finish(
            x,
            v,
            new_x,
            new_v,
            reaction,
            _report(False),
            newton_iterations=iterations,
            newton_residual=residual,
        )
        if status is StepStatus.NOT_CONVERGED and outcome.status is StepStatus.OK:
            outcome.status = StepStatus.NOT_CONVERGED
        status = sim.commit(outcome, h, start).status
        points, on_probe = self._finish(contacts, forces)
        diagnostics = {
            "constraints": contacts.count,
            "active": int(np.sum(forces > 0)),
            "iterations": iterations,
            "pgs_sweeps": sweeps_total,
            "kkt_residual": residual,
            "min_volume_ratio": outcome.min_volume_ratio,
        }
        return status, points, on_probe, diagnostics


def _report(indefinite: bool) -> SolveReport:
    """What a direct solve did, for the integrator's bookkeeping."""
    return SolveReport(0, 0.0, True, True, indefinite)
