"""The reward settings that the tasks' teaching versions share (LesionSearch-v1, ForceScan-v1,
BreastCompress-v2): potential-based shaping of progress, a small cost per step, a success
bonus and a failure on the success's scale.

The shaping term is gamma Phi(s') - Phi(s) (Ng, Harada and Russell 1999), Phi a task's own
potential (its distance from the goal, weighted by ``progress_weight``); why ``shaping_gamma``
defaults to 1 is in :class:`envs.tasks.lesion_search_v1.LesionSearchV1Env`'s docstring.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from envs.errors import EnvConfigError, check_positive, finite_number


@dataclass(frozen=True)
class ShapedRewardConfig:
    """The shared reward settings; a task's config lists this first among its bases, so that
    its defaults (the failure's -10 among them) replace the older version's.

    Attributes:
        failure_reward: the ``failure`` term on a failing last step (<= 0; -10, on the
            scale of the success, not of the whole episode's penalties).
        progress_weight: w in the task's potential Phi(s) = -w d(s) (> 0).
        shaping_gamma: the gamma of the shaping term gamma Phi(s') - Phi(s), in (0, 1].
        time_penalty: the ``time`` term's cost of every step (>= 0).
        smoothness_weight: the ``smoothness`` term's weight (>= 0).
        success_reward: the ``success`` term on the step that succeeds (> 0).
    """

    failure_reward: float | None = -10.0
    progress_weight: float = 5.0
    shaping_gamma: float = 1.0
    time_penalty: float = 0.01
    smoothness_weight: float = 0.02
    success_reward: float = 10.0

    def __post_init__(self) -> None:
        task_checks = getattr(super(), "__post_init__", None)
        if task_checks is not None:
            task_checks()  # the task's own settings (and ``failure_reward``'s sign)
        check_positive(self, ("progress_weight", "success_reward"))
        if not (finite_number(self.shaping_gamma) and 0.0 < self.shaping_gamma <= 1.0):
            raise EnvConfigError(f"shaping_gamma must lie in (0, 1]; got {self.shaping_gamma!r}")
        check_non_negative(self, ("time_penalty", "smoothness_weight"))


def check_non_negative(settings: Any, names: Any) -> None:
    """An :class:`EnvConfigError` naming the first of ``settings``'s fields ``names`` that is
    not a finite number >= 0."""
    for name in names:
        value = getattr(settings, name)
        if not (finite_number(value) and value >= 0.0):
            raise EnvConfigError(f"{name} must be a number >= 0; got {value!r}")


def action_change(action: np.ndarray, last_action: np.ndarray) -> float:
    """The ``smoothness`` term's measure: the mean squared change of the action / 4, in
    [0, 1] for actions in [-1, 1]."""
    return min(1.0, float(np.mean((action - last_action) ** 2)) / 4.0)
