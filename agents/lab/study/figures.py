"""The study's figures: the paper's Fig. 2 (``errors.png``, localisation errors per method
and level) and Fig. 3 (``times.png``, compute time per step, log scale, lines at h = 20 ms and
25 fps) as stacked box plots, one panel per profile, and ``accuracy_vs_time.png`` (median
error against median time per step, hollow where the cells broke off, the Pareto front among
the complete points marked)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from agents.lab.study.tables import (
    complete_front,
    levels_present,
    method_colour,
    method_label,
    methods_present,
    tets_of_level,
)


def plot_boxes(
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
    levels = levels_present(records)
    methods = methods_present(records)
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
                    box.set_facecolor(method_colour(method))
                    box.set_alpha(0.6)
            axis.plot([], [], color=method_colour(method), lw=6, alpha=0.6,
                      label=method_label(method))  # fmt: skip
        for value, colour, label in hlines:
            axis.axhline(value, color=colour, lw=1, ls="--", label=label)
        axis.set_xticks(range(len(levels)))
        axis.set_xticklabels([f"{tets_of_level(records, level):,}" for level in levels], fontsize=8)
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
        colour = method_colour(row["method"])
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
                f"{method_label(row['method'])} {row['config']} {row['tets']:,}",
                points[i], fontsize=7, xytext=(4, 4 if rank % 2 == 0 else -11),
                textcoords="offset points",
            )  # fmt: skip
    for method in methods_present(usable):
        axis.scatter([], [], color=method_colour(method), label=method_label(method))
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
