"""The one interface every probe-tissue contact strategy exposes, and what they share.

A contact model owns a tissue (the FE simulator, or the PBD backend) and a rigid probe.
Each :meth:`ContactModel.step` takes the probe's new pose, advances the tissue one
``tissue_dt`` and returns a :class:`ContactResult`: the wrench on the probe (force [N] and
torque [N m] about the probe origin, world frame), the per-contact forces, the largest
penetration, the landmark positions and a status. Bad input raises; a physical failure is a
status.
"""

from __future__ import annotations

import abc
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tissue.choices import Choice
from tissue.embedding import BarycentricEmbedding
from tissue.errors import TissueInputError
from tissue.mesh import TetMesh, boundary_faces
from tissue.probe import Probe, ProbeShape
from tissue.solvers import SERIAL_STEP_UNKNOWNS
from tissue.status import StepStatus
from tissue.threads import one_thread_below


class ContactMethod(Choice):
    """The probe-tissue interaction strategies (Tagliabue et al. 2020, section 2.1)."""

    PENALTY = "penalty"
    LM = "lm"
    PRESCRIBED = "prescribed"
    PBD = "pbd"

    @classmethod
    def noun(cls) -> str:
        return "contact method"


@dataclass(frozen=True)
class ContactResult:
    """What one coupled step did.

    Attributes:
        status: ``ok`` or the instability met.
        time_s: simulated time after the step [s].
        force_world: force the tissue applies to the probe [N], (3,).
        torque_world: torque of those forces about the probe origin [N m], (3,).
        contact_points: where contact forces act [m], (contact_count, 3).
        contact_forces: force on the probe at each contact point [N], (contact_count, 3).
        penetration_max_m: deepest tissue point inside the probe [m] (>= 0), over the points
            the method keeps out of it (:meth:`ContactModel.contact_points_world`).
        landmarks: landmark positions [m], (landmark_count, 3).
        compute_ms: wall time of the step [ms].
        diagnostics: solver details (iterations, residuals, substeps, ...).
    """

    status: StepStatus
    time_s: float
    force_world: NDArray[np.float64]
    torque_world: NDArray[np.float64]
    contact_points: NDArray[np.float64]
    contact_forces: NDArray[np.float64]
    penetration_max_m: float
    landmarks: NDArray[np.float64]
    compute_ms: float
    diagnostics: dict[str, Any] = field(default_factory=dict)

    @property
    def contact_count(self) -> int:
        return int(self.contact_points.shape[0])


@dataclass(frozen=True)
class SurfacePoints:
    """The tissue points contact acts on: collision-surface vertices embedded in the volume.

    Attributes:
        embedding: barycentric map from volume nodes to the points.
        triangles: the surface's triangles over the points (outward), (t, 3).
    """

    embedding: BarycentricEmbedding
    triangles: NDArray[np.int64]

    @property
    def count(self) -> int:
        return int(self.embedding.weights.shape[0])

    def positions(self, node_positions: NDArray[np.float64]) -> NDArray[np.float64]:
        return self.embedding.interpolate(node_positions)


def contact_surface(mesh: TetMesh) -> SurfacePoints:
    """The mesh's collision surface, or its boundary faces (identity embedding) if it has none."""
    if mesh.collision_surface is not None:
        surface = mesh.collision_surface
        return SurfacePoints(surface.embedding, surface.triangles)
    return boundary_surface(mesh)


def boundary_surface(mesh: TetMesh) -> SurfacePoints:
    """The volume's boundary faces as contact points (each node embedded with weight 1)."""
    faces = boundary_faces(mesh.tets)
    vertices = np.unique(faces)
    # Each boundary node is "embedded" in one tet that contains it, with weight 1 on itself.
    owner = np.full(mesh.node_count, -1, dtype=np.int64)
    corner = np.zeros(mesh.node_count, dtype=np.int64)
    for local in range(4):
        owner[mesh.tets[:, local]] = np.arange(mesh.tet_count)
        corner[mesh.tets[:, local]] = local
    tet_nodes = mesh.tets[owner[vertices]]
    weights = np.zeros((vertices.size, 4))
    weights[np.arange(vertices.size), corner[vertices]] = 1.0
    remap = np.full(mesh.node_count, -1, dtype=np.int64)
    remap[vertices] = np.arange(vertices.size)
    return SurfacePoints(BarycentricEmbedding(tet_nodes, weights), remap[faces])


class ContactModel(abc.ABC):
    """A tissue coupled to a rigid probe through one contact strategy.

    Subclasses implement :meth:`_advance`; everything else (pose handling, penetration,
    wrench, timing, landmarks) is shared.

    Args:
        mesh: the tissue mesh.
        probe_shape: the rigid tool's geometry.
    """

    method: ContactMethod

    def __init__(self, mesh: TetMesh, probe_shape: ProbeShape) -> None:
        self.mesh = mesh
        self.probe = Probe(probe_shape)
        self.surface = contact_surface(mesh)
        self._time = 0.0

    # ------------------------------------------------------------------ interface

    @property
    @abc.abstractmethod
    def node_positions(self) -> NDArray[np.float64]:
        """Current tissue node positions [m], (node_count, 3)."""

    @property
    def time_s(self) -> float:
        return self._time

    def reset(self) -> None:
        """Tissue back at rest, time 0, contact state cleared."""
        self._time = 0.0
        self._reset_tissue()

    def saved_state(self) -> dict[str, NDArray[np.float64]]:
        """The state a run can be resumed from (:meth:`load_state`): named arrays, all a
        later step depends on beyond the mesh, materials and parameters. Kept factorisations
        and other caches are not part of it: they are rebuilt, so a resumed run agrees with
        an uninterrupted one to the solver's tolerance, not bit for bit.

        Only strategies that need it implement it (Lagrange multipliers: the study's
        references, runs of an hour and more, resume from it)."""
        raise NotImplementedError(
            f"{type(self).__name__} cannot save its state; resumable runs need the 'lm' method"
        )

    def load_state(self, state: dict[str, NDArray[np.float64]]) -> None:
        """Continue from a :meth:`saved_state` of a model built the same way."""
        raise NotImplementedError(
            f"{type(self).__name__} cannot load a saved state; resumable runs need the 'lm' method"
        )

    def step(self, position_world: ArrayLike, quat_wxyz: ArrayLike) -> ContactResult:
        """Move the probe to the pose and advance the tissue one ``tissue_dt``.

        Args:
            position_world: probe origin (contact-face centre) [m], (3,).
            quat_wxyz: probe orientation, MuJoCo order (w, x, y, z), (4,).
        """
        position = np.asarray(position_world, dtype=np.float64).reshape(-1)
        if position.shape != (3,) or not np.all(np.isfinite(position)):
            raise TissueInputError(
                f"probe position must be 3 finite numbers [m]; got {position_world!r}"
            )
        start = time.perf_counter()
        self.probe.set_pose(position, quat_wxyz)
        with one_thread_below(3 * self.mesh.node_count, SERIAL_STEP_UNKNOWNS):
            status, points, forces, diagnostics = self._advance()
        if status in (StepStatus.DIVERGED, StepStatus.SOLVER_FAILED):
            # The state was kept from before the step; forces of the failed solve mean nothing.
            points, forces = np.zeros((0, 3)), np.zeros((0, 3))
        force, torque = (
            self.probe.wrench_about_origin(points, forces)
            if points.shape[0]
            else (np.zeros(3), np.zeros(3))
        )
        if status not in (StepStatus.DIVERGED, StepStatus.SOLVER_FAILED):
            self._time += self.dt
        elapsed_ms = 1e3 * (time.perf_counter() - start)
        return ContactResult(
            status=status,
            time_s=self._time,
            force_world=np.asarray(force, dtype=np.float64),
            torque_world=np.asarray(torque, dtype=np.float64),
            contact_points=points,
            contact_forces=forces,
            penetration_max_m=self.penetration_max_m(),
            landmarks=self.landmark_positions(),
            compute_ms=elapsed_ms,
            diagnostics=diagnostics,
        )

    def contact_points_world(self) -> NDArray[np.float64]:
        """The tissue points this method keeps out of the probe [m], (point_count, 3).

        The collision surface by default; methods acting on the volume's boundary nodes
        (prescribed displacement, PBD) override it, because a fine collision surface lying
        above a coarse volume's boundary facets is not what they hold.
        """
        return self.surface.positions(self.node_positions)

    def penetration_max_m(self) -> float:
        """Deepest of :meth:`contact_points_world` inside the probe now [m] (0 if none).

        Only points within the probe's bounding sphere can be inside it: the signed distance
        is evaluated for those (a few dozen of ~500 at the phantom's apex; 24 -> 8 us).
        """
        points = self.contact_points_world()
        near = self.probe.near(points)
        if not np.any(near):
            return 0.0
        distance, _ = self.probe.signed_distance_world(points[near])
        return float(max(0.0, -float(distance.min())))

    def landmark_positions(self) -> NDArray[np.float64]:
        """Current landmark positions [m], (landmark_count, 3)."""
        if self.mesh.landmarks is None:
            return np.zeros((0, 3))
        return self.mesh.landmarks.positions(self.node_positions)

    @property
    @abc.abstractmethod
    def dt(self) -> float:
        """The tissue time step [s]."""

    @abc.abstractmethod
    def _advance(
        self,
    ) -> tuple[StepStatus, NDArray[np.float64], NDArray[np.float64], dict[str, Any]]:
        """One tissue step with the probe at its new pose.

        Returns:
            (status, contact points [m] (k, 3), forces on the probe at them [N] (k, 3),
            diagnostics).
        """

    @abc.abstractmethod
    def _reset_tissue(self) -> None: ...
