"""The v0 tasks' reward terms at known states: pinned numbers that a changed weight,
normaliser or cap breaks, each term's sign and bound (the v1 tasks pin theirs in their own
test files). The terms are computed from a state the test sets, not from a rollout."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest

import envs  # noqa: F401 - registers the environments
from envs.observations import LesionInImage
from envs.probe_env import StepState

MESH = 623
STILL = np.zeros(6)
#: One full action on x after standing still: mean squared change 1/6, over 4: 1/24.
JOLT = np.array([1.0, 0.0, 0.0, 0.0, 0.0, 0.0])


def _env(env_id: str):
    env = gym.make(env_id, mesh=MESH)
    env.reset(seed=0)
    unwrapped = env.unwrapped
    unwrapped._last_action = STILL.copy()
    return env, unwrapped


def _terms(unwrapped, action, force_n: float, success: bool, failed: bool, **state):
    """The task's terms for a step that took ``action`` and measured ``force_n`` (as the
    contact force and its normal part), the task's own state set from ``state``."""
    for name, value in state.items():
        setattr(unwrapped, name, value)
    step = StepState(np.asarray(action, dtype=np.float64), None, force_n, force_n)
    return unwrapped._reward_terms(step, success, failed)


def _lesion(lateral_m: float, depth_m: float, visible: bool = True) -> LesionInImage:
    return LesionInImage(
        lateral_m if visible else 0.0, depth_m if visible else 0.0, 0.0, visible,
        lateral_m, depth_m, 0.0,
    )  # fmt: skip


def test_breast_compress_v0_terms_at_known_states() -> None:
    """depth -0.5 x |error| / 10 mm, centring -0.2 x |lateral| / 20 mm (the half aperture),
    force -0.2 x the force over 5 N as a share of 5-10 N, smoothness -0.1 x change / 4,
    success +1, failure -(250 + 1)."""
    env, unwrapped = _env("probegym/BreastCompress-v0")
    target = unwrapped._target_depth
    lesion = _lesion(0.005, target + 0.004)
    terms = _terms(unwrapped, JOLT, 7.5, False, False, _lesion_now=lesion)
    assert terms == pytest.approx(
        {"depth_error": -0.2, "centring": -0.05, "force": -0.1, "smoothness": -0.1 / 24,
         "success": 0.0, "failure": 0.0}
    )  # fmt: skip
    # Out of view: the depth and centring terms at their floor; the force capped at 10 N.
    terms = _terms(unwrapped, STILL, 20.0, False, True, _lesion_now=_lesion(0.0, 0.0, False))
    assert terms == pytest.approx(
        {"depth_error": -0.5, "centring": -0.2, "force": -0.2, "smoothness": 0.0,
         "success": 0.0, "failure": -251.0}
    )  # fmt: skip
    # At the goal: every shaping term 0, the success +1.
    terms = _terms(unwrapped, STILL, 3.0, True, False, _lesion_now=_lesion(0.0, target))
    assert terms == {
        "depth_error": -0.0, "centring": -0.0, "force": -0.0, "smoothness": -0.0,
        "success": 1.0, "failure": 0.0,
    }  # fmt: skip
    # A step's reward but the last lies in [-1, 0]: the worst non-failing step.
    worst = _terms(unwrapped, -JOLT * 1e3, 1e3, False, False, _lesion_now=_lesion(0.0, 0.0, False))
    assert sum(worst.values()) == pytest.approx(-1.0)
    env.close()


def test_lesion_search_v0_terms_at_known_states() -> None:
    """centring -0.5 x |lateral| / 20 mm (1 out of view), force -0.3 x the distance out of
    0.5-4 N as a share of the band's 3.5 N (capped at 1), smoothness -0.1 x change / 4,
    success +1, failure -(300 + 1)."""
    env, unwrapped = _env("probegym/LesionSearch-v0")
    terms = _terms(unwrapped, JOLT, 5.75, False, False, _lesion_now=_lesion(-0.01, 0.02))
    assert terms == pytest.approx(
        {"centring": -0.25, "force": -0.15, "smoothness": -0.1 / 24, "success": 0.0,
         "failure": 0.0}
    )  # fmt: skip
    terms = _terms(unwrapped, STILL, 0.0, False, True, _lesion_now=_lesion(0.0, 0.0, False))
    # Out of view, no contact: 0.5 N below the band is 1/7 of its width.
    assert terms == pytest.approx(
        {"centring": -0.5, "force": -0.3 / 7, "smoothness": 0.0, "success": 0.0,
         "failure": -301.0}
    )  # fmt: skip
    far = _terms(unwrapped, STILL, 100.0, True, False, _lesion_now=_lesion(0.1, 0.02))
    assert far["centring"] == -0.5 and far["force"] == -0.3 and far["success"] == 1.0
    env.close()


def test_force_scan_v0_terms_at_known_states() -> None:
    """progress 1 x (progress made) / path length, force -0.3 x the distance out of 1-3 N as
    a share of 2 N (capped at 1), tilt -0.3 x the tilt beyond 5 degrees as a share of 5
    degrees (capped at 1), smoothness -0.1 x change / 4, success +1, failure -(200 + 1)."""
    env, unwrapped = _env("probegym/ForceScan-v0")
    length = unwrapped._length
    unwrapped._progress = 0.25 * length
    unwrapped._tilt = math.radians(7.5)
    terms = _terms(unwrapped, JOLT, 3.5, False, False, _progress_before=0.0)
    assert terms == pytest.approx(
        {"progress": 0.25, "force": -0.075, "tilt": -0.15, "smoothness": -0.1 / 24,
         "success": 0.0, "failure": 0.0}
    )  # fmt: skip
    # Going back costs what going forward earned; far out of band and tilted: capped.
    unwrapped._tilt = math.radians(60.0)
    terms = _terms(unwrapped, STILL, 0.0, False, True, _progress_before=0.5 * length)
    assert terms == pytest.approx(
        {"progress": -0.25, "force": -0.15, "tilt": -0.3, "smoothness": 0.0, "success": 0.0,
         "failure": -201.0}
    )  # fmt: skip
    terms = _terms(unwrapped, STILL, 30.0, False, False, _progress_before=0.25 * length)
    assert terms["force"] == -0.3 and terms["progress"] == 0.0
    env.close()
