"""The hard-case catalogue: named scenarios that must stay numerically stable.

Each :class:`HardCase` fixes a mesh level, material, penalty stiffness, probe speed and a
probe path; :func:`run_hard_case` runs one with any contact method and configuration and
judges every step with :class:`tissue.contact.stability.StabilityMonitor` (status, NaN/Inf,
penetration bound, blow-up, landmark jumps beyond the probe's motion, time-out), plus an
energy check for the FE methods: the tissue's elastic plus kinetic energy never exceeds the
work the probe has done on it (trapezoidal rule over the probe's displacement).

Scenarios (``HARD_CASES``), all on the built-in phantom unless said:

===================  ====================================================================
name                 what
===================  ====================================================================
fine_105k            the 105,004-tet level, 10 and 20 mm at the dome's top
fine_176k            the 176,506-tet level, 10 and 20 mm at the dome's top
deep_30mm            10, 20, 25 and 30 mm at the dome's top
paper_level4         the published scene's real poses up to level 4 (26-29 mm), tumour 1
nu_0499              nu = 0.499 (near-incompressible; the default is 0.49)
stiff_lesions        lesions 10 x stiffer than the tissue (default 4 x)
penalty_soft         k_s / 10 (penalty only differs)
penalty_stiff        k_s x 100 (three decades with penalty_soft)
fast_probe           0.1 m/s, ten times the paper's speed, to 20 mm
tilted_30            pressing direction 30 degrees from the skin normal, to 15 mm
edge_contact         probe rolled 60 degrees about its long axis: its edge presses, 10 mm
sliding_40mm         15 mm deep, then 40 mm along the skin at that depth
sudden_release       20 mm deep, then withdrawn to the start in one step, then held
===================  ====================================================================

Unlike the compression study, the landmark-jump check is on: these paths are at the dome's
top, where the tissue cannot slip out from under the probe.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from agents.lab.compress import Waypoint, plan_scene, run_compression, straight_path
from agents.outputs import write_json
from tissue import (
    ConfigError,
    ContactModel,
    NeoHookean,
    ProbeShape,
    TissueMaterials,
    TissueStep,
)
from tissue.lab import (
    PBDConfig,
    PenaltyParams,
    PrescribedParams,
    Probe,
    SimulationConfig,
    StabilityMonitor,
    TetMesh,
    contact_method,
    contact_surface,
    default_stiffness_n_per_m,
    first_contact_pose,
    make_contact_model,
    model_surface,
    parse_probe_spec,
    profile_choices,
    quat_to_matrix,
)

# The energy check allows this much above the work done, relative and absolute [J].
_ENERGY_SLACK_RELATIVE = 0.02
_ENERGY_SLACK_J = 1e-6
# Hold after the last waypoint of a case without levels (steps).
_HOLD_STEPS = 25


@dataclass(frozen=True)
class HardCase:
    """One named scenario (see the module docstring).

    Attributes:
        name: its name.
        description: one line.
        level: phantom level (tet count), or the published scene's level (0: its own mesh).
        path: ``press``, ``tilted``, ``edge``, ``slide``, ``release`` or ``paper``.
        depths_m: depths past first contact [m] (``press``, ``tilted``, ``edge``).
        poisson: the tissue's Poisson ratio.
        lesion_stiffness_ratio: E_lesion / E_tissue.
        penalty_stiffness_scale: k_s relative to the default.
        speed_m_s: probe speed [m/s].
        angle_deg: the tilt (``tilted``) or roll about the long axis (``edge``) [degrees].
    """

    name: str
    description: str
    level: int = 1363
    path: str = "press"
    depths_m: tuple[float, ...] = (0.01, 0.02)
    poisson: float = 0.49
    lesion_stiffness_ratio: float = 4.0
    penalty_stiffness_scale: float = 1.0
    speed_m_s: float = 0.01
    angle_deg: float = 0.0


HARD_CASES: dict[str, HardCase] = {
    case.name: case
    for case in (
        HardCase("fine_105k", "the 105,004-tet level", level=105004),
        HardCase("fine_176k", "the 176,506-tet level", level=176506),
        HardCase("deep_30mm", "30 mm at the dome's top", depths_m=(0.01, 0.02, 0.025, 0.03)),
        HardCase(
            "paper_level4", "the published poses to level 4 (26-29 mm)", level=0, path="paper"
        ),  # fmt: skip
        HardCase("nu_0499", "nu = 0.499", poisson=0.499),
        HardCase("stiff_lesions", "lesions 10 x stiffer", lesion_stiffness_ratio=10.0),
        HardCase("penalty_soft", "k_s / 10", penalty_stiffness_scale=0.1),
        HardCase("penalty_stiff", "k_s x 100", penalty_stiffness_scale=100.0),
        HardCase("fast_probe", "0.1 m/s to 20 mm", speed_m_s=0.1),
        HardCase(
            "tilted_30",
            "30 degrees off the normal, 15 mm",
            path="tilted",
            depths_m=(0.015,),
            angle_deg=30.0,
        ),  # fmt: skip
        HardCase(
            "edge_contact",
            "rolled 60 degrees: the edge presses, 10 mm",
            path="edge",
            depths_m=(0.01,),
            angle_deg=60.0,
        ),  # fmt: skip
        HardCase("sliding_40mm", "15 mm deep, 40 mm along the skin", path="slide"),
        HardCase("sudden_release", "20 mm deep, withdrawn in one step", path="release"),
    )
}

#: The cases that run on the small default mesh in seconds (the fast test tier's).
SMALL_CASES = tuple(
    name for name, case in HARD_CASES.items() if case.level < 10000 and case.path != "paper"
)


def hard_case(name: str) -> HardCase:
    """The case named ``name``; a clear error listing the catalogue otherwise."""
    if name not in HARD_CASES:
        raise ConfigError(f"unknown hard case {name!r}; choose one of {sorted(HARD_CASES)}")
    return HARD_CASES[name]


def build_case_model(
    case: HardCase, method: str, config: str, mesh: TetMesh, shape: ProbeShape
) -> ContactModel:
    """The contact model of ``case`` for ``method`` in configuration ``config``."""
    method = contact_method(method)
    materials = TissueMaterials(
        tissue=NeoHookean(poisson=case.poisson),
        lesion_stiffness_ratio=case.lesion_stiffness_ratio,
    )
    if method == "pbd":
        return make_contact_model(
            method, mesh, shape, materials=materials, config=PBDConfig.for_profile(config)
        )
    kwargs: dict[str, Any] = {"materials": materials, "config": SimulationConfig(mode=config)}
    if method == "penalty":
        surface = model_surface(mesh, kwargs["config"])
        default = default_stiffness_n_per_m(surface, mesh, materials)
        kwargs["params"] = PenaltyParams(stiffness_n_per_m=default * case.penalty_stiffness_scale)
    elif method == "prescribed":
        # As the profile runs it: robust holds an online, sliding node set with the skin
        # guarded (PrescribedContact.profile_params); paper, the set found at first contact.
        online = profile_choices(config).online_prescribed
        kwargs["params"] = PrescribedParams(online=online, sliding=online, skin_guard=online)
    return make_contact_model(method, mesh, shape, **kwargs)


def case_path(
    case: HardCase, mesh: TetMesh, shape: ProbeShape, scene_dir: Path | None = None
) -> tuple[Waypoint, list[Waypoint]]:
    """The probe's start and waypoints for ``case`` on ``mesh``."""
    if case.path == "paper":
        if scene_dir is None:
            raise ConfigError(f"hard case {case.name} needs the published scene directory")
        from tissue.lab import load_paper_scene

        scene = load_paper_scene(scene_dir)
        return plan_scene(scene.probe_poses[scene.tumour_ids[0]])
    surface = contact_surface(mesh)
    # A point just under the dome's top: every line of approach through it enters the skin.
    top = np.array([0.0, 0.0, float(mesh.nodes[:, 2].max()) - 0.005])
    down = np.array([0.0, 0.0, -1.0])
    if case.path in ("press", "tilted", "edge", "release"):
        direction = down
        if case.path == "tilted":  # tilt about the probe's short axis: one end leads
            angle = math.radians(case.angle_deg)
            direction = np.array([math.sin(angle), 0.0, -math.cos(angle)])
        if case.path == "edge":
            position, quat = _edge_pose(surface, mesh, shape, top, case.angle_deg)
        else:
            position, quat = first_contact_pose(surface, mesh.nodes, shape, top, direction)
        if case.path == "release":
            start, stops = straight_path(position, quat, direction, [0.02])
            back = Waypoint(start.position.copy(), quat, None, math.inf)
            return start, [*stops, back]
        return straight_path(position, quat, direction, list(case.depths_m))
    if case.path == "slide":
        depth, half = 0.015, 0.02
        poses = [
            first_contact_pose(surface, mesh.nodes, shape, np.array([x, 0.0, top[2]]), down)
            for x in np.linspace(-half, half, 9)
        ]
        start, stops = straight_path(poses[0][0], poses[0][1], down, [depth])
        # Along the skin at that depth: each pose's first contact, pressed ``depth`` further.
        for index, (position, quat) in enumerate(poses[1:], start=1):
            last = index == len(poses) - 1
            stops.append(Waypoint(position + depth * down, quat, depth if last else None))
        return start, stops
    raise ConfigError(f"hard case {case.name}: unknown path {case.path!r}")


def _edge_pose(
    surface: Any, mesh: TetMesh, shape: ProbeShape, target: NDArray[np.float64], angle_deg: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """First contact of the probe turned ``angle_deg`` about its long axis (x), pressing
    straight down: the long edge of the face meets the skin first.

    Contact here is with the collision surface's vertices and the volume's boundary nodes
    alike (the points the FE methods and PBD hold): turned this far, the probe's side meets
    the coarse levels' boundary nodes between collision vertices, and starting it in contact
    with only the latter left a node 1.1 mm inside it at level 4126 (PBD, which holds the
    nodes, then jolted the tissue in its first step).
    """
    angle = math.radians(angle_deg)
    # Pressing direction (the probe's +y) tilted about world x; the long axis stays along x.
    direction = np.array([0.0, math.sin(angle), -math.cos(angle)])
    position, quat = first_contact_pose(surface, mesh.nodes, shape, target, direction)
    # Move it down along -z to first contact (the edge leads), keeping the orientation.
    probe = Probe(shape)
    probe.set_pose(position, quat)
    vertices = np.concatenate(
        [surface.positions(mesh.nodes), mesh.nodes[np.unique(mesh.boundary_triangles())]]
    )
    for _ in range(8):
        distance, _ = probe.signed_distance_world(vertices)
        closest = float(distance.min())
        if abs(closest) < 1e-9:
            break
        probe.set_pose(probe.position_world + closest * np.array([0.0, 0.0, -1.0]), quat)
    return probe.position_world.copy(), quat


def run_hard_case(
    name: str,
    method: str,
    config: str = "robust",
    level: int | None = None,
    scene_dir: Path | None = None,
) -> dict[str, Any]:
    """Run hard case ``name`` with ``method`` in ``config``; returns its record.

    Args:
        level: override the case's mesh level (tests run the cases on small meshes).
        scene_dir: the published scene (``paper_level4`` only).

    Returns:
        ``case``, ``method``, ``config``, ``tets``, ``stable`` (every check passed),
        ``stability_percent``, ``instability`` (or None), ``energy_ok``, ``energy_excess_j``,
        ``penetration_max_m``, ``median_step_ms``, ``max_step_ms``, ``steps``,
        ``subdivisions`` (robust steps that were split), ``depths`` (per recorded depth).
    """
    case = hard_case(name)
    if level is not None:
        case = replace(case, level=level)
    shape = parse_probe_spec("face")
    if case.path == "paper":
        if scene_dir is None:
            raise ConfigError(f"hard case {name} needs the published scene (scene_dir)")
        from tissue.lab import load_paper_scene, remesh_paper_scene

        mesh = (
            load_paper_scene(scene_dir).mesh
            if case.level == 0
            else remesh_paper_scene(scene_dir, case.level)
        )
    else:
        from tissue.lab import breast_phantom

        mesh = breast_phantom(case.level)
    model = build_case_model(case, method, config, mesh, shape)
    start, stops = case_path(case, mesh, shape, scene_dir)
    if case.path in ("release", "slide") and stops[-1].depth_m is None:
        stops = [*stops, replace(stops[-1], depth_m=0.0)]
    monitor = StabilityMonitor(method, mesh.nodes, start.position)
    energy = _EnergyCheck(model, start.position, start.quat_wxyz)
    started = time.perf_counter()
    run = run_compression(model, start, stops, case.speed_m_s, monitor=monitor, observer=energy)
    times = [step["compute_ms"] for step in run["steps"]]
    instability = run["instability"]
    return {
        "case": name,
        "method": contact_method(method),
        "config": config,
        "level": case.level,
        "tets": mesh.tet_count,
        "stable": instability is None and energy.ok,
        "stability_percent": run["stability_percent"],
        "instability": instability,
        "energy_ok": energy.ok,
        "energy_excess_j": energy.worst_excess_j,
        "penetration_max_m": max(step["penetration_max_m"] for step in run["steps"]),
        "median_step_ms": float(np.median(times)),
        "max_step_ms": float(np.max(times)),
        "steps": len(times),
        "subdivisions": energy.subdivided_steps,
        "depths": run["depths"],
        "wall_s": time.perf_counter() - started,
    }


class _EnergyCheck:
    """Elastic + kinetic energy <= work done by the probe (FE methods; PBD has no energy)."""

    def __init__(
        self,
        model: ContactModel,
        start_position: NDArray[np.float64],
        start_quat: NDArray[np.float64],
    ) -> None:
        self.model = model
        self.sim = getattr(model, "sim", None)
        self.work_j = 0.0
        self.worst_excess_j = 0.0
        self.ok = True
        self.subdivided_steps = 0
        self._last_position = np.asarray(start_position, dtype=np.float64).copy()
        self._last_rotation = quat_to_matrix(start_quat)

    def __call__(self, result: TissueStep, position: NDArray[np.float64]) -> None:
        if result.diagnostics.subdivisions:
            self.subdivided_steps += 1
        # Backward Euler's discrete work: the end-of-step wrench times the step's motion (a
        # probe withdrawn in one step, whose end force is 0, takes no work back). The torque
        # is about the probe origin, so the two terms are the translation's and the
        # rotation's (the published poses turn the probe by up to a few degrees a level).
        rotation = quat_to_matrix(self.model.probe.quat_wxyz)
        turned = Rotation.from_matrix(rotation @ self._last_rotation.T).as_rotvec()
        self.work_j += float(-result.force_world_n @ (position - self._last_position))
        self.work_j += float(-result.torque_world_nm @ turned)
        self._last_position = np.asarray(position).copy()
        self._last_rotation = rotation
        if self.sim is None or result.status.is_failure:
            return
        stored = self.sim.elastic_energy_j() + self.sim.kinetic_energy_j()
        excess = stored - self.work_j
        self.worst_excess_j = max(self.worst_excess_j, excess)
        if excess > _ENERGY_SLACK_RELATIVE * abs(self.work_j) + _ENERGY_SLACK_J:
            self.ok = False


def run_catalogue(
    cases: list[str],
    methods: list[str],
    configs: list[str],
    level: int | None,
    scene_dir: Path | None,
    json_path: Path | None,
) -> list[dict[str, Any]]:
    """Run every case x method x configuration; print a table, write JSON; the records."""

    for name in cases:
        hard_case(name)
    for method in methods:
        contact_method(method)
    records = []
    header = (
        f"{'case':16} {'method':10} {'config':7} {'tets':>7} {'stable':>6} {'%':>5} "
        f"{'pen mm':>7} {'med ms':>8} {'max ms':>8}  instability"
    )
    print(header)
    print("-" * len(header))
    for name in cases:
        for method in methods:
            for config in configs:
                record = run_hard_case(name, method, config, level, scene_dir)
                records.append(record)
                found = record["instability"]
                why = "" if found is None else f"{found['kind']}: {found['detail']}"
                if not record["energy_ok"]:
                    why += f" energy exceeds work by {record['energy_excess_j']:.2e} J"
                print(
                    f"{name:16} {record['method']:10} {config:7} {record['tets']:>7} "
                    f"{'yes' if record['stable'] else 'NO':>6} {record['stability_percent']:5.0f} "
                    f"{record['penetration_max_m'] * 1e3:7.3f} {record['median_step_ms']:8.2f} "
                    f"{record['max_step_ms']:8.1f}  {why}",
                    flush=True,
                )
    if json_path is not None:
        json_path.parent.mkdir(parents=True, exist_ok=True)
        write_json(records, json_path, indent=1)
        print(f"written: {json_path}")
    return records
