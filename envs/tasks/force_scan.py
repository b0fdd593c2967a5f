"""``probegym/ForceScan-v0``: sweep a line on the skin under a controlled force, the face
kept normal to the skin."""

from __future__ import annotations

import math
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
from envs.observations import tissue_step_info
from envs.probe_env import ProbeEnv, StepState
from envs.rotations import quat_matrix

#: The registered episode length [steps] (4 s at 20 ms).
MAX_EPISODE_STEPS = 200
#: Bound of the ``path`` observation's lengths [m].
PATH_BOUND_M = 0.1
#: The stride of the walk along the skin that finds the path's end [m].
STRIDE_M = 0.005
#: How far inside the skin :meth:`ForceScanEnv.rest_normal` aims its probes [m].
REACH_M = 0.03


@dataclass(frozen=True)
class ForceScanConfig:
    """ForceScan's settings (keyword arguments of ``gymnasium.make``).

    Attributes:
        target_lesions: lesions above which the path may start, drawn at reset; None: on
            the built-in phantom :data:`envs.probe_env.PHANTOM_TARGET_LESIONS`
            (under gently sloped skin), elsewhere every lesion.
        path_length_range_m: the path's length along the rest skin, drawn uniformly [m]
            (the start-to-end chord, ``info["path_length_m"]``, is shorter).
        end_tolerance_m: how close (along the skin) the probe's centre must come to the
            path's end [m].
        max_tilt_rad: the largest angle between the probe's pressing axis and the rest
            skin's inward normal under the probe's centre that counts as normal [rad].
        force_band_n: (low, high) band of the normal contact force [N].
        min_good_share: the share of the steps since the force first reached the band on
            which both the tilt and the force must have been good for a success.
        hard_force_n: contact force that ends the episode as a failure [N].
        failure_reward: the ``failure`` term on a failing last step (<= 0); None:
            -(max_episode_steps + 1), so that a failing episode returns less than any other.
        progress_weight: what the whole path's progress earns (> 0): the ``progress`` term
            is this times the step's progress as a share of the path's length.
        workspace_m: how far the probe's target may go from the start sideways [m].
        max_press_m: and into the tissue, along the start's pressing direction [m].
        max_lift_m: and away from it [m].
        max_turn_rad: how far the target may turn from the start's orientation [rad].
    """

    target_lesions: tuple[int, ...] | None = None
    path_length_range_m: tuple[float, float] = (0.030, 0.040)
    end_tolerance_m: float = 0.003
    max_tilt_rad: float = math.radians(5.0)
    force_band_n: tuple[float, float] = (1.0, 3.0)
    min_good_share: float = 0.9
    hard_force_n: float = 10.0
    failure_reward: float | None = None
    progress_weight: float = 1.0
    workspace_m: float = 0.06
    max_press_m: float = 0.035
    max_lift_m: float = 0.02
    max_turn_rad: float = math.radians(75.0)

    def __post_init__(self) -> None:
        check_failure_reward(self.failure_reward)
        check_positive(
            self,
            (
                "end_tolerance_m",
                "max_tilt_rad",
                "hard_force_n",
                "workspace_m",
                "max_press_m",
                "max_lift_m",
                "max_turn_rad",
                "progress_weight",
            ),
        )
        lengths = number_pair(self.path_length_range_m)
        if lengths is None or not (0.0 < lengths[0] <= lengths[1] < self.workspace_m):
            raise EnvConfigError(
                f"path_length_range_m must be (low, high) with 0 < low <= high < workspace_m "
                f"({self.workspace_m!r} m); got {self.path_length_range_m!r}"
            )
        band = number_pair(self.force_band_n)
        if band is None or not (0.0 <= band[0] < band[1] < self.hard_force_n):
            raise EnvConfigError(
                f"force_band_n must be (low, high) with 0 <= low < high < hard_force_n "
                f"({self.hard_force_n!r} N); got {self.force_band_n!r}"
            )
        if not (finite_number(self.min_good_share) and 0.0 < self.min_good_share <= 1.0):
            raise EnvConfigError(
                f"min_good_share must be a number in (0, 1]; got {self.min_good_share!r}"
            )


class ForceScanEnv(ProbeEnv):
    """Sweep a line on the skin with the robot-held probe, holding the normal force in a
    band and the probe's face normal to the skin.

    ## Description

    A UR5e-like arm holds a linear ultrasound probe on a hyperelastic finite-element breast
    phantom (Tagliabue et al. 2020), coupled two ways. The probe starts just touching the
    skin above a lesion, its long axis (x, the image's lateral axis) down the skin's slope;
    the policy must press, then sweep the probe 30-40 mm along its elevation axis (z) to
    the path's end, as a sonographer's linear sweep moves the image plane across the
    tissue, with the normal force within 1-3 N and the pressing axis within 5 degrees of
    the skin's normal.

    The sweep is along z, not x: the phantom's skin is strongly curved (its normal turns
    40-55 degrees over a path) and the contact is frictionless for every method (LM and
    penalty are; prescribed displacement slides its online node set; PBD's contact has no
    friction). Across the direction of travel the 40 mm face lies along the skin's slope
    and can follow its normal; along x it rides over the dome (see
    ``docs/design-decisions.md``). The price: the probe's leading side ploughs the pressed
    tissue ahead of it, a tangential force that ``contact_force_n`` (and the 10 N hard
    limit) counts (up to about 5.5 N under the scripted policy while the normal force stays
    near 1.8 N; its success rates are in docs/environments.md).

    The policy is told the path and the skin's orientation under the probe (the ``path``
    observation); how it keeps the face normal is its business
    (:class:`agents.learning.policies.ForceScanPolicy` turns its pressing axis toward that normal).

    ## Action space

    ``Box(-1, 1, (6,), float32)``, in the probe frame (x: the image's lateral axis, y: into
    the tissue, z: elevation); values beyond the box are clipped, NaN or inf raise:

    | index | meaning | at +1 |
    | --- | --- | --- |
    | 0, 1, 2 | move the probe's target along x, y, z | 5 mm per step |
    | 3, 4, 5 | turn it about x, y, z | 0.05 rad per step |

    (``max_translation_m``, ``max_rotation_rad``). A Cartesian impedance controller tracks
    the target at 500 Hz; the target stays within 60 mm sideways, 35 mm in and 20 mm out of
    the start pose and 75 degrees of its orientation (the skin turns up to 55 along a
    path). ``control_mode="joint_delta"``: the
    action is one number per joint of the arm (6 for the default), moving its target by up
    to 0.05 rad per step.

    ## Observation space

    ``Dict`` of float32 boxes (flattenable), and with ``image=True`` a uint8 image:

    | key | shape | meaning |
    | --- | --- | --- |
    | ``probe_pose`` | (7,) | probe position [m] (phantom frame) and quaternion (w, x, y, z) |
    | ``wrench`` | (6,) | F/T force [N], torque [N m] about the face centre, probe frame |
    | ``joint_pos``, ``joint_vel`` | (n,) | the arm's n joints (6 by default) [rad], [rad/s] |
    | ``path`` | (9,) | the path's end [m], the skin's normal, progress, length [m], share |
    | ``image`` | (128, 128, 1) | with ``image=True``: the B-mode image under the probe, uint8 |

    The phantom frame has its origin at the centre of the phantom's base; the quaternion is
    the one with w >= 0; the wrench is the sensor's, negated, with the probe's weight tared
    (the normal contact force is ``-wrench[1]``). ``path``: [0:3] the path's end (a point on
    the rest skin) from the probe's centre, in the probe frame [m] (its part along the skin
    is where to go; its y component is mostly the press depth); [3:6] the rest skin's
    inward normal at its point nearest the probe's centre, in the probe frame (the tilt is
    its angle from +y: (0, 1, 0) is normal); [6] progress: the probe centre's displacement
    from the path's start along the start-to-end chord, in [0, length] [m]; [7] the path's
    length [m]; [8] the good-step share: of the steps since the normal force first reached
    the band, those with the force in band and the tilt within tolerance (1 before).

    ## Rewards

    Named terms, logged already weighted in ``info["reward_terms"]`` (the reward is their
    sum): ``progress`` (+``progress_weight``, default 1, x the step's change of progress as a
    share of the path's length: the whole chord earns ``progress_weight``), ``force`` (-0.3 x
    the normal force's distance from the 1-3 N band, as a share of the band's width, capped
    at 1), ``tilt`` (-0.3 x the tilt beyond 5 degrees, as a share of 5 degrees, capped at 1),
    ``smoothness`` (-0.1 x the mean squared change of the action / 4), ``success`` (+1 on
    the step that succeeds) and ``failure`` (-(max_episode_steps + 1) on a failing last
    step, or ``failure_reward``).

    ## Starting state

    A lesion is drawn from the target lesions; the path starts on the rest skin above it:
    the probe just touches the skin there (no contact force yet), its pressing axis along
    the rest skin's inward normal at the touching point, its long axis down the slope. The
    path runs 30-40 mm (drawn) along the rest skin from there, heading along the probe's
    +z or -z (drawn), in 5 mm strides kept tangent to the skin; its end is the rest skin
    point reached. ``path_length_m`` is the straight start-to-end chord (shorter, the skin
    being curved: progress runs along it), ``skin_length_m`` the drawn length. The tissue
    at rest. All from the reset's seed.

    ## Episode end

    Terminated with success when the probe's centre is within 3 mm of the path's end along
    the skin (the remaining vector less its part along the rest normal at the end) with
    the normal force in band, having had the force in 1-3 N and the tilt within 5 degrees
    on at least 90 % of the steps since the force first reached 1 N (the press before that
    does not count); as a failure when the contact force exceeds 10 N
    (``info["force_exceeded"]``), the tissue step is not ``ok`` (``info["tissue_unstable"]``
    names the status) or the arm's state is not finite (``info["robot_unstable"]``).
    Truncated at ``max_episode_steps`` (200, 4 s).

    The tilt is the angle between the probe's pressing axis (y) and the rest skin's inward
    normal at the rest skin's point nearest the probe's centre (:meth:`rest_normal`, from
    ``tissue.Tissue.rest_skin_normal``).

    ``info`` carries ``normal_force_n``, ``contact_force_n``, ``tilt_rad``, ``progress_m``,
    ``path_length_m``, ``skin_length_m``, ``remaining_m`` (along the skin), ``good_share``,
    ``skin_penetration_m`` (the tissue step's deepest skin penetration by the probe [m]:
    PBD's honest measure; 0 before the first step) and ``tissue`` (the step's status and
    diagnostics).

    ## Effects

    Its terms need ``force_feedback`` (and the image where it is observed; each term's
    needs are the class's TERM_EFFECTS). Scenes that have it: ``full`` (the default),
    ``imaging`` and ``rigid`` (the breast does not deform: the cheapest scene);
    ``scene=`` or ``effects=`` choose one (:mod:`envs.effects`), and one that lacks an
    effect is refused when made.

    ## Arguments

    ``gymnasium.make("probegym/ForceScan-v0", contact="lm", profile="robust", mesh=1363,
    ...)``: see :mod:`envs.probe_env` for the common ones and :class:`ForceScanConfig` for
    this task's (``path_length_range_m``, ``end_tolerance_m``, ``max_tilt_rad``,
    ``force_band_n``, ``min_good_share``, ``hard_force_n``, ...). Prescribed displacement
    needs its sliding node set (the robust profile's); ``contact="prescribed",
    profile="paper"`` (a node set fixed at first contact: it cannot sweep) is refused.

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
    task_config_type: ClassVar[type] = ForceScanConfig
    task_config: ForceScanConfig

    #: The simulated effects each term needs (see :data:`envs.effects.EFFECTS`).
    TERM_EFFECTS: ClassVar[dict[str, tuple[str, ...]]] = {
        **ProbeEnv.COMMON_TERM_EFFECTS,
        "path": ("force_feedback",),
        "progress": (),
        "force": ("force_feedback",),
        "tilt": (),
        "smoothness": (),
        "success": ("force_feedback",),
        "failure": ("force_feedback",),
    }
    #: The per-step terms' weights (progress's is ``ForceScanConfig.progress_weight``).
    WEIGHTS: ClassVar[dict[str, float]] = {
        "force": 0.3,
        "tilt": 0.3,
        "smoothness": 0.1,
    }

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        params = self.tissue.resolved.params
        if self.tissue.contact == "prescribed" and not getattr(params, "sliding", False):
            raise EnvConfigError(
                f"ForceScan needs prescribed displacement's sliding node set; profile "
                f"{self.tissue.spec.profile!r} fixes the set at first contact (it cannot "
                f"sweep): use profile='robust'"
            )
        self._candidates = self.target_lesions()
        self._target = 0
        self._path_start = np.zeros(3)
        self._path_end = np.zeros(3)
        self._end_normal = np.array([0.0, 0.0, -1.0])
        self._chord = np.array([0.0, 0.0, 1.0])
        self._length = 0.0
        self._skin_length = 0.0
        self._progress = 0.0
        self._progress_before = 0.0
        self._tilt = 0.0
        self._normal = np.array([0.0, 0.0, -1.0])
        self._started = False
        self._counted = 0
        self._good = 0

    def _observation_spaces(self) -> dict[str, spaces.Space]:
        observed = super()._observation_spaces()
        bound = PATH_BOUND_M
        observed["path"] = spaces.Box(
            np.array([-bound] * 3 + [-1.0] * 3 + [0.0] * 3, dtype=np.float32),
            np.array([bound] * 3 + [1.0] * 3 + [bound, bound, 1.0], dtype=np.float32),
            dtype=np.float32,
        )
        return observed

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, NDArray[np.float32]], dict[str, Any]]:
        super().reset(seed=seed)
        rng = self.np_random
        cfg = self.task_config
        label = int(self._candidates[int(rng.integers(len(self._candidates)))])
        self._target = label - 1
        lesion = self.tissue.lesions[self._target]
        above, _ = self.tissue.touching_pose(lesion.rest_centre_m)
        normal = self.rest_normal(above)
        if normal is None:  # pragma: no cover - a lesion under the skin has skin above it
            raise EnvConfigError(f"lesion {label} has no rest skin above it: pick another")
        position, quat = self.tissue.touching_pose(above + REACH_M * normal, normal)
        rotation = quat_matrix(quat)
        self._skin_length = float(rng.uniform(*cfg.path_length_range_m))
        sign = 1.0 if rng.integers(2) == 1 else -1.0
        self._path_start = position.copy()
        end, end_normal = self._walk(position, normal, sign * rotation[:, 2], label)
        self._path_end = end
        self._end_normal = end_normal
        chord = end - position
        self._length = float(np.linalg.norm(chord))
        self._chord = chord / self._length
        self.place_probe(position, rotation)
        self._progress = 0.0
        self._progress_before = 0.0
        self._tilt = self._tilt_now()
        self._started = False
        self._counted = 0
        self._good = 0
        return self._observation(), self._info(None, {}, False) | self._variation_info()

    def _walk(
        self,
        start: NDArray[np.float64],
        normal: NDArray[np.float64],
        heading: NDArray[np.float64],
        label: int,
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The rest skin point ``self._skin_length`` along the skin from ``start``, heading
        along ``heading`` (kept tangent: each stride of at most :data:`STRIDE_M` goes along
        the heading less its part along the skin's normal, then back onto the skin along
        the normal); that point and the rest skin's inward normal there."""
        point, heading = start.copy(), heading.copy()
        left = self._skin_length
        while left > 0.0:
            stride = min(STRIDE_M, left)
            tangent = heading - (heading @ normal) * normal
            tangent /= float(np.linalg.norm(tangent))
            aim = point + stride * tangent
            try:
                point, normal = self.tissue.rest_skin_normal(aim + REACH_M * normal, -normal)
            except tissue.TissueInputError as error:  # pragma: no cover - off the phantom
                raise EnvConfigError(
                    f"the path from lesion {label} leaves the skin ({error}): set "
                    f"target_lesions or a shorter path_length_range_m"
                ) from error
            heading = tangent
            left -= stride
        return point, normal

    def _track(self, state: StepState) -> None:
        self._progress_before = self._progress
        if state.finite:
            self._progress = self._progress_now()
            self._tilt = self._tilt_now()

    def _succeeded(self, state: StepState, failed: bool) -> bool:
        cfg = self.task_config
        low, high = cfg.force_band_n
        in_band = low <= state.normal_n <= high
        if in_band:
            self._started = True
        if self._started:
            self._counted += 1
            self._good += int(in_band and self._tilt <= cfg.max_tilt_rad)
        return (
            not failed
            and self._started
            and in_band
            and self._remaining() <= cfg.end_tolerance_m
            and self._good_share() >= cfg.min_good_share
        )

    # ------------------------------------------------------------------ terms

    def _tilt_now(self) -> float:
        """The angle between the probe's pressing axis and the rest skin's inward normal at
        the rest skin's point nearest the probe's centre [rad] (:meth:`rest_normal`)."""
        position, rotation = self.probe_pose()
        normal = self.rest_normal(position)
        if normal is None:
            return math.pi
        self._normal = normal
        cosine = float(np.clip(normal @ rotation[:, 1], -1.0, 1.0))
        return math.acos(cosine)

    def rest_normal(self, point: NDArray[np.float64]) -> NDArray[np.float64] | None:
        """The rest skin's inward normal at its point nearest ``point`` [m] (one fixed-point
        pass of :meth:`tissue.Tissue.rest_skin_normal`: the normal where the vertical through
        the point leaves the rest skin, then the skin point on the line through the point
        along that normal, and the normal there); None off the skin."""
        try:
            _, normal = self.tissue.rest_skin_normal(point - np.array([0.0, 0.0, REACH_M]))
            _, normal = self.tissue.rest_skin_normal(point + REACH_M * normal, -normal)
        except tissue.TissueInputError:
            return None
        return normal

    def _progress_now(self) -> float:
        position, _ = self.probe_pose()
        along = float((position - self._path_start) @ self._chord)
        return float(np.clip(along, 0.0, self._length))

    def _remaining(self) -> float:
        """The distance from the probe's centre to the path's end along the skin [m]."""
        position, _ = self.probe_pose()
        rest = self._path_end - position
        rest = rest - (rest @ self._end_normal) * self._end_normal
        return float(np.linalg.norm(rest))

    def _good_share(self) -> float:
        return 1.0 if self._counted == 0 else self._good / self._counted

    def _reward_terms(self, state: StepState, success: bool, failed: bool) -> dict[str, float]:
        cfg, weights = self.task_config, self.WEIGHTS
        before, normal, action = self._progress_before, state.normal_n, state.action
        low, high = cfg.force_band_n
        outside = max(0.0, low - normal, normal - high) / (high - low)
        excess = max(0.0, self._tilt - cfg.max_tilt_rad) / cfg.max_tilt_rad
        change = float(np.mean((action - self._last_action) ** 2)) / 4.0
        return {
            "progress": cfg.progress_weight * (self._progress - before) / self._length,
            "force": -weights["force"] * min(1.0, outside),
            "tilt": -weights["tilt"] * min(1.0, excess),
            "smoothness": -weights["smoothness"] * min(1.0, change),
            "success": 1.0 if success else 0.0,
            "failure": self.failure_reward() if failed else 0.0,
        }

    def _observation(self) -> dict[str, NDArray[np.float32]]:
        observed = self._common_observation()
        position, rotation = self.probe_pose()
        remaining = rotation.T @ (self._path_end - position)
        bound = PATH_BOUND_M
        path = np.concatenate(
            [
                np.clip(remaining, -bound, bound),
                rotation.T @ self._normal,
                [min(self._progress, bound), min(self._length, bound), self._good_share()],
            ]
        )
        observed["path"] = path.astype(np.float32)
        return observed

    def _info(
        self,
        step: tissue.TissueStep | None,
        terms: dict[str, float],
        success: bool,
        failure: dict[str, Any] | None = None,
    ) -> dict[str, Any]:
        info: dict[str, Any] = {
            "is_success": bool(success),
            "reward_terms": dict(terms),
            "contact_force_n": self.contact_force_n(step),
            "normal_force_n": self.normal_force_n(step),
            "tilt_rad": float(self._tilt),
            "progress_m": float(self._progress),
            "path_length_m": float(self._length),
            "skin_length_m": float(self._skin_length),
            "remaining_m": self._remaining(),
            "good_share": self._good_share(),
            "target_lesion": self._target + 1,
            "skin_penetration_m": 0.0 if step is None else float(step.skin_penetration_m),
        }
        if step is not None:
            info["tissue"] = tissue_step_info(step)
        info.update(failure or {})
        return info
