"""Penalty contact (Tagliabue et al. 2020, section 2.1.1; SOFA's ``PenalityContactForceField``).

Every collision-surface point closer to the probe than the contact distance gets a
one-sided spring along the probe's outward normal, f = k_s delta n (eq. 6), delta the
penetration past the contact distance. The force is spread to the volume nodes through the
point's barycentric embedding, and its stiffness k_s n n^T (normal frozen, frictionless)
enters the implicit system, so the step stays implicit in the contact too.

In ``paper`` mode the springs are linearised once per step at the start positions, as
SOFA does; in ``robust`` mode they are an energy term of the step's incremental potential,
re-evaluated at every Newton iterate (so contacts appearing during the step are caught).
Their stiffness also goes to the linear solver as one rank-one term per active point, so
that the robust solver's kept factorisation is corrected for springs that joined or left
since it was computed instead of letting CG pay an iteration for each
(:class:`~tissue.sim.solvers.RankOneTerms`).

Robust mode also augments the springs (augmented Lagrangian, Simo & Laursen 1992; Wriggers,
*Computational Contact Mechanics*, 2006, section 6.3): each point carries a force offset
lambda, its force is max(0, lambda + k delta), and after a converged step whose deepest
point is past ``penetration_tolerance_m``, or whose offsets still move the tissue's nodal
contact forces by more than ``force_tolerance`` of them, the offsets take the step's forces
and the step is solved again from the same start (at most ``max_augmentations`` times).
The offsets carry over to the next step, so a steady press needs one or two solves per step.
The penetration falls to the tolerance without the default k_s being raised everywhere,
which keeps the system as well conditioned as the default k_s makes it (the paper's
stability problem with stiff penalties), with two safeguards found on the breast phantom's
coarse levels (623-1,363 tets under a 2 mm skin, where a few skin points carry the whole
press, up to 2.4 N each; ``docs/contact.md``, "Forces that grow with depth"):

- An offset lambda pushes its point until lambda + k delta = 0, that is up to lambda / k
  outside the probe: to the point the probe is inflated by lambda / k. With the default k_s
  (307 N/m under the 2 mm skin) that was 7.8 mm, several times the probe's 1.35 mm rim
  radius, and a loaded point slid round the inflated rim onto the probe's side, where its
  offset shoved the skin sideways: the rounds oscillated (penetration 0.4-1.5 mm after 5),
  and the force fell by 12 % with the probe pressing straight down on the apex. After each
  augmentation k is therefore raised to the largest offset over the penetration tolerance
  (never below the default k_s): no offset reaches farther than the tolerance the method
  already allows, the geometry the springs see is the probe's to within it. The penalty
  parameter update of the method of multipliers (Bertsekas, *Constrained Optimization and
  Lagrange Multiplier Methods*, 1982, section 2.2; Nocedal & Wright, *Numerical
  Optimization*, 2006, section 17.4), first for a geometric reason, and then for the
  method's own one: a round shrinks the offsets' error by about K / (K + k), K the tissue's
  stiffness under the point. Raised only to the tolerance, k left the rounds contracting
  by 0.2-0.5 each as points joined the contact (the bench-peer press at 4,126 tets), so k
  is raised to the largest offset over a tenth of the tolerance (``OFFSET_REACH_SHARE``).
- Penetration alone does not say the offsets are right: a point that slid off the face
  keeps pushing with its old offset from just outside the probe, within the tolerance. The
  rounds go on until the offsets' change also moves the tissue's nodal contact forces (the
  springs' forces spread to the nodes through the embedding, which is what the tissue
  feels; forces shifting among points embedded in the same tet change nothing and are not
  counted) by at most ``force_tolerance`` of them (1 %). Before, penalty's force fell by up
  to 20 % as a 1,363-tet phantom's lesion 6 was pressed, where LM's fell by 5.7 %; after, by
  6.6 %, and by LM's 5.7 % since k is raised for a tenth of the tolerance.

Each augmentation round solves the step again from its start state (Newton from the
extrapolation x + h v + h^2 a in the first round, from where the round before ended in
the others), and the springs' tangent
freezes the contact normal (the exact tangent's -m d2g/dx2 term is left out), so robust
steps converge only linearly where the probe's rounded rim presses hard; the integrator's
extrapolating line search (:mod:`tissue.sim.integrator.line_search`) recovers most of the
lost speed. Why neither alternative was kept is in ``docs/design-decisions.md``.

Limitations: the constraint is only approximately satisfied (penetration ~ force / k_s);
a large k_s worsens the conditioning of the system (the paper's stability problem on fine
meshes). The default k_s scales with the tissue's modulus and the surface's resolution
(see :class:`PenaltyParams`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numba
import numpy as np
from numpy.typing import NDArray

from tissue.contact.fe_model import FEContactModel, detect_contacts
from tissue.contact.registry import register_contact
from tissue.contact.surface_points import SurfacePoints
from tissue.contact.wrench_stiffness import ContactConstraints
from tissue.errors import ConfigError
from tissue.fem.material import TissueMaterials
from tissue.mesh import TetMesh
from tissue.probe import Probe
from tissue.profile import profile_choices
from tissue.sim.integrator import StepOutcome, TermEvaluation, with_work_of
from tissue.sim.simulator import StepResult, TissueSimulator
from tissue.sim.solvers import RankOneTerms
from tissue.status import StepStatus

# The default k_s makes a contact point as stiff as this many times the tissue under it
# (E times the surface's mean edge length): penetrations stay about 2 % of the indentation.
DEFAULT_STIFFNESS_RATIO = 50.0
#: Augmented springs are re-solved until an augmentation would move the nodal contact forces
#: by at most this share of them (see the module docstring): 1 %, a fifth of the 5 % fall
#: the force-growth test allows.
FORCE_TOLERANCE = 0.01
#: k is raised so that no offset reaches farther outside the probe than this share of the
#: penetration tolerance (see the module docstring). Against the whole tolerance (1), on
#: the scripted episodes of ``probegym bench env`` (1,303 tets, 2 mm skin): Newton
#: iterations 999 -> 869 (LesionSearch-v0), 329 -> 252 (ForceScan-v0), 180 -> 145
#: (BreastCompress-v0), rounds 177 -> 93, 99 -> 48, 55 -> 27, and forces closer to LM's. A
#: third gained less; a thirtieth and a hundredth took more iterations on LesionSearch-v0
#: (stiffer springs, harder Newton solves).
OFFSET_REACH_SHARE = 0.1
#: Re-solves of an augmented step at most. With the force tolerance a 0.5 mm press step on
#: the phantom's coarse levels took 2.2 solves on average; 2 % of them stopped at 10.
MAX_AUGMENTATIONS = 10


@dataclass(frozen=True)
class PenaltyParams:
    """Penalty-contact settings.

    Attributes:
        stiffness_n_per_m: k_s [N/m] per contact point; None picks
            ``DEFAULT_STIFFNESS_RATIO`` x E_tissue x mean surface edge length.
        contact_distance_m: springs act when a point is closer than this to the probe [m]
            (the published scene used 1 mm; 0 makes the probe surface itself the contact).
        augmented: augmented-Lagrangian updates (see the module docstring); None: as the
            profile chooses (robust yes; paper keeps the paper's plain springs).
        penetration_tolerance_m: (augmented) re-solve a step while a point is deeper [m];
            an offset pushes a point from at most ``OFFSET_REACH_SHARE`` of it outside the
            probe (k is raised to keep it so).
        force_tolerance: (augmented) re-solve a step while an augmentation would change
            the nodal contact forces by more than this share of them (relative, 2-norm).
        max_augmentations: (augmented) re-solves per step at most.
    """

    stiffness_n_per_m: float | None = None
    contact_distance_m: float = 0.0
    augmented: bool | None = None
    penetration_tolerance_m: float = 1e-4
    force_tolerance: float = FORCE_TOLERANCE
    max_augmentations: int = MAX_AUGMENTATIONS

    def __post_init__(self) -> None:
        if not (np.isfinite(self.penetration_tolerance_m) and self.penetration_tolerance_m > 0):
            raise ConfigError(
                f"penetration_tolerance_m must be > 0 m; got {self.penetration_tolerance_m!r}"
            )
        if not (np.isfinite(self.force_tolerance) and self.force_tolerance > 0):
            raise ConfigError(f"force_tolerance must be > 0; got {self.force_tolerance!r}")
        if not (isinstance(self.max_augmentations, int) and self.max_augmentations >= 0):
            raise ConfigError(
                f"max_augmentations must be an integer >= 0; got {self.max_augmentations!r}"
            )
        if self.stiffness_n_per_m is not None and not (
            np.isfinite(self.stiffness_n_per_m) and self.stiffness_n_per_m > 0
        ):
            raise ConfigError(
                f"penalty stiffness k_s must be a positive number of N/m; got "
                f"{self.stiffness_n_per_m!r} (leave it None for the default)"
            )
        if not (np.isfinite(self.contact_distance_m) and self.contact_distance_m >= 0):
            raise ConfigError(f"contact_distance_m must be >= 0; got {self.contact_distance_m!r}")


class PenaltyTerm:
    """The penalty springs as an energy term of the tissue step (see the module docstring)."""

    def __init__(self, surface: SurfacePoints, probe: Probe, stiffness: float, distance: float):
        self.surface = surface
        self.probe = probe
        #: k_s, the stiffness the springs start from and return to [N/m].
        self.base_stiffness = stiffness
        # The stiffness augmentation raised k to [N/m] (0: not raised; see augment).
        self._raised_stiffness = 0.0
        self.distance = distance
        self._cache_key: NDArray[np.float64] | None = None
        self._cache: TermEvaluation | None = None
        self._cache_pose = np.zeros(8)
        self.last_contacts: Any = None
        self.last_magnitudes = np.zeros(0)
        # Augmented-Lagrangian force offsets per surface point [N] (zero: plain springs).
        self.offsets = np.zeros(surface.count)
        self._offsets_version = 0
        # The springs' forces per surface point at the end of the last two committed steps
        # [N] (None: not known yet), the offsets' predictor (predict_offsets).
        self._ended: NDArray[np.float64] | None = None
        self._ended_before: NDArray[np.float64] | None = None

    @property
    def stiffness(self) -> float:
        """The springs' stiffness k now [N/m]: k_s (:attr:`base_stiffness`), or more where
        augmented offsets raised it (:meth:`augment`). Setting it sets k_s."""
        return max(self.base_stiffness, self._raised_stiffness)

    @stiffness.setter
    def stiffness(self, value: float) -> None:
        self.base_stiffness = float(value)
        self._offsets_version += 1

    def augment(self, positions: NDArray[np.float64], reach_m: float | None = None) -> float:
        """Offsets <- the forces at ``positions`` (lambda <- max(0, lambda + k delta)); with
        ``reach_m`` [m], k <- max(k_s, largest offset / ``reach_m``), so that no offset
        pushes a point from farther outside the probe than ``reach_m`` (see the module
        docstring).

        Returns the deepest penetration past the contact distance there [m] (>= 0), measured
        before the update.
        """
        self.evaluate(positions)
        contacts = self.last_contacts
        depth = self.distance - contacts.distance
        self.offsets[:] = 0.0
        self.offsets[contacts.points] = self.last_magnitudes
        if reach_m is not None:
            self._raised_stiffness = float(self.last_magnitudes.max(initial=0.0)) / reach_m
        self._offsets_version += 1
        return float(max(0.0, depth.max())) if depth.size else 0.0

    def predict_offsets(self, reach_m: float) -> None:
        """Before a step's first solve: offsets <- max(0, 2 f_n - f_(n-1)), the springs'
        forces at the end of the last two committed steps (:meth:`record_forces`) carried
        on linearly, and k raised for them as :meth:`augment` raises it (``reach_m`` [m]).

        The augmentation's rounds end only where the offsets carry the step's forces to
        within the force tolerance: in a steady motion the forces change by a few percent
        a step, so offsets kept from the last step fail that test and cost a re-solve every
        step; carried on, they pass it in the first solve. A wrong prediction (a motion
        reversed) costs what a kept offset costs, a re-solve; the rounds' tests, and so
        the step's accuracy, are unchanged. Nothing is predicted before two steps ended."""
        if self._ended is None or self._ended_before is None:
            return
        np.maximum(2.0 * self._ended - self._ended_before, 0.0, out=self.offsets)
        self._raised_stiffness = float(self.offsets.max(initial=0.0)) / reach_m
        self._offsets_version += 1

    def record_forces(self, positions: NDArray[np.float64]) -> None:
        """After a committed step ending at ``positions``: its springs' forces per point
        (for :meth:`predict_offsets`)."""
        self.evaluate(positions)
        ended = np.zeros(self.surface.count)
        ended[self.last_contacts.points] = self.last_magnitudes
        self._ended_before, self._ended = self._ended, ended

    def release(self) -> None:
        """Plain springs again: no offsets, k = k_s, no forces recorded (a reset)."""
        self.offsets[:] = 0.0
        self._raised_stiffness = 0.0
        self._ended = self._ended_before = None
        self._offsets_version += 1

    def state(self) -> dict[str, Any]:
        """The augmentation's state (copied): the offsets [N], the raised k [N/m] and the
        forces recorded for the predictor [N]."""
        return {
            "offsets": self.offsets.copy(),
            "raised_stiffness": self._raised_stiffness,
            "ended": None if self._ended is None else self._ended.copy(),
            "ended_before": None if self._ended_before is None else self._ended_before.copy(),
        }

    def set_state(self, state: dict[str, Any]) -> None:
        """Adopt a :meth:`state`."""
        self.offsets[:] = state["offsets"]
        self._raised_stiffness = float(state["raised_stiffness"])
        ended, before = state.get("ended"), state.get("ended_before")
        self._ended = None if ended is None else ended.copy()
        self._ended_before = None if before is None else before.copy()
        self._offsets_version += 1

    def force_change(self, positions: NDArray[np.float64]) -> float:
        """How much an augmentation at ``positions`` would change the tissue's nodal contact
        forces, relative to them: ||N (f - lambda)|| / ||N f||, f the springs' forces there,
        lambda the offsets, N spreading point forces along their normals to the nodes
        through the embedding (0 with no force at all).

        The nodes are what the tissue feels: forces moving among points embedded in one tet
        that leave its nodes' forces as they are change nothing and are not counted (on a
        coarse volume under a fine skin such a shift repeats from round to round and kept a
        per-point measure at 5-7 %)."""
        self.evaluate(positions)
        contacts = self.last_contacts
        forces = self.last_magnitudes
        change = forces - self.offsets[contacts.points]
        # Offsets of points no longer found near the probe would fall to zero.
        lost = self.offsets.copy()
        lost[contacts.points] = 0.0
        nodes = self.surface.embedding.tet_nodes[contacts.points]
        weights = self.surface.embedding.weights[contacts.points]
        node_count = int(nodes.max(initial=-1)) + 1
        moved = np.zeros((node_count, 3))
        felt = np.zeros((node_count, 3))
        for a in range(4):
            np.add.at(moved, nodes[:, a], (weights[:, a] * change)[:, None] * contacts.normal)
            np.add.at(felt, nodes[:, a], (weights[:, a] * forces)[:, None] * contacts.normal)
        total = float(np.linalg.norm(felt))
        moved_norm = float(np.hypot(np.linalg.norm(moved), np.linalg.norm(lost)))
        if total == 0.0:
            return 0.0 if moved_norm == 0.0 else np.inf
        return moved_norm / total

    def penetration_m(self, positions: NDArray[np.float64]) -> float:
        """Deepest point past the contact distance at ``positions`` [m] (>= 0)."""
        self.evaluate(positions)
        depth = self.distance - self.last_contacts.distance
        return float(max(0.0, depth.max())) if depth.size else 0.0

    def evaluate(self, positions: NDArray[np.float64]) -> TermEvaluation:
        # One step asks for forces and stiffness at the same positions several times.
        # The probe moves between steps: the cache is keyed on its pose too.
        pose = np.concatenate(
            [self.probe.position_world, self.probe.quat_wxyz, [self._offsets_version]]
        )
        key = self._cache_key
        cached = (
            key is not None
            and key.shape == positions.shape
            and np.array_equal(key, positions)
            and np.array_equal(self._cache_pose, pose)
        )
        if cached and self._cache is not None:
            return self._cache
        # A point with an offset pushes until lambda + k_s delta = 0, a little outside.
        reach = self.distance + float(self.offsets.max(initial=0.0)) / self.stiffness
        contacts = detect_contacts(self.surface, positions, self.probe, reach)
        depth = self.distance - contacts.distance  # > 0 past the contact distance
        magnitude = np.maximum(self.offsets[contacts.points] + self.stiffness * depth, 0.0)
        tet_nodes = self.surface.embedding.tet_nodes[contacts.points]
        weights = self.surface.embedding.weights[contacts.points]
        active = magnitude > 0.0
        count = int(np.count_nonzero(active))
        forces = np.zeros((positions.shape[0], 3))  # on the tissue, away from the probe
        dofs = np.empty((count, 12), dtype=np.int64)
        vectors = np.empty((count, 12))
        rows = np.empty(144 * count, dtype=np.int64)
        cols = np.empty(144 * count, dtype=np.int64)
        values = np.empty(144 * count)
        spring_terms(
            tet_nodes,
            weights,
            contacts.normal,
            magnitude,
            self.stiffness,
            forces,
            dofs,
            vectors,
            rows,
            cols,
            values,
        )
        evaluation = TermEvaluation(
            energy_j=0.5 * float(np.sum(magnitude**2)) / self.stiffness,
            forces=forces,
            stiffness_rows=rows,
            stiffness_cols=cols,
            stiffness_values=values,
            # The same stiffness as one term k_s v v^T per active point, v = (w_a n)_a over
            # its tet's 12 dofs: a kept factorisation is corrected for points entering and
            # leaving contact in low rank (tissue.sim.solvers.RankOneSince).
            rank_one=RankOneTerms(
                keys=contacts.points[active],
                dofs=dofs,
                vectors=vectors,
                scales=np.full(count, self.stiffness),
            ),
        )
        self._cache_key = positions.copy()
        self._cache_pose = pose
        self._cache = evaluation
        self.last_contacts = contacts
        self.last_magnitudes = magnitude
        return evaluation


@register_contact
class PenaltyContact(FEContactModel):
    """Penalty contact between the rigid probe and the FE tissue's collision surface."""

    name = "penalty"
    label = "Penalty"
    colour = "tab:orange"
    #: Penalty leaves about 2 % of the indentation with its default k_s (0.6 mm at 30 mm).
    penetration_bound_m = 0.002

    params_type = PenaltyParams
    params: PenaltyParams

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        stiffness = self.params.stiffness_n_per_m
        if stiffness is None:
            stiffness = default_stiffness_n_per_m(self.surface, self.mesh, self.sim.materials)
        self.stiffness_n_per_m = float(stiffness)
        self.term = PenaltyTerm(
            self.surface, self.probe, self.stiffness_n_per_m, self.params.contact_distance_m
        )
        self.augmentations = 0

    def _advance(
        self, h: float
    ) -> tuple[StepStatus, NDArray[np.float64], NDArray[np.float64], dict[str, Any]]:
        augmented = self.params.augmented
        if augmented is None:
            augmented = profile_choices(self.sim.config.mode).augmented_penalty
        result = self._augmented_step(h) if augmented else self.sim.step((self.term,), h)
        # Forces at the state the step ended in: the springs' final pull on the probe.
        self.term.evaluate(self.sim.positions)
        contacts, magnitudes = self.term.last_contacts, self.term.last_magnitudes
        points, forces = self.surface_points_on_probe(contacts, magnitudes)
        diagnostics = _diagnostics(result, self.term.stiffness)
        diagnostics["augmentations"] = self.augmentations if augmented else 0
        return result.status, points, forces, diagnostics

    def sleep_reach_m(self) -> float:
        """The springs' reach [m]: the contact distance, and beyond it the farthest a
        point's augmented force offset pushes (offset / k_s), as :meth:`PenaltyTerm.evaluate`
        detects them."""
        term = self.term
        return term.distance + float(term.offsets.max(initial=0.0)) / term.stiffness

    def _augmented_step(self, dt: float) -> Any:
        """Solve a step of ``dt`` [s], re-solving from the same start with augmented offsets
        while a point is deeper than the tolerance (see the module docstring)."""
        result, self.augmentations = augmented_step(
            self.sim,
            self.term,
            dt,
            self.params.penetration_tolerance_m,
            self.params.max_augmentations,
            self.params.force_tolerance,
        )
        return result

    def _reset_tissue(self) -> None:
        super()._reset_tissue()
        self.term.release()

    def contact_constraints(self) -> ContactConstraints:
        """The springs acting at the end of the last step, each of compliance 1 / k (k as
        the augmentation left it, see the module docstring)."""
        self.term.evaluate(self.sim.positions)  # the springs at the present state
        contacts = self.term.last_contacts
        active = self.term.last_magnitudes > 0.0
        return self._constraint_rows(
            self.surface,
            contacts.points[active],
            contacts.normal[active],
            1.0 / self.term.stiffness,
        )

    def _snapshot_contact(self) -> dict[str, Any]:
        return self.term.state()

    def _restore_contact(self, snapshot: dict[str, Any]) -> None:
        self.term.set_state(snapshot)


def augmented_step(
    sim: TissueSimulator,
    term: PenaltyTerm,
    dt: float,
    tolerance_m: float,
    max_augmentations: int,
    force_tolerance: float = FORCE_TOLERANCE,
) -> tuple[StepResult, int]:
    """One step of ``dt`` [s] of ``sim`` (its prescribed set and node frames included) with
    the springs of ``term``, committed: the offsets predicted
    (:meth:`PenaltyTerm.predict_offsets`), :func:`augmented_solve`,
    :meth:`TissueSimulator.commit`, the step's forces recorded for the next prediction.
    Returns the committed step and the augmentations made."""
    started = time.perf_counter()
    term.predict_offsets(OFFSET_REACH_SHARE * tolerance_m)
    outcome, rounds = augmented_solve(
        sim, term, dt, tolerance_m, max_augmentations, force_tolerance
    )
    result = sim.commit(outcome, dt, started)
    term.record_forces(sim.positions)
    return result, rounds


def augmented_solve(
    sim: TissueSimulator,
    term: PenaltyTerm,
    dt: float,
    tolerance_m: float,
    max_augmentations: int,
    force_tolerance: float = FORCE_TOLERANCE,
) -> tuple[StepOutcome, int]:
    """One step of ``dt`` [s] of ``sim`` (its prescribed set and node frames included) with
    the springs of ``term``, re-solved from the same start with augmented offsets while a
    point lies deeper than ``tolerance_m`` [m] or an augmentation would move the nodal
    contact forces by more than ``force_tolerance`` of them, at most ``max_augmentations``
    times; each augmentation raises k so that no offset reaches beyond
    ``OFFSET_REACH_SHARE`` x ``tolerance_m`` (see the module docstring). Not committed:
    returns the last round's outcome, carrying the Newton and linear iterations of every
    round (:func:`with_work_of`), and the augmentations made."""
    dofs, targets = sim.constraints()
    x0, v0 = sim.positions.copy(), sim.velocities.copy()
    frames = sim.boundary_state()["frames"]
    # The first round continues the last step: Newton from x + h v + h^2 a, as the
    # integrator's own steps start (x0 and v0 are copies of the state it ended in). A
    # re-solve starts from where the round before ended (unless that round failed): with k
    # raised for a tenth of the tolerance the rounds' offsets move the solution little.
    # With k raised for the whole tolerance, re-solves started there let a press of the
    # 1,363-tet phantom's lesion 6 (tests/tissue/test_force_growth.py) slip at 15.5 mm
    # instead of 16, its force falling 11 % (docs/design-decisions.md).
    spent: StepOutcome | None = None
    for round_index in range(max_augmentations + 1):
        outcome = sim.integrator.step(x0, v0, dt, dofs, targets, (term,), frames)
        if spent is not None:
            outcome = with_work_of(outcome, spent)
        spent = outcome
        if outcome.status in (StepStatus.DIVERGED, StepStatus.SOLVER_FAILED):
            break
        if round_index == max_augmentations:
            break
        change = term.force_change(outcome.positions)
        if term.penetration_m(outcome.positions) <= tolerance_m and change <= force_tolerance:
            break
        term.augment(outcome.positions, OFFSET_REACH_SHARE * tolerance_m)
        sim.integrator.forget_last_step()
        if outcome.status is StepStatus.OK:
            sim.integrator.start_next_step_near(outcome.positions)
    return outcome, round_index


def default_stiffness_n_per_m(
    surface: SurfacePoints, mesh: TetMesh, materials: TissueMaterials
) -> float:
    """The default k_s [N/m]: ``DEFAULT_STIFFNESS_RATIO`` x E_tissue x the surface's mean
    edge length at rest."""
    return DEFAULT_STIFFNESS_RATIO * materials.tissue.young_pa * _mean_edge(surface, mesh.nodes)


def _mean_edge(surface: SurfacePoints, node_positions: NDArray[np.float64]) -> float:
    vertices = surface.positions(node_positions)
    triangles = surface.triangles
    edges = vertices[triangles] - vertices[np.roll(triangles, 1, axis=1)]
    return float(np.mean(np.linalg.norm(edges, axis=2)))


def _diagnostics(result: Any, stiffness: float) -> dict[str, Any]:
    return {
        "stiffness_n_per_m": stiffness,
        "newton_iterations": result.newton_iterations,
        "linear_iterations": result.linear_iterations,
        "linear_residual": result.linear_residual,
        "subdivisions": result.subdivisions,
        "min_volume_ratio": result.min_volume_ratio,
        "tissue_ms": result.compute_ms,
    }


@numba.njit(cache=True)
def spring_terms(
    tet_nodes, weights, normals, magnitudes, stiffness, forces, dofs, vectors, rows, cols, values
):  # pragma: no cover - compiled
    """The springs' nodal forces, stiffness triplets and rank-one terms (a compiled loop: in
    numpy, broadcasting a few points' blocks cost ~45 us a call, called twice a step).

    For every point p of a tet with nodes t_a (``tet_nodes`` (k, 4)), barycentric weights
    w_a, probe normal n and spring force m = ``magnitudes[p]`` [N]: adds w_a m n to
    ``forces`` (node_count, 3) at t_a. For each point with m > 0 (the r-th such, in point
    order): its 12 dofs 3 t_a + i and v = (w_a n_i) as row r of ``dofs`` and ``vectors``, and
    the 144 entries k_s w_a w_b n_i n_j of k_s v v^T at (3 t_a + i, 3 t_b + j), in (a, b, i,
    j) order, from 144 r on in ``rows``, ``cols`` and ``values``.
    """
    row = 0
    for p in range(tet_nodes.shape[0]):
        for a in range(4):
            node = tet_nodes[p, a]
            w = weights[p, a]
            for i in range(3):
                forces[node, i] += w * (magnitudes[p] * normals[p, i])
        if magnitudes[p] <= 0.0:
            continue
        for a in range(4):
            for i in range(3):
                dofs[row, 3 * a + i] = 3 * tet_nodes[p, a] + i
                vectors[row, 3 * a + i] = weights[p, a] * normals[p, i]
        k = 144 * row
        for a in range(4):
            for b in range(4):
                scale = stiffness * weights[p, a] * weights[p, b]
                for i in range(3):
                    for j in range(3):
                        rows[k] = 3 * tet_nodes[p, a] + i
                        cols[k] = 3 * tet_nodes[p, b] + j
                        values[k] = scale * normals[p, i] * normals[p, j]
                        k += 1
        row += 1
