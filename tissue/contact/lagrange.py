"""Lagrange-multiplier contact (Tagliabue et al. 2020, section 2.1.2; SOFA's
``FreeMotionAnimationLoop`` with a Gauss-Seidel constraint solver and
``LinearSolverConstraintCorrection``).

``paper`` mode follows the three phases as written:

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

``robust`` mode solves the same Signorini problem on the nonlinear incremental potential:
each iteration linearises the potential (Newton) and the gaps (contact normals re-detected
at the iterate), solves that linear complementarity problem as above, and repeats until the
KKT residual (force balance on the free dofs) is below the Newton tolerance. Quasi-static
steps complete the exact tangent near the solution with the contact's own terms (the
probe's curvature and an augmented-Lagrangian term, :meth:`LagrangeContact._add_contact_tangent`),
so that Newton converges quadratically where the probe's rounded rim presses. Dynamic steps
with stiffness damping take the exact element tangent from their first iteration (their
Hessian holds M / h^2 + (r_K / h) K_rest beside it), the projected one where that is not
definite or does not reduce the residual.

``paper`` mode factorises A every step, as the paper did. W is built from batches of
columns A^-1 H^T, never all held at once (thousands of constraints on a fine mesh would
take GBs), and the correction is one more solve. Tried and left: paper steps with robust
mode's kept factorisation (the free solve by CG preconditioned with it to a relative 1e-10,
1e-8 or 1e-6, the response iterated to the exact W as below). On the 26,220-tet apex press
(40 steps, loaded machine, one run each) the median step went from 258 to 196 / 209 / 196
ms (mean 174 / 170 / 147), the force within 5e-5 N: the factorisation it saves (208 ms a
step) comes back as refreshes (0.6 a step at 110 ms) and 12-17 triangular solves a step, and
LM stays an order of magnitude above paper penalty's 16 ms there.

``robust`` mode on all but the smallest systems (at least ``_KEEP_FACTORIZATION_UNKNOWNS``,
every phantom level from 1,363 tets up) keeps a (single-precision) factorisation F across
Newton iterations and steps instead:

- solves with A are CG preconditioned by F (``reuse`` solves; F is refreshed when CG
  stalls), to the inexact-Newton tolerance, and no further than the Newton tolerance needs
  (an absolute floor, as the integrator's Newton has);
- W~ = H F^-1 H^T is a submatrix of entries between surface points cached for F
  (:class:`~tissue.contact.compliance.KeptCompliance`: a point costs a column F^-1 H_p^T
  the first time it is seen under F, and again only once its contact normal has turned;
  the columns a Newton iteration will likely need are solved beside its free step's
  first solve, in the same Pardiso call);
- the response is iterated to the exact W: lambda' = LCP(W~, gaps(lambda) - W~ lambda), the
  gaps evaluated with A; with F = A one round is exact, and F is refreshed when a few
  rounds do not bring the gaps within the contact tolerance of the prediction. In the
  Newton iterations of a dynamic step after its first, the response is taken under F
  (F^-1 H^T dlambda from W~'s columns, no solve with A): the forces change little there,
  and the KKT residual of the next iterate judges it;
- the iteration starts from the last iterate's (or step's) forces, applied as a load in the
  free solve, so W~'s error acts only on their change: at 26,220 tets (apex press, 42
  steps) 1.5 rounds per Newton iteration instead of 2.1, and 3 factorisations instead of 14;
- constraints carrying no force more than ``_LAZY_GAP_M`` (0.5 mm) from the probe after the
  free step stay out of the LCP, and so out of W~, until a round's exact gaps bring them
  within it: the columns of W~ they would cost (mostly points approaching the probe's
  rounded rim, whose normals turn) went 600 -> 246 on the apex press at 176,506 tets (30
  steps), with the same Newton iterations, rounds and force; ``bench contact``'s median
  step, two interleaved runs each, 998 / 1,022 -> 891 / 904 ms there, 73.1 / 75.9 -> 67.4 /
  68.7 ms at 26,854 tets, unchanged from 4,141 tets down.

On the smallest systems refactorising every iteration costs the same or less (see the
constant's comment).

lambda are the contact forces. A small regularisation eps I on W keeps PGS well posed when
several points of a flat face are redundant constraints (background.md).

Limitations: frictionless.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from typing import Any

import numba
import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from tissue.contact.base import ContactMethod
from tissue.contact.compliance import COLUMN_BATCH, KeptCompliance
from tissue.contact.fe_model import (
    Contacts,
    FEContactModel,
    constraint_rows,
    dense_transpose,
    detect_contacts,
    transpose_product,
)
from tissue.errors import ConfigError, TissueInputError
from tissue.sim.frames import find_column
from tissue.sim.integrator import (
    LINEAR_SHARE_OF_TOLERANCE,
    PROJECTION_SWITCH,
    RESIDUAL_SCALE_FLOOR,
    ChordHandOver,
    IntegrationMode,
    extrapolated_positions,
    floored_tolerance,
)
from tissue.sim.pardiso import PardisoFactorization
from tissue.sim.solvers import (
    ConstrainedSystem,
    Factorization,
    LinearSolverKind,
    SolveReport,
    vector_norm,
)
from tissue.status import StepStatus
from tissue.wrench_stiffness import ContactConstraints

# Robust steps on systems with at least this many unknowns keep a factorisation across
# Newton iterations and steps (see the module docstring); smaller ones refactorise every
# iteration. Measured on whole study cells (robust LM, lesion 1 unless said, 30 mm, one run
# each, wall time refactorised / kept, loaded machine): 623 tets (417 unknowns) 2.4 / 2.3 s
# (the bench's apex press: median step 2.8-3.2 / 3.1-3.3 ms); 1,363 (834) 2.8 / 2.6 s; 2,539
# (1,374), lesion 3, 5.2 / 4.2 s; 4,126 (2,406) 12.2 / 6.6 s and lesion 7 9.3 / 5.1 s, the
# tracked points and forces the same to 1e-4 mm and 1e-4 N; earlier, on the phantom before its
# lesions moved: 12,861 (8,970) 60 / 33 s; 26,220 (16,239) 234 / 107 s; 105,004 (59,436) 5.37
# / 1.26 s per step in contact. The threshold sits between the two coarsest levels, away from
# both: it was 2,500 once, and the re-meshed 4,126-tet level's 2,406 unknowns fell under it.
_KEEP_FACTORIZATION_UNKNOWNS = 600
# With a kept factorisation, quasi-static robust Newton keeps the projected (PSD) tangent for
# this many iterations of a step, then takes the exact one with the contact terms: a change
# of tangent costs a refactorisation (the kept F must be of the tangent W~ is built from),
# which a step converging within them never pays. Measured on the 26,220-tet
# quasi-static reference (lesion 2, 30 mm): the projected tangent contracted the residual by
# 0.5-0.94 per iteration (14-60 iterations a 1 mm step, failing at 31 mm even at 62 um
# increments); the exact one with the contact terms converges quadratically (5 iterations).
_KEPT_PROJECTED_ITERATIONS = 6
# The augmented-Lagrangian stiffnesses of :meth:`LagrangeContact._add_contact_tangent`, in
# mean diagonal stiffnesses of the dofs they touch, tried in turn until the exact tangent is
# definite (then the projected tangent). As small as will do: the multipliers the LCP finds
# stand for lambda - rho H dx, and rho times what the linearised gaps miss of the true ones
# ends up in the forces. Measured, a sphere (R 8 mm) pressed in 1 mm quasi-static steps into
# a 40 x 40 x 20 mm block (nu 0.45, 3,000 tets, tolerance 1e-5): with 1, every step to 7 mm
# in 3-5 iterations with the forces of a 1e-8 solve to 6 digits; 100 alone put them 0.4-0.9 %
# off (1e4: 1.6 % at a residual of 1e-8); at 8 mm (5,184 tets) 1 left the tangent indefinite,
# 100 made it definite (10 iterations; projected: 60, not converged).
_AUGMENTATION_STIFFNESS = (1.0, 100.0)
# A kept factorisation is refreshed after a contact response whose W~ prediction missed the
# exact gaps in this many rounds.
_REFRESH_AFTER_ROUNDS = 2
# A kept response leaves out of its LCP the constraints whose gap after the free step is
# larger than this [m] and that carry no force (:meth:`LagrangeContact._kept_response`):
# they join once a round's exact gaps bring them within it. A point within the alarm
# distance costs a column of W~ (a solve with F) when first seen under F and whenever its
# normal turns; on the apex press at 176,506 tets (30 steps), 393 of the 608 columns were of
# points carrying no force more than 0.5 mm from the probe, most of them on its rounded rim,
# whose normals turn as they approach.
_LAZY_GAP_M = 0.5e-3
# The W~ columns solved beside the free step's first solve (``_prefetch_compliance``) are
# those of the points within this gap [m] before it: the free step moves points by about the
# probe's advance (0.2 mm a step at the paper's speed), so those within _LAZY_GAP_M after it
# are within this before. Measured on the 173,229-tet apex press (20 steps): with
# _LAZY_GAP_M itself, 86 columns rode along and 11 steps still solved 1-2 columns in a call
# of their own (about 47 ms each); with 0.75 mm, 114 rode and none needed their own call.
_PREFETCH_GAP_M = 0.00075
# The loosest relative tolerance of a response solve (see _kept_response): one CG
# iteration's worth, so that the exact gaps it yields still check W~'s prediction.
_RESPONSE_TOLERANCE_CAP = 0.1
# Newton iterations with a converged residual but a penetration that does not halve before
# the penetration counts as stalled (see LagrangeParams.stalled_penetration_m).
_STALLED_ITERATIONS = 3
# A robust Newton step that would invert a tet (the inversion barrier makes its energy
# infinite) is halved until none inverts, down to this fraction of the step.
_MIN_FEASIBLE_FRACTION = 2.0**-10
# A quasi-static step that does not converge even when split is relaxed to rest (see
# LagrangeContact._relaxed_step): at most this many relaxation steps, their pseudo time step
# [s] starting at the tissue's time step, doubled after each that converges (pseudo-transient
# continuation) up to this many tissue time steps; the static solve is tried again once the
# inertial force of the last relaxation step is below this fraction of the contact load.
_MAX_RELAXATION_STEPS = 60
_MAX_RELAXATION_TIME_STEPS = 1024.0
_RELAXED_INERTIA_FRACTION = 1e-2
# Newton iterations a relaxation step may take before its pseudo time step is quartered.
# Measured at 176,506 tets (lesion 3, 8 mm): the relaxation steps that converged took 2-16;
# two at tau = 0.16 and 0.08 s ran to 60 without converging (90 s each), then 0.04 and
# 0.02 s converged in 4 and 2.
_RELAXATION_ITERATIONS = 20


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
        max_response_iterations: contact-response iterations before the kept factorisation
            is refreshed.
        stalled_penetration_m: (robust mode) an iterate is converged when its KKT residual
            is below the Newton tolerance and no point lies deeper than the contact
            tolerance (:attr:`LagrangeContact.gap_tolerance_m`, ~0.1 um); if the penetration
            then stops shrinking (``_STALLED_ITERATIONS`` iterations without halving), the
            iterate is accepted when no point is deeper than this [m], and the step fails
            (and is subdivided) otherwise. Measured on the 105k level: the linearised gaps
            were met to the PGS tolerance while the exact gap of one point stayed at
            -1.02e-7 m (the probe's curvature, which a linearised gap misses, is the likely
            cause), and 30 iterations went by before the step was split.
    """

    alarm_distance_m: float = 0.002
    contact_distance_m: float = 0.0
    pgs_tolerance_m: float = 1e-8
    pgs_max_iterations: int = 1000
    regularization: float = 1e-8
    max_iterations: int = 30
    max_response_iterations: int = 4
    stalled_penetration_m: float = 1e-6

    def __post_init__(self) -> None:
        for name in (
            "alarm_distance_m",
            "contact_distance_m",
            "pgs_tolerance_m",
            "stalled_penetration_m",
        ):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise ConfigError(f"{name} must be >= 0; got {value!r}")
        if self.alarm_distance_m < self.contact_distance_m:
            raise ConfigError(
                f"alarm_distance_m ({self.alarm_distance_m}) must be >= contact_distance_m "
                f"({self.contact_distance_m})"
            )
        if min(self.pgs_max_iterations, self.max_iterations, self.max_response_iterations) < 1:
            raise ConfigError(
                "pgs_max_iterations, max_iterations and max_response_iterations must be >= 1"
            )
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


# What a failed attempt is undone to: positions [m], velocities [m/s], time [s], warm start [N].
_Checkpoint = tuple[NDArray[np.float64], NDArray[np.float64], float, NDArray[np.float64]]


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
        self._compliance = KeptCompliance(self.surface)
        # The last dynamic robust step that ended OK: (positions [m], velocities [m/s] it
        # ended with, velocities it started from, its step [s]); the next step, if it starts
        # from exactly that state, extrapolates its first iterate from it.
        self._last_step: tuple[NDArray, NDArray, NDArray, float] | None = None
        # A converged dynamic step's matrix, handed to the next (modified Newton).
        self._chords = ChordHandOver()
        # W~ is cached per kept factorisation and LM refreshes it by its own rules (response
        # rounds, exact iterations): no amortised refresh behind its back.
        solver = self.sim.integrator.solver
        solver.config = replace(solver.config, reuse_refresh_factor=0.0)
        # The kept factorisation is single precision, as the tissue's own Newton keeps it:
        # W~ and the CG preconditioner are approximations that the response rounds and the
        # CG correct to the exact A anyway. Measured (robust LM, apex press, loaded machine,
        # one run each): the same Newton iterations, response rounds, refactorisations and
        # force to 4 digits as a double factor, and Pardiso's time 15.1 -> 9.9 s over 42
        # steps at 26,220 tets, 60 -> 32 s over 21 steps at 105,004 (a step 3.3 -> 2.0 s).

    def _reset_tissue(self) -> None:
        super()._reset_tissue()
        self._warm = np.zeros(self.surface.count)
        self._pose_before = None
        self._compliance = KeptCompliance(self.surface)
        self._last_step = None
        self._chords.reset()

    def contact_constraints(self) -> ContactConstraints:
        """The contacts pressing at the end of the last step, exact (zero compliance)."""
        active = np.flatnonzero(self._warm > 0.0)
        positions = self.surface.positions(self.sim.positions)[active]
        _, normal = self.probe.signed_distance_world(positions)
        return self._constraint_rows(self.surface, active, normal, 0.0)

    def drop_caches(self) -> None:
        super().drop_caches()
        self._compliance = KeptCompliance(self.surface)
        self._last_step = None
        self._chords.reset()

    def _snapshot_contact(self) -> dict[str, Any]:
        before = self._pose_before
        return {
            "warm_n": self._warm.copy(),
            "pose_before": None if before is None else (before[0].copy(), before[1].copy()),
        }

    def _restore_contact(self, snapshot: dict[str, Any]) -> None:
        self._warm[:] = snapshot["warm_n"]
        before = snapshot["pose_before"]
        self._pose_before = None if before is None else (before[0].copy(), before[1].copy())

    def _advance(
        self, h: float
    ) -> tuple[StepStatus, NDArray[np.float64], NDArray[np.float64], dict[str, Any]]:
        if self.sim.config.mode is IntegrationMode.PAPER:
            outcome = self._paper_step(h)
        else:
            outcome = self._subdivided_robust_step(h, 0)
        self._pose_before = (self.probe.position_world.copy(), self.probe.quat_wxyz.copy())
        return outcome

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
        # Only at the deepest split: relaxing a whole increment from rest is far harder (176,506
        # tets, lesion 3, 9 mm after 8 mm needed relaxing: relaxation steps absorbing a 1 mm
        # press did not converge in 20 iterations at any tau from 0.02 s down to 0.3 ms; at
        # 1/16 mm they converge in 2-16).
        if failed and quasi_static and not may_split:
            self._restore(before)
            outcome = self._relaxed_step(h)
            failed = False
        if not failed or not may_split:
            outcome[3]["subdivisions"] = depth
            return outcome
        self._restore(before)
        begin = self._pose_before
        assert begin is not None  # may_split
        middle_quat = begin[1] + (end[1] if begin[1] @ end[1] >= 0 else -end[1])
        self.probe.set_pose(0.5 * (begin[0] + end[0]), middle_quat / np.linalg.norm(middle_quat))
        self._pose_before = begin
        first = self._subdivided_robust_step(0.5 * h, depth + 1)
        self._pose_before = (self.probe.position_world.copy(), self.probe.quat_wxyz.copy())
        self.probe.set_pose(*end)
        if first[0] in (StepStatus.DIVERGED, StepStatus.SOLVER_FAILED):
            return first
        second = self._subdivided_robust_step(0.5 * h, depth + 1)
        second[3]["relaxation_steps"] = second[3].get("relaxation_steps", 0) + first[3].get(
            "relaxation_steps", 0
        )
        return second

    def _relaxed_step(self, h: float):
        """A quasi-static step of ``h`` [s] that did not converge even when split, taken by
        relaxing the tissue to rest with the probe held at its pose.

        Where a deep press reaches a limit of the static path (a contact point on the
        probe's rounded rim pressed harder than the tissue round it can hold: the exact
        tangent, with the rim's curvature term, turns indefinite in the last 1/16 of a 1 mm
        increment and stays so however the increment is split; measured at 176,506 tets,
        lesion 3, 8 mm) there is no nearby static solution for Newton to converge to: the
        tissue snaps to another, as it would under any dissipative motion. Relaxation steps
        follow that motion: each is a dynamic step from rest (inertia m / tau^2, the velocity
        dropped after it: a proximal step, which descends the energy and cannot stop on an
        unstable equilibrium), tau doubling while they converge. The step ends once one
        leaves the tissue in static equilibrium to the Newton tolerance (diagnostic
        ``static_residual``), or once the inertial force of the last is a small fraction of
        the contact load and the static step, solved again from there, converges (each
        failed try divides that fraction by ten). Relaxation steps take no simulated time;
        the step's ``h`` is added at its end (diagnostic ``relaxation_steps``).
        """
        sim = self.sim
        tau = sim.config.tissue_dt
        mass = sim.integrator.mass_dof
        threshold = _RELAXED_INERTIA_FRACTION
        steps = 0
        outcome = None
        for steps in range(1, _MAX_RELAXATION_STEPS + 1):  # noqa: B007
            before = self._checkpoint()
            outcome = self._robust_step(h, relax_s=tau)
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
                return outcome
            moved = (sim.positions - before[0]).reshape(-1)
            inertia = vector_norm(mass * moved) / tau**2
            if inertia <= threshold * vector_norm(self._warm):
                relaxed = self._checkpoint()
                settled = self._robust_step(h, True, exact_first_static=True)
                if settled[0] is StepStatus.OK:
                    settled[3]["relaxation_steps"] = steps
                    return settled
                self._restore(relaxed)
                threshold *= 0.1  # not yet: relax further before the next try
            tau = min(2.0 * tau, _MAX_RELAXATION_TIME_STEPS * sim.config.tissue_dt)
        assert outcome is not None
        status = outcome[0] if outcome[0] is not StepStatus.OK else StepStatus.NOT_CONVERGED
        return status, outcome[1], outcome[2], {**outcome[3], "relaxation_steps": steps}

    def saved_state(self) -> dict[str, NDArray[np.float64]]:
        """Positions and velocities [m, m/s] (nodes, 3), time [s], the warm-start forces
        [N] by surface point, the last probe pose (a split step interpolates from it) and,
        after a dynamic step, the velocities it started from [m/s] (nodes, 3) and its step
        [s] (the next step's start is extrapolated from them)."""
        sim = self.sim
        state = {
            "positions": sim.positions.copy(),
            "velocities": sim.velocities.copy(),
            "time_s": np.array([sim.time_s, self.time_s]),
            "warm_n": self._warm.copy(),
        }
        if self._pose_before is not None:
            state["pose_before"] = np.concatenate(self._pose_before)
        last = self._continued_step(sim.positions, sim.velocities)
        if last is not None:
            # What the next step extrapolates its start from (a resumed run starts as this
            # one would have): the velocities the last step started from, and its step [s].
            state["velocities_before"] = last[2].copy()
            state["step_before_s"] = np.array([last[3]])
        return state

    def load_state(self, state: dict[str, NDArray[np.float64]]) -> None:
        try:
            positions, velocities = state["positions"], state["velocities"]
            tissue_time, model_time = (float(t) for t in state["time_s"])
            warm = np.asarray(state["warm_n"], dtype=np.float64)
        except (KeyError, TypeError, ValueError) as error:
            raise TissueInputError(
                f"not a saved Lagrange-multiplier state ({error}); pass what saved_state() returned"
            ) from error
        if warm.shape != self._warm.shape:
            raise TissueInputError(
                f"the saved state has {warm.shape[0]} contact points, this model "
                f"{self._warm.shape[0]}: it was saved from another mesh"
            )
        self._reset_tissue()  # caches of the state being left
        self.sim.set_state(positions, velocities, time_s=tissue_time)
        self._time = model_time
        self._warm[:] = warm
        pose = state.get("pose_before")
        self._pose_before = None if pose is None else (pose[:3].copy(), pose[3:].copy())
        before, step_s = state.get("velocities_before"), state.get("step_before_s")
        if before is not None and step_s is not None:
            self._last_step = (
                self.sim.positions.copy(),
                self.sim.velocities.copy(),
                np.array(before, dtype=np.float64).reshape(self.sim.velocities.shape),
                float(step_s[0]),
            )

    def _extrapolated_start(
        self, x: NDArray[np.float64], v: NDArray[np.float64], h: float
    ) -> NDArray[np.float64] | None:
        """The first iterate of a dynamic step of ``h`` [s] from (x [m], v [m/s]), (3N,):
        x + h v + h^2 (v - v_last) / h_last when the step continues from the state the last
        one ended in (v_last: the velocities it started from), as the integrator's own
        Newton starts (:meth:`tissue.sim.integrator.ImplicitIntegrator.step`); else None."""
        last = self._continued_step(x, v)
        if last is None:
            return None
        _, _, previous, last_h = last
        return extrapolated_positions(x, v, h, previous, last_h)

    def _continued_step(
        self, x: NDArray[np.float64], v: NDArray[np.float64]
    ) -> tuple[NDArray, NDArray, NDArray, float] | None:
        """The last dynamic step's record if (x [m], v [m/s]) is exactly the state it ended in."""
        last = self._last_step
        if last is None or not (np.array_equal(x, last[0]) and np.array_equal(v, last[1])):
            return None
        return last

    def _checkpoint(self) -> _Checkpoint:
        """The state a failed attempt is undone to: positions, velocities, time, warm start."""
        sim = self.sim
        return sim.positions.copy(), sim.velocities.copy(), sim.time_s, self._warm.copy()

    def _restore(self, checkpoint: _Checkpoint) -> None:
        """Undo to a :meth:`_checkpoint`."""
        positions, velocities, time_s, warm = checkpoint
        self.sim.set_state(positions, velocities, time_s=time_s)
        self._warm[:] = warm

    # ------------------------------------------------------------------ shared

    @property
    def gap_tolerance_m(self) -> float:
        """How far a gap may miss complementarity [m]: ten PGS tolerances (and 1 nm)."""
        return 10 * self.params.pgs_tolerance_m + 1e-9

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

        ``under_kept_factor``: take the response under F, F^-1 H^T dlambda from W~'s kept
        columns, as it is (no solve with A, one round unless points join). For the Newton
        iterations of a dynamic step after its first: the forces change little there, so F's
        error on their response is small, and the next KKT residual (exact gradient, gaps
        re-detected) judges the iterate anyway: a response short of A's costs an iteration,
        not accuracy.
        Measured on ``bench contact``'s apex press (stepped by a script reading each step's
        diagnostics, two interleaved runs each): at 173,229 tets Newton iterations 2.16 ->
        2.19 a step, median step 545 / 556 -> 491 / 488 ms, the force within 6e-7 relative;
        at 26,854 tets 1.78 -> 1.82, 44.3 / 44.7 -> 40.9 / 41.1 ms, within 1e-7.

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

        Constraints that carry no force and lie farther than :data:`_LAZY_GAP_M` from the
        probe after the free step are left out of the LCP (no column of W~ is solved for
        them) until a round's exact gaps, which every round computes for all constraints,
        bring one within that distance; it then joins and the round is repeated. A left-out
        point ends with no force and a positive gap, which is its complementarity condition,
        so the solution is the full LCP's.
        """
        solver = self.sim.integrator.solver
        forces = start.copy()
        correction = np.zeros(rows.shape[1])
        gaps = offset.copy()
        guess = start.copy()
        taking = (offset <= _LAZY_GAP_M) | (start > 0.0)
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
            # first iteration would have spent a solve with F on it). Measured on the
            # 26,220-tet apex press of ``bench contact`` (50 steps): CG iterations of the
            # response solves 6.7 -> 3.8 a step, median step 269 -> 238 ms (three alternating
            # runs each, heavily loaded), force within 1e-6 N.
            under_f = self._compliance.response(contacts.points[chosen], new - current)
            # The free step's own solve leaves a residual up to ``accuracy``: the response to
            # the forces' change (mostly much smaller than the step's load) needs no smaller
            # one, so its relative tolerance is that residual over its own load. Measured on
            # the 26,220-tet apex press: CG iterations per response solve 2.6 -> 2.4.
            taken = under_kept_factor and under_f is not None
            refactorized = False
            if taken:
                assert under_f is not None
                increment = under_f
            else:
                change = system.with_rhs(transpose_product(rows, delta))
                load = change.free_rhs_norm()
                relative = _RESPONSE_TOLERANCE_CAP if load == 0.0 else accuracy / load
                increment, report = solver.solve(
                    change,
                    initial_guess=under_f,
                    tolerance=min(_RESPONSE_TOLERANCE_CAP, relative),
                    kind=LinearSolverKind.REUSE,
                )
                refactorized = report.factorized
            correction += increment
            gaps = gaps + rows @ increment
            forces[chosen] = new
            guess = forces
            mismatch = float(np.max(np.abs(gaps[chosen] - predicted), initial=0.0))
            missed += int(mismatch > self.gap_tolerance_m and not fresh)
            joining = ~taking & (gaps <= _LAZY_GAP_M)
            taking |= joining
            exact = fresh or taken or mismatch <= self.gap_tolerance_m
            converged = exact and not np.any(joining)
            fresh = fresh or refactorized
        if missed >= _REFRESH_AFTER_ROUNDS and not fresh:
            solver.refresh_kept_factorization(system)
        diagnostics = {"pgs_sweeps": sweeps_total, "response_rounds": rounds}
        return forces, correction, {**diagnostics, "response_converged": converged}

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

    def _paper_step(self, h: float):
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
        contacts = detect_contacts(self.surface, free_x, self.probe, self.params.alarm_distance_m)
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
        outcome = integrator.paper_finish(x, v, h, linear, dv, _report(indefinite))
        status = sim.commit(outcome, h, start).status
        points, on_probe = self._finish(contacts, forces)
        diagnostics = {
            "constraints": contacts.count,
            "active": int(np.sum(forces > 0)),
            "min_volume_ratio": outcome.min_volume_ratio,
            **response,
        }
        return status, points, on_probe, diagnostics

    # ------------------------------------------------------------------ robust

    def _prefetch_compliance(
        self, contacts: Contacts, forces: NDArray[np.float64], constrained: NDArray[np.bool_]
    ) -> None:
        """Hand the kept factorisation's next solve (the free step's first) the W~ columns the
        response will likely need: those of the points pressing or within
        :data:`_PREFETCH_GAP_M` of the probe now (the response takes those within
        :data:`_LAZY_GAP_M` after the free step, and solves what is missing itself)."""
        kept = self.sim.integrator.solver.kept_factorization
        if kept is None or not contacts.count:
            return
        gap = contacts.distance - self.params.contact_distance_m
        near = (gap <= _PREFETCH_GAP_M) | (forces > 0.0)
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

    def _add_contact_tangent(
        self,
        system: ConstrainedSystem,
        contacts: Contacts,
        forces: NDArray[np.float64],
        stiffness: float,
    ) -> tuple[NDArray[np.bool_], float] | None:
        """Complete the exact Newton tangent with the contacts pressing now (``forces`` > 0
        [N], one per contact), in place in ``system``'s matrix.

        Two terms per such point, in 3 x 3 blocks spread over its tet by its weights:

        - the probe's curvature, -lambda d2g/dx2: a force along a normal that turns as the
          point slides round a rounded edge (g is the signed distance; 0 on flat faces).
          Without it Newton converges only linearly wherever the probe's rim presses;
        - rho n n^T, an augmented-Lagrangian term: the LCP fixes these gaps' change, so it
          moves only the multipliers (by rho times the gap being closed, zero at the
          solution), not the step, and it makes the tangent positive definite where the
          tissue alone is not (a press deep enough that the tissue would buckle sideways
          but for the probe). rho is ``stiffness`` times the mean diagonal stiffness of
          the dofs it touches (:data:`_AUGMENTATION_STIFFNESS`).

        Returns (the points augmented, a mask over ``contacts``; rho [N/m]), or None when
        nothing was added: the multipliers lambda' the LCP then finds stand for lambda' -
        rho H dx in the true linearisation (:meth:`_unaugmented`).
        """
        pressing = forces > 0.0
        if not np.any(pressing):
            return None
        matrix, constrained = system.matrix, system.constrained
        points = contacts.points[pressing]
        nodes = self.surface.embedding.tet_nodes[points]
        weights = self.surface.embedding.weights[points]
        dofs = (3 * nodes[:, :, None] + np.arange(3)).reshape(-1)
        dofs = dofs[~constrained[dofs]]
        if dofs.size == 0:
            return None
        rho = stiffness * float(np.mean(matrix.diagonal()[dofs]))
        normal = contacts.normal[pressing]
        curvature = self.probe.distance_hessian_world(contacts.positions[pressing])
        turning = forces[pressing, None, None] * curvature
        blocks = rho * normal[:, :, None] * normal[:, None, :] - turning
        _add_point_blocks(
            matrix.indptr, matrix.indices, matrix.data, constrained, nodes, weights, blocks
        )
        system.matrix_modified()
        return pressing, rho

    @staticmethod
    def _unaugmented(
        forces: NDArray[np.float64],
        rows: sp.csr_matrix,
        step: NDArray[np.float64],
        augmented: tuple[NDArray[np.bool_], float] | None,
    ) -> NDArray[np.float64]:
        """The forces [N] of the true linearisation from those of the augmented one:
        (A + rho H_a^T H_a) dx = r + H^T lambda' is A dx = r + H^T lambda with lambda =
        lambda' - rho H_a dx on the augmented points (no pull: at least 0). Without this
        the KKT residual would carry rho times the gap each step closes, and grow."""
        if augmented is None:
            return forces
        mask, rho = augmented
        corrected = forces.copy()
        corrected[mask] = np.maximum(forces[mask] - rho * (rows[mask] @ step), 0.0)
        return corrected

    def _robust_step(
        self,
        h: float,
        may_retry: bool = False,
        relax_s: float = 0.0,
        exact_first_static: bool = False,
    ):
        """One robust step of ``h`` [s]. ``may_retry``: the caller will retry a step that
        does not converge (as two halves, or relaxed), so a quasi-static step whose exact
        tangent failed gives up at once rather than crawl on the projected one (measured at
        176,506 tets, 7 mm: 60 projected iterations, not converged, then the halves in 8
        each). ``relax_s`` > 0 (quasi-static only): a relaxation step of
        :meth:`_relaxed_step`, a dynamic step from rest with that time step [s] that takes
        no simulated time. ``exact_first_static`` (quasi-static): the exact tangent with the
        contact terms from the first iteration (the static solve after a relaxation)."""
        sim = self.sim
        start = time.perf_counter()
        integrator, cfg = sim.integrator, sim.integrator.config
        x, v = sim.positions.copy(), sim.velocities.copy()
        dofs, targets = sim.constraints()
        if relax_s > 0.0:
            potential = integrator.incremental_potential(
                x, np.zeros_like(v), relax_s, dofs, targets
            )
            potential.quasi = False  # inertia about x, no damping (built for quasi-static)
        else:
            potential = integrator.incremental_potential(x, v, h, dofs, targets)
        y = potential.start()
        constrained = potential.constrained
        free = ~constrained
        # Continuing a dynamic step, start from x + h v + h^2 a, a the last step's
        # acceleration (the integrator's Newton starts so too). Measured on the 26,220-tet
        # apex press of ``bench contact`` (50 steps): Newton iterations 2.22 -> 1.94 a step,
        # CG iterations 13.9 -> 11.9, the force within 1e-7 N.
        evaluated = None
        # A dynamic step with stiffness damping takes the exact tangent first (below): the
        # start's evaluation assembles it too.
        tangent_first = not cfg.quasi_static and relax_s == 0.0 and cfg.rayleigh_stiffness > 0.0
        guess = self._extrapolated_start(x, v, h) if relax_s == 0.0 else None
        # The last step's matrix, for this step's first iteration (a chord; see
        # ChordHandOver): only continuing the step it came from (``guess``). Measured on
        # ``bench peer``'s press (50 steps, ms per simulated second, runs alternated with the
        # commit before): 4,126 tets 268 / 270 -> 196 / 196 (Newton iterations 67 -> 67,
        # response rounds 116 -> 91; the force within 3e-5 relative, lesion 1 within 1e-8 m);
        # 1,363 tets 144 -> 117, 2,539 201 -> 152, 7,369 441 -> 389, 12,861 803 -> 674;
        # 26,220 tets 2,012 / 1,994 -> 2,069 / 1,970 (79 -> 83 iterations: there the contact
        # set changes in most steps).
        handed = self._chords.take(h, constrained)
        if guess is None or not tangent_first or y.size < _KEEP_FACTORIZATION_UNKNOWNS:
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
            # The inertial prediction x + h v inverts a tet: start from x instead (the
            # constrained dofs where the potential puts them). Measured: robust LM, 105,004
            # tets, lesion 4, step 602 (29.6 mm): x + h v inverted a tet touching the probe's
            # face 2.3 mm from its end, and Newton, started there, converged inverted.
            predicted, y = y, x.reshape(-1).copy()
            y[constrained] = predicted[constrained]
            energy, gradient, scale = potential.evaluate(y)
        contacts = detect_contacts(
            self.surface, y.reshape(-1, 3), self.probe, self.params.alarm_distance_m
        )
        rows = constraint_rows(self.surface, contacts, y.size, constrained)
        # The forces of the start, one per contact: what the step reports if it gives up in
        # its first iteration (a retry-able exact tangent found indefinite at once).
        forces = self._warm[contacts.points]
        scale_floor = RESIDUAL_SCALE_FLOOR * integrator._force_unit
        status = StepStatus.NOT_CONVERGED
        iterations, sweeps_total = 0, 0
        residual = np.inf
        chord: ConstrainedSystem | None = handed
        chord_step = False
        rounds = 0
        deepest, stalled = np.inf, 0
        exact_iterations, rejected, shortened = 0, 0, 0
        # False once this step's exact tangent was found indefinite or took a step that did
        # not reduce the residual: projected for the rest of the step.
        exact_trusted = True
        # Dynamic steps with stiffness damping try the exact tangent first, as the
        # integrator's do (ImplicitIntegrator._newton): their Hessian adds M / h^2 + (r_K / h)
        # K_rest (5 K_rest at the defaults), which covers what the projection would clamp, and
        # an exact tangent that is not definite, or whose step does not reduce the KKT
        # residual, falls back to the projected one for the rest of the step. The projected
        # tangent is what Newton's first iteration misses by: on the 26,220-tet apex press of
        # ``bench contact`` (50 steps) 14 steps converged in one iteration instead of 4, 1.76
        # Newton iterations a step instead of 2.00, the force within 1.1e-5 relative.
        dynamic = not cfg.quasi_static and relax_s == 0.0
        exact_first = dynamic and cfg.rayleigh_stiffness > 0.0
        penetration = 0.0
        limit = self.params.max_iterations
        if relax_s > 0.0:
            limit = min(limit, _RELAXATION_ITERATIONS)
        for iterations in range(1, limit + 1):  # noqa: B007
            before = (y, energy, gradient, scale, contacts, rows, forces, residual, penetration)
            keep = y.size >= _KEEP_FACTORIZATION_UNKNOWNS
            # With a kept factorisation the solves are inexact Newton: each to a tenth of the
            # last KKT residual, as the integrator's own Newton does.
            tolerance = min(1e-2, max(0.1 * residual, 1e-10))
            # ... and, as there, never more accurately than what brings the KKT residual well
            # under the Newton tolerance: the free step and the response solves each get half
            # of the integrator's share (their residuals add). The relative tolerance alone
            # (0.1 x the residual, of a right-hand side itself of the residual's size) asked
            # the second iteration of a steady press for ~1e-7 of the force scale, where the
            # chord step it takes leaves ~5e-5 anyway.
            enough = 0.5 * LINEAR_SHARE_OF_TOLERANCE * cfg.newton_tolerance
            enough *= max(scale, scale_floor)
            # As the integrator: projected (PSD) element tangents far from the solution, the
            # exact tangent near it (projection costs quadratic convergence), the projected
            # one again where that is not definite (W = H A^-1 H^T must be positive for PGS).
            # Quasi-static steps complete the exact tangent with the contact terms and, with a
            # kept factorisation, take it after _KEPT_PROJECTED_ITERATIONS: with no inertia the
            # projected tangent crawls (the study's 26,220-tet reference stalled). Dynamic
            # steps take the exact tangent without the contact terms, from the first iteration
            # (``exact_first``, above): with the contact terms, a full step can leave the step's
            # own solution for another -- on the published scene's lesion 1, pose 4 (tilted;
            # the tissue creeps sideways under the frictionless probe) the dynamic reference
            # with them ended on the slid equilibrium, 1.78 N and the lesion 7.5 mm away, where
            # the cells and the reference without them hold 3.65 N.
            contact_terms = bool(cfg.quasi_static) and relax_s == 0.0
            # A static solve from a relaxed state (``exact_first_static``) is near its solution
            # or nowhere near one: exact from the start, so that a failure costs one try.
            projected_iterations = 0 if exact_first_static else _KEPT_PROJECTED_ITERATIONS
            far = bool(cfg.project_psd) and residual > PROJECTION_SWITCH
            if exact_first:
                project = not exact_trusted
            else:
                project = (
                    not exact_trusted
                    or (far and not (exact_first_static and contact_terms))
                    or (keep and (not contact_terms or iterations <= projected_iterations))
                )
            if iterations > 1 and contacts.count:
                self._warm[contacts.points] = forces  # total forces of the last iterate
            start_forces = self._warm[contacts.points]
            try:
                # The exact tangent with the contact terms, its augmentation raised if that is
                # not definite, then the projected tangent (see _AUGMENTATION_STIFFNESS).
                stiffnesses = _AUGMENTATION_STIFFNESS if contact_terms else (0.0,)
                tangents = [None] if project else [*stiffnesses, None]
                for attempt, stiffness in enumerate(tangents):
                    project = stiffness is None
                    if project and attempt and (contact_terms or exact_first):
                        exact_trusted = False  # not definite: projected for the rest of the step
                        if may_retry and contact_terms:
                            break
                    chord_step = chord is not None and (project or exact_first)
                    if chord is not None and chord_step:
                        system = chord.with_rhs(-gradient)
                    else:
                        system = potential.hessian_system(y, -gradient, project=project)
                    chord = None
                    augmented = None
                    if stiffness and contacts.count:  # 0.0: the exact tangent without them
                        augmented = self._add_contact_tangent(
                            system, contacts, start_forces, stiffness
                        )
                    if keep:
                        # A new kind of tangent needs its own F: W~ = H F^-1 H^T of a projected
                        # F misses the exact compliance by more than the contact tolerance can
                        # see near convergence. (Quasi-static steps turn exact within a step;
                        # dynamic ones keep the exact F across steps.)
                        refreshed = attempt > 0 or (
                            contact_terms and not project and not exact_iterations
                        )
                        if refreshed:
                            integrator.solver.refresh_kept_factorization(system)
                        self._prefetch_compliance(contacts, start_forces, constrained)
                        free_step, report, accuracy = self._loaded_solve(
                            system, rows, start_forces, tolerance, enough
                        )
                        fresh = report.factorized or refreshed
                        indefinite = report.indefinite or (
                            refreshed and integrator.solver.kept_indefinite
                        )
                    else:
                        factorization, indefinite = integrator.solver.factorize(system)
                    if project or not indefinite:
                        break
                if not keep:
                    free_step = np.asarray(factorization.solve(system.rhs)).reshape(-1)
                    free_step = np.where(constrained, system.values, free_step)
            except Exception:  # noqa: BLE001 - a status, not a crash
                status = StepStatus.SOLVER_FAILED
                break
            if not exact_trusted and may_retry and contact_terms:
                break  # no definite exact tangent: the caller retries (not converged)
            if contacts.count:
                offset = contacts.distance + rows @ free_step - self.params.contact_distance_m
                if keep:
                    forces, correction, response = self._kept_response(
                        system,
                        rows,
                        offset,
                        contacts,
                        fresh,
                        accuracy,
                        start_forces,
                        under_kept_factor=exact_first and iterations > 1,
                    )
                else:
                    forces, correction, response = self._exact_response(
                        factorization, rows, offset, 1.0, contacts
                    )
                sweeps_total += response["pgs_sweeps"]
                rounds += response["response_rounds"]
                step = free_step + correction
                forces = self._unaugmented(forces, rows, step, augmented)
            else:
                forces = np.zeros(0)
                step = free_step
            finite = bool(np.all(np.isfinite(step)) and np.all(np.isfinite(forces)))
            if not finite and not project and (contact_terms or exact_first):
                # The exact tangent failed numerically (176,506 tets, quasi-static, 7 mm: the
                # forces of its first exact iteration were not finite): drop its factorisation
                # and go on projected, as for an exact step that does not descend (below).
                y, energy, gradient, scale, contacts, rows, forces, residual, penetration = before
                integrator.solver.forget()
                exact_trusted = False
                rejected += 1
                if may_retry and contact_terms:
                    break
                continue
            if not finite:
                status = StepStatus.DIVERGED
                break
            exact_iterations += int(not project)
            # Robust mode's inversion barrier makes an inverted tet's energy infinite, but
            # this Newton takes full steps (no merit function to search on) and the barrier
            # only acts through the tangent: a step may jump past J = 0, where the inverted
            # tet exerts no force, and converge there (a box pressed 9-11 mm into a coarse
            # block, tests/test_contact.py). The step is halved until no tet inverts; the
            # next iteration re-linearises from there.
            fraction = 1.0
            trial = y + step
            energy, gradient, scale = potential.evaluate(trial)
            while not math.isfinite(energy) and fraction > _MIN_FEASIBLE_FRACTION:
                fraction *= 0.5
                trial = y + fraction * step
                energy, gradient, scale = potential.evaluate(trial)
            if not math.isfinite(energy):
                # No feasible fraction: not converged, from the last feasible iterate (the
                # caller splits the step).
                y, energy, gradient, scale, contacts, rows, forces, residual, penetration = before
                break
            shortened += int(fraction < 1.0)
            # The next iteration of a dynamic step keeps this one's matrix (a chord step): one
            # iteration on (the constrained dofs at their targets) the matrix has barely
            # changed; the residual is still that of the true gradient, and a step needing a
            # third iteration assembles afresh. Measured on the 26,220-tet apex press of
            # ``bench contact`` (50 steps), when every dynamic step was projected: Newton and
            # CG iterations unchanged (1.92 and 11.9 a step), the force within 2e-7 N, one
            # Hessian fewer a step. With the exact tangent (the same press stepped by a script
            # reading each step's diagnostics; two interleaved runs each, one at 4,126 tets):
            # at 26,220 tets the same Newton iterations (1.78 a step) and force to 8 digits,
            # median step 51.7 / 51.4 -> 42.9 / 41.9 ms; at 4,126, 8.2 -> 7.1 ms, the same
            # iterations and force;
            # at 176,506, 2.06 -> 2.16 Newton iterations a step, 559 / 584 -> 530 / 536 ms, the
            # force to 7 digits.
            if keep and (project or exact_first) and dynamic and fraction == 1.0 and not chord_step:
                chord = system
            y = trial
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
            kkt = gradient - transpose_product(rows, forces)
            # The integrator's floor on the force scale: a tissue at rest with no load has
            # scale ~ 0, and its round-off gradient must not read as a large relative residual.
            residual = vector_norm(kkt[free]) / max(scale, scale_floor)
            penetration = float(max(0.0, -(contacts.distance.min() if contacts.count else 0.0)))
            if not np.isfinite(residual):
                status = StepStatus.DIVERGED
                break
            if not project and (contact_terms or exact_first) and residual >= before[7]:
                # Near a bifurcation of a deep press (the tissue could slide either way under
                # the frictionless probe) the exact tangent is nearly singular and its full
                # step can jump millimetres (measured: 9.6 mm for a 1 mm press); an exact
                # step that does not reduce the KKT residual is undone, and the step is retried
                # (``may_retry``: split or relaxed) or goes on with the projected tangent; a
                # dynamic step goes on projected (and so does not reuse this step's matrix as a
                # chord).
                y, energy, gradient, scale, contacts, rows, forces, residual, penetration = before
                exact_trusted = False
                chord = None
                rejected += 1
                if may_retry and contact_terms:
                    break
                continue
            if residual <= cfg.newton_tolerance:
                if penetration <= self.gap_tolerance_m:
                    status = StepStatus.OK
                    break
                stalled = stalled + 1 if penetration > 0.5 * deepest else 0
                deepest = min(deepest, penetration)
                if stalled >= _STALLED_ITERATIONS:
                    if penetration <= self.params.stalled_penetration_m:
                        status = StepStatus.OK
                    break
        if status in (StepStatus.DIVERGED, StepStatus.SOLVER_FAILED):
            integrator.solver.forget()
            return status, np.zeros((0, 3)), np.zeros((0, 3)), {"iterations": iterations}
        new_x = y.reshape(-1, 3)
        new_v = np.zeros_like(v) if cfg.quasi_static else (new_x - x) / h
        reaction = np.zeros(y.size)
        reaction[dofs] = (gradient - transpose_product(rows, forces))[dofs]
        # The last evaluation was at y (unless an exact step was undone): its elastic energy
        # and smallest det F serve the step's end, which saves an element pass a step.
        elastic = potential.last_elastic
        known = elastic[1:] if elastic is not None and elastic[0] is y else None
        outcome = integrator._finish(
            x,
            v,
            new_x,
            new_v,
            reaction,
            _report(False),
            newton_iterations=iterations,
            newton_residual=residual,
            known=known,
        )
        if status is StepStatus.NOT_CONVERGED and outcome.status is StepStatus.OK:
            outcome.status = StepStatus.NOT_CONVERGED
        status = sim.commit(outcome, 0.0 if relax_s else h, start).status
        continues = status is StepStatus.OK and relax_s == 0.0 and not cfg.quasi_static
        self._last_step = (new_x, new_v, v, h) if continues else None
        if continues and exact_first and y.size >= _KEEP_FACTORIZATION_UNKNOWNS:
            full_exact = exact_iterations == iterations and shortened == 0
            self._chords.record(system, h, handed is not None, iterations, full_exact)
        points, on_probe = self._finish(contacts, forces)
        static_residual = residual
        if relax_s > 0.0:
            # How far from static equilibrium the relaxed state is (no inertia).
            static = integrator.incremental_potential(x, v, h, dofs, targets)
            _, static_gradient, static_scale = static.evaluate(y)
            unbalanced = (static_gradient - transpose_product(rows, forces))[free]
            static_residual = vector_norm(unbalanced) / max(static_scale, scale_floor)
        diagnostics = {
            "constraints": contacts.count,
            "active": int(np.sum(forces > 0)),
            "iterations": iterations,
            "exact_iterations": exact_iterations,
            "exact_rejected": rejected,
            "shortened_steps": shortened,
            "chord_from_last_step": handed is not None,
            "started_at_x": started_at_x,
            "pgs_sweeps": sweeps_total,
            "kkt_residual": residual,
            "response_rounds": rounds,
            "min_volume_ratio": outcome.min_volume_ratio,
            "relaxation_steps": 0,
            "static_residual": static_residual,
        }
        return status, points, on_probe, diagnostics


@numba.njit(cache=True)
def _add_point_blocks(
    indptr, indices, data, constrained, nodes, weights, blocks
):  # pragma: no cover - compiled
    """Add, for each contact point c embedded with ``weights`` (4,) in the tet of ``nodes``
    (4,), the 3 x 3 block ``blocks[c]`` times w_a w_b at every node pair (a, b) of its tet, to
    the CSR matrix in place (within its pattern: one tet's nodes are always coupled);
    constrained dofs are skipped (their rows and columns are eliminated)."""
    for c in range(nodes.shape[0]):
        for a in range(4):
            for b in range(4):
                w = weights[c, a] * weights[c, b]
                for k in range(3):
                    i = 3 * nodes[c, a] + k
                    if constrained[i]:
                        continue
                    lo, hi = indptr[i], indptr[i + 1]
                    for m in range(3):
                        j = 3 * nodes[c, b] + m
                        if constrained[j]:
                            continue
                        q = find_column(indices, lo, hi, j)
                        if q >= 0:
                            data[q] += w * blocks[c, k, m]


def _report(indefinite: bool) -> SolveReport:
    """What a direct solve did, for the integrator's bookkeeping."""
    return SolveReport(0, 0.0, True, True, indefinite)
