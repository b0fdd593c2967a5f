"""Baseline records: trained runs, the scripted and the random policy on held-out episodes.

::

    python -m agents.learning.evaluation.baselines --runs runs/ls1/ppo-lm-seed0 ... \\
        --policies scripted,random --ids probegym/LesionSearch-v1 \\
        --episodes 50 --seed 1000 --json docs/results/baselines.json

One record per trained run (its final model) and per task and chosen policy, with the keys
``env_id``, ``algo`` (None for a hand-written policy), ``policy`` (``ppo``, ``sac``,
``scripted``, ``random``), ``seed`` (the training's; None for a hand-written policy),
``steps`` (environment steps trained), ``heldout_success`` (the share of ``--episodes``
episodes reset with seeds ``--seed`` ... that succeeded; the training used seeds S + i and
its evaluations S + 10,000 + i, so choose seeds far from both), ``heldout_episodes``,
``heldout_interval`` (Wilson, 95 %), ``wall_s`` (the training's wall time up to the model's
steps, evaluations included: the span of each TensorBoard event file in ``tb/``, one per
process that trained it, summed over a run resumed any number of times; without them, the
latest episode end in its ``monitor/`` files, which a resume starts afresh), ``steps_per_s``
(``steps`` over it), ``steps_to_80`` (the first training evaluation, at or before the
model's steps, at 80 % success or more; None if none), ``defaults`` (true when the run added
no keyword argument, pre-training or initial model) and ``command`` (what reproduces the
record). Records already in the JSON for other (env, policy, seed) stay; the same ones are
replaced.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from agents.learning.evaluation.report import wilson_interval
from agents.learning.evaluation.run import evaluate
from agents.learning.train.artifacts import read_config, training_folder
from agents.outputs import write_json

#: The training evaluations' success that ``steps_to_80`` looks for.
TARGET_SUCCESS = 0.8


def run_record(path: Path, episodes: int, seed: int) -> dict[str, Any]:
    """The record of one ``probegym train`` folder (its final model) or of a checkpoint
    ``.zip`` in one (see the module docstring)."""
    folder, model = training_folder(path)
    config = read_config(folder)
    records = _held_out(str(config["env_id"]), model, episodes, seed)
    steps = _checkpoint_steps(model) or trained_steps(folder)
    wall = training_wall_s(folder, steps)
    defaults = _defaults(config)
    return _record(config["env_id"], config["algo"], config["algo"], config["seed"], records) | {
        "steps": steps,
        "wall_s": wall,
        "steps_per_s": steps / wall if steps and wall else None,
        "steps_to_80": _steps_to(folder, TARGET_SUCCESS, steps),
        "defaults": bool(defaults),
        "command": config.get("command"),
        "model": str(model),
    }


def policy_record(env_id: str, policy: str, episodes: int, seed: int) -> dict[str, Any]:
    """The record of a hand-written policy (``scripted`` or ``random``) on ``env_id``."""
    records = _held_out(env_id, policy, episodes, seed)
    return _record(env_id, None, policy, None, records) | {
        "steps": 0,
        "wall_s": None,
        "steps_per_s": None,
        "steps_to_80": None,
        "defaults": True,
        "command": f"probegym evaluate {env_id} --policy {policy} --episodes {episodes} "
        f"--seed {seed}",
    }


def _held_out(env_id: str, policy: Any, episodes: int, seed: int) -> list[dict[str, Any]]:
    with tempfile.TemporaryDirectory(prefix="probegym-baselines-") as out:
        return evaluate(env_id, policy, episodes, seed, {}, Path(out))


def _record(
    env_id: str, algo: str | None, policy: str, seed: int | None, records: list[dict[str, Any]]
) -> dict[str, Any]:
    successes = sum(bool(r["success"]) for r in records)
    low, high = wilson_interval(successes, len(records))
    return {
        "env_id": env_id,
        "algo": algo,
        "policy": policy,
        "seed": seed,
        "heldout_success": successes / len(records),
        "heldout_successes": successes,
        "heldout_episodes": len(records),
        "heldout_interval": [low, high],
        "heldout_seeds": [int(records[0]["seed"]), int(records[-1]["seed"])],
    }


#: The environment arguments ``probegym train`` passes when none are given.
DEFAULT_ENV_KWARGS = {"contact": "lm", "mesh": 1363, "profile": "robust"}


def _defaults(config: dict[str, Any]) -> bool:
    """Whether a run used the defaults only: the environment's default arguments, no
    hyper-parameter, pre-training or initial model of its own, normalisation on."""
    settings = config.get("settings") or {}
    env_kwargs = config.get("env_kwargs") or {}
    return (
        all(env_kwargs.get(key, value) == value for key, value in DEFAULT_ENV_KWARGS.items())
        and set(env_kwargs) <= set(DEFAULT_ENV_KWARGS)
        and not settings.get("hyperparameters")
        and not config.get("init_from")
        and not config.get("pretrain_episodes")
        and bool(config.get("normalize", True))
    )


def _checkpoint_steps(model: Path) -> int | None:
    """A checkpoint's steps from its name (``model_<steps>_steps.zip``); None otherwise."""
    parts = model.stem.split("_")
    if len(parts) == 3 and parts[0] == "model" and parts[2] == "steps" and parts[1].isdigit():
        return int(parts[1])
    return None


def trained_steps(folder: Path) -> int:
    """The steps of a ``probegym train`` folder's latest checkpoint (0 without any)."""
    steps = [
        int(path.stem.split("_")[-2]) for path in (folder / "checkpoints").glob("model_*_steps.zip")
    ]
    return max(steps, default=0)


def training_wall_s(folder: Path, steps: int) -> float | None:
    """A training run's wall time up to ``steps`` [s]: the spans of its TensorBoard event
    files (every process that trained it, resumptions included), else its monitor files'
    latest episode end; None without either."""
    return _tensorboard_wall_s(folder, steps) or _wall_s(folder)


def _tensorboard_wall_s(folder: Path, steps: int) -> float | None:
    """The summed span [s] of the run's TensorBoard event files (one per process that
    trained it), each up to its last event at or before ``steps``; None without any."""
    try:
        from tensorboard.backend.event_processing.event_file_loader import EventFileLoader
    except ImportError:  # the rl extra's; the monitor files then give the time
        return None
    total, found = 0.0, False
    for path in sorted((folder / "tb").rglob("events.out.tfevents.*")):
        times = [e.wall_time for e in EventFileLoader(str(path)).Load() if e.step <= steps]
        if len(times) > 1:
            total += max(times) - min(times)
            found = True
    return total if found else None


def _wall_s(folder: Path) -> float | None:
    """The latest episode end [s after the monitor's start] over the run's monitor files."""
    ends = []
    for path in (folder / "monitor").glob("*.monitor.csv"):
        lines = path.read_text().splitlines()[2:]
        if lines:
            ends.append(max(float(line.split(",")[2]) for line in lines if line))
    return max(ends) if ends else None


def _steps_to(folder: Path, target: float, up_to: int | None = None) -> int | None:
    log = folder / "eval" / "evaluations.npz"
    if not log.is_file():
        return None
    data = np.load(log)
    if "successes" not in data:
        return None
    for steps, successes in zip(data["timesteps"], data["successes"], strict=True):
        if up_to is not None and steps > up_to:
            break
        if float(np.mean(successes)) >= target:
            return int(steps)
    return None


def merge(path: Path, new: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The records in ``path`` (if any) with ``new`` replacing those of the same env,
    policy and seed."""
    old: list[dict[str, Any]] = []
    if path.is_file():
        old = json.loads(path.read_text())["records"]
    keys = {(r["env_id"], r["policy"], r["seed"]) for r in new}
    kept = [r for r in old if (r["env_id"], r["policy"], r["seed"]) not in keys]
    return kept + new


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m agents.learning.evaluation.baselines")
    parser.add_argument(
        "--runs", nargs="*", type=Path, default=[], help="probegym train folders or checkpoints"
    )
    parser.add_argument("--ids", default="", help="comma-separated env ids for --policies")
    parser.add_argument("--policies", default="", help="comma-separated: scripted, random")
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--seed", type=int, default=1000, help="the first held-out seed")
    parser.add_argument("--json", type=Path, default=Path("docs/results/baselines.json"))
    parser.add_argument(
        "--markdown", type=Path, default=None, help="also write the JSON's table here"
    )
    args = parser.parse_args(argv)
    if args.episodes < 1 or args.seed < 0:
        parser.error(f"--episodes must be >= 1 and --seed >= 0; got {args.episodes}, {args.seed}")
    policies = [p for p in args.policies.split(",") if p]
    for policy in policies:
        if policy not in ("scripted", "random"):
            parser.error(f"--policies takes scripted and random; got {policy!r}")
    records: list[dict[str, Any]] = []

    def save(record: dict[str, Any]) -> None:
        """Print a record and write the JSON with it at once (nothing computed is lost)."""
        records.append(record)
        _print(record)
        merged = merge(args.json, records)
        write_json({"records": merged}, args.json, indent=1)
        if args.markdown is not None:
            args.markdown.write_text(table(merged))

    for folder in args.runs:
        save(run_record(folder, args.episodes, args.seed))
    for env_id in (i for i in args.ids.split(",") if i):
        for policy in policies:
            save(policy_record(env_id, policy, args.episodes, args.seed))
    return 0


def table(records: list[dict[str, Any]]) -> str:
    """The records as a Markdown table, by task, then policy, then seed."""
    lines = [
        "| env | policy | seed | defaults | steps | steps to 80 % (training evaluations) "
        "| held-out success (95 % Wilson) | wall time | steps/s |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    order = {"ppo": 0, "sac": 1, "scripted": 2, "random": 3}
    for r in sorted(
        records, key=lambda r: (r["env_id"], order.get(r["policy"], 9), r["seed"] or 0)
    ):
        low, high = r["heldout_interval"]
        wall = r.get("wall_s")
        rate = r.get("steps_per_s")
        to_80 = r.get("steps_to_80")
        lines.append(
            f"| {r['env_id']} | {r['policy']} | {'-' if r['seed'] is None else r['seed']} "
            f"| {'yes' if r['defaults'] else 'no'} | {r['steps']:,} "
            f"| {'-' if to_80 is None else f'{to_80:,}'} "
            f"| {r['heldout_successes']}/{r['heldout_episodes']} ({low:.0%}-{high:.0%}) "
            f"| {'-' if wall is None else f'{wall / 60:.0f} min'} "
            f"| {'-' if rate is None else f'{rate:.0f}'} |"
        )
    return "\n".join(lines) + "\n"


def _print(record: dict[str, Any]) -> None:
    low, high = record["heldout_interval"]
    print(
        f"{record['env_id']} {record['policy']} seed {record['seed']}: "
        f"{record['heldout_successes']}/{record['heldout_episodes']} held out "
        f"({low:.0%}-{high:.0%}), {record['steps']:,} steps",
        flush=True,
    )


if __name__ == "__main__":
    raise SystemExit(main())
