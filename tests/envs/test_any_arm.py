"""The environments hold for an arm other than the default: every task with the 7-joint arm
(``assets/robots/arm7.xml``) in both control modes, its last joint driven in ``joint_delta``."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import envs
from envs.errors import EnvConfigError
from envs.scene import ARM7_PATH

MESH = 623


@pytest.mark.parametrize("env_id", envs.ENV_IDS)
@pytest.mark.parametrize("mode", ["cartesian_impedance", "joint_delta"])
def test_every_task_runs_with_a_seven_joint_arm(env_id: str, mode: str) -> None:
    env = gym.make(env_id, mesh=MESH, robot=str(ARM7_PATH), control_mode=mode)
    unwrapped = env.unwrapped
    assert unwrapped.joint_count == 7
    size = 6 if mode == "cartesian_impedance" else 7
    assert env.action_space.shape == (size,)
    assert env.observation_space["joint_pos"].shape == (7,)
    observation, _ = env.reset(seed=0)
    assert env.observation_space.contains(observation)
    # The home pose came from the arm's keyframe: the roll joint near its seed (0), not at a
    # joint limit (the UR5e's six angles padded with a zero gave a roll of 2.9 rad).
    assert abs(unwrapped._home[2]) < 0.5
    start = observation["joint_pos"].copy()
    action = np.zeros(size, dtype=np.float32)
    action[-1] = 0.5  # the last joint in joint_delta mode; a turn about z in Cartesian mode
    for _ in range(5):
        observation, reward, terminated, truncated, info = env.step(action)
        assert env.observation_space.contains(observation) and np.isfinite(reward)
        if terminated or truncated:
            break
    assert "robot_unstable" not in info
    moved = np.abs(observation["joint_pos"] - start)
    if mode == "joint_delta":
        assert moved[6] > 0.05 and moved[6] == moved.max()  # the seventh joint is driven
    else:
        assert moved.max() > 1e-3
    with pytest.raises(EnvConfigError, match=f"an action is {size} numbers"):
        env.step(np.zeros(size + 1, dtype=np.float32))
    env.close()
