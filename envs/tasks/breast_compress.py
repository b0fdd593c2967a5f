"""``probegym/BreastCompress-v0``: compress the breast until a lesion reaches a depth."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from gymnasium import spaces
from numpy.typing import NDArray

import tissue
from envs.errors import EnvConfigError, check_failure_reward
from envs.observations import LesionInImage, lesion_in_image, tissue_step_info
from envs.probe_env import ProbeEnv, StepState
from envs.rotations import quat_matrix, turn_matrix

#: The registered episode length [steps] (5 s at 20 ms).
MAX_EPISODE_STEPS = 250


@dataclass(frozen=True)
class BreastCompressConfig:
    """BreastCompress's settings (keyword arguments of ``gymnasium.make``).

    Attributes:
        target_lesions: lesion numbers drawn from at reset; None: on the built-in phantom
            :data:`envs.probe_env.PHANTOM_TARGET_LESIONS`, elsewhere every lesion 15 mm to
            the imaging depth less 5 mm under the skin.
        compression_range_m: the compression asked, drawn uniformly [m]: how far the lesion
            must move up the image from its depth at the start.
        depth_tolerance_m: success band about the target depth [m].
        hold_steps: steps the lesion must stay in the band, in view, force safe.
        safety_force_n: force above which the ``force`` term penalises [N].
        hard_force_n: force that ends the episode as a failure [N].
        failure_reward: the ``failure`` term on a failing last step (<= 0); None:
            -(max_episode_steps + 1), so that a failing episode returns less than any other.
        start_offset_m: the start's lateral noise, uniform in +- this [m].
        start_tilt_rad: the start's tilt noise, uniform in +- this about each in-plane axis.
        workspace_m: how far the probe's target may go from the start sideways [m].
        max_press_m: and into the tissue, along the start's pressing direction [m].
        max_lift_m: and away from it [m].
        max_turn_rad: how far the target may turn from the start's orientation [rad].
        max_compression_strain: None (v0): the compression asked is the one drawn; a number
            in (0, 1): at most this share of the lesion's depth under the probe at the start
            (a shallow lesion asked to move 5-7 mm would need the tissue above it squeezed by
            up to 47 %, beyond the safety force; docs/baselines.md).
    """

    target_lesions: tuple[int, ...] | None = None
    compression_range_m: tuple[float, float] = (0.005, 0.007)
    depth_tolerance_m: float = 0.001
    hold_steps: int = 25
    safety_force_n: float = 5.0
    hard_force_n: float = 10.0
    failure_reward: float | None = None
    start_offset_m: float = 0.002
    start_tilt_rad: float = math.radians(2.0)
    workspace_m: float = 0.03
    max_press_m: float = 0.035
    max_lift_m: float = 0.02
    max_turn_rad: float = math.radians(30.0)
    max_compression_strain: float | None = None

    def __post_init__(self) -> None:
        check_failure_reward(self.failure_reward)
        strain = self.max_compression_strain
        if strain is not None and not (
            isinstance(strain, (int, float)) and not isinstance(strain, bool) and 0.0 < strain < 1.0
        ):
            raise EnvConfigError(
                f"max_compression_strain must be None or a share of the lesion's depth in "
                f"(0, 1); got {strain!r}"
            )
        low, high = self.compression_range_m
        if not (0.0 < low <= high < 0.05):
            raise EnvConfigError(
                f"compression_range_m must be (low, high) with 0 < low <= high < 0.05 m; got "
                f"{self.compression_range_m!r}"
            )
        if not (isinstance(self.hold_steps, int) and self.hold_steps >= 1):
            raise EnvConfigError(f"hold_steps must be a whole number >= 1; got {self.hold_steps!r}")
        if not 0.0 < self.safety_force_n < self.hard_force_n:
            raise EnvConfigError(
                f"need 0 < safety_force_n < hard_force_n; got {self.safety_force_n!r}, "
                f"{self.hard_force_n!r}"
            )
        for name in (
            "depth_tolerance_m",
            "workspace_m",
            "max_press_m",
            "max_lift_m",
            "max_turn_rad",
        ):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise EnvConfigError(f"{name} must be positive; got {value!r}")
        for name in ("start_offset_m", "start_tilt_rad"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise EnvConfigError(f"{name} must be >= 0; got {value!r}")


class BreastCompressEnv(ProbeEnv):
    """Press the breast with the robot-held probe until a lesion reaches a target depth.

    ## Description

    A UR5e-like arm holds a linear ultrasound probe against a hyperelastic finite-element
    breast phantom with stiff lesions (E = 2850 Pa, lesions 4 x stiffer; Tagliabue et al.
    2020). Sonographers compress the breast to bring a lesion into a better imaging depth
    and to judge its stiffness; here the policy must move the target lesion up the image by
    a given compression (5-7 mm) and hold it there, in view, without pressing harder than
    is safe. The tissue's reaction comes back to the robot (two-way coupling): pressing
    means working against the breast.

    ## Action space

    ``Box(-1, 1, (6,), float32)``, in the probe frame (x: the image's lateral axis, y: into
    the tissue, z: elevation); values beyond the box are clipped, NaN or inf raise:

    | index | meaning | at +1 |
    | --- | --- | --- |
    | 0, 1, 2 | move the probe's target along x, y, z | 5 mm per step |
    | 3, 4, 5 | turn it about x, y, z | 0.05 rad per step |

    (``max_translation_m``, ``max_rotation_rad``). A Cartesian impedance controller (3000
    N/m, 60 N m/rad, critically damped, gravity compensated) tracks the target at 500 Hz;
    the target stays within 30 mm sideways, 35 mm in and 20 mm out of the start pose and 30
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
    | ``target_depth`` | (1,) | the depth to bring it to [m] |
    | ``image`` | (128, 128, 1) | with ``image=True``: B-mode image, uint8 (envs.ultrasound) |

    The image (off by default, and then never computed) is the deformed slice under the
    probe, row 0 at the face, black without contact; a ``BModeConfig`` instead of True sets
    its size and acoustics. The phantom frame has its origin at the centre of the phantom's
    base, on the table; the
    quaternion is the one with w >= 0; the wrench is the sensor's, negated, with the probe's
    own weight tared. The lesion is zeros when it is not visible.

    Visible: the probe touches the skin, the lesion lies within the 40 mm aperture and 50 mm
    of depth, and within its radius plus 1 mm of the 2 mm slice.

    ## Rewards

    Named terms, logged already weighted in ``info["reward_terms"]`` (the reward is their
    sum): ``depth_error`` (-0.5 x |depth - target| / 10 mm, capped; -0.5 out of view),
    ``centring`` (-0.2 x |lateral| / 20 mm; -0.2 out of view), ``force`` (-0.2 x the force
    above 5 N as a share of the 5 N up to the hard limit), ``smoothness`` (-0.1 x the mean
    squared change of the action / 4), ``success`` (+1 on the step that succeeds) and
    ``failure`` (-(max_episode_steps + 1) on a failing last step, or ``failure_reward``).
    A step's reward lies in [-1, 0] but for the last, so an episode ending in failure
    returns less than any that does not (unless ``failure_reward`` is set).

    ## Starting state

    The probe just touches the skin above a lesion drawn from the target lesions, normal to
    the skin (its long axis down the slope), shifted up to 2 mm sideways and tilted up to 2
    degrees, the tissue at rest; the compression asked is drawn from 5-7 mm. All from the
    reset's seed.

    ## Episode end

    Terminated with success when the lesion has stayed visible, within 1 mm of the target
    depth and under the safety force for 25 steps (0.5 s); as a failure when the contact
    force exceeds 10 N (``info["force_exceeded"]``), the tissue step is not ``ok``
    (``info["tissue_unstable"]`` names the status) or the arm's state is not finite.
    Truncated at ``max_episode_steps`` (250, 5 s).

    ## Effects

    Its terms need ``deformation``, ``force_feedback`` and ``lesion_tracking`` (and the
    image where it is observed; each term's needs are the class's TERM_EFFECTS). Scenes
    that have them: ``full`` (the default) and ``imaging``; ``scene=`` or ``effects=``
    choose one (:mod:`envs.effects`), and one that lacks an effect is refused when made.

    ## Arguments

    ``gymnasium.make("probegym/BreastCompress-v0", contact="lm", profile="robust",
    mesh=1363, ...)``: see :mod:`envs.probe_env` for the common ones and
    :class:`BreastCompressConfig` for this task's. Defaults: Lagrange-multiplier contact
    (exact forces), the robust profile (stable under jerky poses), the 1,303-tet phantom.

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
    task_config_type: ClassVar[type] = BreastCompressConfig
    task_config: BreastCompressConfig

    #: The simulated effects each term needs (see :data:`envs.effects.EFFECTS`).
    TERM_EFFECTS: ClassVar[dict[str, tuple[str, ...]]] = {
        **ProbeEnv.COMMON_TERM_EFFECTS,
        "lesion": ("deformation", "lesion_tracking"),
        "target_depth": (),
        "depth_error": ("deformation", "lesion_tracking"),
        "centring": ("deformation", "lesion_tracking"),
        "force": ("force_feedback",),
        "smoothness": (),
        "success": ("deformation", "lesion_tracking"),
        "failure": ("force_feedback",),
    }
    WEIGHTS: ClassVar[dict[str, float]] = {
        "depth_error": 0.5,
        "centring": 0.2,
        "force": 0.2,
        "smoothness": 0.1,
    }

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self._candidates = self.target_lesions(min_depth_m=0.015)
        self._target = 0
        self._target_depth = 0.0
        self._held = 0
        self._lesion_now: LesionInImage | None = None

    def _observation_spaces(self) -> dict[str, spaces.Space]:
        observed = super()._observation_spaces()
        bound = 0.1
        observed["lesion"] = spaces.Box(
            np.array([-bound, -bound, -bound, 0.0], dtype=np.float32),
            np.array([bound, bound, bound, 1.0], dtype=np.float32),
            dtype=np.float32,
        )
        observed["target_depth"] = spaces.Box(0.0, bound, shape=(1,), dtype=np.float32)
        return observed

    # ------------------------------------------------------------------ episode

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, NDArray[Any]], dict[str, Any]]:
        super().reset(seed=seed)
        rng = self.np_random
        cfg = self.task_config
        label = int(self._candidates[int(rng.integers(len(self._candidates)))])
        self._target = label - 1
        lesion = self.tissue.lesions[self._target]
        position, quat = self.tissue.touching_pose(lesion.rest_centre_m)
        rotation = quat_matrix(quat)
        offset = rng.uniform(-cfg.start_offset_m, cfg.start_offset_m, size=2)
        tilt = rng.uniform(-cfg.start_tilt_rad, cfg.start_tilt_rad, size=2)
        direction = (
            rotation @ turn_matrix(np.array([tilt[0], 0.0, tilt[1]])) @ np.array([0.0, 1.0, 0.0])
        )
        aim = lesion.rest_centre_m + rotation @ np.array([offset[0], 0.0, offset[1]])
        position, quat = self.tissue.touching_pose(aim, direction)
        self.place_probe(position, quat_matrix(quat))
        compression = float(rng.uniform(*cfg.compression_range_m))
        start_depth = float(
            (
                self._start_rot.T
                @ (self.tissue.lesion_centroids_m((self._target,))[0] - self._start_pos)
            )[1]
        )
        if cfg.max_compression_strain is not None:
            compression = min(compression, cfg.max_compression_strain * start_depth)
        self._target_depth = start_depth - compression
        self._held = 0
        self._lesion_now = self._lesion(0.0)
        return self._observation(), self._info(None, {}, False) | self._variation_info()

    def _track(self, state: StepState) -> None:
        self._lesion_now = self._lesion(state.force_n)

    def _succeeded(self, state: StepState, failed: bool) -> bool:
        cfg, lesion = self.task_config, self._lesion_now
        assert lesion is not None  # tracked on every step
        in_band = (
            lesion.visible
            and abs(lesion.true_depth_m - self._target_depth) <= cfg.depth_tolerance_m
            and state.force_n <= cfg.safety_force_n
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
        lesion, force, action = self._lesion_now, state.force_n, state.action
        assert lesion is not None  # tracked on every step
        if lesion.visible:
            depth = min(1.0, abs(lesion.true_depth_m - self._target_depth) / 0.01)
            centring = min(1.0, abs(lesion.true_lateral_m) / (0.5 * self.imaging.aperture_m))
        else:
            depth, centring = 1.0, 1.0
        over = max(0.0, force - cfg.safety_force_n) / (cfg.hard_force_n - cfg.safety_force_n)
        change = float(np.mean((action - self._last_action) ** 2)) / 4.0
        return {
            "depth_error": -weights["depth_error"] * depth,
            "centring": -weights["centring"] * centring,
            "force": -weights["force"] * min(1.0, over),
            "smoothness": -weights["smoothness"] * min(1.0, change),
            "success": 1.0 if success else 0.0,
            "failure": self.failure_reward() if failed else 0.0,
        }

    def _observation(self) -> dict[str, NDArray[Any]]:
        observed = self._common_observation()
        lesion = self._lesion_now
        observed["lesion"] = (
            np.zeros(4, dtype=np.float32)
            if lesion is None
            else np.clip(lesion.as_array(), -0.1, 1.0)
        )
        observed["target_depth"] = np.array(
            [np.clip(self._target_depth, 0.0, 0.1)], dtype=np.float32
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
            "target_lesion": self._target + 1,
            "target_depth_m": float(self._target_depth),
            "lesion_depth_m": None if lesion is None else float(lesion.true_depth_m),
            "held_steps": int(self._held),
        }
        if step is not None:
            info["tissue"] = tissue_step_info(step)
        info.update(failure or {})
        return info
