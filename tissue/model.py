"""The front door's tissue: :func:`make_tissue` builds a :class:`Tissue` from a
:class:`~tissue.spec.TissueSpec`; each :meth:`Tissue.step` takes the probe's pose and returns a
:class:`TissueStep`.

The probe frame (every shape, :mod:`tissue.probe`): origin at the centre of the contact face,
+y the pressing direction (into the tissue), x the face's long axis (the ultrasound image's
lateral axis), z its short axis (elevation); the body lies at y < 0. A pose is probe-to-world:
p_world = R p_probe + position, with R from the quaternion (w, x, y, z), MuJoCo's order.
"""

from __future__ import annotations

import copy
import hashlib
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tissue.contact import make_contact_model
from tissue.contact.base import ContactModel
from tissue.contact.placement import RestSkin, first_contact_pose, radial_roll_rad
from tissue.contact.surface_points import SurfacePoints
from tissue.contact.wrench_stiffness import wrench_stiffness
from tissue.errors import MeshError, TissueInputError
from tissue.fem.material import TissueMaterials
from tissue.lesions import Lesion, LesionTracker
from tissue.mesh.lesion_shift import lesion_shift_limits, shift_lesions, surface_after_shift
from tissue.probe import ProbeShape, quat_to_matrix
from tissue.sim.solvers import SERIAL_STEP_UNKNOWNS
from tissue.spec import ResolvedTissue, TissueSpec, resolve_spec
from tissue.status import StepStatus
from tissue.step_result import TissueStep, asleep_diagnostics, frozen, with_lesions
from tissue.surface_mesh import SurfaceMesh, SurfaceView
from tissue.threads import one_thread_below


@dataclass(frozen=True)
class TissueState:
    """A snapshot of a :class:`Tissue` (:meth:`Tissue.state`), to :meth:`Tissue.set_state`
    a tissue built from the same spec. Picklable.

    Attributes:
        fingerprint: identifies the spec and mesh it belongs to.
        time_s: simulated time [s].
        data: the strategy's state (copied arrays).
    """

    fingerprint: str
    time_s: float
    data: dict[str, Any]


def make_tissue(spec: TissueSpec | None = None, **overrides: Any) -> Tissue:
    """Build a tissue: ``make_tissue(TissueSpec(...))`` or ``make_tissue(mesh=1363, ...)``.

    The mesh is generated (phantom levels, cached on disk) or loaded, the profile resolved
    (:func:`tissue.spec.resolve_spec`) and the model built with its one-time work done
    (compiled kernels loaded, solver analysis; a PBD tissue calibrated for the mesh, cached).

    Raises:
        tissue.errors.TissueInputError: a bad spec (the message names the value, what was
            expected and how to fix it).
    """
    if spec is None:
        spec = TissueSpec.from_overrides(**overrides)
    elif overrides:
        raise TissueInputError(
            f"give a TissueSpec or keyword settings, not both; got a spec and {sorted(overrides)}"
        )
    if not isinstance(spec, TissueSpec):
        raise TissueInputError(f"spec must be a tissue.TissueSpec; got {type(spec).__name__}")
    return Tissue(resolve_spec(spec))


class Tissue:
    """A hyperelastic breast (or any tet mesh) pressed by a rigid probe: the front door.

    Build with :func:`make_tissue`. Each :meth:`step` moves the probe to a pose (see the
    module docstring for the probe frame) and advances the tissue ``dt`` seconds. A physical
    failure (divergence, inversion, a solve that fails) is a :class:`TissueStep` status,
    never an exception; bad input raises :class:`tissue.errors.TissueInputError`.

    Snapshots (:meth:`state`, :meth:`set_state`), copies and pickles continue bit for bit
    alike: taking one drops the solver caches (kept factorisations, cached compliances), on
    this tissue as on the copy, and the next step rebuilds them.
    """

    def __init__(self, resolved: ResolvedTissue) -> None:
        self._resolved = resolved
        self._model: ContactModel = make_contact_model(
            resolved.contact_type,
            resolved.mesh,
            resolved.probe_shape,
            materials=resolved.materials,
            config=resolved.config,
            **({} if resolved.params is None else {"params": resolved.params}),
        )
        self._model.sleep_speed_m_s = resolved.spec.sleep_speed_m_s
        mesh = resolved.mesh
        self._lesions = LesionTracker(mesh)
        drawn = resolved.drawn_skin
        self._surface = SurfaceView(
            mesh,
            self._model.skin if drawn is None else SurfacePoints(drawn.embedding, drawn.triangles),
            self._lesions,
        )
        # The mesh and the materials: a state restores only into the same body.
        digest = hashlib.sha256(
            mesh.nodes.tobytes() + mesh.tets.tobytes() + repr(resolved.materials).encode()
        ).hexdigest()[:16]
        self._fingerprint = f"{resolved.spec.contact}/{resolved.spec.profile}/{digest}"
        self._shift_limits: NDArray[np.float64] | None = None
        self._rest_skin: RestSkin | None = None
        # The last step's lesion centroids [m] and the model's state version they were read
        # under: a sleeping step leaves the nodes where they are, so it reports these again
        # instead of summing the lesions' tets (~60 us at 1,363 tets).
        self._centroids: tuple[int, NDArray[np.float64]] | None = None
        self._tracked: NDArray[np.int64] | None = None

    # ------------------------------------------------------------------ description

    @property
    def spec(self) -> TissueSpec:
        """The spec this tissue was built from."""
        return self._resolved.spec

    @property
    def resolved(self) -> ResolvedTissue:
        """Every configuration the spec resolved to (materials, solver settings, ...)."""
        return self._resolved

    @property
    def contact(self) -> str:
        """The contact method's registry name."""
        return self._resolved.method

    @property
    def has_tangent(self) -> bool:
        """Whether the tissue has a stiffness tangent (:meth:`wrench_stiffness` not None)."""
        return self._model.has_tangent

    @property
    def dt(self) -> float:
        """The tissue time step [s]."""
        return self._model.dt

    @property
    def time_s(self) -> float:
        """Simulated time since the last reset [s]."""
        return self._model.time_s

    @property
    def probe_shape(self) -> ProbeShape:
        """The probe's geometry, in the probe frame."""
        return self._resolved.probe_shape

    @property
    def rest_nodes_m(self) -> NDArray[np.float64]:
        """Node positions at rest [m], (node_count, 3)."""
        return self._resolved.mesh.nodes

    @property
    def tets(self) -> NDArray[np.int64]:
        """Tet node indices, (tet_count, 4)."""
        return self._resolved.mesh.tets

    @property
    def regions(self) -> NDArray[np.int64]:
        """Region label per tet, (tet_count,): 0 tissue, k lesion k."""
        return self._resolved.mesh.region

    @property
    def fixed_nodes(self) -> NDArray[np.int64]:
        """Indices of the nodes held fixed (the chest wall)."""
        return self._resolved.mesh.fixed_nodes

    @property
    def positions_m(self) -> NDArray[np.float64]:
        """Current node positions [m], (node_count, 3), read-only."""
        return self._model.node_positions

    @property
    def velocities_m_s(self) -> NDArray[np.float64]:
        """Current node velocities [m/s], (node_count, 3), read-only."""
        return self._model.node_velocities

    @property
    def lesions(self) -> tuple[Lesion, ...]:
        """The lesions: rest centres, radii and tet sets."""
        return self._lesions.lesions

    @property
    def landmark_names(self) -> tuple[str, ...]:
        """Names of the tracked points (:attr:`TissueStep.landmarks_world_m`'s rows)."""
        landmarks = self._resolved.mesh.landmarks
        return () if landmarks is None else landmarks.names

    def lesion_centroids_m(self, lesions: Sequence[int] | None = None) -> NDArray[np.float64]:
        """Deformed lesion centroids now [m]: every lesion's, (lesion_count, 3), or those of
        ``lesions`` (indices into :attr:`lesions`), (len(lesions), 3), computing no other.

        Raises:
            TissueInputError: an index out of range.
        """
        which = None if lesions is None else self._lesion_indices(lesions)
        return self._lesions.centroids(self._model.node_positions, which)

    def track_lesions(self, lesions: Sequence[int] | None) -> None:
        """Which lesions each :class:`TissueStep` locates (``lesion_centroids_world_m``'s
        rows, in this order): indices into :attr:`lesions`; ``()`` none (no lesion is
        evaluated in a step); None (the default) every lesion. A setting of this object,
        not of its state: snapshots and pickles do not carry it.

        Raises:
            TissueInputError: an index out of range.
        """
        self._tracked = None if lesions is None else self._lesion_indices(lesions)
        self._centroids = None

    @property
    def tracked_lesions(self) -> tuple[int, ...] | None:
        """The lesions each step locates (:meth:`track_lesions`); None: every lesion."""
        return None if self._tracked is None else tuple(int(i) for i in self._tracked)

    def _lesion_indices(self, lesions: Sequence[int]) -> NDArray[np.int64]:
        count = len(self._lesions.lesions)
        indices = [int(i) for i in lesions]
        bad = [i for i in indices if not 0 <= i < count]
        if bad or any(isinstance(i, bool) for i in lesions):
            raise TissueInputError(
                f"lesion indices must be in 0..{count - 1} (indices into Tissue.lesions); "
                f"got {list(lesions)!r}"
            )
        return np.array(indices, dtype=np.int64)

    def surface(self) -> SurfaceMesh:
        """The skin and the lesions' boundaries as they are now, with region labels."""
        return self._surface.at(self._model.node_positions)

    def __repr__(self) -> str:
        mesh = self._resolved.mesh
        return (
            f"Tissue({mesh.name}: {mesh.tet_count} tets, contact {self.spec.contact!r}, "
            f"profile {self.spec.profile!r}, dt {self.dt} s)"
        )

    # ------------------------------------------------------------------ stepping

    def step(self, probe_pos_world: ArrayLike, probe_quat_wxyz: ArrayLike) -> TissueStep:
        """Move the probe to the pose and advance the tissue one :attr:`dt`.

        Args:
            probe_pos_world: the probe origin (contact-face centre) [m], (3,).
            probe_quat_wxyz: the probe's orientation (w, x, y, z), (4,), any non-zero norm.

        Raises:
            TissueInputError: a non-finite or mis-shaped pose, or a zero quaternion.
        """
        model = self._model
        start = time.perf_counter()
        if model.sleep_if_clear(probe_pos_world, probe_quat_wxyz):
            return self._asleep_step(start)
        _check_quat(probe_quat_wxyz)
        result = model.step_after_sleep_check(probe_pos_world, probe_quat_wxyz, start)
        return self._step_result(result)

    def _asleep_step(self, start: float) -> TissueStep:
        """The step :meth:`ContactModel.sleep_if_clear` took (every free-air step of a
        resting tissue): what :meth:`_step_result` makes of a sleeping step's result, built
        directly; ``start``: the step's ``time.perf_counter()`` at its start."""
        model = self._model
        version = model.state_version
        kept = self._centroids
        if kept is None or kept[0] != version:
            kept = (version, self._lesions.centroids(model.node_positions, self._tracked))
            self._centroids = kept
        return frozen(
            TissueStep,
            status=StepStatus.OK,
            time_s=model.time_s,
            force_world_n=np.zeros(3),
            torque_world_nm=np.zeros(3),
            contact_points_world_m=np.zeros((0, 3)),
            contact_forces_world_n=np.zeros((0, 3)),
            skin_penetration_m=0.0,
            landmarks_world_m=model.resting_landmarks(),
            lesion_centroids_world_m=kept[1].copy(),
            diagnostics=asleep_diagnostics(1e3 * (time.perf_counter() - start)),
            method_penetration_m=0.0,
        )

    def reset(
        self, probe_pos_world: ArrayLike | None = None, probe_quat_wxyz: ArrayLike | None = None
    ) -> None:
        """Back to rest (time 0, contact state cleared); with a pose, the probe is placed
        there (the next step sweeps from it, see :meth:`place_probe`)."""
        self._model.reset()
        if probe_pos_world is not None or probe_quat_wxyz is not None:
            if probe_pos_world is None or probe_quat_wxyz is None:
                raise TissueInputError("reset takes both the probe's position and quaternion")
            self.place_probe(probe_pos_world, probe_quat_wxyz)

    def place_probe(self, probe_pos_world: ArrayLike, probe_quat_wxyz: ArrayLike) -> None:
        """Put the probe at a pose without stepping the tissue: the next step sweeps the
        probe from here (without a placed pose, the first step after a reset takes the
        probe's pose as it is, with no sweep)."""
        _check_quat(probe_quat_wxyz)
        self._model.place_probe(probe_pos_world, probe_quat_wxyz)

    def touching_pose(
        self,
        target_world_m: ArrayLike,
        direction_world: ArrayLike | None = None,
        roll_rad: float | None = None,
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The probe pose (position [m], quaternion wxyz) that just touches the skin at
        rest above ``target_world_m`` [m] (a lesion centre, say), pressing along
        ``direction_world`` (default: into the skin, along its inward normal where the
        vertical through the target leaves it) with its long axis rolled by ``roll_rad``
        (default: down the skin's slope, a radial scan plane)."""
        target = np.asarray(target_world_m, dtype=np.float64).reshape(-1)
        if target.shape != (3,) or not np.all(np.isfinite(target)):
            raise TissueInputError(f"target must be 3 finite numbers [m]; got {target_world_m!r}")
        mesh = self._resolved.mesh
        if direction_world is None:
            direction = -self._rest_skin_query().normal_where_leaving(target)[1]
        else:
            direction = np.asarray(direction_world, dtype=np.float64).reshape(-1)
        shape = self._resolved.probe_shape
        roll = radial_roll_rad(shape, direction) if roll_rad is None else float(roll_rad)
        return first_contact_pose(
            self._model.skin, mesh.nodes, shape, target, direction, roll, self._rest_skin_query()
        )

    def rest_skin_normal(
        self, point_m: ArrayLike, direction: ArrayLike | None = None
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Where the ray from ``point_m`` [m] along ``direction`` (default straight up, +z)
        leaves the skin at rest [m], (3,), and the skin's inward unit normal there, (3,)
        (area-weighted over the skin triangles within 8 mm: smooth across triangles). About
        60 us on the 2 mm skin (16,710 triangles; the ray walks a grid of its triangles,
        :mod:`tissue.contact.ray_grid`); the same normal :meth:`touching_pose`
        presses along.

        Raises:
            TissueInputError: a non-finite point or direction, or a ray that meets no skin
                (start it inside the tissue).
        """
        point = np.asarray(point_m, dtype=np.float64).reshape(-1)
        if point.shape != (3,) or not np.all(np.isfinite(point)):
            raise TissueInputError(f"point must be 3 finite numbers [m]; got {point_m!r}")
        up = None
        if direction is not None:
            up = np.asarray(direction, dtype=np.float64).reshape(-1)
            if up.shape != (3,) or not np.all(np.isfinite(up)) or not np.any(up):
                raise TissueInputError(
                    f"direction must be 3 finite numbers, not all zero; got {direction!r}"
                )
        hit, outward = self._rest_skin_query().normal_where_leaving(point, up)
        return hit, -outward

    def _rest_skin_query(self) -> RestSkin:
        if self._rest_skin is None:
            self._rest_skin = RestSkin(self._resolved.mesh)
        return self._rest_skin

    def wrench_stiffness(self) -> NDArray[np.float64] | None:
        """How the tissue's wrench on the probe changes with the probe's displacement, now
        (6 x 6, world frame, about the probe origin): K = -d(force, torque) / d(translation,
        rotation) [N/m, N/rad; N m/m, N m/rad], symmetric positive semi-definite where the
        probe presses. The tissue's static response, linearised at the present state and
        contact set; see :mod:`tissue.contact.wrench_stiffness` for how and what it costs.
        None for a strategy without a tangent (PBD; :attr:`has_tangent`)."""
        # Under the step's thread rule: a small tissue's kernels on one thread (tissue.threads).
        with one_thread_below(3 * self._resolved.mesh.node_count, SERIAL_STEP_UNKNOWNS):
            return wrench_stiffness(self._model)

    # ------------------------------------------------------------------ variants

    def varied(
        self,
        materials: TissueMaterials | None = None,
        lesion_offsets_m: ArrayLike | None = None,
    ) -> Tissue:
        """A new tissue like this one with other materials and/or its lesions moved at rest
        (for domain randomisation): same mesh topology, skin, probe, contact method and
        profile; the strategy's settings re-derived for the variant
        (:meth:`ContactModel.settings_for_variant`: PBD keeps its calibration). No mesh is
        generated, so a variant costs about what building the model costs (no gmsh, no
        calibration). This tissue is left as it is.

        Args:
            materials: the variant's materials (None: this tissue's).
            lesion_offsets_m: one offset per lesion [m], (lesion_count, 3): each lesion moves
                by it at rest, the material around it following smoothly
                (:func:`tissue.mesh.lesion_shift.shift_lesions`); None: where they are.

        Raises:
            TissueInputError: materials of another type, or offsets of the wrong shape or
                beyond what the mesh allows (:meth:`lesion_shift_limits_m`).
        """
        resolved = self._resolved
        if materials is None:
            materials = resolved.materials
        elif not isinstance(materials, TissueMaterials):
            raise TissueInputError(
                f"materials must be a tissue.TissueMaterials; got {type(materials).__name__}"
            )
        mesh = resolved.mesh
        drawn = resolved.drawn_skin
        if lesion_offsets_m is not None:
            try:
                mesh = shift_lesions(mesh, lesion_offsets_m)
            except MeshError as error:
                raise TissueInputError(str(error)) from error
            if drawn is not None:
                drawn = surface_after_shift(drawn, resolved.mesh.nodes, mesh.nodes, mesh.tets)
        spec = replace(
            resolved.spec, young_pa=None, poisson=None, lesion_stiffness_ratio=None,
            materials=materials,
        )  # fmt: skip
        variant = replace(resolved, spec=spec, mesh=mesh, materials=materials, drawn_skin=drawn)
        config, params = resolved.contact_type.settings_for_variant(variant, mesh, materials)
        return Tissue(replace(variant, config=config, params=params))

    def lesion_shift_limits_m(self) -> NDArray[np.float64]:
        """Per lesion, the largest offset [m] :meth:`varied` accepts for it in any direction
        (:func:`tissue.mesh.lesion_shift.lesion_shift_limits`), (lesion_count,); computed
        once per tissue (a few tenths of a second on the coarse levels, 2 s at 12,861 tets)."""
        if self._shift_limits is None:
            self._shift_limits = lesion_shift_limits(self._resolved.mesh)
        return self._shift_limits.copy()

    # ------------------------------------------------------------------ snapshots

    def state(self) -> TissueState:
        """A snapshot to :meth:`set_state` from (a cache boundary: see the class docstring)."""
        snapshot = self._model.snapshot()
        return TissueState(self._fingerprint, self._model.time_s, copy.deepcopy(snapshot))

    def set_state(self, state: TissueState) -> None:
        """Continue from a :meth:`state` of a tissue built from the same spec."""
        if not isinstance(state, TissueState):
            raise TissueInputError(
                f"set_state takes a TissueState from Tissue.state(); got {type(state).__name__}"
            )
        if state.fingerprint != self._fingerprint:
            raise TissueInputError(
                f"this state belongs to another tissue ({state.fingerprint}); this one is "
                f"{self._fingerprint}: restore states into a tissue built from the same spec"
            )
        self._model.restore(copy.deepcopy(state.data))

    def __reduce__(self) -> tuple[Any, ...]:
        # Rebuilt from the resolved spec (no mesh generation, no PBD calibration again),
        # then restored: factorisations are not pickled, they are rebuilt.
        return (_rebuilt_tissue, (self._resolved, self.state()))

    # ------------------------------------------------------------------ internals

    @property
    def contact_model(self) -> ContactModel:
        """The contact strategy behind this tissue (for the study and benchmarks; not part
        of the front door's stable surface)."""
        return self._model

    def _step_result(self, result: TissueStep) -> TissueStep:
        """The contact model's step with the tracked lesions' centroids added."""
        version = self._model.state_version
        kept = self._centroids
        if result.diagnostics.details.get("asleep") and kept is not None and kept[0] == version:
            centroids = kept[1]  # the nodes have not moved since
        else:
            centroids = self._lesions.centroids(self._model.node_positions, self._tracked)
            self._centroids = (version, centroids)
        return with_lesions(result, centroids.copy())


def pressing_direction(probe_quat_wxyz: ArrayLike) -> NDArray[np.float64]:
    """The probe's +y axis in the world for an orientation (w, x, y, z), (3,): the direction
    it presses."""
    _check_quat(probe_quat_wxyz)
    return quat_to_matrix(probe_quat_wxyz)[:, 1].copy()


def _rebuilt_tissue(resolved: ResolvedTissue, state: TissueState) -> Tissue:
    tissue = Tissue(resolved)
    tissue.set_state(state)
    return tissue


def _check_quat(quat_wxyz: ArrayLike) -> None:
    quat = np.asarray(quat_wxyz, dtype=np.float64).reshape(-1)
    # Four math.isfinite calls: a fraction of np.isfinite's cost on 4 numbers (every step).
    if (
        quat.shape != (4,)
        or not all(math.isfinite(v) for v in quat.tolist())
        or float(quat @ quat) == 0.0
    ):
        raise TissueInputError(
            f"probe quaternion must be 4 finite numbers (w, x, y, z), not all zero; got "
            f"{quat_wxyz!r}"
        )
