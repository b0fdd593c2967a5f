"""The solvers' caps and thresholds: how far a kept factorisation is corrected before it is
refactorised, and below what size the compiled kernels run on one thread.

Inside the package these are read through it at each use (``solvers.MAX_CONSTRAINED_SINCE``
after ``import tissue.sim.solvers as solvers``), not bound at import, so that setting them on
:mod:`tissue.sim.solvers` takes effect: the tests lower the caps to reach the refactorisation
and column-growth paths with small systems. Setting them on this module does not.
"""

from __future__ import annotations

#: A kept factorisation is corrected for at most this many dofs constrained since it was
#: computed (:class:`~tissue.sim.solvers.constrained_correction.ConstrainedSince`); beyond,
#: it is refactorised. It holds one column of F^-1 per dof, n doubles each: 192 columns of
#: 95k unknowns are 146 MB.
MAX_CONSTRAINED_SINCE = 192

#: A kept factorisation is corrected for at most this many rank-one terms changed since it
#: was computed (:class:`~tissue.sim.solvers.rank_one_correction.RankOneSince`; one column
#: F^-1 v held per term, as for constrained dofs); beyond, it is refactorised.
MAX_RANK_ONE_SINCE = 192

#: What one column F^-1 v solved beside a right-hand side costs, in CG iterations (a
#: multi-right-hand-side Pardiso call reads the factor once for all of its columns, so an
#: extra column costs well under a single solve). Counted into ``reuse``'s refresh rule
#: (:attr:`~tissue.sim.solvers.settings.LinearSolverConfig.reuse_refresh_factor`).
RANK_ONE_COLUMN_COST = 0.4

#: Below this many unknowns CG runs on one thread (its kernels' serial builds, see
#: :mod:`tissue.threads`): each CG iteration is three or four parallel regions, and starting
#: and joining the worker threads for each costs more than the work it shares out on small
#: meshes.
SERIAL_CG_UNKNOWNS = 40_000

#: Below this many unknowns (3 per node) a whole step runs its compiled kernels on one thread
#: (``ContactModel.step``, ``TissueSimulator.step``): its assembly, element and contact kernels
#: are a dozen parallel regions a step besides CG's, each paying the workers' start and join
#: for little work.
SERIAL_STEP_UNKNOWNS = 3_000
