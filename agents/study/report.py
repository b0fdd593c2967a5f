"""The study's tables, figures and report, written from ``results.jsonl``.

- ``stability.md``: the paper's Table 1 -- mean, median and range of the stability metric
  per method and level -- one column group per configuration.
- ``errors.png``: the paper's Fig. 2 -- localisation errors (eq. 12) per method and level;
  as the paper, only depths that every method of the configuration simulated stably count,
  so a method that survives longer is not judged on more (harder) depths.
- ``times.png``: the paper's Fig. 3 -- compute time per step (each cell's median), log
  scale, lines at h = 20 ms (real time) and 40 ms (25 fps).
- ``accuracy_vs_time.png``: median error against median time per step, one point per
  method x level x configuration, the Pareto front (no other point both faster and more
  accurate) marked among the points whose cells all completed: a point whose cells broke
  off is drawn hollow and is not an option on the front (its error counts only the depths
  it reached).
- ``report.md`` and ``report.html``: all of it with the run's configuration and machine.

PBD has both configurations too: ``paper`` is the 10-substep, FleX-like baseline, ``robust``
runs 60 substeps (:meth:`tissue.pbd.PBDConfig.for_mode`).
"""

from __future__ import annotations

import html
import json
import os
import platform
from collections import Counter, defaultdict
from pathlib import Path
from typing import Any

import numpy as np

from agents.compress import SETTLED_SPEED_M_S
from agents.outputs import strict_json
from agents.study.spec import StudySpec, level_label

METHOD_ORDER = ("lm", "penalty", "prescribed", "pbd")
METHOD_LABEL = {"lm": "LM", "penalty": "Penalty", "prescribed": "PrescrDispl", "pbd": "PBD"}
METHOD_COLOUR = {"lm": "tab:blue", "penalty": "tab:orange", "prescribed": "tab:green",
                 "pbd": "tab:red"}  # fmt: skip


def _by_config(records: list[dict[str, Any]], configs: list[str]) -> dict[str, list[dict]]:
    """Records per configuration column group."""
    groups: dict[str, list[dict[str, Any]]] = {config: [] for config in configs}
    for record in records:
        if record["config"] in groups:
            groups[record["config"]].append(record)
    return groups


def _methods(records: list[dict[str, Any]]) -> list[str]:
    present = {record["method"] for record in records}
    return [m for m in METHOD_ORDER if m in present]


def _levels(records: list[dict[str, Any]]) -> list[int]:
    return sorted({record["level"] for record in records}, key=lambda v: (v != 0, v))


def _tets(records: list[dict[str, Any]], level: int) -> int:
    return next(record["tets"] for record in records if record["level"] == level)


# ---------------------------------------------------------------------- stability


#: Tagliabue et al. 2020, Table 1: mean (median, range) of the stability metric [%] per
#: volume-mesh level, for the methods of :data:`PAPER_TABLE1_METHODS` (PBD was not in it).
PAPER_TABLE1_METHODS = ("lm", "penalty", "prescribed")
PAPER_TABLE1: dict[int, tuple[str, str, str]] = {
    623: ("100 (100, 93-100)", "100 (100, 100-100)", "100 (100, 100-100)"),
    1363: ("100 (100, 88-100)", "100 (100, 90-100)", "100 (100, 100-100)"),
    2539: ("97 (100, 64-100)", "100 (100, 100-100)", "100 (100, 100-100)"),
    4126: ("99 (100, 84-100)", "100 (100, 100-100)", "100 (100, 100-100)"),
    7369: ("99 (100, 75-100)", "100 (100, 92-100)", "100 (100, 100-100)"),
    12861: ("98 (100, 72-100)", "93 (100, 59-100)", "100 (100, 100-100)"),
    26220: ("96 (100, 60-100)", "72 (71, 42-100)", "100 (100, 100-100)"),
    105004: ("88 (92, 56-100)", "87 (100, 52-100)", "100 (100, 94-100)"),
    176506: ("69 (70, 49-88)", "53 (48, 25-100)", "98 (100, 80-100)"),
}


def level_and_tets(level: int, tets: int) -> str:
    """How a level is named wherever one is shown: ``level 4126 (4,141 tets)``; the paper's
    level names are its tet counts, our meshes' own counts differ a little."""
    return f"level {level_label(level)} ({tets:,} tets)"


def stability_table(records: list[dict[str, Any]], configs: list[str]) -> str:
    """Table 1 in Markdown, one table per profile: per level, each method's mean stability
    [%] with its median and range; beside the paper profile, Tagliabue et al.'s Table 1."""
    groups = _by_config(records, configs)
    methods = _methods(records)
    lesion_count = len({r["lesion"] for r in records})
    tables = []
    for config in configs:
        paper = config == "paper" and any(level in PAPER_TABLE1 for level in _levels(records))
        head = ["level (tets)", *(METHOD_LABEL[m] for m in methods)]
        if paper:
            head += [f"2020 {METHOD_LABEL[m]}" for m in methods if m in PAPER_TABLE1_METHODS]
        lines = [
            f"**{config} profile**: mean (median, range) of the % of the experiment completed"
            + (" (right: Tagliabue et al. 2020, Table 1)" if paper else ""),
            "",
            "| " + " | ".join(head) + " |",
            "|" + "---|" * len(head),
        ]
        for level in _levels(records):
            row = [level_and_tets(level, _tets(records, level))]
            for method in methods:
                values = [
                    r["stability_percent"]
                    for r in groups[config]
                    if r["level"] == level and r["method"] == method
                ]
                fewer = f", n={len(values)}" if 0 < len(values) < lesion_count else ""
                row.append(
                    f"{np.mean(values):.0f} ({np.median(values):.0f}, "
                    f"{np.min(values):.0f}-{np.max(values):.0f}{fewer})"
                    if values
                    else ""
                )
            if paper:
                published = PAPER_TABLE1.get(level)
                for method in methods:
                    if method in PAPER_TABLE1_METHODS:
                        index = PAPER_TABLE1_METHODS.index(method)
                        row.append("" if published is None else published[index])
            lines.append("| " + " | ".join(row) + " |")
        tables.append("\n".join(lines))
    return "\n\n".join(tables) + "\n"


# ---------------------------------------------------------------------- errors


def valid_errors(
    records: list[dict[str, Any]], configs: list[str]
) -> dict[str, dict[tuple[str, int], list[float]]]:
    """Per profile, errors [m] per (method, level) on the depths every method of every
    profile reached.

    A depth of a (level, lesion) counts only if every (profile, method) that reached a depth
    there has an error at it (the paper's "valid" deformations, taken across profiles). So
    both profiles are scored on the same depths: a cell that broke off early would otherwise
    be scored on the shallow, easier depths it reached and look more accurate than one that
    went on (the paper profile's cells against the robust one's). A method that failed
    before its first depth drops out of that case (its stability records the failure) rather
    than taking every other method's errors with it: in the paper profile prescribed
    displacement fails by penetration before 10 mm on most lesions from 4,126 tets up.
    """
    wanted = set(configs)
    by_case: dict[tuple[int, ...], dict[tuple[str, str], list[float | None]]] = defaultdict(dict)
    for record in records:
        if record["config"] in wanted:
            key = (record["config"], record["method"])
            lesion_case: tuple[int, ...] = (record["level"], record["lesion"])
            by_case[lesion_case][key] = record.get("errors_m", [])
    expected = {(r["config"], r["method"]) for r in records if r["config"] in wanted}
    out: dict[str, dict[tuple[str, int], list[float]]] = {c: defaultdict(list) for c in configs}
    for lesion_case, per_run in by_case.items():
        level = lesion_case[0]
        if set(per_run) != expected:
            continue
        reached = [key for key in sorted(per_run) if per_run[key]]
        if not reached:
            continue
        depth_count = min(len(per_run[key]) for key in reached)
        for index in range(depth_count):
            row = [per_run[key][index] for key in reached]
            if any(value is None for value in row):
                continue
            for (config, method), value in zip(reached, row, strict=True):
                assert value is not None
                out[config][(method, level)].append(value)
    return {config: dict(errors) for config, errors in out.items()}


def _median_times(
    records: list[dict[str, Any]], configs: list[str]
) -> dict[str, dict[tuple[str, int], list[float]]]:
    out: dict[str, dict[tuple[str, int], list[float]]] = {}
    for config, group in _by_config(records, configs).items():
        times: dict[tuple[str, int], list[float]] = defaultdict(list)
        for record in group:
            if record["step_ms"].get("count", 0):
                times[(record["method"], record["level"])].append(record["step_ms"]["median"])
        out[config] = dict(times)
    return out


def summary_rows(records: list[dict[str, Any]], configs: list[str]) -> list[dict[str, Any]]:
    """One row per configuration x method x level: median error [mm], median step [ms],
    mean stability [%], cell count."""
    errors = valid_errors(records, configs)
    times = _median_times(records, configs)
    groups = _by_config(records, configs)
    rows = []
    for config in configs:
        for method in _methods(groups[config]):
            for level in _levels(groups[config]):
                cells = [r for r in groups[config] if r["method"] == method and r["level"] == level]
                if not cells:
                    continue
                error = errors[config].get((method, level), [])
                time = times[config].get((method, level), [])
                rows.append(
                    {
                        "config": config,
                        "method": method,
                        "level": level,
                        "tets": cells[0]["tets"],
                        "cells": len(cells),
                        "median_error_mm": float(np.median(error) * 1e3) if error else None,
                        "median_step_ms": float(np.median(time)) if time else None,
                        "mean_stability_percent": float(
                            np.mean([c["stability_percent"] for c in cells])
                        ),
                    }
                )
    return rows


def pareto_front(points: list[tuple[float, float]]) -> list[int]:
    """Indices of the points (time, error) that no other point beats in both (ties kept)."""
    front = []
    for i, (time_i, error_i) in enumerate(points):
        dominated = any(
            time_j <= time_i and error_j <= error_i and (time_j < time_i or error_j < error_i)
            for j, (time_j, error_j) in enumerate(points)
            if j != i
        )
        if not dominated:
            front.append(i)
    return front


def complete_front(rows: list[dict[str, Any]]) -> list[int]:
    """Indices of ``rows`` (``median_step_ms``, ``median_error_mm``,
    ``mean_stability_percent``) on the Pareto front among the rows whose cells all completed,
    by increasing time.

    A row whose cells broke off has the error of the depths it reached: on the front it would
    claim a smaller error than the whole experiment would have had (on the full study, five
    were: paper prescribed at 571, 1,303 and 4,141 tets, completing 76, 62 and 22 % of their
    experiments on average, and paper penalty at 571 and 12,971, 82 and 99.8 %).
    """
    complete = [i for i, r in enumerate(rows) if r["mean_stability_percent"] >= 100.0]
    points = [(rows[i]["median_step_ms"], rows[i]["median_error_mm"]) for i in complete]
    front = [complete[k] for k in pareto_front(points)]
    return sorted(front, key=lambda i: rows[i]["median_step_ms"])


# ---------------------------------------------------------------------- figures


def _plot_boxes(
    path: Path,
    data: dict[str, dict[tuple[str, int], list[float]]],
    records: list[dict[str, Any]],
    ylabel: str,
    scale: float,
    log: bool,
    hlines: list[tuple[float, str, str]],
) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    configs = list(data)
    levels = _levels(records)
    methods = _methods(records)
    # One row per profile, so that the figure stays legible at a page's width.
    figure, axes = plt.subplots(
        len(configs), 1, figsize=(min(9.0, 3.0 + 0.75 * len(levels)), 2.9 * len(configs)),
        squeeze=False, sharey=True, sharex=True,
    )  # fmt: skip
    width = 0.8 / max(1, len(methods))
    for axis, config in zip(axes[:, 0], configs, strict=True):
        for m, method in enumerate(methods):
            positions, values = [], []
            for l_index, level in enumerate(levels):
                sample = data[config].get((method, level), [])
                if sample:
                    positions.append(l_index + (m - (len(methods) - 1) / 2) * width)
                    values.append(np.asarray(sample) * scale)
            if values:
                boxes = axis.boxplot(
                    values, positions=positions, widths=width * 0.9, patch_artist=True,
                    showfliers=True, manage_ticks=False,
                )  # fmt: skip
                for box in boxes["boxes"]:
                    box.set_facecolor(METHOD_COLOUR[method])
                    box.set_alpha(0.6)
            axis.plot([], [], color=METHOD_COLOUR[method], lw=6, alpha=0.6,
                      label=METHOD_LABEL[method])  # fmt: skip
        for value, colour, label in hlines:
            axis.axhline(value, color=colour, lw=1, ls="--", label=label)
        axis.set_xticks(range(len(levels)))
        axis.set_xticklabels([f"{_tets(records, level):,}" for level in levels], fontsize=8)
        axis.set_title(f"{config} profile", fontsize=10)
        axis.set_ylabel(ylabel, fontsize=9)
        if log:
            axis.set_yscale("log")
        axis.grid(axis="y", alpha=0.3)
    axes[-1][0].set_xlabel("tetrahedra of each level's mesh")
    axes[0][0].legend(fontsize=7, ncol=3)
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)


def plot_accuracy_vs_time(path: Path, rows: list[dict[str, Any]]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    usable = [r for r in rows if r["median_error_mm"] is not None and r["median_step_ms"]]
    figure, axis = plt.subplots(figsize=(7.5, 5))
    markers = {"paper": "o", "robust": "s"}
    for row in usable:
        # Hollow where the cells did not complete on average: their error counts only the
        # depths reached, so a hollow point's accuracy is not the whole experiment's (where
        # the paper configuration stops being usable as the mesh is refined).
        colour = METHOD_COLOUR[row["method"]]
        complete = row["mean_stability_percent"] >= 100.0
        axis.scatter(
            row["median_step_ms"], row["median_error_mm"], marker=markers.get(row["config"], "^"),
            s=20 + 12 * np.log10(row["tets"]), alpha=0.75,
            facecolors=colour if complete else "none", edgecolors="none" if complete else colour,
            linewidths=0 if complete else 1.5,
        )  # fmt: skip
    points = [(r["median_step_ms"], r["median_error_mm"]) for r in usable]
    front = complete_front(usable)
    if front:
        axis.plot(
            [points[i][0] for i in front], [points[i][1] for i in front], "k--", lw=1,
            label="Pareto front (complete points)",
        )  # fmt: skip
        for rank, i in enumerate(front):
            row = usable[i]
            # Above and below the front in turn: neighbours on the front often share an
            # error (the finest level's robust cells all near 0) and their labels overlapped.
            axis.annotate(
                f"{METHOD_LABEL[row['method']]} {row['config']} {row['tets']:,}",
                points[i], fontsize=7, xytext=(4, 4 if rank % 2 == 0 else -11),
                textcoords="offset points",
            )  # fmt: skip
    for method in METHOD_ORDER:
        axis.scatter([], [], color=METHOD_COLOUR[method], label=METHOD_LABEL[method])
    for config, marker in markers.items():
        axis.scatter([], [], color="grey", marker=marker, label=config)
    axis.scatter([], [], facecolors="none", edgecolors="grey", linewidths=1.5,
                 label="mean stability < 100 %")  # fmt: skip
    axis.axvline(20, color="tab:blue", lw=1, ls=":")
    axis.axvline(40, color="black", lw=1, ls=":")
    axis.set_xscale("log")
    axis.set_xlabel("median compute time per step [ms] (h = 20 ms dotted blue, 25 fps black)")
    axis.set_ylabel("median localisation error [mm]")
    axis.set_title("What accuracy costs in time (marker size grows with the tet count)")
    axis.grid(alpha=0.3)
    axis.legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)


# ---------------------------------------------------------------------- report


def _machine() -> dict[str, Any]:
    import numpy

    return {
        "host": platform.node(),
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
        "numpy": numpy.__version__,
    }


def write_report(
    out: Path,
    spec: StudySpec,
    records: list[dict[str, Any]],
    references: dict[int, dict[str, Any]],
) -> None:
    """Write every output file of the study into ``out`` (see the module docstring)."""
    configs = [c.value for c in spec.configs]
    wanted = {(c, m.value) for c in configs for m in spec.methods}
    records = [
        r for r in records
        if r["level"] in spec.levels
        and (r["config"], r["method"]) in wanted
        and (spec.lesions is None or r["lesion"] in spec.lesions)
    ]  # fmt: skip
    stability = stability_table(records, configs) if records else "(no cells)\n"
    (out / "stability.md").write_text(
        "# Stability (% of the experiment completed before an instability)\n\n" + stability
    )
    if not records:
        return
    errors = valid_errors(records, configs)
    # The paper's red line: the PBD baseline's median error (its paper configuration here).
    baseline = "paper" if "paper" in errors else configs[0]
    pbd = [v for (m, _), vals in errors[baseline].items() if m == "pbd" for v in vals]
    hlines = [(float(np.median(pbd)) * 1e3, "red", f"PBD ({baseline}) median")] if pbd else []
    _plot_boxes(out / "errors.png", errors, records, "localisation error [mm]", 1e3, False,
                hlines)  # fmt: skip
    times = _median_times(records, configs)
    _plot_boxes(out / "times.png", times, records, "compute time per step [ms]", 1.0, True,
                [(20.0, "tab:blue", "h = 20 ms"), (40.0, "black", "25 fps")])  # fmt: skip
    rows = summary_rows(records, configs)
    plot_accuracy_vs_time(out / "accuracy_vs_time.png", rows)
    (out / "summary.json").write_text(strict_json(rows, indent=1))
    _write_markdown_and_html(out, spec, records, references, stability, rows)


def _provenance(records: list[dict[str, Any]]) -> str:
    """Which hosts and code revisions the cells ran on, with counts: a study resumed over
    several sessions (or machines) says so."""

    def counted(field: str) -> str:
        counts = Counter(str(r.get(field) or "unknown") for r in records)
        return ", ".join(f"{name} ({n})" for name, n in sorted(counts.items()))

    return f"Cells ran on hosts {counted('host')}; code revisions {counted('revision')}."


def _load_words(records: list[dict[str, Any]]) -> str:
    """The machine's load the cells' timings ran under (1-minute load average at each cell's
    end): times on a shared machine move with it."""
    loads = [r["load_average"] for r in records if r.get("load_average") is not None]
    if not loads:
        return "The machine's load was not recorded for these cells."
    return (
        f"Timings ran under a 1-minute load average of {min(loads):.1f} to {max(loads):.1f} "
        f"(median {np.median(loads):.1f}) on {os.cpu_count()} cores: compare times taken in "
        "one run."
    )


def _conclusions(
    records: list[dict[str, Any]], rows: list[dict[str, Any]], configs: list[str]
) -> str:
    """A short paragraph of what the numbers say, written from them."""
    sentences = []
    for config in configs:
        group = [r for r in records if r["config"] == config]
        if not group:
            continue
        complete = sum(r["stability_percent"] >= 100.0 for r in group)
        by_method = {
            METHOD_LABEL[m]: np.mean([r["stability_percent"] for r in group if r["method"] == m])
            for m in _methods(group)
        }
        worst = min(by_method, key=lambda name: by_method[name])
        sentences.append(
            f"In the {config} profile {complete} of {len(group)} cells completed their "
            f"experiment; the least stable method was {worst} "
            f"({by_method[worst]:.0f} % of the experiment on average)."
        )
    paper = [r for r in records if r["config"] == "paper"]
    levels = sorted({r["level"] for r in paper if isinstance(r["level"], int)})
    if len(levels) >= 2:
        coarse = np.mean([r["stability_percent"] for r in paper if r["level"] == levels[0]])
        fine = np.mean([r["stability_percent"] for r in paper if r["level"] == levels[-1]])
        trend = "fell" if fine < coarse else "did not fall"
        sentences.append(
            f"As in Tagliabue et al.'s Table 1, the paper profile's stability {trend} with the "
            f"mesh's resolution here ({coarse:.0f} % on average at level {levels[0]}, "
            f"{fine:.0f} % at level {levels[-1]}); their Table 1 is beside ours below."
        )
    scored = [r for r in rows if r["median_error_mm"] is not None]
    if scored:
        low = min(scored, key=lambda r: r["median_error_mm"])
        high = max(scored, key=lambda r: r["median_error_mm"])
        sentences.append(
            f"Median localisation errors ranged from {low['median_error_mm']:.2f} mm "
            f"({METHOD_LABEL[low['method']]}, {low['config']}, level {level_label(low['level'])}) "
            f"to {high['median_error_mm']:.2f} mm ({METHOD_LABEL[high['method']]}, "
            f"{high['config']}, level {level_label(high['level'])}), on the depths every "
            "method reached."
        )
    front = complete_front(
        [r for r in rows if r["median_error_mm"] is not None and r["median_step_ms"]]
    )
    if front:
        usable = [r for r in rows if r["median_error_mm"] is not None and r["median_step_ms"]]
        fastest = usable[front[0]]
        sentences.append(
            f"Of the cells that all completed, the fastest on the accuracy-time front was "
            f"{METHOD_LABEL[fastest['method']]} ({fastest['config']}, "
            f"{fastest['tets']:,} tets: {fastest['median_step_ms']:.1f} ms a step, "
            f"{fastest['median_error_mm']:.2f} mm)."
        )
    return " ".join(sentences)


def _path_words(spec: StudySpec) -> str:
    """How the probe moves in this study's scene, in words for the report."""
    if spec.scene == "synthetic":
        depths = ", ".join(f"{d * 1e3:g}" for d in spec.depths_m)
        return (
            "the probe on the skin above each lesion, normal to the surface, pressed through "
            f"{depths} mm past first contact"
        )
    return (
        "the probe through the scene's own published poses for each lesion (Transform1..4, "
        "which tilt as well as press; `depths_m` below does not apply)"
    )


def _write_markdown_and_html(
    out: Path,
    spec: StudySpec,
    records: list[dict[str, Any]],
    references: dict[int, dict[str, Any]],
    stability: str,
    rows: list[dict[str, Any]],
) -> None:
    lines = [
        "# probegym compression study",
        "",
        f"Reproduces the compression study of Tagliabue et al. (2020): {_path_words(spec)}, at "
        f"{spec.speed_m_s * 1e3:g} mm/s with h = 20 ms, settling at each depth "
        f"(held until no node moves faster than {SETTLED_SPEED_M_S * 1e3:g} mm/s, at most "
        f"{spec.settle_steps} steps).",
        "",
        "## Configuration",
        "",
        "```json",
        json.dumps(spec.as_json(), indent=1),
        "```",
        "",
        "## Machine",
        "",
        "```json",
        json.dumps(_machine(), indent=1),
        "```",
        "",
        _provenance(records),
        "",
        _load_words(records),
        "",
        "## What this run shows",
        "",
        _conclusions(records, rows, [c.value for c in spec.configs]),
        "",
        "## Stability (the paper's Table 1)",
        "",
        stability,
        "## Accuracy and time",
        "",
        "Median localisation error (eq. 12) and median compute time per step, per profile, "
        "contact method and level. Errors count only the depths every method of every "
        "profile reached for that lesion and level (the paper's valid deformations, across "
        "profiles): a cell that broke off is not scored on the shallow, easier depths it "
        "reached alone. A method that failed before its first depth drops out of that lesion "
        "and level, its stability telling why.",
        "",
        "| profile | contact | level (tets) | cells | median error [mm] | median step [ms] "
        "| mean stability [%] |",
        "|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        error = "" if row["median_error_mm"] is None else f"{row['median_error_mm']:.2f}"
        time = "" if row["median_step_ms"] is None else f"{row['median_step_ms']:.2f}"
        lines.append(
            f"| {row['config']} | {METHOD_LABEL[row['method']]} "
            f"| {level_and_tets(row['level'], row['tets'])} | {row['cells']} | {error} "
            f"| {time} | {row['mean_stability_percent']:.0f} |"
        )
    lines += [
        "",
        "![errors](errors.png)",
        "",
        "Localisation errors per profile, contact method and level, on the depths every "
        "method of every profile reached (the red line: the paper profile's PBD median).",
        "",
        "![times](times.png)",
        "",
        "Compute time per step (each cell's median), log scale; h = 20 ms is real time.",
        "",
        "![accuracy vs time](accuracy_vs_time.png)",
        "",
        "## Reference",
        "",
    ]
    if references:
        lines += ["| lesion | kind | level | tets | depths reached | status | wall [s] |",
                  "|---|---|---|---|---|---|---|"]  # fmt: skip
        for lesion, ref in sorted(references.items()):
            status = "ok" if ref["instability"] is None else ref["instability"]["kind"]
            lines.append(
                f"| {lesion} | {ref.get('kind', 'quasi-static')} | {ref['level_label']} "
                f"| {ref['tets']:,} | "
                f"{len(ref['tracked_m'])}/{len(ref['depths_m'])} | {status} "
                f"| {ref['wall_s']:.1f} |"
            )
    else:
        lines.append("Scored against measured positions (--measured).")
    unstable = [r for r in records if r["instability"] is not None]
    lines += ["", "## Instabilities", ""]
    if unstable:
        lines += ["| cell | stability [%] | kind | detail |", "|---|---|---|---|"]
        for record in unstable:
            lines.append(
                f"| {record['key']} | {record['stability_percent']:.0f} | "
                f"{record['instability']['kind']} | {record['instability']['detail']} |"
            )
    else:
        lines.append("None: every cell completed its experiment.")
    markdown = "\n".join(lines) + "\n"
    (out / "report.md").write_text(markdown)
    (out / "report.html").write_text(_markdown_to_html(markdown))


def _markdown_to_html(markdown: str) -> str:
    """A small converter for the report's own Markdown (headings, tables, code, images)."""
    body: list[str] = []
    in_code = in_table = False
    for line in markdown.splitlines():
        if line.startswith("```"):
            body.append("</pre>" if in_code else "<pre>")
            in_code = not in_code
            continue
        if in_code:
            body.append(html.escape(line))
            continue
        if line.startswith("|"):
            cells = [html.escape(c.strip()) for c in line.strip("|").split("|")]
            if set("".join(cells)) <= {"-"}:
                continue
            if not in_table:
                body.append("<table border=1 cellspacing=0 cellpadding=3>")
                in_table = True
            body.append("<tr>" + "".join(f"<td>{c}</td>" for c in cells) + "</tr>")
            continue
        if in_table:
            body.append("</table>")
            in_table = False
        if line.startswith("#"):
            depth = len(line) - len(line.lstrip("#"))
            body.append(f"<h{depth}>{html.escape(line.lstrip('#').strip())}</h{depth}>")
        elif line.startswith("!["):
            alt, src = line[2:].split("](")
            body.append(f'<p><img src="{html.escape(src.rstrip(")"))}" alt="{html.escape(alt)}">')
        elif line:
            body.append(f"<p>{html.escape(line)}</p>")
    if in_table:
        body.append("</table>")
    return (
        "<!doctype html><html><head><meta charset='utf-8'><title>probegym study</title>"
        "</head><body>\n" + "\n".join(body) + "\n</body></html>\n"
    )
