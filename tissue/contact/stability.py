"""What "stable" means for a coupled probe-tissue run, checked after every step.

The compression study's instability detector and the hard-case tests use this one monitor.
A step is unstable when any of these holds:

- ``status``: the tissue step itself failed (not converged, an inverted element, solver
  divergence or failure; see :class:`tissue.status.StepStatus`);
- ``non_finite``: NaN or Inf in the node positions, the wrench or the landmarks;
- ``penetration``: the deepest collision-surface point lies further inside the probe than
  the method's bound (its strategy class's ``penetration_bound_m``);
- ``blow_up``: a node moved further from rest than ``blow_up_factor`` times the probe's
  largest travel so far plus ``blow_up_margin_m`` (nothing but the probe moves the tissue);
- ``landmark_jump``: a landmark moved further in one step than the probe did in any of the
  last ``recent_steps`` steps plus ``landmark_jump_margin_m`` (trajectories must be
  continuous; the window lets tissue spring back after a probe withdrawn in one step).
  Frictionless contact on a sloped skin can also jump physically: pressed deep enough, the
  tissue slips out from under the probe (the converged quasi-static solution of the default
  phantom does so under lesion 4 at 25 mm, a 24 mm jump). Scenarios where that can happen
  (the compression study) set the margin to None and record the jumps as data instead;
- ``timeout``: one step took longer than ``step_timeout_s`` of wall time.

The energy bound (elastic + kinetic energy below the work done by the probe) is checked by
the hard-case runner (:mod:`agents.lab.hard_cases`) for the FE methods, not here: it needs the
probe's work over the whole run, and the PBD backend has no energy to compare.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from tissue.contact.registry import contact_class, contact_method
from tissue.errors import ConfigError
from tissue.status import StepStatus
from tissue.step_result import TissueStep


@dataclass(frozen=True)
class StabilityLimits:
    """Bounds of a stable step.

    Attributes:
        penetration_m: largest penetration [m]; None takes the method's own
            (its class's ``penetration_bound_m``).
        blow_up_factor: a node may move at most this many times the probe's travel ...
        blow_up_margin_m: ... plus this [m] from rest.
        landmark_jump_margin_m: a landmark may move at most the probe's largest motion in
            the last ``recent_steps`` steps plus this [m]; None: not checked.
        recent_steps: that window (steps).
        step_timeout_s: wall-time limit of one step [s].
        penetrated_is_unstable: whether a ``penetrated`` step (the skin's facets deeper in
            the probe than the method's bound and the skin's resolution explain; a physical
            failure, not a numerical one) ends the run. The compression study sets it False:
            Table 1 counts instabilities as the paper did, and on its coarse volumes the
            paper's skin floats up to 13 mm above the boundary nodes that prescribed
            displacement and PBD hold, so its facets reach into the probe where the method's
            own points do not; the skin's depth is recorded instead.
    """

    penetration_m: float | None = None
    blow_up_factor: float = 3.0
    blow_up_margin_m: float = 0.005
    landmark_jump_margin_m: float | None = 0.001
    step_timeout_s: float = 120.0
    recent_steps: int = 10
    penetrated_is_unstable: bool = True

    def __post_init__(self) -> None:
        for name in ("blow_up_factor", "blow_up_margin_m", "landmark_jump_margin_m"):
            value = getattr(self, name)
            if value is None and name == "landmark_jump_margin_m":
                continue
            if not (np.isfinite(value) and value > 0):
                raise ConfigError(f"StabilityLimits.{name} must be > 0; got {value!r}")
        if not (isinstance(self.recent_steps, int) and self.recent_steps >= 1):
            raise ConfigError(
                f"StabilityLimits.recent_steps must be >= 1; got {self.recent_steps!r}"
            )
        if not (np.isfinite(self.step_timeout_s) and self.step_timeout_s > 0):
            raise ConfigError(
                f"StabilityLimits.step_timeout_s must be > 0 s; got {self.step_timeout_s!r}"
            )
        if self.penetration_m is not None and not (
            np.isfinite(self.penetration_m) and self.penetration_m > 0
        ):
            raise ConfigError(
                f"StabilityLimits.penetration_m must be > 0 m or None; got {self.penetration_m!r}"
            )


@dataclass(frozen=True)
class Instability:
    """Why a step was judged unstable.

    Attributes:
        kind: ``status``, ``non_finite``, ``penetration``, ``blow_up``, ``landmark_jump`` or
            ``timeout``.
        detail: a sentence with the measured value and the bound.
    """

    kind: str
    detail: str


class StabilityMonitor:
    """Checks each step of one run against :class:`StabilityLimits`.

    Args:
        method: the contact method (picks the penetration bound).
        rest_positions: tissue node positions at rest [m], (node_count, 3).
        start_probe_position: the probe origin at the start of the run [m], (3,).
        limits: the bounds.
    """

    def __init__(
        self,
        method: str,
        rest_positions: NDArray[np.float64],
        start_probe_position: NDArray[np.float64],
        limits: StabilityLimits | None = None,
    ) -> None:
        self.method = contact_method(method)
        self.limits = limits if limits is not None else StabilityLimits()
        self.penetration_bound_m = (
            self.limits.penetration_m
            if self.limits.penetration_m is not None
            else contact_class(self.method).penetration_bound_m
        )
        self._rest = np.asarray(rest_positions, dtype=np.float64)
        self._start = np.asarray(start_probe_position, dtype=np.float64).copy()
        self._previous_probe = self._start.copy()
        self._previous_landmarks: NDArray[np.float64] | None = None
        self._largest_travel = 0.0
        self._recent_motion: list[float] = []

    def observe(
        self, probe_position: NDArray[np.float64], landmarks: NDArray[np.float64]
    ) -> tuple[float, NDArray[np.float64] | None]:
        """Add one step to the history the checks compare against, without judging it: how
        a resumed run catches up on the steps it did before (:meth:`check` calls it too).

        Args:
            probe_position: the probe origin of the step [m], (3,).
            landmarks: the landmark positions after it [m], (landmark_count, 3).

        Returns:
            (the largest probe motion per step lately [m], the previous step's landmarks or
            None).
        """
        probe_position = np.asarray(probe_position, dtype=np.float64)
        self._recent_motion.append(float(np.linalg.norm(probe_position - self._previous_probe)))
        del self._recent_motion[: -self.limits.recent_steps]
        self._previous_probe = probe_position.copy()
        travel = float(np.linalg.norm(probe_position - self._start))
        self._largest_travel = max(self._largest_travel, travel)
        previous, self._previous_landmarks = self._previous_landmarks, landmarks
        return max(self._recent_motion), previous

    def check(
        self,
        result: TissueStep,
        node_positions: NDArray[np.float64],
        probe_position: NDArray[np.float64],
    ) -> Instability | None:
        """Judge one step; returns None when it is stable.

        Args:
            result: what the step returned.
            node_positions: tissue node positions after the step [m], (node_count, 3).
            probe_position: the probe origin the step was taken at [m], (3,).
        """
        landmarks = result.landmarks_world_m
        probe_motion, previous_landmarks = self.observe(probe_position, landmarks)
        skin_only = (
            result.status is StepStatus.PENETRATED and not self.limits.penetrated_is_unstable
        )
        if result.status.is_failure and not skin_only:
            return Instability("status", f"the tissue step reported '{result.status.value}'")
        finite = (
            np.all(np.isfinite(node_positions))
            and np.all(np.isfinite(result.force_world_n))
            and np.all(np.isfinite(result.torque_world_nm))
            and np.all(np.isfinite(landmarks))
        )
        if not finite:
            return Instability("non_finite", "NaN or Inf in the positions, wrench or landmarks")
        if result.diagnostics.compute_ms > 1e3 * self.limits.step_timeout_s:
            return Instability(
                "timeout",
                f"the step took {result.diagnostics.compute_ms / 1e3:.1f} s "
                f"(limit {self.limits.step_timeout_s:g} s)",
            )
        if result.method_penetration_m > self.penetration_bound_m:
            return Instability(
                "penetration",
                f"penetration {result.method_penetration_m * 1e3:.3f} mm beyond the "
                f"{self.method} bound {self.penetration_bound_m * 1e3:.2f} mm",
            )
        allowed = self.limits.blow_up_factor * self._largest_travel + self.limits.blow_up_margin_m
        moved = float(np.sqrt(np.max(np.sum((node_positions - self._rest) ** 2, axis=1))))
        if moved > allowed:
            return Instability(
                "blow_up",
                f"a node moved {moved * 1e3:.1f} mm from rest; the probe travelled at most "
                f"{self._largest_travel * 1e3:.1f} mm (bound {allowed * 1e3:.1f} mm)",
            )
        margin = self.limits.landmark_jump_margin_m
        if margin is not None and previous_landmarks is not None and landmarks.size:
            jump = float(np.sqrt(np.max(np.sum((landmarks - previous_landmarks) ** 2, axis=1))))
            if jump > probe_motion + margin:
                return Instability(
                    "landmark_jump",
                    f"a landmark jumped {jump * 1e3:.2f} mm in one step; the probe moved at "
                    f"most {probe_motion * 1e3:.2f} mm per step lately",
                )
        return None
