"""``probegym bench effects``: what each simulated effect costs, and that what is not
needed costs nothing (:mod:`envs.effects`).

For each contact method and profile, on ``probegym/ForceScan-v0`` (its terms need only
``force_feedback``, so it runs on every scene) at the default training mesh, one process,
no rendering:

- **free air**: reset with seed 0 (the probe just touching the skin, no force), lift the
  probe 20 mm in 5 steps, then 40 steps sweeping sideways 2 mm a step, well clear of the
  skin; the tissue untouched since the reset;
- **robot only**: the same in the ``rigid`` scene (no FE tissue: the arm, the controller,
  MuJoCo's collision of the probe's face with the breast's hull, the observation), the
  two scenes stepped in turn (full, rigid, full, ...) over three episodes, so that a
  shared machine's load falls on both alike; the ratio is the median of the pairs';
- **contact**: reset with seed 0, 30 steps pressing 0.2 mm a step, then 40 sliding 0.2 mm
  a step along the image's lateral axis (timed).

Per record: the median CPU time of a step in each phase (``time.process_time``), the
tissue's share of a step (the median of tissue time / step time, wall clock, from
:attr:`envs.probe_env.ProbeEnv.last_timing`) in free air and in contact, the free-air step
against the robot-only step, and the cost each effect adds when on: ``deformation`` (a
contact step in the full scene less one in the rigid scene), ``force_feedback`` (the wrench
stiffness in contact, median per step), ``lesion_tracking`` (locating the target lesion:
:meth:`tissue.Tissue.lesion_centroids_m` of one lesion and its projection into the image
plane; no tissue step locates any lesion in the environments), and
``image`` (a 128 x 128 B-mode frame).

Targets: the tissue's share of a free-air step at most 5 %; a free-air step at most 1.1 x a
robot-only step.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from agents.lab.bench.contact import threading_environment
from agents.lab.bench.env import image_frame_ms
from agents.lab.bench.report import BenchRecord, MarkdownTable, write_records

ENV_ID = "probegym/ForceScan-v0"
DEFAULT_METHODS = ("lm", "penalty", "prescribed", "pbd")
DEFAULT_PROFILES = ("robust", "paper")
DEFAULT_LEVEL = 1363
LIFT_STEPS = 5
HOVER_STEPS = 40
PRESS_STEPS = 30
SLIDE_STEPS = 40
#: Episodes of the free-air phase, each scene stepped in turn.
FREE_AIR_REPEATS = 3
TARGET_FREE_AIR_SHARE = 0.05
TARGET_FREE_AIR_RATIO = 1.1
#: Repeats of the lesion-tracking timing.
LESION_REPEATS = 200


def _timed_steps(env: Any, actions: list[np.ndarray]) -> dict[str, Any]:
    """Step ``actions``; median CPU time [ms], median tissue share, statuses, whether the
    tissue slept (steps with ``details['asleep']``)."""
    unwrapped = env.unwrapped
    cpu, shares, stiffness, statuses, asleep = [], [], [], [], 0
    for action in actions:
        tic_cpu, tic = time.process_time(), time.perf_counter()
        _, _, terminated, truncated, info = env.step(action)
        wall = time.perf_counter() - tic
        cpu.append(time.process_time() - tic_cpu)
        timing = unwrapped.last_timing
        shares.append(timing["tissue_s"] / wall if wall > 0 else 0.0)
        stiffness.append(timing["stiffness_s"])
        statuses.append(info.get("tissue", {}).get("status"))
        step = unwrapped.coupling.last_step
        if step is not None and step.diagnostics.details.get("asleep"):
            asleep += 1
        if terminated or truncated:
            break
    return {
        "ms": float(np.median(cpu)) * 1e3,
        "tissue_share": float(np.median(shares)),
        "stiffness_ms": float(np.median(stiffness)) * 1e3,
        "steps": len(cpu),
        "asleep": asleep,
        "statuses": {status: statuses.count(status) for status in set(statuses)},
    }


def _free_air_actions(env: Any) -> list[np.ndarray]:
    lift = np.array([0.0, -0.8, 0.0, 0.0, 0.0, 0.0], dtype=np.float32)
    sweep = [
        np.array([0.4 if (k // 10) % 2 == 0 else -0.4, 0, 0, 0, 0, 0], dtype=np.float32)
        for k in range(HOVER_STEPS)
    ]
    return [lift] * LIFT_STEPS + sweep


def _contact_actions(env: Any) -> tuple[list[np.ndarray], list[np.ndarray]]:
    per_step = 0.0002 / env.unwrapped.action_config.max_translation_m
    press = [np.array([0.0, per_step, 0, 0, 0, 0], dtype=np.float32)] * PRESS_STEPS
    slide = [np.array([per_step, 0.0, 0, 0, 0, 0], dtype=np.float32)] * SLIDE_STEPS
    return press, slide


def _free_air_pairs(full: Any, rigid: Any, actions: list[np.ndarray]) -> dict[str, Any]:
    """The free-air phase in both scenes, step by step in turn (full, rigid, full, ...), so
    that a shared machine's load falls on both alike: :data:`FREE_AIR_REPEATS` episodes'
    hover steps after an untimed lift. Medians of each scene's CPU time [ms] and of the
    pairs' ratios, the full scene's tissue share and its sleeping steps."""
    full_ms, rigid_ms, ratios, shares, asleep = [], [], [], [], 0
    unwrapped = full.unwrapped
    for _ in range(FREE_AIR_REPEATS):
        for env in (full, rigid):
            env.reset(seed=0)
            for action in actions[:LIFT_STEPS]:
                env.step(action)
        for action in actions[LIFT_STEPS:]:
            tic_cpu, tic = time.process_time(), time.perf_counter()
            full.step(action)
            wall = time.perf_counter() - tic
            ours = time.process_time() - tic_cpu
            tic_cpu = time.process_time()
            rigid.step(action)
            theirs = time.process_time() - tic_cpu
            full_ms.append(ours * 1e3)
            rigid_ms.append(theirs * 1e3)
            if theirs > 0:
                ratios.append(ours / theirs)
            shares.append(unwrapped.last_timing["tissue_s"] / wall if wall > 0 else 0.0)
            step = unwrapped.coupling.last_step
            asleep += bool(step is not None and step.diagnostics.details.get("asleep"))
    return {
        "full_ms": float(np.median(full_ms)),
        "rigid_ms": float(np.median(rigid_ms)),
        "ratio": float(np.median(ratios)),
        "tissue_share": float(np.median(shares)),
        "asleep": asleep,
        "steps": len(full_ms),
    }


def _phase(env: Any, actions: list[np.ndarray], warm: list[np.ndarray] | None = None) -> Any:
    env.reset(seed=0)
    if warm:
        _timed_steps(env, warm)
    return _timed_steps(env, actions)


def _lesion_tracking_ms(env: Any) -> float:
    """Median time of locating one lesion (a task's target) in the image plane now [ms]:
    what ``lesion_tracking`` adds to a step of a task that tracks one."""
    from envs.observations import lesion_in_image

    unwrapped = env.unwrapped
    lesion = unwrapped.tissue.lesions[0]
    position, rotation = unwrapped.probe_pose()
    times = []
    for _ in range(LESION_REPEATS):
        tic = time.perf_counter()
        centroid = unwrapped.tissue.lesion_centroids_m((0,))[0]
        lesion_in_image(centroid, lesion.radius_m, position, rotation, 1.0, unwrapped.imaging)
        times.append(time.perf_counter() - tic)
    return float(np.median(times)) * 1e3


def benchmark_effects(contact: str, profile: str, level: int) -> dict[str, Any]:
    """One record (see the module docstring)."""
    import gymnasium as gym

    import envs  # noqa: F401 - registers the ids

    kwargs: dict[str, Any] = {"contact": contact, "profile": profile, "mesh": level}
    full = gym.make(ENV_ID, **kwargs)
    rigid = gym.make(ENV_ID, scene="rigid", **kwargs)
    free_actions = _free_air_actions(full)
    press, slide = _contact_actions(full)
    for env in (full, rigid):
        _phase(env, free_actions)  # once untimed: kernels loaded, caches warm
    free = _free_air_pairs(full, rigid, free_actions)
    contact_run = _phase(full, slide, warm=press)
    rigid_contact = _phase(rigid, slide, warm=press)
    lesion_ms = _lesion_tracking_ms(full)
    image_ms = image_frame_ms(full.unwrapped)
    unwrapped: Any = full.unwrapped
    tets = int(unwrapped.tissue.tets.shape[0])
    full.close()
    rigid.close()
    record: dict[str, Any] = {
        "env_id": ENV_ID,
        "contact": contact,
        "profile": profile,
        "level": level,
        "tets": tets,
        "free_air_ms": free["full_ms"],
        "free_air_tissue_share": free["tissue_share"],
        "free_air_asleep_steps": free["asleep"],
        "free_air_steps": free["steps"],
        "robot_only_ms": free["rigid_ms"],
        "free_air_ratio": free["ratio"],
        "contact_ms": contact_run["ms"],
        "contact_tissue_share": contact_run["tissue_share"],
        "rigid_contact_ms": rigid_contact["ms"],
        "deformation_ms": contact_run["ms"] - rigid_contact["ms"],
        "force_feedback_ms": contact_run["stiffness_ms"],
        "lesion_tracking_ms": lesion_ms,
        "image_ms": image_ms,
        "statuses": contact_run["statuses"],
        "load_average": list(os.getloadavg()),
    }
    record["meets_share_target"] = record["free_air_tissue_share"] <= TARGET_FREE_AIR_SHARE
    record["meets_ratio_target"] = record["free_air_ratio"] <= TARGET_FREE_AIR_RATIO
    return record


def run_effects_benchmark(
    methods: list[str] | None,
    profiles: list[str] | None,
    level: int | None,
    json_path: Path,
    command: str | None = None,
) -> list[dict[str, Any]]:
    """Every method and profile; prints a table and writes the JSON as it goes."""
    records: list[dict[str, Any]] = []
    started = time.strftime("%Y-%m-%dT%H:%M:%S")
    provenance = BenchRecord("probegym bench effects: what each effect costs", command)
    import envs.errors

    for profile in profiles or DEFAULT_PROFILES:
        for contact in methods or DEFAULT_METHODS:
            try:
                record = benchmark_effects(contact, profile, level or DEFAULT_LEVEL)
            except envs.errors.EnvConfigError as refused:  # the task's own limit
                print(f"{contact} {profile}: skipped: {refused}")
                continue
            records.append(record)
            _print(record)
            write_records(json_path, "effects", started, records, threads=threading_environment())
    provenance.write(json_path, [_table(records)])
    return records


def _verdict(value: float, met: bool, text: str) -> str:
    return f"{text} ({'met' if met else 'missed'})"


def _table(records: list[dict[str, Any]]) -> MarkdownTable:
    table = MarkdownTable(
        "a ForceScan step's cost [ms, median CPU] by phase, the tissue's share, and what "
        "each effect adds when on [ms]",
        ["contact", "profile", "level (tets)", "free air", "robot only",
         "free air / robot (<= 1.1)", "tissue share free air (<= 5 %)", "contact",
         "tissue share contact", "deformation", "force feedback", "lesion tracking",
         "image"],
    )  # fmt: skip
    for r in records:
        table.rows.append([
            r["contact"], r["profile"], f"{r['level']} ({r['tets']:,})",
            f"{r['free_air_ms']:.2f}", f"{r['robot_only_ms']:.2f}",
            _verdict(r["free_air_ratio"], r["meets_ratio_target"], f"{r['free_air_ratio']:.2f}"),
            _verdict(
                r["free_air_tissue_share"], r["meets_share_target"],
                f"{100 * r['free_air_tissue_share']:.1f} %",
            ),
            f"{r['contact_ms']:.2f}", f"{100 * r['contact_tissue_share']:.0f} %",
            f"{r['deformation_ms']:.2f}", f"{r['force_feedback_ms']:.2f}",
            f"{r['lesion_tracking_ms']:.3f}", f"{r['image_ms']:.2f}",
        ])  # fmt: skip
    return table


def _print(r: dict[str, Any]) -> None:
    print(
        f"{r['contact']:10s} {r['profile']:6s} level {r['level']} ({r['tets']:,} tets): free "
        f"air {r['free_air_ms']:.2f} ms (tissue {100 * r['free_air_tissue_share']:.1f} %, "
        f"asleep {r['free_air_asleep_steps']}/{r['free_air_steps']}), robot only "
        f"{r['robot_only_ms']:.2f} ms (x{r['free_air_ratio']:.2f}), contact "
        f"{r['contact_ms']:.2f} ms (tissue {100 * r['contact_tissue_share']:.0f} %); adds: "
        f"deformation {r['deformation_ms']:.2f}, force feedback {r['force_feedback_ms']:.2f}, "
        f"lesion tracking {r['lesion_tracking_ms']:.3f}, image {r['image_ms']:.2f} ms",
        flush=True,
    )
