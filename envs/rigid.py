"""The rigid breast: the cheapest scene, for learning to reach and approach.

A scene without ``deformation`` (:mod:`envs.effects`) never steps the FE tissue. The breast
is a static MuJoCo mesh geom, the convex hull of the rest skin (MuJoCo collides meshes by
their convex hulls; the phantom's skin is a dome, so the hull is the skin but for its few
concave folds), which only the probe's face collides with (its own contact bit, so the
arm's links and the table are unaffected). MuJoCo's contact is the reaction: the F/T
sensor reads it within the substeps, as it reads the FE tissue's applied wrench in the full
scene. The lesions stay at rest.

:class:`RigidCoupling` has :class:`envs.coupling.TissueCoupling`'s interface: each
:meth:`RigidCoupling.step` returns a :class:`tissue.TissueStep` built from MuJoCo's contacts
(force, torque about the probe origin, contact points, the deepest penetration), so the
tasks read it as they read the FE tissue's.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import mujoco
import numpy as np
from numpy.typing import NDArray

import tissue
from envs.controller import cross3
from envs.coupling import probe_site_pose
from envs.scene import RIGID_BREAST_GEOM, SceneNames


class RigidCoupling:
    """Steps the arm against the rigid breast (see the module docstring).

    Args:
        model: the compiled scene, with the rigid breast geom.
        data: its data.
        names: its ids.
        tissue_model: the tissue whose rest geometry the breast is (its lesions are read at
            rest; it is never stepped).
    """

    #: Rigid contact is MuJoCo's own: nothing is applied to the probe from outside.
    reaction = False

    def __init__(
        self,
        model: mujoco.MjModel,
        data: mujoco.MjData,
        names: SceneNames,
        tissue_model: tissue.Tissue,
    ) -> None:
        self.model = model
        self.data = data
        self.names = names
        self.tissue = tissue_model
        self.substeps = max(1, int(round(tissue_model.dt / model.opt.timestep)))
        self.breast_geom = model.geom(RIGID_BREAST_GEOM).id
        self.probe_geoms = frozenset(
            g for g in range(model.ngeom) if model.geom_bodyid[g] == names.probe_body
        )
        self.last_step: tissue.TissueStep | None = None
        self._time = 0.0
        #: Wall time of the last step's parts [s], as :class:`TissueCoupling`'s (the tissue's
        #: are zero: it is not stepped).
        self.timing: dict[str, float] = {"substeps_s": 0.0, "tissue_s": 0.0, "stiffness_s": 0.0}

    def probe_pose(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The probe site's pose now: position [m] (3,), rotation matrix (3, 3), world."""
        return probe_site_pose(self.data, self.names)

    def reset(self) -> None:
        """Time back to 0; nothing else holds state (the breast is rigid)."""
        self._time = 0.0
        self.data.xfrc_applied[self.names.probe_body] = 0.0
        self.last_step = None

    def step(self, control: Callable[[mujoco.MjData], NDArray[np.float64]]) -> tissue.TissueStep:
        """``substeps`` MuJoCo substeps (``control(data)`` gives the motor commands before
        each), then the contact on the probe read as a tissue step."""
        model, data = self.model, self.data
        started = time.perf_counter()
        for _ in range(self.substeps):
            mujoco.mj_step1(model, data)
            data.ctrl[self.names.actuators] = control(data)
            mujoco.mj_step2(model, data)
        mujoco.mj_forward(model, data)  # contacts and their forces at the step's end
        self.timing["substeps_s"] = time.perf_counter() - started
        self._time += self.substeps * model.opt.timestep
        self.last_step = self._contact_step()
        return self.last_step

    def _contact_step(self) -> tissue.TissueStep:
        """The breast's contact on the probe now, as a :class:`tissue.TissueStep`."""
        data = self.data
        origin = data.site_xpos[self.names.probe_site]
        points, forces = [], []
        deepest = 0.0
        wrench = np.zeros(6)
        for index in range(data.ncon):
            contact = data.contact[index]
            pair = {int(contact.geom1), int(contact.geom2)}
            if self.breast_geom not in pair or not pair & self.probe_geoms:
                continue
            local = np.zeros(6)
            mujoco.mj_contactForce(self.model, data, index, local)
            frame = contact.frame.reshape(3, 3)
            # The force geom1 exerts on geom2, along the frame's rows (normal first).
            force = frame.T @ local[:3]
            if int(contact.geom2) == self.breast_geom:
                force = -force
            points.append(contact.pos.copy())
            forces.append(force)
            wrench[:3] += force
            wrench[3:] += cross3(contact.pos - origin, force)
            deepest = max(deepest, -float(contact.dist))
        centroids = self.tissue.lesion_centroids_m(self.tissue.tracked_lesions)
        return tissue.TissueStep(
            status=tissue.StepStatus.OK,
            time_s=self._time,
            force_world_n=wrench[:3].copy(),
            torque_world_nm=wrench[3:].copy(),
            contact_points_world_m=np.array(points).reshape(-1, 3),
            contact_forces_world_n=np.array(forces).reshape(-1, 3),
            skin_penetration_m=deepest,
            landmarks_world_m=np.zeros((0, 3)),
            lesion_centroids_world_m=centroids,
            diagnostics=tissue.StepDiagnostics(
                iterations=0,
                linear_iterations=0,
                contact_count=len(points),
                sub_motions=1,
                subdivisions=0,
                min_volume_ratio=None,
                compute_ms=0.0,
                details={"rigid": 1.0},
            ),
        )
