"""The study's numbers, from its ``results.jsonl`` records: the paper's Table 1 per profile
(the stability metric's mean, median and range per method and level), localisation errors
(eq. 12) on the depths every profile of a comparison simulated stably, median step times,
and the accuracy-against-time summary with its Pareto front among the cells that completed.
"""

from __future__ import annotations

from collections import defaultdict
from typing import Any

import numpy as np

from agents.lab.study.spec import STUDY_METHODS, level_label
from tissue.lab import CONTACT_MODELS


def method_label(method: str) -> str:
    """The method's short name in tables and figures: its strategy class's ``label``, or
    the name itself for a method not registered in this process (records read back)."""
    registered = CONTACT_MODELS.get(method)
    return registered.label if registered is not None else method


def method_colour(method: str) -> str:
    """The method's colour in figures (its strategy class's ``colour``; grey if unknown)."""
    registered = CONTACT_MODELS.get(method)
    return registered.colour if registered is not None else "tab:gray"


def _by_config(records: list[dict[str, Any]], configs: list[str]) -> dict[str, list[dict]]:
    """Records per configuration column group."""
    groups: dict[str, list[dict[str, Any]]] = {config: [] for config in configs}
    for record in records:
        if record["config"] in groups:
            groups[record["config"]].append(record)
    return groups


def methods_present(records: list[dict[str, Any]]) -> list[str]:
    """The methods in ``records``: the study's own in their order, then any others."""
    present = {record["method"] for record in records}
    return [m for m in STUDY_METHODS if m in present] + sorted(present - set(STUDY_METHODS))


def levels_present(records: list[dict[str, Any]]) -> list[int]:
    return sorted({record["level"] for record in records}, key=lambda v: (v != 0, v))


def tets_of_level(records: list[dict[str, Any]], level: int) -> int:
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
    methods = methods_present(records)
    lesion_count = len({r["lesion"] for r in records})
    tables = []
    for config in configs:
        paper = config == "paper" and any(
            level in PAPER_TABLE1 for level in levels_present(records)
        )
        head = ["level (tets)", *(method_label(m) for m in methods)]
        if paper:
            head += [f"2020 {method_label(m)}" for m in methods if m in PAPER_TABLE1_METHODS]
        lines = [
            f"**{config} profile**: mean (median, range) of the % of the experiment completed"
            + (" (right: Tagliabue et al. 2020, Table 1)" if paper else ""),
            "",
            "| " + " | ".join(head) + " |",
            "|" + "---|" * len(head),
        ]
        for level in levels_present(records):
            row = [level_and_tets(level, tets_of_level(records, level))]
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


def median_times(
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
    times = median_times(records, configs)
    groups = _by_config(records, configs)
    rows = []
    for config in configs:
        for method in methods_present(groups[config]):
            for level in levels_present(groups[config]):
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
