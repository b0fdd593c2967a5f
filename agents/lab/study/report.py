"""The study's report, written from ``results.jsonl`` into the output folder:

- ``stability.md``: the paper's Table 1 per profile (:mod:`agents.lab.study.tables`);
- ``errors.png``, ``times.png`` and ``accuracy_vs_time.png`` (:mod:`agents.lab.study.figures`);
- ``summary.json``: the accuracy-against-time rows;
- ``report.md`` and ``report.html``: all of it with the run's configuration, machine and
  load, the paper's Table 1 beside ours, and a paragraph of what the run shows.

PBD has both profiles too: ``paper`` is the 10-substep, FleX-like baseline, ``robust`` runs
60 substeps (:meth:`tissue.pbd.PBDConfig.for_profile`).
"""

from __future__ import annotations

import html
import json
import os
import platform
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from agents.lab.compress import SETTLED_SPEED_M_S
from agents.lab.study.figures import plot_accuracy_vs_time, plot_boxes
from agents.lab.study.spec import StudySpec, level_label
from agents.lab.study.tables import (
    complete_front,
    level_and_tets,
    median_times,
    method_label,
    methods_present,
    stability_table,
    summary_rows,
    valid_errors,
)
from agents.outputs import strict_json


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
    wanted = {(c, m) for c in configs for m in spec.methods}
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
    plot_boxes(out / "errors.png", errors, records, "localisation error [mm]", 1e3, False,
                hlines)  # fmt: skip
    times = median_times(records, configs)
    plot_boxes(out / "times.png", times, records, "compute time per step [ms]", 1.0, True,
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
            method_label(m): np.mean([r["stability_percent"] for r in group if r["method"] == m])
            for m in methods_present(group)
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
            f"({method_label(low['method'])}, {low['config']}, level {level_label(low['level'])}) "
            f"to {high['median_error_mm']:.2f} mm ({method_label(high['method'])}, "
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
            f"{method_label(fastest['method'])} ({fastest['config']}, "
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
            f"| {row['config']} | {method_label(row['method'])} "
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
