"""An evaluation's plots (matplotlib's Agg canvas, no pyplot and no display):

- ``success_rate.png``: the success rate with its 95 % Wilson interval;
- ``contact_force.png``: the contact force over each episode's steps;
- ``lesion_path.png`` (tasks with a lesion in the observation): where the target lesion
  went in the image plane, lateral against depth, each episode's first sight and end
  marked;
- ``scan_progress.png`` (ForceScan): the path left along the skin over each episode.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

#: Seconds of simulated time per environment step (every task steps at 50 Hz).
STEP_S = 0.02


def _figure(width: float = 6.0, height: float = 4.0) -> Any:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(width, height), dpi=100)
    FigureCanvasAgg(figure)
    return figure


def _save(figure: Any, path: Path) -> Path:
    figure.tight_layout()
    figure.savefig(path, format="png")
    return path


def write_plots(folder: Path, records: list[dict[str, Any]], summary: dict[str, Any]) -> list[Path]:
    """Write the plots that apply to this run; returns their paths."""
    paths = [success_plot(folder / "success_rate.png", summary)]
    paths.append(force_plot(folder / "contact_force.png", records, summary["env_id"]))
    if all("lesion" in record["series"] for record in records):
        paths.append(lesion_plot(folder / "lesion_path.png", records, summary["env_id"]))
    if all("remaining_m" in record["series"] for record in records):
        paths.append(progress_plot(folder / "scan_progress.png", records, summary["env_id"]))
    return paths


def _colours(count: int) -> list[Any]:
    from matplotlib import colormaps

    cmap = colormaps["viridis"]
    return [cmap(i / max(1, count - 1) * 0.9) for i in range(count)]


def success_plot(path: Path, summary: dict[str, Any]) -> Path:
    figure = _figure(4.0, 4.0)
    axes = figure.add_subplot()
    rate = summary["success_rate"]
    low, high = summary["success_rate_ci95"]
    axes.bar([0], [100 * rate], width=0.5, color="tab:blue")
    axes.errorbar(
        [0], [100 * rate], yerr=[[100 * (rate - low)], [100 * (high - rate)]],
        color="black", capsize=8,
    )  # fmt: skip
    axes.text(0, 100 * high + 2, f"{summary['successes']}/{summary['episodes']}", ha="center")
    axes.set_xlim(-1, 1)
    axes.set_ylim(0, 110)
    axes.set_xticks([0], [summary["policy"] if len(summary["policy"]) < 24 else "policy"])
    axes.set_ylabel("success rate [%] (95 % Wilson interval)")
    axes.set_title(summary["env_id"].split("/")[-1], fontsize=10)
    return _save(figure, path)


def force_plot(path: Path, records: list[dict[str, Any]], env_id: str) -> Path:
    figure = _figure()
    axes = figure.add_subplot()
    for record, colour in zip(records, _colours(len(records)), strict=True):
        forces = record["series"]["contact_force_n"]
        times = [STEP_S * (step + 1) for step in range(len(forces))]
        mark = "" if record["success"] else " (failed)"
        axes.plot(times, forces, color=colour, label=f"episode {record['episode']}{mark}")
    axes.set_xlabel("time [s]")
    axes.set_ylabel("contact force [N]")
    axes.set_title(f"{env_id.split('/')[-1]}: contact force per episode", fontsize=10)
    if len(records) <= 12:
        axes.legend(fontsize=7)
    return _save(figure, path)


def lesion_plot(path: Path, records: list[dict[str, Any]], env_id: str) -> Path:
    figure = _figure(5.0, 5.0)
    axes = figure.add_subplot()
    for record, colour in zip(records, _colours(len(records)), strict=True):
        seen = [point for point in record["series"]["lesion"] if point[2] > 0.5]
        if not seen:
            continue
        lateral = [1e3 * point[0] for point in seen]
        depth = [1e3 * point[1] for point in seen]
        axes.plot(lateral, depth, color=colour, linewidth=1, label=f"episode {record['episode']}")
        axes.plot(lateral[0], depth[0], "o", color=colour, markerfacecolor="none")
        end_visible = record["series"]["lesion"][-1][2] > 0.5
        axes.plot(lateral[-1], depth[-1], "x" if end_visible else "s", color=colour)
    axes.plot([], [], "ko", markerfacecolor="none", label="first seen")
    axes.plot([], [], "kx", label="end")
    axes.plot([], [], "ks", label="last seen (lost at the end)")
    axes.axvline(0.0, color="grey", linewidth=0.5)
    axes.invert_yaxis()  # depth grows down the image
    axes.set_xlabel("lateral [mm] (0: the image's centre line)")
    axes.set_ylabel("depth [mm]")
    axes.set_title(f"{env_id.split('/')[-1]}: the lesion in the image", fontsize=10)
    axes.legend(fontsize=7)
    return _save(figure, path)


def progress_plot(path: Path, records: list[dict[str, Any]], env_id: str) -> Path:
    figure = _figure()
    axes = figure.add_subplot()
    for record, colour in zip(records, _colours(len(records)), strict=True):
        left = record["series"]["remaining_m"]
        times = [STEP_S * step for step in range(len(left))]
        values = [float("nan") if value is None else 1e3 * value for value in left]
        axes.plot(times, values, color=colour, label=f"episode {record['episode']}")
    axes.set_xlabel("time [s]")
    axes.set_ylabel("path left along the skin [mm]")
    axes.set_title(f"{env_id.split('/')[-1]}: progress along the path", fontsize=10)
    if len(records) <= 12:
        axes.legend(fontsize=7)
    return _save(figure, path)
