"""A transfer study's outputs: the records as JSON and CSV, per task the success matrix
(training configuration x evaluation configuration) as a heat map, success on the reference
against training wall time (the learning counterpart of the study's accuracy against time),
and a report that states its conclusions."""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

import numpy as np

from agents.learning.evaluation.report import wilson_interval
from agents.learning.transfer.spec import TransferSpec, short_name
from agents.outputs import write_json

#: A cell "breaks" where its success falls this far below the policy's own configuration's
#: and the drop is significant (below).
BREAK_DROP = 0.2
#: Fisher's exact test (one-sided: fewer successes than on the policy's own configuration)
#: at this level: with 20 episodes a cell, 75 % against 50 % is not told from chance
#: (p = 0.10), 95 % against 60 % is (p = 0.01). The test treats the two cells' episodes as
#: independent samples; they share their seeds, so it is conservative.
BREAK_P = 0.05
#: The best buy: the cheapest training whose reference success is within this of the best.
BEST_BUY_MARGIN = 0.1

CSV_COLUMNS = (
    "env_id", "algo", "train", "seed", "steps", "train_wall_s", "evaluate", "reference",
    "episodes", "successes", "success_rate", "success_low", "success_high",
    "contact_force_mean_n", "lesion_error_mean_m",
)  # fmt: skip


def write_report(
    spec: TransferSpec, records: list[dict[str, Any]], out: Path, command: str | None
) -> list[Path]:
    """Write ``transfer.json``, ``transfer.csv``, per task ``<Task>-matrix.png`` and
    ``<Task>-pareto.png``, and ``report.md`` into ``out``; returns the paths."""
    out = Path(out)
    written = [
        write_json({"command": command, "records": records}, out / "transfer.json"),
        _write_csv(records, out / "transfer.csv"),
    ]
    sections = []
    for env_id in spec.env_ids:
        mine = [r for r in records if r["env_id"] == env_id]
        if not mine:
            continue
        matrix = success_matrix(spec, mine)
        written.append(_matrix_figure(env_id, matrix, out / f"{short_name(env_id)}-matrix.png"))
        points = reference_points(spec, mine)
        written.append(
            _pareto_figure(env_id, points, spec, out / f"{short_name(env_id)}-pareto.png")
        )
        sections.append(_section(spec, env_id, matrix, points, mine))
    report = out / "report.md"
    report.write_text(_report(spec, sections, command))
    written.append(report)
    return written


def success_matrix(spec: TransferSpec, records: list[dict[str, Any]]) -> dict[str, Any]:
    """Rows: training configurations; columns: evaluation configurations. ``values``: each
    cell's success over every seed's held-out episodes (successes / episodes), NaN where not
    evaluated; ``successes`` and ``episodes``: the counts behind it (0 where not evaluated);
    all of shape (rows, columns)."""
    rows = [c.label for c in spec.train]
    columns = [c.label for c in spec.evaluate]
    successes = np.zeros((len(rows), len(columns)), dtype=int)
    episodes = np.zeros((len(rows), len(columns)), dtype=int)
    for i, row in enumerate(rows):
        for j, column in enumerate(columns):
            cells = [r for r in records if r["train"] == row and r["evaluate"] == column]
            successes[i, j] = sum(r["successes"] for r in cells)
            episodes[i, j] = sum(r["episodes"] for r in cells)
    with np.errstate(invalid="ignore", divide="ignore"):
        values = np.where(episodes > 0, successes / np.maximum(episodes, 1), np.nan)
    return {
        "rows": rows, "columns": columns, "values": values,
        "successes": successes, "episodes": episodes,
    }  # fmt: skip


def reference_points(spec: TransferSpec, records: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per training configuration: its mean training wall time [s] over seeds, its success
    on the reference and on its own configuration (None where not evaluated), and whether
    it lies on the Pareto front (no other trains faster and succeeds at least as often)."""
    points = []
    for config in spec.train:
        on_reference = [
            r
            for r in records
            if r["train"] == config.label and r["evaluate"] == spec.reference.label
        ]
        own = [r for r in records if r["train"] == config.label and r["evaluate"] == config.label]
        walls = [r["train_wall_s"] for r in on_reference if r.get("train_wall_s") is not None]
        if not on_reference:
            continue
        points.append(
            {
                "train": config.label,
                "wall_s": float(np.mean(walls)) if walls else None,
                "reference_success": sum(r["successes"] for r in on_reference)
                / sum(r["episodes"] for r in on_reference),
                "own_success": (
                    sum(r["successes"] for r in own) / sum(r["episodes"] for r in own)
                    if own
                    else None
                ),
            }
        )
    for point in points:
        point["pareto"] = point["wall_s"] is not None and not any(
            other is not point
            and other["wall_s"] is not None
            and other["wall_s"] <= point["wall_s"]
            and other["reference_success"] >= point["reference_success"]
            and (other["wall_s"], -other["reference_success"])
            != (point["wall_s"], -point["reference_success"])
            for other in points
        )
    return points


def conclusions(
    spec: TransferSpec, matrix: dict[str, Any], points: list[dict[str, Any]]
) -> list[str]:
    """The section's findings, in words: the best buy, where transfer breaks (a drop of
    more than ``BREAK_DROP`` that Fisher's exact test tells from chance at ``BREAK_P``), the
    drops that the episodes cannot tell from chance, and what was not learned."""
    from scipy.stats import fisher_exact

    found = []
    timed = [p for p in points if p["wall_s"] is not None]
    if timed:
        best = max(p["reference_success"] for p in timed)
        good = [p for p in timed if p["reference_success"] >= best - BEST_BUY_MARGIN]
        buy = min(good, key=lambda p: p["wall_s"])
        column = matrix["columns"].index(spec.reference.label)
        row = matrix["rows"].index(buy["train"])
        low, high = wilson_interval(
            int(matrix["successes"][row, column]), int(matrix["episodes"][row, column])
        )
        found.append(
            f"Best buy: training on {buy['train']} ({buy['wall_s'] / 60:.1f} min) succeeds in "
            f"{100 * buy['reference_success']:.0f} % of the reference's ({spec.reference.label}) "
            f"episodes (95 % interval {100 * low:.0f}-{100 * high:.0f} %), within "
            f"{100 * BEST_BUY_MARGIN:.0f} points of the best training configuration's "
            f"{100 * best:.0f} %."
        )
    breaks: list[str] = []
    unclear: list[str] = []
    rows, columns, values = matrix["rows"], matrix["columns"], matrix["values"]
    wins, tries = matrix["successes"], matrix["episodes"]
    for i, row in enumerate(rows):
        if row not in columns:
            continue
        o = columns.index(row)
        own = values[i, o]
        for j, column in enumerate(columns):
            if not (np.isfinite(own) and np.isfinite(values[i, j])):
                continue
            if values[i, j] < own - BREAK_DROP:
                table = [
                    [int(wins[i, o]), int(tries[i, o] - wins[i, o])],
                    [int(wins[i, j]), int(tries[i, j] - wins[i, j])],
                ]
                p = float(fisher_exact(table, alternative="greater").pvalue)
                words = (
                    f"{row} on {column} ({100 * values[i, j]:.0f} % against {100 * own:.0f} %, "
                    f"p = {p:.2f})"
                )
                (breaks if p < BREAK_P else unclear).append(words)
    if breaks:
        found.append(
            f"Transfer breaks (success more than {100 * BREAK_DROP:.0f} points under the policy's "
            f"own configuration's, Fisher's exact test p < {BREAK_P}) for: {'; '.join(breaks)}."
        )
    else:
        found.append(
            f"Transfer holds: no policy loses significantly more than {100 * BREAK_DROP:.0f} "
            "points of success between its own configuration and any other evaluated."
        )
    if unclear:
        found.append(
            f"Drops of more than {100 * BREAK_DROP:.0f} points that these episodes cannot tell "
            f"from chance (p >= {BREAK_P}; more episodes or seeds would): {'; '.join(unclear)}."
        )
    failing = [
        p["train"] for p in points if p["own_success"] is not None and p["own_success"] < 0.5
    ]
    if failing:
        found.append(
            f"Not learned within the budget on its own configuration (under 50 %): "
            f"{', '.join(failing)}; their transfer says little."
        )
    return found


def _section(
    spec: TransferSpec,
    env_id: str,
    matrix: dict[str, Any],
    points: list[dict[str, Any]],
    records: list[dict[str, Any]],
) -> str:
    name = short_name(env_id)
    lines = [
        f"## {env_id}",
        "",
        f"![success matrix]({name}-matrix.png)",
        "",
        f"![success on the reference against training time]({name}-pareto.png)",
        "",
    ]
    header = (
        "| trained on \\ evaluated on | " + " | ".join(matrix["columns"]) + " | training [min] |"
    )
    lines += [header, "|" + " --- |" * (len(matrix["columns"]) + 2)]
    walls = {p["train"]: p["wall_s"] for p in points}
    for i, row in enumerate(matrix["rows"]):
        cells = ["" if not np.isfinite(v) else f"{100 * v:.0f} %" for v in matrix["values"][i]]
        wall = walls.get(row)
        lines.append(
            f"| {row} | " + " | ".join(cells) + f" | {'' if wall is None else f'{wall / 60:.1f}'} |"
        )
    episodes = sorted({r["episodes"] for r in records})
    seeds = sorted({r["seed"] for r in records})
    budget = f"{spec.steps[env_id]:,} training steps a run"
    lines += [
        "",
        f"Held-out episodes per cell: {', '.join(map(str, episodes))}; seeds: "
        f"{', '.join(map(str, seeds))}; {budget}.",
        "",
    ]
    lines += [f"- {finding}" for finding in conclusions(spec, matrix, points)]
    return "\n".join(lines) + "\n"


def _report(spec: TransferSpec, sections: list[str], command: str | None) -> str:
    head = [
        "# What accuracy costs in learning: the transfer study",
        "",
        "Each policy is trained with "
        f"{spec.algo.upper()} on one contact method and mesh (robust profile) and evaluated, "
        "deterministically, on held-out episodes (seeds never used in training) on every "
        f"configuration and on the reference, {spec.reference.label}. Success rates pool the "
        "seeds; training time is the run's wall time, evaluations during training included.",
        "",
        f"Command: `{command or 'probegym study --transfer'}`",
        "",
    ]
    return "\n".join(head) + "\n" + "\n".join(sections)


def _write_csv(records: list[dict[str, Any]], path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(CSV_COLUMNS)
        for r in records:
            low, high = r["success_interval"]
            row = {**r, "success_low": low, "success_high": high}
            writer.writerow(["" if row.get(c) is None else row[c] for c in CSV_COLUMNS])
    return path


def _matrix_figure(env_id: str, matrix: dict[str, Any], path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows, columns, values = matrix["rows"], matrix["columns"], matrix["values"]
    fig, ax = plt.subplots(figsize=(1.1 * len(columns) + 2.5, 0.55 * len(rows) + 1.8))
    image = ax.imshow(np.ma.masked_invalid(values), vmin=0.0, vmax=1.0, cmap="viridis")
    ax.set_xticks(range(len(columns)), columns, rotation=45, ha="right")
    ax.set_yticks(range(len(rows)), rows)
    ax.set_xlabel("evaluated on")
    ax.set_ylabel("trained on")
    for i in range(len(rows)):
        for j in range(len(columns)):
            if np.isfinite(values[i, j]):
                ax.text(j, i, f"{100 * values[i, j]:.0f}", ha="center", va="center",
                        color="white" if values[i, j] < 0.6 else "black", fontsize=8)  # fmt: skip
    fig.colorbar(image, ax=ax, label="held-out success")
    ax.set_title(f"{short_name(env_id)}: success, trained on x evaluated on")
    fig.tight_layout()
    fig.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(fig)
    return path


def _pareto_figure(
    env_id: str, points: list[dict[str, Any]], spec: TransferSpec, path: Path
) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.0, 4.2))
    timed = [p for p in points if p["wall_s"] is not None]
    for point in timed:
        ax.scatter(point["wall_s"] / 60, 100 * point["reference_success"],
                   color="C3" if point["pareto"] else "C0")  # fmt: skip
        ax.annotate(point["train"], (point["wall_s"] / 60, 100 * point["reference_success"]),
                    textcoords="offset points", xytext=(4, 4), fontsize=8)  # fmt: skip
    front = sorted((p for p in timed if p["pareto"]), key=lambda p: p["wall_s"])
    if len(front) > 1:
        ax.step([p["wall_s"] / 60 for p in front], [100 * p["reference_success"] for p in front],
                where="post", color="C3", label="Pareto front")  # fmt: skip
        ax.legend(loc="lower right")
    ax.set_xlabel("training wall time [min]")
    ax.set_ylabel(f"success on {spec.reference.label} [%]")
    ax.set_ylim(-5, 105)
    ax.set_title(f"{short_name(env_id)}: what accuracy costs in learning")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
