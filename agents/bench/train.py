"""``probegym bench train``: what a training run's environment step costs, by phase.

For each environment id and contact method (robust profile, the environments' default skin),
one environment in this process, records with a ``phase`` key:

- ``press``: the scripted press of ``probegym bench env`` (reset with seed 0, 40 steps pressing
  0.2 mm a step along the probe's axis, 60 sliding along the image's lateral axis), steps per
  second from the median CPU time of a step;
- ``exploring``: actions as a freshly initialised PPO policy draws them: Gaussian about SB3's
  initial mean (close to 0: its action layer starts with weights of gain 0.01) with the
  spread ``probegym train`` gives PPO (``log_std_init`` in
  :data:`agents.train.run.DEFAULT_HYPERPARAMETERS`), clipped to the action box as SB3 clips
  them, episodes reset with seeds 1, 2, ... as they end. Timed over the steps whose tissue
  step starts with the probe in contact (``contact_share`` says how many that was), median
  CPU time, with the mean Newton iterations of the tissue's steps beside it.

``exploring_over_press`` is the ratio the training-speed work aims to raise to 0.85.

Limitations: the ``train`` phase (``probegym train``'s own path end to end, with its parts:
transfers, normalisation, inference, gradient updates) and the replay of a trained policy are
not measured here yet.
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from agents.bench.contact import threading_environment
from agents.bench.env import scripted_press
from agents.bench.report import BenchRecord, MarkdownTable, write_records

DEFAULT_IDS = ("probegym/BreastCompress-v0",)
DEFAULT_METHODS = ("lm",)
DEFAULT_LEVEL = 1363
#: Exploring steps drawn per record (episodes reset as they end).
EXPLORING_STEPS = 300
#: The ratio of the exploring step's rate to the press's that the training-speed work aims at.
TARGET_EXPLORING_OVER_PRESS = 0.85


def exploring_spread() -> float:
    """The standard deviation of a fresh PPO policy's actions under ``probegym train``."""
    from agents.train.run import DEFAULT_HYPERPARAMETERS

    log_std = DEFAULT_HYPERPARAMETERS["ppo"]["policy_kwargs"].get("log_std_init", 0.0)
    return float(np.exp(log_std))


def _make(env_id: str, contact: str, level: int) -> Any:
    import gymnasium as gym

    import envs  # noqa: F401 - registers the ids

    return gym.make(env_id, contact=contact, mesh=level, profile="robust")


def _identity(env: Any, env_id: str, contact: str, level: int, phase: str) -> dict[str, Any]:
    unwrapped = env.unwrapped
    return {
        "phase": phase,
        "env_id": env_id,
        "contact": contact,
        "profile": unwrapped.tissue.spec.profile,
        "level": level,
        "tets": int(unwrapped.tissue.tets.shape[0]),
        "collision_edge_m": unwrapped.tissue.spec.collision_edge_m,
    }


def press_record(env_id: str, contact: str, level: int) -> dict[str, Any]:
    """The ``press`` phase (see the module docstring): every step timed, as ``bench env``."""
    env = _make(env_id, contact, level)
    env.reset(seed=0)
    record = _identity(env, env_id, contact, level, "press")
    timed = _time_steps(env, iter(scripted_press(env.unwrapped)), contact_only=False)
    env.close()
    return record | timed


def exploring_record(
    env_id: str, contact: str, level: int, steps: int = EXPLORING_STEPS, seed: int = 0
) -> dict[str, Any]:
    """The ``exploring`` phase (see the module docstring): the steps in contact timed."""
    env = _make(env_id, contact, level)
    rng = np.random.default_rng(seed)
    spread = exploring_spread()
    low, high = env.action_space.low, env.action_space.high
    draws = (
        np.clip(spread * rng.standard_normal(low.shape), low, high).astype(np.float32)
        for _ in range(steps)
    )
    env.reset(seed=1)
    record = _identity(env, env_id, contact, level, "exploring")
    record |= _time_steps(env, draws, contact_only=True, next_seed=2)
    env.close()
    record["action_std"] = spread
    return record


def _time_steps(
    env: Any, actions: Iterator[np.ndarray], contact_only: bool, next_seed: int | None = None
) -> dict[str, Any]:
    """Step ``env`` through ``actions`` and time each step (CPU time). A step is in contact
    when its tissue step starts with a pressing force; ``contact_only`` times only those.
    An episode that ends stops the run (``next_seed`` None) or resets with the next seed.
    Returns :func:`_rates`' fields, ``contact_share`` (of the steps taken) and ``episodes``."""
    unwrapped = env.unwrapped
    cpu, iterations, in_contact = [], [], []
    episodes = 1
    for action in actions:
        touching = unwrapped.normal_force_n(unwrapped.coupling.last_step) > 0.0
        tic = time.process_time()
        _, _, terminated, truncated, _ = env.step(action)
        elapsed = time.process_time() - tic
        in_contact.append(touching)
        if touching or not contact_only:
            cpu.append(elapsed)
            iterations.append(_newton_iterations(unwrapped))
        if terminated or truncated:
            if next_seed is None:
                break
            env.reset(seed=next_seed + episodes - 1)
            episodes += 1
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


def run_train_benchmark(
    env_ids: list[str] | None,
    methods: list[str] | None,
    level: int,
    json_path: Path,
    command: str | None = None,
) -> list[dict[str, Any]]:
    """Both phases for every id and method; prints a table and writes the JSON as it goes."""
    records: list[dict[str, Any]] = []
    started = time.strftime("%Y-%m-%dT%H:%M:%S")
    provenance = BenchRecord("probegym bench train: a training step's cost, by phase", command)
    for env_id in env_ids or DEFAULT_IDS:
        for contact in methods or DEFAULT_METHODS:
            press = press_record(env_id, contact, level)
            exploring = exploring_record(env_id, contact, level)
            if press["steps_per_s"] and exploring["steps_per_s"]:
                ratio = exploring["steps_per_s"] / press["steps_per_s"]
                exploring["exploring_over_press"] = ratio
                exploring["target_exploring_over_press"] = TARGET_EXPLORING_OVER_PRESS
                exploring["meets_target"] = ratio >= TARGET_EXPLORING_OVER_PRESS
            for record in (press, exploring):
                records.append(record)
                _print(record)
            write_records(json_path, "train", started, records, threads=threading_environment())
    provenance.write(json_path, [_table(records)])
    return records


def _table(records: list[dict[str, Any]]) -> MarkdownTable:
    table = MarkdownTable(
        "one environment's steps per second by phase (median CPU time), robust profile",
        ["env", "contact", "level (tets)", "skin edge (mm)", "phase", "steps/s",
         "Newton iterations", "steps timed", "in contact", "exploring / press (target 0.85)"],
    )  # fmt: skip
    for r in records:
        edge = r["collision_edge_m"]
        ratio = r.get("exploring_over_press")
        verdict = (
            "" if ratio is None else f"{ratio:.2f} ({'met' if r['meets_target'] else 'missed'})"
        )
        rate = r["steps_per_s"]
        table.rows.append([
            r["env_id"], r["contact"], f"{r['level']} ({r['tets']:,})",
            "paper" if edge is None else f"{edge * 1e3:g}", r["phase"],
            "-" if rate is None else f"{rate:.0f}",
            f"{r.get('newton_iterations_mean', 0.0):.2f}",
            str(r["steps_timed"]), f"{r['contact_share'] * 100:.0f} %", verdict,
        ])  # fmt: skip
    return table


def _print(record: dict[str, Any]) -> None:
    rate = record["steps_per_s"]
    ratio = record.get("exploring_over_press")
    print(
        f"{record['env_id']} {record['contact']} level {record['level']} {record['phase']:9s}: "
        + ("no step timed" if rate is None else f"{rate:6.0f} steps/s")
        + f", {record.get('newton_iterations_mean', 0.0):.2f} Newton iterations, "
        f"{record['steps_timed']} steps timed, {record['contact_share'] * 100:.0f} % in contact"
        + ("" if ratio is None else f"; exploring / press {ratio:.2f}"),
        flush=True,
    )
