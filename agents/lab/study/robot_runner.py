"""Running ``probegym study --robot``: every cell with the arm (:mod:`agents.lab.study.robot`)
beside its kinematic twin, resumably, into the ``robot/`` folder of the study's ``--out``.

``robot/results.jsonl`` gets one record per finished cell, appended as it finishes; a rerun
with the same ``--out`` skips the cells it holds (``robot/study.json`` records the settings,
and a rerun with other physics is refused). Each cell's kinematic twin is read from the
kinematic study's ``results.jsonl`` in ``--out`` when that study ran the same scene, depths,
speed and settling, and is run here with the study's own code
(:func:`agents.lab.study.cell.run_cell`) otherwise.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from agents.lab.study.cell import run_cell, scene_for
from agents.lab.study.robot import (
    ROBOT_DIR,
    ROBOT_ENV_ID,
    STUDY_TWIN_METHODS,
    TWIN_ENV_TISSUE,
    TWIN_FROM_RESULTS,
    TWIN_RUN,
    check_robot_spec,
    make_robot_env,
    max_press_m,
    run_robot_cell,
)
from agents.lab.study.robot_report import write_robot_report
from agents.lab.study.runner import RESULTS_FILE, SPEC_FILE, read_results, study_lesions
from agents.lab.study.spec import Cell, StudySpec
from agents.outputs import exclusive_folder, strict_json
from tissue import ConfigError, TissueSpec

#: Physics settings a resumed robot study must keep (the study's own, and the arm's).
_PHYSICS_KEYS = ("scene", "depths_m", "speed_m_s", "settle_steps", "env", "max_press_m")


# ---------------------------------------------------------------------- comparison


def compare_with_kinematic(
    robot: dict[str, Any], kinematic: dict[str, Any], source: str
) -> dict[str, Any]:
    """The robot record with its kinematic twin's force and lesion position per depth, and
    the lesion error (robot minus kinematic tracked point) [m] on the depths both reached."""
    both = min(len(robot["tracked_m"]), len(kinematic["tracked_m"]))
    errors: list[float | None] = [
        float(np.linalg.norm(np.subtract(robot["tracked_m"][i], kinematic["tracked_m"][i])))
        for i in range(both)
    ]
    errors += [None] * (len(robot["tracked_m"]) - both)
    return robot | {
        "kinematic": {
            "source": source,
            # Records written before twins ran on other tissues were all the study's.
            "tissue": kinematic.get("tissue", "study"),
            "status": kinematic["status"],
            "stability_percent": kinematic["stability_percent"],
            "depths_m": kinematic["depths_m"],
            "tracked_m": kinematic["tracked_m"],
            "force_normal_n": kinematic["force_normal_n"],
            "penetration_max_m": kinematic["penetration_max_m"],
            "step_ms": kinematic["step_ms"],
        },
        "lesion_error_m": errors,
    }


def kinematic_twin(
    spec: StudySpec,
    cell: Cell,
    tissue_spec: TissueSpec,
    twins: dict[str, dict[str, Any]],
) -> tuple[dict[str, Any], str]:
    """The kinematic cell to compare a robot cell with, and where it came from.

    LM and penalty (:data:`~agents.lab.study.robot.STUDY_TWIN_METHODS`): the kinematic study's
    record in ``twins`` when there is one, else the study's cell run now. Other methods:
    the study's protocol run now on ``tissue_spec``, the environment's own tissue, so that
    robot and kinematic cells differ only in who holds the probe.
    """
    if cell.method not in STUDY_TWIN_METHODS:
        return run_cell(spec, cell, tissue_spec), TWIN_ENV_TISSUE
    twin = twins.get(cell.key)
    if twin is not None:
        return twin, TWIN_FROM_RESULTS
    return run_cell(spec, cell), TWIN_RUN


def robot_cell_with_twin(
    spec: StudySpec, cell: Cell, twins: dict[str, dict[str, Any]]
) -> dict[str, Any]:
    """One robot cell compared with its kinematic twin (:func:`kinematic_twin`, on the
    tissue the cell's environment built): its ``results.jsonl`` record."""
    env = make_robot_env(cell, spec)
    try:
        record = run_robot_cell(spec, cell, env)
        tissue_spec = env.tissue.spec
    finally:
        env.close()
    twin, source = kinematic_twin(spec, cell, tissue_spec, twins)
    return compare_with_kinematic(record, twin, source)


def kinematic_records(
    spec: StudySpec, study_out: Path, log: Callable[[str], None]
) -> dict[str, dict[str, Any]]:
    """The kinematic study's records in ``study_out`` by key, when it ran the same physics
    (scene, depths, speed, settling); else {} (the robot study runs its cells itself)."""
    spec_path = study_out / SPEC_FILE
    if not spec_path.exists():
        return {}
    previous = json.loads(spec_path.read_text())
    current = spec.as_json()
    keys = ("scene", "collision_edge_m", "depths_m", "speed_m_s", "settle_steps")
    changed = [key for key in keys if previous.get(key) != current.get(key)]
    if changed:
        log(
            f"kinematic results in {study_out} ran other {', '.join(changed)}; the kinematic "
            "cells are run here"
        )
        return {}
    records = {r["key"]: r for r in read_results(study_out / RESULTS_FILE)}
    if records:
        log(f"kinematic cells read from {study_out / RESULTS_FILE} where they are there")
    return records


# ---------------------------------------------------------------------- the study


@dataclass
class RobotOutcome:
    """What a robot study did: every record (old and new), the cells run now and skipped,
    and the cells that raised (a bug: not recorded, a rerun retries them)."""

    records: list[dict[str, Any]]
    ran_now: int
    skipped: int
    failed: list[str] = field(default_factory=list)


def robot_spec_json(spec: StudySpec) -> dict[str, Any]:
    return spec.as_json() | {"env": ROBOT_ENV_ID, "max_press_m": max_press_m()}


def run_robot_study(
    spec: StudySpec,
    study_out: Path,
    progress: bool = True,
    log: Callable[[str], None] = print,
) -> RobotOutcome:
    """Run (or finish) the robot study into ``study_out / robot`` and write its tables and
    figures; kinematic twins come from ``study_out``'s results where they match, else they
    are run here with the study's own code."""
    check_robot_spec(spec)
    scene = scene_for(spec)
    lesions = study_lesions(spec, scene)
    out = study_out / ROBOT_DIR
    with exclusive_folder(out, "probegym study --robot"):
        spec_path = out / SPEC_FILE
        current = robot_spec_json(spec)
        if spec_path.exists():
            previous = json.loads(spec_path.read_text())
            changed = [k for k in _PHYSICS_KEYS if previous.get(k) != current.get(k)]
            if changed:
                raise ConfigError(
                    f"{out} holds a robot study with different {', '.join(changed)}; give a "
                    "new --out or the same settings"
                )
        spec_path.write_text(strict_json(current, indent=2))
        results = out / RESULTS_FILE
        records = read_results(results)
        done = {r["key"] for r in records}
        cells = [cell for cell in spec.cells(tuple(lesions)) if cell.key not in done]
        twins = kinematic_records(spec, study_out, log) if cells else {}
        log(f"study --robot: {len(cells)} cells to run, {len(done)} already in {results}")
        failed: list[str] = []
        from tqdm import tqdm

        for cell in tqdm(cells, desc="study --robot", disable=not progress):
            try:
                record = robot_cell_with_twin(spec, cell, twins)
            except (ConfigError, KeyboardInterrupt):
                raise
            except Exception as error:  # noqa: BLE001 - a bug in one cell, reported
                failed.append(f"cell {cell.key}: {type(error).__name__}: {error}")
                log(f"{failed[-1]} -- not recorded; the study goes on, and a rerun retries it")
                continue
            with results.open("a") as file:
                file.write(strict_json(record) + "\n")
            records.append(record)
            log(_cell_line(record))
        write_robot_report(out, spec, records)
    return RobotOutcome(records, len(cells) - len(failed), len(done), failed)


def _cell_line(record: dict[str, Any]) -> str:
    tracking = record["tracking"]
    errors = [e for e in record["lesion_error_m"] if e is not None]
    along = tracking["along_m"]
    return (
        f"{record['key']}: {record['status']}, {len(record['depths_m'])} depths, "
        f"lesion vs kinematic max {1e3 * max(errors, default=float('nan')):.2f} mm, "
        f"probe short of target {-1e3 * min(along, default=float('nan')):.2f} mm at depth, "
        f"{record['wall_s']:.1f} s"
    )
