"""Clocks that ``probegym bench train`` puts into a ``probegym train`` run, and the run's parts.

:func:`agents.learning.train.run.train` takes a :class:`TrainTiming` and, where given, wraps each
worker's environment in :class:`StepClock`, the vector environment below the observation
normalisation and above it in :class:`TimedVecEnv`, and adds :class:`TrainClock` to its
callbacks; nothing else in the run changes. The parts of the learning loop's wall time
(:meth:`TrainTiming.parts`), in seconds:

- ``env_s``: the environments' steps on the critical path: per vector step, the slowest
  worker's ``env.step`` (its wall time inside the worker: tissue, controller, MuJoCo,
  observation, the ``Monitor``), summed; ``env_tissue_s`` the tissue's share of it;
- ``transfer_s``: the vector step's wall time less ``env_s``: actions and results pickled
  through the workers' pipes, and the wait for a worker behind its peers (``env_s`` takes
  the slowest's step, so load imbalance counts here only as far as it shifts between steps);
- ``normalisation_s``: ``VecNormalize``'s own time (the wrapped vector step's time less the
  unwrapped one's);
- ``inference_s``: the rest of collecting the rollouts: the policy's forward pass, the
  rollout or replay buffer, the callbacks;
- ``updates_s``: the learning loop's wall time outside collecting rollouts: gradient updates
  (PPO after each rollout, SAC after every vector step), with SB3's logging.

stable-baselines3 (the ``rl`` extra) is imported when a :class:`TrainTiming` is made, not
with this module, so that the command line (which imports every command) works without it.

Limitations: resets inside ``step`` (SB3's auto-reset in the worker) count as environment
time; the time the run spends before ``learn`` (building the workers, the first evaluation
environment) is not in the loop's wall time, so steps per second are those of the loop.
"""

from __future__ import annotations

import functools
import time
from typing import Any

import gymnasium as gym
import numpy as np


class StepClock(gym.Wrapper):
    """Puts the wall time of ``env.step`` [s] in ``info["bench_step_s"]`` and the tissue's
    share (the environment's ``last_timing["tissue_s"]``) in ``info["bench_tissue_s"]``."""

    def step(self, action: Any) -> tuple[Any, Any, Any, Any, dict[str, Any]]:
        tic = time.perf_counter()
        observation, reward, terminated, truncated, info = self.env.step(action)
        info["bench_step_s"] = time.perf_counter() - tic
        timing = getattr(self.env.unwrapped, "last_timing", {})
        info["bench_tissue_s"] = float(timing.get("tissue_s", 0.0))
        return observation, reward, terminated, truncated, info


@functools.cache
def _clock_classes() -> tuple[type, type]:
    """(TimedVecEnv, TrainClock), defined once stable-baselines3 is imported."""
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.vec_env import VecEnv, VecEnvWrapper

    class TimedVecEnv(VecEnvWrapper):
        """Adds up the wall time [s] from ``step_async`` to the end of ``step_wait``."""

        def __init__(self, venv: VecEnv) -> None:
            super().__init__(venv)
            self.step_s = 0.0
            self._started = 0.0

        def step_async(self, actions: np.ndarray) -> None:
            self._started = time.perf_counter()
            self.venv.step_async(actions)

        def step_wait(self) -> Any:
            result = self.venv.step_wait()
            self.step_s += time.perf_counter() - self._started
            return result

        def reset(self) -> Any:
            return self.venv.reset()

    class TrainClock(BaseCallback):
        """The learning loop's wall time, the rollouts' share, and the workers' step times."""

        def __init__(self) -> None:
            super().__init__(verbose=0)
            self.loop_s = 0.0
            self.rollout_s = 0.0
            self.env_s = 0.0
            self.env_tissue_s = 0.0
            self.env_cpu_sum_s = 0.0
            self.vector_steps = 0
            self._loop_start = 0.0
            self._rollout_start = 0.0

        def _on_training_start(self) -> None:
            self._loop_start = time.perf_counter()

        def _on_rollout_start(self) -> None:
            self._rollout_start = time.perf_counter()

        def _on_step(self) -> bool:
            infos = self.locals.get("infos", [])
            steps = [float(info.get("bench_step_s", 0.0)) for info in infos]
            if steps:
                slowest = int(np.argmax(steps))
                self.env_s += steps[slowest]
                self.env_tissue_s += float(infos[slowest].get("bench_tissue_s", 0.0))
                self.env_cpu_sum_s += float(np.sum(steps))
            self.vector_steps += 1
            return True

        def _on_rollout_end(self) -> None:
            self.rollout_s += time.perf_counter() - self._rollout_start

        def _on_training_end(self) -> None:
            self.loop_s = time.perf_counter() - self._loop_start

    return TimedVecEnv, TrainClock


class TrainTiming:
    """The hooks :func:`agents.learning.train.run.train` takes (see the module docstring)."""

    env_wrapper = StepClock

    def __init__(self) -> None:
        self._timed, clock = _clock_classes()
        self.callback = clock()
        self._inner: Any = None
        self._outer: Any = None

    def inner(self, venv: Any) -> Any:
        """Wrap the workers' vector environment (below the normalisation)."""
        self._inner = self._timed(venv)
        return self._inner

    def outer(self, venv: Any) -> Any:
        """Wrap the vector environment the algorithm steps (above the normalisation)."""
        self._outer = self._timed(venv)
        return self._outer

    def mirror(self, venv: Any) -> Any:
        """The evaluation's vector environment wrapped as the training's, below and above
        the normalisation (SB3 copies the normalisation's statistics by walking both wrapper
        chains side by side); its time is not counted."""
        return self._timed(venv)

    def parts(self) -> dict[str, float]:
        """The learning loop's wall time and its parts [s] (see the module docstring)."""
        clock = self.callback
        inner = self._inner.step_s if self._inner is not None else 0.0
        outer = self._outer.step_s if self._outer is not None else inner
        return {
            "loop_s": clock.loop_s,
            "env_s": clock.env_s,
            "env_tissue_s": clock.env_tissue_s,
            "transfer_s": max(0.0, inner - clock.env_s),
            "normalisation_s": max(0.0, outer - inner),
            "inference_s": max(0.0, clock.rollout_s - outer),
            "updates_s": max(0.0, clock.loop_s - clock.rollout_s),
            "env_steps_summed_s": clock.env_cpu_sum_s,
            "vector_steps": float(clock.vector_steps),
        }
