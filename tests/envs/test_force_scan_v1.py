"""``probegym/ForceScan-v1``: v0's task with a shaped reward and the force's history."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest

import envs  # noqa: F401 - registers the environments
from agents.learning.policies import SCRIPTED_POLICIES
from envs.errors import EnvConfigError
from envs.tasks.force_scan import ForceScanConfig
from envs.tasks.force_scan_v1 import ForceScanV1Config

ENV_ID = "probegym/ForceScan-v1"
MESH = 623
RL_EXTRA = "SB3 needs the rl extra: pip install -e '.[rl]' (a CPU torch first: see the README)"


def _make(mesh: int = MESH, **kwargs):
    return gym.make(ENV_ID, mesh=mesh, **kwargs)


def test_checkers_pass_and_the_task_is_v0s() -> None:
    from gymnasium.utils.env_checker import check_env

    assert ENV_ID in envs.ENV_IDS and gym.registry[ENV_ID].max_episode_steps == 200
    env = _make()
    unwrapped = env.unwrapped
    check_env(unwrapped, skip_render_check=True)
    sb3 = pytest.importorskip("stable_baselines3.common.env_checker", reason=RL_EXTRA)
    sb3.check_env(unwrapped, warn=False)
    v0 = ForceScanConfig()
    for name in v0.__dataclass_fields__:
        if name not in ("failure_reward", "progress_weight"):
            assert getattr(unwrapped.task_config, name) == getattr(v0, name), name
    assert unwrapped.action_config.max_translation_m == 0.002
    assert unwrapped.action_config.max_rotation_rad == 0.05
    env.close()


def test_the_potential_at_known_states() -> None:
    """Pinned: Phi = -5 (min(1.5, left / length) + min(1, outside 1-3 N / 2 N) + min(9, tilt
    beyond 5 degrees / 5 degrees))."""
    env = _make()
    env.reset(seed=0)
    unwrapped = env.unwrapped
    length = unwrapped._length
    five = math.radians(5.0)
    assert unwrapped.potential(0.0, 2.0, 0.0) == 0.0  # at the end, in band, normal: the goal
    assert unwrapped.potential(0.5 * length, 2.0, five) == pytest.approx(-2.5)
    assert unwrapped.potential(length, 0.0, 1.5 * five) == pytest.approx(-5 * (1 + 0.5 + 0.5))
    assert unwrapped.potential(length, 2.0, 6 * five) == pytest.approx(-5 * (1 + 5))
    assert unwrapped.potential(3 * length, 12.0, math.pi) == pytest.approx(-57.5)  # capped
    env.close()


@pytest.mark.parametrize("gamma", [1.0, 0.99])
def test_the_shaping_telescopes_and_the_terms_keep_their_bounds(gamma: float) -> None:
    env = _make(shaping_gamma=gamma)
    policy = SCRIPTED_POLICIES[ENV_ID]()
    observation, info = env.reset(seed=1)
    start = info["potential"]
    total, discount, done = 0.0, 1.0, False
    while not done:
        observation, reward, terminated, truncated, info = env.step(policy(observation))
        terms = info["reward_terms"]
        assert set(terms) == {"progress", "time", "bad_step", "smoothness", "success", "failure"}
        assert terms["time"] == -0.01 and terms["bad_step"] in (0.0, -0.05)
        assert -0.02 <= terms["smoothness"] <= 0.0 and abs(terms["progress"]) <= 57.5
        assert reward == pytest.approx(sum(terms.values()))
        total += discount * terms["progress"]
        discount *= gamma
        done = terminated or truncated
    assert info["is_success"] and info["reward_terms"]["success"] == 10.0
    assert total == pytest.approx(discount * info["potential"] - start, abs=1e-9)
    env.close()


def test_the_force_history_is_observed() -> None:
    env = _make()
    observation, _ = env.reset(seed=2)
    np.testing.assert_array_equal(observation["force_history"], np.zeros(4))
    forces = []
    for _ in range(6):
        action = np.array([0, 0.8, 0, 0, 0, 0], dtype=np.float32)
        observation, _, _, _, info = env.step(action)
        forces.insert(0, info["normal_force_n"])
        expected = (forces + [0.0] * 4)[:4]  # zeros before the first steps
        np.testing.assert_allclose(observation["force_history"], expected, rtol=1e-6)
        np.testing.assert_array_equal(observation["last_action"], action)
    assert forces[0] > 0.0
    env.close()


@pytest.mark.parametrize(
    ("kwargs", "words"),
    [
        ({"shaping_gamma": 1.5}, ["shaping_gamma", "(0, 1]", "1.5"]),
        ({"bad_step_penalty": -0.1}, ["bad_step_penalty", ">= 0", "-0.1"]),
        ({"success_reward": 0.0}, ["success_reward", "0.0"]),
    ],
)
def test_bad_reward_settings_are_refused(kwargs: dict, words: list[str]) -> None:
    with pytest.raises(EnvConfigError) as refused:
        _make(**kwargs)
    for word in words:
        assert word in str(refused.value)


def test_the_config_defaults_are_documented_values() -> None:
    config = ForceScanV1Config()
    assert (config.failure_reward, config.success_reward, config.progress_weight) == (-10, 10, 5)
    assert (config.time_penalty, config.bad_step_penalty, config.smoothness_weight) == (
        0.01,
        0.05,
        0.02,
    )
