"""``probegym/LesionSearch-v1``: LesionSearch-v0's task with a reward and an observation that
teach it (the same starts, tolerances, holding time and force limits)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from gymnasium import spaces
from numpy.typing import NDArray

import tissue
from envs.observations import LesionInImage
from envs.probe_env import StepState
from envs.tasks.lesion_search import LesionSearchConfig, LesionSearchEnv
from envs.tasks.shaping import ShapedRewardConfig, action_change

#: v1's action scale at |a| = 1: 2 mm and 0.02 rad a step (v0: 5 mm and 0.05 rad), so that
#: a fresh policy's exploring motion (spread e^-1: about 0.7 mm a step) stays well inside
#: the 3 mm centring tolerance. ``max_translation_m`` / ``max_rotation_rad`` still set it.
V1_MAX_TRANSLATION_M = 0.002
V1_MAX_ROTATION_RAD = 0.02
#: Bound of the sweep observations [m] (the workspace is 40 mm either way).
SCAN_BOUND_M = 0.1
#: The centring distance's share of the potential's d(s) is capped at this (40 mm: the
#: start's farthest offset and more).
CENTRING_CAP = 2.0


@dataclass(frozen=True)
class LesionSearchV1Config(ShapedRewardConfig, LesionSearchConfig):
    """LesionSearch-v1's settings: v0's (:class:`LesionSearchConfig`, the task itself) and
    the reward's (:class:`envs.tasks.shaping.ShapedRewardConfig`; its ``progress_weight``
    is w in this task's potential, see the env's docstring)."""


class LesionSearchV1Env(LesionSearchEnv):
    """Find the target lesion with the robot-held probe, centre it in the image and hold
    the contact force in a band: LesionSearch-v0's task, with a reward in which progress
    toward the goal dominates and an observation that holds the sweep so far.

    ## Description

    As ``probegym/LesionSearch-v0`` (the same phantom, arm, starting states, tolerances,
    holding time and force limit: a success means what it meant there). The policy must
    press to get an image, sweep along the scan line until the lesion appears, bring it to
    the image's centre line and hold it there with an adequate, safe contact force.

    What changed from v0, and why (docs/learning-runs.md measured v0's failure to learn): v0
    charged up to 0.9 every step and ended a force-limit failure at -(301), so keeping away
    from the skin was the best policy a learner found; its 5 mm a step at full action put
    a fresh policy's exploring motion at 1.8 mm a step against a 3 mm tolerance; and its
    observation did not say how far the probe had swept, which a search needs.

    ## Action space

    ``Box(-1, 1, (6,), float32)``, in the probe frame (x: the image's lateral axis, y: into
    the tissue, z: elevation); values beyond the box are clipped, NaN or inf raise:

    | index | meaning | at +1 |
    | --- | --- | --- |
    | 0, 1, 2 | move the probe's target along x, y, z | 2 mm per step |
    | 3, 4, 5 | turn it about x, y, z | 0.02 rad per step |

    (``max_translation_m``, ``max_rotation_rad``: v0's 5 mm and 0.05 rad were 2.5 times
    these). The controller and the target's workspace are v0's.

    ## Observation space

    ``Dict`` of float32 boxes (flattenable): v0's (``probe_pose``, ``wrench``,
    ``joint_pos``, ``joint_vel``, ``lesion``, with ``image=True`` ``image``) and

    | key | shape | meaning |
    | --- | --- | --- |
    | ``last_action`` | the action's | the last step's action (zeros after a reset) |
    | ``scan_offset`` | (3,) | the probe's position from its start, in the start's probe frame [m] |
    | ``scan_extent`` | (2,) | the least and greatest ``scan_offset[0]`` reached this episode [m] |

    ``scan_extent`` is the search's memory: where along the scan line the probe has been,
    so that a policy that swept one way without seeing the lesion knows to sweep back.

    ## Rewards

    Named terms, logged in ``info["reward_terms"]`` (the reward is their sum):

    - ``progress``: gamma Phi(s') - Phi(s), potential-based shaping (Ng, Harada and Russell
      1999), with the potential Phi(s) = -w d(s), w = ``progress_weight`` (5), d(s) = min(2,
      r / 20 mm) + min(1, the normal force's distance from the 0.5-4 N band / the band's
      width), r the distance of the lesion's centre from the image's centre line within the
      image plane and across it (sqrt(lateral^2 + out-of-plane^2), from the simulated truth
      whether the lesion is visible or not). Phi lies in [-15, 0]; ``info["potential"]``
      reports it. gamma is ``shaping_gamma``, 1 by default: the terms then sum over an
      episode to Phi(s_T) - Phi(s_0), standing still earns nothing, and an episode's return
      reads as progress made. With gamma equal to the learner's discount (0.99 for
      ``probegym train``) the optimal policy would be exactly the task's, but standing still
      would earn (1 - gamma) |Phi| a step: a random policy's 300 steps far from the lesion
      returned as much as the scripted policy's success. Against a learner's gamma < 1 the
      default differs from that by a reward of -(1 - gamma) w d(s) a step: a small pull
      toward the goal, the task's own direction;
    - ``time``: -0.01 a step (``time_penalty``);
    - ``smoothness``: -0.02 x the mean squared change of the action / 4 (at most 0.02);
    - ``success``: +10 on the step that succeeds (``success_reward``);
    - ``failure``: -10 on a failing last step (``failure_reward``), and the episode's end
      stops the shaping's earnings: failing never pays, yet it is on the success's scale,
      not v0's -(301) that made keeping away from the skin the best policy found.

    ## Starting state, episode end, effects

    As v0: the probe just touches the skin, its long axis along the radial scan plane
    through the lesion, 24-30 mm to either side; success after 15 steps (0.3 s) with the
    lesion visible, within 3 mm of the centre line and the force in 0.5-4 N; failure above
    10 N, a tissue step that is not ``ok`` or a non-finite arm; truncated at 300 steps.
    ``start_offset_range_m`` is the curriculum's keyword (10-20 mm: the lesion shows at the
    first press); the defaults need none.

    ## Arguments

    ``gymnasium.make("probegym/LesionSearch-v1", ...)``: v0's arguments (see
    :class:`envs.tasks.lesion_search.LesionSearchEnv`) and the reward's
    (:class:`LesionSearchV1Config`).

    ## Version history

    - v1: the reward, the observation and the action scale above; the task is v0's.
    """

    task_config_type: ClassVar[type] = LesionSearchV1Config
    task_config: LesionSearchV1Config

    TERM_EFFECTS: ClassVar[dict[str, tuple[str, ...]]] = {
        **{
            term: needs
            for term, needs in LesionSearchEnv.TERM_EFFECTS.items()
            if term not in ("centring", "force")  # v0's terms, folded into the potential
        },
        "progress": ("lesion_tracking", "force_feedback"),
        "time": (),
        "last_action": (),
        "scan_offset": (),
        "scan_extent": (),
    }

    def __init__(self, **kwargs: Any) -> None:
        kwargs.setdefault("max_translation_m", V1_MAX_TRANSLATION_M)
        kwargs.setdefault("max_rotation_rad", V1_MAX_ROTATION_RAD)
        super().__init__(**kwargs)
        self._potential = 0.0
        self._extent = np.zeros(2)

    def _observation_spaces(self) -> dict[str, spaces.Space]:
        observed = super()._observation_spaces()
        bound = SCAN_BOUND_M
        observed["last_action"] = spaces.Box(-1.0, 1.0, shape=(self.action_size,), dtype=np.float32)
        observed["scan_offset"] = spaces.Box(-bound, bound, shape=(3,), dtype=np.float32)
        observed["scan_extent"] = spaces.Box(-bound, bound, shape=(2,), dtype=np.float32)
        return observed

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, NDArray[np.float32]], dict[str, Any]]:
        self._extent = np.zeros(2)
        observation, info = super().reset(seed=seed, options=options)
        assert self._lesion_now is not None
        self._potential = self.potential(self._lesion_now, 0.0)
        info["potential"] = self._potential
        return observation, info

    def _advance(self, action: NDArray[np.float64]) -> tissue.TissueStep:
        step = super()._advance(action)
        along = float(self._scan_offset()[0])
        self._extent = np.array([min(self._extent[0], along), max(self._extent[1], along)])
        return step

    def _scan_offset(self) -> NDArray[np.float64]:
        position, _ = self.probe_pose()
        offset: NDArray[np.float64] = self._start_rot.T @ (position - self._start_pos)
        return offset

    def potential(self, lesion: LesionInImage, normal: float) -> float:
        """Phi(s) (see the class docstring) of the lesion in the image and the normal
        contact force ``normal`` [N]."""
        cfg = self.task_config
        off = math.hypot(lesion.true_lateral_m, lesion.true_out_of_plane_m)
        centring = min(CENTRING_CAP, off / (0.5 * self.imaging.aperture_m))
        low, high = cfg.force_band_n
        outside = min(1.0, max(0.0, low - normal, normal - high) / (high - low))
        return -cfg.progress_weight * (centring + outside)

    def _reward_terms(self, state: StepState, success: bool, failed: bool) -> dict[str, float]:
        cfg, lesion = self.task_config, self._lesion_now
        normal, action = state.normal_n, state.action
        assert lesion is not None  # tracked on every step
        potential = self.potential(lesion, normal)
        shaping = cfg.shaping_gamma * potential - self._potential
        self._potential = potential
        return {
            "progress": shaping,
            "time": -cfg.time_penalty,
            "smoothness": -cfg.smoothness_weight * action_change(action, self._last_action),
            "success": cfg.success_reward if success else 0.0,
            "failure": self.failure_reward() if failed else 0.0,
        }

    def _observation(self) -> dict[str, NDArray[np.float32]]:
        observed = super()._observation()
        bound = SCAN_BOUND_M
        observed["last_action"] = self._last_action.astype(np.float32)
        observed["scan_offset"] = np.clip(self._scan_offset(), -bound, bound).astype(np.float32)
        observed["scan_extent"] = np.clip(self._extent, -bound, bound).astype(np.float32)
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
