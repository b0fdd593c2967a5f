"""Running a study: every cell and the references it is scored against, resumably,
locally or on Ray.

``results.jsonl`` in the output directory gets one line per finished cell, appended and
flushed as it finishes; a rerun with the same directory skips the cells it holds, so a
killed study loses at most the cells in flight, and of a reference in flight its step in
flight and the two minutes before (a reference saves its progress beside its cache file
after a step every two minutes, and a rerun resumes it: see
:func:`~agents.lab.study.reference.compute_reference`). The references run in
the same queue as the cells, before the cells on the reference level: a cell finishing
before its lesion's reference is appended with ``"truth": "pending"`` and its errors are
filled in, the file rewritten atomically, once the references are known (so a reference
recomputed by a new version rescores every record too). Each reference is also kept in
``references/`` of the output directory, under its cache key, so a study moved to another
machine (or a fresh cache) resumes without recomputing them. ``study.json`` records the
specification; rerunning with different physics (scene, depths, speed, reference) into the
same directory is refused. Timing: with ``workers`` > 1 the cells share the machine's
cores, so their per-step times are comparable within the run but slower than a one-worker
run's."""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable, Iterator
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from agents.lab.first_use import compile_kernels_once
from agents.lab.study.cell import run_cell, scene_for
from agents.lab.study.reference import (
    keepable,
    load_or_compute_reference,
    partial_path,
    read_measured_csv,
    reference_path,
)
from agents.lab.study.scenes import StudyScene
from agents.lab.study.spec import StudySpec, level_label
from agents.outputs import exclusive_folder, readable, strict_json
from tissue import ConfigError
from tissue.lab import TetMesh, parse_probe_spec

RESULTS_FILE = "results.jsonl"
SPEC_FILE = "study.json"
REFERENCES_FILE = "references.json"
# Each reference's own cache file is also kept here in the study directory, so that the
# study resumes elsewhere (another machine, a fresh cache) without recomputing them: on the
# finest level they take the longest of any task.
CARRIED_REFERENCES_DIR = "references"
# Settings that change the physics of a cell: a rerun must keep them.
_PHYSICS_KEYS = (
    "scene",
    "collision_edge_m",
    "depths_m",
    "speed_m_s",
    "settle_steps",
    "reference_level",
    "measured_csv",
)


#: A reference's work in cells of its level (the progress bar's weight).
REFERENCE_WEIGHT = 3


@dataclass
class StudyOutcome:
    """What a run did: the records (old and new), the references, the cells run now."""

    records: list[dict[str, Any]]
    references: dict[int, dict[str, Any]]
    ran_now: int
    skipped: int
    references_computed: int
    # Tasks that raised (a bug, not an instability): "cell KEY: Error: message" or
    # "reference lesion N: ...". Nothing of theirs is written; a rerun retries them.
    failed: list[str] = field(default_factory=list)


def read_results(path: Path) -> list[dict[str, Any]]:
    """The records of ``results.jsonl``; a line cut short by a kill is ignored."""
    if not path.exists():
        return []
    records = []
    for line in path.read_text().splitlines():
        try:
            records.append(json.loads(line))
        except json.JSONDecodeError:
            continue
    return records


def _append(path: Path, record: dict[str, Any]) -> None:
    # A kill can leave a line without its newline: start a fresh line after it.
    cut_short = False
    if path.exists() and path.stat().st_size > 0:
        with path.open("rb") as existing:
            existing.seek(-1, os.SEEK_END)
            cut_short = existing.read(1) != b"\n"
    with path.open("a") as file:
        file.write(("\n" if cut_short else "") + strict_json(record) + "\n")
        file.flush()
        os.fsync(file.fileno())


def _check_depths_reachable(
    spec: StudySpec, scene: StudyScene, lesions: tuple[int, ...], mesh: TetMesh
) -> None:
    """Refuse depths that drive the probe into the fixed base above some lesion."""
    shape = parse_probe_spec("face")
    clearances = {
        lesion: scene.base_clearance_m(mesh, shape, lesion, spec.depths_m) for lesion in lesions
    }
    blocked = {lesion: c for lesion, c in clearances.items() if c <= 0.0}
    if blocked:
        listed = ", ".join(f"lesion {k}: {1e3 * c:.1f} mm" for k, c in sorted(blocked.items()))
        raise ConfigError(
            f"--depths up to {1e3 * spec.depths_m[-1]:g} mm drive the probe into the fixed "
            f"base ({listed} between probe and base at the deepest pose); give smaller "
            "--depths or other --lesions"
        )


def _check_resume(spec: StudySpec, out: Path) -> None:
    spec_path = out / SPEC_FILE
    if spec_path.exists():
        previous = json.loads(spec_path.read_text())
        current = spec.as_json()
        changed = [key for key in _PHYSICS_KEYS if previous.get(key) != current.get(key)]
        if changed:
            raise ConfigError(
                f"{out} holds a study with different {', '.join(changed)} "
                f"({', '.join(f'{k}={previous.get(k)!r}' for k in changed)}); "
                "give a new --out or the same settings"
            )
    spec_path.write_text(strict_json(spec.as_json(), indent=2))


def tracked_errors(
    record: dict[str, Any], truth: list[list[float] | None] | None
) -> list[float | None]:
    """Eq. (12) per depth reached: distance [m] between the cell's and the true tracked
    point; None where the truth has no such depth."""
    errors: list[float | None] = []
    for index, point in enumerate(record["tracked_m"]):
        true_point = truth[index] if truth is not None and index < len(truth) else None
        if true_point is None:
            errors.append(None)
        else:
            errors.append(float(np.linalg.norm(np.subtract(point, true_point))))
    return errors


def run_study(
    spec: StudySpec,
    out: Path,
    workers: int = 1,
    ray_address: str | None = None,
    progress: bool = True,
    log: Callable[[str], None] = print,
) -> StudyOutcome:
    """Run (or finish) the study into ``out`` and write its report.

    Args:
        spec: what to run.
        out: output directory (created).
        workers: local processes running cells (1: in this process).
        ray_address: run on this Ray cluster instead (``auto``, ``local`` or an address).
        progress: show a progress bar with an ETA.
        log: where status lines go.
    """
    if workers < 1:
        raise ConfigError(f"--workers must be >= 1; got {workers}")
    scene = scene_for(spec)
    lesions = study_lesions(spec, scene)
    measured = read_measured_csv(spec.measured_csv) if spec.measured_csv else None
    # One study writes to a folder at a time: two rewriting results.jsonl at once each kept
    # only their own records.
    with exclusive_folder(out, "probegym study"):
        return _run_in(spec, out, workers, ray_address, progress, log, scene, lesions, measured)


def _run_in(
    spec: StudySpec,
    out: Path,
    workers: int,
    ray_address: str | None,
    progress: bool,
    log: Callable[[str], None],
    scene: StudyScene,
    lesions: tuple[int, ...],
    measured: dict[int, dict[int, list[float]]] | None,
) -> StudyOutcome:
    """:func:`run_study`'s work, with ``out`` locked."""
    _check_resume(spec, out)
    results_path = out / RESULTS_FILE
    records = read_results(results_path)
    done = {record["key"] for record in records}
    cells = [cell for cell in spec.cells(lesions) if cell.key not in done]

    # Meshes are generated (or read from the cache) here, once, before workers start.
    needed = sorted({cell.level for cell in cells} | ({spec.reference_level} if cells else set()))
    for index, level in enumerate(needed):  # coarse first
        mesh = scene.mesh(level)
        log(f"mesh {level_label(level)}: {mesh.tet_count} tets, {mesh.node_count} nodes")
        if index == 0 and scene.directory is None:
            # On the coarsest mesh, before the others are made: depths that drive the probe
            # into the base are refused before any more work.
            _check_depths_reachable(spec, scene, lesions, mesh)
    if cells:
        # Here, before the workers and the progress bar's clock: its estimate of the time left
        # is then the cells', not the compiler's (workers load the kernels from the cache).
        compile_kernels_once(log)
    tets = {level: scene.mesh(level).tet_count for level in needed}

    with _executor(workers, ray_address) as submit:
        references, waiting = _cached_references(spec, scene, lesions, measured, log, out)
        # Uncached references run as tasks in the cells' queue, just before the first cell on
        # the reference level: a reference on the finest level takes tens of minutes, and the
        # coarse levels' cells (seconds to minutes each) need not wait for it. A cell that
        # finishes before its lesion's reference is appended with its errors pending; every
        # record's errors are filled in (or refreshed) once the references are known.
        coarse = [cell for cell in cells if cell.level < spec.reference_level]
        tasks: list[_Task] = [
            *(("cell", cell) for cell in coarse),
            *(("reference", lesion) for lesion in waiting),
            *(("cell", cell) for cell in cells if cell.level >= spec.reference_level),
        ]
        resuming = sum(
            partial_path(reference_path(spec, scene, lesion)).exists() for lesion in waiting
        )
        log(
            f"study: {len(cells)} cells to run, {len(done)} already in {results_path}; "
            f"{len(waiting)} references to compute"
            + (f" ({resuming} resuming from saved progress)" if resuming else "")
        )
        computed = 0
        # The bar counts work, not tasks: a cell's cost grows with its mesh (a 4,141-tet
        # cell takes several times a 571-tet one), so counting cells made the first, coarse
        # cells promise an end far too soon. Work: the level's tets, and a reference
        # (Newton to 1e-5, the same path) as a few cells of its level.
        weights = [
            tets[item.level] if kind == "cell" else REFERENCE_WEIGHT * tets[spec.reference_level]
            for kind, item in tasks
        ]
        weight_of = dict(zip(tasks, weights, strict=True))
        bar = _progress_bar(sum(weights), progress)
        done_cells = 0
        window = 1 if workers == 1 and ray_address is None else 2 * workers
        failed: list[str] = []
        failed_cells = 0
        for (kind, item), result, error in _run_all(tasks, spec, submit, window):
            bar.update(weight_of[(kind, item)])
            done_cells += 1
            if error is not None:
                name = f"cell {item.key}" if kind == "cell" else f"reference lesion {item}"
                failed.append(f"{name}: {type(error).__name__}: {error}")
                failed_cells += int(kind == "cell")
                log(f"{failed[-1]} -- not recorded; the study goes on, and a rerun retries it")
                continue
            if kind == "reference":
                record, fresh = result
                references[item] = record
                computed += int(fresh)
                if keepable(record):
                    _carry_reference(out, reference_path(spec, scene, item), record)
                _log_reference(spec, item, record, fresh, log)
                bar.set_postfix_str(f"{done_cells}/{len(tasks)}: reference lesion {item}")
                continue
            result.update(_scoring(result, _truth(spec, result["lesion"], measured, references)))
            _append(results_path, result)
            records.append(result)
            bar.set_postfix_str(f"{done_cells}/{len(tasks)}: {result['key']} {result['status']}")
        bar.close()
        (out / REFERENCES_FILE).write_text(strict_json(references, indent=1))
        records = _rescore(results_path, records, spec, measured, references, log)

    from agents.lab.study.report import write_report

    write_report(out, spec, records, references)
    return StudyOutcome(records, references, len(cells) - failed_cells, len(done), computed, failed)


# A queued piece of work: ("cell", Cell) or ("reference", lesion).
_Task = tuple[str, Any]


def _truth(
    spec: StudySpec,
    lesion: int,
    measured: dict[int, dict[int, list[float]]] | None,
    references: dict[int, dict[str, Any]],
) -> tuple[str, list[list[float] | None] | None]:
    """What ``lesion``'s cells are scored against: (kind, tracked point per depth or None).

    kind is ``measured``, ``reference`` or ``pending`` (its reference not computed yet).
    """
    if measured is not None:
        points = measured.get(lesion)
        if points is None:
            return "measured", None
        return "measured", [points.get(i + 1) for i in range(len(spec.depths_m))]
    if lesion not in references:
        return "pending", None
    return "reference", references[lesion]["tracked_m"]


def _scoring(
    record: dict[str, Any], truth: tuple[str, list[list[float] | None] | None]
) -> dict[str, Any]:
    """The fields of ``record`` that depend on the truth: ``errors_m`` and ``truth``."""
    kind, points = truth
    return {"errors_m": tracked_errors(record, points), "truth": kind}


def _rescore(
    path: Path,
    records: list[dict[str, Any]],
    spec: StudySpec,
    measured: dict[int, dict[int, list[float]]] | None,
    references: dict[int, dict[str, Any]],
    log: Callable[[str], None],
) -> list[dict[str, Any]]:
    """Every record scored against the truth now known; ``results.jsonl`` is rewritten
    (atomically) when any record's errors were pending or scored against another truth."""
    changed = 0
    for record in records:
        fields = _scoring(record, _truth(spec, record["lesion"], measured, references))
        if any(record.get(key) != value for key, value in fields.items()):
            record.update(fields)
            changed += 1
    if changed:
        handle, temporary = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
        with os.fdopen(handle, "w") as file:
            file.writelines(strict_json(record) + "\n" for record in records)
            file.flush()
            os.fsync(file.fileno())
        readable(Path(temporary))  # mkstemp makes it 0600; the other outputs are 0644
        os.replace(temporary, path)  # a kill leaves the old file or the new, never half
        log(f"errors of {changed} cells scored against the truth now known")
    return records


def _cached_references(
    spec: StudySpec,
    scene: StudyScene,
    lesions: tuple[int, ...],
    measured: dict[int, dict[int, list[float]]] | None,
    log: Callable[[str], None],
    out: Path,
) -> tuple[dict[int, dict[str, Any]], list[int]]:
    """The references already on disk (in the cache, or carried in the study directory
    ``out``), and the lesions whose reference must be computed."""
    if measured is not None:
        log("truth: measured positions from --measured; no reference computed")
        return {}, []
    references, waiting = {}, []
    for lesion in lesions:
        path = reference_path(spec, scene, lesion)
        carried = out / CARRIED_REFERENCES_DIR / path.name
        if path.exists():
            references[lesion] = json.loads(path.read_text())
            _carry_reference(out, path, references[lesion])
        elif carried.exists():
            references[lesion] = json.loads(carried.read_text())
        else:
            waiting.append(lesion)
            continue
        _log_reference(spec, lesion, references[lesion], False, log)
    return references, waiting


def _carry_reference(out: Path, cached: Path, record: dict[str, Any]) -> None:
    """Keep a copy of a reference (named as its cache file, by its key) in ``out``."""
    carried = out / CARRIED_REFERENCES_DIR / cached.name
    if carried.exists():
        return
    carried.parent.mkdir(exist_ok=True)
    handle, temporary = tempfile.mkstemp(dir=carried.parent, suffix=".tmp")
    with os.fdopen(handle, "w") as file:
        file.write(strict_json(record))
    readable(Path(temporary))
    os.replace(temporary, carried)


def _log_reference(
    spec: StudySpec, lesion: int, record: dict[str, Any], fresh: bool, log: Callable[[str], None]
) -> None:
    found = record.get("instability")
    log(
        f"reference lesion {lesion} ({level_label(spec.reference_level)}): "
        + (f"computed in {record['wall_s']:.1f} s" if fresh else "cached")
        + (
            " (resumed after step " + ", ".join(map(str, record["resumed_after"])) + ")"
            if fresh and record.get("resumed_after")
            else ""
        )
        + (
            f"; it stopped at step {found['step']} ({found['kind']}: {found['detail']}), "
            f"so it holds {len(record['tracked_m'])} of {len(spec.depths_m)} depths"
            if found
            else ""
        )
    )


def _reference_task(spec: StudySpec, lesion: int) -> tuple[dict[str, Any], bool]:
    return load_or_compute_reference(spec, scene_for(spec), lesion)


def _run_all(
    tasks: list[_Task], spec: StudySpec, submit: Callable[..., Future[Any]], window: int
) -> Iterator[tuple[_Task, Any, Exception | None]]:
    """Yield each task with its result, or the exception it raised, as it finishes (at most
    ``window`` in flight): one task's bug must not take the others' work with it."""
    pending: dict[Future[Any], _Task] = {}
    queue = list(tasks)
    while queue or pending:
        while queue and len(pending) < window:
            task = queue.pop(0)
            function = run_cell if task[0] == "cell" else _reference_task
            pending[submit(function, spec, task[1])] = task
        finished, _ = wait(pending, return_when=FIRST_COMPLETED)
        for future in finished:
            task = pending.pop(future)
            try:
                result = future.result()
            except Exception as error:  # noqa: BLE001 - reported by the caller
                yield task, None, error
            else:
                yield task, result, None


class _Immediate(Future[Any]):
    """A future already resolved: the one-worker executor runs tasks when submitted."""

    def __init__(self, function: Callable[..., Any], *args: Any) -> None:
        super().__init__()
        try:
            self.set_result(function(*args))
        except BaseException as error:  # noqa: BLE001 - re-raised by result()
            self.set_exception(error)


class _executor:  # noqa: N801 - used as a context manager like a function
    """A ``submit(function, *args) -> Future`` for in-process, process-pool or Ray runs."""

    def __init__(self, workers: int, ray_address: str | None) -> None:
        self.workers = workers
        self.ray_address = ray_address
        self._pool: ProcessPoolExecutor | None = None

    def __enter__(self) -> Callable[..., Future[Any]]:
        if self.ray_address is not None:
            from agents.lab.study.ray_backend import ray_submitter

            return ray_submitter(self.ray_address, self.workers)
        if self.workers == 1:
            return _Immediate
        import multiprocessing

        from agents.lab.study.worker import init_worker

        self._pool = ProcessPoolExecutor(
            max_workers=self.workers,
            mp_context=multiprocessing.get_context("spawn"),
            initializer=init_worker,
            initargs=(self.workers, os.getpid()),
        )
        return self._pool.submit

    def __exit__(self, kind: type[BaseException] | None, *rest: object) -> None:
        if self._pool is None:
            return
        if kind is None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            return
        # Interrupted (Ctrl-C) or failed: what is finished is on disk; do not wait for the
        # cells in hand (minutes on fine levels). The workers ignore SIGINT (their tracebacks
        # would bury the one line saying what was kept): they are ended here.
        processes = list((getattr(self._pool, "_processes", None) or {}).values())
        for process in processes:
            process.terminate()
        for process in processes:
            process.join(timeout=10)
        self._pool.shutdown(wait=True, cancel_futures=True)  # prompt: its workers are gone


def _progress_bar(total: int, enabled: bool) -> Any:
    """A bar over ``total`` units of work, showing the share done and the time left."""
    from tqdm import tqdm

    return tqdm(
        total=total,
        disable=not enabled,
        desc="study",
        bar_format="{desc}: {percentage:3.0f}%|{bar}| {elapsed}<{remaining}, {postfix}",
        dynamic_ncols=True,
    )


def study_lesions(spec: StudySpec, scene: StudyScene) -> tuple[int, ...]:
    """The lesions the study runs: ``spec.lesions`` (checked against the scene's) or all."""
    lesions = spec.lesions if spec.lesions is not None else scene.lesion_ids
    unknown = sorted(set(lesions) - set(scene.lesion_ids))
    if unknown:
        raise ConfigError(
            f"lesion(s) {unknown} not in the {scene.name} scene; choose from "
            f"{list(scene.lesion_ids)}"
        )
    return tuple(lesions)
