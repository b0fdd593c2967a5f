"""Implicit time integration of the tissue: the paper's linearised backward Euler (``paper``) and
Newton on the step's incremental potential (``robust``); the equations are in :mod:`.implicit`.

The modules:

- :mod:`.config`: :class:`IntegratorConfig`, Newton's tuning
  included.
- :mod:`.outcome`: :class:`StepOutcome`, substeps merged into one, re-solves' work added.
- :mod:`.assembly`: the compiled kernels the step's systems are assembled with.
- :mod:`.potential`: the extra energy terms (:class:`TermEvaluation`, :class:`EnergyTerm`)
  and robust mode's :class:`IncrementalPotential` (energy, gradient, Hessian, Newton
  direction).
- :mod:`.line_search`: backtracking Armijo search, the secant extrapolation of a full step
  that fell short, the extrapolated first iterate.
- :mod:`.chords`: :class:`ChordHandOver`, modified Newton across dynamic steps.
- :mod:`.core`: what both modes share: state, caches, the terms' stiffness, a step's outcome.
- :mod:`.paper`: ``paper`` mode's linearised step (:class:`PaperSystem`).
- :mod:`.newton`: ``robust`` mode's Newton step and its subdivision.
- :mod:`.implicit`: :class:`ImplicitIntegrator`, the two modes composed.
"""

from __future__ import annotations

from tissue.sim.integrator.chords import ChordHandOver
from tissue.sim.integrator.config import (
    IntegratorConfig,
)
from tissue.sim.integrator.implicit import ImplicitIntegrator
from tissue.sim.integrator.line_search import extrapolated_positions
from tissue.sim.integrator.outcome import StepOutcome, with_work_of
from tissue.sim.integrator.paper import PaperSystem
from tissue.sim.integrator.potential import (
    EnergyTerm,
    IncrementalPotential,
    TermEvaluation,
    floored_tolerance,
)

__all__ = [
    "ChordHandOver",
    "EnergyTerm",
    "ImplicitIntegrator",
    "IncrementalPotential",
    "IntegratorConfig",
    "PaperSystem",
    "StepOutcome",
    "TermEvaluation",
    "extrapolated_positions",
    "floored_tolerance",
    "with_work_of",
]
