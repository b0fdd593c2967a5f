"""``probegym/BreastCompress-v0``: the coupled environment, for every contact method."""

from __future__ import annotations

import os

import gymnasium as gym
import numpy as np
import pytest

import envs  # noqa: F401 - registers the environments
import tissue
from agents.learning.policies import CompressionPolicy
from envs.effects import EFFECTS
from envs.errors import EnvConfigError
from envs.tasks.breast_compress import BreastCompressEnv

ENV_ID = "probegym/BreastCompress-v0"
METHODS = ("lm", "penalty", "prescribed", "pbd")
MESH = 623

RL_EXTRA = "SB3 needs the rl extra: pip install -e '.[rl]' (a CPU torch first: see the README)"


def _make(contact: str = "lm", **kwargs):
    return gym.make(ENV_ID, contact=contact, mesh=MESH, **kwargs)


@pytest.mark.parametrize("contact", METHODS)
def test_gymnasium_and_sb3_checkers_pass(contact: str) -> None:
    from gymnasium.utils.env_checker import check_env

    env = _make(contact)
    check_env(env.unwrapped, skip_render_check=True)
    sb3 = pytest.importorskip(
        "stable_baselines3.common.env_checker",
        reason=RL_EXTRA,
    )
    sb3.check_env(env.unwrapped, warn=False)
    env.close()


def _rollout(env, seed: int, steps: int) -> list:
    rng = np.random.default_rng(seed)
    obs, info = env.reset(seed=seed)
    trace = [(obs, info)]
    for _ in range(steps):
        action = rng.uniform(-0.3, 0.3, size=6).astype(np.float32)
        obs, reward, terminated, truncated, info = env.step(action)
        trace.append((obs, reward, terminated, truncated, info))
        if terminated or truncated:
            break
    return trace


@pytest.mark.parametrize("contact", METHODS)
def test_same_seed_same_trajectory_and_reward_is_the_sum_of_its_terms(contact: str) -> None:
    first = _rollout(_make(contact), seed=3, steps=25)
    second = _rollout(_make(contact), seed=3, steps=25)
    assert len(first) == len(second)
    for a, b in zip(first, second, strict=True):
        for key in a[0]:
            np.testing.assert_array_equal(a[0][key], b[0][key])
        assert a[1:] == b[1:]
    for record in first[1:]:
        _, reward, _, _, info = record
        assert reward == sum(info["reward_terms"].values())
        assert set(info["reward_terms"]) <= set(
            envs.tasks.breast_compress.BreastCompressEnv.TERM_EFFECTS
        )
        for obs in (record[0],):
            assert all(np.all(np.isfinite(value)) for value in obs.values())


def test_every_term_declares_known_effects() -> None:
    env = _make("lm")
    obs, _ = env.reset(seed=0)
    _, _, _, _, info = env.step(np.zeros(6, dtype=np.float32))
    declared = BreastCompressEnv.TERM_EFFECTS
    assert set(obs) | set(info["reward_terms"]) <= set(declared)
    assert all(set(effects) <= set(EFFECTS) for effects in declared.values())


def test_the_probe_site_is_the_tissues_probe_frame() -> None:
    """The pose MuJoCo's probe site has is the pose the tissue's contact uses, and the
    probe geometry drawn on it is the tissue's probe shape."""
    env = _make("lm")
    env.reset(seed=1)
    for _ in range(5):
        env.step(np.array([0.0, 0.2, 0.0, 0.0, 0.05, 0.0], dtype=np.float32))
    unwrapped = env.unwrapped
    position, rotation = unwrapped.probe_pose()
    probe = unwrapped.tissue.contact_model.probe
    np.testing.assert_allclose(probe.position_world, position, atol=1e-12)
    np.testing.assert_allclose(probe.rotation_world(), rotation, atol=1e-12)
    # The drawn face (its geom) lies on the tissue's face: the face geom's outer side at y=0.
    model, data = unwrapped.model, unwrapped.data
    face = model.geom("probe_face").id
    centre_local = rotation.T @ (data.geom_xpos[face] - position)
    half = model.geom_size[face]
    assert centre_local[1] + half[1] == pytest.approx(0.0, abs=1e-9)
    low, high = unwrapped.tissue.probe_shape.local_bounds_m()
    assert 2 * (half[0] + half[2]) == pytest.approx(high[0] - low[0], rel=0.02)


def _press_and_hold(env, depth_m: float, hold_steps: int, seed: int = 2):
    """Press the target ``depth_m`` along the probe's axis (0.2 mm a step), then hold."""
    unwrapped = env.unwrapped
    env.reset(seed=seed)
    per_step = 0.0002 / unwrapped.action_config.max_translation_m
    for _ in range(int(round(depth_m / 0.0002))):
        env.step(np.array([0.0, per_step, 0.0, 0.0, 0.0, 0.0], dtype=np.float32))
    positions, wrenches, steps = [], [], []
    for _ in range(hold_steps):
        _, _, terminated, _, info = env.step(np.zeros(6, dtype=np.float32))
        assert not terminated, info
        positions.append(unwrapped.probe_pose()[0])
        wrenches.append(unwrapped.tissue_step_wrench())
        steps.append(unwrapped.coupling.last_step)
    return np.array(positions), np.array(wrenches), steps


@pytest.mark.parametrize("contact", METHODS)
def test_a_held_press_does_not_chatter(contact: str) -> None:
    env = _make(contact)
    positions, wrenches, _ = _press_and_hold(env, 0.006, 275)
    held, force = positions[25:], np.linalg.norm(wrenches[25:, :3], axis=1)
    assert np.linalg.norm(held - held.mean(axis=0), axis=1).max() <= 0.2e-3
    assert force.min() > 0.2
    assert (force.max() - force.min()) <= 0.02 * force.mean()


@pytest.mark.parametrize("contact", METHODS)
def test_the_sensed_wrench_at_rest_is_the_tissues(contact: str) -> None:
    env = _make(contact)
    _, wrenches, _ = _press_and_hold(env, 0.006, 100)
    unwrapped = env.unwrapped
    _, rotation = unwrapped.probe_pose()
    tissue_wrench = wrenches[-1]
    expected = np.concatenate([rotation.T @ tissue_wrench[:3], rotation.T @ tissue_wrench[3:]])
    sensed = unwrapped.sensed_wrench()
    np.testing.assert_allclose(sensed[:3], expected[:3], rtol=0.01, atol=1e-3)
    np.testing.assert_allclose(sensed[3:], expected[3:], rtol=0.01, atol=1e-3 * 0.05)


@pytest.mark.slow
@pytest.mark.parametrize("contact", METHODS)
def test_a_slow_press_through_the_robot_gives_the_kinematic_force_depth_curve(
    contact: str,
) -> None:
    """Settled at 2-10 mm, the robot-held probe's force equals the kinematic probe's at the
    same pose within 5 % (the tissue alone, as ``probegym compress`` drives it)."""
    env = _make(contact)
    unwrapped = env.unwrapped
    env.reset(seed=4)
    start, rotation = unwrapped.probe_pose()
    pressing = rotation[:, 1]
    per_step = 0.0002 / unwrapped.action_config.max_translation_m
    # The environment's own tissue (its skin, profile and sleep), driven without the arm.
    reference = tissue.make_tissue(unwrapped.tissue.spec)
    for depth_mm in (2, 4, 6, 8, 10):
        for _ in range(10):
            env.step(np.array([0.0, per_step, 0.0, 0.0, 0.0, 0.0], dtype=np.float32))
        for _ in range(100):
            env.step(np.zeros(6, dtype=np.float32))
        position, turned = unwrapped.probe_pose()
        robot_force = float(-unwrapped.tissue_step_wrench()[:3] @ pressing)
        # The kinematic probe: slowly to the robot's pose, held as long.
        quat = unwrapped.tissue.contact_model.probe.quat_wxyz
        reference.reset(start, quat)
        for k in range(1, 101):
            reference.step(start + (k / 100) * (position - start), quat)
        for _ in range(100):
            kinematic = reference.step(position, quat)
        kinematic_force = float(-kinematic.force_world_n @ pressing)
        depth = float((position - start) @ pressing)
        assert depth > 0.8 * depth_mm * 1e-3
        assert robot_force == pytest.approx(kinematic_force, rel=0.05), depth_mm


@pytest.mark.parametrize("reaction", [True, False])
def test_the_tissue_moves_the_robot(reaction: bool) -> None:
    """With a soft impedance (200 N/m) a commanded 20 mm press stops where the tissue's
    force equals the controller's; without the reaction the probe reaches its target and
    the balance fails."""
    env = _make("lm", stiffness_n_per_m=200.0)
    unwrapped = env.unwrapped
    unwrapped.coupling.reaction = reaction  # the one-way coupling, under the task's terms
    env.reset(seed=5)
    start, rotation = unwrapped.probe_pose()
    pressing = rotation[:, 1]
    per_step = 0.0005 / unwrapped.action_config.max_translation_m
    for _ in range(40):  # the target 20 mm in
        env.step(np.array([0.0, per_step, 0.0, 0.0, 0.0, 0.0], dtype=np.float32))
    for _ in range(150):
        env.step(np.zeros(6, dtype=np.float32))
    position, _ = unwrapped.probe_pose()
    target = unwrapped.controller.target_pos
    lag = float((target - position) @ pressing)
    tissue_force = float(-unwrapped.tissue_step_wrench()[:3] @ pressing)
    balanced = abs(200.0 * lag - tissue_force) <= 0.05 * tissue_force
    if reaction:
        assert lag > 0.005 and tissue_force > 0.5
        assert balanced, (200.0 * lag, tissue_force)
    else:
        assert lag < 0.0005
        assert not balanced


def test_a_failing_episode_returns_less_than_a_non_failing_one() -> None:
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
    env.reset(seed=6)
    lasting, truncated = 0.0, False
    while not truncated:
        _, reward, terminated, truncated, info = env.step(
            np.array([0.0, -0.2, 0.0, 0.0, 0.0, 0.0], dtype=np.float32)  # lifts off: worst reward
        )
        lasting += reward
        assert not terminated
    assert failing < lasting


@pytest.mark.parametrize("contact", METHODS)
def test_the_scripted_policy_solves_the_task(contact: str) -> None:
    env = _make(contact)
    policy = CompressionPolicy()
    for seed in (0, 1):
        obs, _ = env.reset(seed=seed)
        for _ in range(250):
            obs, _, terminated, truncated, info = env.step(policy(obs))
            if terminated or truncated:
                break
        assert info["is_success"], (seed, info)


def test_an_unstable_tissue_ends_the_episode_with_its_flag(monkeypatch) -> None:
    env = _make("lm")
    env.reset(seed=0)
    unwrapped = env.unwrapped
    real = unwrapped.tissue.step

    def diverging(position, quat):
        step = real(position, quat)
        from dataclasses import replace

        return replace(step, status=tissue.StepStatus.DIVERGED)

    monkeypatch.setattr(unwrapped.tissue, "step", diverging)
    obs, reward, terminated, _, info = env.step(np.zeros(6, dtype=np.float32))
    assert terminated and info["tissue_unstable"] == "diverged"
    assert reward < -250
    assert all(np.all(np.isfinite(value)) for value in obs.values())


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"contact": "springs"}, "unknown contact method 'springs'"),
        ({"profile": "fast"}, "unknown profile"),
        ({"colour": "red"}, "unknown keyword argument"),
        ({"control_mode": "torque"}, "unknown control_mode"),
        ({"render_mode": "video"}, "unknown render_mode"),
        ({"camera_name": "top"}, "unknown camera_name"),
        ({"compression_range_m": (0.01, 0.005)}, "compression_range_m"),
        ({"stiffness_n_per_m": -3.0}, "stiffness_n_per_m"),
        ({"robot": "/nowhere/arm.xml"}, "does not exist"),
        ({"target_lesions": (11,)}, "target_lesions"),
    ],
)
def test_bad_keyword_arguments_are_named(kwargs: dict, message: str) -> None:
    with pytest.raises(tissue.TissueInputError, match=message):
        gym.make(ENV_ID, mesh=MESH, **kwargs)


def test_nan_actions_are_refused_and_large_ones_clipped() -> None:
    env = _make("lm")
    env.reset(seed=0)
    with pytest.raises(EnvConfigError, match="finite"):
        env.step(np.array([np.nan, 0, 0, 0, 0, 0], dtype=np.float32))
    _, _, _, _, clipped = env.step(np.array([0, 50.0, 0, 0, 0, 0], dtype=np.float32))
    env.reset(seed=0)
    _, _, _, _, unit = env.step(np.array([0, 1.0, 0, 0, 0, 0], dtype=np.float32))
    assert clipped["contact_force_n"] == unit["contact_force_n"]


def test_joint_delta_control_moves_the_arm() -> None:
    env = _make("lm", control_mode="joint_delta")
    obs, _ = env.reset(seed=0)
    for _ in range(10):
        obs2, *_ = env.step(np.array([0.5, 0, 0, 0, 0, 0], dtype=np.float32))
    assert obs2["joint_pos"][0] > obs["joint_pos"][0] + 0.05


def test_a_rendered_frame_shows_the_breast_and_the_probe() -> None:
    """Pixels change where the breast and the probe are drawn: hiding either changes the
    frame, and pressing dents the breast."""
    env = _make("lm", render_mode="rgb_array", camera_name="probe_side", width=160, height=120)
    env.reset(seed=0)
    try:
        frame = env.render()
    except Exception as error:  # noqa: BLE001 - no OpenGL here: say why, skip
        pytest.skip(
            f"no offscreen OpenGL (MUJOCO_GL={os.environ.get('MUJOCO_GL')}): {error}; install "
            "Mesa's EGL (Debian: libegl1 libgl1-mesa-dri) or osmesa (libosmesa6)"
        )
    assert frame.shape == (120, 160, 3) and frame.dtype == np.uint8
    renderer = env.unwrapped._renderer
    model = renderer.model
    breast = [f for f in range(model.nflex)]
    saved = model.flex_rgba.copy()
    model.flex_rgba[breast, 3] = 0.0
    without_breast = env.render()
    model.flex_rgba[:] = saved
    probe_geoms = [g for g in range(model.ngeom) if model.geom(g).name.startswith("probe_")]
    saved_geom = model.geom_rgba.copy()
    model.geom_rgba[probe_geoms, 3] = 0.0
    without_probe = env.render()
    model.geom_rgba[:] = saved_geom
    changed = lambda a, b: np.mean(np.any(a != b, axis=2))  # noqa: E731
    assert changed(frame, without_breast) > 0.02
    assert changed(frame, without_probe) > 0.005
    for _ in range(30):
        env.step(np.array([0, 0.2, 0, 0, 0, 0], dtype=np.float32))
    assert changed(frame, env.render()) > 0.005


@pytest.mark.parametrize(
    "mode, context",
    [
        ("sync", None),
        ("async", "fork"),
        pytest.param("async", "forkserver", marks=pytest.mark.slow),
        pytest.param("async", "spawn", marks=pytest.mark.slow),
    ],
)
def test_vector_environments_reset_as_the_env_declares(mode: str, context: str | None) -> None:
    """Gymnasium's vector environments, workers started every way (the tissue's kernels are
    built in this process first: fork must survive them), reset an ended episode as
    ``metadata["autoreset_mode"]`` declares: the step after the end returns the next
    episode's first observation, reward 0, neither terminated nor truncated."""
    from gymnasium.vector import AutoresetMode

    single = _make("lm")
    mode_declared = single.metadata["autoreset_mode"]
    assert mode_declared == AutoresetMode.NEXT_STEP
    single.close()
    vector_kwargs = {} if context is None else {"context": context}
    vec = gym.make_vec(
        ENV_ID,
        num_envs=2,
        vectorization_mode=mode,
        vector_kwargs=vector_kwargs,
        contact="lm",
        mesh=MESH,
        max_episode_steps=2,
    )
    assert vec.metadata["autoreset_mode"] == mode_declared
    vec.reset(seed=0)
    press = np.tile(np.array([0, 0.2, 0, 0, 0, 0], dtype=np.float32), (2, 1))
    for _ in range(2):
        obs, reward, terminated, truncated, _ = vec.step(press)
    assert np.all(truncated) and np.all(np.isfinite(reward))
    assert np.all(np.abs(obs["wrench"]).max(axis=1) > 0.01)  # the probe presses the skin
    obs, reward, terminated, truncated, _ = vec.step(press)
    # The reset step: action ignored, the start seeded by the same generator (not seed 0's).
    assert reward.tolist() == [0.0, 0.0]
    assert not np.any(terminated) and not np.any(truncated)
    assert obs["lesion"].shape == (2, 4) and np.all(np.isfinite(obs["wrench"]))
    assert np.all(np.abs(obs["wrench"]) < 1e-9)  # the probe starts clear of the skin again
    vec.close()


def test_sb3_subprocess_vector_environment() -> None:
    pytest.importorskip("stable_baselines3", reason=RL_EXTRA)
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import SubprocVecEnv

    # "envs:<id>": a worker process (forkserver, SB3's default) imports envs before making.
    vec = make_vec_env(
        f"envs:{ENV_ID}",
        n_envs=2,
        vec_env_cls=SubprocVecEnv,
        env_kwargs={"contact": "lm", "mesh": MESH},
    )
    vec.reset()
    obs, reward, done, info = vec.step(np.tile(np.array([0, 0.2, 0, 0, 0, 0]), (2, 1)))
    assert np.all(np.isfinite(reward)) and obs["wrench"].shape == (2, 6)
    vec.close()


def test_another_arm_attaches_by_its_flange_site(tmp_path) -> None:
    """Any MJCF arm with a named flange site: here the UR5e's file with the site renamed."""
    from envs.scene import UR5E_PATH

    arm = tmp_path / "arm.xml"
    arm.write_text(UR5E_PATH.read_text().replace('site name="flange"', 'site name="tool0"'))
    with pytest.raises(tissue.TissueInputError, match="no site 'flange'"):
        gym.make(ENV_ID, mesh=MESH, robot=str(arm))
    env = gym.make(ENV_ID, mesh=MESH, robot=str(arm), flange_site="tool0")
    obs, _ = env.reset(seed=0)
    obs, *_ = env.step(np.array([0, 0.2, 0, 0, 0, 0], dtype=np.float32))
    assert np.all(np.isfinite(obs["wrench"]))


@pytest.mark.slow
def test_a_random_policy_rarely_succeeds() -> None:
    """The task is not solved by chance: a uniform random policy succeeds in under 5 % of
    episodes (measured on the default 1,303-tet phantom: 0 of 100, 26 ending on the force
    limit; here 40 episodes on the 623-tet one)."""
    env = _make("lm")
    env.action_space.seed(0)
    successes = 0
    for episode in range(40):
        env.reset(seed=100 + episode)
        while True:
            _, _, terminated, truncated, info = env.step(env.action_space.sample())
            if terminated or truncated:
                break
        successes += bool(info["is_success"])
    assert successes < 0.05 * 40


@pytest.mark.parametrize("contact", ["lm", "penalty"])
def test_the_linearised_wrench_predicts_the_next_tissue_step(contact: str) -> None:
    """What the substeps feel, w0 - K (q - q0), is closer to the next tissue step's force
    than holding w0 would be, pressing at 1 mm a step (a wrong K or sign is worse)."""
    env = _make(contact)
    coupling = env.unwrapped.coupling
    env.reset(seed=2)
    errors = {"linearised": [], "held": []}
    real = coupling.after_substeps

    def compared():
        predicted, held = coupling.wrench_now().force, coupling._w0[:3].copy()
        step = real()
        errors["linearised"].append(np.linalg.norm(predicted - step.force_world_n))
        errors["held"].append(np.linalg.norm(held - step.force_world_n))
        return step

    coupling.after_substeps = compared
    for _ in range(12):
        env.step(np.array([0.0, 0.2, 0.0, 0.0, 0.0, 0.0], dtype=np.float32))
    assert np.mean(errors["linearised"][3:]) < 0.8 * np.mean(errors["held"][3:])
