"""Running a transfer study: every training run, then every (run, evaluation configuration)
cell, each kept on disk so that an interrupted study resumes where it stopped.

Layout under ``OUT`` (``probegym-out/study/transfer`` by default)::

    <Task>/train/<method>@<level>-seed<S>/          a probegym train folder
    <Task>/cells/<method>@<level>-seed<S>/on-<method>@<level>/
        cell.json                                   the cell's record (written last)
        episodes.json, summary.json, ...            probegym evaluate's outputs
    transfer.json, transfer.csv                     every cell's record
    <Task>-matrix.png, <Task>-pareto.png, report.md

A finished training run is never trained again (``probegym train`` resumes from its latest
checkpoint and stops at its budget); a cell with a readable ``cell.json`` of the same
study is never evaluated again; one that cannot be read is reported and evaluated again.
"""

from __future__ import annotations

import json
import multiprocessing
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from agents.learning.evaluation.baselines import trained_steps, training_wall_s
from agents.learning.evaluation.report import wilson_interval
from agents.learning.evaluation.run import evaluate
from agents.learning.train.run import TrainSettings, train
from agents.learning.transfer.spec import (
    HELD_OUT_SEED,
    Configuration,
    TransferSpec,
    short_name,
)
from agents.outputs import write_json

#: The record keys a finished cell must hold to be kept.
CELL_KEYS = ("env_id", "train", "seed", "evaluate", "episodes", "successes", "success_rate")


@dataclass
class TransferOutcome:
    """What a run of the study did.

    Attributes:
        records: every cell's record, the study's order.
        trained_now: training runs trained (or resumed) by this call.
        evaluated_now: cells evaluated by this call.
        redone: cells whose record could not be read, evaluated again.
    """

    records: list[dict[str, Any]] = field(default_factory=list)
    trained_now: int = 0
    evaluated_now: int = 0
    redone: list[str] = field(default_factory=list)


def run_folder(out: Path, env_id: str, config: Configuration, seed: int) -> Path:
    return out / short_name(env_id) / "train" / f"{config.label}-seed{seed}"


def cell_folder(
    out: Path, env_id: str, config: Configuration, seed: int, on: Configuration
) -> Path:
    return out / short_name(env_id) / "cells" / f"{config.label}-seed{seed}" / f"on-{on.label}"


def train_settings(spec: TransferSpec, out: Path) -> list[TrainSettings]:
    """One :class:`TrainSettings` per training run (the task's default hyper-parameters;
    two training evaluations, at half and at the whole budget, of 10 episodes or the cells'
    ``spec.episodes`` where fewer)."""
    settings = []
    for env_id, config, seed in spec.runs():
        steps = spec.steps[env_id]
        settings.append(
            TrainSettings(
                env_id=env_id,
                out=run_folder(out, env_id, config, seed),
                algo=spec.algo,
                env_kwargs=config.env_kwargs(),
                steps=steps,
                n_envs=spec.n_envs,
                seed=seed,
                eval_every=max(1, steps // 2),
                eval_episodes=min(10, spec.episodes),
                checkpoint_every=max(1, steps // 2),
                progress=False,
            )
        )
    return settings


def run_transfer(
    spec: TransferSpec,
    out: Path,
    *,
    ray_address: str | None = None,
    command: str | None = None,
    log: Callable[[str], Any] = print,
) -> TransferOutcome:
    """Train every run not yet trained (here, or each as a Ray task), evaluate every cell not
    yet evaluated, and write ``transfer.json`` / ``transfer.csv`` and the report."""
    from agents.learning.transfer.report import write_report

    out = Path(out)
    outcome = TransferOutcome()
    settings = train_settings(spec, out)
    pending = [s for s in settings if not _trained(s)]
    if ray_address is not None and pending:
        from agents.learning.train.command import train_on_ray

        train_on_ray(pending, ray_address, command or "probegym study --transfer")
    else:
        for s in pending:
            log(f"training {s.env_id} on {s.env_kwargs['contact']}@{s.env_kwargs['mesh']}, "
                f"seed {s.seed}, {s.steps:,} steps")  # fmt: skip
            train(s, command=command, log=log)
    outcome.trained_now = len(pending)
    cells: list[tuple[TrainSettings, Configuration, Configuration, Path]] = []
    for s in settings:
        trained_on = Configuration(str(s.env_kwargs["contact"]), int(s.env_kwargs["mesh"]))
        cells.extend(
            (s, trained_on, on, cell_folder(out, s.env_id, trained_on, s.seed, on))
            for on in spec.evaluate
        )
    records: list[dict[str, Any] | None] = [
        _finished_cell(folder, spec, s, on, outcome) for s, _, on, folder in cells
    ]
    todo = [i for i, record in enumerate(records) if record is None]
    for i, record in _evaluate_cells(spec, cells, todo, log):
        records[i] = record
        outcome.evaluated_now += 1
    outcome.records = [record for record in records if record is not None]
    write_report(spec, outcome.records, out, command)
    return outcome


def _evaluate_cells(
    spec: TransferSpec,
    cells: list[tuple[TrainSettings, Configuration, Configuration, Path]],
    todo: list[int],
    log: Callable[[str], Any],
) -> Iterator[tuple[int, dict[str, Any]]]:
    """Evaluate the cells ``todo`` (indices into ``cells``), ``spec.n_envs`` at a time in
    spawned processes (one per core, as training's workers; numba's OpenMP layer forbids
    fork); yields (index, record) as each finishes. A cell that fails does not stop the
    others: the first failure is raised once every cell has run, the finished cells kept."""
    if not todo:
        return

    def label(i: int) -> str:
        s, trained_on, on, _ = cells[i]
        return f"{s.env_id} {trained_on.label}-seed{s.seed} on {on.label}"

    if spec.n_envs <= 1 or len(todo) == 1:
        for i in todo:
            log(f"evaluating {label(i)}")
            yield i, evaluate_cell(spec, *cells[i])
        return
    failure: BaseException | None = None
    context = multiprocessing.get_context("spawn")
    pool = ProcessPoolExecutor(spec.n_envs, mp_context=context, initializer=_one_torch_thread)
    with pool:
        futures = {pool.submit(evaluate_cell, spec, *cells[i]): i for i in todo}
        for future in as_completed(futures):
            i = futures[future]
            try:
                record = future.result()
            except Exception as error:  # reported once the others have finished
                log(f"evaluating {label(i)} failed: {error!r}")
                failure = failure or error
                continue
            log(f"evaluated {label(i)}: {record['successes']}/{record['episodes']}")
            yield i, record
    if failure is not None:
        raise failure


def _one_torch_thread() -> None:
    """A cell worker's networks run on one thread: the workers have the cores."""
    import torch

    torch.set_num_threads(1)


def _trained(settings: TrainSettings) -> bool:
    return (Path(settings.out) / "model.zip").is_file() and trained_steps(
        Path(settings.out)
    ) >= settings.steps


def _finished_cell(
    folder: Path, spec: TransferSpec, settings: TrainSettings, on: Configuration,
    outcome: TransferOutcome,
) -> dict[str, Any] | None:  # fmt: skip
    """The cell's record where it was finished by this study; None where it must run (a
    record that cannot be read, or of other settings, is reported in ``outcome.redone``)."""
    path = folder / "cell.json"
    if not path.is_file():
        return None
    try:
        record = json.loads(path.read_text())
        complete = isinstance(record, dict) and all(key in record for key in CELL_KEYS)
    except (OSError, ValueError):
        complete, record = False, None
    if not complete or not isinstance(record, dict):
        outcome.redone.append(f"{path}: unreadable or incomplete, evaluated again")
        return None
    if record["episodes"] != spec.episodes or record.get("steps") != settings.steps:
        outcome.redone.append(f"{path}: another study's cell, evaluated again")
        return None
    return record


def evaluate_cell(
    spec: TransferSpec,
    settings: TrainSettings,
    trained_on: Configuration,
    on: Configuration,
    folder: Path,
) -> dict[str, Any]:
    """Evaluate the run's final model on ``on`` over the held-out episodes; write and return
    the cell's record."""
    started = time.perf_counter()
    episodes = evaluate(
        settings.env_id,
        Path(settings.out),
        spec.episodes,
        HELD_OUT_SEED,
        on.env_kwargs(),
        folder,
        command=f"probegym study --transfer (cell {trained_on.label} on {on.label})",
    )
    successes = sum(1 for episode in episodes if episode["success"])
    low, high = wilson_interval(successes, len(episodes))
    errors = [e["centring_error_m"] for e in episodes if e.get("centring_error_m") is not None]
    run = Path(settings.out)
    steps = trained_steps(run)
    record = {
        "env_id": settings.env_id,
        "algo": settings.algo,
        "train": trained_on.label,
        "train_method": trained_on.method,
        "train_level": trained_on.level,
        "seed": settings.seed,
        "steps": settings.steps,
        "trained_steps": steps,
        "train_wall_s": training_wall_s(run, steps),
        "evaluate": on.label,
        "evaluate_method": on.method,
        "evaluate_level": on.level,
        "reference": on == spec.reference,
        "episodes": len(episodes),
        "successes": successes,
        "success_rate": successes / len(episodes),
        "success_interval": [low, high],
        "contact_force_mean_n": sum(e["contact_force_mean_n"] for e in episodes) / len(episodes),
        "lesion_error_mean_m": sum(errors) / len(errors) if errors else None,
        "ends": _ends(episodes),
        "eval_wall_s": time.perf_counter() - started,
        "model": str(run / "model.zip"),
    }
    write_json(record, folder / "cell.json")
    return record


def _ends(episodes: list[dict[str, Any]]) -> dict[str, int]:
    ends: dict[str, int] = {}
    for episode in episodes:
        ends[episode["end"]] = ends.get(episode["end"], 0) + 1
    return dict(sorted(ends.items()))
