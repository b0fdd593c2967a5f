"""``probegym/LesionSearch-v1``: v0's task with a shaped reward and the sweep observed."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest

import envs  # noqa: F401 - registers the environments
from agents.learning.policies import SCRIPTED_POLICIES
from envs.errors import EnvConfigError
from envs.observations import LesionInImage
from envs.tasks.lesion_search import LesionSearchConfig
from envs.tasks.lesion_search_v1 import LesionSearchV1Config

ENV_ID = "probegym/LesionSearch-v1"
MESH = 623
RL_EXTRA = "SB3 needs the rl extra: pip install -e '.[rl]' (a CPU torch first: see the README)"


def _make(mesh: int = MESH, **kwargs):
    return gym.make(ENV_ID, mesh=mesh, **kwargs)


def _lesion(lateral_m: float, out_of_plane_m: float = 0.0) -> LesionInImage:
    return LesionInImage(0.0, 0.0, 0.0, False, lateral_m, 0.02, out_of_plane_m)


def test_it_is_registered_beside_v0() -> None:
    assert ENV_ID in envs.ENV_IDS and "probegym/LesionSearch-v0" in envs.ENV_IDS
    assert gym.registry[ENV_ID].max_episode_steps == 300


def test_checkers_pass_and_the_task_is_v0s() -> None:
    from gymnasium.utils.env_checker import check_env

    env = _make()
    unwrapped = env.unwrapped
    check_env(unwrapped, skip_render_check=True)
    sb3 = pytest.importorskip("stable_baselines3.common.env_checker", reason=RL_EXTRA)
    sb3.check_env(unwrapped, warn=False)
    # The task is v0's: its settings are v0's defaults; only the reward's and the scale differ.
    v0 = LesionSearchConfig()
    for name in v0.__dataclass_fields__:
        if name != "failure_reward":
            assert getattr(unwrapped.task_config, name) == getattr(v0, name), name
    assert unwrapped.action_config.max_translation_m == 0.002
    assert unwrapped.action_config.max_rotation_rad == 0.02
    env.close()


def test_the_potential_at_known_states() -> None:
    """Pinned numbers: Phi = -5 (min(2, r / 20 mm) + min(1, force outside 0.5-4 N / 3.5 N))."""
    env = _make()
    potential = env.unwrapped.potential
    assert potential(_lesion(0.0), 1.0) == 0.0  # centred, in band: the goal
    assert potential(_lesion(0.010), 0.0) == pytest.approx(-5 * (0.5 + 0.5 / 3.5))
    assert potential(_lesion(0.006, 0.008), 2.0) == pytest.approx(-5 * 0.5)  # r = 10 mm
    assert potential(_lesion(-0.030), 5.75) == pytest.approx(-5 * (1.5 + 0.5))
    assert potential(_lesion(0.2), 20.0) == pytest.approx(-15.0)  # both capped
    env.close()


def test_each_term_has_its_sign_and_bound() -> None:
    env = _make()
    env.reset(seed=0)
    for _ in range(30):
        _, reward, terminated, truncated, info = env.step(np.array([0.9, 0.6, 0, 0, 0, 0.5]))
        terms = info["reward_terms"]
        assert set(terms) == {"progress", "time", "smoothness", "success", "failure"}
        assert terms["time"] == -0.01
        assert -0.02 <= terms["smoothness"] <= 0.0
        assert terms["success"] in (0.0, 10.0) and terms["failure"] in (0.0, -10.0)
        assert abs(terms["progress"]) <= 15.0
        assert reward == pytest.approx(sum(terms.values()))
        if terminated or truncated:
            break
    env.close()


@pytest.mark.parametrize("gamma", [1.0, 0.99])
def test_the_shaping_telescopes_over_an_episode(gamma: float) -> None:
    """sum_t gamma^t (gamma Phi(s_t+1) - Phi(s_t)) = gamma^T Phi(s_T) - Phi(s_0)."""
    env = _make(shaping_gamma=gamma)
    policy = SCRIPTED_POLICIES[ENV_ID]()
    observation, info = env.reset(seed=1)
    start = info["potential"]
    total, discount, done = 0.0, 1.0, False
    while not done:
        observation, _, terminated, truncated, info = env.step(policy(observation))
        total += discount * info["reward_terms"]["progress"]
        discount *= gamma
        done = terminated or truncated
    assert info["is_success"]
    assert total == pytest.approx(discount * info["potential"] - start, abs=1e-9)
    assert info["potential"] > start  # it ended nearer the goal than it started
    env.close()


def test_progress_rewards_moving_the_lesion_toward_the_centre_line() -> None:
    env = _make()
    unwrapped = env.unwrapped
    _, info = env.reset(seed=2)
    toward = -math.copysign(1.0, info["start_offset_m"])  # the probe moves toward the lesion
    for _ in range(6):  # press into the band first
        env.step(np.array([0, 0.5, 0, 0, 0, 0], dtype=np.float32))
    _, _, _, _, info = env.step(np.array([toward, 0, 0, 0, 0, 0], dtype=np.float32))
    assert info["reward_terms"]["progress"] > 0.0
    assert unwrapped.task_config.progress_weight == 5.0
    env.close()


def test_the_sweep_is_observed() -> None:
    env = _make()
    observation, _ = env.reset(seed=3)
    np.testing.assert_array_equal(observation["last_action"], np.zeros(6))
    np.testing.assert_allclose(observation["scan_offset"], 0.0, atol=1e-9)
    np.testing.assert_array_equal(observation["scan_extent"], np.zeros(2))
    low = high = 0.0
    for sign in [3.0] * 6 + [-3.0] * 12:  # beyond the box: clipped to +-1
        action = np.array([sign, 0.1, 0, 0, 0, 0], dtype=np.float32)
        observation, *_ = env.step(action)
        along = float(observation["scan_offset"][0])
        low, high = min(low, along), max(high, along)
        np.testing.assert_array_equal(observation["last_action"], np.clip(action, -1, 1))
        assert observation["scan_extent"][0] == pytest.approx(low, abs=1e-6)
        assert observation["scan_extent"][1] == pytest.approx(high, abs=1e-6)
    assert high > 0.004 and low < -0.002  # it went both ways, millimetres each
    env.close()


@pytest.mark.parametrize(
    ("kwargs", "words"),
    [
        ({"shaping_gamma": 0.0}, ["shaping_gamma", "(0, 1]", "0.0"]),
        ({"progress_weight": -1.0}, ["progress_weight", "-1.0"]),
        ({"time_penalty": float("nan")}, ["time_penalty", ">= 0", "nan"]),
        ({"success_rewrd": 1.0}, ["success_rewrd", "success_reward"]),
    ],
)
def test_bad_reward_settings_are_refused(kwargs: dict, words: list[str]) -> None:
    with pytest.raises(EnvConfigError) as refused:
        _make(**kwargs)
    for word in words:
        assert word in str(refused.value)


def test_the_config_defaults_are_documented_values() -> None:
    config = LesionSearchV1Config()
    assert (config.failure_reward, config.success_reward) == (-10.0, 10.0)
    assert (config.shaping_gamma, config.time_penalty, config.smoothness_weight) == (
        1.0,
        0.01,
        0.02,
    )
