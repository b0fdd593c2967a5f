"""The Lagrange-multiplier model's state and what its paper and robust steps share.

:class:`LagrangeState` holds what a step leaves for the next beyond the tissue's positions
and velocities: the contact forces by surface point (the next LCP's warm start), the last
probe pose (a split step interpolates from it), the compliance cache of the kept
factorisation, the last dynamic step (the next one extrapolates its start from it) and its
matrix (a chord for the next step). It saves and loads that state, undoes failed attempts,
and turns a step's forces into the contact points and forces on the probe.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from tissue.contact.compliance import KeptCompliance
from tissue.contact.fe_model import Contacts, FEContactModel, detect_contacts, movable_points
from tissue.contact.lagrange.params import LagrangeParams
from tissue.contact.wrench_stiffness import ContactConstraints
from tissue.errors import TissueInputError
from tissue.sim.integrator import ChordHandOver, extrapolated_positions
from tissue.sim.solvers import SolveReport

# What a failed attempt is undone to: positions [m], velocities [m/s], time [s], warm start [N].
_Checkpoint = tuple[NDArray[np.float64], NDArray[np.float64], float, NDArray[np.float64]]


class LagrangeState(FEContactModel):
    """The state of Lagrange-multiplier contact between steps (the base of
    :class:`~tissue.contact.lagrange.LagrangeContact`)."""

    params_type = LagrangeParams
    params: LagrangeParams

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        # Warm start: last forces by surface point.
        self._warm = np.zeros(self.surface.count)
        # The surface points a free dof can move: the others (on the fixed base) are never
        # constraints (their compliance is 0: see :func:`movable_points`).
        self._movable = movable_points(self.surface, self.mesh.fixed_nodes)
        # The probe pose of the last step (a failed robust step is retried from it).
        self._pose_before: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None
        self._compliance = KeptCompliance(self.surface)
        # The last dynamic robust step that ended OK: (positions [m], velocities [m/s] it
        # ended with, velocities it started from, its step [s]); the next step, if it starts
        # from exactly that state, extrapolates its first iterate from it.
        self._last_step: tuple[NDArray, NDArray, NDArray, float] | None = None
        # A converged dynamic step's matrix, handed to the next (modified Newton).
        self._chords = ChordHandOver(self.sim.integrator.config.chord_backoff_max_steps)
        # W~ is cached per kept factorisation and LM refreshes it by its own rules (response
        # rounds, exact iterations): no amortised refresh behind its back.
        solver = self.sim.integrator.solver
        solver.config = replace(solver.config, reuse_refresh_factor=0.0)
        # The kept factorisation is single precision, as the tissue's own Newton keeps it:
        # W~ and the CG preconditioner are approximations that the response rounds and the
        # CG correct to the exact A anyway (the same iterations and forces as a double
        # factor, in a half to two thirds of Pardiso's time).

    def _reset_tissue(self) -> None:
        super()._reset_tissue()
        self._warm = np.zeros(self.surface.count)
        self._pose_before = None
        self._compliance = KeptCompliance(self.surface)
        self._last_step = None
        self._chords.reset()

    def sleep_reach_m(self) -> float:
        """The alarm distance [m]: points closer than it become constraints (at least the
        contact distance, :class:`LagrangeParams` checks)."""
        return max(self.params.alarm_distance_m, self.params.contact_distance_m)

    def _in_contact(self) -> bool:
        return bool(np.any(self._warm > 0.0))

    def _advance_asleep(self, h: float, pieces: int) -> None:
        super()._advance_asleep(h, pieces)
        self._pose_before = (self.probe.position_world.copy(), self.probe.quat_wxyz.copy())

    def contact_constraints(self) -> ContactConstraints:
        """The contacts pressing at the end of the last step, exact (zero compliance)."""
        active = np.flatnonzero(self._warm > 0.0)
        positions = self.surface.positions_of(self.sim.positions, active)
        _, normal = self.probe.signed_distance_world(positions)
        return self._constraint_rows(self.surface, active, normal, 0.0)

    def drop_caches(self) -> None:
        super().drop_caches()
        self._compliance = KeptCompliance(self.surface)
        self._last_step = None
        self._chords.reset()

    def _snapshot_contact(self) -> dict[str, Any]:
        before = self._pose_before
        return {
            "warm_n": self._warm.copy(),
            "pose_before": None if before is None else (before[0].copy(), before[1].copy()),
        }

    def _restore_contact(self, snapshot: dict[str, Any]) -> None:
        self._warm[:] = snapshot["warm_n"]
        before = snapshot["pose_before"]
        self._pose_before = None if before is None else (before[0].copy(), before[1].copy())

    def saved_state(self) -> dict[str, NDArray[np.float64]]:
        """Positions and velocities [m, m/s] (nodes, 3), time [s], the warm-start forces
        [N] by surface point, the last probe pose (a split step interpolates from it) and,
        after a dynamic step, the velocities it started from [m/s] (nodes, 3) and its step
        [s] (the next step's start is extrapolated from them)."""
        sim = self.sim
        state = {
            "positions": sim.positions.copy(),
            "velocities": sim.velocities.copy(),
            "time_s": np.array([sim.time_s, self.time_s]),
            "warm_n": self._warm.copy(),
        }
        if self._pose_before is not None:
            state["pose_before"] = np.concatenate(self._pose_before)
        last = self._continued_step(sim.positions, sim.velocities)
        if last is not None:
            # What the next step extrapolates its start from (a resumed run starts as this
            # one would have): the velocities the last step started from, and its step [s].
            state["velocities_before"] = last[2].copy()
            state["step_before_s"] = np.array([last[3]])
        return state

    def load_state(self, state: dict[str, NDArray[np.float64]]) -> None:
        try:
            positions, velocities = state["positions"], state["velocities"]
            tissue_time, model_time = (float(t) for t in state["time_s"])
            warm = np.asarray(state["warm_n"], dtype=np.float64)
        except (KeyError, TypeError, ValueError) as error:
            raise TissueInputError(
                f"not a saved Lagrange-multiplier state ({error}); pass what saved_state() returned"
            ) from error
        if warm.shape != self._warm.shape:
            raise TissueInputError(
                f"the saved state has {warm.shape[0]} contact points, this model "
                f"{self._warm.shape[0]}: it was saved from another mesh"
            )
        self._reset_tissue()  # caches of the state being left
        self._state_replaced()
        self.sim.set_state(positions, velocities, time_s=tissue_time)
        self._time = model_time
        self._warm[:] = warm
        pose = state.get("pose_before")
        self._pose_before = None if pose is None else (pose[:3].copy(), pose[3:].copy())
        before, step_s = state.get("velocities_before"), state.get("step_before_s")
        if before is not None and step_s is not None:
            self._last_step = (
                self.sim.positions.copy(),
                self.sim.velocities.copy(),
                np.array(before, dtype=np.float64).reshape(self.sim.velocities.shape),
                float(step_s[0]),
            )

    def _extrapolated_start(
        self, x: NDArray[np.float64], v: NDArray[np.float64], h: float
    ) -> NDArray[np.float64] | None:
        """The first iterate of a dynamic step of ``h`` [s] from (x [m], v [m/s]), (3N,):
        x + h v + h^2 (v - v_last) / h_last when the step continues from the state the last
        one ended in (v_last: the velocities it started from), as the integrator's own
        Newton starts (:meth:`tissue.sim.integrator.ImplicitIntegrator.step`); else None."""
        last = self._continued_step(x, v)
        if last is None:
            return None
        _, _, previous, last_h = last
        return extrapolated_positions(x, v, h, previous, last_h)

    def _continued_step(
        self, x: NDArray[np.float64], v: NDArray[np.float64]
    ) -> tuple[NDArray, NDArray, NDArray, float] | None:
        """The last dynamic step's record if (x [m], v [m/s]) is exactly the state it ended in."""
        last = self._last_step
        if last is None or not (np.array_equal(x, last[0]) and np.array_equal(v, last[1])):
            return None
        return last

    def _checkpoint(self) -> _Checkpoint:
        """The state a failed attempt is undone to: positions, velocities, time, warm start."""
        sim = self.sim
        return sim.positions.copy(), sim.velocities.copy(), sim.time_s, self._warm.copy()

    def _restore(self, checkpoint: _Checkpoint) -> None:
        """Undo to a :meth:`_checkpoint`."""
        positions, velocities, time_s, warm = checkpoint
        self.sim.set_state(positions, velocities, time_s=time_s)
        self._warm[:] = warm

    # ------------------------------------------------------------------ shared by the steps

    def _detect_contacts(self, node_positions: NDArray[np.float64]) -> Contacts:
        """The movable surface points within the alarm distance of the probe at
        ``node_positions`` [m] (nodes, 3): the step's constraints."""
        return detect_contacts(
            self.surface,
            node_positions,
            self.probe,
            self.params.alarm_distance_m,
            self._movable,
        )

    @property
    def gap_tolerance_m(self) -> float:
        """How far a gap may miss complementarity [m]: ten PGS tolerances (and 1 nm)."""
        return 10 * self.params.pgs_tolerance_m + 1e-9

    def _finish(
        self, contacts: Contacts, forces: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Keep the forces for the next warm start; contact points and forces on the probe."""
        self._warm[:] = 0.0
        self._warm[contacts.points] = forces
        positions = self.surface.positions_of(self.sim.positions, contacts.points)
        active = forces > 0.0
        if not np.any(active):
            return np.zeros((0, 3)), np.zeros((0, 3))
        _, normal = self.probe.signed_distance_world(positions[active])
        return positions[active], -forces[active, None] * normal


def solve_report(indefinite: bool) -> SolveReport:
    """What a direct solve did, for the integrator's bookkeeping."""
    return SolveReport(0, 0.0, True, True, indefinite)
