"""Modified Newton across dynamic steps: a converged step's matrix handed to the next."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from tissue.sim.integrator.config import IntegratorConfig
from tissue.sim.solvers import ConstrainedSystem


class ChordHandOver:
    """Modified Newton across dynamic steps: the matrix of a step that converged in one full,
    exact (unprojected) iteration is handed to the next step, whose first iteration takes
    it as a chord and assembles no tangent. A handed matrix whose step converges at once is
    handed on again, so one matrix may serve many steps (as CVODE keeps its Jacobian while
    Newton converges); every step still iterates to the Newton tolerance, and a chord that
    falls short costs an iteration, not accuracy.

    Where it pays: the kept factorisation F is refreshed from the system being solved (the
    ski-rental rule of ``reuse``), so under a handed matrix F soon factorises that very
    matrix: CG then converges in one iteration, and LM's W~ = H F^-1 H^T is the chord's exact
    compliance (one response round instead of two). Where the contact set changes every
    step, handed chords need a second iteration more often: after such a chord the hand-over
    pauses for 1, 2, 4, ... steps (``max_backoff_steps`` at most: the integrator's
    :attr:`~tissue.sim.integrator.config.IntegratorConfig.chord_backoff_max_steps`), and each
    chord that converges at once halves the pause again.

    LM's robust steps use it (:mod:`tissue.contact.lagrange`). This integrator's own Newton
    does not: there a chord needs the constrained dofs on their targets from the first
    iterate, and prescribed displacement moves its targets every step; penalty's springs
    change k with the largest offset from step to step, and a matrix handed on to its steps
    cost more Newton iterations than the assemblies it saved (the bench-peer press at 2,549
    tets: 88 -> 103 iterations for 71 -> 65 assemblies; with k changed only by factors of
    two, 98 for 53), and no less time.
    """

    def __init__(self, max_backoff_steps: int = IntegratorConfig.chord_backoff_max_steps) -> None:
        self.max_backoff_steps = max_backoff_steps
        self._handed: tuple[ConstrainedSystem, float] | None = None
        self._backoff = 0
        self._pause = 0

    def reset(self) -> None:
        """Forget the handed matrix and the back-off (a new or restored state)."""
        self._handed = None
        self._backoff = 0
        self._pause = 0

    def take(self, h: float, constrained: NDArray[np.bool_]) -> ConstrainedSystem | None:
        """The matrix (as a system) handed to a step of ``h`` [s] with ``constrained`` dofs
        (mask (3N,)), or None if none was or it was for another time step, constraint set or
        node frames. Taken once: a step that does not take it drops it."""
        handed, self._handed = self._handed, None
        if handed is None:
            return None
        system, handed_h = handed
        if handed_h != h or system.frames is not None:
            return None
        if not np.array_equal(system.constrained, constrained):
            return None
        return system

    def record(
        self,
        system: ConstrainedSystem,
        h: float,
        took_handed: bool,
        iterations: int,
        full_exact: bool,
    ) -> None:
        """After a converged dynamic step of ``h`` [s] whose last iteration solved ``system``:
        hand its matrix to the next step if the step converged in one iteration that was
        ``full_exact`` (unprojected, its full step taken), unless the hand-over is paused.
        ``took_handed``: this step's first iteration took a handed matrix."""
        if took_handed:
            if iterations > 1:
                self._backoff = min(max(1, 2 * self._backoff), self.max_backoff_steps)
                self._pause = self._backoff
                return
            self._backoff //= 2
        if self._pause > 0:
            self._pause -= 1
            return
        if iterations == 1 and full_exact:
            self._handed = (system, h)
