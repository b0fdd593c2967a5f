"""What a step returns (:class:`StepOutcome`), substeps merged into one, and re-solves'
work added to the solve kept."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from tissue.status import SEVERITY, StepStatus, worst


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


def rank(outcome: StepOutcome) -> int:
    return SEVERITY[outcome.status]


def merge(first: StepOutcome, second: StepOutcome) -> StepOutcome:
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


def with_work_of(final: StepOutcome, earlier: StepOutcome) -> StepOutcome:
    """``final`` with the solver work of ``earlier``, a solve of the same step that it
    replaced (an augmentation round, a node set settled again), added: Newton and linear
    iterations and factorisations are summed, so that a step reports all it cost; its
    state, status, residuals and the rest are ``final``'s."""
    return replace(
        final,
        newton_iterations=earlier.newton_iterations + final.newton_iterations,
        linear_iterations=earlier.linear_iterations + final.linear_iterations,
        factorizations=earlier.factorizations + final.factorizations,
    )
