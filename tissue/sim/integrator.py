"""Implicit time integration of the tissue: the paper's linearised backward Euler and Newton.

Modes:

* ``paper``: backward Euler exactly as Tagliabue et al. (2020), eq. (5), after Baraff &
  Witkin (1998): one linearised solve per step,

      (M (1 + h r_M) + (h r_K + h^2) K) dv = h (f - r_M M v - r_K K v) - h^2 K v,

  with K = d2E/dx2 the stiffness (positive), f the internal plus external force and
  Rayleigh damping (r_M, r_K). Then v += dv and x += h v. No iteration: large steps or an
  unconverged linear solve leave residual forces, as in the paper's framework.
* ``robust``: Newton's method on the step's incremental potential (Kane et al. 2000;
  Martin et al. 2011)

      E(y) = |y - x - h v|^2_M / (2 h^2) + Psi(y) - f_ext . y + |y - x|^2_D / (2 h),
      D = r_M M + r_K K(x),

  iterated to a relative residual tolerance with a backtracking (Armijo) line search,
  element tangents projected to positive semi-definite far from the solution of a
  quasi-static step (so every Newton direction descends; a dynamic step's Hessian holds M /
  h^2 + (r_K / h) K_rest beside them, and projects only where the exact tangent fails to give
  a descent direction), and a failed step retried as two half steps, recursively (automatic
  subdivision, reported).

``quasi_static=True`` drops inertia and damping: each step seeks static equilibrium with the
constraints of that step (one linearised solve in ``paper`` mode, Newton in ``robust``).

Constraints are Dirichlet conditions on degrees of freedom (3·node + axis): the fixed set
(always) and prescribed target coordinates for the step (the probe's nodes in prescribed-
displacement contact; a frictionless platen prescribes one axis only). Reaction forces at
constrained dofs are returned; the force the tissue exerts on whatever holds them is their
negative.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numba
import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from tissue.choices import Choice
from tissue.errors import ConfigError
from tissue.fem.elasticity import Elasticity, ElasticState
from tissue.sim.frames import NodeFrames, find_column
from tissue.sim.solvers import (
    ConstrainedSystem,
    LinearSolver,
    LinearSolverConfig,
    LinearSolverKind,
    RankOneTerms,
    SolveReport,
    SymmetricProduct,
    _dot,
    _free_square_norm,
)
from tissue.status import SEVERITY, StepStatus, worst
from tissue.threads import parallel_kernel

# A node further than this many mesh extents from its rest position means the step blew up.
_BLOW_UP_EXTENTS = 2.0
# Armijo sufficient-decrease constant and the smallest line-search step tried.
_ARMIJO_C = 1e-4
# Floor of the force scale a Newton residual is relative to, as a fraction of
# (mu + lambda)_max x extent^2: a tissue at rest with nothing acting has forces of round-off
# size only (1e-14 of that unit on the published mesh), which must read as converged.
RESIDUAL_SCALE_FLOOR = 1e-10
_MIN_STEP_FRACTION = 2.0**-12
# Extrapolation: a full Newton step along which the energy still falls at more than this
# fraction of its initial rate (the directional derivative at the step's end over the one
# at its start) was too short, as where Newton only converges linearly (the penalty
# springs' tangent freezes the contact normal; see tissue/contact/penalty.py). The secant
# step, where the directional derivative interpolates to zero, is tried then, up to
# _MAX_EXTRAPOLATION full steps, and kept if its energy is lower. Measured (robust penalty,
# study cells, one run each): 4,126 tets, lesion 3, Newton iterations 578 -> 555 and the
# most in a step 19 -> 8; 2,539 tets, lesion 1, 851 -> 834, 23 -> 17 and one split step ->
# none; final forces within 2e-5 N. The 176,506-tet cell, lesion 8 (partly loaded
# machine): 886 -> 730 s of steps, 100 %, steps 639-645 at 29-30 mm 206 -> 145 s, one step
# split (643, 99 s, five augmentation rounds) where four were. Cells where it never acts
# are bit-identical.
_EXTRAPOLATE_BELOW = 0.5
_MAX_EXTRAPOLATION = 4.0
# Relative Newton residual below which the exact (unprojected) tangent is tried first in
# quasi-static steps and in dynamic ones without stiffness damping.
PROJECTION_SWITCH = 1e-1
# A Newton direction is solved no more accurately than needed to bring the residual to this
# fraction of the Newton tolerance: the new residual is, to first order, the linear one
# (176k-tet phantom, steady compression: relative linear residual 6.3e-2 x ||rhs|| / force
# scale 5.7e-4 = 3.6e-5 predicted, 3.6e-5 measured).
LINEAR_SHARE_OF_TOLERANCE = 0.5


class IntegrationMode(Choice):
    """How each implicit step is solved."""

    PAPER = "paper"
    ROBUST = "robust"

    @classmethod
    def noun(cls) -> str:
        return "integration mode"


@dataclass(frozen=True)
class IntegratorConfig:
    """Settings of the implicit integrator.

    Attributes:
        mode: ``paper`` (one linearised solve) or ``robust`` (Newton, line search).
        quasi_static: seek static equilibrium each step (no inertia, no damping).
        rayleigh_mass: r_M [1/s], mass-proportional damping.
        rayleigh_stiffness: r_K [s], stiffness-proportional damping.
        linear_solver: the linear solver; None picks the mode's default (``paper``: CG capped
            at 25 iterations as the paper; ``robust``: factorisation reused as preconditioner).
        project_psd: project element tangents to PSD; None means True in ``robust`` and False
            in ``paper`` (as the paper's framework).
        newton_tolerance: relative residual at which Newton stops (residual norm over the
            norm of the forces acting).
        newton_max_iterations: Newton iterations before a step is declared not converged.
        max_subdivisions: how many times a failed robust step may be halved (0 disables).
    """

    mode: IntegrationMode | str = IntegrationMode.PAPER
    quasi_static: bool = False
    rayleigh_mass: float = 0.1
    rayleigh_stiffness: float = 0.1
    linear_solver: LinearSolverConfig | None = None
    project_psd: bool | None = None
    newton_tolerance: float = 1e-4
    newton_max_iterations: int = 30
    max_subdivisions: int = 4

    def __post_init__(self) -> None:
        object.__setattr__(self, "mode", IntegrationMode.parse(self.mode))
        if self.rayleigh_mass < 0 or self.rayleigh_stiffness < 0:
            raise ConfigError(
                "Rayleigh damping factors must be >= 0; got rayleigh_mass="
                f"{self.rayleigh_mass}, rayleigh_stiffness={self.rayleigh_stiffness}"
            )
        if not 0 < self.newton_tolerance < 1:
            raise ConfigError(f"newton_tolerance must lie in (0, 1); got {self.newton_tolerance}")
        if self.newton_max_iterations < 1:
            raise ConfigError(
                f"newton_max_iterations must be >= 1; got {self.newton_max_iterations}"
            )
        if self.max_subdivisions < 0:
            raise ConfigError(f"max_subdivisions must be >= 0; got {self.max_subdivisions}")
        if self.linear_solver is None:
            default = (
                LinearSolverConfig(kind=LinearSolverKind.CG)
                if self.mode is IntegrationMode.PAPER
                else LinearSolverConfig(kind=LinearSolverKind.REUSE)
            )
            object.__setattr__(self, "linear_solver", default)
        if self.project_psd is None:
            object.__setattr__(self, "project_psd", self.mode is IntegrationMode.ROBUST)


@dataclass(frozen=True)
class TermEvaluation:
    """What an extra energy term (penalty contact, a spring) adds to a step.

    Attributes:
        energy_j: the term's potential energy [J].
        forces: force on the nodes, -d(energy)/dx [N], shape (node_count, 3).
        stiffness_rows, stiffness_cols, stiffness_values: d2(energy)/dx2 as COO triplets over
            dofs (3·node + axis); entries must couple nodes of a common tet so they fall inside
            the elastic sparsity pattern. Empty arrays for none.
        rank_one: the same stiffness as rank-one terms (one per contact point), or None;
            lets ``reuse`` correct a kept factorisation as terms come and go.
    """

    energy_j: float
    forces: NDArray[np.float64]
    stiffness_rows: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    stiffness_cols: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    stiffness_values: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    rank_one: RankOneTerms | None = None


class EnergyTerm(Protocol):
    """An extra conservative term added to the tissue's potential during a step."""

    def evaluate(self, positions: NDArray[np.float64]) -> TermEvaluation: ...


@dataclass
class StepOutcome:
    """The result of one integrator step.

    Attributes:
        status: how the step ended.
        positions: node positions after the step [m], (node_count, 3) (the start state when
            the step diverged).
        velocities: node velocities after the step [m/s], (node_count, 3).
        reaction_forces: force the constraints apply to the tissue at each node [N],
            (node_count, 3), zero at free nodes.
        elastic_energy_j: strain energy after the step [J].
        newton_iterations: Newton iterations over all substeps (1 per step in paper mode).
        linear_iterations: CG iterations over all solves.
        linear_residual: the largest relative residual left by a linear solve.
        newton_residual: relative Newton residual at the end (0 in paper mode: not measured).
        subdivisions: how many extra substeps automatic subdivision added.
        min_volume_ratio: smallest det F over the tets after the step.
        factorizations: numerical factorisations computed.
    """

    status: StepStatus
    positions: NDArray[np.float64]
    velocities: NDArray[np.float64]
    reaction_forces: NDArray[np.float64]
    elastic_energy_j: float
    newton_iterations: int = 0
    linear_iterations: int = 0
    linear_residual: float = 0.0
    newton_residual: float = 0.0
    subdivisions: int = 0
    min_volume_ratio: float = 1.0
    factorizations: int = 0
    seconds: float = 0.0
    newton_residuals: list[float] = field(default_factory=list)


@dataclass
class PaperSystem:
    """The linear system of one paper-mode step, with what is needed to finish the step.

    Attributes:
        system: the constrained system (matrix eliminated in place).
        constrained_rows: the constrained rows before elimination, as CSR arrays
            (row pointer, column indices, values), one row per constrained dof (for reactions).
        rhs: the right-hand side before elimination.
        dofs: the constrained dofs.
        frames: node frames the system is written in (None: world coordinates).
    """

    system: ConstrainedSystem
    constrained_rows: tuple[NDArray[np.int64], NDArray[np.int32], NDArray[np.float64]]
    rhs: NDArray[np.float64]
    dofs: NDArray[np.int64]
    frames: NodeFrames | None = None


class IncrementalPotential:
    """The incremental potential of one robust step and its derivatives.

    E(y) = |y - x - h v|^2_M / (2 h^2) + Psi(y) + sum(terms) - f_ext . y + |y - x|^2_D / (2 h),
    D = r_M M + r_K K_rest (the rest stiffness: constant, PSD, no assembly per step).
    Quasi-static: E(y) = Psi(y) + sum(terms) - f_ext . y.

    With node ``frames`` the unknown is z = Q y (see :mod:`tissue.sim.frames`): ``evaluate``,
    ``hessian_system``, ``start``, ``dofs`` and ``targets`` are all in those coordinates.
    """

    def __init__(
        self,
        integrator: ImplicitIntegrator,
        x0,
        v0,
        h,
        dofs,
        targets,
        terms,
        frames: NodeFrames | None = None,
        quasi_static: bool | None = None,
    ) -> None:
        cfg = integrator.config
        self.frames = frames
        self.integrator = integrator
        self.h = h
        self.x0_flat = x0.reshape(-1)
        self.inertia_target = self.x0_flat + h * v0.reshape(-1)
        self.dofs = dofs
        self.targets = targets
        self.terms = terms
        self.constrained = integrator._dof_mask(dofs)
        # None: the integrator's setting; True: the static potential whatever it says.
        self.quasi = cfg.quasi_static if quasi_static is None else quasi_static
        self.mass = integrator.mass_dof
        self.external = (
            integrator.external_force.reshape(-1) if integrator.external_force is not None else None
        )
        damped = not self.quasi and cfg.rayleigh_stiffness > 0
        self.damping = integrator._rest_stiffness() if damped else None
        self._damping_product = integrator._rest_stiffness_product() if damped else None
        # D_K (y - x), reused by every evaluation (zeros without stiffness damping).
        self.damping_product = np.zeros_like(self.x0_flat)
        # (y, elastic energy [J], smallest det F) of the last evaluation, for the step's end.
        self.last_elastic: tuple[NDArray[np.float64], float, float] | None = None
        # (z, a copy of it, the elastic state with its exact tangent) of an evaluation that
        # assembled the tangent for the Hessian that follows it (``evaluate(with_tangent)``).
        self._tangent_state: tuple[NDArray[np.float64], NDArray[np.float64], ElasticState] | None
        self._tangent_state = None

    def start(self) -> NDArray[np.float64]:
        """The first iterate: the inertial prediction x + h v (x when quasi-static)."""
        return self.local(self.x0_flat if self.quasi else self.inertia_target)

    def local(self, y_flat: NDArray[np.float64]) -> NDArray[np.float64]:
        """World positions [m] (3N,) in the potential's coordinates (a new array)."""
        return y_flat.copy() if self.frames is None else self.frames.to_local(y_flat)

    def world(self, z_flat: NDArray[np.float64]) -> NDArray[np.float64]:
        """The potential's coordinates [m] (3N,) in world ones (``z_flat`` itself if framed
        nodes are none)."""
        return z_flat if self.frames is None else self.frames.to_world(z_flat)

    def evaluate(
        self, z_flat: NDArray[np.float64], with_tangent: bool = False
    ) -> tuple[float, NDArray[np.float64], float]:
        """(energy [J], gradient [N] (3N,), force scale [N]) at z [m] (3N,).

        ``with_tangent``: also assemble the exact (unprojected) elastic tangent there, kept
        for the next :meth:`hessian_system` at this z. For a start point whose Hessian is
        surely wanted next (a dynamic step's first iterate): one element pass instead of a
        force pass and a tangent pass (0.20 ms of 0.72 at 4,126 tets, 1.5 of 5.1 at 26,220).
        """
        cfg, h = self.integrator.config, self.h
        y_flat = self.world(z_flat)
        y3 = y_flat.reshape(-1, 3)
        state = self.integrator.elasticity.evaluate(y3, tangent=with_tangent)
        self._tangent_state = (z_flat, z_flat.copy(), state) if with_tangent else None
        self.last_elastic = (z_flat, state.energy_j, state.min_volume_ratio)
        energy = state.energy_j
        internal = state.forces.reshape(-1)
        for term in self.terms:
            evaluation = term.evaluate(y3)
            energy += evaluation.energy_j
            internal = internal + evaluation.forces.reshape(-1)
        gradient = -internal
        scale = math.sqrt(_dot(internal, internal))
        if self.external is not None:
            energy -= _dot(self.external, y_flat)
            gradient -= self.external
            scale = max(scale, math.sqrt(_dot(self.external, self.external)))
        if not self.quasi:
            damped = self.damping_product
            if self._damping_product is not None:
                self._damping_product(y_flat - self.x0_flat, damped)
            inertia_energy, inertial_square = _add_inertia_and_damping(
                y_flat,
                self.inertia_target,
                self.x0_flat,
                self.mass,
                h,
                cfg.rayleigh_mass,
                cfg.rayleigh_stiffness if self.damping is not None else 0.0,
                damped,
                gradient,
            )
            energy += inertia_energy
            scale = max(scale, math.sqrt(inertial_square))
        if self.frames is not None:
            gradient = self.frames.to_local(gradient)
        return energy, gradient, scale

    def hessian_system(
        self, z_flat: NDArray[np.float64], rhs: NDArray[np.float64], project: bool
    ) -> ConstrainedSystem:
        """Hessian at z with constrained increments reaching the targets, right-hand side rhs."""
        integrator, cfg, h, m = self.integrator, self.integrator.config, self.h, self.mass
        y3 = self.world(z_flat).reshape(-1, 3)
        kept, self._tangent_state = self._tangent_state, None  # its matrix is used once
        if (
            kept is not None
            and not project
            and kept[0] is z_flat
            and np.array_equal(kept[1], z_flat)
        ):
            state = kept[2]
        else:
            state = integrator.elasticity.evaluate(y3, tangent=True, project_psd=project)
        # A fresh matrix (every evaluation fills a new data array): modified in place.
        matrix = integrator._stiffness_with_terms(state, y3, self.terms)
        if not self.quasi:
            damping = self.damping
            _scale_add_diagonal(
                matrix.data,
                1.0,
                damping.data if damping is not None else matrix.data,
                cfg.rayleigh_stiffness / h if damping is not None else 0.0,
                integrator._diagonal(matrix),
                m / (h * h) + cfg.rayleigh_mass * m / h,
            )
        if self.frames is not None:
            self.frames.rotate_matrix(matrix)
        values = np.zeros_like(z_flat)
        values[self.dofs] = self.targets - z_flat[self.dofs]
        return ConstrainedSystem(
            matrix,
            rhs,
            self.constrained,
            values,
            # Rank-one terms are world-coordinate vectors: with frames the kept factorisation
            # is not corrected for them (CG makes up the difference).
            _rank_one_terms(self.terms, y3) if self.frames is None else None,
            frames=self.frames,
        )

    def newton_direction(self, y_flat, gradient, project, tolerance, enough=0.0, chord=None):
        """Newton direction [m] (3N,), the solve report and the system solved.

        ``tolerance`` is the relative residual asked of the linear solve; ``enough`` [N], if
        positive, an absolute residual over the free dofs at which it may stop earlier.
        ``chord``: a system of an earlier iterate of this step whose matrix is taken instead
        of the Hessian at ``y_flat`` (a chord step; the constrained dofs must be on their
        targets already).
        """
        if chord is not None:
            system = chord.with_rhs(-gradient)
        else:
            system = self.hessian_system(y_flat, -gradient, project)
        if enough > 0.0:
            tolerance = floored_tolerance(tolerance, enough, system.free_rhs_norm())
        step, report = self.integrator.solver.solve(system, tolerance=tolerance)
        return step, report, system


# A Newton matrix handed from step to step (:class:`ChordHandOver`) stops being handed on, after
# a chord that needed more than one iteration, for 1, 2, 4, ... steps, up to this many.
CHORD_BACKOFF_MAX_STEPS = 16


class ChordHandOver:
    """Modified Newton across dynamic steps: the matrix of a step that converged in one full,
    exact (unprojected) iteration is handed to the next step, whose first iteration takes
    it as a chord and assembles no tangent. A handed matrix whose step converges at once is
    handed on again, so one matrix may serve many steps (as CVODE keeps its Jacobian while
    Newton converges); every step still iterates to the Newton tolerance, and a chord that
    falls short costs an iteration, not accuracy.

    Where it pays: the kept factorisation F is refreshed from the system being solved (the
    ski-rental rule of ``reuse``), so under a handed matrix F soon factorises that very
    matrix: CG then converges in one iteration, and LM's W~ = H F^-1 H^T is the chord's exact
    compliance (one response round instead of two). Where the contact set changes every
    step, handed chords need a second iteration more often: after such a chord the hand-over
    pauses for 1, 2, 4, ... steps (:data:`CHORD_BACKOFF_MAX_STEPS` at most), and each chord
    that converges at once halves the pause again.

    LM's robust steps use it (:mod:`tissue.contact.lagrange`). This integrator's own Newton
    does not: there a chord needs the constrained dofs on their targets from the first
    iterate, and prescribed displacement moves its targets every step, while penalty's
    augmented rounds pass copies of the state, which never continue a step (nor start from
    the extrapolation: letting them made its 26,220-tet press slower, 1,354 -> 1,667 ms per
    simulated second, 1,749 with the hand-over too, and gained nothing at 4,126 tets).
    """

    def __init__(self) -> None:
        self._handed: tuple[ConstrainedSystem, float] | None = None
        self._backoff = 0
        self._pause = 0

    def reset(self) -> None:
        """Forget the handed matrix and the back-off (a new or restored state)."""
        self._handed = None
        self._backoff = 0
        self._pause = 0

    def take(self, h: float, constrained: NDArray[np.bool_]) -> ConstrainedSystem | None:
        """The matrix (as a system) handed to a step of ``h`` [s] with ``constrained`` dofs
        (mask (3N,)), or None if none was or it was for another time step, constraint set or
        node frames. Taken once: a step that does not take it drops it."""
        handed, self._handed = self._handed, None
        if handed is None:
            return None
        system, handed_h = handed
        if handed_h != h or system.frames is not None:
            return None
        if not np.array_equal(system.constrained, constrained):
            return None
        return system

    def record(
        self,
        system: ConstrainedSystem,
        h: float,
        took_handed: bool,
        iterations: int,
        full_exact: bool,
    ) -> None:
        """After a converged dynamic step of ``h`` [s] whose last iteration solved ``system``:
        hand its matrix to the next step if the step converged in one iteration that was
        ``full_exact`` (unprojected, its full step taken), unless the hand-over is paused.
        ``took_handed``: this step's first iteration took a handed matrix."""
        if took_handed:
            if iterations > 1:
                self._backoff = min(max(1, 2 * self._backoff), CHORD_BACKOFF_MAX_STEPS)
                self._pause = self._backoff
                return
            self._backoff //= 2
        if self._pause > 0:
            self._pause -= 1
            return
        if iterations == 1 and full_exact:
            self._handed = (system, h)


def floored_tolerance(tolerance: float, enough: float, rhs_norm: float) -> float:
    """The relative residual to ask of a linear solve: ``tolerance``, loosened (to at most 0.5)
    so that the solve may stop once its absolute residual over the free dofs reaches
    ``enough`` [N], for a right-hand side of norm ``rhs_norm`` [N] (see
    :data:`LINEAR_SHARE_OF_TOLERANCE`)."""
    if enough > 0.0 and rhs_norm > 0.0:
        return max(tolerance, min(enough / rhs_norm, 0.5))
    return tolerance


def _rank_one_terms(terms, positions: NDArray[np.float64]) -> RankOneTerms | None:
    """The terms' stiffness as rank-one terms at ``positions`` (evaluations are cached), or
    None unless exactly one term gives them (keys must be unique; one contact term is all a
    step has)."""
    given = [term.evaluate(positions).rank_one for term in terms]
    found = [rank_one for rank_one in given if rank_one is not None]
    return found[0] if len(found) == 1 else None


def extrapolated_positions(
    x: NDArray[np.float64],
    v: NDArray[np.float64],
    h: float,
    previous_v: NDArray[np.float64],
    last_h: float,
) -> NDArray[np.float64]:
    """x + h v + h^2 (v - previous_v) / last_h [m], flat (3N,): where a step of ``h`` [s]
    from (x [m], v [m/s]) lands if it keeps the acceleration of the last step (``last_h``
    [s], which started at ``previous_v``). Newton's first iterate when continuing a step."""
    return (x + h * v + (h * h / last_h) * (v - previous_v)).reshape(-1)


@numba.njit(cache=True)
def _add_inertia_and_damping(
    y, inertia_target, x0, mass, h, rayleigh_mass, rayleigh_stiffness, damped, gradient
):  # pragma: no cover - compiled
    """Add inertia and Rayleigh damping to ``gradient`` (in place).

    With d = y - (x + h v), dx = y - x: inertial force m d / h^2 and damping force
    (r_M m dx + r_K D_K dx) / h, ``damped`` = D_K dx. Returns (their energy
    d.m d / (2 h^2) + dx.damping / 2 [J], ||inertial force||^2 [N^2]).
    """
    energy = 0.0
    inertial_square = 0.0
    for i in range(y.shape[0]):
        d = y[i] - inertia_target[i]
        inertial = mass[i] * d / (h * h)
        dx = y[i] - x0[i]
        damping = rayleigh_mass * mass[i] * dx / h + rayleigh_stiffness * damped[i] / h
        energy += 0.5 * (d * inertial + dx * damping)
        gradient[i] += inertial + damping
        inertial_square += inertial * inertial
    return energy, inertial_square


@parallel_kernel
def _scale_add_diagonal(
    data, scale, other, other_scale, diagonal, diagonal_add
):  # pragma: no cover - compiled
    """data = scale data + other_scale other; then data[diagonal[i]] += diagonal_add[i]."""
    if scale != 1.0 or other_scale != 0.0:
        for k in numba.prange(data.shape[0]):
            data[k] = scale * data[k] + other_scale * other[k]
    for i in numba.prange(diagonal.shape[0]):
        data[diagonal[i]] += diagonal_add[i]


@numba.njit(cache=True)
def _row_products(indptr, indices, data, rows, x):  # pragma: no cover - compiled
    """(A x)[rows] for a CSR matrix."""
    out = np.zeros(rows.shape[0])
    for i in range(rows.shape[0]):
        row = rows[i]
        acc = 0.0
        for k in range(indptr[row], indptr[row + 1]):
            acc += data[k] * x[indices[k]]
        out[i] = acc
    return out


class ImplicitIntegrator:
    """Advances positions and velocities of a tet mesh by one implicit step.

    Args:
        elasticity: the hyperelastic model (mesh, materials, lumped mass, pattern).
        config: integrator settings.
        external_force: constant external nodal force (gravity) [N], (node_count, 3), or None.
    """

    def __init__(
        self,
        elasticity: Elasticity,
        config: IntegratorConfig,
        external_force: NDArray[np.float64] | None = None,
    ) -> None:
        self.elasticity = elasticity
        self.config = config
        self.solver = LinearSolver(config.linear_solver)
        mass = elasticity.lumped_mass
        self.mass_dof = np.repeat(mass, 3)
        self.external_force = external_force
        rest = elasticity.mesh.nodes
        self._rest = rest
        extent = float(np.max(np.ptp(rest, axis=0)))
        self._blow_up_m = _BLOW_UP_EXTENTS * extent
        mu, lam, _ = elasticity.materials.per_tet(elasticity.mesh.region)
        self._force_unit = float(np.max(mu + lam)) * extent * extent
        self._diagonal_positions: NDArray[np.int64] | None = None
        self._rest_stiffness_matrix: sp.csr_matrix | None = None
        self._rest_product: SymmetricProduct | None = None
        self._keys: NDArray[np.int64] | None = None
        # The last robust step that ended OK: (positions, velocities) it returned, the
        # velocities it started from and its step [s]; a step continuing from exactly those
        # arrays extrapolates its first Newton iterate from them.
        self._last_step: (
            tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], float] | None
        ) = None
        # A paper step ends by evaluating the elasticity at its new positions (the energy and
        # det F its outcome reports): with the tangent, that evaluation is the next step's, which
        # starts there. (positions [m] (nodes, 3), projected?, the state), taken once.
        self._end_state: tuple[NDArray[np.float64], bool, ElasticState] | None = None

    # ------------------------------------------------------------------ public

    def prepare(self, fixed_dofs: NDArray[np.int64] | None = None) -> None:
        """Do the first step's one-time work now, when the model is built: load the compiled
        element kernels (numba reads them from its cache on a process's first call: ~0.8 s
        here), the rest stiffness and its products robust mode's first step needs, the
        direct solver's library and, in robust mode, its analysis of the stiffness pattern
        with ``fixed_dofs`` (always constrained, (k,)) left out. Without it all of that
        landed in the first simulated step."""
        if self.config.mode is IntegrationMode.ROBUST:
            rest = self._rest_stiffness()
            self._rest_stiffness_product()
            if fixed_dofs is not None:
                self.solver.analyse(rest, self._dof_mask(fixed_dofs))
        else:  # kept for a first step from rest
            self._keep_end_state(self._rest)
        _ = self.solver.factorizer

    def drop_caches(self) -> None:
        """Forget what steps keep for the next (the kept factorisation and its corrections,
        the last step's record its Newton start is extrapolated from, a paper step's end
        evaluation): the next step then starts as in a freshly built integrator."""
        self.solver.forget()
        self._last_step = None
        self._end_state = None

    def step(
        self,
        positions: NDArray[np.float64],
        velocities: NDArray[np.float64],
        dt: float,
        constrained_dofs: NDArray[np.int64],
        targets: NDArray[np.float64],
        terms: Sequence[EnergyTerm] = (),
        frames: NodeFrames | None = None,
    ) -> StepOutcome:
        """Advance one step of ``dt`` [s].

        Args:
            positions: node positions at the start [m], (node_count, 3).
            velocities: node velocities at the start [m/s], (node_count, 3).
            dt: the step [s].
            constrained_dofs: dofs (3·node + axis) whose end coordinate is prescribed (fixed
                nodes included), (k,), unique.
            targets: their coordinates at the end of the step [m], (k,).
            terms: extra energy terms (penalty contact) active during the step.
            frames: node frames; the dofs of framed nodes (3·node + local axis) and their
                targets are then along the frames' axes (see :mod:`tissue.sim.frames`).
        """
        start = time.perf_counter()
        if self.config.mode is IntegrationMode.PAPER:
            outcome = self._paper_step(
                positions, velocities, dt, constrained_dofs, targets, terms, frames
            )
        else:
            outcome = self._robust_step(
                positions,
                velocities,
                dt,
                constrained_dofs,
                targets,
                terms,
                self.config.max_subdivisions,
                frames,
            )
            self._last_step = (
                (outcome.positions, outcome.velocities, velocities, dt)
                if outcome.status is StepStatus.OK and not self.config.quasi_static
                else None
            )
        outcome.seconds = time.perf_counter() - start
        return outcome

    # ------------------------------------------------------------------ paper

    def _paper_step(self, x, v, h, dofs, targets, terms, frames=None) -> StepOutcome:
        linear = self.paper_system(x, v, h, dofs, targets, terms, frames)
        try:
            solution, report = self.solver.solve(linear.system)
        except Exception:  # noqa: BLE001 - a failed factorisation is a step failure, not a crash
            return self._failed(x, v, StepStatus.SOLVER_FAILED)
        return self.paper_finish(x, v, h, linear, solution, report)

    def paper_system(self, x, v, h, dofs, targets, terms=(), frames=None) -> PaperSystem:
        """The linear system of the paper's eq. (5) (or K dx = f when quasi-static).

        The unknown is dv [m/s] (dx [m] when quasi-static), with constrained dofs set so that
        the step ends at ``targets``; with node ``frames``, all of it in their coordinates.
        """
        cfg = self.config
        if frames is not None and terms:
            raise ConfigError("node frames and energy terms cannot be combined in one step")
        state = self._take_end_state(x)
        if state is None:
            state = self.elasticity.evaluate(x, tangent=True, project_psd=bool(cfg.project_psd))
        # A fresh matrix (every evaluation fills a new data array): it becomes the system's,
        # modified in place.
        elastic = state.stiffness
        assert elastic is not None
        force = state.forces.reshape(-1) + self._term_forces(x, terms)
        if self.external_force is not None:
            force = force + self.external_force.reshape(-1)
        v_flat = np.ascontiguousarray(v, dtype=np.float64).reshape(-1)
        x_local = x.reshape(-1) if frames is None else frames.to_local(x.reshape(-1))
        v_local = v_flat if frames is None else frames.to_local(v_flat)
        values = np.zeros(x.size)
        if cfg.quasi_static:
            rhs = force
            values[dofs] = targets - x_local[dofs]
            matrix = self._stiffness_with_terms(state, x, terms)
        else:
            m = self.mass_dof
            # Rayleigh damping is the tissue's: it uses the elastic stiffness only, never the
            # contact springs (damping them would make the contact viscous).
            elastic_v = np.empty_like(v_flat)
            self.solver.product(elastic, v_flat, elastic_v)
            # The terms' stiffness is a few entries per contact point: (K + K_terms) v as
            # K v plus their product, not a second product with the whole matrix.
            stiffness_v = elastic_v
            if terms:
                stiffness_v = elastic_v + self._term_stiffness_product(x, terms, v_flat)
            damping_force = cfg.rayleigh_mass * m * v_flat + cfg.rayleigh_stiffness * elastic_v
            rhs = h * (force - damping_force) - h * h * stiffness_v
            values[dofs] = (targets - x_local[dofs]) / h - v_local[dofs]
            # (h^2 + h r_K) K + (1 + h r_M) M, then h^2 K_terms, in place (K v is taken).
            _scale_add_diagonal(
                elastic.data,
                h * h + h * cfg.rayleigh_stiffness,
                elastic.data,
                0.0,
                self._diagonal(elastic),
                (1.0 + h * cfg.rayleigh_mass) * m,
            )
            matrix = self._stiffness_with_terms(state, x, terms, scale=h * h)
        if frames is not None:
            frames.rotate_matrix(matrix)
            rhs = frames.to_local(rhs)
        # Reactions need the constrained rows as they were before elimination: keep only those
        # (a copy of the whole matrix costs tens of MB on the finest meshes).
        starts = matrix.indptr[dofs].astype(np.int64)
        counts = matrix.indptr[dofs + 1] - starts
        row_pointer = np.concatenate([[0], np.cumsum(counts)])
        positions = np.arange(row_pointer[-1]) + np.repeat(starts - row_pointer[:-1], counts)
        rows = (row_pointer, matrix.indices[positions], matrix.data[positions].copy())
        system = ConstrainedSystem(matrix, rhs, self._dof_mask(dofs), values, frames=frames)
        return PaperSystem(system, rows, rhs, dofs, frames)

    def paper_finish(self, x, v, h, linear: PaperSystem, solution, report) -> StepOutcome:
        """Update the state from a solution of :meth:`paper_system`; reactions included."""
        if not np.all(np.isfinite(solution)):
            return self._failed(x, v, StepStatus.SOLVER_FAILED)
        dofs = linear.dofs
        # Reactions: what the constraints add so that the constrained rows balance.
        pointer, indices, data = linear.constrained_rows
        rows = _row_products(pointer, indices, data, np.arange(dofs.size), solution)
        reaction = np.zeros(x.size)
        if linear.frames is not None:
            solution = linear.frames.to_world(solution)
        if self.config.quasi_static:
            new_x = x + solution.reshape(-1, 3)
            new_v = np.zeros_like(v)
            reaction[dofs] = rows - linear.rhs[dofs]
        else:
            new_v = v + solution.reshape(-1, 3)
            new_x = x + h * new_v
            reaction[dofs] = (rows - linear.rhs[dofs]) / h
        if linear.frames is not None:
            reaction = linear.frames.to_world(reaction)
        known = None
        if np.all(np.isfinite(new_x)):
            state = self._keep_end_state(new_x)
            known = (state.energy_j, state.min_volume_ratio)
        return self._finish(
            x,
            v,
            new_x,
            new_v,
            reaction,
            report,
            newton_iterations=1,
            newton_residual=0.0,
            known=known,
        )

    def _keep_end_state(self, positions: NDArray[np.float64]) -> ElasticState:
        """Evaluate the elasticity (with the paper step's tangent) at ``positions`` [m]
        (nodes, 3) and keep it for a paper step starting there: each step then evaluates
        once, not twice. The energy-only pass this saves took 0.03 / 0.10 / 0.55 ms at 623 /
        4,126 / 26,220 tets (median of 30, loaded machine), about 3 % of a paper step; the
        first step from rest also finds its evaluation done when the model is built (0.15 /
        0.79 / 9.7 ms for the tangent pass)."""
        project = bool(self.config.project_psd)
        state = self.elasticity.evaluate(positions, tangent=True, project_psd=project)
        self._end_state = (positions.copy(), project, state)
        return state

    def _take_end_state(self, positions: NDArray[np.float64]) -> ElasticState | None:
        """The kept state if it was evaluated at exactly ``positions`` with this step's
        projection; once only (the step modifies its matrix in place)."""
        kept, self._end_state = self._end_state, None
        if kept is None or kept[1] != bool(self.config.project_psd):
            return None
        if not np.array_equal(kept[0], positions):
            return None
        return kept[2]

    # ------------------------------------------------------------------ robust

    def _robust_step(
        self, x, v, h, dofs, targets, terms, subdivisions_left, frames=None
    ) -> StepOutcome:
        outcome = self._newton(x, v, h, dofs, targets, terms, frames)
        if not outcome.status.is_failure or subdivisions_left == 0:
            return outcome
        # Retry as two half steps, the prescribed targets interpolated linearly.
        start = (x.reshape(-1) if frames is None else frames.to_local(x.reshape(-1)))[dofs]
        middle = start + 0.5 * (targets - start)
        left = subdivisions_left - 1
        first = self._robust_step(x, v, 0.5 * h, dofs, middle, terms, left, frames)
        if first.status in (StepStatus.DIVERGED, StepStatus.SOLVER_FAILED):
            return outcome  # halving found nothing better: the undivided attempt stands
        second = self._robust_step(
            first.positions, first.velocities, 0.5 * h, dofs, targets, terms, left, frames
        )
        merged = _merge(first, second)
        merged.subdivisions += 1
        return merged if _rank(merged) <= _rank(outcome) else outcome

    def incremental_potential(
        self, x0, v0, h, dofs, targets, terms=(), frames=None
    ) -> IncrementalPotential:
        """The step's incremental potential (robust mode), for Newton and constrained solvers."""
        return IncrementalPotential(self, x0, v0, h, dofs, targets, terms, frames)

    def _newton(self, x0, v0, h, dofs, targets, terms, frames=None) -> StepOutcome:
        cfg = self.config
        quasi = cfg.quasi_static
        potential = self.incremental_potential(x0, v0, h, dofs, targets, terms, frames)
        free = ~potential.constrained
        evaluate, direction = potential.evaluate, potential.newton_direction

        # Start from the inertial prediction x + h v: for a probe moving steadily the free
        # nodes keep moving much as they did, which saves Newton iterations. Continuing the
        # last step, add its velocity change too (x + h v + h^2 a, a = dv / h_last): about
        # fifty times closer to the solution in a steady compression.
        y = potential.start()
        guess = self._extrapolated_start(x0, v0, h)
        if guess is not None:
            guess = potential.local(guess)
        # See the projection rule in the loop: dynamic steps with stiffness damping take the
        # exact tangent first, so the start's evaluation assembles it too.
        exact_first = not quasi and cfg.rayleigh_stiffness > 0.0
        evaluated = evaluate(guess, exact_first) if guess is not None else None
        if guess is not None and evaluated is not None and _finite(evaluated[0], evaluated[1]):
            y = guess
        else:
            evaluated = evaluate(y, exact_first)
        energy, gradient, scale = evaluated
        # Forces below this are round-off (at rest the residual is pure noise): a fraction of
        # what the stiffest material's moduli exert over the mesh's extent squared.
        scale_floor = RESIDUAL_SCALE_FLOOR * self._force_unit
        total_linear = 0
        worst_linear = 0.0
        factorizations = 0
        relative = math.inf
        history: list[float] = []
        converged = False
        iterations = 0
        # A dynamic step's second iteration keeps the first's matrix (a chord step), as
        # LM's robust steps do (see there): after a full step from the extrapolated start
        # the matrix has barely changed, and the residual stays the true gradient's, so a
        # chord that falls short costs an iteration, not accuracy. Only with a kept
        # factorisation (``reuse``), which solves it without refactorising. Measured on
        # ``bench peer``'s press (median / mean step): penalty at 4,126 tets 5.04 / 4.74 ->
        # 3.82 / 4.17 ms, at 26,220 tets 26.5 / 29.6 -> 20.8 / 26.2 ms; prescribed at 26,220
        # 26.6 / 28.8 -> 23.9 / 27.6 ms; forces within 6e-6 N. At a tight tolerance (1e-6)
        # a chord may cost an iteration where the start was poor (tests/test_integrator.py).
        chord_allowed = exact_first and self.solver.config.kind is LinearSolverKind.REUSE
        chord: ConstrainedSystem | None = None
        while True:
            mismatch = float(np.max(np.abs(targets - y[dofs]))) if dofs.size else 0.0
            relative = math.sqrt(_free_square_norm(gradient, ~free)) / max(scale, scale_floor)
            history.append(relative)
            if not (np.isfinite(relative) and math.isfinite(energy)):
                return self._failed(x0, v0, StepStatus.DIVERGED)
            converged = mismatch == 0.0 and relative <= cfg.newton_tolerance
            if converged or iterations == cfg.newton_max_iterations:
                break
            iterations += 1
            # Projected tangents make every direction descend but cost quadratic convergence
            # (the clamped Hessian is not the true one): far from the solution we project,
            # near it we use the exact tangent, falling back to projection whenever the exact
            # one does not give a descent direction.
            # A dynamic step with stiffness damping tries the exact tangent first even far
            # from its solution: its Hessian adds M / h^2 + (r_K / h) K_rest (5 K_rest at the
            # defaults) to the elastic one, which covers what the projection would clamp in
            # all but the most compressed tets, and the fallback below projects where it
            # does not. The projection costs 2.5 x a plain assembly (193 against 77 ms at
            # 176,506 tets); on `bench contact`'s apex press there, median step, penalty 809
            # -> 726 / 755 ms idle (949 -> 822 loaded), prescribed 503 -> 514 / 502 idle (it
            # projects in few steps), the same Newton and CG iterations and forces; the
            # published scene's lesion 1 path (penalty, 9,295 tets) ends within 7e-9 m of the
            # projected run.
            project = bool(cfg.project_psd) and relative > PROJECTION_SWITCH and not exact_first
            # Inexact Newton: solve only as accurately as the current residual deserves, and
            # never beyond what brings the residual well under the Newton tolerance.
            tolerance = min(1e-2, max(0.1 * relative, 1e-10))
            enough = LINEAR_SHARE_OF_TOLERANCE * cfg.newton_tolerance * max(scale, scale_floor)
            chord_step = chord is not None and mismatch == 0.0
            fell_back = False
            try:
                step, report, system = direction(
                    y, gradient, project, tolerance, enough, chord if chord_step else None
                )
                descends = mismatch > 0.0 or _dot(gradient, step) < 0.0
                if chord_step and not descends:  # the chord misled: the Hessian here
                    total_linear += report.iterations
                    factorizations += int(report.factorized)
                    chord_step = False
                    step, report, system = direction(y, gradient, project, tolerance, enough)
                    descends = mismatch > 0.0 or _dot(gradient, step) < 0.0
                if cfg.project_psd and not project and (report.indefinite or not descends):
                    total_linear += report.iterations
                    factorizations += int(report.factorized)
                    fell_back = True
                    step, report, system = direction(y, gradient, True, tolerance, enough)
            except Exception:  # noqa: BLE001 - report, don't crash
                return self._failed(x0, v0, StepStatus.SOLVER_FAILED)
            total_linear += report.iterations
            worst_linear = max(worst_linear, report.relative_residual)
            factorizations += int(report.factorized)
            if not np.all(np.isfinite(step)):
                return self._failed(x0, v0, StepStatus.SOLVER_FAILED)
            found = self._line_search(y, step, gradient, mismatch, evaluate, energy, dofs, targets)
            if found is None:
                return self._failed(x0, v0, StepStatus.DIVERGED)
            # The next iteration may keep this matrix if this one was assembled here (not a
            # chord, not the projected fallback) and its full step was taken as it is.
            chord = None
            if chord_allowed and not chord_step and not fell_back:
                full = y + step
                if mismatch > 0.0:
                    full[dofs] = targets
                chord = system if np.array_equal(found[0], full) else None
            y, energy, gradient, scale = found
        new_x = potential.world(y).reshape(-1, 3)
        new_v = np.zeros_like(v0) if quasi else (new_x - x0) / h
        # Reaction at constrained dofs: the constraint force balancing the residual there.
        reaction = np.zeros_like(y)
        reaction[dofs] = gradient[dofs]
        reaction = potential.world(reaction)
        report = SolveReport(total_linear, worst_linear, True, factorizations > 0)
        # The last evaluation was at y (the accepted point): its energy and det F serve.
        elastic = potential.last_elastic
        known = elastic[1:] if elastic is not None and elastic[0] is y else None
        outcome = self._finish(
            x0,
            v0,
            new_x,
            new_v,
            reaction,
            report,
            newton_iterations=iterations,
            newton_residual=relative,
            known=known,
        )
        outcome.factorizations = factorizations
        outcome.newton_residuals = history
        if not converged and outcome.status is StepStatus.OK:
            outcome.status = StepStatus.NOT_CONVERGED
        return outcome

    def _rest_stiffness(self) -> sp.csr_matrix:
        if self._rest_stiffness_matrix is None:
            state = self.elasticity.evaluate(self._rest, tangent=True)
            assert state.stiffness is not None
            self._rest_stiffness_matrix = state.stiffness
        return self._rest_stiffness_matrix

    def _rest_stiffness_product(self) -> SymmetricProduct:
        """Products with the rest stiffness (robust steps' damping, every evaluation)."""
        if self._rest_product is None:
            self._rest_product = SymmetricProduct(self._rest_stiffness())
        return self._rest_product

    def _line_search(self, y, step, gradient, mismatch, evaluate, energy, dofs=None, targets=None):
        """Backtracking Armijo search along ``step``, extrapolating a full step that fell short.

        Returns (y, energy, gradient, scale) at the accepted point, or None when no finite
        point was found. A full step puts the constrained dofs exactly on ``targets`` (y +
        (t - y) may miss t by an ulp, which would read as a constraint not yet met). A full
        step accepted with the energy still falling steeply at its end tries a longer one
        (see ``_EXTRAPOLATE_BELOW``); the last evaluation is always at the returned point.
        """
        slope = _dot(gradient, step)
        alpha = 1.0
        while alpha >= _MIN_STEP_FRACTION:
            trial = y + alpha * step
            if alpha == 1.0 and dofs is not None and mismatch > 0.0:
                trial[dofs] = targets
            trial_energy, trial_gradient, trial_scale = evaluate(trial)
            if math.isfinite(trial_energy) and (
                # While constraints still move the boundary the energy may rightly rise: accept
                # any finite full step then; afterwards require sufficient decrease.
                mismatch > 0.0
                or slope >= 0.0
                or trial_energy <= energy + _ARMIJO_C * alpha * slope + 1e-14 * abs(energy)
            ):
                if alpha == 1.0 and mismatch == 0.0 and slope < 0.0:
                    longer = _extrapolate(
                        y, step, slope, trial, trial_energy, trial_gradient, evaluate
                    )
                    if longer is not None:
                        return longer
                return trial, trial_energy, trial_gradient, trial_scale
            alpha *= 0.5
        # No decrease along the direction: keep the smallest step if it is finite.
        trial = y + _MIN_STEP_FRACTION * step
        trial_energy, trial_gradient, trial_scale = evaluate(trial)
        if math.isfinite(trial_energy):
            return trial, trial_energy, trial_gradient, trial_scale
        return None

    # ------------------------------------------------------------------ helpers

    def _finish(
        self,
        x,
        v,
        new_x,
        new_v,
        reaction,
        report,
        *,
        newton_iterations,
        newton_residual,
        known: tuple[float, float] | None = None,
    ):
        """The outcome of a step ending at (new_x, new_v); ``known``: its (elastic energy [J],
        smallest det F) when already evaluated there."""
        if not (np.all(np.isfinite(new_x)) and np.all(np.isfinite(new_v))):
            return self._failed(x, v, StepStatus.DIVERGED)
        # Finite positions far enough out overflow when squared (1e155 m and beyond): that is
        # the blow-up this check is for, and no warning for the user to puzzle over.
        with np.errstate(over="ignore"):
            moved = float(np.max(np.linalg.norm(new_x - self._rest, axis=1)))
        if moved > self._blow_up_m:
            return self._failed(x, v, StepStatus.DIVERGED)
        energy, min_ratio = (
            known if known is not None else self.elasticity.energy_and_min_volume_ratio(new_x)
        )
        status = StepStatus.INVERTED if min_ratio <= 0.0 else StepStatus.OK
        return StepOutcome(
            status=status,
            positions=new_x,
            velocities=new_v,
            reaction_forces=reaction.reshape(-1, 3),
            elastic_energy_j=float(energy),
            newton_iterations=newton_iterations,
            linear_iterations=report.iterations,
            linear_residual=report.relative_residual,
            newton_residual=newton_residual,
            min_volume_ratio=min_ratio,
            factorizations=int(report.factorized),
        )

    def _failed(self, x, v, status: StepStatus) -> StepOutcome:
        self.solver.forget()
        self._last_step = None
        return StepOutcome(
            status=status,
            positions=x.copy(),
            velocities=v.copy(),
            reaction_forces=np.zeros_like(x),
            elastic_energy_j=float(self.elasticity.energy(x)),
            min_volume_ratio=float(self.elasticity.volume_ratios(x).min()),
        )

    def _extrapolated_start(self, x0, v0, h) -> NDArray[np.float64] | None:
        """x + h v + h^2 (v - v_last) / h_last when (x0, v0) are what the last step returned."""
        last = self._last_step
        if last is None or self.config.quasi_static:
            return None
        positions, velocities, previous, last_h = last
        if positions is not x0 or velocities is not v0:
            return None
        return extrapolated_positions(x0, v0, h, previous, last_h)

    def _dof_mask(self, dofs: NDArray[np.int64]) -> NDArray[np.bool_]:
        mask = np.zeros(self.mass_dof.shape[0], dtype=bool)
        mask[dofs] = True
        return mask

    def _diagonal(self, matrix: sp.csr_matrix) -> NDArray[np.int64]:
        """Positions of the diagonal entries in the (fixed) CSR pattern, found once: the
        pattern's keys row * n + col are sorted (rows in order, columns sorted in each), so
        one search finds them all (a loop over rows took 7 of a 4,141-tet paper step's
        first 11 ms under cProfile; unprofiled, that first step went 8.8 -> 4.1 ms)."""
        if self._diagonal_positions is None:
            rows = np.arange(matrix.shape[0], dtype=np.int64)
            keys = self._pattern_keys(matrix)
            self._diagonal_positions = np.searchsorted(keys, rows * matrix.shape[1] + rows)
        return self._diagonal_positions

    def _pattern_keys(self, matrix: sp.csr_matrix) -> NDArray[np.int64]:
        """row * n + col of every stored entry, computed once for the fixed pattern."""
        if self._keys is None:
            rows = np.repeat(np.arange(matrix.shape[0], dtype=np.int64), np.diff(matrix.indptr))
            self._keys = rows * matrix.shape[1] + matrix.indices
        return self._keys

    @staticmethod
    def _stiffness_with_terms(
        state: ElasticState, positions, terms, scale: float = 1.0
    ) -> sp.csr_matrix:
        """``state``'s stiffness matrix with ``scale`` times the terms' stiffness at
        ``positions`` added, in place: the state's matrix is the system's from then on (a
        copy of it cost a step 1 MB at 4,126 tets, 8 MB at 26,220)."""
        stiffness = state.stiffness
        assert stiffness is not None
        for term in terms:
            evaluation = term.evaluate(positions)
            if not evaluation.stiffness_values.size:
                continue
            added = evaluation.stiffness_values
            if scale != 1.0:
                added = scale * added
            if not _add_triplets(
                stiffness.indptr,
                stiffness.indices,
                stiffness.data,
                evaluation.stiffness_rows,
                evaluation.stiffness_cols,
                added,
            ):
                raise ValueError(
                    "an energy term's stiffness couples dofs outside the mesh's pattern"
                )
        return stiffness

    @staticmethod
    def _term_stiffness_product(positions, terms, vector) -> NDArray[np.float64]:
        """The terms' stiffness at ``positions`` times ``vector`` (3N,), summed over terms."""
        total = np.zeros(vector.size)
        for term in terms:
            evaluation = term.evaluate(positions)
            if evaluation.stiffness_values.size:
                total += np.bincount(
                    evaluation.stiffness_rows,
                    weights=evaluation.stiffness_values * vector[evaluation.stiffness_cols],
                    minlength=vector.size,
                )
        return total

    @staticmethod
    def _term_forces(positions, terms) -> NDArray[np.float64]:
        total = np.zeros(positions.size)
        for term in terms:
            total += term.evaluate(positions).forces.reshape(-1)
        return total


@numba.njit(cache=True)
def _add_triplets(indptr, indices, data, rows, cols, values):  # pragma: no cover - compiled
    """data[(rows[k], cols[k])] += values[k] in order, each entry found by bisection in its
    row's sorted columns; False (data partly updated) if one is outside the pattern.

    (Searching the whole pattern's keys with numpy and ``np.add.at`` took ~0.1 ms for a
    few contact points' 144 entries each at 4,126 tets.)"""
    for k in range(rows.shape[0]):
        position = find_column(indices, indptr[rows[k]], indptr[rows[k] + 1], cols[k])
        if position < 0:
            return False
        data[position] += values[k]
    return True


def _extrapolate(y, step, slope, accepted, energy, gradient, evaluate):
    """The secant step past an accepted full step, if the energy still falls steeply there.

    ``slope`` [J] is the directional derivative along ``step`` at y; ``accepted`` = y +
    step, ``energy`` [J] and ``gradient`` [N] its evaluation. Returns (y', energy,
    gradient, scale) at y' = y + alpha step, alpha in [2, ``_MAX_EXTRAPOLATION``] (where
    the directional derivative, interpolated linearly from its values at 0 and 1,
    vanishes; the cap where it does not rise), when that energy is lower; else None,
    with ``accepted`` evaluated again if y' was tried (the contact terms report the
    last evaluation's forces).
    """
    end_slope = _dot(gradient, step)
    if not end_slope < _EXTRAPOLATE_BELOW * slope:
        return None
    rise = end_slope - slope  # > 0 where the energy is convex along the step
    alpha = _MAX_EXTRAPOLATION
    if rise > 0.0:
        alpha = min(alpha, -slope / rise)
    trial = y + alpha * step
    trial_energy, trial_gradient, trial_scale = evaluate(trial)
    if math.isfinite(trial_energy) and trial_energy < energy:
        return trial, trial_energy, trial_gradient, trial_scale
    evaluate(accepted)
    return None


def _finite(energy: float, gradient: NDArray[np.float64]) -> bool:
    return math.isfinite(energy) and bool(np.all(np.isfinite(gradient)))


def _rank(outcome: StepOutcome) -> int:
    return SEVERITY[outcome.status]


def _merge(first: StepOutcome, second: StepOutcome) -> StepOutcome:
    """Two consecutive substeps as one: the state of the second, the worse status, all work."""
    return StepOutcome(
        status=worst(first.status, second.status),
        positions=second.positions,
        velocities=second.velocities,
        reaction_forces=second.reaction_forces,
        elastic_energy_j=second.elastic_energy_j,
        newton_iterations=first.newton_iterations + second.newton_iterations,
        linear_iterations=first.linear_iterations + second.linear_iterations,
        linear_residual=max(first.linear_residual, second.linear_residual),
        newton_residual=second.newton_residual,
        subdivisions=first.subdivisions + second.subdivisions,
        min_volume_ratio=second.min_volume_ratio,
        factorizations=first.factorizations + second.factorizations,
    )
