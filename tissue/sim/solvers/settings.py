"""What a :class:`~tissue.sim.solvers.linear_solver.LinearSolver` is asked to do: which of the
three solvers (``cg``, ``direct``, ``reuse``), which library factorises, and their settings.

``cg``'s cap of 25 iterations is SOFA's ``CGLinearSolver`` default, as in the paper; ``reuse``'s
refresh rule is described at :attr:`LinearSolverConfig.reuse_refresh_factor`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from tissue.choices import Choice
from tissue.errors import ConfigError


class LinearSolverKind(Choice):
    """The linear solver used for each implicit step."""

    CG = "cg"
    DIRECT = "direct"
    REUSE = "reuse"

    @classmethod
    def noun(cls) -> str:
        return "linear solver"


class DirectBackend(Choice):
    """The library behind direct factorisations."""

    AUTO = "auto"
    PARDISO = "pardiso"
    SUPERLU = "superlu"

    @classmethod
    def noun(cls) -> str:
        return "direct solver backend"


@dataclass(frozen=True)
class LinearSolverConfig:
    """Settings of the linear solver.

    Attributes:
        kind: ``cg``, ``direct`` or ``reuse``.
        cg_max_iterations: iteration cap of ``cg`` (25 as in the paper).
        cg_tolerance: relative residual at which ``cg`` stops early.
        direct_backend: ``auto`` (Pardiso where available, else SuperLU), ``pardiso``, ``superlu``.
        reuse_max_iterations: preconditioned-CG iterations after which ``reuse`` refactorises.
        reuse_refresh_factor: ``reuse`` also refactorises once the CG iterations beyond the
            first of each solve since the kept factorisation add up to this times the square
            root of the free unknowns: a numeric refactorisation (single-precision Pardiso)
            costs about 0.15 sqrt(n) CG iterations on the phantom's meshes. 0 refreshes only
            when CG stalls.
    """

    kind: LinearSolverKind | str = LinearSolverKind.CG
    cg_max_iterations: int = 25
    cg_tolerance: float = 1e-5
    direct_backend: DirectBackend | str = DirectBackend.AUTO
    reuse_max_iterations: int = 12
    reuse_refresh_factor: float = 0.15

    def __post_init__(self) -> None:
        object.__setattr__(self, "kind", LinearSolverKind.parse(self.kind))
        object.__setattr__(self, "direct_backend", DirectBackend.parse(self.direct_backend))
        if self.cg_max_iterations < 1:
            raise ConfigError(f"cg_max_iterations must be >= 1; got {self.cg_max_iterations}")
        if not 0 < self.cg_tolerance < 1:
            raise ConfigError(f"cg_tolerance must lie in (0, 1); got {self.cg_tolerance}")
        if self.reuse_max_iterations < 1:
            raise ConfigError(f"reuse_max_iterations must be >= 1; got {self.reuse_max_iterations}")
        if not (math.isfinite(self.reuse_refresh_factor) and self.reuse_refresh_factor >= 0.0):
            raise ConfigError(
                "reuse_refresh_factor must be a finite number >= 0 (0: refactorise only when CG "
                f"stalls); got {self.reuse_refresh_factor}"
            )
