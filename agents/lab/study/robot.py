"""``probegym study --robot``: the study's protocol with the probe held by the arm.

Tagliabue et al. (2020) held the probe by hand and planned to "repeat the same experiments
with the probe held by a robotic manipulator". Here each cell of the study (method, level,
lesion, profile) runs in ``probegym/BreastCompress-v0``: the environment's arm holds the
probe, its Cartesian impedance controller tracks a target, and its coupling
(:class:`envs.coupling.TissueCoupling`) steps the arm and the tissue together, two ways.
Nothing here simulates: the scripted controller only moves the target.

The protocol is the kinematic cell's (:func:`agents.lab.study.cell.run_cell`), pose for pose:
the probe is placed (inverse kinematics, at rest) at the kinematic path's start, 1 mm clear
of the skin above the lesion, normal to the skin; each 20 ms step moves the target along the
kinematic path (0.2 mm at 0.01 m/s, the same steps to each depth); at each depth the target
holds still until no tissue node moves faster than 0.1 mm/s, for at most ``settle_steps``
steps, and the depth is recorded. The arm's probe lags its target: the record holds the
tracking error (probe minus target, along and across the pressing axis, and the angle
between their orientations) per settled depth and over the motion, and the same cell run
kinematically, to compare force and lesion position depth by depth.

A physical failure (a tissue step not ``ok``, any instability of
:mod:`tissue.contact.stability`, the arm's state not finite) ends the cell and is recorded
in it, as the kinematic study does.
"""

from __future__ import annotations

import math
import os
import platform
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from agents.lab.compress import SETTLED_SPEED_M_S, START_CLEARANCE_M
from agents.lab.study.cell import STUDY_LIMITS, scene_for, source_revision, summarise_times
from agents.lab.study.spec import Cell, StudySpec
from tissue import ConfigError, TissueInputError
from tissue.lab import StabilityMonitor

#: The environment the robot cells run in.
ROBOT_ENV_ID = "probegym/BreastCompress-v0"
#: The methods whose environment tissue is the study's own configuration in both profiles:
#: their kinematic twins may be read from the kinematic study's results. The front door
#: builds robust prescribed displacement sliding with a skin guard (the study: sticking),
#: paper prescribed with the node set chosen at first contact (the study: the published
#: set) and PBD with its per-mesh calibration (the study: fixed constants), so the twins of
#: those cells run the kinematic protocol on the environment's own tissue
#: (:func:`agents.lab.study.cell.run_cell` with its ``tissue_spec``).
STUDY_TWIN_METHODS = ("lm", "penalty")
#: Where a robot cell's kinematic twin came from (the record's ``kinematic.source``): the
#: kinematic study's results, the study's cell run now, or the study's protocol run on the
#: environment's own tissue.
TWIN_FROM_RESULTS = "results.jsonl"
TWIN_RUN = "run"
TWIN_ENV_TISSUE = "run on the environment's tissue"
#: ``--robot --quick``: two coarse levels and two lesions (the dome's top and lesion 10,
#: under skin tilted 26 degrees), every method, robust.
ROBOT_QUICK_LEVELS = (623, 1363)
ROBOT_QUICK_LESIONS = (1, 10)
#: Where a robot study writes, inside the study's ``--out``.
ROBOT_DIR = "robot"


def max_press_m() -> float:
    """How far BreastCompress lets the probe's target go into the tissue from its start [m]
    (its workspace clip, ``max_press_m``)."""
    from envs.tasks.breast_compress import BreastCompressConfig

    return float(BreastCompressConfig().max_press_m)


def max_robot_depth_m() -> float:
    """The deepest press past first contact the arm may be asked for [m]: the start is
    :data:`~agents.lab.compress.START_CLEARANCE_M` clear of the skin."""
    return max_press_m() - START_CLEARANCE_M


def check_robot_spec(spec: StudySpec) -> None:
    """Refuse what the robot study cannot run, naming the value and the fix."""
    if spec.scene != "synthetic":
        raise ConfigError(
            f"--robot runs on --scene synthetic only; got --scene {spec.scene}: the arm's base, "
            "home pose and workspace are placed for the built-in phantom, on the table at the "
            "origin; the published scene lies in its own frame (6-14 cm under that table, "
            "pressed partly upwards), where no placement of the arm is defined"
        )
    deepest = max_robot_depth_m()
    if spec.depths_m[-1] > deepest + 1e-12:
        raise ConfigError(
            f"--depths up to {spec.depths_m[-1] * 1e3:g} mm are beyond the arm's allowed press: "
            f"{ROBOT_ENV_ID} keeps the probe's target within {max_press_m() * 1e3:g} mm of its "
            f"start, {START_CLEARANCE_M * 1e3:g} mm clear of the skin; give --depths up to "
            f"{deepest:g} (e.g. 0.01,0.02,0.025,0.03)"
        )


# ---------------------------------------------------------------------- one cell


def make_robot_env(cell: Cell, spec: StudySpec) -> Any:
    """The cell's environment, unwrapped (the arm, the probe and the cell's tissue), its skin
    the study's (the paper's surface unless ``--skin`` says otherwise), so that robot and
    kinematic cells press the same skin."""
    import gymnasium as gym

    import envs  # noqa: F401 - registers the environments

    return gym.make(
        ROBOT_ENV_ID,
        mesh=cell.level,
        contact=cell.method,
        profile=cell.config.value,
        collision_edge_m=spec.collision_edge_m,
    ).unwrapped


@dataclass
class _Trace:
    """Per-step series of a robot cell (JSON lists in the record's ``trace``)."""

    t_s: list[float] = field(default_factory=list)
    commanded_depth_m: list[float] = field(default_factory=list)
    along_m: list[float] = field(default_factory=list)
    across_m: list[float] = field(default_factory=list)
    orientation_deg: list[float] = field(default_factory=list)
    force_normal_n: list[float] = field(default_factory=list)
    moving: list[bool] = field(default_factory=list)

    def as_json(self) -> dict[str, list[Any]]:
        """The series, numbers to 6 significant digits (a cell's trace is ~1,000 steps)."""
        return {
            name: [v if isinstance(v, bool) else float(f"{v:.6g}") for v in values]
            for name, values in vars(self).items()
        }


def tracking_error(
    env: Any, position: NDArray[np.float64], rotation: NDArray[np.float64]
) -> tuple[float, float, float]:
    """The probe's pose now minus the commanded one: along the pressing axis [m] (negative:
    short of the target), across it [m], and the angle between the orientations [deg]."""
    from envs.rotations import rotation_angle

    actual, actual_rot = env.probe_pose()
    offset = actual - position
    axis = rotation[:, 1]
    along = float(offset @ axis)
    across = float(np.linalg.norm(offset - along * axis))
    return along, across, math.degrees(rotation_angle(actual_rot, rotation))


def _arm_finite(env: Any) -> bool:
    data = env.data
    return bool(np.all(np.isfinite(data.qpos)) and np.all(np.isfinite(data.qvel)))


def run_robot_cell(spec: StudySpec, cell: Cell, env: Any | None = None) -> dict[str, Any]:
    """Run one cell with the arm holding the probe; returns its record (no kinematic
    comparison yet: :func:`agents.lab.study.robot_runner.compare_with_kinematic` adds it).

    ``env``: the cell's environment (:func:`make_robot_env`), left open for the caller (whose
    twin reads its tissue's spec); None: made here and closed.
    """
    from envs.rotations import quat_matrix

    started = time.perf_counter()
    scene = scene_for(spec)
    mesh = scene.mesh(cell.level)
    owned = env is None
    if env is None:
        env = make_robot_env(cell, spec)
    try:
        if not np.array_equal(env.tissue.rest_nodes_m, mesh.nodes):
            raise RuntimeError(f"the environment's level {cell.level} mesh is not the study's")
        start, stops = scene.path(mesh, env.tissue.probe_shape, cell.lesion, spec.depths_m)
        rotation = quat_matrix(start.quat_wxyz)
        axis = rotation[:, 1]
        contact = start.position + START_CLEARANCE_M * axis
        env.reset(seed=0)
        env.place_probe(start.position, rotation)
        tracked = env.tissue.landmark_names.index(scene.landmark_name(cell.lesion))
        monitor = StabilityMonitor(cell.method, mesh.nodes, start.position, STUDY_LIMITS)
        scale = env.action_config.max_translation_m
        dt = env.tissue.dt
        trace = _Trace()
        depths: list[dict[str, Any]] = []
        step_ms: list[float] = []
        tissue_ms: list[float] = []
        instability: dict[str, Any] | None = None
        steps = 0

        def take(position: NDArray[np.float64], moving: bool) -> Any:
            """One 20 ms step towards ``position``; returns the tissue step (None: the arm's
            state went non-finite); sets ``instability`` on a failure."""
            nonlocal instability, steps
            action = np.zeros(6)
            action[:3] = rotation.T @ (position - env.controller.target_pos) / scale
            tic = time.perf_counter()
            try:
                _, _, _, _, info = env.step(action)
            except TissueInputError as error:  # the arm's NaN pose reached the tissue
                if _arm_finite(env):
                    raise
                instability = {"step": steps, "kind": "robot_non_finite", "detail": str(error)}
                return None
            step_ms.append(1e3 * (time.perf_counter() - tic))
            step = env.coupling.last_step
            tissue_ms.append(step.diagnostics.compute_ms)
            commanded = env.controller.target_pos.copy()
            along, across, turned = tracking_error(env, commanded, rotation)
            trace.t_s.append(float(step.time_s))
            trace.commanded_depth_m.append(float((commanded - contact) @ axis))
            trace.along_m.append(along)
            trace.across_m.append(across)
            trace.orientation_deg.append(turned)
            trace.force_normal_n.append(env.normal_force_n(step))
            trace.moving.append(moving)
            if info.get("robot_unstable"):
                instability = {
                    "step": steps,
                    "kind": "robot_non_finite",
                    "detail": "the arm's joint positions or velocities are not finite",
                }
            else:
                actual, _ = env.probe_pose()
                found = monitor.check(step, env.tissue.positions_m, actual)
                if found is not None:
                    instability = {"step": steps, "kind": found.kind, "detail": found.detail}
            steps += 1
            return step

        counts = _motion_step_counts(start.position, [s.position for s in stops], spec, dt)
        motion_done = 0
        begin = start.position
        for stop, count in zip(stops, counts, strict=True):
            for i in range(1, count + 1):
                take(begin + i / count * (stop.position - begin), True)
                if instability is not None:
                    break
                motion_done += 1
            if instability is not None:
                break
            begin = stop.position
            step = None
            for _ in range(spec.settle_steps):
                previous = env.tissue.positions_m.copy()
                step = take(stop.position, False)
                if instability is not None:
                    break
                speed = float(np.max(np.abs(env.tissue.positions_m - previous))) / dt
                if speed < SETTLED_SPEED_M_S:
                    break
            if instability is not None:
                motion_done -= 1  # the depth was reached but never held
                break
            assert step is not None
            commanded = env.controller.target_pos.copy()
            along, across, turned = tracking_error(env, commanded, rotation)
            depths.append(
                {
                    "depth_m": stop.depth_m,
                    "tracked_m": step.landmarks_world_m[tracked].tolist(),
                    "force_normal_n": env.normal_force_n(step),
                    "skin_penetration_m": float(step.skin_penetration_m),
                    "penetration_max_m": float(env.tissue.contact_model.penetration_max_m()),
                    "along_m": along,
                    "across_m": across,
                    "orientation_deg": turned,
                }
            )
        moving = np.array(trace.moving, dtype=bool)
        motion_errors = {
            "along_max_m": _abs_max(trace.along_m, moving),
            "across_max_m": _abs_max(trace.across_m, moving),
            "orientation_max_deg": _abs_max(trace.orientation_deg, moving),
        }
    finally:
        if owned:
            env.close()
    assert mesh.landmarks is not None
    return {
        "key": cell.key,
        "robot": True,
        "env": ROBOT_ENV_ID,
        "scene": scene.name,
        "config": cell.config.value,
        "method": cell.method,
        "level": cell.level,
        "tets": mesh.tet_count,
        "nodes": mesh.node_count,
        "lesion": cell.lesion,
        "depths_m": [d["depth_m"] for d in depths],
        "rest_tracked_m": mesh.landmarks.rest_positions[tracked].tolist(),
        "tracked_m": [d["tracked_m"] for d in depths],
        "force_normal_n": [d["force_normal_n"] for d in depths],
        "skin_penetration_m": [d["skin_penetration_m"] for d in depths],
        # The method's own measure, as the kinematic record's ``penetration_max_m``.
        "penetration_max_m": [d["penetration_max_m"] for d in depths],
        # Probe minus target at each settled depth: along the pressing axis [m] (negative:
        # the probe stops short, pushed back by the tissue against the impedance), across
        # it [m], and the angle between the orientations [deg].
        "tracking": {
            "along_m": [d["along_m"] for d in depths],
            "across_m": [d["across_m"] for d in depths],
            "orientation_deg": [d["orientation_deg"] for d in depths],
            **motion_errors,
        },
        "step_ms": summarise_times(np.array(step_ms)),
        "tissue_step_ms": summarise_times(np.array(tissue_ms)),
        "stability_percent": 100.0 * max(motion_done, 0) / max(sum(counts), 1),
        "status": "ok" if instability is None else "unstable",
        "instability": instability,
        "trace": trace.as_json(),
        "wall_s": time.perf_counter() - started,
        "load_average": os.getloadavg()[0],
        "host": platform.node(),
        "pid": os.getpid(),
        "revision": source_revision(),
    }


def _abs_max(values: list[float], mask: NDArray[np.bool_]) -> float | None:
    chosen = np.abs(np.asarray(values, dtype=np.float64))[mask] if values else np.zeros(0)
    return float(chosen.max()) if chosen.size else None


def _motion_step_counts(
    start: NDArray[np.float64], stops: list[NDArray[np.float64]], spec: StudySpec, dt: float
) -> list[int]:
    """Steps to each depth from the previous one, as :func:`agents.lab.compress.run_compression`
    takes them (>= 1 each)."""
    counts, position = [], start
    for stop in stops:
        distance = float(np.linalg.norm(stop - position))
        counts.append(max(1, math.ceil(distance / (spec.speed_m_s * dt) - 1e-9)))
        position = stop
    return counts
