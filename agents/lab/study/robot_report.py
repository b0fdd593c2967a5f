"""The robot study's outputs, written from its ``results.jsonl`` (see
:mod:`agents.lab.study.robot`):

- ``robot.md``: per profile, method and level, a table of every cell's depths: the force
  (robot and kinematic), the lesion error (the robot's tracked lesion point against the
  kinematic cell's) and the tracking error (along and across the pressing axis, orientation)
  at each settled depth, then the largest tracking error over the motion and the stability;
- ``stability.md``: the study's stability table (:func:`agents.lab.study.tables.stability_table`)
  for the robot cells;
- ``robot_vs_kinematic.png``: force against depth (robot solid, kinematic dashed) and the
  lesion error against depth, per cell;
- ``tracking.png``: the probe's tracking error along the pressing axis over each cell's run;
- ``summary.json``: one row per cell.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from agents.lab.study.robot import TWIN_ENV_TISSUE, TWIN_FROM_RESULTS, TWIN_RUN
from agents.lab.study.spec import StudySpec
from agents.lab.study.tables import level_and_tets, method_colour, method_label, stability_table
from agents.outputs import strict_json


def _mm(value: float | None, digits: int = 2) -> str:
    return "–" if value is None else f"{1e3 * value:.{digits}f}"


def _n(value: float | None) -> str:
    return "–" if value is None else f"{value:.3f}"


#: How ``robot.md`` names where each kinematic twin came from (the record's
#: ``kinematic.source``, :mod:`agents.lab.study.robot_runner`).
_TWIN_SOURCES = {
    TWIN_FROM_RESULTS: "the kinematic study's cell, read from its results.jsonl",
    TWIN_RUN: "the kinematic study's cell, run with the study's configuration",
    TWIN_ENV_TISSUE: (
        "the study's protocol run kinematically on the environment's own tissue (its contact "
        "settings differ from the kinematic study's)"
    ),
}


def cell_table(records: list[dict[str, Any]]) -> str:
    """The Markdown tables of ``robot.md``: one per profile, method and level."""
    groups: dict[tuple[str, str, int], list[dict[str, Any]]] = {}
    for record in records:
        groups.setdefault((record["config"], record["method"], record["level"]), []).append(record)
    parts = []
    for (config, method, level), group in sorted(groups.items()):
        tets = group[0]["tets"]
        sources = sorted({r["kinematic"]["source"] for r in group})
        lines = [
            f"### {config} profile, {method_label(method)}, {level_and_tets(level, tets)}",
            "",
            f"Kinematic twin: {', '.join(_TWIN_SOURCES.get(s, s) for s in sources)}.",
            "",
            "| lesion | depth [mm] | force robot [N] | force kinematic [N] | lesion error "
            "robot vs kinematic [mm] | along [mm] | across [mm] | orientation [deg] |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for record in sorted(group, key=lambda r: r["lesion"]):
            kinematic = record["kinematic"]
            tracking = record["tracking"]
            for i, depth in enumerate(record["depths_m"]):
                kin_force = (
                    kinematic["force_normal_n"][i] if i < len(kinematic["force_normal_n"]) else None
                )
                lines.append(
                    f"| {record['lesion']} | {1e3 * depth:g} | {_n(record['force_normal_n'][i])} "
                    f"| {_n(kin_force)} | {_mm(record['lesion_error_m'][i])} "
                    f"| {_mm(tracking['along_m'][i])} | {_mm(tracking['across_m'][i], 4)} "
                    f"| {tracking['orientation_deg'][i]:.4f} |"
                )
        lines += [
            "",
            "| lesion | robot: stability [%] | status | kinematic: stability [%] | status "
            "| motion: along max [mm] | across max [mm] | orientation max [deg] | wall [s] |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        for record in sorted(group, key=lambda r: r["lesion"]):
            kinematic, tracking = record["kinematic"], record["tracking"]
            status = record["status"]
            if record["instability"] is not None:
                status += f" ({record['instability']['kind']}: {record['instability']['detail']})"
            orientation = tracking["orientation_max_deg"]
            lines.append(
                f"| {record['lesion']} | {record['stability_percent']:.0f} | {status} "
                f"| {kinematic['stability_percent']:.0f} | {kinematic['status']} "
                f"| {_mm(tracking['along_max_m'])} | {_mm(tracking['across_max_m'], 4)} "
                f"| {'–' if orientation is None else f'{orientation:.4f}'} "
                f"| {record['wall_s']:.1f} |"
            )
        parts.append("\n".join(lines))
    return "\n\n".join(parts) + "\n"


def write_robot_report(out: Path, spec: StudySpec, records: list[dict[str, Any]]) -> None:
    """Write the robot study's tables, figures and summary into ``out``."""
    configs = [c.value for c in spec.configs]
    records = [
        r for r in records
        if r["level"] in spec.levels and r["config"] in configs and r["method"] in spec.methods
        and (spec.lesions is None or r["lesion"] in spec.lesions)
    ]  # fmt: skip
    header = (
        "# The study with the probe held by the arm\n\n"
        "Each cell runs the kinematic study's protocol in the coupled environment: the arm's "
        f"impedance controller tracks the kinematic path at {spec.speed_m_s:g} m/s and holds "
        "still at each depth to settle. Force: along the probe's pressing axis. Lesion error: "
        "distance between the tracked lesion point with the arm and with the kinematic probe, "
        "after settling at the same commanded depth. Tracking: the probe's pose minus the "
        "target's after settling (along the pressing axis, negative: short of the target).\n\n"
    )
    (out / "robot.md").write_text(header + (cell_table(records) if records else "(no cells)\n"))
    stability = stability_table(records, configs) if records else "(no cells)\n"
    (out / "stability.md").write_text(
        "# Stability with the arm (% of the experiment completed before an instability)\n\n"
        + stability
    )
    (out / "summary.json").write_text(strict_json(summary_json(records), indent=1))
    if records:
        plot_robot_vs_kinematic(out / "robot_vs_kinematic.png", records)
        plot_tracking(out / "tracking.png", records)


def _label(record: dict[str, Any]) -> str:
    return f"{record['config']} {record['method']} {record['level']} L{record['lesion']}"


def plot_robot_vs_kinematic(path: Path, records: list[dict[str, Any]]) -> None:
    """Force against depth (robot solid, kinematic dashed) and lesion error against depth."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, (force, error) = plt.subplots(1, 2, figsize=(11, 4.5))
    for record in records:
        colour = method_colour(record["method"])
        depths = 1e3 * np.asarray(record["depths_m"])
        kinematic = record["kinematic"]
        # A kinematic record lists every planned depth; its forces only those reached.
        kin_force = kinematic["force_normal_n"]
        kin_depths = 1e3 * np.asarray(kinematic["depths_m"][: len(kin_force)])
        line = force.plot(depths, record["force_normal_n"], "o-", color=colour, alpha=0.7,
                          label=_label(record))[0]  # fmt: skip
        force.plot(kin_depths, kin_force, "x--", color=line.get_color(),
                   alpha=0.5)  # fmt: skip
        values = [np.nan if e is None else 1e3 * e for e in record["lesion_error_m"]]
        error.plot(depths, values, "o-", color=colour, alpha=0.7, label=_label(record))
    force.set_xlabel("commanded depth past first contact [mm]")
    force.set_ylabel("normal force [N] (robot solid, kinematic dashed)")
    error.set_xlabel("commanded depth past first contact [mm]")
    error.set_ylabel("lesion error, robot vs kinematic [mm]")
    for axes in (force, error):
        axes.grid(alpha=0.3)
    if len(records) <= 12:
        error.legend(fontsize=7)
    figure.suptitle("The probe held by the arm against the kinematic probe")
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)


def plot_tracking(path: Path, records: list[dict[str, Any]]) -> None:
    """The probe's tracking error along the pressing axis over each cell's run."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(figsize=(8, 4.5))
    for record in records:
        trace = record["trace"]
        axes.plot(trace["t_s"], 1e3 * np.asarray(trace["along_m"]),
                  color=method_colour(record["method"]), alpha=0.6, lw=1,
                  label=_label(record))  # fmt: skip
    axes.set_xlabel("time [s]")
    axes.set_ylabel("probe minus target along the pressing axis [mm]")
    axes.grid(alpha=0.3)
    if len(records) <= 12:
        axes.legend(fontsize=7)
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)


def summary_json(records: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per cell for ``summary.json``: the figures the tables show."""
    rows = []
    for r in records:
        tracking = r["tracking"]
        rows.append(
            {
                "key": r["key"],
                "status": r["status"],
                "stability_percent": r["stability_percent"],
                "kinematic_status": r["kinematic"]["status"],
                "lesion_error_max_m": max(
                    (e for e in r["lesion_error_m"] if e is not None), default=None
                ),
                "along_at_depth_max_m": max((abs(a) for a in tracking["along_m"]), default=None),
                "along_motion_max_m": tracking["along_max_m"],
                "across_motion_max_m": tracking["across_max_m"],
                "orientation_motion_max_deg": tracking["orientation_max_deg"],
            }
        )
    return rows
