"""``probegym bench sweep``: each contact method's force along one sliding sweep, against LM.

For each seed, the scripted ForceScan policy
(:class:`agents.learning.policies.ForceScanPolicy`) sweeps its path on
``probegym/ForceScan-v0`` with Lagrange-multiplier contact (exact, frictionless);
its actions are then replayed, open loop, with every other method on the same path (same seed,
mesh and profile), so that each method sees the same probe commands. Per method and seed:

- ``rms_error_n`` / ``max_error_n``: the normal force's RMS and largest difference from LM's
  over the steps both ran (a replay ends where its own episode ends: success, failure);
- ``max_skin_penetration_mm``: the deepest skin penetration into the probe over the sweep,
  as each method's step reports it (LM keeps the skin's contact points out exactly; penalty's
  springs, prescribed displacement's skin between its held nodes and PBD's projection leave
  some);
- ``tissue_ms``: the median tissue step time (with its wrench stiffness);
- ``success``: whether the replay's own episode succeeded.

What it answers: how much each cheaper method's force differs from the exact one while the
probe slides, and what that saving buys in time.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from agents.lab.bench.report import BenchRecord, MarkdownTable, write_records

ENV_ID = "probegym/ForceScan-v0"
DEFAULT_SEEDS = (0, 1, 2, 3, 4)
DEFAULT_METHODS = ("penalty", "prescribed", "pbd")
REFERENCE = "lm"


def _episode(
    contact: str, mesh: int, profile: str, seed: int, actions: list[np.ndarray] | None
) -> dict[str, Any]:
    """One episode: the scripted policy's (``actions`` None) or a replay of ``actions``."""
    import gymnasium as gym

    import envs  # noqa: F401 - registers the ids
    from agents.learning.policies import ForceScanPolicy
    from envs.probe_env import ProbeEnv

    env = gym.make(ENV_ID, contact=contact, mesh=mesh, profile=profile)
    unwrapped = env.unwrapped
    assert isinstance(unwrapped, ProbeEnv)
    observation, _ = env.reset(seed=seed)
    policy = ForceScanPolicy()
    policy.reset()
    taken: list[np.ndarray] = []
    forces, penetrations, tissue_s = [], [], []
    info: dict[str, Any] = {}
    limit = len(actions) if actions is not None else 10_000
    for k in range(limit):
        action = policy(observation) if actions is None else actions[k]
        taken.append(np.asarray(action, dtype=np.float32))
        observation, _, terminated, truncated, info = env.step(action)
        forces.append(float(info["normal_force_n"]))
        penetrations.append(float(info["tissue"]["skin_penetration_m"]))
        tissue_s.append(unwrapped.last_timing["tissue_s"])
        if terminated or truncated:
            break
    env.close()
    return {
        "actions": taken,
        "forces": np.array(forces),
        "penetration_m": float(max(penetrations, default=0.0)),
        "tissue_ms": float(np.median(tissue_s)) * 1e3,
        "success": bool(info.get("is_success", False)),
        "steps": len(forces),
    }


def run_sweep_benchmark(
    seeds: list[int] | None,
    methods: list[str] | None,
    mesh: int,
    profile: str,
    json_path: Path,
    command: str | None = None,
) -> list[dict[str, Any]]:
    """Every seed and method against LM; prints a table and writes the JSON as it goes."""
    provenance = BenchRecord("probegym bench sweep: the force along a sweep, against LM", command)
    started = time.strftime("%Y-%m-%dT%H:%M:%S")
    records: list[dict[str, Any]] = []
    for seed in seeds or DEFAULT_SEEDS:
        reference = _episode(REFERENCE, mesh, profile, seed, None)
        records.append(_record(REFERENCE, seed, reference, reference))
        _print(records[-1])
        for contact in methods or DEFAULT_METHODS:
            replay = _episode(contact, mesh, profile, seed, reference["actions"])
            records.append(_record(contact, seed, replay, reference))
            _print(records[-1])
            _write(json_path, records, started, mesh, profile)
    _write(json_path, records, started, mesh, profile)
    provenance.write(json_path, [_table(records)])
    return records


def _record(
    contact: str, seed: int, run: dict[str, Any], reference: dict[str, Any]
) -> dict[str, Any]:
    both = min(run["steps"], reference["steps"])
    error = run["forces"][:both] - reference["forces"][:both]
    return {
        "contact": contact,
        "seed": seed,
        "steps": run["steps"],
        "steps_compared": both,
        "rms_error_n": float(np.sqrt(np.mean(error**2))) if both else float("nan"),
        "max_error_n": float(np.max(np.abs(error))) if both else float("nan"),
        "mean_force_n": float(np.mean(run["forces"])) if run["steps"] else 0.0,
        "max_skin_penetration_mm": run["penetration_m"] * 1e3,
        "tissue_ms": run["tissue_ms"],
        "success": run["success"],
    }


def _table(records: list[dict[str, Any]]) -> MarkdownTable:
    """One row per method: medians and ranges over the seeds."""
    table = MarkdownTable(
        "normal force against LM along the replayed sweep (median over seeds, [min, max])",
        ["contact", "seeds", "RMS error (N)", "largest error (N)", "skin penetration (mm)",
         "tissue step (ms)", "replays that succeed"],
    )  # fmt: skip
    order = [REFERENCE] + [c for c in dict.fromkeys(r["contact"] for r in records) if c != "lm"]
    for contact in order:
        rows = [r for r in records if r["contact"] == contact]
        if not rows:
            continue

        def spread(key: str, scale: float = 1.0, rows: list[dict[str, Any]] = rows) -> str:
            values = np.array([r[key] for r in rows]) * scale
            return f"{np.median(values):.3f} [{values.min():.3f}, {values.max():.3f}]"

        table.rows.append([
            contact, str(len(rows)), spread("rms_error_n"), spread("max_error_n"),
            spread("max_skin_penetration_mm"), f"{np.median([r['tissue_ms'] for r in rows]):.2f}",
            f"{sum(r['success'] for r in rows)} / {len(rows)}",
        ])  # fmt: skip
    return table


def _print(record: dict[str, Any]) -> None:
    print(
        f"seed {record['seed']} {record['contact']:10s}: {record['steps']} steps "
        f"({record['steps_compared']} compared), force error RMS {record['rms_error_n']:.3f} N, "
        f"max {record['max_error_n']:.3f} N, skin penetration "
        f"{record['max_skin_penetration_mm']:.3f} mm, tissue {record['tissue_ms']:.2f} ms, "
        f"success {record['success']}",
        flush=True,
    )


def _write(
    path: Path, records: list[dict[str, Any]], started: str, mesh: int, profile: str
) -> None:
    write_records(path, "sweep", started, records, mesh=mesh, profile=profile)
