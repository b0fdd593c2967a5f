"""Sparse linear solvers for the implicit step: capped Jacobi-CG, direct factorisation, reuse.

Every system here is symmetric, of size n = 3 node_count, with some degrees of freedom
*constrained* (fixed base, prescribed surface nodes), eliminated in place so that the
sparsity pattern never changes and a symbolic factorisation is computed once per mesh
(:class:`ConstrainedSystem`). :class:`LinearSolver` solves them in one of three ways
(:class:`LinearSolverConfig`):

* ``cg``: conjugate gradient with a Jacobi preconditioner and an iteration cap (25 by
  default, as SOFA's ``CGLinearSolver`` in the paper). Fast, but on fine meshes 25
  iterations are far from converged; the report says how far (``relative_residual``).
  Elasticity matrices are made of 3x3 node blocks: CG then multiplies with the upper blocks
  only (half the memory traffic, in double precision).
* ``direct``: a sparse Cholesky-type factorisation, Intel MKL Pardiso (:mod:`tissue.sim.pardiso`)
  in SPD mode with a symmetric-indefinite fallback, or scipy's SuperLU where MKL is
  unavailable.
* ``reuse``: CG preconditioned by the last factorisation, refactorising only when CG stalls
  or when its extra iterations add up to a factorisation's cost. Consecutive implicit steps
  change the matrix little, so most steps cost a few triangular solves instead of a
  factorisation (Courtecuisse et al. 2014 use a one-step-old factorisation as preconditioner
  in the same spirit). The kept factorisation is in single precision and corrected in
  capacitance (Woodbury) form for what changes in low rank between solves: dofs constrained
  since it was computed, and rank-one terms a system declares (:class:`RankOneTerms`:
  penalty springs) changed since.

Modules, one concept each:

* :mod:`~tissue.sim.solvers.settings`: the solver kinds, direct backends and settings.
* :mod:`~tissue.sim.solvers.limits`: the corrections' caps and the one-thread thresholds.
* :mod:`~tissue.sim.solvers.constrained_system`: the eliminated systems and rank-one terms.
* :mod:`~tissue.sim.solvers.vector_kernels`: compiled dot products, norms and column updates.
* :mod:`~tissue.sim.solvers.node_blocks`: products through the upper 3x3 node blocks.
* :mod:`~tissue.sim.solvers.jacobi_cg`: ``cg``'s compiled Jacobi-preconditioned CG.
* :mod:`~tissue.sim.solvers.direct_factorization`: Pardiso and SuperLU factorisations.
* :mod:`~tissue.sim.solvers.factor_cg`: CG preconditioned by a factorisation (``reuse``).
* :mod:`~tissue.sim.solvers.constrained_correction`: a kept factorisation corrected for dofs
  constrained (and node frames turned) since.
* :mod:`~tissue.sim.solvers.rank_one_correction`: a kept factorisation corrected for
  rank-one terms changed since.
* :mod:`~tissue.sim.solvers.linear_solver`: :class:`LinearSolver`, the three-way dispatch and
  the state kept across steps.
"""

from __future__ import annotations

from tissue.sim.solvers.constrained_correction import ConstrainedSince as ConstrainedSince
from tissue.sim.solvers.constrained_system import ConstrainedSystem, RankOneTerms
from tissue.sim.solvers.direct_factorization import DirectFactorizer, Factorization
from tissue.sim.solvers.jacobi_cg import jacobi_pcg as jacobi_pcg
from tissue.sim.solvers.limits import (
    MAX_CONSTRAINED_SINCE,
    MAX_RANK_ONE_SINCE,
    RANK_ONE_COLUMN_COST,
    SERIAL_CG_UNKNOWNS,
    SERIAL_STEP_UNKNOWNS,
)
from tissue.sim.solvers.linear_solver import LinearSolver, SolveReport
from tissue.sim.solvers.node_blocks import NO_BLOCKS as NO_BLOCKS
from tissue.sim.solvers.node_blocks import NodeBlocks as NodeBlocks
from tissue.sim.solvers.node_blocks import SymmetricProduct
from tissue.sim.solvers.node_blocks import node_block_product as node_block_product
from tissue.sim.solvers.rank_one_correction import RankOneSince as RankOneSince
from tissue.sim.solvers.settings import DirectBackend, LinearSolverConfig, LinearSolverKind
from tissue.sim.solvers.vector_kernels import dot as dot
from tissue.sim.solvers.vector_kernels import free_square_norm as free_square_norm
from tissue.sim.solvers.vector_kernels import subtract_columns as subtract_columns
from tissue.sim.solvers.vector_kernels import vector_norm

__all__ = [
    "MAX_CONSTRAINED_SINCE",
    "MAX_RANK_ONE_SINCE",
    "RANK_ONE_COLUMN_COST",
    "SERIAL_CG_UNKNOWNS",
    "SERIAL_STEP_UNKNOWNS",
    "ConstrainedSystem",
    "DirectBackend",
    "DirectFactorizer",
    "Factorization",
    "LinearSolver",
    "LinearSolverConfig",
    "LinearSolverKind",
    "RankOneTerms",
    "SolveReport",
    "SymmetricProduct",
    "vector_norm",
]
