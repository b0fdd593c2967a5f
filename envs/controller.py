"""Driving the arm: a Cartesian impedance controller for the probe, a joint-space one, and IK.

:class:`CartesianImpedance` (the default) tracks a target pose of the probe site:

    F = K e - D v,   tau = J^T F + c(q, qdot) + N (k_p (q_rest - q) - k_d qdot),

e the pose error (position, and the rotation vector of R_target R^T), v the site's twist, J
its 6 x n Jacobian, c MuJoCo's bias forces (gravity, Coriolis: the arm and probe are
gravity-compensated), N the dynamically consistent null-space projector (a posture for
arms with more than six joints), and D_i = 2 zeta sqrt(K_i Lambda_ii) with Lambda =
(J M^-1 J^T)^-1 the task-space inertia, so each axis is damped near critically. Stiffness is
in N/m and N m/rad: what the tissue's force works against (a press stops where the tissue's
force equals K times the probe's lag behind its target). Torques are clipped to the motors'
limits. :class:`JointImpedance` tracks joint targets with the same gravity compensation.

The task-space inertia and the Jacobian are computed once per environment step (they change
little in 20 ms): the substeps between reuse them.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np
from numpy.typing import NDArray

from envs.errors import EnvConfigError, check_positive
from envs.scene import SceneNames

CONTROL_MODES = ("cartesian_impedance", "joint_delta")
# The largest joint change of one IK iteration [rad].
_IK_MAX_STEP_RAD = 0.2


@dataclass(frozen=True)
class ControllerConfig:
    """How actions drive the arm.

    Attributes:
        mode: ``cartesian_impedance`` (default: the action moves the probe's target pose) or
            ``joint_delta`` (the action moves the joints' targets).
        stiffness_n_per_m: translational stiffness of the probe's impedance [N/m].
        rotational_stiffness_nm_per_rad: its rotational stiffness [N m/rad].
        damping_ratio: zeta of every axis (1: critical).
        joint_stiffness_nm_per_rad: ``joint_delta`` mode's joint stiffness [N m/rad].
        posture_stiffness_nm_per_rad: null-space pull to the reset posture [N m/rad].
    """

    mode: str = "cartesian_impedance"
    stiffness_n_per_m: float = 3000.0
    rotational_stiffness_nm_per_rad: float = 60.0
    damping_ratio: float = 1.0
    joint_stiffness_nm_per_rad: float = 400.0
    posture_stiffness_nm_per_rad: float = 5.0

    def __post_init__(self) -> None:
        if self.mode not in CONTROL_MODES:
            raise EnvConfigError(
                f"unknown control_mode {self.mode!r}; choose one of {', '.join(CONTROL_MODES)}"
            )
        check_positive(
            self,
            (
                "stiffness_n_per_m",
                "rotational_stiffness_nm_per_rad",
                "damping_ratio",
                "joint_stiffness_nm_per_rad",
            ),
        )
        if not (
            np.isfinite(self.posture_stiffness_nm_per_rad)
            and self.posture_stiffness_nm_per_rad >= 0
        ):
            raise EnvConfigError(
                "posture_stiffness_nm_per_rad must be >= 0; got "
                f"{self.posture_stiffness_nm_per_rad!r}"
            )


def cross3(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """a x b for 3-vectors (np.cross spends ~20 us in Python layers a call)."""
    return np.array(
        [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    )


def rotation_vector(rotation: NDArray[np.float64]) -> NDArray[np.float64]:
    """The rotation vector (axis x angle [rad]) of a rotation matrix, (3,)."""
    quat = np.empty(4)
    mujoco.mju_mat2Quat(quat, np.ascontiguousarray(rotation).reshape(-1))
    vector = np.empty(3)
    mujoco.mju_quat2Vel(vector, quat, 1.0)
    return vector


class CartesianImpedance:
    """Tracks a probe-site target pose (see the module docstring).

    Args:
        model: the compiled scene.
        names: its ids.
        config: gains.
    """

    def __init__(self, model: mujoco.MjModel, names: SceneNames, config: ControllerConfig):
        self.model = model
        self.names = names
        self.config = config
        nv = model.nv
        self._jacp = np.zeros((3, nv))
        self._jacr = np.zeros((3, nv))
        self._dofs = names.joint_dof
        self._stiffness = np.array(
            [config.stiffness_n_per_m] * 3 + [config.rotational_stiffness_nm_per_rad] * 3
        )
        self._damping = np.zeros(6)
        self._null = np.zeros((len(self._dofs), len(self._dofs)))
        self._jacobian = np.zeros((6, len(self._dofs)))
        self.target_pos = np.zeros(3)
        self.target_rot = np.eye(3)
        self.posture = np.zeros(len(self._dofs))

    def set_target(self, position: NDArray[np.float64], rotation: NDArray[np.float64]) -> None:
        """The probe site's target: position [m] (3,), rotation matrix (3, 3), world frame."""
        self.target_pos = np.array(position, dtype=np.float64)
        self.target_rot = np.array(rotation, dtype=np.float64)

    def jacobian(self, data: mujoco.MjData) -> NDArray[np.float64]:
        """The probe site's Jacobian over the arm's dofs, (6, n) (positions computed)."""
        mujoco.mj_jacSite(self.model, data, self._jacp, self._jacr, self.names.probe_site)
        return np.vstack([self._jacp[:, self._dofs], self._jacr[:, self._dofs]])

    def update_inertia(self, data: mujoco.MjData) -> None:
        """Recompute the Jacobian, the damping from the task-space inertia and the
        null-space projector (kept for the substeps of an environment step)."""
        jacobian = self.jacobian(data)
        self._jacobian = jacobian
        full = np.zeros((self.model.nv, self.model.nv))
        mujoco.mj_fullM(self.model, data, full)
        mass = full[np.ix_(self._dofs, self._dofs)]
        mass_inv_jt = np.linalg.solve(mass, jacobian.T)
        task_inverse = jacobian @ mass_inv_jt
        task = np.linalg.pinv(task_inverse, rcond=1e-6)
        self._damping = (
            2.0
            * self.config.damping_ratio
            * np.sqrt(self._stiffness * np.clip(np.diag(task), 0, None))
        )
        # Dynamically consistent null space: N = I - J^T (Lambda J M^-1).
        self._null = np.eye(len(self._dofs)) - jacobian.T @ (task @ mass_inv_jt.T)

    def torques(self, data: mujoco.MjData) -> NDArray[np.float64]:
        """Joint torques [N m] for the present state (positions and velocities computed;
        the Jacobian of the last :meth:`update_inertia`, 20 ms old at most)."""
        jacobian = self._jacobian
        site_pos = data.site_xpos[self.names.probe_site]
        site_rot = data.site_xmat[self.names.probe_site].reshape(3, 3)
        error = np.concatenate(
            [self.target_pos - site_pos, rotation_vector(self.target_rot @ site_rot.T)]
        )
        qvel = data.qvel[self._dofs]
        twist = jacobian @ qvel
        force = self._stiffness * error - self._damping * twist
        qpos = data.qpos[self.names.joint_qpos]
        posture = self.config.posture_stiffness_nm_per_rad * (self.posture - qpos) - 0.1 * qvel
        tau = jacobian.T @ force + data.qfrc_bias[self._dofs] + self._null @ posture
        return np.clip(tau, -self.names.torque_limits, self.names.torque_limits)


class JointImpedance:
    """Tracks joint targets: tau = k (q* - q) - 2 sqrt(k m_ii) qdot + bias, clipped."""

    def __init__(self, model: mujoco.MjModel, names: SceneNames, config: ControllerConfig):
        self.model = model
        self.names = names
        self.config = config
        self.target_q = np.zeros(len(names.joint_qpos))
        self._damping = np.zeros(len(names.joint_qpos))

    def update_inertia(self, data: mujoco.MjData) -> None:
        full = np.zeros((self.model.nv, self.model.nv))
        mujoco.mj_fullM(self.model, data, full)
        diagonal = np.diag(full)[self.names.joint_dof]
        self._damping = 2.0 * np.sqrt(self.config.joint_stiffness_nm_per_rad * diagonal)

    def torques(self, data: mujoco.MjData) -> NDArray[np.float64]:
        qpos = data.qpos[self.names.joint_qpos]
        qvel = data.qvel[self.names.joint_dof]
        tau = (
            self.config.joint_stiffness_nm_per_rad * (self.target_q - qpos)
            - self._damping * qvel
            + data.qfrc_bias[self.names.joint_dof]
        )
        return np.clip(tau, -self.names.torque_limits, self.names.torque_limits)


def solve_ik(
    model: mujoco.MjModel,
    data: mujoco.MjData,
    names: SceneNames,
    position: NDArray[np.float64],
    rotation: NDArray[np.float64],
    start: NDArray[np.float64],
    iterations: int = 200,
    tolerance: float = 1e-7,
) -> tuple[NDArray[np.float64], float]:
    """Joint angles that put the probe site at a pose (damped least squares from ``start``,
    within the joints' ranges). Returns (angles [rad], remaining error: position [m] plus
    rotation [rad]). Leaves ``data`` at those angles with positions computed."""
    jacp = np.zeros((3, model.nv))
    jacr = np.zeros((3, model.nv))
    q = np.array(start, dtype=np.float64)
    low, high = names.joint_ranges[:, 0], names.joint_ranges[:, 1]
    error_norm = np.inf
    for _ in range(iterations):
        data.qpos[names.joint_qpos] = q
        mujoco.mj_kinematics(model, data)
        mujoco.mj_comPos(model, data)
        site_pos = data.site_xpos[names.probe_site]
        site_rot = data.site_xmat[names.probe_site].reshape(3, 3)
        error = np.concatenate([position - site_pos, rotation_vector(rotation @ site_rot.T)])
        error_norm = float(np.linalg.norm(error))
        if error_norm < tolerance:
            break
        mujoco.mj_jacSite(model, data, jacp, jacr, names.probe_site)
        jacobian = np.vstack([jacp[:, names.joint_dof], jacr[:, names.joint_dof]])
        damping = 1e-4
        step = jacobian.T @ np.linalg.solve(jacobian @ jacobian.T + damping * np.eye(6), error)
        largest = float(np.abs(step).max())
        if largest > _IK_MAX_STEP_RAD:  # small steps: no jumping to another solution branch
            step *= _IK_MAX_STEP_RAD / largest
        q = np.clip(q + step, low, high)
    return q, error_norm
