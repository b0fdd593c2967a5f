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

import time
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from tissue.profile import profile_choices
from tissue.sim.frames import NodeFrames
from tissue.sim.integrator.newton import NewtonSteps
from tissue.sim.integrator.outcome import StepOutcome
from tissue.sim.integrator.paper import PaperSteps
from tissue.sim.integrator.potential import EnergyTerm
from tissue.status import StepStatus


class ImplicitIntegrator(PaperSteps, NewtonSteps):
    """Advances positions and velocities of a tet mesh by one implicit step.

    Args:
        elasticity: the hyperelastic model (mesh, materials, lumped mass, pattern).
        config: integrator settings.
        external_force: constant external nodal force (gravity) [N], (node_count, 3), or None.
    """

    def prepare(self, fixed_dofs: NDArray[np.int64] | None = None) -> None:
        """Do the first step's one-time work now, when the model is built: load the compiled
        element kernels (numba reads them from its cache on a process's first call: ~0.8 s
        here), the rest stiffness and its products robust mode's first step needs, the
        direct solver's library and, in robust mode, its analysis of the stiffness pattern
        with ``fixed_dofs`` (always constrained, (k,)) left out. Without it all of that
        landed in the first simulated step."""
        if profile_choices(self.config.mode).newton:
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
        if not profile_choices(self.config.mode).newton:
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
        self._start_near = None  # handed over for this step only, taken or not
        outcome.seconds = time.perf_counter() - start
        return outcome
