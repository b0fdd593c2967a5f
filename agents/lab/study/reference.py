"""The study's ground truth: a converged solution, or measured positions from a CSV.

The published data holds no measured lesion positions under compression, so by default
each lesion's tracked point is scored against a reference computed once per scene, lesion
and reference level and cached on disk, with Lagrange-multiplier contact (exact, no
penetration) and Newton to a relative residual of 1e-5, along the same probe path as the
cells. It is one of two kinds (``StudySpec.reference_kind``, ``--reference-kind``):

* **dynamic** (the default): the cells' own experiment -- the probe driven at the study's
  speed with the cells' time step, damping and hold at each depth -- on the reference
  level, with Newton to the tight tolerance. What it differs from a cell in is then only
  what eq. (12) is meant to measure: the mesh and the solver.
* **quasi-static**: static equilibrium at every probe pose, the probe advanced in 1 mm
  increments (2 mm put four of ten lesions on another equilibrium at the 4,126-tet level,
  0.47-2.03 mm away, where 1, 0.5 and 0.2 mm increments agree to 1e-6 m).

Why two, and why dynamic by default. Under a deep press the phantom has more than one
static equilibrium for the same probe pose (the tissue can settle shifted sideways under the
frictionless probe), and which one a run ends on depends on the path it took. On the
published scene's real poses, which tilt the probe as well as press, the quasi-static path
lands elsewhere: lesion 1 on the scene's own mesh (9,295 tets), robust LM driven
dynamically is 0.012 / 2.99 / 3.26 / 7.51 mm from the quasi-static solution at the four
poses (forces 1.088 / 2.232 / 2.676 / 3.650 N against 1.087 / 2.614 / 3.102 / 1.772 N), with
the quasi-static one converged in its increments (1, 0.5 and 0.25 mm agree to 1e-6 m); against
the dynamic reference on the same mesh the robust LM cell is within 0.001 mm at all four
poses, what the solver tolerance leaves. On the built-in phantom's straight presses the two
mostly agree -- lesion 2 at 12,861 tets: 0.008 / 0.036 / 0.058 / 0.057 mm apart at the four
depths, forces within 0.4 %; lesion 3 at 26,220 tets: 0.007 / 0.013 / 0.028 / 0.675 mm,
forces within 2 % -- but the quasi-static path is the dearer one, the more so on fine meshes,
where a deep press reaches limits of the static path that a 1 mm increment must be relaxed
across (at 176,506 tets neither lesion 2's nor lesion 3's quasi-static reference had reached
its first depth after two hours of a loaded machine, stuck in one increment of the first
leg; lesion 1's whole quasi-static reference took 3,485 s), where the dynamic one's inertia keeps
every step definite. One run each on a loaded machine: 12,861 tets, lesion 2, dynamic 65 s
against quasi-static 139 s; 26,220 tets, lesion 3, 242 s against 688 s.

The dynamic reference holds as long as the cells (``StudySpec.settle_steps``), so both stop
at the same moment of the experiment. At the published scene's lesion 1, fourth pose, that
is not yet rest: the tissue creeps sideways under the frictionless probe for another 28 s
(1,660 steps in all before no node moves faster than 0.01 mm/s; the force falls from 3.65 to
3.24 N and the tracked point moves 1.35 mm). A study that wants the resting state there
passes a longer ``--settle-steps``, which both then follow.

Measured positions (``--measured FILE.csv``) replace it. The CSV has a header and one row
per lesion and depth::

    lesion,depth_index,x_m,y_m,z_m
    1,1,0.0123,-0.0045,0.0571

``depth_index`` counts the experiment's depths from 1; coordinates are metres in the
scene's frame.
"""

from __future__ import annotations

import csv
import hashlib
import json
import os
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from agents.lab.compress import SETTLED_SPEED_M_S, CompressionProgress, run_compression
from agents.lab.study.cell import STUDY_LIMITS
from agents.lab.study.scenes import StudyScene
from agents.lab.study.spec import ReferenceKind, StudySpec, level_label
from tissue import ConfigError
from tissue.lab import (
    LagrangeParams,
    SimulationConfig,
    StabilityMonitor,
    mesh_cache_dir,
    parse_probe_spec,
)

#: Bump when the reference computation changes (5: quasi-static LM's contact tangent, which
#: completes references that stalled or diverged before and were cached as such).
REFERENCE_VERSION = 5
#: The two kinds of reference (see the module docstring).
QUASI_STATIC = ReferenceKind.QUASI_STATIC.value
DYNAMIC = ReferenceKind.DYNAMIC.value
REFERENCE_TOLERANCE = 1e-5
#: The probe's advance per quasi-static solve [m] (see the module docstring for why not 2 mm).
REFERENCE_INCREMENT_M = 0.001
REFERENCE_MAX_ITERATIONS = 60
#: A reference is computed once, offline: its steps may take minutes (a 2 mm quasi-static
#: step on the 176k level took 30-70 s here, more on a loaded machine; the cells' 120 s limit
#: timed out the first references). An hour still ends a hung solve.
REFERENCE_LIMITS = replace(STUDY_LIMITS, step_timeout_s=3600.0)


def reference_kind(spec: StudySpec) -> str:
    """:data:`DYNAMIC` or :data:`QUASI_STATIC`, as ``spec`` asks."""
    return spec.reference_kind.value


def reference_key(spec: StudySpec, scene: StudyScene, lesion: int) -> str:
    """The cache key of one lesion's reference: the scene's data, the level, the probe's
    path (every pose, so a change in how paths are planned is a new key) and the solver."""
    start, stops = scene.path(
        scene.mesh(spec.reference_level), parse_probe_spec("face"), lesion, spec.depths_m
    )
    poses = [start] + stops
    path = ";".join(
        ",".join(f"{v:.9f}" for v in (*w.position, *w.quat_wxyz, w.depth_m or 0.0)) for w in poses
    )
    parts = [
        f"v{REFERENCE_VERSION}",
        scene.fingerprint(),
        f"lesion{lesion}",
        f"level{spec.reference_level}",
        path,
        f"tol{REFERENCE_TOLERANCE:g}",
        f"inc{REFERENCE_INCREMENT_M:g}",
    ]
    if reference_kind(spec) == DYNAMIC:
        parts[-1] = (
            f"dynamic-speed{spec.speed_m_s:g}-dt{SimulationConfig().tissue_dt:g}"
            f"-hold{spec.settle_steps}-{SETTLED_SPEED_M_S:g}"
        )
    return hashlib.sha256("|".join(parts).encode()).hexdigest()[:20]


def reference_path(spec: StudySpec, scene: StudyScene, lesion: int) -> Path:
    return mesh_cache_dir() / "references" / f"reference-{reference_key(spec, scene, lesion)}.json"


def load_or_compute_reference(
    spec: StudySpec, scene: StudyScene, lesion: int
) -> tuple[dict[str, Any], bool]:
    """The lesion's reference record, and whether it was computed now (False: cached)."""
    path = reference_path(spec, scene, lesion)
    if path.exists():
        return json.loads(path.read_text()), False
    progress = partial_path(path)
    record = compute_reference(spec, scene, lesion, progress)
    if not keepable(record):
        # Cut short by the machine's load: keep the progress, which a rerun resumes from.
        return record, True
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
    with os.fdopen(handle, "w") as file:
        json.dump(record, file)
    os.replace(temporary, path)  # atomic: a concurrent reader never sees half a file
    progress.unlink(missing_ok=True)
    return record, True


def keepable(record: dict[str, Any]) -> bool:
    """Whether a reference may be cached and reused: not one a step time-out cut short
    (the machine's load, not the physics)."""
    return (record["instability"] or {}).get("kind") != "timeout"


def partial_path(path: Path) -> Path:
    """Where the reference cached at ``path`` keeps its progress while being computed."""
    return path.with_name(path.stem + ".partial.npz")


#: How often a reference saves its progress between depths [s] (see compute_reference).
_PROGRESS_EVERY_S = 120.0


def _save_progress(
    path: Path, progress: CompressionProgress, elapsed_s: float, resumed: list[int]
) -> None:
    """Write ``progress`` atomically (a kill mid-write leaves the last complete one)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    record = {
        "stops_done": progress.stops_done,
        "stop_motion_done": progress.stop_motion_done,
        "settle_done": progress.settle_done,
        "level_status": progress.level_status,
        "motion_done": progress.motion_done,
        "steps": progress.steps,
        "depths": progress.depths,
        "elapsed_s": elapsed_s,
        "resumed_after": resumed,
    }
    arrays: dict[str, Any] = {f"state_{k}": v for k, v in progress.model_state.items()}
    arrays["record"] = np.array(json.dumps(record))
    handle, temporary = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
    with os.fdopen(handle, "wb") as file:
        np.savez(file, **arrays)
    os.replace(temporary, path)


def _load_progress(path: Path) -> tuple[CompressionProgress, float, list[int]] | None:
    """The progress saved at ``path``, or None (none, or unreadable: start afresh)."""
    if not path.exists():
        return None
    try:
        with np.load(path) as saved:
            record = json.loads(str(saved["record"]))
            state = {
                name.removeprefix("state_"): saved[name]
                for name in saved.files
                if name.startswith("state_")
            }
        # Saved before depths were called depths: their key was "levels".
        depths = record["depths"] if "depths" in record else record["levels"]
        progress = CompressionProgress(
            record["stops_done"], record["motion_done"], record["steps"], depths, state,
            record["stop_motion_done"], record["level_status"], record.get("settle_done", 0),
        )  # fmt: skip
        return progress, float(record["elapsed_s"]), list(record["resumed_after"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def compute_reference(
    spec: StudySpec, scene: StudyScene, lesion: int, progress_path: Path | None = None
) -> dict[str, Any]:
    """Run the converged LM experiment for ``lesion`` on the reference level, of the
    spec's :func:`reference_kind`.

    With ``progress_path`` it saves its progress there after each depth and every
    :data:`_PROGRESS_EVERY_S` between (after a step), and, if it finds progress saved there,
    resumes from it: on the 176,506-tet level a reference takes about an hour (a
    quasi-static one of lesions 2 and 3, hours: one 1 mm increment needs relaxing, at
    1/16 mm), and a killed study loses at most the step in flight and the two minutes before
    it (one relaxed quasi-static step can itself take an hour there). ``wall_s`` is the
    compute behind the result: each earlier run's time up to its last save, plus this run's;
    ``resumed_after`` lists how many steps had been taken at each resumption. The file is
    removed once the reference is complete. A resumed reference agrees with an uninterrupted
    one to the solver tolerance (the kept factorisation is rebuilt)."""
    started = time.perf_counter()
    saved = _load_progress(progress_path) if progress_path is not None else None
    resume, before_s, resumed = (None, 0.0, []) if saved is None else saved
    if resume is not None:
        resumed = [*resumed, len(resume.steps)]
    kind = reference_kind(spec)
    mesh = scene.mesh(spec.reference_level)
    shape = parse_probe_spec("face")
    config = SimulationConfig(
        mode="robust", quasi_static=kind == QUASI_STATIC, newton_tolerance=REFERENCE_TOLERANCE
    )
    from tissue import TissueMaterials
    from tissue.lab import make_contact_model

    model = make_contact_model(
        "lm",
        mesh,
        shape,
        materials=TissueMaterials(),
        config=config,
        params=LagrangeParams(max_iterations=REFERENCE_MAX_ITERATIONS),
    )
    start, stops = scene.path(mesh, shape, lesion, spec.depths_m)
    monitor = StabilityMonitor("lm", mesh.nodes, start.position, REFERENCE_LIMITS)
    # Quasi-static: one solve per 1 mm increment, each already at rest, so the hold's length
    # does not matter (references at 623 / 2,539 / 4,126 tets came out bit-identical with
    # holds of 50 and 250 steps); dynamic: the cells' speed and hold.
    speed = REFERENCE_INCREMENT_M / model.dt if kind == QUASI_STATIC else spec.speed_m_s

    last_saved = time.perf_counter()

    def keep(progress: CompressionProgress) -> None:
        # Every depth, and mid-way at most every _PROGRESS_EVERY_S (a 176k save is 1.6 MB).
        nonlocal last_saved
        now = time.perf_counter()
        if progress.stop_motion_done and now - last_saved < _PROGRESS_EVERY_S:
            return
        assert progress_path is not None
        _save_progress(progress_path, progress, before_s + now - started, resumed)
        last_saved = now

    run = run_compression(
        model,
        start,
        stops,
        speed,
        monitor=monitor,
        max_settle_steps=spec.settle_steps,
        resume=resume,
        on_progress=keep if progress_path is not None else None,
    )
    assert mesh.landmarks is not None
    tracked = mesh.landmarks.names.index(scene.landmark_name(lesion))
    return {
        "lesion": lesion,
        "level": spec.reference_level,
        "level_label": level_label(spec.reference_level),
        "tets": mesh.tet_count,
        "depths_m": [stop.depth_m for stop in stops],
        "tracked_m": [depth["landmarks"][tracked] for depth in run["depths"]],
        "force_normal_n": [depth["force_normal_n"] for depth in run["depths"]],
        "level_status": [depth["status"] for depth in run["depths"]],
        "instability": run["instability"],
        "wall_s": before_s + time.perf_counter() - started,
        "resumed_after": resumed,
        "method": f"lm, robust, {kind}",
        "kind": kind,
        "tolerance": REFERENCE_TOLERANCE,
    }


def read_measured_csv(path: Path) -> dict[int, dict[int, list[float]]]:
    """Measured tracked points: ``{lesion: {depth_index: [x, y, z] [m]}}``."""
    try:
        text = Path(path).read_text()
    except OSError as error:
        raise ConfigError(f"--measured {path}: cannot read it ({error})") from None
    rows = list(csv.DictReader(text.splitlines()))
    expected = {"lesion", "depth_index", "x_m", "y_m", "z_m"}
    if not rows or not expected <= set(rows[0]):
        raise ConfigError(
            f"--measured {path}: expected a header with columns {sorted(expected)} and one row "
            "per lesion and depth (see agents/lab/study/reference.py)"
        )
    measured: dict[int, dict[int, list[float]]] = {}
    for number, row in enumerate(rows, start=2):
        try:
            lesion, index = int(row["lesion"]), int(row["depth_index"])
            point = [float(row["x_m"]), float(row["y_m"]), float(row["z_m"])]
        except (TypeError, ValueError):
            raise ConfigError(f"--measured {path}, line {number}: not numbers: {row}") from None
        if index < 1:
            raise ConfigError(f"--measured {path}, line {number}: depth_index counts from 1")
        measured.setdefault(lesion, {})[index] = point
    return measured
