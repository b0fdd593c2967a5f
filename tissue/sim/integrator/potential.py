"""Robust mode's incremental potential of a step (energy, gradient, Hessian system, Newton
direction) and the extra energy terms (penalty contact) a step may carry."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Protocol

import numpy as np
from numpy.typing import NDArray

from tissue.fem.elasticity import ElasticState
from tissue.sim.frames import NodeFrames
from tissue.sim.integrator.assembly import add_inertia_and_damping, scale_add_diagonal
from tissue.sim.solvers import ConstrainedSystem, RankOneTerms, dot

if TYPE_CHECKING:
    from tissue.sim.integrator.core import IntegratorCore


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
        integrator: IntegratorCore,
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
        scale = math.sqrt(dot(internal, internal))
        if self.external is not None:
            energy -= dot(self.external, y_flat)
            gradient -= self.external
            scale = max(scale, math.sqrt(dot(self.external, self.external)))
        if not self.quasi:
            damped = self.damping_product
            if self._damping_product is not None:
                self._damping_product(y_flat - self.x0_flat, damped)
            inertia_energy, inertial_square = add_inertia_and_damping(
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
        integrator, cfg, h, m = (
            self.integrator,
            self.integrator.config,
            self.h,
            self.mass,
        )
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
            scale_add_diagonal(
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


def floored_tolerance(tolerance: float, enough: float, rhs_norm: float) -> float:
    """The relative residual to ask of a linear solve: ``tolerance``, loosened (to at most 0.5)
    so that the solve may stop once its absolute residual over the free dofs reaches
    ``enough`` [N], for a right-hand side of norm ``rhs_norm`` [N] (see
    :attr:`~tissue.sim.integrator.config.IntegratorConfig.linear_share_of_tolerance`)."""
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
