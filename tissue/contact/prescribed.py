"""Prescribed surface displacement (Tagliabue et al. 2020, section 2.1.3).

The surface nodes under the probe are moved rigidly with it (a Dirichlet condition); there
is no collision detection at all. The reaction forces at those nodes are the contact forces,
and their negative is the wrench on the probe.

The node set: by default, the volume's boundary nodes within ``capture_distance_m`` of the
probe at the first pose where any comes that close (the probe's first contact pose), each
keeping its offset from the probe; or a given set (the published scene ships one per lesion,
``springnodes_500.txt``, which its loader maps to the nearest volume boundary nodes).

Beyond the paper, ``online=True`` updates the set every step from the probe's footprint: a
boundary node the probe's new pose would contain joins, and then sticks to the probe, at
the point where the probe first touched it (for a probe pressing straight in: the node moved
back along the motion onto the probe's surface; otherwise the nearest surface point); a node
whose reaction would pull the probe (tension) leaves.
This removes the paper's main limitation ("a priori knowledge of contact area needed").

``sliding=True`` (online only) makes the contact frictionless: a node in contact is held
only along the probe's normal, on the plane tangent to the probe at its nearest surface
point at the step's pose, and slides freely within it (a Dirichlet condition on its normal
coordinate, in a frame rotated to that normal; see :mod:`tissue.sim.frames`). Its reaction is
normal to the probe; it leaves contact when that reaction pulls.

With the skin guarded as well (``skin_guard``, the robust profile's), the set is settled
within the step, from the solved state rather than predicted from the start: a node joins
when the guarded step leaves it inside the probe deeper than the guard lets the skin lie,
and leaves when its reaction pulls, even where the probe's new pose would hold it inside;
the step is solved again from its start after each change (:meth:`_settled_step`). Holding
a node the probe's new pose merely contained put it on the probe's face where the skin
above it -- the collision surface, about 0.5 mm outside the coarse volume's boundary node
there -- was kept out by the guard: the node pulled the probe in (6-19 N at the apex of
1,363 tets under a 2 mm skin) while the guard's springs pushed out by as much, and the
force fell by a quarter as the two fought (``docs/contact.md``, "Forces that grow with
depth"). A node in tension that the pressing probe's new pose held inside was never let go.

Where online prescribed displacement still differs from Lagrange multipliers:

- without ``sliding``, nodes in contact stick to the probe (no tangential sliding: infinite
  friction), where LM is frictionless; with it, a node holds the tangent plane of the step's
  start for the whole step (on a curved probe, a node sliding s off the touching point
  ends s^2 / 2R inside or outside the surface; the next step projects it again);
- contact acts on volume boundary nodes, not on the collision surface's points (so its
  penetration is measured on those nodes: on a coarse volume the finer collision surface
  bulges between them by up to the chord's sag, about 1 mm at 623 tets);
- a node leaves contact one step after its reaction turns tensile (at once when the probe
  withdraws past it), and enters only once the probe has passed it (a penetration of up to
  one step's motion is corrected at entry); a node in tension that the probe's new pose
  would hold inside it stays held where it was (all three without the guard; with it the
  set is settled within the step, above).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from tissue.contact.fe_model import FEContactModel
from tissue.contact.penalty import (
    OFFSET_REACH_SHARE,
    PenaltyTerm,
    augmented_solve,
    augmented_step,
    default_stiffness_n_per_m,
)
from tissue.contact.registry import register_contact
from tissue.contact.wrench_stiffness import ContactConstraints
from tissue.errors import ConfigError
from tissue.mesh import TetMesh, boundary_faces
from tissue.profile import profile_choices
from tissue.sim.integrator import StepOutcome, with_work_of
from tissue.status import StepStatus

# Re-solves of a guarded step's springs at most (see PrescribedParams.skin_guard); as the
# penalty method's augmentations (tissue.contact.penalty.MAX_AUGMENTATIONS).
_GUARD_ROUNDS = 10
# Re-solves of a guarded sliding step whose node set changed at most (see _settled_step).
_SET_ROUNDS = 3
# Online mode releases a node at once if the probe would pull it back by more than this [m]
# in one step (a sudden withdrawal); sliding over the curved skin pulls far less per step.
_PULL_RELEASE_M = 0.0005


@dataclass(frozen=True)
class PrescribedParams:
    """Prescribed-displacement settings.

    Attributes:
        online: update the node set every step from the probe's footprint.
        sliding: (online) hold nodes along the probe's normal only, free to slide on it
            (frictionless contact) instead of moving them rigidly with the probe.
        capture_distance_m: (offline) boundary nodes this close to the probe at first
            contact form the set [m].
        node_set: (offline) a given set of volume node indices instead.
        skin_guard: (robust mode) keep the skin -- the collision surface, which on a coarse
            volume bulges between the boundary nodes the method holds -- out of the probe:
            a skin point inside it is pushed out by an augmented-Lagrangian spring solved in
            the same Newton step as the held nodes, the step re-solved until the deepest
            lies within ``skin_guard_tolerance_m`` and the springs' forces have settled (the
            penalty method's rounds, :func:`tissue.contact.penalty.augmented_solve`); with
            ``sliding`` the node set is then settled on the solved step (see the module
            docstring).
        skin_guard_tolerance_m: how deep a skin point may stay inside the probe [m].
    """

    online: bool = False
    sliding: bool = False
    capture_distance_m: float = 0.002
    node_set: tuple[int, ...] | None = field(default=None)
    skin_guard: bool = False
    skin_guard_tolerance_m: float = 1e-4

    def __post_init__(self) -> None:
        if not (np.isfinite(self.capture_distance_m) and self.capture_distance_m >= 0):
            raise ConfigError(f"capture_distance_m must be >= 0; got {self.capture_distance_m!r}")
        if self.online and self.node_set is not None:
            raise ConfigError("a given node_set and online=True exclude each other; choose one")
        if not (np.isfinite(self.skin_guard_tolerance_m) and self.skin_guard_tolerance_m > 0):
            raise ConfigError(
                f"skin_guard_tolerance_m must be > 0 m; got {self.skin_guard_tolerance_m!r}"
            )
        if self.sliding and not self.online:
            raise ConfigError(
                "sliding=True needs online=True: the paper's fixed node set moves rigidly with "
                "the probe"
            )


@register_contact
class PrescribedContact(FEContactModel):
    """The surface nodes under the probe follow it rigidly (Dirichlet conditions)."""

    name = "prescribed"
    label = "PrescrDispl"
    colour = "tab:green"
    #: Held nodes follow the probe: 0.5 mm, as the hard-cases catalogue asks of enforced
    #: contact.
    penetration_bound_m = 0.0005

    params_type = PrescribedParams
    params: PrescribedParams

    @classmethod
    def profile_params(cls, spec: Any, mesh: TetMesh) -> PrescribedParams:
        """Robust: an online, sliding node set with the skin guarded. Paper: the node set
        chosen at first contact, or on the published scene (``spec.scene_lesion``) the
        scene's own set for that lesion."""
        if profile_choices(spec.profile).online_prescribed:
            return PrescribedParams(online=True, sliding=True, skin_guard=True)
        if spec.scene_lesion is not None:
            return PrescribedParams(node_set=spec.published_node_set(mesh))
        return PrescribedParams()

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        boundary = np.unique(boundary_faces(self.mesh.tets))
        self.boundary_nodes = np.setdiff1d(boundary, self.mesh.fixed_nodes)
        if self.params.node_set is not None:
            given = np.asarray(self.params.node_set, dtype=np.int64)
            if given.size == 0 or given.min() < 0 or given.max() >= self.mesh.node_count:
                raise ConfigError(
                    f"node_set must hold node indices in [0, {self.mesh.node_count - 1}]; got "
                    f"{given.size} indices"
                )
        self._guard: PenaltyTerm | None = None
        if self.params.skin_guard:
            if not profile_choices(self.sim.config.mode).newton:
                raise ConfigError(
                    "skin_guard needs robust mode (its springs are re-solved in Newton's "
                    "step); the paper configuration keeps the paper's node set alone"
                )
            stiffness = default_stiffness_n_per_m(self.skin, self.mesh, self.sim.materials)
            self._guard = PenaltyTerm(self.skin, self.probe, stiffness, 0.0)
        self._nodes = np.zeros(0, dtype=np.int64)
        self._local = np.zeros((0, 3))  # each node's position in the probe frame
        self._last_reaction: NDArray[np.float64] | None = None
        # The probe's position at the last step and its translation since [m].
        self._last_position: NDArray[np.float64] | None = None
        self._step_motion: NDArray[np.float64] | None = None

    def _reset_tissue(self) -> None:
        super()._reset_tissue()
        if self._guard is not None:
            self._guard.release()
        self._nodes = np.zeros(0, dtype=np.int64)
        self._local = np.zeros((0, 3))
        self._last_reaction = None
        self._last_position = None
        self._step_motion = None

    def sleep_reach_m(self) -> float | None:
        """The skin guard's reach [m] (its springs' force offsets over k_s; 0 without
        them: online nodes join only once inside the probe), and for a node set taken at
        first contact the capture distance. None for a given node set: it is taken at the
        first step wherever the probe is, so that step must run."""
        params = self.params
        if params.node_set is not None:
            return None
        reach = 0.0
        if self._guard is not None:
            reach = float(self._guard.offsets.max(initial=0.0)) / self._guard.stiffness
        if not params.online:
            reach = max(reach, params.capture_distance_m)
        return reach

    def _in_contact(self) -> bool:
        return bool(self._nodes.size)

    def _advance_asleep(self, h: float, pieces: int) -> None:
        # What a step with no node held records (see _advance).
        super()._advance_asleep(h, pieces)
        position = self.probe.position_world.copy()
        before = self._last_position
        self._step_motion = None if before is None else position - before
        self._last_position = position
        self._last_reaction = np.zeros((0, 3))

    def contact_points_world(self) -> NDArray[np.float64]:
        """The free boundary nodes [m], (k, 3): the points the method moves with the probe."""
        return self.sim.positions[self.boundary_nodes]

    def contact_points_near(self) -> NDArray[np.float64]:
        return self.contact_points_world()

    @property
    def contact_nodes(self) -> NDArray[np.int64]:
        """The nodes currently moved with the probe."""
        return self._nodes

    def contact_constraints(self) -> ContactConstraints:
        """The held nodes: three exact constraints each (sticking), or one along the probe's
        normal (sliding)."""
        nodes = self._nodes
        positions = self.sim.positions[nodes]
        if self.params.sliding:
            _, normal = self.probe.signed_distance_world(positions)
            directions, owners = normal, np.arange(nodes.size)
        else:
            directions = np.tile(np.eye(3), (nodes.size, 1))
            owners = np.repeat(np.arange(nodes.size), 3)
        count = owners.size
        columns = (3 * nodes[owners])[:, None] + np.arange(3)[None, :]
        rows = sp.csr_matrix(
            (directions.reshape(-1), columns.reshape(-1), np.arange(0, 3 * count + 1, 3)),
            shape=(count, self.mesh.dof_count),
        )
        held = ContactConstraints(rows, positions[owners], directions, np.zeros(count))
        if self._guard is None:
            return held
        self._guard.evaluate(self.sim.positions)
        contacts = self._guard.last_contacts
        active = self._guard.last_magnitudes > 0.0
        springs = self._constraint_rows(
            self.skin,
            contacts.points[active],
            contacts.normal[active],
            1.0 / self._guard.stiffness,
        )
        return ContactConstraints(
            sp.vstack([held.rows, springs.rows]).tocsr(),
            np.concatenate([held.points_world_m, springs.points_world_m]),
            np.concatenate([held.directions_world, springs.directions_world]),
            np.concatenate([held.compliance_m_per_n, springs.compliance_m_per_n]),
        )

    def _snapshot_contact(self) -> dict[str, Any]:
        def copied(value: NDArray[np.float64] | None) -> NDArray[np.float64] | None:
            return None if value is None else value.copy()

        return {
            "guard": None if self._guard is None else self._guard.state(),
            "nodes": self._nodes.copy(),
            "local": self._local.copy(),
            "last_reaction": copied(self._last_reaction),
            "last_position": copied(self._last_position),
            "step_motion": copied(self._step_motion),
        }

    def _restore_contact(self, snapshot: dict[str, Any]) -> None:
        def copied(value: NDArray[np.float64] | None) -> NDArray[np.float64] | None:
            return None if value is None else np.array(value)

        if self._guard is not None:
            self._guard.set_state(snapshot["guard"])
        self._nodes = np.array(snapshot["nodes"], dtype=np.int64)
        self._local = np.array(snapshot["local"], dtype=np.float64)
        self._last_reaction = copied(snapshot["last_reaction"])
        self._last_position = copied(snapshot["last_position"])
        self._step_motion = copied(snapshot["step_motion"])

    def _advance(
        self, h: float
    ) -> tuple[StepStatus, NDArray[np.float64], NDArray[np.float64], dict[str, Any]]:
        position = self.probe.position_world.copy()
        before = self._last_position
        self._step_motion = None if before is None else position - before
        self._last_position = position
        settled = self.params.sliding and self._guard is not None
        if self.params.sliding:
            self._update_sliding(settled)
        elif self.params.online:
            self._update_online()
        elif self._nodes.size == 0:
            self._capture_offline()
        planes: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None
        if self._nodes.size and self.params.sliding:
            # Each node on the plane tangent to the probe at its nearest surface point.
            positions = self.sim.positions[self._nodes]
            distance, normal = self.probe.signed_distance_world(positions)
            planes = (positions - distance[:, None] * normal, normal)
            self.sim.prescribe_normal(self._nodes, *planes)
        elif self._nodes.size:
            self.sim.prescribe(self._nodes, self.probe.to_world_frame(self._local))
        else:
            self.sim.clear_prescribed()
        guard_rounds = set_rounds = 0
        if self._guard is None:
            result = self.sim.step(dt=h)
        elif settled:
            started = time.perf_counter()
            self._guard.predict_offsets(OFFSET_REACH_SHARE * self.params.skin_guard_tolerance_m)
            outcome, guard_rounds, set_rounds = self._settled_step(h, planes)
            result = self.sim.commit(outcome, h, started)
            self._guard.record_forces(self.sim.positions)
        else:
            result, guard_rounds = augmented_step(
                self.sim, self._guard, h, self.params.skin_guard_tolerance_m, _GUARD_ROUNDS
            )
        reaction = result.reaction_forces[self._nodes]  # on the tissue
        self._last_reaction = reaction
        points = self.sim.positions[self._nodes].copy()
        forces = -reaction
        guarded = 0
        if self._guard is not None:
            # The guard's springs at the step's end push the skin out of the probe: their
            # reaction is on the probe too.
            self._guard.evaluate(self.sim.positions)
            spring_points, spring_forces = self.surface_points_on_probe(
                self._guard.last_contacts, self._guard.last_magnitudes
            )
            guarded = int(spring_points.shape[0])
            points = np.concatenate([points, spring_points])
            forces = np.concatenate([forces, spring_forces])
        diagnostics = {
            "guarded_skin_points": guarded,
            "guard_augmentations": guard_rounds,
            "node_set_rounds": set_rounds,
            "contact_nodes": int(self._nodes.size),
            "newton_iterations": result.newton_iterations,
            "linear_iterations": result.linear_iterations,
            "linear_residual": result.linear_residual,
            "subdivisions": result.subdivisions,
            "min_volume_ratio": result.min_volume_ratio,
        }
        return result.status, points, forces, diagnostics

    def _capture_offline(self) -> None:
        if self.params.node_set is not None:
            nodes = np.unique(np.asarray(self.params.node_set, dtype=np.int64))
        else:
            positions = self.sim.positions[self.boundary_nodes]
            distance, _ = self.probe.signed_distance_world(positions)
            nodes = self.boundary_nodes[distance <= self.params.capture_distance_m]
            if nodes.size == 0:
                return  # not in contact yet: the tissue moves freely
        self._nodes = nodes
        self._local = self.probe.to_probe_frame(self.sim.positions[nodes])

    def _update_online(self) -> None:
        positions = self.sim.positions
        keep = np.ones(self._nodes.size, dtype=bool)
        reaction = self._last_reaction
        if self._nodes.size and reaction is not None and reaction.shape[0] == self._nodes.size:
            # The probe pushes the tissue along its outward normal; a node whose reaction
            # pulls it back towards the probe is in tension and is released ...
            distance, normal = self.probe.signed_distance_world(positions[self._nodes])
            # ... unless the probe's new pose holds it inside: then it stays where it is held.
            # Released and at once re-captured at a new entry point, it would slip under the
            # probe while held (no-slip), and that slip's work is not the probe's (published
            # level-4 poses: 1-2 nodes a step; elastic + kinetic energy rose 2.2 mJ, 5 %,
            # above the probe's work); left free, it would lie inside the probe for a step.
            keep = (np.einsum("ij,ij->i", reaction, normal) > 0.0) | (distance < 0.0)
        # Contact only pushes: a node the probe's new pose would pull back out of the
        # tissue by more than ``_PULL_RELEASE_M`` (a probe withdrawn faster than the skin
        # can follow) is released now; slower withdrawal shows as tension one step later.
        if self._nodes.size:
            targets = self.probe.to_world_frame(self._local)
            pressing = self.probe.pressing_direction_world()
            keep &= (targets - positions[self._nodes]) @ pressing >= -_PULL_RELEASE_M
        nodes, local = self._nodes[keep], self._local[keep]
        # Nodes just released do not re-enter in the same update (none lies inside the probe).
        candidates = self._free_nodes_near_probe(positions)
        distance, normal = self.probe.signed_distance_world(positions[candidates])
        entering = distance < 0.0
        if np.any(entering):
            on_surface = self._entry_points(
                positions[candidates[entering]], distance[entering], normal[entering]
            )
            nodes = np.concatenate([nodes, candidates[entering]])
            local = np.concatenate([local, self.probe.to_probe_frame(on_surface)])
        order = np.argsort(nodes)
        self._nodes, self._local = nodes[order], local[order]

    def _free_nodes_near_probe(self, positions: NDArray[np.float64]) -> NDArray[np.int64]:
        """The boundary nodes not held now that lie within the probe's bounding sphere (only
        those can be inside it), ascending; ``positions`` [m] (node_count, 3).

        A mask, where ``np.setdiff1d`` sorted both sets (60-odd Python-level calls a step),
        and the signed distance for the few dozen nodes near the probe, not all ~500."""
        held = np.zeros(self.mesh.node_count, dtype=bool)
        held[self._nodes] = True
        nodes = self.boundary_nodes[~held[self.boundary_nodes]]
        return nodes[self.probe.near(positions[nodes])]

    def _update_sliding(self, settled: bool = False) -> None:
        """Frictionless online set: nodes inside the probe's new pose join; a node leaves
        when its (normal) reaction pulls the probe, unless the new pose holds it inside, or
        at once when the new pose lies more than ``_PULL_RELEASE_M`` clear of it.

        ``settled`` (the skin guarded): a node whose reaction pulled leaves even where the
        new pose holds it inside, and none joins here: nodes join from the solved step
        (:meth:`_settled_step`)."""
        positions = self.sim.positions
        nodes = self._nodes
        if nodes.size:
            distance, normal = self.probe.signed_distance_world(positions[nodes])
            keep = distance <= _PULL_RELEASE_M
            reaction = self._last_reaction
            if reaction is not None and reaction.shape[0] == nodes.size:
                pushing = np.einsum("ij,ij->i", reaction, normal) > 0.0
                keep &= pushing if settled else pushing | (distance < 0.0)
            nodes = nodes[keep]
        self._local = np.zeros((nodes.size, 3))  # unused: sliding nodes keep no anchor
        if settled:
            self._nodes = nodes
            return
        candidates = self._free_nodes_near_probe(positions)
        distance, _ = self.probe.signed_distance_world(positions[candidates])
        self._nodes = np.union1d(nodes, candidates[distance < 0.0])
        self._local = np.zeros((self._nodes.size, 3))

    def _settled_step(
        self, h: float, planes: tuple[NDArray[np.float64], NDArray[np.float64]] | None
    ) -> tuple[StepOutcome, int, int]:
        """A guarded sliding step of ``h`` [s] whose node set is settled on the solved state
        (see the module docstring): solved with the guard's springs (not committed); a free
        boundary node it leaves inside the probe deeper than the guard's tolerance joins, on
        the plane tangent to the probe at its nearest surface point; a held node whose
        reaction pulls leaves; after a change the step is solved again from its start, at
        most ``_SET_ROUNDS`` times. ``planes``: the held nodes' planes (points [m], normals),
        (k, 3) each, as prescribed. Returns the outcome, the guard's augmentations (all
        rounds) and the re-solves; the outcome carries the Newton and linear iterations of
        every solve (:func:`tissue.sim.integrator.with_work_of`)."""
        sim, guard = self.sim, self._guard
        assert guard is not None
        tolerance = self.params.skin_guard_tolerance_m
        points, normals = planes if planes is not None else (np.zeros((0, 3)), np.zeros((0, 3)))
        augmentations = 0
        spent: StepOutcome | None = None
        for set_round in range(_SET_ROUNDS + 1):
            outcome, rounds = augmented_solve(sim, guard, h, tolerance, _GUARD_ROUNDS)
            if spent is not None:
                outcome = with_work_of(outcome, spent)
            spent = outcome
            augmentations += rounds
            if set_round == _SET_ROUNDS or outcome.status in (
                StepStatus.DIVERGED,
                StepStatus.SOLVER_FAILED,
            ):
                break
            solved = outcome.positions
            nodes = self._nodes
            keep = np.ones(nodes.size, dtype=bool)
            if nodes.size:
                _, normal = self.probe.signed_distance_world(solved[nodes])
                reaction = outcome.reaction_forces[nodes]
                keep = np.einsum("ij,ij->i", reaction, normal) > 0.0
            held = np.zeros(self.mesh.node_count, dtype=bool)
            held[nodes] = True
            free = self.boundary_nodes[~held[self.boundary_nodes]]
            free = free[self.probe.near(solved[free])]
            distance, normal = self.probe.signed_distance_world(solved[free])
            entering = distance < -tolerance
            if keep.all() and not entering.any():
                break
            joining = free[entering]
            nodes = np.concatenate([nodes[keep], joining])
            points = np.concatenate(
                [points[keep], solved[joining] - distance[entering, None] * normal[entering]]
            )
            normals = np.concatenate([normals[keep], normal[entering]])
            order = np.argsort(nodes)
            self._nodes, points, normals = nodes[order], points[order], normals[order]
            self._local = np.zeros((self._nodes.size, 3))
            if self._nodes.size:
                sim.prescribe_normal(self._nodes, points, normals)
            else:
                sim.clear_prescribed()
        return outcome, augmentations, set_round

    def _entry_points(
        self,
        points: NDArray[np.float64],
        distance: NDArray[np.float64],
        normal: NDArray[np.float64],
    ) -> NDArray[np.float64]:
        """Where the probe first touched each entering node [m], shape (k, 3).

        A node the probe has passed lies inside it. When the probe translated along its
        pressing direction p this step, it touched the node where the node, moved back
        along its motion relative to the probe, leaves the probe: ``x + t p`` with t > 0 on
        the surface (bisection on the signed distance). Projecting onto the nearest surface
        point instead drags nodes under a rounded rim sideways, towards the rim, which
        over-stiffens the footprint (Hertz: +4.2 % against +3.9 %). Otherwise, or if the ray
        does not bring the node out within 1.5 times its penetration depth, the node takes
        the nearest surface point.
        """
        nearest = points - distance[:, None] * normal
        # Only for a probe translating along its pressing direction (within ~10 degrees):
        # moving any other way, a node's first touch is not where the ray says (an edge
        # pressing at 60 degrees put strain energy beyond the probe's work into the tissue).
        direction = self.probe.pressing_direction_world()
        motion = self._step_motion
        length = float(np.linalg.norm(motion)) if motion is not None else 0.0
        if motion is None or length <= 1e-12 or motion @ direction < 0.985 * length:
            return nearest
        depth = -distance  # > 0
        reach = 1.5 * depth + 1e-9
        far = points + reach[:, None] * direction
        outside, _ = self.probe.signed_distance_world(far)
        ray = outside >= 0.0
        low = np.zeros_like(depth)
        high = reach.copy()
        # 30 halvings leave ~1e-9 of the bracket: far below any mesh's node spacing.
        for _ in range(30):
            middle = 0.5 * (low + high)
            value, _ = self.probe.signed_distance_world(points + middle[:, None] * direction)
            inside = value < 0.0
            low = np.where(inside, middle, low)
            high = np.where(inside, high, middle)
        entry = points + high[:, None] * direction
        return np.where(ray[:, None], entry, nearest)
