"""What the probe's owner can measure: the lesion in the image plane and the F/T wrench.

Image plane of a linear probe (probe frame, ``tissue`` module docstring): lateral = x,
depth = y (into the tissue), out-of-plane = z (elevation). A lesion is *visible* when the
probe touches the skin (the tissue pushes on it), the lesion lies inside the aperture
(|lateral| <= aperture / 2) and the imaging depth (0 < depth <= imaging depth), and its
distance from the plane is under half the slice thickness plus its radius. Out of view, the
observation is zeros and the flag 0: the policy is told only what a sonographer would see.
Defaults are the paper's Telemed L12-5N40 linear probe: about 40 mm aperture, 50 mm depth,
2 mm slice thickness.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np
from numpy.typing import NDArray

import tissue
from envs.controller import cross3
from envs.errors import EnvConfigError
from envs.scene import SceneNames

#: A contact force below this [N] does not count as touching the skin.
TOUCH_FORCE_N = 1e-3


@dataclass(frozen=True)
class ImagingConfig:
    """The linear probe's imaging geometry [m].

    Attributes:
        aperture_m: width of the image (the array's length used), centred on the probe.
        imaging_depth_m: deepest point imaged, from the face.
        slice_thickness_m: thickness of the imaged slice (elevation).
    """

    aperture_m: float = 0.040
    imaging_depth_m: float = 0.050
    slice_thickness_m: float = 0.002

    def __post_init__(self) -> None:
        for name in ("aperture_m", "imaging_depth_m", "slice_thickness_m"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and np.isfinite(value) and value > 0):
                raise EnvConfigError(f"{name} must be a positive length in metres; got {value!r}")


@dataclass(frozen=True)
class LesionInImage:
    """A lesion in the probe's image plane.

    Attributes:
        lateral_m, depth_m, out_of_plane_m: its centroid in the probe frame [m] (zeros when
            not visible).
        visible: whether a sonographer would see it (module docstring).
        true_lateral_m, true_depth_m, true_out_of_plane_m: the same whether visible or not
            (for rewards and checks, not for the policy).
    """

    lateral_m: float
    depth_m: float
    out_of_plane_m: float
    visible: bool
    true_lateral_m: float
    true_depth_m: float
    true_out_of_plane_m: float

    def as_array(self) -> NDArray[np.float32]:
        return np.array(
            [self.lateral_m, self.depth_m, self.out_of_plane_m, float(self.visible)],
            dtype=np.float32,
        )


def lesion_in_image(
    centroid_world_m: NDArray[np.float64],
    radius_m: float,
    probe_pos_world: NDArray[np.float64],
    probe_rot_world: NDArray[np.float64],
    contact_force_n: float,
    imaging: ImagingConfig,
) -> LesionInImage:
    """Where a lesion lies in the image plane, and whether it is visible (module docstring)."""
    local = probe_rot_world.T @ (centroid_world_m - probe_pos_world)
    lateral, depth, out_of_plane = (float(v) for v in local)
    visible = (
        contact_force_n > TOUCH_FORCE_N
        and abs(lateral) <= 0.5 * imaging.aperture_m
        and 0.0 < depth <= imaging.imaging_depth_m
        and abs(out_of_plane) <= 0.5 * imaging.slice_thickness_m + radius_m
    )
    shown = (lateral, depth, out_of_plane) if visible else (0.0, 0.0, 0.0)
    return LesionInImage(*shown, visible, lateral, depth, out_of_plane)


def sensed_wrench(
    model: mujoco.MjModel, data: mujoco.MjData, names: SceneNames
) -> NDArray[np.float64]:
    """The wrench on the probe from the outside as the F/T sensor gives it, (6,): force [N]
    then torque [N m] about the probe origin, in the probe frame (forward dynamics computed
    at the present state: the couplings do so at each step's end).

    The sensor (at the flange end of the probe) reads the wrench the flange puts on the
    probe, F_s (in its frame, torque about the site). Newton-Euler for the probe (mass m,
    centre of mass c, inertia I_c, acceleration a_c, angular velocity w and acceleration
    alpha) gives everything else acting on it, the tissue and any MuJoCo contact:

        F_ext = -F_s + m (a_c - g),
        T_ext(site) = -T_s + I_c alpha + w x (I_c w) + (c - site) x m (a_c - g),

    a sensor's load compensation: at rest it tares the probe's weight (a_c - g = -g), moving
    its inertia too (with the arm's 20 ms target steps the probe's speed ripples within each
    step, m a_c about 0.03 N at 25 mm/s). The torque is then moved to the probe origin and
    both turned into the probe frame.
    """
    site = names.ft_site
    site_rot = data.site_xmat[site].reshape(3, 3)
    force_site = data.sensordata[names.force_sensor_adr : names.force_sensor_adr + 3]
    torque_site = data.sensordata[names.torque_sensor_adr : names.torque_sensor_adr + 3]
    body = names.probe_body
    # The probe's velocity and acceleration at its centre of mass, world frame, (angular,
    # linear); MuJoCo's linear acceleration is a_c - g, what an accelerometer there reads.
    velocity, acceleration = np.empty(6), np.empty(6)
    mujoco.mj_objectVelocity(model, data, mujoco.mjtObj.mjOBJ_BODY, body, velocity, 0)
    mujoco.mj_objectAcceleration(model, data, mujoco.mjtObj.mjOBJ_BODY, body, acceleration, 0)
    spin, angular_acc = velocity[:3], acceleration[:3]
    load = model.body_mass[body] * acceleration[3:]  # m (a_c - g) [N]
    principal = data.ximat[body].reshape(3, 3)
    inertia = principal @ np.diag(model.body_inertia[body]) @ principal.T  # I_c, world
    site_pos = data.site_xpos[site]
    force = -site_rot @ force_site + load
    torque_about_site = (
        -site_rot @ torque_site
        + inertia @ angular_acc
        + cross3(spin, inertia @ spin)
        + cross3(data.xipos[body] - site_pos, load)
    )
    origin = data.site_xpos[names.probe_site]
    torque = torque_about_site + cross3(site_pos - origin, force)
    probe_rot = data.site_xmat[names.probe_site].reshape(3, 3)
    return np.concatenate([probe_rot.T @ force, probe_rot.T @ torque])


def tissue_step_info(step: tissue.TissueStep) -> dict[str, Any]:
    """What ``info["tissue"]`` says of a tissue step: its status, Newton iterations,
    sub-motions and the skin's penetration into the probe [m]."""
    return {
        "status": step.status.value,
        "iterations": step.diagnostics.iterations,
        "sub_motions": step.diagnostics.sub_motions,
        "skin_penetration_m": float(step.skin_penetration_m),
    }
