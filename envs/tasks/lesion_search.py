"""``probegym/LesionSearch-v0``: find a lesion, centre it in the image and hold contact."""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from gymnasium import spaces
from numpy.typing import NDArray

import tissue
from envs.errors import (
    EnvConfigError,
    check_failure_reward,
    check_positive,
    finite_number,
    number_pair,
)
from envs.observations import LesionInImage, lesion_in_image, tissue_step_info
from envs.probe_env import ProbeEnv, StepState
from envs.rotations import quat_matrix, turn_matrix

#: The registered episode length [steps] (6 s at 20 ms).
MAX_EPISODE_STEPS = 300
#: Bound of the ``lesion`` observation's lengths [m].
LESION_BOUND_M = 0.1


@dataclass(frozen=True)
class LesionSearchConfig:
    """LesionSearch's settings (keyword arguments of ``gymnasium.make``).

    Attributes:
        target_lesions: lesion numbers drawn from at reset; None: on the built-in phantom
            :data:`envs.probe_env.PHANTOM_TARGET_LESIONS` (those under gently
            sloped skin), elsewhere every lesion 10 mm to the imaging depth less 5 mm under
            the skin.
        start_offset_range_m: the start's distance from the lesion along the probe's x axis
            (the image's lateral axis), drawn uniformly, with a random sign [m]; the default
            puts the lesion beyond half the 40 mm aperture, out of the image.
        start_tilt_rad: the start's tilt noise, uniform in +- this about each in-plane axis.
        centre_tolerance_m: success band of the lesion's lateral offset from the image's
            centre line [m].
        force_band_n: (low, high) success band of the normal contact force [N].
        hold_steps: steps the lesion must stay centred, in view, the force in band.
        hard_force_n: contact force that ends the episode as a failure [N].
        failure_reward: the ``failure`` term on a failing last step (<= 0); None:
            -(max_episode_steps + 1), so that a failing episode returns less than any other.
        workspace_m: how far the probe's target may go from the start sideways [m].
        max_press_m: and into the tissue, along the start's pressing direction [m].
        max_lift_m: and away from it [m].
        max_turn_rad: how far the target may turn from the start's orientation [rad].
    """

    target_lesions: tuple[int, ...] | None = None
    start_offset_range_m: tuple[float, float] = (0.024, 0.030)
    start_tilt_rad: float = math.radians(2.0)
    centre_tolerance_m: float = 0.003
    force_band_n: tuple[float, float] = (0.5, 4.0)
    hold_steps: int = 15
    hard_force_n: float = 10.0
    failure_reward: float | None = None
    workspace_m: float = 0.04
    max_press_m: float = 0.035
    max_lift_m: float = 0.02
    max_turn_rad: float = math.radians(30.0)

    def __post_init__(self) -> None:
        check_failure_reward(self.failure_reward)
        check_positive(
            self,
            (
                "centre_tolerance_m",
                "hard_force_n",
                "workspace_m",
                "max_press_m",
                "max_lift_m",
                "max_turn_rad",
            ),
        )
        if not (finite_number(self.start_tilt_rad) and self.start_tilt_rad >= 0):
            raise EnvConfigError(f"start_tilt_rad must be >= 0; got {self.start_tilt_rad!r}")
        offsets = number_pair(self.start_offset_range_m)
        if offsets is None or not (0.0 <= offsets[0] <= offsets[1] <= self.workspace_m):
            raise EnvConfigError(
                f"start_offset_range_m must be (low, high) with 0 <= low <= high <= "
                f"workspace_m ({self.workspace_m!r} m); got {self.start_offset_range_m!r}"
            )
        band = number_pair(self.force_band_n)
        if band is None or not (0.0 <= band[0] < band[1] < self.hard_force_n):
            raise EnvConfigError(
                f"force_band_n must be (low, high) with 0 <= low < high < hard_force_n "
                f"({self.hard_force_n!r} N); got {self.force_band_n!r}"
            )
        if isinstance(self.hold_steps, bool) or not (
            isinstance(self.hold_steps, numbers.Integral) and self.hold_steps >= 1
        ):
            raise EnvConfigError(f"hold_steps must be a whole number >= 1; got {self.hold_steps!r}")


class LesionSearchEnv(ProbeEnv):
    """Find the target lesion with the robot-held probe, centre it in the image and hold
    the contact force in a band.

    ## Description

    A UR5e-like arm holds a linear ultrasound probe on a hyperelastic finite-element breast
    phantom with stiff lesions (Tagliabue et al. 2020); the tissue's reaction comes back to
    the robot (two-way coupling). The probe starts just touching the skin beside the target
    lesion, displaced 24-30 mm along the image's lateral axis, either way: beyond half the
    40 mm aperture, so the lesion is out of the image (and nothing is seen before the probe
    presses: no contact, no image). The policy must press to get an image, search for the
    lesion as a sonographer does, sweeping along the scan line until it appears, bring it
    to the image's centre line and hold it there with an adequate, safe contact force. A
    ``start_offset_range_m`` under half the aperture (say 10-20 mm) makes the easier task
    where the lesion shows at the first press.

    The policy sees only what a sonographer sees: the lesion in the image (or nothing), the
    force and its own pose. It is not told where the lesion is or on which side; it is
    told, here, that the start is displaced along the probe's x axis (the scan line), so
    sweeping along x, one way and then back, finds it
    (:class:`agents.learning.policies.LesionSearchPolicy` does; the frictionless tissue is dragged
    along by a deep press, so it sweeps lightly and keeps the face on the skin's slope).

    ## Action space

    ``Box(-1, 1, (6,), float32)``, in the probe frame (x: the image's lateral axis, y: into
    the tissue, z: elevation); values beyond the box are clipped, NaN or inf raise:

    | index | meaning | at +1 |
    | --- | --- | --- |
    | 0, 1, 2 | move the probe's target along x, y, z | 5 mm per step |
    | 3, 4, 5 | turn it about x, y, z | 0.05 rad per step |

    (``max_translation_m``, ``max_rotation_rad``). A Cartesian impedance controller (3000
    N/m, 60 N m/rad, critically damped, gravity compensated) tracks the target at 500 Hz;
    the target stays within 40 mm sideways, 35 mm in and 20 mm out of the start pose and 30
    degrees of its orientation. ``control_mode="joint_delta"``: the action is one number per
    joint of the arm (6 for the default), moving its target by up to 0.05 rad per step.

    ## Observation space

    ``Dict`` of float32 boxes (flattenable), and with ``image=True`` a uint8 image:

    | key | shape | meaning |
    | --- | --- | --- |
    | ``probe_pose`` | (7,) | probe position [m] (phantom frame) and quaternion (w, x, y, z) |
    | ``wrench`` | (6,) | F/T force [N], torque [N m] about the face centre, probe frame |
    | ``joint_pos``, ``joint_vel`` | (n,) | the arm's n joints (6 by default) [rad], [rad/s] |
    | ``lesion`` | (4,) | target lesion in the image: lateral, depth, out-of-plane [m], visible |
    | ``image`` | (128, 128, 1) | with ``image=True``: the B-mode image under the probe, uint8 |

    The phantom frame has its origin at the centre of the phantom's base, on the table; the
    quaternion is the one with w >= 0; the wrench is the sensor's, negated, with the probe's
    own weight tared, so pressing into the tissue reads a negative ``wrench[1]`` (the
    normal contact force is ``-wrench[1]``). The lesion is zeros when it is not visible.

    Visible: the probe touches the skin, the lesion lies within the 40 mm aperture and 50 mm
    of depth, and within its radius plus 1 mm of the 2 mm slice.

    ## Rewards

    Named terms, logged already weighted in ``info["reward_terms"]`` (the reward is their
    sum): ``centring`` (-0.5 x |lateral| / 20 mm, capped; -0.5 out of view), ``force``
    (-0.3 x the normal force's distance from the 0.5-4 N band, as a share of the band's
    width, capped at 1), ``smoothness`` (-0.1 x the mean squared change of the action / 4),
    ``success`` (+1 on the step that succeeds) and ``failure`` (-(max_episode_steps + 1) on
    a failing last step, or ``failure_reward``). A step's reward lies in [-0.9, 0] but for
    the last, so an episode ending in failure returns less than any that does not (unless
    ``failure_reward`` is set).

    ## Starting state

    A lesion is drawn from the target lesions; the probe just touches the skin (no
    contact force yet), its pressing axis along the skin's inward normal above the lesion
    tilted up to 2 degrees about each in-plane axis, its long axis down the skin's slope
    (the radial scan plane through the lesion), displaced along that axis by 24-30 mm with
    a random sign: the lesion lies in the image plane, that far to the side, out of the
    image; the tissue at rest. All from the reset's seed.

    The skin slopes there, so the end of the face meets it first. Pressed on that rounded
    edge and slid along the image's lateral axis at a constant depth, the force snaps from
    one skin point to the next (up to 72 % of it lost in one 0.2 mm step at 1,303 tets,
    every FE method; docs/environments.md, "The force along a slide"): a limitation of the
    coarse volume under the skin, not of the task (ForceScan's scripted slide, the face on
    the skin, moves by 1 % a step at most).

    ## Episode end

    Terminated with success when the lesion has stayed visible, within 3 mm of the image's
    centre line, with the normal contact force in 0.5-4 N, for 15 steps (0.3 s); as a
    failure when the contact force exceeds 10 N (``info["force_exceeded"]``), the tissue
    step is not ``ok`` (``info["tissue_unstable"]`` names the status) or the arm's state
    is not finite (``info["robot_unstable"]``). Truncated at ``max_episode_steps`` (300,
    6 s).

    ## Effects

    Its terms need ``force_feedback`` and ``lesion_tracking`` (and the image where it is
    observed; each term's needs are the class's TERM_EFFECTS). Scenes that have them:
    ``full`` (the default), ``imaging`` and ``rigid`` (the breast does not deform and the
    lesions stay at rest: the cheapest scene, to learn to approach, press and sweep);
    ``scene=`` or ``effects=`` choose one (:mod:`envs.effects`), and one that lacks an
    effect is refused when made.

    ## Arguments

    ``gymnasium.make("probegym/LesionSearch-v0", contact="lm", profile="robust",
    mesh=1363, ...)``: see :mod:`envs.probe_env` for the common ones and
    :class:`LesionSearchConfig` for this task's (``start_offset_range_m``,
    ``centre_tolerance_m``, ``force_band_n``, ``hold_steps``, ``hard_force_n``, ...).

    ``domain_randomization=True`` (or a dict, or an :class:`envs.DomainRandomization`) draws
    a patient at each reset (tissue and lesion stiffness, lesions moved at rest) and makes
    the observed ``wrench`` and ``probe_pose`` noisy (F/T bias and noise, pose noise); the
    reset's ``info["variation"]`` says what was drawn. Rewards and success use the simulated
    truth. See :mod:`envs.randomization`.

    ## Version history

    - v0: first release. Since 2026-12 its skin is at the probe's scale by default
      (``collision_edge_m=0.002``; a step whose skin lies in the probe beyond what its
      resolution explains is ``penetrated`` and ends the episode) and its F/T reading is
      the tissue's wrench at the probe's pose; ``collision_edge_m=None`` presses the paper's
      1,004 triangles as the earlier published results did.
    """

    episode_steps: ClassVar[int] = MAX_EPISODE_STEPS
    task_config_type: ClassVar[type] = LesionSearchConfig
    task_config: LesionSearchConfig

    #: The simulated effects each term needs (see :data:`envs.effects.EFFECTS`).
    TERM_EFFECTS: ClassVar[dict[str, tuple[str, ...]]] = {
        **ProbeEnv.COMMON_TERM_EFFECTS,
        "lesion": ("lesion_tracking",),
        "centring": ("lesion_tracking",),
        "force": ("force_feedback",),
        "smoothness": (),
        "success": ("lesion_tracking", "force_feedback"),
        "failure": ("force_feedback",),
    }
    WEIGHTS: ClassVar[dict[str, float]] = {
        "centring": 0.5,
        "force": 0.3,
        "smoothness": 0.1,
    }

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self._candidates = self.target_lesions(min_depth_m=0.010)
        self._target = 0
        self._start_offset = 0.0
        self._held = 0
        self._lesion_now: LesionInImage | None = None

    def _observation_spaces(self) -> dict[str, spaces.Space]:
        observed = super()._observation_spaces()
        bound = LESION_BOUND_M
        observed["lesion"] = spaces.Box(
            np.array([-bound, -bound, -bound, 0.0], dtype=np.float32),
            np.array([bound, bound, bound, 1.0], dtype=np.float32),
            dtype=np.float32,
        )
        return observed

    # ------------------------------------------------------------------ episode

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, NDArray[np.float32]], dict[str, Any]]:
        super().reset(seed=seed)
        rng = self.np_random
        cfg = self.task_config
        label = int(self._candidates[int(rng.integers(len(self._candidates)))])
        self._target = label - 1
        lesion = self.tissue.lesions[self._target]
        _, quat = self.tissue.touching_pose(lesion.rest_centre_m)
        rotation = quat_matrix(quat)
        distance = float(rng.uniform(*cfg.start_offset_range_m))
        sign = 1.0 if rng.integers(2) == 1 else -1.0
        tilt = rng.uniform(-cfg.start_tilt_rad, cfg.start_tilt_rad, size=2)
        tilted = rotation @ turn_matrix(np.array([tilt[0], 0.0, tilt[1]]))
        self._start_offset = sign * distance
        aim = lesion.rest_centre_m + rotation @ np.array([self._start_offset, 0.0, 0.0])
        position, quat = self._touching_pose(aim, tilted)
        self.place_probe(position, quat_matrix(quat))
        self._held = 0
        self._lesion_now = self._lesion(0.0)
        return self._observation(), self._info(None, {}, False) | self._variation_info()

    def _touching_pose(
        self, aim: NDArray[np.float64], rotation: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The pose that just touches the skin along ``rotation``'s y axis through ``aim``,
        with ``rotation``'s x axis (the scan line along which the start is offset: the
        tissue's default roll, down the slope at the new direction, may turn it, and near
        the apex by much)."""
        direction = rotation[:, 1]
        _, quat = self.tissue.touching_pose(aim, direction, roll_rad=0.0)
        unrolled = quat_matrix(quat)
        # The roll turns x towards -z about the pressing axis: x(r) = cos r x0 - sin r z0.
        wanted = rotation[:, 0]
        roll = math.atan2(-float(wanted @ unrolled[:, 2]), float(wanted @ unrolled[:, 0]))
        return self.tissue.touching_pose(aim, direction, roll_rad=roll)

    def _track(self, state: StepState) -> None:
        self._lesion_now = self._lesion(state.force_n)

    def _succeeded(self, state: StepState, failed: bool) -> bool:
        cfg, lesion = self.task_config, self._lesion_now
        assert lesion is not None  # tracked on every step
        low, high = cfg.force_band_n
        in_band = (
            lesion.visible
            and abs(lesion.true_lateral_m) <= cfg.centre_tolerance_m
            and low <= state.normal_n <= high
        )
        return self._held_for(in_band, failed, cfg.hold_steps)

    # ------------------------------------------------------------------ terms

    def _lesion(self, force: float) -> LesionInImage:
        position, rotation = self.probe_pose()
        lesion = self.tissue.lesions[self._target]
        return lesion_in_image(
            self.tissue.lesion_centroids_m((self._target,))[0],
            lesion.radius_m,
            position,
            rotation,
            force,
            self.imaging,
        )

    def _reward_terms(self, state: StepState, success: bool, failed: bool) -> dict[str, float]:
        cfg, weights = self.task_config, self.WEIGHTS
        lesion, normal, action = self._lesion_now, state.normal_n, state.action
        assert lesion is not None  # tracked on every step
        if lesion.visible:
            centring = min(1.0, abs(lesion.true_lateral_m) / (0.5 * self.imaging.aperture_m))
        else:
            centring = 1.0
        low, high = cfg.force_band_n
        outside = max(0.0, low - normal, normal - high) / (high - low)
        change = float(np.mean((action - self._last_action) ** 2)) / 4.0
        return {
            "centring": -weights["centring"] * centring,
            "force": -weights["force"] * min(1.0, outside),
            "smoothness": -weights["smoothness"] * min(1.0, change),
            "success": 1.0 if success else 0.0,
            "failure": self.failure_reward() if failed else 0.0,
        }

    def _observation(self) -> dict[str, NDArray[np.float32]]:
        observed = self._common_observation()
        lesion = self._lesion_now
        bound = LESION_BOUND_M
        observed["lesion"] = (
            np.zeros(4, dtype=np.float32)
            if lesion is None
            else np.clip(lesion.as_array(), -bound, 1.0).astype(np.float32)
        )
        return observed

    def _info(
        self,
        step: tissue.TissueStep | None,
        terms: dict[str, float],
        success: bool,
        failure: dict[str, Any] | None = None,
    ) -> dict[str, Any]:
        lesion = self._lesion_now
        info: dict[str, Any] = {
            "is_success": bool(success),
            "reward_terms": dict(terms),
            "contact_force_n": self.contact_force_n(step),
            "normal_force_n": self.normal_force_n(step),
            "target_lesion": self._target + 1,
            "start_offset_m": float(self._start_offset),
            "lesion_lateral_m": None if lesion is None else float(lesion.true_lateral_m),
            "lesion_visible": False if lesion is None else bool(lesion.visible),
            "held_steps": int(self._held),
        }
        if step is not None:
            info["tissue"] = tissue_step_info(step)
        info.update(failure or {})
        return info
