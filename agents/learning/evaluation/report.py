"""What an evaluation writes: ``episodes.json`` and ``episodes.csv`` (one record per
episode), ``summary.json`` and ``summary.md`` (the aggregates, the command and the code
revision) and the plots (:mod:`agents.learning.evaluation.plots`)."""

from __future__ import annotations

import csv
import io
import math
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from agents.lab.bench.report import MarkdownTable, code_revision
from agents.learning.evaluation.records import CSV_COLUMNS, OUTPUT_FILES, TIMING_PREFIX
from agents.outputs import readable, write_json

#: The normal quantile of the success rate's two-sided 95 % interval.
Z95 = 1.959963984540054


def wilson_interval(successes: int, trials: int, z: float = Z95) -> tuple[float, float]:
    """The Wilson score interval of a binomial proportion (95 % by default)."""
    if trials < 1:
        return (0.0, 1.0)
    p = successes / trials
    denominator = 1 + z * z / trials
    centre = (p + z * z / (2 * trials)) / denominator
    half = z * math.sqrt(p * (1 - p) / trials + z * z / (4 * trials * trials)) / denominator
    # It contains p; at 0 or all successes rounding could leave p a hair outside.
    return (min(p, max(0.0, centre - half)), max(p, min(1.0, centre + half)))


def _mean(values: list[Any]) -> float | None:
    present = [float(v) for v in values if v is not None]
    return float(np.mean(present)) if present else None


def summarise(
    records: list[dict[str, Any]],
    env_id: str,
    policy: str,
    seed: int,
    env_kwargs: dict[str, Any],
    command: str | None,
) -> dict[str, Any]:
    """The run's aggregates; timings apart under ``timing``."""
    n = len(records)
    successes = sum(1 for record in records if record["success"])
    returns = np.array([record["return"] for record in records], dtype=float)
    ends: dict[str, int] = {}
    for record in records:
        ends[record["end"]] = ends.get(record["end"], 0) + 1

    def column(name: str) -> list[Any]:
        return [record[name] for record in records]

    return {
        "env_id": env_id,
        "policy": policy,
        "episodes": n,
        "seed": seed,
        "seeds": [record["seed"] for record in records],
        "env_kwargs": env_kwargs,
        "command": command,
        "revision": code_revision(),
        "successes": successes,
        "success_rate": successes / n,
        "success_rate_ci95": list(wilson_interval(successes, n)),
        "return_mean": float(returns.mean()),
        "return_std": float(returns.std(ddof=1)) if n > 1 else 0.0,
        "return_min": float(returns.min()),
        "return_max": float(returns.max()),
        "length_mean": float(np.mean(column("length"))),
        "ends": dict(sorted(ends.items())),
        "contact_force_mean_n": float(np.mean(column("contact_force_mean_n"))),
        "contact_force_peak_n": float(np.max(column("contact_force_peak_n"))),
        "normal_force_mean_n": float(np.mean(column("normal_force_mean_n"))),
        "centring_error_mean_m": _mean(column("centring_error_m")),
        "remaining_end_mean_m": _mean(column("remaining_end_m")),
        "good_share_end_mean": _mean(column("good_share_end")),
        "timing": {
            "step_ms_mean": float(np.mean(column("timing_step_ms_mean"))),
            "step_ms_max": float(np.max(column("timing_step_ms_max"))),
            "policy_ms_mean": float(np.mean(column("timing_policy_ms_mean"))),
        },
    }


def write_outputs(
    folder: Path,
    records: list[dict[str, Any]],
    env_id: str,
    policy: str,
    seed: int,
    env_kwargs: dict[str, Any],
    command: str | None,
) -> list[Path]:
    """Write every file into ``folder``; an evaluation file this run does not write (a
    plot another task had) is removed, so the folder never mixes runs. Returns the paths."""
    from agents.learning.evaluation.plots import write_plots

    summary = summarise(records, env_id, policy, seed, env_kwargs, command)
    head = {key: summary[key] for key in ("env_id", "policy", "seed", "env_kwargs")}
    written = [
        write_json({**head, "episodes": records}, folder / "episodes.json", indent=1),
        _write_csv(records, folder / "episodes.csv"),
        write_json(summary, folder / "summary.json", indent=1),
    ]
    written += write_plots(folder, records, summary)
    written.append(_write_text(summary_markdown(summary, written), folder / "summary.md"))
    for name in OUTPUT_FILES:
        if folder / name not in written:
            (folder / name).unlink(missing_ok=True)
    return written


def _write_text(text: str, path: Path) -> Path:
    """Write ``text`` atomically (a reader never sees half a file), readable by all."""
    handle, partial = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    with os.fdopen(handle, "w", newline="") as file:
        file.write(text)
    readable(Path(partial))
    os.replace(partial, path)
    return path


def _cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return repr(value) if math.isfinite(value) else ""
    return str(value)


def _write_csv(records: list[dict[str, Any]], path: Path) -> Path:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(CSV_COLUMNS)
    for record in records:
        writer.writerow([_cell(record[name]) for name in CSV_COLUMNS])
    return _write_text(buffer.getvalue(), path)


def _mm(value: float | None) -> str:
    return "n/a" if value is None else f"{1e3 * value:.2f} mm"


def summary_markdown(summary: dict[str, Any], written: list[Path]) -> str:
    """The summary page: what was run, the figures, the timings apart, the files."""
    n = summary["episodes"]
    low, high = summary["success_rate_ci95"]
    seeds = summary["seeds"]
    kwargs = ", ".join(f"{key}={value!r}" for key, value in summary["env_kwargs"].items())
    env_id = summary["env_id"]
    table = MarkdownTable("Results (deterministic for a seed)", ["figure", "value"])
    table.rows.append(
        [
            "success rate",
            f"{summary['successes']}/{n} = {100 * summary['success_rate']:.0f} % "
            f"(95 % Wilson interval {100 * low:.0f}-{100 * high:.0f} %)",
        ]
    )
    table.rows.append(
        [
            "return",
            f"{summary['return_mean']:.3f} ± {summary['return_std']:.3f} (mean ± sd; "
            f"min {summary['return_min']:.3f}, max {summary['return_max']:.3f})",
        ]
    )
    table.rows.append(["episode length", f"{summary['length_mean']:.1f} steps (mean)"])
    table.rows.append(
        ["episodes ended by", ", ".join(f"{k} {v}" for k, v in summary["ends"].items())]
    )
    table.rows.append(
        [
            "contact force",
            f"mean {summary['contact_force_mean_n']:.3f} N, "
            f"peak {summary['contact_force_peak_n']:.3f} N",
        ]
    )
    table.rows.append(["normal force", f"mean {summary['normal_force_mean_n']:.3f} N"])
    if "/LesionSearch-" in env_id:
        table.rows.append(
            [
                "centring error at the end",
                f"{_mm(summary['centring_error_mean_m'])} (lesion to the image's centre line)",
            ]
        )
    elif "/BreastCompress-" in env_id:
        table.rows.append(
            [
                "centring error at the end",
                f"{_mm(summary['centring_error_mean_m'])} (lesion depth to the target depth)",
            ]
        )
    else:
        share = summary["good_share_end_mean"]
        table.rows.append(["centring error", "n/a (no lesion target)"])
        table.rows.append(["path left at the end", f"{_mm(summary['remaining_end_mean_m'])}"])
        table.rows.append(
            ["good-step share at the end", "n/a" if share is None else f"{share:.3f}"]
        )
    timing = summary["timing"]
    lines = [
        f"# Evaluation: {env_id}, policy {summary['policy']}",
        "",
        f"Written by `{summary['command'] or 'agents.learning.evaluation.evaluate'}` on revision "
        f"`{summary['revision']}`. {n} episode(s), seeds {seeds[0]}-{seeds[-1]} (episode k "
        f"is reset with seed {summary['seed']} + k); `gymnasium.make({env_id!r}"
        f"{', ' + kwargs if kwargs else ''})`. Means are over episodes; per-episode figures "
        "are in `episodes.csv`.",
        "",
        table.text(),
        f"**Timings** (wall clock on this machine, {TIMING_PREFIX}* in the files: they vary "
        "from run to run and are no part of the results above): "
        f"`env.step` {timing['step_ms_mean']:.2f} ms per step (mean; slowest step "
        f"{timing['step_ms_max']:.2f} ms), the policy {timing['policy_ms_mean']:.3f} ms per "
        "step.",
        "",
        "Files: " + ", ".join(f"`{path.name}`" for path in written) + ", `summary.md`.",
        "",
    ]
    return "\n".join(lines)
