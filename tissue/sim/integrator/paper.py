"""``paper`` mode's step: one linearised backward-Euler solve, the paper's eq. (5) (or K dx = f
when quasi-static), with its reactions; the elasticity evaluated at a step's end kept for the
next step, which starts there."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from tissue.errors import ConfigError
from tissue.fem.elasticity import ElasticState
from tissue.sim.frames import NodeFrames
from tissue.sim.integrator.assembly import row_products, scale_add_diagonal
from tissue.sim.integrator.core import IntegratorCore
from tissue.sim.integrator.outcome import StepOutcome
from tissue.sim.solvers import ConstrainedSystem
from tissue.status import StepStatus


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


class PaperSteps(IntegratorCore):
    """``paper`` mode's linearised step (public: :meth:`paper_system` and :meth:`paper_finish`,
    which contact strategies solving the system themselves call)."""

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
            scale_add_diagonal(
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
        rows = row_products(pointer, indices, data, np.arange(dofs.size), solution)
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
