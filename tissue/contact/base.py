"""The one interface every probe-tissue contact strategy exposes, and what they share.

A contact model owns a tissue (the FE simulator, or the PBD backend) and a rigid probe.
Each :meth:`ContactModel.step` takes the probe's new pose, advances the tissue one
``tissue_dt`` and returns a :class:`tissue.TissueStep` (the same record the front door
returns): the wrench on the probe (force [N] and torque [N m] about the probe origin, world
frame), the per-contact forces, the penetration, the landmark positions, how the step was
solved and a status. Bad input raises; a physical failure is a
status.
"""

from __future__ import annotations

import abc
import math
import time
from typing import Any, ClassVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tissue.contact.sleep import FreeAirSleep, RestPoints
from tissue.contact.surface_points import boundary_surface, contact_surface
from tissue.contact.tunnelling import face_samples, skin_behind_probe
from tissue.errors import TissueInputError
from tissue.mesh import TetMesh
from tissue.probe import Probe, ProbeShape
from tissue.probe.surface_depth import SurfaceDepth, surface_depth
from tissue.sim.simulator import SimulationConfig
from tissue.sim.solvers import SERIAL_STEP_UNKNOWNS
from tissue.status import StepStatus, worst
from tissue.step_result import (
    TissueStep,
    asleep_diagnostics,
    frozen,
    iteration_key,
    typed_diagnostics,
)
from tissue.threads import one_thread_below

#: A contact model's own step locates no lesions (the tissue's step adds them): (0, 3).
NO_LESIONS = np.zeros((0, 3))
NO_LESIONS.flags.writeable = False

#: A probe pressed back harder than this [N] has not passed through the tissue, whatever its
#: samples say (see :mod:`tissue.contact.tunnelling`).
TUNNELLED_FORCE_N = 1e-3

#: A step never splits its probe motion into more sub-motions than this (a probe teleported
#: across the room is split into this many, each then longer than the tunnelling bound; the
#: step's diagnostics say so).
MAX_SUB_MOTIONS = 64


class ContactModel(FreeAirSleep, abc.ABC):
    """A tissue coupled to a rigid probe through one contact strategy.

    Subclasses implement :meth:`_advance`; everything else (pose handling, sub-motions
    against tunnelling, penetration, wrench, timing, landmarks, snapshots, sleep in free air)
    is shared. A subclass states its facts as class attributes and is registered under its
    name with :func:`tissue.contact.registry.register_contact`. One that may sleep (see
    :meth:`step`) states its reach (:meth:`sleep_reach_m`), any contact it holds beyond the
    last step's forces (:meth:`_in_contact`) and what its step records besides the tissue's
    state (:meth:`_advance_asleep`).

    Class attributes:
        name: the registry key (``TissueSpec(contact=name)``, ``--contact name``).
        label: its short name in tables and figures.
        colour: its matplotlib colour in figures.
        params_type: its parameters' dataclass (``TissueSpec.contact_params``); built with
            no arguments for the defaults.
        penetration_bound_m: the largest penetration a stable step may leave [m]
            (:class:`tissue.contact.stability.StabilityMonitor`).
        has_tangent: whether the strategy exposes its tissue's stiffness tangent and contact
            constraints (the finite-element strategies do), so that the wrench can be
            linearised (:meth:`tissue.Tissue.wrench_stiffness`).

    Args:
        mesh: the tissue mesh.
        probe_shape: the rigid tool's geometry.
    """

    name: ClassVar[str]
    label: ClassVar[str]
    colour: ClassVar[str] = "tab:gray"
    params_type: ClassVar[type]
    penetration_bound_m: ClassVar[float]
    has_tangent: ClassVar[bool] = False

    @property
    def method(self) -> str:
        """The registry name of this model's strategy."""
        return self.name

    @classmethod
    def settings_for(cls, spec: Any, mesh: TetMesh, materials: Any) -> tuple[Any, Any]:
        """The ``(config, params)`` this strategy is built with for a
        :class:`tissue.TissueSpec` (its profile, time step and ``contact_params``): the
        profile's finite-element settings and the given parameters, else the profile's
        (:meth:`profile_params`). A strategy with a tissue of its own (PBD) overrides this.
        """
        config = SimulationConfig(mode=spec.profile, tissue_dt=spec.tissue_dt)
        params = spec.contact_params
        if params is None:
            params = cls.profile_params(spec, mesh)
        return config, params

    @classmethod
    def settings_for_variant(cls, resolved: Any, mesh: TetMesh, materials: Any) -> tuple[Any, Any]:
        """The ``(config, params)`` of a variant of a resolved tissue
        (:meth:`tissue.Tissue.varied`: other materials, lesions moved at rest): by default
        :meth:`settings_for` again. A strategy whose settings were fitted to the nominal
        tissue (PBD's calibrated compliance scales) keeps them instead of fitting again."""
        return cls.settings_for(resolved.spec, mesh, materials)

    @classmethod
    def profile_params(cls, spec: Any, mesh: TetMesh) -> Any:
        """The strategy's parameters under ``spec``'s profile: the defaults unless a
        strategy's profiles differ (prescribed displacement's node set)."""
        return cls.params_type()

    def __init__(self, mesh: TetMesh, probe_shape: ProbeShape) -> None:
        self.mesh = mesh
        self.probe = Probe(probe_shape)
        self.surface = contact_surface(mesh)
        # The skin: the collision surface (or the volume's boundary), whatever points the
        # method itself acts on; skin penetration is measured on it for every method.
        self.skin = contact_surface(mesh)
        # Each skin triangle's longest edge at rest [m]: the skin's resolution, which sets
        # how deep a facet may lie with its vertices held (skin_depth).
        corners = self.skin.positions(mesh.nodes)[self.skin.triangles]
        self._skin_rest_longest_m = np.ascontiguousarray(
            np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2).max(axis=1)
            if corners.size
            else np.zeros(0)
        )
        self._time = 0.0
        # The probe pose the tissue last saw (a step sweeps from it), None before the first.
        self._last_pose: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None
        bounds = probe_shape.local_bounds_m()
        #: The longest probe motion one tissue step takes [m]: half the probe's thinnest
        #: dimension, so that no skin point can pass through the probe within one (a step
        #: whose probe moves farther is split, see :meth:`step`).
        self.max_sub_motion_m = 0.5 * float(np.min(bounds[1] - bounds[0]))
        # The probe's bounding radius [m], the longest sub-motion [m], the most sub-motions
        # and its local bounding box [m] (2, 3), as the sleeping step's compiled checks take
        # them (see RestPoints.kernel_args).
        self._probe_geometry = (
            float(probe_shape.bounding_radius_m),
            self.max_sub_motion_m,
            MAX_SUB_MOTIONS,
            np.ascontiguousarray(bounds, dtype=np.float64),
        )
        # Tunnelling is judged against the volume's boundary (the tissue itself), whatever
        # surface the method holds: the collision surface embedded in a coarse volume can
        # fold over the probe where a method holds the boundary nodes (sticking prescribed
        # displacement on the 45-degree flank, 2,549 tets, lesion 3: the skin 5.7 mm inside
        # the probe while the volume was pressed as it should be).
        self._volume_boundary = boundary_surface(mesh)
        self._tunnel_samples = face_samples(self.probe)
        self._sleep_speed_m_s: float | None = None
        self._landmarks_kept: tuple[int, NDArray[np.float64]] | None = None
        # Whether the last step (or the reset) left the tissue out of contact with status
        # ok: only then may the next step sleep.
        self._quiet = True
        # While the tissue may sleep: the points that must stay clear of the probe, the
        # volume's boundary points and the reach they must be clear by (see _rest_check).
        # Forgotten whenever the state changes.
        self._rest: RestPoints | None = None
        self._rest_known = False
        self._state_version = 0

    # ------------------------------------------------------------------ interface

    @property
    @abc.abstractmethod
    def node_positions(self) -> NDArray[np.float64]:
        """Current tissue node positions [m], (node_count, 3)."""

    @property
    @abc.abstractmethod
    def node_velocities(self) -> NDArray[np.float64]:
        """Current tissue node velocities [m/s], (node_count, 3)."""

    @property
    def time_s(self) -> float:
        return self._time

    def reset(self) -> None:
        """Tissue back at rest, time 0, contact state cleared, no probe pose seen yet."""
        self._time = 0.0
        self._last_pose = None
        self.drop_caches()
        self._reset_tissue()
        self._quiet = True
        self._forget_rest()

    def place_probe(self, position_world: ArrayLike, quat_wxyz: ArrayLike) -> None:
        """Put the probe at a pose without stepping the tissue (a start pose): the next
        :meth:`step` sweeps the probe from here. The pose must not hold the skin inside
        the probe (nothing checks it here; the next step would push it out)."""
        self.probe.set_pose(position_world, quat_wxyz)
        self._last_pose = (self.probe.position_world.copy(), self.probe.quat_wxyz.copy())

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

    def snapshot(self) -> dict[str, Any]:
        """Everything a later step depends on, copied (for :meth:`restore`).

        Taking a snapshot is a cache boundary: the solver caches (kept factorisations and
        their corrections, cached compliances, a Newton start extrapolated from the last
        step) are dropped here, as a restored model starts without them; the next step
        rebuilds them. So this model and any restored from the snapshot continue bit for bit
        alike, at the price of one refactorisation in the next step.
        """
        self.drop_caches()
        last = self._last_pose
        return {
            "time_s": self._time,
            "probe_pose": (self.probe.position_world.copy(), self.probe.quat_wxyz.copy()),
            "last_pose": None if last is None else (last[0].copy(), last[1].copy()),
            "quiet": self._quiet,
            **self._snapshot_tissue(),
        }

    def restore(self, snapshot: dict[str, Any]) -> None:
        """Continue from a :meth:`snapshot` of a model built the same way (same mesh,
        materials, method and parameters)."""
        self.drop_caches()
        self._time = float(snapshot["time_s"])
        self.probe.set_pose(*snapshot["probe_pose"])
        last = snapshot["last_pose"]
        self._last_pose = None if last is None else (last[0].copy(), last[1].copy())
        self._restore_tissue(snapshot)
        # A snapshot from before sleep existed cannot say: the next step then runs.
        self._quiet = bool(snapshot.get("quiet", False))
        self._forget_rest()

    def drop_caches(self) -> None:  # noqa: B027 - strategies without caches keep it empty
        """Forget every solver cache (see :meth:`snapshot`); the physical state stays."""

    # ------------------------------------------------------------------ sleep

    def _asleep_step(
        self,
        end: tuple[NDArray[np.float64], NDArray[np.float64]],
        h: float,
        pieces: int,
        start: float,
    ) -> TissueStep:
        """A sleeping step that :meth:`sleep_if_clear` left to the full checks (see
        :meth:`step`): the probe at ``end``, the clock advanced as ``pieces`` sub-motions of
        ``h`` [s] would advance it; ``start``: the step's ``time.perf_counter()`` at its
        start."""
        if pieces > 1:
            self.probe.set_pose(*end)  # as the last sub-motion sets it (the same bits)
        self._fall_asleep(
            h, pieces, (self.probe.position_world.copy(), self.probe.quat_wxyz.copy())
        )
        return self._asleep_result(start)

    def _asleep_result(self, start: float) -> TissueStep:
        """What a sleeping step returns; ``start``: its ``time.perf_counter()`` at its
        start."""
        return frozen(
            TissueStep,
            status=StepStatus.OK,
            time_s=self._time,
            force_world_n=np.zeros(3),
            torque_world_nm=np.zeros(3),
            contact_points_world_m=np.zeros((0, 3)),
            contact_forces_world_n=np.zeros((0, 3)),
            skin_penetration_m=0.0,
            landmarks_world_m=self.resting_landmarks(),
            lesion_centroids_world_m=NO_LESIONS,
            diagnostics=asleep_diagnostics(1e3 * (time.perf_counter() - start)),
            method_penetration_m=0.0,
        )

    def step(self, position_world: ArrayLike, quat_wxyz: ArrayLike) -> TissueStep:
        """Move the probe to the pose and advance the tissue one ``tissue_dt``.

        A probe motion longer than :attr:`max_sub_motion_m` since the pose the tissue last
        saw (the translation plus the rotation angle times the probe's bounding radius) is
        split into equal sub-motions shorter than it, each a tissue step of an equal share
        of ``tissue_dt``: otherwise the skin could pass through the probe within one step
        and no method would see it (``diagnostics.sub_motions`` counts them). A
        sub-motion that fails (diverged, solver failed) ends the step there, with the
        state of the sub-motions before it.

        Sleep (with :attr:`sleep_speed_m_s` set): a step does no tissue work at all when the
        last step (or the reset) left the tissue out of contact with status ok, every node
        is slower than :attr:`sleep_speed_m_s`, and every skin point (:attr:`skin`) and
        every point the method acts on (:meth:`contact_points_world`) lies farther from the
        probe at its new pose than the probe's travel since the last pose (as
        :meth:`sub_motion_count` bounds it) plus the method's reach (:meth:`sleep_reach_m`),
        :data:`tissue.contact.sleep.SLEEP_SAFETY_MARGIN_M` and the distance a node at that
        speed covers in a step; and the probe is not behind the skin (the check a step
        makes, :meth:`probe_behind_skin`). Then no point can come within the method's reach
        anywhere along the motion, and the step would only relax a tissue already at rest. A
        sleeping step moves the probe, advances the time, leaves positions and velocities as
        they are and returns no force, no contact points, zero penetration, status ok and
        ``diagnostics.details["asleep"] = 1.0``; the method's solve is not run. The next step that
        does not meet these conditions (the probe approaching) runs in full, sweeping from
        the last pose. A full step in free air moves a tissue at rest only by round-off
        (about 1e-17 m, where it moves it at all): so much does a sleeping step differ from
        it.

        A sleeping step whose checks one compiled call settles takes
        :meth:`sleep_if_clear`; one with a point near enough to the probe to need its exact
        signed distance, and every step that runs, :meth:`step_after_sleep_check`.

        Args:
            position_world: probe origin (contact-face centre) [m], (3,).
            quat_wxyz: probe orientation, MuJoCo order (w, x, y, z), (4,).
        """
        start = time.perf_counter()
        if self.sleep_if_clear(position_world, quat_wxyz):
            return self._asleep_result(start)
        return self.step_after_sleep_check(position_world, quat_wxyz, start)

    def step_after_sleep_check(
        self, position_world: ArrayLike, quat_wxyz: ArrayLike, start: float | None = None
    ) -> TissueStep:
        """:meth:`step` once :meth:`sleep_if_clear` has returned False for this pose: the
        step's full checks (it may still sleep) and, unless it sleeps, its work.
        ``start``: the step's ``time.perf_counter()`` at its start (None: now)."""
        position = np.asarray(position_world, dtype=np.float64).reshape(-1)
        if position.shape != (3,) or not np.all(np.isfinite(position)):
            raise TissueInputError(
                f"probe position must be 3 finite numbers [m]; got {position_world!r}"
            )
        if start is None:
            start = time.perf_counter()
        self.probe.set_pose(position, quat_wxyz)
        end = (self.probe.position_world.copy(), self.probe.quat_wxyz.copy())
        begin = self._last_pose
        travel = 0.0 if begin is None else self.probe_travel_m(begin, end)
        pieces = 1 if begin is None else self._sub_motions(travel)
        h = self.dt if pieces == 1 else self.dt / pieces
        if self._sleep_speed_m_s is not None and self._may_sleep(travel):
            return self._asleep_step(end, h, pieces, start)
        self._forget_rest()
        status = StepStatus.OK
        # Every sub-motion's iterations are the step's work (the last one's dictionary
        # carries the rest of the diagnostics).
        spent: dict[str, float] = {}
        with one_thread_below(3 * self.mesh.node_count, SERIAL_STEP_UNKNOWNS):
            for piece in range(1, pieces + 1):
                if piece < pieces:
                    assert begin is not None
                    self.probe.set_pose(*interpolate_pose(begin, end, piece / pieces))
                elif pieces > 1:
                    self.probe.set_pose(*end)
                piece_status, points, forces, diagnostics = self._advance(h)
                for key in (iteration_key(diagnostics), "linear_iterations"):
                    if key in diagnostics:
                        spent[key] = spent.get(key, 0) + diagnostics[key]
                status = worst(status, piece_status)
                if piece_status in (StepStatus.DIVERGED, StepStatus.SOLVER_FAILED):
                    break
                self._time += h
                self._last_pose = (
                    self.probe.position_world.copy(),
                    self.probe.quat_wxyz.copy(),
                )
        if status in (StepStatus.DIVERGED, StepStatus.SOLVER_FAILED):
            # The state is the last completed sub-motion's; forces of a failed solve mean
            # nothing.
            points, forces = np.zeros((0, 3)), np.zeros((0, 3))
        force, torque = (
            self.probe.wrench_about_origin(points, forces)
            if points.shape[0]
            else (np.zeros(3), np.zeros(3))
        )
        if status not in (StepStatus.DIVERGED, StepStatus.SOLVER_FAILED):
            if not (np.all(np.isfinite(force)) and np.all(np.isfinite(torque))):
                # A non-finite wrench is a divergence, never ok (the state stays finite).
                status = StepStatus.DIVERGED
                points, forces = np.zeros((0, 3)), np.zeros((0, 3))
                force, torque = np.zeros(3), np.zeros(3)
            elif self.probe_behind_skin(force):
                status = worst(status, StepStatus.TUNNELLED)
        skin = self.skin_depth()
        if skin.excess_m > self.penetration_bound_m:
            status = worst(status, StepStatus.PENETRATED)
        diagnostics = {
            **diagnostics,
            **spent,
            "sub_motions": pieces,
            "skin_vertex_penetration_m": skin.vertex_depth_m,
        }
        self._quiet = status is StepStatus.OK and points.shape[0] == 0
        elapsed_ms = 1e3 * (time.perf_counter() - start)
        return TissueStep(
            status=status,
            time_s=self._time,
            force_world_n=np.asarray(force, dtype=np.float64),
            torque_world_nm=np.asarray(torque, dtype=np.float64),
            contact_points_world_m=points,
            contact_forces_world_n=forces,
            skin_penetration_m=skin.depth_m,
            landmarks_world_m=self.landmark_positions(),
            lesion_centroids_world_m=NO_LESIONS,
            diagnostics=typed_diagnostics(diagnostics, int(points.shape[0]), elapsed_ms),
            method_penetration_m=self.penetration_max_m(),
        )

    def sub_motion_count(
        self,
        begin: tuple[NDArray[np.float64], NDArray[np.float64]],
        end: tuple[NDArray[np.float64], NDArray[np.float64]],
    ) -> int:
        """Sub-motions a step from pose ``begin`` to ``end`` (position [m], quaternion) is
        split into: each moves no point of the probe farther than :attr:`max_sub_motion_m`
        (translation + rotation angle x bounding radius bounds every point's travel), at
        most :data:`MAX_SUB_MOTIONS`."""
        return self._sub_motions(self.probe_travel_m(begin, end))

    def _sub_motions(self, travel: float) -> int:
        """:meth:`sub_motion_count` for a probe ``travel`` [m] (:meth:`probe_travel_m`)."""
        return min(MAX_SUB_MOTIONS, max(1, math.ceil(travel / self.max_sub_motion_m - 1e-12)))

    def probe_travel_m(
        self,
        begin: tuple[NDArray[np.float64], NDArray[np.float64]],
        end: tuple[NDArray[np.float64], NDArray[np.float64]],
    ) -> float:
        """A bound on how far any point of the probe moves from pose ``begin`` to ``end``
        (position [m], quaternion) [m]: the translation plus the rotation angle times the
        shape's bounding radius."""
        translation = float(np.linalg.norm(end[0] - begin[0]))
        cosine = min(1.0, abs(float(begin[1] @ end[1])))
        angle = 2.0 * math.acos(cosine)
        return translation + angle * self.probe.shape.bounding_radius_m

    def probe_behind_skin(self, force_world: NDArray[np.float64]) -> bool:
        """Whether the probe has passed through the tissue: its face lies behind the volume's
        boundary by more than half its thinnest dimension and the tissue does not push it
        back (``force_world`` [N], the step's force on the probe; see
        :mod:`tissue.contact.tunnelling`)."""
        if float(-force_world @ self.probe.pressing_direction_world()) > TUNNELLED_FORCE_N:
            return False
        return self._behind_skin(self._volume_boundary.positions(self.node_positions))

    def _behind_skin(self, boundary_points: NDArray[np.float64]) -> bool:
        """:meth:`probe_behind_skin`'s geometric half, for the volume's boundary points
        [m] (b, 3) as they are now."""
        if not self.probe.any_near(boundary_points, self.max_sub_motion_m):
            return False
        return skin_behind_probe(
            self.probe, self._tunnel_samples, boundary_points, self._volume_boundary.triangles
        )

    def contact_points_world(self) -> NDArray[np.float64]:
        """The tissue points this method keeps out of the probe [m], (point_count, 3).

        The collision surface by default; methods acting on the volume's boundary nodes
        (prescribed displacement, PBD) override it, because a fine collision surface lying
        above a coarse volume's boundary facets is not what they hold.
        """
        return self.surface.positions(self.node_positions)

    def contact_points_near(self) -> NDArray[np.float64]:
        """Those of :meth:`contact_points_world` [m] (k, 3) that may lie inside the probe
        (within its local bounding box); a method that overrides
        :meth:`contact_points_world` overrides this too."""
        _, positions = self.surface.near(self.node_positions, self.probe, 0.0)
        return positions

    def penetration_max_m(self) -> float:
        """Deepest of :meth:`contact_points_world` inside the probe now [m] (0 if none)."""
        return self.probe.deepest_inside_m(self.contact_points_near())

    def skin_penetration_m(self) -> float:
        """How far the skin lies inside the probe now [m] (>= 0): the deepest point of the
        collision surface's facets (the volume's boundary faces where the mesh has no
        collision surface) inside the probe's body (:meth:`skin_depth`)."""
        return self.skin_depth().depth_m

    def skin_depth(self) -> SurfaceDepth:
        """How the skin lies inside the probe now, measured over its facets, not only its
        vertices (:func:`tissue.probe.surface_depth.surface_depth`), the same way for every
        method whatever points the method itself acts on.

        A step is ``penetrated`` (:class:`tissue.status.StepStatus`) when a facet lies
        deeper than its allowance (how deep a facet of its size can cut the probe's
        rounded edge with its vertices outside,
        :func:`tissue.probe.surface_depth.facet_allowance_m`) plus the method's
        :attr:`penetration_bound_m`: deeper than the method's bound on the points it holds
        and the skin's resolution together explain. Its size as deformed, up to twice its
        size at rest (:data:`tissue.probe.surface_depth.ALLOWED_STRETCH`): a facet dragged
        across the probe, its vertices on either side, is the skin passing through it, not
        a coarse skin."""
        return surface_depth(
            self.probe,
            self.skin.positions(self.node_positions),
            self.skin.triangles,
            self._skin_rest_longest_m,
        )

    def resting_landmarks(self) -> NDArray[np.float64]:
        """:meth:`landmark_positions` for a sleeping step: read once per state version
        (the nodes do not move while the tissue sleeps), a copy each time."""
        kept = self._landmarks_kept
        if kept is None or kept[0] != self.state_version:
            kept = (self.state_version, self.landmark_positions())
            self._landmarks_kept = kept
        return kept[1].copy()

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
        self, h: float
    ) -> tuple[StepStatus, NDArray[np.float64], NDArray[np.float64], dict[str, Any]]:
        """One tissue step of ``h`` [s] (``dt``, or a share of it for a sub-motion) with the
        probe at its new pose.

        Returns:
            (status, contact points [m] (k, 3), forces on the probe at them [N] (k, 3),
            diagnostics).
        """

    @abc.abstractmethod
    def _reset_tissue(self) -> None: ...

    @abc.abstractmethod
    def _snapshot_tissue(self) -> dict[str, Any]:
        """The tissue's and the strategy's state, copied (see :meth:`snapshot`)."""

    @abc.abstractmethod
    def _restore_tissue(self, snapshot: dict[str, Any]) -> None:
        """Adopt what :meth:`_snapshot_tissue` returned."""


def interpolate_pose(
    begin: tuple[NDArray[np.float64], NDArray[np.float64]],
    end: tuple[NDArray[np.float64], NDArray[np.float64]],
    fraction: float,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The pose a ``fraction`` of the way from ``begin`` to ``end`` (position [m],
    quaternion): positions linearly, orientations by normalised linear interpolation the
    short way round."""
    position = begin[0] + fraction * (end[0] - begin[0])
    other = end[1] if float(begin[1] @ end[1]) >= 0.0 else -end[1]
    quat = (1.0 - fraction) * begin[1] + fraction * other
    return position, quat / np.linalg.norm(quat)
