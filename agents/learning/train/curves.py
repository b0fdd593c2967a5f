"""Learning curves from ``probegym train`` folders: success rate and mean return of each
evaluation against environment steps, one line per run.

``python -m agents.learning.train.curves RUN [RUN ...] --out curve.png [--title TEXT]``
draws them and prints a table (each run's evaluations); ``--json PATH`` writes the numbers too.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np

from agents.learning.train.artifacts import read_config
from agents.outputs import write_json


def learning_curve(folder: Path) -> dict[str, Any]:
    """One run's evaluations: steps, mean return and success rate (None where not logged)."""
    log = folder / "eval" / "evaluations.npz"
    if not log.is_file():
        raise FileNotFoundError(f"{folder} has no eval/evaluations.npz: not a probegym train run")
    data = np.load(log)
    config = read_config(folder)
    successes = data.get("successes", None)
    return {
        "run": folder.name,
        "seed": config.get("seed"),
        "algo": config.get("algo"),
        "env_id": config.get("env_id"),
        "env_kwargs": config.get("env_kwargs"),
        "steps": [int(v) for v in data["timesteps"]],
        "mean_return": [float(np.mean(r)) for r in data["results"]],
        "success_rate": None if successes is None else [float(np.mean(s)) for s in successes],
        "episodes_per_evaluation": int(np.asarray(data["results"]).shape[1]),
    }


def plot_curves(curves: list[dict[str, Any]], path: Path, title: str) -> Path:
    """Success rate and mean return against steps, one line per run, as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, (success_axis, return_axis) = plt.subplots(1, 2, figsize=(10, 3.8))
    for curve in curves:
        label = str(curve["run"])  # the run's folder name
        steps = np.array(curve["steps"]) / 1e3
        if curve["success_rate"] is not None:
            success_axis.plot(steps, curve["success_rate"], marker="o", ms=3, label=label)
        return_axis.plot(steps, curve["mean_return"], marker="o", ms=3, label=label)
    episodes = curves[0]["episodes_per_evaluation"] if curves else 0
    success_axis.set(
        xlabel="environment steps [thousands]",
        ylabel=f"success rate ({episodes} episodes)",
        ylim=(-0.05, 1.05),
    )
    return_axis.set(xlabel="environment steps [thousands]", ylabel="mean return")
    for axis in (success_axis, return_axis):
        axis.grid(alpha=0.3)
        axis.legend(fontsize=8)
    figure.suptitle(title)
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=110)
    plt.close(figure)
    return path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m agents.learning.train.curves", description=__doc__
    )
    parser.add_argument("runs", nargs="+", type=Path, help="probegym train --out folders")
    parser.add_argument("--out", type=Path, required=True, help="the PNG to write")
    parser.add_argument("--title", default="", help="the figure's title")
    parser.add_argument("--json", type=Path, default=None, help="also write the numbers")
    args = parser.parse_args(argv)
    curves = [learning_curve(run) for run in args.runs]
    for curve in curves:
        print(f"{curve['run']}:")
        rates = curve["success_rate"] or [float("nan")] * len(curve["steps"])
        for steps, value, rate in zip(curve["steps"], curve["mean_return"], rates, strict=True):
            print(f"  {steps:>8,} steps: return {value:8.2f}, success {rate:.2f}")
    plot_curves(curves, args.out, args.title or (curves[0]["env_id"] if curves else ""))
    if args.json is not None:
        write_json({"curves": curves}, args.json, indent=1)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
