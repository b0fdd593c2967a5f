"""What robust mode's Newton-LCP iteration (:mod:`.newton`) carries: an iterate
(:class:`Iterate`), an iteration's Newton system and free step (:class:`FreeStep`), and one
step's run with its setting and tallies (:class:`NewtonRun`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from tissue.contact.fe_model import Contacts
from tissue.sim.integrator import IncrementalPotential
from tissue.sim.solvers import ConstrainedSystem, Factorization
from tissue.status import StepStatus


@dataclass(frozen=True, eq=False)
class Iterate:
    """A Newton iterate of a robust step and what was evaluated there."""

    y: NDArray[np.float64]  # positions (3N,) [m]
    energy: float  # incremental potential [J]
    gradient: NDArray[np.float64]  # (3N,) [N]
    scale: float  # force scale of the residual [N]
    contacts: Contacts  # detected at y
    rows: sp.csr_matrix  # their constraint Jacobian H
    forces: NDArray[np.float64]  # one per contact [N]
    residual: float  # relative KKT residual (inf before the first iteration)
    penetration: float  # deepest point inside the probe [m]


@dataclass(eq=False)
class FreeStep:
    """An iteration's Newton system and its free step (contact forces fixed)."""

    system: ConstrainedSystem
    # (points augmented, rho [N/m]) of the contact terms added to the tangent, or None.
    augmented: tuple[NDArray[np.bool_], float] | None
    # Whether the last tangent tried was the projected one.
    project: bool
    indefinite: bool
    step: NDArray[np.float64] | None = None  # (3N,) [m]
    factorization: Factorization | None = None  # of A (refactorising)
    fresh: bool = False  # kept factorisation: F is of this A
    accuracy: float = 0.0  # kept factorisation: the free solve's absolute residual [N]


@dataclass(eq=False)
class NewtonRun:
    """One robust step's Newton-LCP iteration: its setting, its iterate and its tallies."""

    h: float  # the step [s]
    may_retry: bool
    relax_s: float
    exact_first_static: bool
    x: NDArray[np.float64]  # positions at the start (nodes, 3) [m]
    v: NDArray[np.float64]  # velocities at the start (nodes, 3) [m/s]
    dofs: NDArray[np.int64]  # constrained dofs and their targets [m]
    targets: NDArray[np.float64]
    potential: IncrementalPotential
    constrained: NDArray[np.bool_]  # mask (3N,)
    free: NDArray[np.bool_]
    scale_floor: float  # the integrator's floor on the force scale [N]
    keep: bool  # a kept factorisation
    dynamic: bool  # a dynamic step (not quasi-static, not a relaxation step)
    exact_first: bool  # dynamic with stiffness damping: exact tangent from the start
    contact_terms: bool  # quasi-static: the exact tangent carries the contact terms
    projected_iterations: int  # kept, quasi-static: iterations on the projected tangent
    limit: int  # iteration cap
    handed: ConstrainedSystem | None  # the last step's matrix, taken as a chord
    started_at_x: bool
    at: Iterate
    chord: ConstrainedSystem | None  # the matrix the next iteration reuses
    chord_step: bool = False
    system: ConstrainedSystem | None = None  # the last Newton system
    status: StepStatus = StepStatus.NOT_CONVERGED
    iterations: int = 0
    sweeps_total: int = 0
    rounds: int = 0
    deepest: float = np.inf
    stalled: int = 0
    exact_iterations: int = 0
    rejected: int = 0
    shortened: int = 0
    # False once this step's exact tangent was found indefinite or took a step that did
    # not reduce the residual: projected for the rest of the step.
    exact_trusted: bool = True
