"""What the integrator's paper and robust steps share (:class:`IntegratorCore`): the model and
its linear solver, the state kept between steps, the matrix pattern's diagonal, the rest
stiffness, the energy terms' contributions, and how a step's outcome is finished."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from tissue.fem.elasticity import Elasticity, ElasticState
from tissue.sim.integrator.assembly import add_triplets
from tissue.sim.integrator.config import IntegratorConfig
from tissue.sim.integrator.outcome import StepOutcome
from tissue.sim.solvers import LinearSolver, SymmetricProduct
from tissue.status import StepStatus


class IntegratorCore:
    """The base of :class:`~tissue.sim.integrator.ImplicitIntegrator`: its state and the
    helpers both modes' steps use (arguments as there)."""

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
        self._blow_up_m = config.blow_up_extents * extent
        mu, lam, _ = elasticity.materials.per_tet(elasticity.mesh.region)
        self._force_unit = float(np.max(mu + lam)) * extent * extent
        self._diagonal_positions: NDArray[np.int64] | None = None
        self._rest_stiffness_matrix: sp.csr_matrix | None = None
        self._rest_product: SymmetricProduct | None = None
        self._keys: NDArray[np.int64] | None = None
        # The last robust step that ended OK: (positions, velocities) it returned, the
        # velocities it started from and its step [s]; a step continuing from that state
        # (equal in value) extrapolates its first Newton iterate from them. A state set from
        # outside forgets it (:meth:`forget_last_step`).
        self._last_step: (
            tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], float] | None
        ) = None
        # Where the next step's Newton starts instead (:meth:`start_next_step_near`), once.
        self._start_near: NDArray[np.float64] | None = None
        # A paper step ends by evaluating the elasticity at its new positions (the energy and
        # det F its outcome reports): with the tangent, that evaluation is the next step's, which
        # starts there. (positions [m] (nodes, 3), projected?, the state), taken once.
        self._end_state: tuple[NDArray[np.float64], bool, ElasticState] | None = None

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

    def forget_last_step(self) -> None:
        """The next step does not continue the last one (a state set from outside): its
        Newton starts from x + h v, not extrapolated from the last step's acceleration."""
        self._last_step = None
        self._start_near = None

    def start_next_step_near(self, positions: NDArray[np.float64]) -> None:
        """The next robust dynamic step's Newton starts from ``positions`` [m] (N, 3) instead
        of x + h v (once; a start that inverts a tet falls back to x + h v): for a step
        solved again from the same state where an earlier solve's solution lies close to the
        new one, as the augmented Lagrangian's rounds
        (:func:`tissue.contact.penalty.augmented_solve`)."""
        start = np.array(positions, dtype=np.float64)
        if start.shape != self._rest.shape:
            raise ValueError(
                f"start_next_step_near needs positions of shape {self._rest.shape} (the "
                f"mesh's nodes, [m]); got {start.shape}: pass a state of this simulation"
            )
        self._start_near = start.reshape(-1)

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

    def _dof_mask(self, dofs: NDArray[np.int64]) -> NDArray[np.bool_]:
        mask = np.zeros(self.mass_dof.shape[0], dtype=bool)
        mask[dofs] = True
        return mask

    def _diagonal(self, matrix: sp.csr_matrix) -> NDArray[np.int64]:
        """Positions of the diagonal entries in the (fixed) CSR pattern, found once: the
        pattern's keys row * n + col are sorted (rows in order, columns sorted in each), so
        one search finds them all (a loop over the rows was most of a small mesh's first
        step)."""
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
            if not add_triplets(
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
