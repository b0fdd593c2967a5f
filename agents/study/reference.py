"""The study's ground truth: a converged solution, or measured positions from a CSV.

The published data holds no measured lesion positions under compression, so by default
each lesion's tracked point is scored against a reference computed once per scene, lesion
and reference level and cached on disk: Lagrange-multiplier contact (exact, no
penetration) solved quasi-statically -- static equilibrium at every probe pose, Newton to a
relative residual of 1e-5 -- with the probe advanced in 1 mm increments along the same path
as the cells. Settled cells are static equilibria too, so the two compare like for like.

The increments must follow the path closely: under a deep press the phantom has more than
one static equilibrium for the same probe pose (the tissue can settle shifted sideways under
the frictionless probe), and the quasi-static solve lands on the one nearest where the last
increment left it. Measured on the 4,126-tet level, all ten lesions: 2 mm increments put
four lesions' tracked points on another equilibrium at one or two depths, 0.47-2.03 mm from
where 1 mm, 0.5 mm and 0.2 mm increments all agree (to 1e-6 m), the force differing by up
to 3 % (lesion 1 at 20 mm: 3.192 N against 3.294 N); the probe's own path at 0.2 mm per
step, settled long enough, reaches the latter too (within 0.08 mm). 1 mm costs about 1.3 x
the time of 2 mm.

Known limit: on the published scene's real poses, which tilt the probe as well as press, the
quasi-static reference and the cells' dynamic path settle on different equilibria from the
second pose on. Lesion 1 on the scene's own mesh: robust LM is 0.001 / 3.03 / 3.29 / 6.57 mm
from its reference (forces 1.087 / 2.230 / 2.670 / 3.244 N against 1.087 / 2.614 / 3.102 /
1.772 N), with the reference converged in its increments (1, 0.5 and 0.25 mm agree to 1e-6 m)
and the cell held up to 1,500 steps until no node moved faster than 0.01 mm/s. Scores on that
scene measure this parting as much as the methods' error.

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

from agents.compress import run_compression
from agents.study.cell import STUDY_LIMITS
from agents.study.scenes import StudyScene
from agents.study.spec import StudySpec, level_label
from tissue.contact.base import ContactMethod
from tissue.contact.lagrange import LagrangeParams
from tissue.contact.stability import StabilityMonitor
from tissue.errors import ConfigError
from tissue.phantom import mesh_cache_dir
from tissue.probe import parse_probe_spec
from tissue.simulator import SimulationConfig

#: Bump when the reference computation changes.
REFERENCE_VERSION = 4
REFERENCE_TOLERANCE = 1e-5
#: The probe's advance per quasi-static solve [m] (see the module docstring for why not 2 mm).
REFERENCE_INCREMENT_M = 0.001
REFERENCE_MAX_ITERATIONS = 60
#: A reference is computed once, offline: its steps may take minutes (a 2 mm quasi-static
#: step on the 176k level took 30-70 s here, more on a loaded machine; the cells' 120 s limit
#: timed out the first references). An hour still ends a hung solve.
REFERENCE_LIMITS = replace(STUDY_LIMITS, step_timeout_s=3600.0)


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
    record = compute_reference(spec, scene, lesion)
    if (record["instability"] or {}).get("kind") == "timeout":
        return record, True  # the machine's load, not the physics: not cached
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
    with os.fdopen(handle, "w") as file:
        json.dump(record, file)
    os.replace(temporary, path)  # atomic: a concurrent reader never sees half a file
    return record, True


def compute_reference(spec: StudySpec, scene: StudyScene, lesion: int) -> dict[str, Any]:
    """Run the converged quasi-static LM experiment for ``lesion`` on the reference level."""
    started = time.perf_counter()
    mesh = scene.mesh(spec.reference_level)
    shape = parse_probe_spec("face")
    config = SimulationConfig(
        mode="robust", quasi_static=True, newton_tolerance=REFERENCE_TOLERANCE
    )
    from tissue.contact import make_contact_model
    from tissue.material import TissueMaterials

    model = make_contact_model(
        ContactMethod.LM,
        mesh,
        shape,
        materials=TissueMaterials(),
        config=config,
        params=LagrangeParams(max_iterations=REFERENCE_MAX_ITERATIONS),
    )
    start, stops = scene.path(mesh, shape, lesion, spec.depths_m)
    monitor = StabilityMonitor(ContactMethod.LM, mesh.nodes, start.position, REFERENCE_LIMITS)
    run = run_compression(model, start, stops, REFERENCE_INCREMENT_M / model.dt, monitor=monitor)
    assert mesh.landmarks is not None
    tracked = mesh.landmarks.names.index(scene.landmark_name(lesion))
    return {
        "lesion": lesion,
        "level": spec.reference_level,
        "level_label": level_label(spec.reference_level),
        "tets": mesh.tet_count,
        "depths_m": [stop.depth_m for stop in stops],
        "tracked_m": [level["landmarks"][tracked] for level in run["levels"]],
        "force_normal_n": [level["force_normal_n"] for level in run["levels"]],
        "level_status": [level["status"] for level in run["levels"]],
        "instability": run["instability"],
        "wall_s": time.perf_counter() - started,
        "method": "lm, robust, quasi-static",
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
            "per lesion and depth (see agents/study/reference.py)"
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
