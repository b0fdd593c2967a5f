"""BreastCompress-v1: v0's task with the compression asked capped at 28 % of the lesion's
depth; v0 unchanged beside it."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import envs
from envs.errors import EnvConfigError

MESH = 623


def _start(env_id: str, seed: int, **kwargs) -> tuple[int, float, float]:
    """(target lesion, its depth under the probe at the start [m], compression asked [m])."""
    env = gym.make(env_id, mesh=MESH, **kwargs)
    _, info = env.reset(seed=seed)
    unwrapped = env.unwrapped
    centroid = unwrapped.tissue.lesion_centroids_m((unwrapped._target,))[0]
    depth = float((unwrapped._start_rot.T @ (centroid - unwrapped._start_pos))[1])
    env.close()
    return info["target_lesion"], depth, depth - info["target_depth_m"]


def test_it_is_registered_beside_v0_and_checks_pass() -> None:
    from gymnasium.utils.env_checker import check_env

    assert {"probegym/BreastCompress-v0", "probegym/BreastCompress-v1"} <= set(envs.ENV_IDS)
    env = gym.make("probegym/BreastCompress-v1", mesh=MESH)
    check_env(env.unwrapped, skip_render_check=True)
    spec = type(env.unwrapped).__doc__ or ""
    assert "- v1: the compression asked at most 28 %" in spec and "BreastCompress-v1" in spec
    assert env.unwrapped.task_config.max_compression_strain == 0.28
    env.close()


def test_the_compression_is_capped_at_its_share_of_the_depth_and_otherwise_v0s() -> None:
    """Same seed, same lesion and draw: v1 asks min(v0's compression, 0.28 x depth)."""
    capped = 0
    for seed in range(12):
        lesion, depth, asked = _start("probegym/BreastCompress-v1", seed)
        lesion_v0, depth_v0, asked_v0 = _start("probegym/BreastCompress-v0", seed)
        assert (lesion, depth) == (lesion_v0, depth_v0)
        assert asked == pytest.approx(min(asked_v0, 0.28 * depth), abs=1e-12)
        assert 0.005 <= asked_v0 <= 0.007 and asked <= 0.28 * depth + 1e-12
        capped += asked < asked_v0
    assert capped > 0  # some start asked v0 more than 28 % of its depth
    _, depth, asked = _start("probegym/BreastCompress-v0", 0, max_compression_strain=0.1)
    assert asked == pytest.approx(0.1 * depth)


@pytest.mark.parametrize("bad", [0.0, 1.0, -0.2, True, "0.3", float("nan")])
def test_a_bad_strain_is_refused_naming_it(bad) -> None:
    for env_id in ("probegym/BreastCompress-v0", "probegym/BreastCompress-v1"):
        with pytest.raises(EnvConfigError, match="max_compression_strain must be None or a"):
            gym.make(env_id, mesh=MESH, max_compression_strain=bad)


def test_the_scripted_policy_succeeds_where_v0_asked_too_much() -> None:
    """A start where v0's compression exceeds 28 % of the depth: v1's scripted press
    succeeds, holding under the safety force."""
    from agents.learning.policies import SCRIPTED_POLICIES

    seed = next(
        s for s in range(50)
        if (lambda start: start[2] > 0.28 * start[1])(_start("probegym/BreastCompress-v0", s))
    )  # fmt: skip
    env = gym.make("probegym/BreastCompress-v1", mesh=MESH)
    policy = SCRIPTED_POLICIES["probegym/BreastCompress-v1"]()
    observation, _ = env.reset(seed=seed)
    done = False
    while not done:
        observation, _, terminated, truncated, info = env.step(policy(observation))
        done = terminated or truncated
    assert info["is_success"] and info["contact_force_n"] <= 5.0
    assert np.isfinite(info["target_depth_m"])
    env.close()
