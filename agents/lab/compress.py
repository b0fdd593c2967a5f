"""``probegym compress``: one scripted probe compression, recorded step by step, as JSON.

The probe starts just clear of the surface, moves along the pressing direction at a
constant speed, and holds at each requested depth (measured from first contact) until the
tissue settles; one record per step and one per depth are written.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from tissue import (
    ConfigError,
    ContactModel,
    ProbeShape,
    StepStatus,
    TissueInputError,
    TissueSpec,
    TissueStep,
    make_tissue,
)
from tissue.lab import (
    PBDConfig,
    PrescribedParams,
    Probe,
    StabilityMonitor,
    TetMesh,
    boundary_faces,
    contact_method,
    first_contact_pose,
    profile_choices,
    ray_surface_hit,
    worst,
)

# The probe starts this far before first contact [m].
START_CLEARANCE_M = 0.001
# Settling at a depth ends when no node moves faster than this [m/s] ...
SETTLED_SPEED_M_S = 1e-4
# ... or after this many steps: run_compression's default, enough for the hard cases, whose
# holds check stability, not where the tissue comes to rest ...
MAX_SETTLE_STEPS = 50
#: ... and a hold long enough to settle (5 s at 0.02 s), for ``probegym compress``'s depths
#: and the study. Measured with robust LM on the 4,126-tet level against its own quasi-static
#: reference: after 50 steps lesion 1 at 30 mm was still 2.16 mm from equilibrium and lesion 5
#: 1.15 mm (the tissue creeps for seconds under the probe); after 100 / 150 / 200 / 300 steps
#: lesion 1 was 0.61 / 0.24 / 0.12 / 0.08 mm away, and five lesions were within 0.08 mm at
#: every depth after 300.
ACCURATE_SETTLE_STEPS = 250


@dataclass(frozen=True)
class Waypoint:
    """A probe pose to reach, and whether to settle and record a depth there.

    Attributes:
        position: probe origin [m], (3,).
        quat_wxyz: probe orientation, (4,).
        depth_m: the depth to record after settling there; None: pass through.
        speed_m_s: the probe's speed on the way here [m/s]; None: the run's speed;
            ``math.inf``: in one step (a sudden jump or release).
    """

    position: NDArray[np.float64]
    quat_wxyz: NDArray[np.float64]
    depth_m: float | None  # None: pass through without recording
    speed_m_s: float | None = None


def straight_path(
    contact_position: NDArray[np.float64],
    quat_wxyz: NDArray[np.float64],
    direction: NDArray[np.float64],
    depths_m: list[float],
) -> tuple[Waypoint, list[Waypoint]]:
    """Start pose (just clear of contact) and one waypoint per depth along ``direction``."""
    _check_depths(depths_m)
    direction = direction / np.linalg.norm(direction)
    start = Waypoint(contact_position - START_CLEARANCE_M * direction, quat_wxyz, None)
    stops = [Waypoint(contact_position + d * direction, quat_wxyz, d) for d in depths_m]
    return start, stops


def _check_depths(depths_m: list[float]) -> None:
    if not depths_m:
        raise ConfigError("--depths needs at least one depth in metres, e.g. 0.01,0.02")
    values = np.asarray(depths_m, dtype=np.float64)
    if not np.all(np.isfinite(values)) or np.any(values <= 0):
        raise ConfigError(
            f"depths are distances past first contact and must be > 0 m; got {depths_m} "
            "(a path with no motion)"
        )
    if np.any(np.diff(values) <= 0):
        raise ConfigError(f"--depths must increase; got {depths_m}")
    if values.max() > 0.1:
        raise ConfigError(
            f"depths are in metres; {values.max():g} m is deeper than any phantom "
            "(did you mean millimetres? 20 mm is 0.02)"
        )


@dataclass(frozen=True)
class CompressionProgress:
    """Where a run stands after a motion step, a step of a hold or a recorded depth: what
    :func:`run_compression` needs to resume it there.

    Attributes:
        stops_done: the waypoints passed (held and recorded, where they have a depth).
        motion_done: the motion steps completed (for ``stability_percent``).
        steps: the step records so far.
        depths: the records of the depths reached so far.
        model_state: the model's :meth:`~tissue.contact.base.ContactModel.saved_state`.
        stop_motion_done: the motion steps taken towards the next waypoint (0 just after a
            recorded depth).
        level_status: the worst step status on the way to the next waypoint so far.
        settle_done: the steps held still at the next waypoint so far (its motion done).
    """

    stops_done: int
    motion_done: int
    steps: list[dict[str, Any]]
    depths: list[dict[str, Any]]
    model_state: dict[str, NDArray[np.float64]]
    stop_motion_done: int = 0
    level_status: str = StepStatus.OK.value
    settle_done: int = 0


def run_compression(
    model: ContactModel,
    start: Waypoint,
    stops: list[Waypoint],
    speed_m_s: float,
    progress: bool = False,
    monitor: StabilityMonitor | None = None,
    observer: Callable[[TissueStep, NDArray[np.float64]], None] | None = None,
    max_settle_steps: int = MAX_SETTLE_STEPS,
    resume: CompressionProgress | None = None,
    on_progress: Callable[[CompressionProgress], None] | None = None,
) -> dict[str, Any]:
    """Drive ``model`` through the waypoints; returns the JSON-ready record.

    At each waypoint with a depth the probe holds still until no node moves faster than
    :data:`SETTLED_SPEED_M_S`, or for ``max_settle_steps`` steps, and the depth is recorded.

    With a ``monitor`` the run stops at the first unstable step (the step is recorded) and
    the record gains ``instability`` ({step, kind, detail}, or None) and
    ``stability_percent``: the share of the path's motion steps completed before it (the
    paper's stability metric; a failure while settling at a depth counts as failing on
    that depth's last motion step). ``observer(result, probe_position)`` is called after
    every step.

    ``on_progress(progress)`` is called after each stable motion step, each step of a hold
    but its last and each recorded depth, with what ``resume`` needs to continue from there
    (a :class:`CompressionProgress`, the model's state included: only models with
    :meth:`~tissue.contact.base.ContactModel.saved_state`). A resumed run takes the same path
    from there on, its records continuing the saved ones; the ``monitor`` is caught up on the
    saved steps first.
    """
    if not (np.isfinite(speed_m_s) and speed_m_s > 0):
        raise ConfigError(f"--speed must be a positive number of m/s; got {speed_m_s!r}")
    dt = model.dt
    counts = _motion_step_counts(start, stops, speed_m_s, dt)
    instability: dict[str, Any] | None = None
    if resume is None:
        model.reset()
        model.place_probe(start.position, start.quat_wxyz)
        # Paths are planned against the collision surface, so that is what must start clear
        # (a method holding the volume's boundary nodes may find one a fraction of a mm inside,
        # where the surface's flat facets cut under the curved boundary; it pushes it out in
        # step one).
        surface = model.surface.positions(model.node_positions)
        distance, _ = model.probe.signed_distance_world(surface)
        if distance.size and float(distance.min()) < 0.0:
            raise TissueInputError(
                "the probe starts inside the tissue (penetration "
                f"{-float(distance.min()) * 1e3:.2f} mm); start it clear of the surface"
            )
        steps: list[dict[str, Any]] = []
        depths: list[dict[str, Any]] = []
        motion_done, first_stop, first_step, first_settle = 0, 0, 1, 0
        position, quat = start.position.copy(), start.quat_wxyz.copy()
        level_status = StepStatus.OK
    else:
        if (
            not 0 <= resume.stops_done <= len(stops)
            or resume.stop_motion_done < 0
            or resume.settle_done < 0
        ):
            raise ConfigError(
                f"cannot resume after waypoint {resume.stops_done} (and "
                f"{resume.stop_motion_done} steps) of a path of {len(stops)}"
            )
        reached = stops[resume.stops_done - 1] if resume.stops_done else start
        position, quat = reached.position.copy(), reached.quat_wxyz.copy()
        model.load_state(resume.model_state)
        steps, depths = list(resume.steps), list(resume.depths)
        motion_done, first_stop = resume.motion_done, resume.stops_done
        first_step = resume.stop_motion_done + 1
        first_settle = resume.settle_done
        level_status = StepStatus(resume.level_status)
        if first_step == 1:
            model.place_probe(position, quat)  # mid-way, the saved state holds the pose
        if monitor is not None:
            for done in steps:
                monitor.observe(np.asarray(done["probe_pos"]), np.asarray(done["landmarks"]))

    def take(pose: NDArray[np.float64], pose_quat: NDArray[np.float64]) -> TissueStep:
        nonlocal instability
        result = model.step(pose, pose_quat)
        steps.append(_step_record(result, pose))
        if observer is not None:
            observer(result, pose)
        if monitor is not None:
            found = monitor.check(result, model.node_positions, pose)
            if found is not None:
                instability = {"step": len(steps) - 1, "kind": found.kind, "detail": found.detail}
        return result

    def progress_now(
        stops_done: int, into: int, status: StepStatus, settled: int = 0
    ) -> CompressionProgress:
        return CompressionProgress(
            stops_done, motion_done, list(steps), list(depths), model.saved_state(), into,
            status.value, settled,
        )  # fmt: skip

    for index, (stop, count) in enumerate(zip(stops, counts, strict=True)):
        if index < first_stop:
            continue
        begin, begin_quat = position, quat
        for i in range(first_step if index == first_stop else 1, count + 1):
            fraction = i / count
            pose = begin + fraction * (stop.position - begin)
            result = take(pose, _slerp(begin_quat, stop.quat_wxyz, fraction))
            level_status = worst(level_status, result.status)
            if instability is not None:
                break
            motion_done += 1
            if on_progress is not None and i < count:
                on_progress(progress_now(index, i, level_status))
        if instability is not None:
            break
        position, quat = stop.position.copy(), stop.quat_wxyz.copy()
        if stop.depth_m is None:
            continue
        # A hold resumed part-way goes on from its saved step (it was saved only before its
        # last, so at least one is left: ``result`` is this hold's).
        held = first_settle if index == first_stop else 0
        for settled in range(held + 1, max_settle_steps + 1):
            previous = model.node_positions.copy()
            result = take(position, quat)
            level_status = worst(level_status, result.status)
            speed = float(np.max(np.abs(model.node_positions - previous))) / dt
            if speed < SETTLED_SPEED_M_S or result.status.is_failure or instability is not None:
                break
            if on_progress is not None and settled < max_settle_steps:
                # On the finest level a hold is minutes of a reference's compute.
                on_progress(progress_now(index, count, level_status, settled))
        if instability is not None:
            motion_done -= 1  # the depth was reached but never held
            break
        depths.append(_depth_record(result, stop.depth_m, model, level_status))
        if on_progress is not None:
            on_progress(progress_now(index + 1, 0, StepStatus.OK))
        if progress:
            print(
                f"depth {stop.depth_m * 1e3:6.2f} mm: force {depths[-1]['force_normal_n']:8.4f} N, "
                f"penetration {result.method_penetration_m * 1e3:6.3f} mm, {level_status.value}",
                flush=True,
            )
        level_status = StepStatus.OK
    record: dict[str, Any] = {"steps": steps, "depths": depths}
    if monitor is not None:
        record["instability"] = instability
        record["stability_percent"] = 100.0 * max(motion_done, 0) / max(sum(counts), 1)
        if progress and instability is not None:
            print(f"unstable at step {instability['step']}: {instability['detail']}", flush=True)
    return record


def _motion_step_counts(
    start: Waypoint, stops: list[Waypoint], speed_m_s: float, dt: float
) -> list[int]:
    """Steps to each waypoint from the previous one at its speed (>= 1 each)."""
    counts = []
    position = start.position
    for stop in stops:
        distance = float(np.linalg.norm(stop.position - position))
        step_m = (stop.speed_m_s if stop.speed_m_s is not None else speed_m_s) * dt
        counts.append(max(1, math.ceil(distance / step_m - 1e-9)))
        position = stop.position
    return counts


def _step_record(result: TissueStep, position: NDArray[np.float64]) -> dict[str, Any]:
    return {
        "t": result.time_s,
        "probe_pos": position.tolist(),
        "force": result.force_world_n.tolist(),
        "torque": result.torque_world_nm.tolist(),
        "penetration_max_m": result.method_penetration_m,
        "skin_penetration_m": result.skin_penetration_m,
        "landmarks": result.landmarks_world_m.tolist(),
        "status": result.status.value,
        "compute_ms": result.diagnostics.compute_ms,
    }


def _depth_record(
    result: TissueStep, depth: float, model: ContactModel, status: StepStatus
) -> dict[str, Any]:
    pressing = model.probe.pressing_direction_world()
    return {
        "depth_m": depth,
        "force": result.force_world_n.tolist(),
        # The tissue pushes the probe back: report the normal force as a positive number.
        "force_normal_n": float(-result.force_world_n @ pressing),
        "penetration_max_m": result.method_penetration_m,
        "skin_penetration_m": result.skin_penetration_m,
        "landmarks": result.landmarks_world_m.tolist(),
        "status": status.value,
    }


def _slerp(a: NDArray[np.float64], b: NDArray[np.float64], t: float) -> NDArray[np.float64]:
    dot = float(a @ b)
    if dot < 0:
        b, dot = -b, -dot
    if dot > 0.9995:
        out = a + t * (b - a)
        return out / np.linalg.norm(out)
    theta = math.acos(dot)
    return (math.sin((1 - t) * theta) * a + math.sin(t * theta) * b) / math.sin(theta)


def build_model(
    mesh: TetMesh,
    shape: ProbeShape,
    method: str,
    mode: str,
    young_pa: float | None,
    poisson: float | None,
    online: bool | None,
    node_set: tuple[int, ...] | None = None,
    sliding: bool = False,
    pbd_config: PBDConfig | None = None,
) -> ContactModel:
    """The contact model for a compression, built through the front door
    (:func:`tissue.make_tissue`): the profile's defaults, unless the arguments say otherwise.

    ``online`` None takes the profile's node set for prescribed displacement (robust:
    online, sliding, the skin guarded; paper: chosen at first contact); True / False an
    online (sticking, or ``sliding``) or fixed set, without the guard, as the study runs it.
    ``pbd_config``: PBD settings instead of the profile's per-mesh calibration.
    """
    method = contact_method(method)
    if online and method != "prescribed":
        raise ConfigError(f"--online applies to --method prescribed only; got --method {method}")
    if online is None and sliding:
        online = profile_choices(mode).online_prescribed  # the profile's node set
    if sliding and not (online and method == "prescribed"):
        raise ConfigError(
            "--sliding applies to --method prescribed with an online node set (--online; the "
            f"default in robust mode); got --method {method}, online {online}"
        )
    params: Any = None
    if method == "prescribed" and (online is not None or sliding or node_set is not None):
        params = PrescribedParams(online=bool(online), sliding=sliding, node_set=node_set)
    elif method == "pbd" and pbd_config is not None:
        params = pbd_config
    spec = TissueSpec(
        mesh=mesh,
        contact=method,
        profile=mode,
        young_pa=young_pa,
        poisson=poisson,
        contact_params=params,
        probe=shape,
    )
    return make_tissue(spec).contact_model


def plan_straight(
    model: ContactModel,
    at_xy: tuple[float, float] | None,
    direction: NDArray[np.float64],
    depths_m: list[float],
) -> tuple[Waypoint, list[Waypoint]]:
    """A straight press at ``at_xy`` (default: the centre of the mesh's top in plan view)."""
    nodes = model.mesh.nodes
    if at_xy is None:
        at_xy = tuple((nodes[:, :2].min(axis=0) + nodes[:, :2].max(axis=0)) / 2)  # type: ignore[assignment]
    assert at_xy is not None
    target = np.array([at_xy[0], at_xy[1], nodes[:, 2].mean()])
    _check_press_line(model.mesh, target, direction, depths_m)
    position, quat = first_contact_pose(model.surface, nodes, model.probe.shape, target, direction)
    return straight_path(position, quat, direction, depths_m)


def _check_press_line(
    mesh: TetMesh,
    target: NDArray[np.float64],
    direction: NDArray[np.float64],
    depths_m: list[float],
) -> None:
    """Refuse a press that enters the tissue through its fixed base (pressing the chest wall
    from behind) or goes deeper than the tissue is thick along the line."""
    norm = float(np.linalg.norm(direction))
    if not (np.isfinite(norm) and norm > 0.0):
        raise ConfigError(f"--direction must be a non-zero vector; got {direction.tolist()}")
    direction = direction / norm
    faces = boundary_faces(mesh.tets)
    fixed = np.zeros(mesh.node_count, dtype=bool)
    fixed[mesh.fixed_nodes] = True
    extent = float(np.max(np.ptp(mesh.nodes, axis=0)))
    start = target - 2.0 * extent * direction
    entry = ray_surface_hit(mesh.nodes, faces, start, direction)
    if entry is None:
        return  # first_contact_pose says the line misses the tissue
    base = faces[fixed[faces].all(axis=1)]
    base_entry = ray_surface_hit(mesh.nodes, base, start, direction) if base.size else None
    if base_entry is not None and float(np.linalg.norm(base_entry - entry)) < 1e-9:
        raise ConfigError(
            f"--direction {direction.round(3).tolist()} presses the tissue's fixed base from "
            "behind; press its free surface (the phantom's top: 0,0,-1)"
        )
    exit_point = ray_surface_hit(mesh.nodes, faces, target + 2.0 * extent * direction, -direction)
    thickness = float(np.linalg.norm(exit_point - entry)) if exit_point is not None else np.inf
    if depths_m and max(depths_m) >= thickness:
        raise ConfigError(
            f"--depths up to {1e3 * max(depths_m):g} mm go through the tissue, which is "
            f"{1e3 * thickness:.1f} mm thick along this line; give smaller --depths"
        )


def plan_scene(poses: NDArray[np.float64]) -> tuple[Waypoint, list[Waypoint]]:
    """The published scene's path: Transform0 (at rest) then Transform1..4, each a depth."""
    start_position, start_quat = Probe.pose_from_matrix(poses[0])
    stops = []
    for transform in poses[1:]:
        position, quat = Probe.pose_from_matrix(transform)
        pressing = transform[:3, :3] @ np.array([0.0, 1.0, 0.0])
        depth = float((position - start_position) @ pressing)
        stops.append(Waypoint(position, quat, depth))
    return Waypoint(start_position, start_quat, None), stops


def write_json(record: dict[str, Any], path: Path) -> None:
    """The record as strict JSON (non-finite numbers as null)."""
    from agents.outputs import write_json as write_strict

    write_strict(record, path)
