"""``probegym/ForceScan-v1``: ForceScan-v0's task with a reward and an observation that teach
it (the same paths, tolerances, force band, good-step share and force limit)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from gymnasium import spaces
from numpy.typing import NDArray

import tissue
from envs.probe_env import StepState
from envs.tasks.force_scan import ForceScanConfig, ForceScanEnv
from envs.tasks.shaping import ShapedRewardConfig, action_change, check_non_negative

#: v1's translation at |a| = 1: 2 mm a step (v0: 5 mm), so that a fresh policy's exploring
#: motion (spread e^-1: about 0.7 mm a step) does not throw the force out of its 1-3 N band.
#: The rotation stays v0's 0.05 rad: the skin's normal turns up to 55 degrees along a path,
#: which the probe must follow within 5 degrees. ``max_translation_m`` still sets it.
V1_MAX_TRANSLATION_M = 0.002
#: Steps of normal force the ``force_history`` observation holds (the latest first).
FORCE_HISTORY = 4
#: Bound of the ``force_history`` observation [N] (beyond the 10 N limit).
FORCE_BOUND_N = 20.0
#: The remaining path's share of the potential's d(s) is capped at this.
PATH_CAP = 1.5
#: And the tilt's excess over its tolerance, in tolerances (9: 50 degrees of tilt, the
#: skin's normal turning up to 55 along a path), so that every degree turned toward the
#: normal pays however far off the probe is.
TILT_CAP = 9.0


@dataclass(frozen=True)
class ForceScanV1Config(ShapedRewardConfig, ForceScanConfig):
    """ForceScan-v1's settings: v0's (:class:`ForceScanConfig`, the task itself) and the
    reward's (:class:`envs.tasks.shaping.ShapedRewardConfig`; its ``progress_weight`` is w in
    this task's potential, see the env's docstring).

    Attributes:
        bad_step_penalty: the ``bad_step`` term's cost of a step with the force out of its
            band or the tilt beyond its tolerance (>= 0).
    """

    bad_step_penalty: float = 0.05

    def __post_init__(self) -> None:
        super().__post_init__()
        check_non_negative(self, ("bad_step_penalty",))


class ForceScanV1Env(ForceScanEnv):
    """Sweep the probe along a line on the skin with the normal force in a band and the face
    normal to the skin: ForceScan-v0's task, with a reward in which progress along the path
    dominates and an observation that holds the force's recent history.

    ## Description

    As ``probegym/ForceScan-v0`` (the same phantom, arm, paths of 30-40 mm along the skin,
    3 mm end tolerance, 1-3 N band, 5 degree tilt, 90 % good steps and 10 N limit: a success
    means what it meant there).

    What changed from v0, and why (docs/learning-runs.md measured v0's failure to learn from
    scratch): v0 paid +1 for the whole path while each step out of the force band or tilt
    cost up to 0.6 and a failure -(201), so holding still was the cheaper policy; its 5 mm a
    step at full action made a fresh policy's exploring motion 1.8 mm a step, enough to lose
    the 1-3 N band; and the scripted policy that solves it filters the force over steps,
    which the observation did not show.

    ## Action space

    ``Box(-1, 1, (6,), float32)``, in the probe frame (x: the image's lateral axis, y: into
    the tissue, z: elevation); values beyond the box are clipped, NaN or inf raise:

    | index | meaning | at +1 |
    | --- | --- | --- |
    | 0, 1, 2 | move the probe's target along x, y, z | 2 mm per step |
    | 3, 4, 5 | turn it about x, y, z | 0.05 rad per step |

    (``max_translation_m``, ``max_rotation_rad``). The controller and the target's workspace
    are v0's.

    ## Observation space

    ``Dict`` of float32 boxes (flattenable): v0's (``probe_pose``, ``wrench``,
    ``joint_pos``, ``joint_vel``, ``path``, with ``image=True`` ``image``) and

    | key | shape | meaning |
    | --- | --- | --- |
    | ``last_action`` | the action's | the last step's action (zeros after a reset) |
    | ``force_history`` | (4,) | the normal contact force [N] now and at the last 3 steps |

    ## Rewards

    Named terms, logged in ``info["reward_terms"]`` (the reward is their sum):

    - ``progress``: gamma Phi(s') - Phi(s), potential-based shaping (Ng, Harada and Russell
      1999), Phi(s) = -w d(s), w = ``progress_weight`` (5), d(s) = min(1.5, the distance
      left to the path's end along the skin / the path's length) + min(1, the normal
      force's distance from the 1-3 N band / the band's width) + min(9, the tilt beyond 5
      degrees / 5 degrees); Phi lies in [-57.5, 0], ``info["potential"]`` reports it, and
      gamma is ``shaping_gamma`` (1: the terms sum to Phi(s_T) - Phi(s_0), and standing
      still earns nothing);
    - ``time``: -0.01 a step (``time_penalty``);
    - ``bad_step``: -0.05 on a step with the normal force out of the 1-3 N band or the tilt
      beyond 5 degrees, from the first step: what the shaping cannot say, since an
      excursion out of the band and back sums to nothing there but costs the good-step
      share; and it makes the press come first, where the task's share starts counting
      only once the force has reached the band (a probe could otherwise ride above the
      skin along the path and press at its end);
    - ``smoothness``: -0.02 x the mean squared change of the action / 4;
    - ``success``: +10 on the step that succeeds (``success_reward``);
    - ``failure``: -10 on a failing last step (``failure_reward``).

    ## Starting state, episode end, effects

    As v0 (:class:`envs.tasks.force_scan.ForceScanEnv`): truncated at 200 steps.
    ``path_length_range_m`` is the curriculum's keyword (10-15 mm paths first); the
    defaults need none.

    ## Arguments

    ``gymnasium.make("probegym/ForceScan-v1", ...)``: v0's arguments and the reward's
    (:class:`ForceScanV1Config`).

    ## Version history

    - v1: the reward, the observation and the translation scale above; the task is v0's.
    """

    task_config_type: ClassVar[type] = ForceScanV1Config
    task_config: ForceScanV1Config

    TERM_EFFECTS: ClassVar[dict[str, tuple[str, ...]]] = {
        **{
            term: needs
            for term, needs in ForceScanEnv.TERM_EFFECTS.items()
            if term not in ("force", "tilt")  # v0's terms, folded into the potential
        },
        "progress": ("force_feedback",),
        "time": (),
        "bad_step": ("force_feedback",),
        "last_action": (),
        "force_history": ("force_feedback",),
    }

    def __init__(self, **kwargs: Any) -> None:
        kwargs.setdefault("max_translation_m", V1_MAX_TRANSLATION_M)
        super().__init__(**kwargs)
        self._potential = 0.0
        self._forces = np.zeros(FORCE_HISTORY)

    def _observation_spaces(self) -> dict[str, spaces.Space]:
        observed = super()._observation_spaces()
        observed["last_action"] = spaces.Box(-1.0, 1.0, shape=(self.action_size,), dtype=np.float32)
        observed["force_history"] = spaces.Box(
            0.0, FORCE_BOUND_N, shape=(FORCE_HISTORY,), dtype=np.float32
        )
        return observed

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, NDArray[np.float32]], dict[str, Any]]:
        self._forces = np.zeros(FORCE_HISTORY)
        observation, info = super().reset(seed=seed, options=options)
        self._potential = self.potential(self._remaining(), 0.0, self._tilt)
        info["potential"] = self._potential
        return observation, info

    def _advance(self, action: NDArray[np.float64]) -> tissue.TissueStep:
        step = super()._advance(action)
        normal = min(FORCE_BOUND_N, max(0.0, self.normal_force_n(step)))
        self._forces = np.concatenate([[normal], self._forces[:-1]])
        return step

    def potential(self, remaining_m: float, normal: float, tilt_rad: float) -> float:
        """Phi(s) (see the class docstring) of the distance left along the skin [m], the
        normal contact force [N] and the tilt [rad]."""
        cfg = self.task_config
        left = min(PATH_CAP, remaining_m / self._length) if self._length > 0 else 0.0
        low, high = cfg.force_band_n
        outside = min(1.0, max(0.0, low - normal, normal - high) / (high - low))
        excess = min(TILT_CAP, max(0.0, tilt_rad - cfg.max_tilt_rad) / cfg.max_tilt_rad)
        return -cfg.progress_weight * (left + outside + excess)

    def _reward_terms(self, state: StepState, success: bool, failed: bool) -> dict[str, float]:
        cfg, normal, action = self.task_config, state.normal_n, state.action
        potential = self.potential(self._remaining(), normal, self._tilt)
        shaping = cfg.shaping_gamma * potential - self._potential
        self._potential = potential
        low, high = cfg.force_band_n
        good = low <= normal <= high and self._tilt <= cfg.max_tilt_rad
        return {
            "progress": shaping,
            "time": -cfg.time_penalty,
            "bad_step": 0.0 if good else -cfg.bad_step_penalty,
            "smoothness": -cfg.smoothness_weight * action_change(action, self._last_action),
            "success": cfg.success_reward if success else 0.0,
            "failure": self.failure_reward() if failed else 0.0,
        }

    def _observation(self) -> dict[str, NDArray[np.float32]]:
        observed = super()._observation()
        observed["last_action"] = self._last_action.astype(np.float32)
        observed["force_history"] = self._forces.astype(np.float32)
        return observed

    def _info(
        self,
        step: tissue.TissueStep | None,
        terms: dict[str, float],
        success: bool,
        failure: dict[str, Any] | None = None,
    ) -> dict[str, Any]:
        info = super()._info(step, terms, success, failure)
        info["potential"] = self._potential
        return info
