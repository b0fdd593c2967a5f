"""Bad input to the environments: one family with the tissue's (``tissue.TissueInputError``)."""

from __future__ import annotations

import numbers
from typing import Any

import numpy as np

import tissue


class EnvConfigError(tissue.ConfigError):
    """A keyword argument or setting an environment cannot take: the message names the
    value, what was expected and how to fix it."""


def finite_number(value: Any) -> bool:
    """Whether ``value`` is a finite real number (not a bool)."""
    return (
        isinstance(value, numbers.Real)
        and not isinstance(value, bool)
        and bool(np.isfinite(float(value)))
    )


def number_pair(value: Any) -> tuple[float, float] | None:
    """``value`` as two finite numbers (a tuple or list of two), or None."""
    if not isinstance(value, (tuple, list)) or len(value) != 2:
        return None
    if not all(finite_number(v) for v in value):
        return None
    return float(value[0]), float(value[1])


def check_positive(settings: Any, names: Any) -> None:
    """An :class:`EnvConfigError` naming the first of ``settings``'s fields ``names`` that is
    not a finite number > 0."""
    for name in names:
        value = getattr(settings, name)
        if not (finite_number(value) and value > 0):
            raise EnvConfigError(f"{name} must be a positive number; got {value!r}")


def check_failure_reward(value: object) -> None:
    """A task's ``failure_reward``: None or a finite number <= 0."""
    if value is None:
        return
    if isinstance(value, bool) or not finite_number(value) or float(value) > 0.0:  # type: ignore[arg-type]
        raise EnvConfigError(
            f"failure_reward must be a number <= 0 (or None: -(max_episode_steps + 1)); "
            f"got {value!r}"
        )
