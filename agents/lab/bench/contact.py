"""``probegym bench contact``: cost and outcome of each contact strategy, per mesh level.

What is measured: the default linear probe (:func:`tissue.probe.linear_probe`: the
published face backed by the probe's housing, as ``probegym compress``, the study and the
hard cases use; the bare 2.7 mm face plate let paper LM push a tissue point through to its
back, where the contact force pulls the probe down: -0.23 N at the end of the 4,141-tet run),
pressing straight down (-z) into the apex of the built-in breast phantom at the paper's
0.01 m/s (0.2 mm per 0.02 s tissue step), starting 0.1 mm clear of the skin and going on for
``steps`` steps after the first step with contact (50 steps: 10 mm beyond first contact).
Every strategy sees the same probe path. Per method, mode and level one record:

- ``step_ms``: median wall time of one :meth:`ContactModel.step` over the steps in
  contact [ms] (steps before contact are cheaper and are left out);
- ``step_ms_mean``: their mean [ms]: what a run costs per step, refactorisations included
  (a kept factorisation is refreshed every few steps; the median leaves those steps out);
- ``step_ms_max``: the slowest step in contact [ms] (a few slow steps hide in a median);
- ``penetration_max_m``: the deepest collision-surface point inside the probe over the
  whole run [m] (LM and prescribed keep it near zero by construction; penalty trades it
  against its stiffness);
- ``force_n``: the normal (+z, the pressing axis) force on the probe at the final depth [N];
- ``skin``: the skin's resolution (``paper``: the phantom's own 1,004 triangles, or the
  collision surface's edge, ``2 mm``; ``--skin``), with ``collision_edge_m`` (None for the
  paper's) and ``skin_vertices``;
- ``skin_penetration_max_m``: the deepest point of the skin's facets inside the probe over
  the run [m] (:meth:`tissue.ContactModel.skin_depth`), beside
  ``skin_vertex_penetration_max_m``, its vertices' (what a method holding the vertices
  keeps near zero: a coarse skin's facets cut the probe's rim between them);
- ``force_largest_dip``: the largest fall of the normal force below its running maximum
  over the press, as a fraction of that maximum (0 for a force that never falls: the
  press's smoothness);
- ``status_counts``: how many steps ended with each :class:`tissue.status.StepStatus`;
- ``stopped_by_wall_budget``: the run was cut after :data:`RUN_WALL_BUDGET_S` of steps
  (its force and displacement are then at a shallower depth, ``depth_beyond_contact_m``);
- ``lesion1_displacement_m``: how far lesion landmark 1 (under the apex) moved from rest
  at the final depth [m].

Methods: ``penalty``, ``lm``, ``prescribed`` (online: the node set follows the probe's
footprint, as a user without a pre-computed node set would run it; in robust mode as the
profile runs it, sliding with the skin guarded) and
``pbd`` (paper: 10 substeps; robust: 60, every skin vertex in contact; each calibrated for the
mesh as the front door does, :meth:`tissue.pbd.PBDContact.settings_for`).

The speed targets, printed against the measurements: penalty and prescribed in paper mode
<= 5 ms per step up to 4.1k tets and <= 20 ms (real time at 0.02 s) up to 26k tets; LM <= 2 x
penalty (same mode) at every level up to 26k tets; for every method's robust
mode: a median step <= 20 / 100 / 500 ms on the 4,126 / 26,220 / 176,506-tet levels, every
step ok (``robust_target_step_ms``, ``meets_robust_target``). Times are wall clock on a
shared machine: read ratios taken in one run, not absolute numbers across runs.
"""

from __future__ import annotations

import os
import platform
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from agents.lab.bench.report import BenchRecord, MarkdownTable
from agents.lab.bench.tissue import robust_step_target
from agents.outputs import write_json
from tissue import TissueSpec
from tissue.lab import (
    PAPER_PROBE_SPEED_M_S,
    PAPER_TISSUE_DT_S,
    PHANTOM_LEVELS,
    PBDContact,
    PrescribedParams,
    Probe,
    SimulationConfig,
    breast_phantom,
    linear_probe,
    make_contact_model,
)

DEFAULT_LEVELS = tuple(level for level in PHANTOM_LEVELS if level <= 26220)
DEFAULT_METHODS = ("penalty", "lm", "prescribed", "pbd")
DEFAULT_MODES = ("paper", "robust")
#: The skin resolutions compared by default: the paper's surface and the environments' skin
#: at the probe's scale (:data:`envs.probe_env.COLLISION_EDGE_M`, 2 mm).
DEFAULT_SKINS: tuple[float | None, ...] = (None, 0.002)
# Probe advance per tissue step at the paper's speed and step [m].
STEP_ADVANCE_M = PAPER_PROBE_SPEED_M_S * PAPER_TISSUE_DT_S
# The probe starts this far above the apex [m], so that its first step already touches and
# every timed step is one in contact.
START_CLEARANCE_M = 0.0001
# A run stops once its steps have taken this much wall time [s]; the record says so.
RUN_WALL_BUDGET_S = 120.0
# Steps allowed before contact must have happened (clearance / advance, with margin).
MAX_APPROACH_STEPS = 20
# The paper-mode targets [ms per step] and the tet count up to which the tighter one applies.
TARGET_FAST_MS = 5.0
TARGET_FAST_TETS = 4200
TARGET_REALTIME_MS = 20.0
TARGET_LM_OVER_PENALTY = 2.0
# Steps in contact of the untimed warm-up run of each method and mode.
WARMUP_STEPS = 3


def _apex_probe(mesh: Any) -> Probe:
    """The probe, centred over the mesh's plan-view centre, just above its top, pressing -z."""
    centre = (mesh.nodes[:, :2].min(axis=0) + mesh.nodes[:, :2].max(axis=0)) / 2
    top = float(mesh.nodes[:, 2].max())
    start = np.array([centre[0], centre[1], top + START_CLEARANCE_M])
    return Probe.looking_along(linear_probe(), start, np.array([0.0, 0.0, -1.0]))


def skin_label(collision_edge_m: float | None) -> str:
    """How tables name a skin resolution: ``paper`` or the edge, ``2 mm``."""
    return "paper" if collision_edge_m is None else f"{collision_edge_m * 1e3:g} mm"


#: A step-to-step change of the normal force by more than this share of it is a jump
#: (:func:`largest_step_fall`).
FORCE_JUMP = 0.2


def largest_force_dip(forces: list[float] | NDArray[np.float64], floor_n: float = 0.02) -> float:
    """The largest fall of a force below its running maximum, as a fraction of that maximum
    (0: it never falls), counted once the maximum exceeds ``floor_n`` [N] (first-contact
    noise below it is not a press)."""
    values = np.asarray(forces, dtype=np.float64)
    if values.size == 0:
        return 0.0
    peak = np.maximum.accumulate(values)
    counted = peak > floor_n
    if not np.any(counted):
        return 0.0
    return float(np.max(1.0 - values[counted] / peak[counted]).clip(min=0.0))


def largest_step_fall(
    forces: list[float] | NDArray[np.float64], floor_n: float = 0.02
) -> tuple[float, int]:
    """How a force moves from one step to the next: its largest fall as a fraction of the
    step before (0: it never falls), and the steps where it moved by more than
    :data:`FORCE_JUMP` of the step before, up or down; steps whose force before is at most
    ``floor_n`` [N] (out of contact, first-contact noise) are not counted."""
    values = np.asarray(forces, dtype=np.float64)
    before, after = values[:-1], values[1:]
    counted = before > floor_n
    if not np.any(counted):
        return 0.0, 0
    change = (after[counted] - before[counted]) / before[counted]
    return float(max(0.0, -change.min())), int(np.count_nonzero(np.abs(change) > FORCE_JUMP))


def benchmark_one(
    method: str, mode: str, level: int, steps: int, collision_edge_m: float | None = None
) -> dict[str, Any]:
    """Press the face ``steps`` steps beyond first contact with one method; the JSON record.

    Args:
        method: ``penalty``, ``lm``, ``prescribed`` (run online) or ``pbd``.
        mode: ``paper`` or ``robust``.
        level: phantom level (tet count of :data:`tissue.mesh.phantom.PHANTOM_LEVELS`).
        steps: probe advances of 0.2 mm after the first step in contact.
        collision_edge_m: the skin's edge [m] (:attr:`tissue.TissueSpec.collision_edge_m`);
            None: the paper's surface.
    """
    mesh = breast_phantom(level, collision_edge_m=collision_edge_m)
    shape = linear_probe()
    kwargs: dict[str, Any] = {}
    # PBD as the profile runs it (calibrated for the mesh, its skin contact): the front
    # door's settings for this mesh and skin.
    kwargs["config"] = (
        PBDContact.settings_for(TissueSpec(mesh=mesh, contact="pbd", profile=mode), mesh, None)[0]
        if method == "pbd"
        else SimulationConfig(mode=mode)
    )
    if method == "prescribed":
        kwargs["params"] = (
            PrescribedParams(online=True, sliding=True, skin_guard=True)
            if mode == "robust"
            else PrescribedParams(online=True)
        )
    model = make_contact_model(method, mesh, shape, **kwargs)
    start = _apex_probe(mesh)
    quat = start.quat_wxyz
    direction = np.array([0.0, 0.0, -1.0])
    if mesh.landmarks is None:
        raise ValueError(f"phantom level {level} has no lesion landmarks to track")
    rest_lesion = mesh.landmarks.rest_positions[0]
    load_before = os.getloadavg()[0]

    contact_ms: list[float] = []
    wall_s = 0.0
    stopped = False
    statuses: Counter[str] = Counter()
    penetration_max = 0.0
    skin_max = 0.0
    skin_vertex_max = 0.0
    normal_forces: list[float] = []
    first_contact_step: int | None = None
    step = 0
    result = None
    while True:
        step += 1
        travel = STEP_ADVANCE_M * step
        result = model.step(start.position_world + travel * direction, quat)
        wall_s += result.diagnostics.compute_ms / 1e3
        statuses[result.status.value] += 1
        penetration_max = max(penetration_max, result.method_penetration_m)
        skin_max = max(skin_max, result.skin_penetration_m)
        skin_vertex_max = max(
            skin_vertex_max, float(result.diagnostics.details.get("skin_vertex_penetration_m", 0.0))
        )
        normal_forces.append(float(-direction @ result.force_world_n))
        in_contact = result.contact_count > 0 or bool(np.any(result.force_world_n != 0.0))
        if first_contact_step is None and in_contact:
            first_contact_step = step
        if first_contact_step is not None:
            contact_ms.append(result.diagnostics.compute_ms)
            if step - first_contact_step >= steps:
                break
        elif step >= MAX_APPROACH_STEPS:
            break
        if wall_s > RUN_WALL_BUDGET_S:
            stopped = True
            break
    assert result is not None

    lesion = result.landmarks_world_m[0]
    contact_step = first_contact_step if first_contact_step is not None else step
    return {
        "method": method,
        "mode": mode,
        "level": level,
        "tets": mesh.tet_count,
        "nodes": mesh.node_count,
        "skin": skin_label(collision_edge_m),
        "collision_edge_m": collision_edge_m,
        "skin_vertices": model.skin.count,
        "step_ms": float(np.median(contact_ms)) if contact_ms else float("nan"),
        "step_ms_mean": float(np.mean(contact_ms)) if contact_ms else float("nan"),
        "step_ms_max": float(np.max(contact_ms)) if contact_ms else float("nan"),
        "steps_in_contact": len(contact_ms),
        "penetration_max_m": penetration_max,
        "skin_penetration_max_m": skin_max,
        "skin_vertex_penetration_max_m": skin_vertex_max,
        "force_largest_dip": largest_force_dip(normal_forces),
        "force_n": float(-direction @ result.force_world_n),
        "force_world_n": [float(f) for f in result.force_world_n],
        "depth_beyond_contact_m": STEP_ADVANCE_M * (step - contact_step),
        "status_counts": dict(statuses),
        "stopped_by_wall_budget": stopped,
        "wall_s": wall_s,
        "lesion1_displacement_m": float(np.linalg.norm(lesion - rest_lesion)),
        "lesion1_displacement_world_m": [float(d) for d in lesion - rest_lesion],
        # 1-minute load average before and after: above the core count, times are inflated.
        "load_average": [load_before, os.getloadavg()[0]],
        "cpu_count": os.cpu_count(),
        "threading": threading_environment(),
    }


def threading_environment() -> dict[str, Any]:
    """How our numba kernels were threaded: on a shared 2-core machine the OpenMP layer's
    waiting policy can change parallel kernels' times by orders of magnitude."""
    import numba

    try:
        layer = numba.threading_layer()
    except ValueError:  # no parallel kernel has run yet
        layer = None
    return {
        "numba_threading_layer": layer,
        "numba_num_threads": numba.get_num_threads(),
        "OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY"),
        "KMP_BLOCKTIME": os.environ.get("KMP_BLOCKTIME"),
    }


def _annotate_targets(records: list[dict[str, Any]]) -> None:
    """Add each record's target fields (in place): ``target_step_ms``/``meets_target`` for
    penalty and prescribed in paper mode, ``lm_over_penalty`` for LM records."""
    penalty_ms = {
        (r["mode"], r["level"], r.get("skin", "paper")): r["step_ms"]
        for r in records
        if r["method"] == "penalty"
    }
    for record in records:
        if record["method"] in ("penalty", "prescribed") and record["mode"] == "paper":
            limit = TARGET_FAST_MS if record["tets"] <= TARGET_FAST_TETS else TARGET_REALTIME_MS
            record["target_step_ms"] = limit
            record["meets_target"] = bool(record["step_ms"] <= limit)
        if record["mode"] == "robust":
            # Every step of the run ended ok (converged), and the median in time.
            converged = (
                set(record["status_counts"]) == {"ok"} and not record["stopped_by_wall_budget"]
            )
            record.update(robust_step_target(record["level"], record["step_ms"], converged))
        if record["method"] == "lm":
            reference = penalty_ms.get((record["mode"], record["level"], _row_key(record)[2]))
            if reference:
                ratio = record["step_ms"] / reference
                record["lm_over_penalty"] = ratio
                record["meets_target"] = bool(ratio <= TARGET_LM_OVER_PENALTY)


def _write(records: list[dict[str, Any]], json_path: Path) -> None:
    json_path.parent.mkdir(parents=True, exist_ok=True)
    write_json(records, json_path, indent=2)


def _pivot(
    records: list[dict[str, Any]], levels: list[int], key: str, scale: float, fmt: str
) -> list[str]:
    rows = []
    for method, mode, skin in _row_keys(records):
        cells = []
        for level in levels:
            match = [
                r for r in records if _row_key(r) == (method, mode, skin) and r["level"] == level
            ]
            cells.append(format(match[0][key] * scale, fmt) if match else "-".rjust(9))
        rows.append(f"{method:>10} {mode:>6} {skin:>7} " + " ".join(cells))
    return rows


def _row_key(record: dict[str, Any]) -> tuple[str, str, str]:
    return record["method"], record["mode"], record.get("skin", "paper")


def _row_keys(records: list[dict[str, Any]]) -> list[tuple[str, str, str]]:
    """The tables' rows: method, profile and skin, in the order first measured."""
    return list(dict.fromkeys(_row_key(r) for r in records))


#: The contact benchmark's figures: (caption, record key, scale, format).
_FIGURES = (
    ("median step time in contact [ms]", "step_ms", 1.0, ".2f"),
    ("slowest step in contact [ms]", "step_ms_max", 1.0, ".1f"),
    ("normal force at the final depth [N]", "force_n", 1.0, ".3f"),
    ("largest penetration over the run [mm]", "penetration_max_m", 1e3, ".3f"),
    ("deepest skin facet inside the probe over the run [mm]", "skin_penetration_max_m", 1e3, ".3f"),
    ("largest dip of the normal force over the press [%]", "force_largest_dip", 100.0, ".1f"),
    ("lesion 1 displacement at the final depth [mm]", "lesion1_displacement_m", 1e3, ".2f"),
)


def markdown_tables(records: list[dict[str, Any]], levels: list[int]) -> list[MarkdownTable]:
    """The printed tables as Markdown: one per figure, method and profile by level."""
    tets = {r["level"]: r["tets"] for r in records}
    columns = [f"{level} ({tets[level]:,} tets)" for level in levels if level in tets]
    tables = []
    for caption, key, scale, fmt in _FIGURES:
        table = MarkdownTable(caption, ["method", "profile", "skin", *columns])
        for method, mode, skin in _row_keys(records):
            cells = []
            for level in levels:
                if level not in tets:
                    continue
                match = [
                    r for r in records
                    if _row_key(r) == (method, mode, skin) and r["level"] == level
                ]  # fmt: skip
                cells.append(format(match[0][key] * scale, fmt) if match else "-")
            table.rows.append([method, mode, skin, *cells])
        tables.append(table)
    targets = MarkdownTable(
        "speed targets", ["target", "method / profile", "tets", "measured", "target", ""]
    )
    targets.rows = list(target_rows(records))
    if targets.rows:
        tables.append(targets)
    return tables


def _print_record(record: dict[str, Any]) -> None:
    print(
        f"  {record['tets']:>6} tets {record['method']:>10}/{record['mode']:<6} "
        f"{record['skin']:>7} skin {record['step_ms']:8.2f} ms/step "
        f"(max {record['step_ms_max']:.1f}), F {record['force_n']:.3f} N "
        f"(largest dip {record['force_largest_dip'] * 100:.1f} %), pen "
        f"{record['penetration_max_m'] * 1e3:.3f} mm, skin "
        f"{record['skin_penetration_max_m'] * 1e3:.3f} mm, lesion 1 "
        f"{record['lesion1_displacement_m'] * 1e3:.2f} mm, {record['status_counts']}",
        flush=True,
    )


def print_tables(records: list[dict[str, Any]], levels: list[int]) -> None:
    """Print step time, force and penetration per method/mode (rows) and level (columns),
    then the speed targets against the measurements."""
    tets = {r["level"]: r["tets"] for r in records}
    header = f"{'method':>10} {'mode':>6} {'skin':>7} " + " ".join(
        f"{tets.get(level, level):>9}" for level in levels
    )
    for title, key, scale, fmt in _FIGURES:
        print(f"\n{title} — columns: tets")
        print(header)
        for row in _pivot(records, levels, key, scale, "9" + fmt):
            print(row)
    print("\nnon-ok steps:")
    for record in records:
        bad = {k: v for k, v in record["status_counts"].items() if k != "ok"}
        if bad:
            print(
                f"  {record['method']}/{record['mode']} {record['skin']} skin "
                f"{record['tets']} tets: {bad}"
            )
        if record["stopped_by_wall_budget"]:
            print(
                f"  {record['method']}/{record['mode']} {record['tets']} tets: stopped by the "
                f"{RUN_WALL_BUDGET_S:.0f} s wall budget at "
                f"{record['depth_beyond_contact_m'] * 1e3:.1f} mm"
            )

    print("\nspeed targets")
    for target in target_rows(records):
        print("  {:<13} {:<18} {:>7} tets: {:>10} {:<9} {}".format(*target))


def target_rows(records: list[dict[str, Any]]) -> list[list[str]]:
    """The speed targets against the measurements, one row each: (target, method and
    profile, tets, measured, target, verdict)."""

    def verdict(met: bool) -> str:
        return "met" if met else "MISSED"

    rows = []
    for r in records:
        where = f"{r['method']}/{r['mode']} ({r.get('skin', 'paper')} skin)"
        tets = f"{r['tets']:,}"
        if "target_step_ms" in r:
            limit, met = f"<= {r['target_step_ms']:.0f} ms", verdict(r["meets_target"])
            rows.append(["paper step", where, tets, f"{r['step_ms']:.2f} ms", limit, met])
        if "lm_over_penalty" in r:
            limit, met = f"<= {TARGET_LM_OVER_PENALTY:.0f} x", verdict(r["meets_target"])
            rows.append(["LM / penalty", where, tets, f"{r['lm_over_penalty']:.2f} x", limit, met])
        if "robust_target_step_ms" in r:
            limit = f"<= {r['robust_target_step_ms']:.0f} ms"
            met = verdict(r["meets_robust_target"])
            rows.append(["robust step", where, tets, f"{r['step_ms']:.2f} ms", limit, met])
    return rows


def run_contact_benchmark(
    levels: list[int] | None,
    methods: list[str] | None,
    modes: list[str],
    json_path: Path,
    steps: int = 50,
    command: str | None = None,
    skins: list[float | None] | None = None,
) -> list[dict[str, Any]]:
    """Benchmark every method x mode x skin x level; print tables; write a JSON list of
    records.

    Args:
        levels: phantom levels (tet counts); None: 623 to 26,220.
        methods: any of ``penalty``, ``lm``, ``prescribed``, ``pbd``; None: all four.
        modes: integration modes, ``paper`` and/or ``robust``.
        json_path: where the records go; rewritten after every record.
        steps: probe advances of 0.2 mm after first contact (50: a 10 mm press).
        skins: the skin's resolutions, collision edges [m] or None for the paper's surface;
            None: :data:`DEFAULT_SKINS`.

    Returns:
        The records (see the module docstring for the fields).
    """
    levels = list(levels or DEFAULT_LEVELS)
    methods = list(methods or DEFAULT_METHODS)
    modes = list(modes or DEFAULT_MODES)
    skins = list(DEFAULT_SKINS if skins is None else skins)
    print(
        f"probegym bench contact — face into the apex at 0.01 m/s, {steps} steps "
        f"({steps * STEP_ADVANCE_M * 1e3:.0f} mm) beyond first contact "
        f"({platform.processor() or platform.machine()})"
    )
    # Compile (or load from numba's cache) every kernel the runs use before timing anything.
    for method in methods:
        for mode in modes:
            benchmark_one(method, mode, min(PHANTOM_LEVELS), WARMUP_STEPS)
    records: list[dict[str, Any]] = []
    provenance = BenchRecord("probegym bench contact: step time, force and penetration", command)
    for level in levels:
        for skin in skins:
            for method in methods:
                for mode in modes:
                    record = benchmark_one(method, mode, level, steps, skin)
                    records.append(record)
                    _print_record(record)
                    _annotate_targets(records)
                    _write(records, json_path)  # keep what is measured so far
    print_tables(records, levels)
    markdown = provenance.write(json_path, markdown_tables(records, levels))
    print(f"written: {json_path}, {markdown}")
    return records
