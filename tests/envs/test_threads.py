"""The environments' thread policy (``tissue.configure_threads``), and their observations'
bits on one numba thread and on two."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import numba
import pytest

import envs  # noqa: F401 - registers the environments
import tissue
import tissue.sim.solvers as solvers
from tissue.threads import thread_policy

ROOT = Path(__file__).resolve().parents[2]
ENV_ID = "probegym/BreastCompress-v0"
METHODS = ("lm", "penalty", "prescribed", "pbd")
POOL_THREADS = int(numba.config.NUMBA_NUM_THREADS)  # type: ignore[attr-defined]

# One process's rollouts: per case (contact:level), reset with seed 0 and press for the
# given steps; a digest of every step's observation and of the tissue's node positions [m]
# (float64: the observations' float32 hide the last bits for tens of steps).
_ROLLOUTS = """
import hashlib, sys
import gymnasium, numba, numpy as np
import envs  # noqa: F401
steps = int(sys.argv[1])
press = np.array([0.0, 0.04, 0.0, 0.0, 0.0, 0.0], dtype=np.float32)
for case in sys.argv[2:]:
    contact, level = case.split(":")
    env = gymnasium.make("probegym/BreastCompress-v0", contact=contact, mesh=int(level))
    env.reset(seed=0)
    digest = hashlib.sha256()
    for _ in range(steps):
        obs = env.step(press)[0]
        for key in sorted(obs):
            digest.update(np.ascontiguousarray(obs[key]).tobytes())
        digest.update(env.unwrapped.tissue.positions_m.tobytes())
    nodes = env.unwrapped.tissue.rest_nodes_m.shape[0]
    print(case, numba.get_num_threads(), nodes, digest.hexdigest())
    env.close()
"""


def _rollout_digests(threads: int, steps: int, cases: list[str]) -> list[list[str]]:
    """The rollouts in a fresh process with numba's pool at ``threads`` threads."""
    out = subprocess.run(
        [sys.executable, "-c", _ROLLOUTS, str(steps), *cases],
        capture_output=True,
        text=True,
        check=True,
        env={**os.environ, "NUMBA_NUM_THREADS": str(threads)},
        cwd=ROOT,
        timeout=1800,
    )
    lines = [line.split() for line in out.stdout.splitlines()]
    assert [line[0] for line in lines] == cases, out.stdout
    return lines


@pytest.mark.slow
def test_observations_are_the_same_bits_on_one_and_two_numba_threads() -> None:
    """From phantom level 7,369 up a step runs its kernels in parallel; up to 26,220 its
    observations are still the same bits on any number of threads (before the products'
    one-part rule the node positions differed from the first step, the observations from
    step 11 to 28). Slow: about 1 min here (eight environments built twice)."""
    cases = [f"{contact}:{level}" for level in (7369, 26220) for contact in METHODS]
    one, two = _rollout_digests(1, 5, cases), _rollout_digests(2, 5, cases)
    for (case, threads_1, nodes, digest_1), (_, threads_2, _, digest_2) in zip(
        one, two, strict=True
    ):
        assert (threads_1, threads_2) == ("1", "2")
        # Parallel steps, one-thread CG: the sizes whose bits the one-part rule keeps.
        assert solvers.SERIAL_STEP_UNKNOWNS <= 3 * int(nodes) < solvers.SERIAL_CG_UNKNOWNS
        assert digest_1 == digest_2, f"{case}: observations differ on 1 and 2 numba threads"


def test_environment_applies_the_thread_policy_before_building_its_tissue(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    calls: list[str] = []
    configure, make = tissue.configure_threads, tissue.make_tissue

    def configure_threads(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202 - a spy
        calls.append("configure_threads")
        return configure(*args, **kwargs)

    def make_tissue(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202 - a spy
        calls.append("make_tissue")
        return make(*args, **kwargs)

    monkeypatch.setattr(tissue, "configure_threads", configure_threads)
    monkeypatch.setattr(tissue, "make_tissue", make_tissue)
    gym.make(ENV_ID, contact="prescribed", mesh=623).close()
    assert calls == ["configure_threads", "make_tissue"]


def test_environment_keeps_a_thread_policy_its_user_set() -> None:
    policy, threads = thread_policy(), numba.get_num_threads()
    try:
        tissue.configure_threads(threads=1)
        gym.make(ENV_ID, contact="prescribed", mesh=623).close()
        assert thread_policy().threads == 1 and numba.get_num_threads() == 1
    finally:
        tissue.configure_threads(threads=policy.threads or POOL_THREADS)
        numba.set_num_threads(threads)
