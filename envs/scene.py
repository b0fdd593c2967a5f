"""The MuJoCo scene: an arm holding the linear probe over a table that carries the phantom.

Built with ``MjSpec`` from ``assets/robots/ur5e.xml`` (or any MJCF arm with a flange site):
the arm is attached at its base pose on the table, the probe at the arm's flange with a
force-torque sensor site between them, and two cameras (``overview``, ``probe_side``). The
breast is not a MuJoCo body: the FE tissue (``tissue``) is simulated outside MuJoCo and its
reaction applied to the probe (:mod:`envs.coupling`). For drawing, :func:`build_scene` can add
the deformed breast as display-only flexes whose vertices are mocap bodies (the skin and each
lesion), which :class:`envs.rendering.SceneRenderer` moves before each frame; the scene the
physics steps leaves them out (600-odd bodies of kinematics every substep, for nothing).

The probe body's frame *is* the tissue's probe frame (``tissue`` module docstring): origin
at the centre of the contact face, +y pressing, x the image's lateral axis, z elevation. Its
site is named ``probe``.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np
from numpy.typing import NDArray

import tissue
from envs.errors import EnvConfigError

ASSETS = Path(__file__).resolve().parents[1] / "assets"
#: The default arm: the UR5e's kinematics and dynamics in primitive geometry.
UR5E_PATH = ASSETS / "robots" / "ur5e.xml"
UR5E_FLANGE_SITE = "flange"
#: A redundant 7-joint arm of the UR5e's dimensions (an upper-arm roll added), for arms other
#: than the default: ``gymnasium.make(..., robot=ARM7_PATH)``.
ARM7_PATH = ASSETS / "robots" / "arm7.xml"
#: The keyframe of an arm's MJCF whose joint angles seed its home pose's IK, where it has one.
HOME_KEY = "home"

# The linear probe as drawn and weighed (the tissue's contact shape is the same face: 52.9 x
# 13.2 mm, backed by an 80 mm housing; tissue.probe.linear_probe).
PROBE_MASS_KG = 0.25
FACE_PLATE_M = 0.0027

ROBOT_PREFIX = "robot/"
PROBE_BODY = "probe"
PROBE_SITE = "probe"
FT_SITE = "ft_sensor"
FORCE_SENSOR = "ft_force"
#: The rigid breast's geom and mesh (:mod:`envs.rigid`).
RIGID_BREAST_GEOM = "breast_rigid"
#: The contact bit the probe's face shares with the table (the chest wall under the
#: phantom's fixed base) and the rigid breast, and nothing else (MuJoCo's default, 1, is the
#: arm's): a probe pressed past the breast's flank stops on the table, as on a chest wall.
RIGID_CONTACT_BIT = 2
TORQUE_SENSOR = "ft_torque"


@dataclass(frozen=True)
class SceneConfig:
    """The scene's layout.

    Attributes:
        robot_path: the arm's MJCF (default: the UR5e model in ``assets/robots``).
        flange_site: the name of the arm's flange site (its z axis out of the flange).
        robot_base_m: where the arm's base stands [m], world frame (the phantom's base is
            the table top, z = 0, centred at the origin).
        robot_dt: MuJoCo's time step [s].
    """

    robot_path: str | Path = UR5E_PATH
    flange_site: str = UR5E_FLANGE_SITE
    robot_base_m: tuple[float, float, float] = (-0.42, 0.0, 0.0)
    robot_dt: float = 0.002

    def __post_init__(self) -> None:
        path = Path(self.robot_path)
        if not path.is_file():
            raise EnvConfigError(
                f"robot={str(path)!r} does not exist; give an MJCF file of an arm with a "
                f"flange site (the default is {UR5E_PATH})"
            )
        if not (isinstance(self.robot_dt, float) and 0.0 < self.robot_dt <= 0.01):
            raise EnvConfigError(
                f"robot_dt must be a time step in seconds in (0, 0.01]; got {self.robot_dt!r}"
            )
        base = np.asarray(self.robot_base_m, dtype=np.float64)
        if base.shape != (3,) or not np.all(np.isfinite(base)):
            raise EnvConfigError(f"robot_base_m must be 3 finite metres; got {self.robot_base_m!r}")


@dataclass(frozen=True)
class SceneNames:
    """Ids of what the environment reads and drives in a compiled scene."""

    joint_qpos: NDArray[np.int64]
    joint_dof: NDArray[np.int64]
    actuators: NDArray[np.int64]
    probe_body: int
    probe_site: int
    ft_site: int
    force_sensor_adr: int
    torque_sensor_adr: int
    torque_limits: NDArray[np.float64]
    joint_ranges: NDArray[np.float64]


def build_scene(
    config: SceneConfig,
    probe_shape: tissue.ProbeShape | None = None,
    surface: tissue.SurfaceMesh | None = None,
    rigid_breast: tissue.SurfaceMesh | None = None,
) -> mujoco.MjModel:
    """Compile the scene; with ``surface``, the breast's flexes too (for drawing only).

    Args:
        config: the layout.
        probe_shape: the tissue's probe (only its outline is drawn: a stadium of its local
            bounds' length and width), default the linear probe.
        surface: the tissue's surface at rest (:meth:`tissue.Tissue.surface`): one mocap body
            per vertex, a flex per region.
        rigid_breast: the tissue's surface at rest, for the rigid breast (:mod:`envs.rigid`):
            a static mesh geom of its skin that the probe's face collides with.
    """
    spec = mujoco.MjSpec()
    spec.modelname = "probegym"
    spec.option.timestep = config.robot_dt
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    spec.visual.global_.offwidth = 1280
    spec.visual.global_.offheight = 960
    spec.visual.quality.shadowsize = 0  # no shadow map: 30-36 ms a 480 x 480 frame, not 170
    _add_stage(spec)
    arm = mujoco.MjSpec.from_file(str(config.robot_path))
    base = spec.worldbody.add_frame(pos=list(config.robot_base_m))
    spec.attach(arm, frame=base, prefix=ROBOT_PREFIX)
    flange = spec.site(ROBOT_PREFIX + config.flange_site)
    if flange is None:
        names = [site.name for site in spec.sites if site.name.startswith(ROBOT_PREFIX)]
        raise EnvConfigError(
            f"the arm in {config.robot_path} has no site {config.flange_site!r}; its sites: "
            f"{[name[len(ROBOT_PREFIX) :] for name in names]} (give flange_site=NAME)"
        )
    _add_probe(spec, flange, probe_shape)
    if surface is not None:
        _add_breast(spec, surface)
    if rigid_breast is not None:
        _add_rigid_breast(spec, rigid_breast)
    return _compile(spec)


def scene_names(model: mujoco.MjModel) -> SceneNames:
    """The ids the environment needs (the arm's hinge joints in order, its motors, ...)."""
    joints = [
        j
        for j in range(model.njnt)
        if model.joint(j).name.startswith(ROBOT_PREFIX)
        and model.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE
    ]
    actuators = [
        a
        for a in range(model.nu)
        if model.actuator_trntype[a] == mujoco.mjtTrn.mjTRN_JOINT
        and model.actuator_trnid[a, 0] in joints
    ]
    if not joints or len(actuators) != len(joints):
        raise EnvConfigError(
            f"the arm must have a motor on each of its hinge joints; found {len(joints)} "
            f"hinges and {len(actuators)} joint motors"
        )
    by_joint = {int(model.actuator_trnid[a, 0]): a for a in actuators}
    ordered = [by_joint[j] for j in joints]
    limits = np.array(
        [
            model.actuator_ctrlrange[a, 1] if model.actuator_ctrllimited[a] else np.inf
            for a in ordered
        ]
    )
    force = model.sensor(FORCE_SENSOR)
    torque = model.sensor(TORQUE_SENSOR)
    return SceneNames(
        joint_qpos=np.array([model.jnt_qposadr[j] for j in joints], dtype=np.int64),
        joint_dof=np.array([model.jnt_dofadr[j] for j in joints], dtype=np.int64),
        actuators=np.array(ordered, dtype=np.int64),
        probe_body=model.body(PROBE_BODY).id,
        probe_site=model.site(PROBE_SITE).id,
        ft_site=model.site(FT_SITE).id,
        force_sensor_adr=int(model.sensor_adr[force.id]),
        torque_sensor_adr=int(model.sensor_adr[torque.id]),
        torque_limits=limits,
        joint_ranges=np.array([model.jnt_range[j] for j in joints]),
    )


def _add_stage(spec: mujoco.MjSpec) -> None:
    """Floor, table, lights and the two named cameras."""
    world = spec.worldbody
    world.add_light(pos=[0.3, -0.6, 1.4], dir=[-0.2, 0.4, -1.0], diffuse=[0.8, 0.8, 0.8])
    world.add_light(pos=[-0.6, 0.6, 1.2], dir=[0.4, -0.4, -1.0], diffuse=[0.4, 0.4, 0.4])
    world.add_geom(
        name="floor",
        type=mujoco.mjtGeom.mjGEOM_PLANE,
        size=[2.0, 2.0, 0.05],
        pos=[0.0, 0.0, -0.75],
        rgba=[0.55, 0.57, 0.6, 1.0],
        contype=0,
        conaffinity=0,
    )
    world.add_geom(
        name="table",
        type=mujoco.mjtGeom.mjGEOM_BOX,
        size=[0.45, 0.35, 0.375],
        pos=[-0.15, 0.0, -0.375],
        rgba=[0.85, 0.85, 0.82, 1.0],
        contype=RIGID_CONTACT_BIT,
        conaffinity=RIGID_CONTACT_BIT,
    )
    for name, position, target in (
        ("overview", (0.42, -0.62, 0.48), (-0.12, 0.0, 0.12)),
        ("probe_side", (0.02, -0.30, 0.13), (0.0, 0.0, 0.045)),
    ):
        world.add_camera(
            name=name, pos=list(position), xyaxes=_look_at(position, target), fovy=45.0
        )


def _look_at(position: tuple[float, ...], target: tuple[float, ...]) -> list[float]:
    """A camera's xyaxes looking from ``position`` at ``target`` [m], world z up."""
    forward = np.subtract(target, position)
    forward /= np.linalg.norm(forward)
    x_axis = np.cross(forward, [0.0, 0.0, 1.0])
    x_axis /= np.linalg.norm(x_axis)
    y_axis = np.cross(x_axis, forward)
    return [*x_axis.tolist(), *y_axis.tolist()]


def _add_probe(
    spec: mujoco.MjSpec, flange: mujoco.MjsSite, probe_shape: tissue.ProbeShape | None
) -> None:
    """The probe on the flange: its frame is the tissue's probe frame, its +y along the
    flange's z, its back (the housing's end) on the flange, the F/T site there. Its face
    collides with the table and the rigid breast (:data:`RIGID_CONTACT_BIT`)."""
    shape = probe_shape if probe_shape is not None else _default_probe()
    low, high = shape.local_bounds_m()
    length = float(high[0] - low[0])
    width = float(high[2] - low[2])
    depth = float(-low[1])
    holder = flange.parent.add_frame(pos=list(flange.pos), quat=list(flange.quat))
    # Probe frame -> flange frame: x -> x, y -> z, z -> -y (a quarter turn about x).
    half = math.sqrt(0.5)
    probe = holder.add_body(name=PROBE_BODY, pos=[0.0, 0.0, depth], quat=[half, half, 0.0, 0.0])
    probe.mass = PROBE_MASS_KG
    probe.ipos = [0.0, -0.5 * depth, 0.0]
    probe.inertia = [
        PROBE_MASS_KG * (depth**2 + width**2) / 12.0,
        PROBE_MASS_KG * (length**2 + width**2) / 12.0,
        PROBE_MASS_KG * (length**2 + depth**2) / 12.0,
    ]
    probe.explicitinertial = True
    radius = 0.5 * width
    straight = max(0.5 * length - radius, 1e-4)
    housing = [0.2, 0.22, 0.26, 1.0]
    face = [0.15, 0.35, 0.75, 1.0]
    for name, y_from, y_to, rgba in (
        ("housing", -depth, -FACE_PLATE_M, housing),
        ("face", -FACE_PLATE_M, 0.0, face),
    ):
        middle, half_height = 0.5 * (y_from + y_to), 0.5 * (y_to - y_from)
        bit = RIGID_CONTACT_BIT if name == "face" else 0
        probe.add_geom(
            name=f"probe_{name}",
            type=mujoco.mjtGeom.mjGEOM_BOX,
            size=[straight, half_height, radius],
            pos=[0.0, middle, 0.0],
            rgba=rgba,
            contype=bit,
            conaffinity=bit,
            mass=0.0,
        )
        for sign in (-1.0, 1.0):
            probe.add_geom(
                name=f"probe_{name}_end{'+' if sign > 0 else '-'}",
                type=mujoco.mjtGeom.mjGEOM_CYLINDER,
                size=[radius, half_height, 0.0],
                pos=[sign * straight, middle, 0.0],
                quat=[half, half, 0.0, 0.0],
                rgba=rgba,
                contype=bit,
                conaffinity=bit,
                mass=0.0,
            )
    probe.add_site(name=PROBE_SITE, pos=[0.0, 0.0, 0.0], size=[0.003, 0.003, 0.003])
    probe.add_site(name=FT_SITE, pos=[0.0, -depth, 0.0], size=[0.006, 0.006, 0.006])
    spec.add_sensor(
        name=FORCE_SENSOR,
        type=mujoco.mjtSensor.mjSENS_FORCE,
        objtype=mujoco.mjtObj.mjOBJ_SITE,
        objname=FT_SITE,
    )
    spec.add_sensor(
        name=TORQUE_SENSOR,
        type=mujoco.mjtSensor.mjSENS_TORQUE,
        objtype=mujoco.mjtObj.mjOBJ_SITE,
        objname=FT_SITE,
    )


def _default_probe() -> tissue.ProbeShape:
    return tissue.TissueSpec(mesh=623).probe_shape()


#: Colours of the drawn breast: skin (see-through, so the lesions show) and lesions.
SKIN_RGBA = (0.93, 0.76, 0.66, 0.4)
LESION_RGBA = (0.75, 0.08, 0.1, 1.0)


def breast_vertex_body(index: int) -> str:
    return f"breast/v{index}"


def _add_breast(spec: mujoco.MjSpec, surface: tissue.SurfaceMesh) -> None:
    """One mocap body per surface vertex and display-only 2-D flexes: the lesions (red) and
    the skin (see-through), the skin in patches (MuJoCo sorts see-through objects by their
    distance to the camera, not the triangles within one: a single skin flex blended its far
    side over its near side in patches), its base on the table left out."""
    world = spec.worldbody
    for index, position in enumerate(surface.vertices_m):
        world.add_body(name=breast_vertex_body(index), mocap=True, pos=list(position))
    for name, triangles, rgba in _breast_parts(surface):
        used = np.unique(triangles)
        local = np.searchsorted(used, triangles)
        flex = spec.add_flex()
        flex.name = name
        flex.dim = 2
        flex.vertbody = [breast_vertex_body(int(v)) for v in used]
        flex.elem = local.reshape(-1).astype(int).tolist()
        flex.rgba = list(rgba)
        flex.radius = 0.0005
        flex.contype = 0
        flex.conaffinity = 0


def _add_rigid_breast(spec: mujoco.MjSpec, surface: tissue.SurfaceMesh) -> None:
    """The rest skin as one static mesh geom (collided by its convex hull) that only the
    probe's face touches."""
    skin = surface.triangles[surface.triangle_region == 0]
    used = np.unique(skin)
    spec.add_mesh(
        name=RIGID_BREAST_GEOM,
        uservert=surface.vertices_m[used].reshape(-1).tolist(),
        userface=np.searchsorted(used, skin).reshape(-1).astype(int).tolist(),
    )
    spec.worldbody.add_geom(
        name=RIGID_BREAST_GEOM,
        type=mujoco.mjtGeom.mjGEOM_MESH,
        meshname=RIGID_BREAST_GEOM,
        rgba=list(SKIN_RGBA[:3]) + [1.0],
        contype=RIGID_CONTACT_BIT,
        conaffinity=RIGID_CONTACT_BIT,
    )


#: The skin's patches: azimuth and elevation bins about the skin's centre.
_PATCHES = (12, 4)


def _breast_parts(
    surface: tissue.SurfaceMesh,
) -> list[tuple[str, NDArray[np.int64], tuple[float, float, float, float]]]:
    """(flex name, triangles, colour) of each part drawn."""
    vertices, triangles, region = surface.vertices_m, surface.triangles, surface.triangle_region
    corners = vertices[triangles]
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normal /= np.maximum(np.linalg.norm(normal, axis=1), 1e-300)[:, None]
    parts = []
    for label in np.unique(region[region > 0]):
        parts.append((f"lesion_{label}", triangles[region == label], LESION_RGBA))
    skin = (region == 0) & (normal[:, 2] > -0.9)  # the base faces the table: not drawn
    centre = vertices[np.unique(triangles[region == 0])].mean(axis=0)
    middle = corners.mean(axis=1) - centre
    azimuth = np.arctan2(middle[:, 1], middle[:, 0])
    elevation = np.arctan2(middle[:, 2], np.hypot(middle[:, 0], middle[:, 1]))
    a_bins, e_bins = _PATCHES
    a_index = np.clip(((azimuth + np.pi) / (2 * np.pi) * a_bins).astype(int), 0, a_bins - 1)
    e_index = np.clip(((elevation + 0.5 * np.pi) / np.pi * e_bins).astype(int), 0, e_bins - 1)
    patch = a_index * e_bins + e_index
    for index in np.unique(patch[skin]):
        parts.append((f"skin_{index}", triangles[skin & (patch == index)], SKIN_RGBA))
    return parts


def _compile(spec: mujoco.MjSpec) -> mujoco.MjModel:
    """Compile, keeping MuJoCo's harmless warning about display-only flexes ("not rigid and
    has no equality constraints or passive forces") off the terminal."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*is not rigid and has no equality.*")
        return spec.compile()
