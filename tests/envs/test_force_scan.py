"""``probegym/ForceScan-v0``: sweep a path on the skin, the force in a band, the face normal."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import envs  # noqa: F401 - registers the environments
import tissue
from agents.learning.policies import ForceScanPolicy
from envs.effects import EFFECTS
from envs.errors import EnvConfigError
from envs.probe_env import PHANTOM_TARGET_LESIONS
from envs.tasks.force_scan import MAX_EPISODE_STEPS, ForceScanEnv

ENV_ID = "probegym/ForceScan-v0"
MESH = 623
#: The scripted policy's tests run on the default phantom (1,303 tets).
POLICY_MESH = 1363

RL_EXTRA = "SB3 needs the rl extra: pip install -e '.[rl]' (a CPU torch first: see the README)"


def _make(contact: str = "lm", mesh: int = MESH, **kwargs):
    return gym.make(ENV_ID, contact=contact, mesh=mesh, **kwargs)


def test_it_is_registered() -> None:
    assert ENV_ID in envs.ENV_IDS and ENV_ID in gym.registry
    assert gym.registry[ENV_ID].max_episode_steps == MAX_EPISODE_STEPS


def test_gymnasium_and_sb3_checkers_pass() -> None:
    from gymnasium.utils.env_checker import check_env

    env = _make("lm")
    check_env(env.unwrapped, skip_render_check=True)
    sb3 = pytest.importorskip("stable_baselines3.common.env_checker", reason=RL_EXTRA)
    sb3.check_env(env.unwrapped, warn=False)
    env.close()


def _rollout(env, seed: int, steps: int) -> list:
    rng = np.random.default_rng(seed)
    obs, info = env.reset(seed=seed)
    trace = [(obs, info)]
    for _ in range(steps):
        action = rng.uniform(-0.3, 0.3, size=6).astype(np.float32)
        action[1] += 0.2  # into the tissue: contact, forces
        action[3:] *= 0.2
        obs, reward, terminated, truncated, info = env.step(action)
        trace.append((obs, reward, terminated, truncated, info))
        if terminated or truncated:
            break
    return trace


@pytest.mark.parametrize("contact", ["lm", "penalty"])
def test_same_seed_same_episode_and_reward_is_the_sum_of_its_terms(contact: str) -> None:
    first = _rollout(_make(contact), seed=3, steps=20)
    second = _rollout(_make(contact), seed=3, steps=20)
    assert len(first) == len(second)
    for a, b in zip(first, second, strict=True):
        for key in a[0]:
            np.testing.assert_array_equal(a[0][key], b[0][key])
        assert a[1:] == b[1:]
    for record in first[1:]:
        obs, reward, _, _, info = record
        assert reward == sum(info["reward_terms"].values())
        assert all(np.all(np.isfinite(value)) for value in obs.values())
        for key in ("normal_force_n", "tilt_rad", "progress_m", "skin_penetration_m"):
            assert np.isfinite(info[key])
    assert any(record[4]["normal_force_n"] > 0.1 for record in first[1:])


def test_progress_weight_scales_the_progress_term_alone() -> None:
    base = _rollout(_make("lm"), seed=3, steps=20)
    heavy = _rollout(_make("lm", progress_weight=20.0), seed=3, steps=20)
    moved = 0
    for a, b in zip(base[1:], heavy[1:], strict=True):
        terms, heavier = a[4]["reward_terms"], b[4]["reward_terms"]
        assert heavier["progress"] == pytest.approx(20.0 * terms["progress"], rel=1e-12, abs=1e-15)
        assert {k: v for k, v in heavier.items() if k != "progress"} == {
            k: v for k, v in terms.items() if k != "progress"
        }
        moved += terms["progress"] != 0.0
    assert moved > 0


def test_the_seed_draws_the_path() -> None:
    """The start touches the skin above a target lesion, normal to it; the path runs 30-40
    mm along the probe's elevation axis (either way) to a point on the rest skin."""
    env = _make("lm")
    unwrapped = env.unwrapped
    lengths, ends, lesions = set(), set(), set()
    for seed in range(8):
        obs, info = env.reset(seed=seed)
        assert info["target_lesion"] in PHANTOM_TARGET_LESIONS
        assert 0.030 <= info["skin_length_m"] <= 0.040
        # The chord: shorter than the walk along the curved skin, not by much.
        assert 0.7 * info["skin_length_m"] <= info["path_length_m"] <= info["skin_length_m"]
        assert info["progress_m"] == 0.0 and info["contact_force_n"] == 0.0
        assert info["tilt_rad"] < np.radians(5.0)
        path = obs["path"]
        assert path[7] == pytest.approx(info["path_length_m"], rel=1e-5)
        # The end lies mostly along the probe's z (elevation), the path's length away.
        assert abs(path[2]) > 3.0 * abs(path[0])
        chord = unwrapped._path_end - unwrapped._path_start
        assert np.linalg.norm(chord) == pytest.approx(info["path_length_m"])
        assert unwrapped.rest_normal(unwrapped._path_end) is not None  # on the skin
        lengths.add(round(info["skin_length_m"], 6))
        ends.add(float(np.sign(path[2])))
        lesions.add(info["target_lesion"])
    assert len(lengths) == 8 and ends == {-1.0, 1.0} and len(lesions) >= 2


def test_every_term_declares_known_effects() -> None:
    env = _make("lm")
    obs, _ = env.reset(seed=0)
    _, _, _, _, info = env.step(np.zeros(6, dtype=np.float32))
    declared = ForceScanEnv.TERM_EFFECTS
    assert set(obs) | set(info["reward_terms"]) | {"image"} <= set(declared)
    assert set(info["reward_terms"]) == {
        "progress",
        "force",
        "tilt",
        "smoothness",
        "success",
        "failure",
    }
    assert all(set(effects) <= set(EFFECTS) for effects in declared.values())


def _scan(env, seed: int) -> tuple[dict, int]:
    policy = ForceScanPolicy()
    obs, info = env.reset(seed=seed)
    steps = 0
    while True:
        obs, _, terminated, truncated, info = env.step(policy(obs))
        steps += 1
        if terminated or truncated:
            return info, steps


@pytest.mark.parametrize("contact", ["lm", "penalty"])
def test_the_scripted_policy_sweeps_the_path(contact: str) -> None:
    """Three seeds on the default phantom (measured: see the report's numbers)."""
    env = _make(contact, mesh=POLICY_MESH)
    for seed in (0, 1, 2):
        info, steps = _scan(env, seed)
        assert info["is_success"], (seed, info)
        assert steps < MAX_EPISODE_STEPS
        assert info["remaining_m"] <= 0.003
        assert 1.0 <= info["normal_force_n"] <= 3.0
        assert info["good_share"] >= 0.9
        # The episode ends once within 3 mm of the end (up to a tenth of a 30 mm path), the
        # pressed centre below the curved skin: measured 0.78-0.88 of the chord, seeds 0-9.
        assert info["progress_m"] > 0.75 * info["path_length_m"]


@pytest.mark.slow
def test_the_scripted_policy_with_prescribed_displacement() -> None:
    """Prescribed displacement (robust: online, sliding node set), three seeds (measured 10
    of 10 on seeds 0-9; slow: 4 s here, kept out of the fast run's 20 s)."""
    env = _make("prescribed", mesh=POLICY_MESH)
    for seed in (0, 1, 2):
        info, _ = _scan(env, seed)
        assert info["is_success"], (seed, info)
        assert info["skin_penetration_m"] < 0.001


@pytest.mark.slow
def test_the_scripted_policy_with_pbd() -> None:
    """PBD (measured 10 of 10 on seeds 0-9; seeds 0 and 1 overshot the force past the
    10 N limit before the policy kept its own copy of the impedance target): three seeds,
    and the skin penetration reported (slow: 5 s here, 60 substeps)."""
    env = _make("pbd", mesh=POLICY_MESH)
    for seed in (0, 1, 2):
        info, _ = _scan(env, seed)
        assert info["is_success"], (seed, info)
        assert 0.0 <= info["skin_penetration_m"] < 0.002


def test_doing_nothing_does_not_succeed() -> None:
    env = _make("lm", mesh=POLICY_MESH, max_episode_steps=60)
    obs, _ = env.reset(seed=0)
    for _ in range(60):
        obs, _, terminated, truncated, info = env.step(np.zeros(6, dtype=np.float32))
        if terminated or truncated:
            break
    assert not info["is_success"] and truncated
    assert info["progress_m"] < 0.002


def test_pressing_without_sweeping_does_not_succeed() -> None:
    """Force in band at the start but no sweep: not a success."""
    env = _make("lm", mesh=POLICY_MESH, max_episode_steps=60)
    policy = ForceScanPolicy(sweep_m=0.0)
    obs, _ = env.reset(seed=0)
    for _ in range(60):
        obs, _, terminated, truncated, info = env.step(policy(obs))
        if terminated or truncated:
            break
    assert not info["is_success"] and truncated
    assert 1.0 <= info["normal_force_n"] <= 3.0


def test_pressing_too_hard_fails_and_returns_less() -> None:
    env = _make("lm", max_episode_steps=40)
    env.reset(seed=6)
    failing, failed = 0.0, {}
    for _ in range(40):
        _, reward, terminated, truncated, info = env.step(
            np.array([0.0, 1.0, 0.0, 0.0, 0.0, 0.0], dtype=np.float32)
        )
        failing += reward
        if terminated or truncated:
            failed = info
            break
    assert failed.get("force_exceeded") or failed.get("tissue_unstable"), failed
    assert failed["reward_terms"]["failure"] <= -41.0
    assert failing < -40.0


def test_an_unstable_tissue_ends_the_episode_with_its_flag(monkeypatch) -> None:
    env = _make("lm")
    env.reset(seed=0)
    unwrapped = env.unwrapped
    real = unwrapped.tissue.step

    def diverging(position, quat):
        from dataclasses import replace

        return replace(real(position, quat), status=tissue.StepStatus.DIVERGED)

    monkeypatch.setattr(unwrapped.tissue, "step", diverging)
    obs, reward, terminated, _, info = env.step(np.zeros(6, dtype=np.float32))
    assert terminated and info["tissue_unstable"] == "diverged" and not info["is_success"]
    assert reward < -MAX_EPISODE_STEPS
    assert all(np.all(np.isfinite(value)) for value in obs.values())


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"path_length_range_m": (0.04, 0.03)}, r"path_length_range_m .*\(0\.04, 0\.03\)"),
        ({"path_length_range_m": (0.0, 0.03)}, "path_length_range_m"),
        ({"path_length_range_m": (0.03, 0.5)}, "workspace_m"),
        ({"path_length_range_m": 0.03}, "path_length_range_m"),
        ({"force_band_n": (3.0, 1.0)}, r"force_band_n .*\(3\.0, 1\.0\)"),
        ({"force_band_n": (1.0, 12.0)}, "hard_force_n"),
        ({"max_tilt_rad": -0.1}, "max_tilt_rad .*-0.1"),
        ({"max_tilt_rad": float("nan")}, "max_tilt_rad"),
        ({"end_tolerance_m": 0.0}, "end_tolerance_m"),
        ({"min_good_share": 1.5}, "min_good_share .*1.5"),
        ({"min_good_share": 0.0}, "min_good_share"),
        ({"hard_force_n": 0.0}, "hard_force_n"),
        ({"progress_weight": 0.0}, "progress_weight .*0.0"),
        ({"target_lesions": (11,)}, "target_lesions"),
        ({"colour": "red"}, "unknown keyword argument"),
    ],
)
def test_bad_keyword_arguments_are_named(kwargs: dict, message: str) -> None:
    with pytest.raises(EnvConfigError, match=message):
        gym.make(ENV_ID, mesh=MESH, **kwargs)


def test_prescribed_displacement_without_sliding_is_refused() -> None:
    """The paper profile's prescribed displacement fixes its node set at first contact:
    it cannot sweep, and ProbeEnv cannot pass it contact parameters."""
    with pytest.raises(EnvConfigError, match="profile='robust'"):
        gym.make(ENV_ID, mesh=MESH, contact="prescribed", profile="paper")


def test_nan_actions_are_refused() -> None:
    env = _make("lm")
    env.reset(seed=0)
    with pytest.raises(EnvConfigError, match="finite"):
        env.step(np.array([np.nan, 0, 0, 0, 0, 0], dtype=np.float32))
