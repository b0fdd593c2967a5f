"""Two-way coupling of the MuJoCo arm and the FE tissue: :class:`TissueCoupling`.

Step contract. :meth:`TissueCoupling.step` advances MuJoCo ``robot_substeps`` substeps of
``robot_dt`` and then the tissue one ``tissue_dt`` (= ``robot_substeps * robot_dt``) with the
probe's pose at the end; the tissue's new wrench and its stiffness act on the probe during the
next call's substeps. Any MuJoCo stepping loop can host it (the environments do; the Studio
simulation plugin can) by calling :meth:`step` with a control callback, or
:meth:`before_substep` / :meth:`after_substeps` around its own ``mj_step``.

What the F/T sensor reads. :meth:`after_substeps` ends by applying the new tissue step's
wrench (the probe is where the tissue just saw it: q = q0, w = w0) and computing MuJoCo's
forward dynamics there (``mj_forward``, 7 us), so that the step ends with the sensor reading
the tissue's wrench at the probe's present pose: what a kinematic replay of the same poses
gives (``tissue.make_tissue``, ``Tissue.step``). Left to the substeps, the sensor kept the
last one's reading: the previous tissue step's w0 extrapolated by K to the pose one substep
(2 ms) earlier, which missed the force-depth curve's stiffening and the contact points that
entered within the step (pressing at 25 mm/s, 0.85 % low on average and up to 3 % where
contact points enter; docs/environments.md, "The F/T sensor"). The extra ``mj_forward``
changes no wrench the substeps apply; the arm's controller, which reads the mass matrix at
the start of each step, now reads it at the step's end pose instead of one substep earlier.

The wrench on the probe between tissue steps is the tissue's wrench linearised in the probe's
displacement from the pose the tissue last saw:

    w(q) = w0 - K (q - q0),   K = Tissue.wrench_stiffness() (6 x 6),

applied at the probe origin (moved to the probe body's centre of mass for ``xfrc_applied``,
which the force-torque sensor sees; ``qfrc_applied`` would bypass it). Why it is stable: a
zero-order hold of w0 gives the robot no stiffness to feel within a tissue step, so a stiff
contact sampled every 20 ms can chatter (the probe moves on into the tissue for a whole
step, the next step pushes it back too hard: a sampled spring k with the arm's effective
mass m goes unstable once k h^2 / m nears 4, h = 20 ms); with K the robot feels the
tissue's static stiffness at its own 2 ms rate, and only the tissue's slower dynamics are
sampled. It is also the better prediction of the next step's force (measured, pressing the
1,303-tet phantom at 0.2 and 1 mm a step: within 0.018 and 0.058 N, holding w0 0.036 and
0.12 N). With the soft phantom and the default arm both schemes are stable here; the
linearised one keeps its margin for stiff contacts. K costs about a tissue step to compute,
so it is computed again only when the contact set changes, the probe has moved 1 mm, or every
10 steps. The linearised force never pulls the probe into the tissue (contact only pushes):
where it would, no wrench is applied. PBD has no tangent (K = 0: a zero-order hold).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import mujoco
import numpy as np
from numpy.typing import NDArray

import tissue
from envs.controller import cross3, rotation_vector
from envs.errors import EnvConfigError
from envs.scene import SceneNames

#: K is computed again at least every this many tissue steps ...
STIFFNESS_REFRESH_STEPS = 10
#: ... and once the probe has moved this far from where it was computed [m].
STIFFNESS_REFRESH_M = 0.001


@dataclass(frozen=True)
class ProbeWrench:
    """A wrench on the probe: force [N] and torque [N m] about the probe origin."""

    force: NDArray[np.float64]
    torque: NDArray[np.float64]


class TissueCoupling:
    """Steps an arm holding the probe and the tissue together (see the module docstring).

    Args:
        model: the compiled scene (the probe's body and site named as in :mod:`envs.scene`).
        data: its data.
        names: its ids.
        tissue_model: the tissue (its ``dt`` must be a whole number of ``robot_dt``).
        reaction: apply the tissue's wrench to the probe (False: one-way coupling, the
            tissue follows the probe and the robot never feels it; no wrench stiffness is
            computed: a scene without ``force_feedback``, :mod:`envs.effects`).
        linearised: apply w0 - K (q - q0) (True) or hold w0 (False).
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        data: mujoco.MjData,
        names: SceneNames,
        tissue_model: tissue.Tissue,
        reaction: bool = True,
        linearised: bool = True,
    ) -> None:
        ratio = tissue_model.dt / model.opt.timestep
        self.substeps = int(round(ratio))
        if self.substeps < 1 or abs(ratio - self.substeps) > 1e-9:
            raise EnvConfigError(
                f"tissue_dt {tissue_model.dt} s must be a whole number of robot_dt "
                f"{model.opt.timestep} s; choose robot_dt = tissue_dt / k"
            )
        self.model = model
        self.data = data
        self.names = names
        self.tissue = tissue_model
        self.reaction = reaction
        # Without the reaction nothing is applied: K is never computed.
        self.linearised = linearised and tissue_model.has_tangent and reaction
        self._w0 = np.zeros(6)
        self._stiffness = np.zeros((6, 6))
        self._q0_pos = np.zeros(3)
        self._q0_rot = np.eye(3)
        # (contact points, probe position [m], steps since) when K was last computed.
        self._stiffness_from: tuple[int, NDArray[np.float64], int] | None = None
        self.last_step: tissue.TissueStep | None = None
        # No wrench and no stiffness since the last tissue step (free air): nothing to apply.
        self._idle = True
        #: Wall time of the last step's parts [s]: substeps (controller included), the
        #: tissue's step, its wrench stiffness.
        self.timing: dict[str, float] = {"substeps_s": 0.0, "tissue_s": 0.0, "stiffness_s": 0.0}

    # ------------------------------------------------------------------ probe pose

    def probe_pose(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The probe site's pose now: position [m] (3,), rotation matrix (3, 3), world."""
        return probe_site_pose(self.data, self.names)

    def reset(self) -> None:
        """The tissue back at rest with the probe placed where the arm holds it now
        (positions computed); nothing applied to the probe."""
        position, rotation = self.probe_pose()
        self.tissue.reset(position, _quat(rotation))
        self._w0[:] = 0.0
        self._stiffness[:] = 0.0
        self._stiffness_from = None
        self._idle = True
        self._q0_pos, self._q0_rot = position, rotation
        self.data.xfrc_applied[self.names.probe_body] = 0.0
        self.last_step = None

    # ------------------------------------------------------------------ stepping

    def step(self, control: Callable[[mujoco.MjData], NDArray[np.float64]]) -> tissue.TissueStep:
        """``substeps`` MuJoCo substeps (``control(data)`` gives the arm's motor commands
        before each, positions and velocities computed), then one tissue step."""
        model, data = self.model, self.data
        started = time.perf_counter()
        for _ in range(self.substeps):
            mujoco.mj_step1(model, data)
            self.before_substep()
            data.ctrl[self.names.actuators] = control(data)
            mujoco.mj_step2(model, data)
        mujoco.mj_kinematics(model, data)  # the probe's pose after the last substep
        self.timing["substeps_s"] = time.perf_counter() - started
        return self.after_substeps()

    def before_substep(self) -> None:
        """Apply the tissue's (linearised) wrench for the substep about to be taken
        (positions computed)."""
        body = self.names.probe_body
        if not self.reaction or self._idle:
            # Nothing to apply (one-way coupling, or no force and no stiffness: free air).
            self.data.xfrc_applied[body] = 0.0
            return
        wrench = self.wrench_now()
        origin = self.data.site_xpos[self.names.probe_site]
        centre = self.data.xipos[body]
        # xfrc_applied acts at the body's centre of mass: move the torque there.
        torque = wrench.torque + cross3(origin - centre, wrench.force)
        self.data.xfrc_applied[body, :3] = wrench.force
        self.data.xfrc_applied[body, 3:] = torque

    def wrench_now(self) -> ProbeWrench:
        """The tissue's wrench on the probe at its present pose (linearised), world frame,
        about the probe origin."""
        w = self._w0
        if self.linearised:
            position, rotation = self.probe_pose()
            displacement = np.concatenate(
                [position - self._q0_pos, rotation_vector(rotation @ self._q0_rot.T)]
            )
            w = w - self._stiffness @ displacement
            pressing = rotation[:, 1]
            if float(w[:3] @ pressing) > 0.0:
                w = np.zeros(6)  # contact only pushes the probe back
        return ProbeWrench(w[:3].copy(), w[3:].copy())

    def _stiffness_stale(self, step: tissue.TissueStep, position: NDArray[np.float64]) -> bool:
        """Whether K must be computed again (one factorisation of the tissue's tangent and a
        solve per contact point, as much as a tissue step): when the contact set grew or
        shrank, the probe moved more than :data:`STIFFNESS_REFRESH_M` since, or it is
        :data:`STIFFNESS_REFRESH_STEPS` steps old. K only needs to be about right: it keeps
        the substeps stable, the tissue's steps keep the force exact."""
        if self._stiffness_from is None:
            return True
        count, where, age = self._stiffness_from
        return (
            step.diagnostics.contact_count != count
            or age + 1 >= STIFFNESS_REFRESH_STEPS
            or float(np.linalg.norm(position - where)) > STIFFNESS_REFRESH_M
        )

    def after_substeps(self) -> tissue.TissueStep:
        """The tissue's step with the probe where the substeps left it (positions computed);
        its wrench and stiffness then act until the next. Ends with MuJoCo's forward
        dynamics computed under the new wrench, so that the F/T sensor reads it (the module
        docstring)."""
        position, rotation = self.probe_pose()
        # The tissue's input, converted from MuJoCo's pose: the coupling's work, timed apart
        # from the tissue's step.
        quat = _quat(rotation)
        started = time.perf_counter()
        step = self.tissue.step(position, quat)
        stepped = time.perf_counter()
        self._q0_pos, self._q0_rot = position, rotation
        if step.status in (tissue.StepStatus.DIVERGED, tissue.StepStatus.SOLVER_FAILED):
            self._w0[:] = 0.0
            self._stiffness[:] = 0.0
            self._stiffness_from = None
            self._idle = True
        elif self._idle and step.diagnostics.details.get("asleep"):
            # Free air, as before: w0 and K were zero and stay so (no force, no contact
            # point); only K's bookkeeping runs on, as below.
            if self.linearised and self._stiffness_stale(step, position):
                self._stiffness_from = (0, position, 0)
            elif self._stiffness_from is not None:
                count, where, age = self._stiffness_from
                self._stiffness_from = (count, where, age + 1)
        else:
            self._w0 = np.concatenate([step.force_world_n, step.torque_world_nm])
            if self.linearised and self._stiffness_stale(step, position):
                # No contact point, nothing to be stiff: K = 0 without a factorisation.
                stiffness = (
                    self.tissue.wrench_stiffness() if step.diagnostics.contact_count else None
                )
                self._stiffness = np.zeros((6, 6)) if stiffness is None else stiffness
                self._stiffness_from = (step.diagnostics.contact_count, position, 0)
            elif self._stiffness_from is not None:
                count, where, age = self._stiffness_from
                self._stiffness_from = (count, where, age + 1)
            self._idle = not (np.any(self._w0) or np.any(self._stiffness))
        self.timing["tissue_s"] = stepped - started
        self.timing["stiffness_s"] = time.perf_counter() - stepped
        self.last_step = step
        self._sense_at_step_end()
        return step

    def _sense_at_step_end(self) -> None:
        """Apply the new tissue step's wrench (the probe is at q0: no displacement) and
        compute MuJoCo's forward dynamics at the step's end, so that the F/T sensor reads
        the tissue's wrench at the pose the tissue just stepped to (positions computed).

        Without it the sensor would keep the last substep's reading: the previous tissue
        step's w0 extrapolated by K to the pose one substep earlier. ``mj_forward`` leaves
        MuJoCo's integration state (positions, velocities, controls, warm start) as it is;
        only what is derived from it is the step end's, such as the mass matrix the
        controller reads at the next step's start (as :class:`envs.rigid.RigidCoupling`'s
        step already leaves it)."""
        self.before_substep()
        mujoco.mj_forward(self.model, self.data)


def probe_site_pose(
    data: mujoco.MjData, names: SceneNames
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The probe site's pose in ``data``: position [m] (3,), rotation matrix (3, 3), world
    (copies)."""
    site = names.probe_site
    return data.site_xpos[site].copy(), data.site_xmat[site].reshape(3, 3).copy()


def _quat(rotation: NDArray[np.float64]) -> NDArray[np.float64]:
    quat = np.empty(4)
    mujoco.mju_mat2Quat(quat, np.ascontiguousarray(rotation).reshape(-1))
    return quat
