"""One cell of the study: build the model, run the experiment, summarise it as a record."""

from __future__ import annotations

import dataclasses
import functools
import os
import platform
import subprocess
import time
from pathlib import Path
from typing import Any

import numpy as np

from agents.lab.compress import build_model, run_compression
from agents.lab.study.scenes import StudyScene, open_scene
from agents.lab.study.spec import Cell, StudySpec
from tissue import ContactModel, TissueSpec, make_tissue
from tissue.lab import (
    PBDConfig,
    StabilityLimits,
    StabilityMonitor,
    TetMesh,
    parse_probe_spec,
    profile_choices,
)

#: The study's instability detector: every check of :mod:`tissue.contact.stability` but the
#: landmark jump, which frictionless contact on the sloped phantom also trips physically
#: (the tissue slipping out from under the probe; the largest jump is recorded instead), and
#: the skin's facets in the probe (``penetrated``: a physical failure the paper did not
#: count; the skin's depth is recorded per depth instead).
STUDY_LIMITS = StabilityLimits(landmark_jump_margin_m=None, penetrated_is_unstable=False)

# Scenes opened in this process (a worker runs many cells of one scene), by scene and skin.
_SCENES: dict[tuple[str, float | None], StudyScene] = {}


def scene_for(spec: StudySpec) -> StudyScene:
    """The study's scene, with its skin at the spec's resolution."""
    key = (spec.scene, spec.collision_edge_m)
    if key not in _SCENES:
        _SCENES[key] = open_scene(spec.scene, spec.collision_edge_m)
    return _SCENES[key]


def run_cell(spec: StudySpec, cell: Cell, tissue_spec: TissueSpec | None = None) -> dict[str, Any]:
    """Run one experiment; returns its ``results.jsonl`` record (errors are added later).

    The record holds the cell, the mesh size, the tracked point of the cell's lesion at rest
    and after settling at each depth reached [m], the normal force [N] and penetration [m]
    there, a summary of the per-step compute times [ms], the stability percentage and the
    instability met (None when the experiment completed).

    ``tissue_spec``: run the cell's protocol on that tissue instead of the study's own
    configuration (the kinematic twin of an environment's tissue, for ``--robot``); its
    mesh must be the cell's level and it is stepped without sleeping. The record's
    ``tissue`` says which: ``"study"`` or ``"environment"``.
    """
    started = time.perf_counter()
    scene = scene_for(spec)
    mesh = scene.mesh(cell.level)
    if tissue_spec is None:
        model, shape = _study_model(scene, mesh, cell)
    else:
        tissue = make_tissue(dataclasses.replace(tissue_spec, sleep_speed_m_s=None))
        if not np.array_equal(tissue.rest_nodes_m, mesh.nodes):
            raise ValueError(
                f"the tissue spec's mesh ({tissue_spec.mesh!r}) is not the study's level "
                f"{cell.level} mesh of scene {scene.name}"
            )
        if (tissue.spec.contact, tissue.spec.profile) != (cell.method, cell.config.value):
            raise ValueError(
                f"the tissue spec's contact and profile ({tissue.spec.contact}, "
                f"{tissue.spec.profile}) are not cell {cell.key}'s"
            )
        model, shape = tissue.contact_model, tissue.probe_shape
    start, stops = scene.path(mesh, shape, cell.lesion, spec.depths_m)
    monitor = StabilityMonitor(cell.method, mesh.nodes, start.position, STUDY_LIMITS)
    run = run_compression(
        model, start, stops, spec.speed_m_s, monitor=monitor, max_settle_steps=spec.settle_steps
    )
    assert mesh.landmarks is not None
    tracked = mesh.landmarks.names.index(scene.landmark_name(cell.lesion))
    step_ms = np.array([step["compute_ms"] for step in run["steps"]], dtype=np.float64)
    instability = run["instability"]
    return {
        "key": cell.key,
        "scene": scene.name,
        "tissue": "study" if tissue_spec is None else "environment",
        "config": cell.config.value,
        "method": cell.method,
        "level": cell.level,
        "tets": mesh.tet_count,
        "nodes": mesh.node_count,
        "lesion": cell.lesion,
        "depths_m": [stop.depth_m for stop in stops],
        "rest_tracked_m": mesh.landmarks.rest_positions[tracked].tolist(),
        "tracked_m": [depth["landmarks"][tracked] for depth in run["depths"]],
        "force_normal_n": [depth["force_normal_n"] for depth in run["depths"]],
        "penetration_max_m": [depth["penetration_max_m"] for depth in run["depths"]],
        # The skin's facets in the probe (the skin's own measure, judged apart: see
        # STUDY_LIMITS).
        "skin_penetration_m": [depth["skin_penetration_m"] for depth in run["depths"]],
        "step_ms": summarise_times(step_ms),
        "landmark_jump_max_m": landmark_jump_beyond_probe(run["steps"]),
        "stability_percent": run["stability_percent"],
        "status": "ok" if instability is None else "unstable",
        "instability": instability,
        "wall_s": time.perf_counter() - started,
        # The machine's load as the cell ended: its times depend on it (measured here: the
        # same cell at 1,303 tets 20 x slower beside a full load).
        "load_average": os.getloadavg()[0],
        "host": platform.node(),
        "pid": os.getpid(),
        "revision": source_revision(),
    }


def _study_model(scene: StudyScene, mesh: TetMesh, cell: Cell) -> tuple[ContactModel, Any]:
    """The study's own contact model for ``cell`` and its probe's shape."""
    shape = parse_probe_spec("face")
    prescribed = cell.method == "prescribed"
    online = prescribed and profile_choices(cell.config).online_prescribed
    node_set = scene.prescribed_nodes(mesh, cell.lesion) if prescribed and not online else None
    # The study's own configurations, fixed (its published results were computed with them):
    # robust prescribed online and sticking, PBD with the constants calibrated at 4,126 tets.
    model = build_model(
        mesh,
        shape,
        cell.method,
        cell.config.value,
        None,
        None,
        online if prescribed else None,
        node_set,
        pbd_config=PBDConfig.for_profile(cell.config.value),
    )
    return model, shape


@functools.cache
def source_revision() -> str | None:
    """The git commit the code ran from (``+dirty`` with uncommitted changes), or None
    outside a checkout of this project: a study resumed across sessions can then tell which
    cells ran on which code."""
    root = Path(__file__).resolve().parents[2]

    def git(*args: str) -> str:
        return subprocess.run(
            ["git", "-C", str(root), *args],
            capture_output=True,
            text=True,
            timeout=10,
            check=True,
        ).stdout.strip()

    try:
        # An installed copy inside some other repository must not report that one's commit.
        if Path(git("rev-parse", "--show-toplevel")).resolve() != root:
            return None
        head = git("rev-parse", "--short=12", "HEAD")
        dirty = git("status", "--porcelain", "--untracked-files=no")
    except (OSError, subprocess.SubprocessError):
        return None
    return head + ("+dirty" if dirty else "") if head else None


def summarise_times(step_ms: np.ndarray) -> dict[str, float | int]:
    """Median, mean, 10th/90th percentile, max and count of per-step times [ms]."""
    if step_ms.size == 0:
        return {"count": 0}
    return {
        "median": float(np.median(step_ms)),
        "mean": float(np.mean(step_ms)),
        "p10": float(np.percentile(step_ms, 10)),
        "p90": float(np.percentile(step_ms, 90)),
        "max": float(np.max(step_ms)),
        "count": int(step_ms.size),
    }


def landmark_jump_beyond_probe(steps: list[dict[str, Any]]) -> float:
    """Largest one-step landmark motion beyond the probe's motion in that step [m] (>= 0)."""
    if len(steps) < 2:
        return 0.0
    landmarks = np.array([step["landmarks"] for step in steps], dtype=np.float64)
    probe = np.array([step["probe_pos"] for step in steps], dtype=np.float64)
    jumps = np.linalg.norm(np.diff(landmarks, axis=0), axis=2).max(axis=1)
    probe_motion = np.linalg.norm(np.diff(probe, axis=0), axis=1)
    excess = np.nan_to_num(jumps - probe_motion, nan=np.inf)
    return float(max(0.0, excess.max()))
