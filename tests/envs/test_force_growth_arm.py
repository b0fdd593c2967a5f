"""Forces that grow with depth, under the arm: ``probegym/BreastCompress-v0`` pressed along
the probe's axis by a scripted action, the force read from the F/T observation, never
falls by more than 5 % as the probe goes deeper (slow tier: coupled rollouts).

The same protocol as ``tests/tissue/test_force_growth.py`` (``docs/contact.md``, "Forces
that grow with depth"), with the robot in the loop: each of the environment's target
lesions, the start without its noise (just touching the skin at rest, normal to it), the
target moved 0.5 mm along the probe's axis every step, the impedance-controlled probe
following it (0.47 mm a step once under way); until the force passes the 5 N safety force.
The force is the F/T observation's component along the probe's pressing axis (the
observation is the tissue's wrench on the probe, probe frame: the tissue pushes back along
-y). The depth is the probe's own, along its starting axis. As in the tissue test, each
press stops a step (0.5 mm) short of the depth where the tissue slips on the sloped skin
(that test's ``SLIP_FROM_M``, measured with the probe held kinematically; under the arm the
falls come at the same depths: 16.1, 11.7 and 19.5 mm at 1,363 tets, 19.4 mm at 623), for
the reasons that test gives.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import envs  # noqa: F401 - registers the environments
from envs.probe_env import PHANTOM_TARGET_LESIONS

ENV_ID = "probegym/BreastCompress-v0"
METHODS = ("lm", "penalty", "prescribed", "pbd")
STEP_M = 0.0005
FORCE_RANGE_N = 5.0
ALLOWED_FALL = 0.05
LEAST_FORCE_N = 1.5
MAX_STEPS = 70
#: As ``tests/tissue/test_force_growth.py``'s: the depth [m] at which the tissue slips at
#: (level, lesion).
SLIP_FROM_M = {
    (623, 10): 0.018,
    (1363, 6): 0.016,
    (1363, 7): 0.0115,
    (1363, 10): 0.0195,
}


def test_the_lesions_pressed_are_the_environments_targets() -> None:
    # The tissue test's sites are these lesions and the apex.
    assert PHANTOM_TARGET_LESIONS == (1, 4, 6, 7, 10)


@pytest.mark.slow
@pytest.mark.parametrize("lesion", PHANTOM_TARGET_LESIONS)
@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("level", [623, 1363])
def test_a_press_through_the_arm_never_loses_force(level: int, method: str, lesion: int) -> None:
    env = gym.make(
        ENV_ID,
        contact=method,
        mesh=level,
        target_lesions=(lesion,),
        start_offset_m=0.0,
        start_tilt_rad=0.0,
    )
    unwrapped = env.unwrapped
    env.reset(seed=0)
    start, rotation = unwrapped.probe_pose()
    pressing = rotation[:, 1]
    action = np.zeros(6, dtype=np.float32)
    action[1] = STEP_M / unwrapped.action_config.max_translation_m
    stop_at = SLIP_FROM_M.get((level, lesion), np.inf) - STEP_M
    forces: list[float] = []
    for _ in range(MAX_STEPS):
        observation, _, terminated, truncated, info = env.step(action)
        position, _ = unwrapped.probe_pose()
        if float((position - start) @ pressing) >= stop_at:
            break
        assert not (terminated or truncated), info
        assert info["tissue"]["status"] == "ok", info
        forces.append(-float(observation["wrench"][1]))
        if forces[-1] > FORCE_RANGE_N:
            break
    env.close()
    assert max(forces) >= LEAST_FORCE_N, forces
    highest = np.maximum.accumulate(forces)
    falls = (highest - forces) / np.where(highest > 0.0, highest, 1.0)
    assert falls.max() <= ALLOWED_FALL, np.round(forces, 3).tolist()
