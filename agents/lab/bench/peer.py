"""``probegym bench peer``: our FE tissue against MuJoCo's own flex on the same compression.

The scene, on both sides: one level of the built-in breast phantom (the same nodes and
tets; the base nodes ``mesh.fixed_nodes`` pinned), E = 2850 Pa, 1075 kg/m^3, no gravity, and
a rigid 53 x 13 mm box probe (:class:`tissue.probe.BoxProbe`; a MuJoCo mocap box) that
starts 0.1 mm above the apex and moves straight down (-z) at 0.01 m/s for ``sim_seconds``
(1 s: 10 mm of travel).

What each side is:

- **Ours**: an FE contact model (Lagrange multipliers by default, prescribed
  displacement with ``online=True``, and penalty with its default k_s) with ``tissue_dt``
  = 0.02 s, in ``paper`` mode (one linearised backward-Euler solve, CG capped at 25
  iterations, as the paper) and in ``robust`` mode (Newton to tolerance; exact contact for
  LM and prescribed, penetration within 0.1 mm for penalty). Material: the project's default,
  stable neo-Hookean, nu = 0.49, lesions 4 x stiffer than the tissue, Rayleigh damping
  0.1/s (mass) and 0.1 s (stiffness). Contact is frictionless.
- **MuJoCo**: a ``<flexcomp type="direct" dim="3">`` built in code from our nodes and tets
  (its vertex order is our node order; this is checked at rest), with
  ``<elasticity young="2850" poisson=... damping="0.1"/>`` and ``<pin>`` on our fixed nodes,
  the ``discrete`` integrator at dt = 0.02 s (the only MuJoCo 4.0 integrator that treats
  flex elasticity implicitly: ``implicit``/``implicitfast`` refuse to compile it, and
  explicit ``Euler`` went unstable on the 4.1k-tet level even at dt = 0.3 ms), frictionless
  contact (``condim="1"``), flex radius 0.2 mm, autoreset disabled so that an instability
  shows as NaN instead of a silent reset. The settings tried are :data:`MUJOCO_VARIANTS`;
  the first (CG, nu 0.45, the configuration the issue quotes) is the one ``ratio`` uses.

What MuJoCo cannot match, and which therefore lands in its lesion error: its 3D flex
elasticity is Saint Venant-Kirchhoff (linear stress-strain in Green strain), not
neo-Hookean; one material per flex, so the lesions are not stiffer; flexcomp gives every
point the same mass (total = density x volume) rather than a lumped FE mass; no
mass-proportional damping (flex bodies may not carry joint damping); soft constraint-based
contact (penetration is reported) rather than exact non-penetration.

Accuracy: lesion landmark 1 (under the apex) at the final depth, against our converged
reference: the LM contact model in ``robust`` mode, ``quasi_static=True``, following the
same path in 1 mm increments to the same final depth. For MuJoCo the landmark is
interpolated from the flex vertex positions with the mesh's barycentric embedding. MuJoCo
runs also get ``lesion_error_matched_material_m``: the error against the same quasi-static
reference computed with MuJoCo's own material (uniform, its nu, neo-Hookean), which
separates what MuJoCo's engine gets wrong (soft contact, SVK, its solver) from the material
it cannot represent. Contact softness matters: with MuJoCo's default ``solimp`` the box
sank about 2 mm into the 4.1k-tet flex; the ``-hard`` variant uses (0.99, 0.999, 0.001).

Speed: wall time of the steps only (our ``ContactModel.step``; MuJoCo's ``mj_step``), summed
over the run and divided by the simulated time: milliseconds of computation per simulated
second. ``ratio`` is MuJoCo's over ours (> 1: ours is faster). The ``*_steady`` fields leave
the first step out on both sides. One-time costs are counted on neither side: MuJoCo's is its
compile (``compile_s``), ours the model's construction, which loads the direct solver's
library (:meth:`tissue.sim.integrator.ImplicitIntegrator.prepare`; until it did, a process's first
step took 0.5-3.5 s here, mostly numba loading its cache and pypardiso searching the
environment for MKL, and dominated a 1 s press at 4.1k tets: LM 0.62 x and prescribed 1.34 x
in robust mode, against 1.31 x and 4.19 x since, in runs on one loaded machine), and the
process's loading of our compiled kernels: an untimed warm-up press of the same method, mode
and level (:data:`WARMUP_SIM_S`) precedes each timed one. The timed press still builds its own
model and pays its own first factorisation. Targets: ratio >= 3 in paper mode,
>= 2 in robust mode. Times are wall clock on a shared machine; compare the ratios taken in one
run.
"""

from __future__ import annotations

import math
import os
import platform
import time
from collections import Counter
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from agents.lab.bench.contact import START_CLEARANCE_M, threading_environment
from agents.lab.bench.report import BenchRecord, MarkdownTable
from agents.outputs import write_json
from tissue import NeoHookean, TissueMaterials
from tissue.lab import (
    PAPER_PROBE_SPEED_M_S,
    PAPER_TISSUE_DT_S,
    BoxProbe,
    PrescribedParams,
    Probe,
    SimulationConfig,
    TetMesh,
    breast_phantom,
    make_contact_model,
)

DEFAULT_LEVELS = (623, 4126, 26220)
# Probe face (LX along world x, LZ along world y) and depth behind the face [m].
PROBE_FACE_M = (0.053, 0.013)
PROBE_DEPTH_M = 0.010
# Our methods, the first is the headline one (exact contact); prescribed runs online.
OURS_METHODS = ("lm", "prescribed", "penalty")
OURS_MODES = ("paper", "robust")
# Increment of the quasi-static reference path [m] (0.5 mm changed lesion 1 by ~1e-8 m).
REFERENCE_INCREMENT_M = 0.001
# Material on the MuJoCo side (one per flex).
YOUNG_PA = 2850.0
DENSITY_KG_M3 = 1075.0
# Stiffness-proportional Rayleigh damping [s], as our rayleigh_stiffness.
DAMPING_S = 0.1
FLEX_RADIUS_M = 0.0002
# A run (MuJoCo variant or ours) stops once its steps have taken this much wall time [s]
# (MuJoCo's Newton on fine levels takes seconds per step); its ms per simulated second is
# then from the steps run, and it gets no lesion error.
MUJOCO_WALL_BUDGET_S = 60.0
# Simulated time of the untimed warm-up press of each of our methods and modes [s], on
# each level before its timed press: numba loads a compiled kernel from its disk cache on
# the process's first call of each signature (~3 ms each), and the larger levels take code
# paths the smallest does not (robust mode keeps a factorisation from 3,000 unknowns on;
# on the 4,141-tet level two kernels were still loaded in the timed first step, 29 ms).
WARMUP_SIM_S = 0.2


@dataclass(frozen=True)
class MujocoSettings:
    """One MuJoCo configuration of the flex scene.

    Attributes:
        name: label in tables and JSON.
        integrator: MuJoCo ``option/integrator``.
        solver: ``option/solver`` (``CG`` or ``Newton``; PGS is refused with flex elasticity).
        timestep_s: ``option/timestep`` [s].
        poisson: flex ``elasticity/poisson`` (MuJoCo accepts [0, 0.5)).
        iterations: ``option/iterations`` (solver cap).
        tolerance: ``option/tolerance``.
        contact_solimp: probe-tissue contact impedance (dmin, dmax, width [m]), on both the
            box and the flex; MuJoCo's default is (0.9, 0.95, 0.001), closer to 1 is harder.
    """

    name: str
    integrator: str = "discrete"
    solver: str = "CG"
    timestep_s: float = 0.02
    poisson: float = 0.45
    iterations: int = 100
    tolerance: float = 1e-8
    contact_solimp: tuple[float, float, float] = (0.9, 0.95, 0.001)


MUJOCO_VARIANTS: tuple[MujocoSettings, ...] = (
    MujocoSettings("discrete-CG-nu0.45"),
    MujocoSettings("discrete-CG-nu0.49-hard", poisson=0.49, contact_solimp=(0.99, 0.999, 0.001)),
    MujocoSettings("discrete-Newton-nu0.45", solver="Newton"),
)


def probe_start_position(mesh: TetMesh) -> NDArray[np.float64]:
    """Probe face centre at the start [m], (3,): over the plan-view centre, above the top."""
    centre = (mesh.nodes[:, :2].min(axis=0) + mesh.nodes[:, :2].max(axis=0)) / 2
    return np.array([centre[0], centre[1], float(mesh.nodes[:, 2].max()) + START_CLEARANCE_M])


def flex_mjcf(
    mesh: TetMesh, settings: MujocoSettings, face_start_world: NDArray[np.float64]
) -> str:
    """The MJCF of the phantom as a 3D elastic flex pressed by a mocap box.

    Args:
        mesh: the phantom; flexcomp point i is mesh node i.
        settings: integrator, solver, timestep and Poisson ratio.
        face_start_world: the box's lower (contact) face centre at t = 0 [m], (3,).
    """
    points = " ".join(f"{value:.10g}" for value in mesh.nodes.ravel())
    elements = " ".join(str(int(i)) for i in mesh.tets.ravel())
    pins = " ".join(str(int(i)) for i in mesh.fixed_nodes)
    mass = DENSITY_KG_M3 * float(mesh.tet_volumes().sum())
    half = (PROBE_FACE_M[0] / 2, PROBE_FACE_M[1] / 2, PROBE_DEPTH_M / 2)
    centre = face_start_world + np.array([0.0, 0.0, half[2]])
    solimp = " ".join(f"{v:g}" for v in settings.contact_solimp)
    return f"""<mujoco model="probegym-peer">
  <option timestep="{settings.timestep_s}" integrator="{settings.integrator}"
          solver="{settings.solver}" iterations="{settings.iterations}"
          tolerance="{settings.tolerance}" gravity="0 0 0">
    <flag autoreset="disable"/>
  </option>
  <worldbody>
    <body name="probe" mocap="true" pos="{centre[0]:.10g} {centre[1]:.10g} {centre[2]:.10g}">
      <geom name="probe" type="box" size="{half[0]} {half[1]} {half[2]}" condim="1"
            solimp="{solimp}"/>
    </body>
    <flexcomp name="tissue" type="direct" dim="3" radius="{FLEX_RADIUS_M}" mass="{mass:.10g}"
              point="{points}" element="{elements}">
      <contact condim="1" selfcollide="none" solimp="{solimp}"/>
      <elasticity young="{YOUNG_PA}" poisson="{settings.poisson}" damping="{DAMPING_S}"/>
      <pin id="{pins}"/>
    </flexcomp>
  </worldbody>
</mujoco>"""


def _probe_force_z(mujoco: Any, model: Any, data: Any) -> float:
    """Upward (+z) force of the tissue on the probe [N], summed over its contacts."""
    wrench = np.zeros(6)
    total = 0.0
    for i in range(data.ncon):
        contact = data.contact[i]
        mujoco.mj_contactForce(model, data, i, wrench)
        # frame row 0 is the normal; the normal force is wrench[0] >= 0 along it.
        total += abs(float(wrench[0] * contact.frame[2]))
    return total


def run_mujoco(mesh: TetMesh, settings: MujocoSettings, sim_seconds: float) -> dict[str, Any]:
    """Simulate the press with MuJoCo's flex; timings, status and the final lesion 1.

    Never raises for a MuJoCo failure: compile errors, NaN and bad-acceleration warnings
    become ``status``.
    """
    import mujoco

    # MuJoCo's default warning handler prints and appends to MUJOCO_LOG.TXT in the working
    # directory; collect the messages into the record instead.
    messages: list[str] = []
    previous = mujoco.get_mju_user_warning()
    mujoco.set_mju_user_warning(messages.append)
    try:
        record = _run_mujoco(mujoco, mesh, settings, sim_seconds)
    finally:
        mujoco.set_mju_user_warning(previous)
    # The first few distinct messages (they repeat every step with other numbers).
    distinct = list(dict.fromkeys(message.split(" Time =")[0] for message in messages))
    record["warning_messages"] = distinct[:4]
    record["warning_message_count"] = len(messages)
    return record


def _run_mujoco(
    mujoco: Any, mesh: TetMesh, settings: MujocoSettings, sim_seconds: float
) -> dict[str, Any]:
    record: dict[str, Any] = {"settings": asdict(settings), "mujoco_version": mujoco.__version__}
    face = probe_start_position(mesh)
    try:
        start = time.perf_counter()
        model = mujoco.MjModel.from_xml_string(flex_mjcf(mesh, settings, face))
        record["compile_s"] = time.perf_counter() - start
    except ValueError as error:
        record["status"] = f"compile_error: {error}"
        return record
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    order_error = float(np.abs(data.flexvert_xpos - mesh.nodes).max())
    record["vertex_order_error_m"] = order_error
    if order_error > 1e-7:
        record["status"] = "vertex_order_mismatch"
        return record

    step_count = int(round(sim_seconds / settings.timestep_s))
    advance = PAPER_PROBE_SPEED_M_S * settings.timestep_s
    start_z = float(data.mocap_pos[0, 2])
    half_x, half_y = PROBE_FACE_M[0] / 2, PROBE_FACE_M[1] / 2
    in_footprint = (np.abs(mesh.nodes[:, 0] - face[0]) <= half_x) & (
        np.abs(mesh.nodes[:, 1] - face[1]) <= half_y
    )
    bad_qacc = int(mujoco.mjtWarning.mjWARN_BADQACC)
    samples: list[float] = []
    iterations: list[int] = []
    penetration_max = 0.0
    status = "ok"
    for step in range(1, step_count + 1):
        data.mocap_pos[0, 2] = start_z - advance * step
        start = time.perf_counter()
        mujoco.mj_step(model, data)
        samples.append(time.perf_counter() - start)
        iterations.append(int(data.solver_niter[0]))
        if not np.all(np.isfinite(data.qpos)) or data.warning[bad_qacc].number > 0:
            status = f"unstable at t = {step * settings.timestep_s:.3f} s"
            break
        face_z = float(data.mocap_pos[0, 2]) - PROBE_DEPTH_M / 2
        inside = data.flexvert_xpos[in_footprint, 2] - face_z
        if inside.size:
            penetration_max = max(penetration_max, float(inside.max()))
        if sum(samples) > MUJOCO_WALL_BUDGET_S and step < step_count:
            status = f"stopped by the {MUJOCO_WALL_BUDGET_S:.0f} s wall budget"
            break
    completed = len(samples) * settings.timestep_s
    warnings = {
        name: int(data.warning[int(value)].number)
        for name, value in mujoco.mjtWarning.__members__.items()
        if name != "mjNWARNING" and data.warning[int(value)].number
    }
    record.update(
        status=status,
        completed_sim_s=completed,
        **_timing(samples, settings.timestep_s),
        solver_iterations_median=float(np.median(iterations)),
        solver_iterations_at_cap=int(sum(i >= settings.iterations for i in iterations)),
        warnings=warnings,
        penetration_max_m=penetration_max,
        nv=int(model.nv),
    )
    if status == "ok":
        assert mesh.landmarks is not None
        record["lesion1_m"] = [float(v) for v in mesh.landmarks.positions(data.flexvert_xpos)[0]]
        record["force_n"] = _probe_force_z(mujoco, model, data)
    return record


def _press_ours(
    mesh: TetMesh,
    method: str,
    config: SimulationConfig,
    increment_m: float,
    travel_m: float,
    materials: TissueMaterials | None = None,
) -> tuple[list[float], Counter[str], Any]:
    """Press our box probe ``travel_m`` down in equal increments of about ``increment_m``.

    Returns the wall time of each step [s], the step statuses and the last TissueStep.
    Stops early (statuses then count ``stopped_by_wall_budget``) once the steps have taken
    :data:`MUJOCO_WALL_BUDGET_S`, the same budget MuJoCo runs get.
    """
    shape = BoxProbe((PROBE_FACE_M[0], PROBE_DEPTH_M, PROBE_FACE_M[1]))
    kwargs: dict[str, Any] = {"config": config, "materials": materials}
    if method == "prescribed":
        kwargs["params"] = PrescribedParams(online=True)
    model = make_contact_model(method, mesh, shape, **kwargs)
    probe = Probe.looking_along(shape, probe_start_position(mesh), np.array([0.0, 0.0, -1.0]))
    step_count = max(1, int(round(travel_m / increment_m)))
    samples: list[float] = []
    statuses: Counter[str] = Counter()
    result = None
    for step in range(1, step_count + 1):
        position = probe.position_world - np.array([0.0, 0.0, travel_m * step / step_count])
        start = time.perf_counter()
        result = model.step(position, probe.quat_wxyz)
        samples.append(time.perf_counter() - start)
        statuses[result.status.value] += 1
        if sum(samples) > MUJOCO_WALL_BUDGET_S and step < step_count:
            statuses["stopped_by_wall_budget"] += 1
            break
    return samples, statuses, result


def reference_lesion(
    mesh: TetMesh, travel_m: float, materials: TissueMaterials | None = None
) -> tuple[NDArray[np.float64], dict[str, Any]]:
    """Lesion 1 at the final depth [m], (3,), from the converged quasi-static LM reference.

    Args:
        mesh: the phantom level.
        travel_m: probe travel from the start pose [m].
        materials: None for the project's default materials (the reference every side is
            judged against), or MuJoCo's uniform material for a matched-material check.
    """
    config = SimulationConfig(mode="robust", quasi_static=True)
    samples, statuses, result = _press_ours(
        mesh, "lm", config, REFERENCE_INCREMENT_M, travel_m, materials
    )
    info = {
        "method": "lm",
        "mode": "robust",
        "quasi_static": True,
        "increment_m": travel_m / len(samples),
        "status_counts": dict(statuses),
        "force_n": float(result.force_world_n[2]),
        "wall_s": float(sum(samples)),
    }
    return np.asarray(result.landmarks_world_m[0], dtype=np.float64), info


def run_ours(
    mesh: TetMesh, method: str, mode: str, sim_seconds: float, reference: NDArray[np.float64]
) -> dict[str, Any]:
    """Our dynamic press at tissue_dt = 0.02 s; timings, status and lesion 1 error [m]."""
    travel = PAPER_PROBE_SPEED_M_S * sim_seconds
    config = SimulationConfig(mode=mode, tissue_dt=PAPER_TISSUE_DT_S)
    samples, statuses, result = _press_ours(
        mesh, method, config, PAPER_PROBE_SPEED_M_S * PAPER_TISSUE_DT_S, travel
    )
    lesion = np.asarray(result.landmarks_world_m[0], dtype=np.float64)
    stopped = "stopped_by_wall_budget" in statuses
    completed = len(samples) * PAPER_TISSUE_DT_S
    return {
        "method": method,
        "mode": mode,
        "completed_sim_s": completed,
        **_timing(samples, PAPER_TISSUE_DT_S),
        "status_counts": dict(statuses),
        "force_n": float(result.force_world_n[2]),
        "penetration_max_m": float(result.method_penetration_m),
        "lesion1_m": [float(v) for v in lesion],
        # A run cut short ends at another depth: no error against the reference.
        "lesion_error_m": math.nan if stopped else float(np.linalg.norm(lesion - reference)),
    }


def benchmark_level(level: int, sim_seconds: float) -> dict[str, Any]:
    """One level: reference, ours (every method and mode), MuJoCo (every variant)."""
    mesh = breast_phantom(level)
    assert mesh.landmarks is not None
    travel = PAPER_PROBE_SPEED_M_S * sim_seconds
    rest = mesh.landmarks.rest_positions[0]
    reference, reference_info = reference_lesion(mesh, travel)
    ours = []
    for method in OURS_METHODS:
        for mode in OURS_MODES:
            run_ours(mesh, method, mode, WARMUP_SIM_S, reference)  # untimed warm-up
            ours.append(run_ours(mesh, method, mode, sim_seconds, reference))
    # MuJoCo's own material (uniform, its nu) in our solver: how much of MuJoCo's error is
    # the material it cannot represent, and how much is its engine (contact, SVK, dynamics).
    matched: dict[float, NDArray[np.float64]] = {}
    for poisson in sorted({settings.poisson for settings in MUJOCO_VARIANTS}):
        uniform = TissueMaterials(
            tissue=NeoHookean(YOUNG_PA, poisson, DENSITY_KG_M3), lesion_stiffness_ratio=1.0
        )
        matched[poisson], _ = reference_lesion(mesh, travel, uniform)
    mujoco_runs = []
    for settings in MUJOCO_VARIANTS:
        run = run_mujoco(mesh, settings, sim_seconds)
        if "lesion1_m" in run:
            lesion = np.asarray(run["lesion1_m"])
            run["lesion_error_m"] = float(np.linalg.norm(lesion - reference))
            run["lesion_error_matched_material_m"] = float(
                np.linalg.norm(lesion - matched[settings.poisson])
            )
        mujoco_runs.append(run)

    headline = {run["mode"]: run for run in ours if run["method"] == OURS_METHODS[0]}
    primary = mujoco_runs[0]
    mujoco_ms = primary.get("ms_per_sim_s", math.nan)
    mujoco_steady = primary.get("ms_per_sim_s_steady", math.nan)
    for run in ours:
        run["ratio"] = mujoco_ms / run["ms_per_sim_s"]
        run["ratio_steady"] = mujoco_steady / run["ms_per_sim_s_steady"]
    return {
        "level": level,
        "tets": mesh.tet_count,
        "nodes": mesh.node_count,
        "sim_seconds": sim_seconds,
        "travel_m": travel,
        "ours_method": OURS_METHODS[0],
        "ours_ms_per_sim_s": {mode: headline[mode]["ms_per_sim_s"] for mode in OURS_MODES},
        "mujoco_ms_per_sim_s": mujoco_ms,
        "ratio": {mode: headline[mode]["ratio"] for mode in OURS_MODES},
        "ours_ms_per_sim_s_steady": {
            mode: headline[mode]["ms_per_sim_s_steady"] for mode in OURS_MODES
        },
        "mujoco_ms_per_sim_s_steady": mujoco_steady,
        "ratio_steady": {mode: headline[mode]["ratio_steady"] for mode in OURS_MODES},
        "ours_lesion_error_m": {mode: headline[mode]["lesion_error_m"] for mode in OURS_MODES},
        "mujoco_lesion_error_m": primary.get("lesion_error_m", math.nan),
        "mujoco_status": primary["status"],
        "mujoco_settings": primary["settings"],
        "reference_lesion1_m": [float(v) for v in reference],
        "reference_lesion1_displacement_m": float(np.linalg.norm(reference - rest)),
        "reference": reference_info,
        "matched_material_reference_lesion1_m": {
            str(poisson): [float(v) for v in position] for poisson, position in matched.items()
        },
        "ours": ours,
        "mujoco": mujoco_runs,
        "load_average": os.getloadavg()[0],
        "cpu_count": os.cpu_count(),
        "threading": threading_environment(),
    }


def _timing(samples: list[float], dt_s: float) -> dict[str, float]:
    """Per-simulated-second costs of a run from its step wall times [s].

    ``ms_per_sim_s`` counts every step; ``ms_per_sim_s_steady`` leaves out the first step,
    which on our side carries one-time lazy setup (about 0.3 s even on the 622-tet level;
    MuJoCo's one-time cost is its compile, reported apart as ``compile_s``).
    """
    steady = samples[1:] or samples
    return {
        "ms_per_sim_s": 1e3 * sum(samples) / (len(samples) * dt_s),
        "ms_per_sim_s_steady": 1e3 * sum(steady) / (len(steady) * dt_s),
        "first_step_ms": 1e3 * samples[0],
        "step_ms": 1e3 * float(np.median(samples)),
    }


def _mm(value: float) -> str:
    return f"{value * 1e3:8.3f}" if math.isfinite(value) else f"{'nan':>8}"


def markdown_tables(records: list[dict[str, Any]]) -> list[MarkdownTable]:
    """Each of our runs against MuJoCo's headline variant: ms of computation per simulated
    second, the ratio (MuJoCo / ours, the target beside it) and lesion 1's error."""
    needed = {"paper": 3.0, "robust": 2.0}
    table = MarkdownTable(
        f"ms per simulated s (all steps), MuJoCo {MUJOCO_VARIANTS[0].name} / ours, lesion 1 "
        "error against the quasi-static LM reference [mm]",
        ["tets", "ours", "ours ms/sim s", "MuJoCo ms/sim s", "ratio", "target", "ours error",
         "MuJoCo error"],
    )  # fmt: skip
    for r in records:
        for run in r["ours"]:
            mode = run["mode"]
            verdict = "met" if run["ratio"] >= needed[mode] else "missed"
            table.rows.append([
                f"{r['tets']:,}", f"{run['method']}/{mode}", f"{run['ms_per_sim_s']:.0f}",
                f"{r['mujoco_ms_per_sim_s']:.0f}", f"{run['ratio']:.2f}",
                f">= {needed[mode]:.0f} ({verdict})", _mm(run["lesion_error_m"]).strip(),
                _mm(r["mujoco_lesion_error_m"]).strip(),
            ])  # fmt: skip
    return [table]


def print_tables(records: list[dict[str, Any]]) -> None:
    """The headline table, then every run of both sides per level, then the targets."""
    print(
        f"\nheadline: ours = {OURS_METHODS[0]}, MuJoCo = {MUJOCO_VARIANTS[0].name}; "
        "ms of computation per simulated s, all steps (steady: without the first step)"
    )
    print(
        f"{'tets':>6} {'ours paper':>15} {'ours robust':>15} {'MuJoCo':>13} "
        f"{'ratio paper':>13} {'ratio robust':>13} {'err p mm':>9} {'err r mm':>9} "
        f"{'MJ err mm':>9}  MJ status"
    )
    for r in records:
        ours, steady = r["ours_ms_per_sim_s"], r["ours_ms_per_sim_s_steady"]
        ratio, ratio_steady = r["ratio"], r["ratio_steady"]
        err = r["ours_lesion_error_m"]
        print(
            f"{r['tets']:>6} {ours['paper']:>7.0f} ({steady['paper']:>5.0f}) "
            f"{ours['robust']:>7.0f} ({steady['robust']:>5.0f}) "
            f"{r['mujoco_ms_per_sim_s']:>6.0f} ({r['mujoco_ms_per_sim_s_steady']:>4.0f}) "
            f"{ratio['paper']:>5.2f} ({ratio_steady['paper']:>5.2f}) "
            f"{ratio['robust']:>5.2f} ({ratio_steady['robust']:>5.2f}) "
            f"{_mm(err['paper']):>9} {_mm(err['robust']):>9} "
            f"{_mm(r['mujoco_lesion_error_m']):>9}  {r['mujoco_status']}"
        )
    print(
        "\nall runs: lesion 1 error against the quasi-static LM reference (MuJoCo: in brackets,"
        " against our solver with MuJoCo's own uniform material); ratio = MuJoCo "
        f"{MUJOCO_VARIANTS[0].name} / this run, all steps (steady)"
    )
    print(
        f"{'tets':>6} {'side':>30} {'ms/sim s':>9} {'steady':>7} {'1st ms':>7} {'ms/step':>8} "
        f"{'ratio':>13} {'err mm':>8} {'F_z N':>7} {'pen mm':>7}  status"
    )
    for r in records:
        print(
            f"{r['tets']:>6} {'reference (quasi-static LM)':>30} {'':>9} {'':>7} {'':>7} "
            f"{'':>8} {'':>13} {'0':>8} {r['reference']['force_n']:>7.3f} {'':>7}  "
            f"{r['reference']['status_counts']} "
            f"(lesion 1 moved {r['reference_lesion1_displacement_m'] * 1e3:.2f} mm)"
        )
        for run in r["ours"]:
            print(
                f"{r['tets']:>6} {'ours ' + run['method'] + '/' + run['mode']:>30} "
                f"{run['ms_per_sim_s']:>9.0f} {run['ms_per_sim_s_steady']:>7.0f} "
                f"{run['first_step_ms']:>7.0f} {run['step_ms']:>8.1f} "
                f"{run['ratio']:>5.2f} ({run['ratio_steady']:>5.2f}) "
                f"{_mm(run['lesion_error_m']):>8} {run['force_n']:>7.3f} "
                f"{run['penetration_max_m'] * 1e3:>7.3f}  {run['status_counts']}"
            )
        for run in r["mujoco"]:
            name = "MuJoCo " + run["settings"]["name"]
            if "ms_per_sim_s" not in run:
                print(f"{r['tets']:>6} {name:>30}  {run['status']}")
                continue
            print(
                f"{r['tets']:>6} {name:>30} {run['ms_per_sim_s']:>9.0f} "
                f"{run['ms_per_sim_s_steady']:>7.0f} {run['first_step_ms']:>7.0f} "
                f"{run['step_ms']:>8.1f} {'':>13} "
                f"{_mm(run.get('lesion_error_m', math.nan)):>8} "
                f"{run.get('force_n', math.nan):>7.3f} {run['penetration_max_m'] * 1e3:>7.3f}  "
                f"[{_mm(run.get('lesion_error_matched_material_m', math.nan)).strip()} mm] "
                f"{run['status']}; compile {run['compile_s']:.2f} s, solver iterations "
                f"median {run['solver_iterations_median']:.0f} (at cap "
                f"{run['solver_iterations_at_cap']}), warnings {run['warnings']}"
            )
    print(
        "\ntargets: MuJoCo / ours >= 3 in paper mode, >= 2 in robust mode, "
        f"for each of our methods (the headline is {OURS_METHODS[0]})"
    )
    needed = {"paper": 3.0, "robust": 2.0}
    for r in records:
        for run in r["ours"]:
            value, steady, mode = run["ratio"], run["ratio_steady"], run["mode"]
            verdict = "meets" if value >= needed[mode] else "MISSES"
            print(
                f"  {r['tets']:>6} tets {run['method']:>10} {mode:>6}: {value:6.2f} x "
                f"(steady {steady:.2f} x) >= {needed[mode]:.0f} x? {verdict}"
            )


def run_peer_benchmark(
    levels: list[int] | None,
    json_path: Path,
    sim_seconds: float = 1.0,
    command: str | None = None,
) -> list[dict[str, Any]]:
    """Benchmark ours against MuJoCo flex per level; print tables; write a JSON list.

    Args:
        levels: phantom levels (tet counts); None: 623, 4126 and 26,220.
        json_path: where the records go; rewritten after every level.
        sim_seconds: simulated time of the press [s] (0.01 m/s: 1 s is 10 mm of travel).

    Returns:
        One record per level (see the module docstring for what is compared).
    """
    levels = list(levels or DEFAULT_LEVELS)
    print(
        f"probegym bench peer — box probe {PROBE_FACE_M[0] * 1e3:.0f} x "
        f"{PROBE_FACE_M[1] * 1e3:.0f} mm into the apex at {PAPER_PROBE_SPEED_M_S} m/s for "
        f"{sim_seconds} s ({platform.processor() or platform.machine()})"
    )
    records: list[dict[str, Any]] = []
    provenance = BenchRecord("probegym bench peer: ours against MuJoCo's flex", command)
    for level in levels:
        record = benchmark_level(level, sim_seconds)
        records.append(record)
        print(
            f"  {record['tets']:>6} tets: ours {record['ours_ms_per_sim_s']}, MuJoCo "
            f"{record['mujoco_ms_per_sim_s']:.0f} ms per simulated s ({record['mujoco_status']})",
            flush=True,
        )
        json_path.parent.mkdir(parents=True, exist_ok=True)
        # Keep what is measured so far; NaN (a failed run) is written as null.
        write_json(records, json_path, indent=2)
    print_tables(records)
    markdown = provenance.write(json_path, markdown_tables(records))
    print(f"written: {json_path}, {markdown}")
    return records
