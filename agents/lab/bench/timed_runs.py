"""Timed runs of an environment, stepped alone or in turn with others.

A :data:`TimedRun` is a generator that steps one environment with an actor's actions and
times each step (CPU time), yielding the share of its planned steps done after each and
returning its rates. :func:`interleave` steps several in turn, the one furthest behind
next, so that a machine whose speed drifts while they run slows each alike: their ratios
hold where their absolute rates do not (``probegym bench train``'s phases).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Generator
from typing import Any

import numpy as np

#: A phase's timed run: yields its share of work done (0-1] after each step, returns its
#: record.
TimedRun = Generator[float, None, dict[str, Any]]


def run_alone(run: TimedRun) -> dict[str, Any]:
    """A timed run stepped to its end on its own."""
    return interleave([run])[0]


def interleave(runs: list[TimedRun]) -> list[dict[str, Any]]:
    """Step ``runs`` in turn, the one that has done the smallest share of its work next, until
    each ends; their records, in order. A machine that slows down for a while (shared
    machines do, by 1.5 x within minutes) then slows every phase alike."""
    done: list[float] = [0.0] * len(runs)
    records: list[dict[str, Any] | None] = [None] * len(runs)
    live = set(range(len(runs)))
    while live:
        index = min(live, key=lambda i: done[i])
        try:
            done[index] = next(runs[index])
        except StopIteration as ended:
            records[index] = ended.value
            live.discard(index)
    return [record for record in records if record is not None]


#: An action source for :func:`timed_steps`: the next action for an observation, None to stop.
Actor = Callable[[dict[str, Any]], "np.ndarray | None"]


def replaying(actions: list[np.ndarray]) -> Actor:
    """An actor that plays ``actions`` in order, whatever it observes, then stops."""
    remaining = iter(actions)
    return lambda _: next(remaining, None)


def timed_steps(
    env: Any,
    act: Actor,
    observation: dict[str, Any],
    planned: int,
    contact_only: bool,
    next_seed: int | None = None,
) -> TimedRun:
    """Step ``env`` (just reset to ``observation``) with ``act``'s actions until it gives
    None, and time each step (CPU time; the action is chosen outside the clock), yielding
    the steps taken over ``planned`` after each. A step is in contact when its tissue step
    starts with a pressing force; ``contact_only`` times only those. An episode that ends
    stops the run (``next_seed`` None) or resets with the next seed. Returns
    :func:`_rates`' fields, ``contact_share`` (of the steps taken) and ``episodes``."""
    unwrapped = env.unwrapped
    cpu, iterations, in_contact = [], [], []
    episodes = 1
    while (action := act(observation)) is not None:
        touching = unwrapped.normal_force_n(unwrapped.coupling.last_step) > 0.0
        tic = time.process_time()
        observation, _, terminated, truncated, _ = env.step(action)
        elapsed = time.process_time() - tic
        in_contact.append(touching)
        if touching or not contact_only:
            cpu.append(elapsed)
            iterations.append(_newton_iterations(unwrapped))
        if terminated or truncated:
            if next_seed is None:
                break
            observation, _ = env.reset(seed=next_seed + episodes - 1)
            episodes += 1
        yield len(in_contact) / max(planned, 1)
    rates = _rates(cpu, iterations)
    rates["contact_share"] = float(np.mean(in_contact)) if in_contact else 0.0
    rates["episodes"] = episodes
    return rates


def _newton_iterations(unwrapped: Any) -> int:
    step = unwrapped.coupling.last_step
    return 0 if step is None else int(step.diagnostics.iterations)


def _rates(cpu: list[float], iterations: list[int]) -> dict[str, Any]:
    """Steps per second from the median CPU time of the timed steps, and how many were timed."""
    if not cpu:
        return {"steps_timed": 0, "steps_per_s": None}
    median = float(np.median(cpu))
    return {
        "steps_timed": len(cpu),
        "steps_per_s": 1.0 / median if median > 0 else None,
        "step_cpu_ms": median * 1e3,
        "newton_iterations_mean": float(np.mean(iterations)),
        "load_average": list(os.getloadavg()),
    }
