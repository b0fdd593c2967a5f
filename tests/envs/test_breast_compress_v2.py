"""``probegym/BreastCompress-v2``: v1's task with a shaped reward, the hold observed and a
finer action."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import envs
from agents.learning.policies import SCRIPTED_POLICIES
from envs.errors import EnvConfigError
from envs.observations import LesionInImage
from envs.tasks.breast_compress_v1 import BreastCompressV1Config
from envs.tasks.breast_compress_v2 import BreastCompressV2Config

ENV_ID = "probegym/BreastCompress-v2"
MESH = 623
RL_EXTRA = "SB3 needs the rl extra: pip install -e '.[rl]' (a CPU torch first: see the README)"


def _make(**kwargs):
    return gym.make(ENV_ID, mesh=MESH, **kwargs)


def _lesion(true_depth_m: float, visible: bool = True) -> LesionInImage:
    depth = true_depth_m if visible else 0.0
    return LesionInImage(0.0, depth, 0.0, visible, 0.003, true_depth_m, 0.0)


def test_it_is_registered_beside_v0_and_v1() -> None:
    assert {ENV_ID, "probegym/BreastCompress-v1", "probegym/BreastCompress-v0"} <= set(envs.ENV_IDS)
    assert gym.registry[ENV_ID].max_episode_steps == 250


def test_checkers_pass_and_the_task_is_v1s() -> None:
    from gymnasium.utils.env_checker import check_env

    env = _make()
    unwrapped = env.unwrapped
    check_env(unwrapped, skip_render_check=True)
    sb3 = pytest.importorskip("stable_baselines3.common.env_checker", reason=RL_EXTRA)
    sb3.check_env(unwrapped, warn=False)
    v1 = BreastCompressV1Config()
    for name in v1.__dataclass_fields__:
        if name != "failure_reward":
            assert getattr(unwrapped.task_config, name) == getattr(v1, name), name
    assert unwrapped.action_config.max_translation_m == 0.003
    assert unwrapped.action_config.max_rotation_rad == 0.03
    spec = type(unwrapped).__doc__ or ""
    for words in ("- v2: the reward", "``hold``", "``depth_error``", "Phi(s) = -w d(s)"):
        assert words in spec
    env.close()


def test_the_same_seed_asks_what_v1_asks() -> None:
    for seed in range(4):
        infos = []
        for env_id in (ENV_ID, "probegym/BreastCompress-v1"):
            env = gym.make(env_id, mesh=MESH)
            _, info = env.reset(seed=seed)
            infos.append((info["target_lesion"], info["target_depth_m"]))
            env.close()
        assert infos[0] == infos[1]


def test_the_potential_at_known_states() -> None:
    """Pinned numbers: Phi = -5 (min(2, |depth - target| / 5 mm) + unseen + min(1, force
    over 5 N / 5 N))."""
    env = _make()
    unwrapped = env.unwrapped
    env.reset(seed=0)
    target = unwrapped._target_depth
    potential = unwrapped.potential
    assert potential(_lesion(target), 3.0) == 0.0  # at depth, seen, safe: the goal
    assert potential(_lesion(target + 0.0025), 5.0) == pytest.approx(-2.5)
    assert potential(_lesion(target - 0.004), 7.5) == pytest.approx(-5 * (0.8 + 0.5))
    assert potential(_lesion(target + 0.006, visible=False), 0.0) == pytest.approx(-5 * 2.2)
    assert potential(_lesion(target + 0.05, visible=False), 30.0) == pytest.approx(-20.0)
    env.close()


def test_each_term_has_its_sign_and_bound() -> None:
    env = _make()
    env.reset(seed=1)
    for _ in range(25):
        _, reward, terminated, truncated, info = env.step(np.array([0.3, 0.8, 0, 0.2, 0, 0]))
        terms = info["reward_terms"]
        assert set(terms) == {"progress", "time", "smoothness", "success", "failure"}
        assert terms["time"] == -0.01
        assert -0.02 <= terms["smoothness"] <= 0.0
        assert terms["success"] in (0.0, 10.0) and terms["failure"] in (0.0, -10.0)
        assert abs(terms["progress"]) <= 20.0
        assert reward == pytest.approx(sum(terms.values()))
        if terminated or truncated:
            break
    env.close()


@pytest.mark.parametrize("gamma", [1.0, 0.99])
def test_the_shaping_telescopes_and_the_scripted_press_succeeds(gamma: float) -> None:
    """sum_t gamma^t (gamma Phi(s_t+1) - Phi(s_t)) = gamma^T Phi(s_T) - Phi(s_0); the
    scripted press (at v2's scale) ends at the goal, held, under the safety force."""
    env = _make(shaping_gamma=gamma)
    policy = SCRIPTED_POLICIES[ENV_ID]()
    observation, info = env.reset(seed=2)
    start = info["potential"]
    total, discount, done = 0.0, 1.0, False
    while not done:
        observation, _, terminated, truncated, info = env.step(policy(observation))
        total += discount * info["reward_terms"]["progress"]
        discount *= gamma
        done = terminated or truncated
    assert info["is_success"] and info["contact_force_n"] <= 5.0
    assert total == pytest.approx(discount * info["potential"] - start, abs=1e-9)
    assert start <= -5.0 < info["potential"]  # unseen at the start; within 1 mm at the end
    assert observation["hold"][0] == 1.0 and abs(observation["depth_error"][0]) <= 0.001
    env.close()


def test_the_press_is_observed() -> None:
    env = _make()
    observation, _ = env.reset(seed=3)
    np.testing.assert_array_equal(observation["last_action"], np.zeros(6))
    np.testing.assert_allclose(observation["press_offset"], 0.0, atol=1e-9)
    assert observation["hold"][0] == 0.0
    seen = False
    for _ in range(8):
        action = np.array([0, 3.0, 0, 0, 0, 0], dtype=np.float32)  # beyond the box: clipped
        observation, *_ = env.step(action)
        np.testing.assert_array_equal(observation["last_action"], np.clip(action, -1, 1))
        lesion, target = observation["lesion"], observation["target_depth"][0]
        if lesion[3] > 0.5:
            seen = True
            assert observation["depth_error"][0] == pytest.approx(lesion[1] - target, abs=1e-6)
        else:
            assert observation["depth_error"][0] == 0.0
    assert seen
    # 8 steps of 3 mm: the probe went in (+y) by several millimetres, not sideways.
    offset = observation["press_offset"]
    assert 0.008 < offset[1] <= 0.024 + 1e-3 and abs(offset[0]) < 0.002
    env.close()


@pytest.mark.parametrize(
    ("kwargs", "words"),
    [
        ({"shaping_gamma": 1.5}, ["shaping_gamma", "(0, 1]", "1.5"]),
        ({"progress_weight": 0.0}, ["progress_weight", "0.0"]),
        ({"smoothness_weight": -1.0}, ["smoothness_weight", ">= 0", "-1.0"]),
        ({"failure_reward": 3.0}, ["failure_reward", "3.0"]),
        ({"max_compression_strain": 1.2}, ["max_compression_strain", "1.2"]),
    ],
)
def test_bad_settings_are_refused(kwargs: dict, words: list[str]) -> None:
    with pytest.raises(EnvConfigError) as refused:
        _make(**kwargs)
    for word in words:
        assert word in str(refused.value)


def test_the_config_defaults_are_documented_values() -> None:
    config = BreastCompressV2Config()
    assert (config.failure_reward, config.success_reward, config.progress_weight) == (
        -10.0,
        10.0,
        5.0,
    )
    assert (config.shaping_gamma, config.time_penalty, config.smoothness_weight) == (
        1.0,
        0.01,
        0.02,
    )
    assert config.max_compression_strain == 0.28
