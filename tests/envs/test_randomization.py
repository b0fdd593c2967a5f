"""Domain randomisation (``domain_randomization=``): off by default, drawn from the reset's
seed, acting on the mechanics and on what the policy observes, never on the truth."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import envs
from agents.learning.policies import LesionSearchPolicy
from envs.errors import EnvConfigError
from envs.randomization import DomainRandomization

MESH = 1363
SEARCH = "probegym/LesionSearch-v0"
COMPRESS = "probegym/BreastCompress-v0"


def _make(env_id: str = COMPRESS, contact: str = "penalty", **kwargs):
    return gym.make(env_id, contact=contact, mesh=MESH, **kwargs)


def test_off_by_default_and_then_nothing_varies() -> None:
    env = _make()
    assert env.unwrapped.randomizer is None
    nominal = env.unwrapped.tissue
    _, info = env.reset(seed=3)
    assert "variation" not in info
    assert env.unwrapped.tissue is nominal
    env.close()


def test_the_same_seed_draws_the_same_variation_and_episode() -> None:
    runs = []
    for _ in range(2):
        env = _make(domain_randomization=True)
        observation, info = env.reset(seed=11)
        steps = [env.step(np.array([0, 0.3, 0, 0, 0, 0], dtype=np.float32))[0] for _ in range(5)]
        runs.append((info["variation"], observation, steps))
        env.close()
    assert runs[0][0] == runs[1][0]
    for a, b in zip([runs[0][1], *runs[0][2]], [runs[1][1], *runs[1][2]], strict=True):
        for key in a:
            np.testing.assert_array_equal(a[key], b[key])
    env = _make(domain_randomization=True)
    _, other = env.reset(seed=12)
    assert other["variation"]["young_pa"] != runs[0][0]["young_pa"]
    # Without a new seed the next reset draws the next variation.
    _, following = env.reset()
    assert following["variation"]["young_pa"] != other["variation"]["young_pa"]
    env.close()


def test_the_task_draws_the_same_start_with_and_without_randomisation() -> None:
    """The start is drawn around the target lesion: where lesions stay, it is the same."""
    still = DomainRandomization(lesion_jitter_m=0.0)
    plain, varied = _make(SEARCH), _make(SEARCH, domain_randomization=still)
    plain.reset(seed=5)
    varied.reset(seed=5)
    assert plain.unwrapped._target == varied.unwrapped._target
    np.testing.assert_array_equal(plain.unwrapped._start_pos, varied.unwrapped._start_pos)
    plain.close()
    varied.close()


def test_the_drawn_tissue_is_the_one_simulated_and_imaged() -> None:
    settings = DomainRandomization(lesion_jitter_m=0.002)
    env = _make(SEARCH, domain_randomization=settings, image=True)
    nominal = env.unwrapped.tissue
    room = nominal.lesion_shift_limits_m()
    young = []
    for seed in range(4):
        _, info = env.reset(seed=seed)
        variation = info["variation"]
        model = env.unwrapped.tissue
        assert model is not nominal and env.unwrapped.coupling.tissue is model
        materials = model.resolved.materials
        assert materials.tissue.young_pa == pytest.approx(variation["young_pa"])
        assert materials.lesion_stiffness_ratio == pytest.approx(
            variation["lesion_stiffness_ratio"]
        )
        low, high = settings.tissue_stiffness_scale
        assert low * 2850.0 <= variation["young_pa"] <= high * 2850.0
        offsets = np.asarray(variation["lesion_offsets_m"])
        lengths = np.linalg.norm(offsets, axis=1)
        assert np.all(lengths <= np.minimum(0.002, 0.9 * room) + 1e-12) and np.any(lengths > 0)
        for k, lesion in enumerate(model.lesions):
            np.testing.assert_allclose(
                lesion.rest_centre_m, nominal.lesions[k].rest_centre_m + offsets[k], atol=1e-12
            )
        # The image labels the lesions where the simulated tissue has them.
        centres = np.array([lesion.rest_centre_m for lesion in model.lesions])
        np.testing.assert_array_equal(env.unwrapped.imager._lesion_centres, centres)
        young.append(variation["young_pa"])
    assert len(set(young)) == 4
    env.close()


def test_a_stiffer_draw_pushes_back_harder_through_the_robot() -> None:
    """The same press on two draws: the force follows the drawn modulus."""
    settings = DomainRandomization(lesion_stiffness_ratio=None, lesion_jitter_m=0.0)
    env = _make(domain_randomization=settings)
    forces = {}
    for seed in (0, 1, 2):
        _, info = env.reset(seed=seed)
        for _ in range(12):
            _, _, _, _, step_info = env.step(np.array([0, 0.3, 0, 0, 0, 0], dtype=np.float32))
        forces[info["variation"]["young_pa"]] = step_info["contact_force_n"]
    env.close()
    moduli = sorted(forces)
    assert moduli[-1] / moduli[0] > 1.2
    assert forces[moduli[-1]] > forces[moduli[0]]


def test_the_sensor_and_pose_noise_have_their_bias_and_spread() -> None:
    settings = DomainRandomization(
        tissue_stiffness_scale=(1.0, 1.0),
        lesion_stiffness_ratio=None,
        lesion_jitter_m=0.0,
        force_noise_n=0.1,
        force_bias_n=0.5,
        position_noise_m=0.001,
    )
    assert not settings.varies_tissue
    env = _make(domain_randomization=settings)
    _, info = env.reset(seed=4)
    assert env.unwrapped.tissue is env.unwrapped.randomizer.nominal
    bias = np.asarray(info["variation"]["force_bias_n"])
    assert np.all(np.abs(bias) <= 0.5) and np.any(bias != 0.0)
    errors, pose_errors = [], []
    for _ in range(60):
        observation, *_ = env.step(np.zeros(6, dtype=np.float32))
        truth = env.unwrapped.sensed_wrench()
        errors.append(observation["wrench"][:3] - truth[:3])
        position, _ = env.unwrapped.probe_pose()
        pose_errors.append(observation["probe_pose"][:3] - position)
    errors = np.array(errors)
    np.testing.assert_allclose(errors.mean(axis=0), bias, atol=0.05)
    assert np.all((errors.std(axis=0) > 0.07) & (errors.std(axis=0) < 0.13))
    spread = np.array(pose_errors).std(axis=0)
    assert np.all((spread > 0.0007) & (spread < 0.0013))
    env.close()


@pytest.mark.parametrize(
    ("value", "message"),
    [
        ("yes", "must be True, False, a dict"),
        ({"force_noise": 0.1}, "valid ones: force_bias_n"),
        ({"force_noise_n": -1.0}, "force_noise_n must be a number >= 0"),
        ({"lesion_jitter_m": 0.05}, "at most 0.01 m"),
        ({"tissue_stiffness_scale": (2.0, 1.0)}, "low <= high"),
        ({"lesion_stiffness_ratio": 4.0}, "lesion_stiffness_ratio must be"),
    ],
)
def test_bad_settings_are_named(value, message: str) -> None:
    with pytest.raises(EnvConfigError, match=message):
        _make(domain_randomization=value)


def test_it_is_public() -> None:
    assert envs.DomainRandomization is DomainRandomization


@pytest.mark.slow
def test_the_scripted_search_still_succeeds_on_randomised_patients() -> None:
    env = _make(SEARCH, contact="lm", domain_randomization=True)
    successes = 0
    for seed in range(6):
        observation, _ = env.reset(seed=seed)
        policy = LesionSearchPolicy()
        done = False
        while not done:
            observation, _, terminated, truncated, info = env.step(policy(observation))
            done = terminated or truncated
        successes += bool(info["is_success"])
    env.close()
    assert successes == 6


def test_the_gymnasium_checker_passes_with_randomisation() -> None:
    from gymnasium.utils.env_checker import check_env

    env = _make(domain_randomization=True)
    check_env(env.unwrapped, skip_render_check=True)
    env.close()


def test_offsets_the_mesh_refuses_shrink_and_never_fail_a_reset(monkeypatch) -> None:
    """Where the lesions' blends together squeeze a tet too far, the same draw is tried
    smaller, down to no move: a reset never raises for it, and says what it used."""
    import tissue

    env = _make(domain_randomization=DomainRandomization(lesion_jitter_m=0.002))
    nominal = env.unwrapped.randomizer.nominal
    original = type(nominal).varied
    tried = []

    def refusing(self, materials=None, lesion_offsets_m=None):
        tried.append(None if lesion_offsets_m is None else np.linalg.norm(lesion_offsets_m))
        if lesion_offsets_m is not None:
            raise tissue.TissueInputError("squeezed")
        return original(self, materials, None)

    monkeypatch.setattr(type(nominal), "varied", refusing)
    _, info = env.reset(seed=1)
    assert len(tried) == 4 and tried[-1] is None and tried[0] > 0.0
    assert not np.any(info["variation"]["lesion_offsets_m"])
    assert env.unwrapped.tissue is not nominal
    env.close()
