"""LM's kept compliance: W~ = H F^-1 H^T [m/N] between collision-surface points, under one
kept factorisation F of the step's matrix A, cached per point across Newton iterations and
steps (see :class:`KeptCompliance`; used by :mod:`tissue.contact.lagrange`).
"""

from __future__ import annotations

from collections.abc import Callable

import numba
import numpy as np
from numpy.typing import NDArray

from tissue.contact.surface_points import SurfacePoints
from tissue.sim.solvers import Factorization

# A point's entries of the kept compliance W~ are recomputed once its contact normal has
# turned further than this (cos 2 degrees) from the one they were computed with.
_NORMAL_TURN_COS = float(np.cos(np.radians(2.0)))
# Constraint columns solved for together (memory: dofs x this doubles).
COLUMN_BATCH = 96
# The compliance cache keeps its columns F^-1 E_p^T n_p (to start each response solve from
# their combination) while they take at most this many bytes [B]; beyond, it drops them.
_KEPT_COLUMNS_BYTES = 256 * 2**20


class KeptCompliance:
    """Entries W~_pq = n_p^T E_p F^-1 E_q^T n_q [m/N] between collision-surface points p and q
    for one kept factorisation F, E_p the point's barycentric embedding (3 x dofs, zero at
    constrained dofs) and n_p its contact normal as it was when its entries were computed.

    W~ of any contact set is then a submatrix. A point costs one solve, F^-1 E_p^T n_p, the
    first time it is seen under F, and again only once its normal has turned by more than 2
    degrees (:data:`_NORMAL_TURN_COS`; a point sliding round the probe's rim). A new F starts
    afresh, so W~ of a freshly factorised A is exact. Between, the normals it carries may lag
    the contacts' by up to that angle: one more approximation of W~ beside F's own, which the
    response rounds correct as they correct F's (their fixed point uses the exact gaps).

    While they fit in :data:`_KEPT_COLUMNS_BYTES` the columns F^-1 E_p^T n_p are kept too
    (:meth:`response`; at 176k tets they take 0.8 MB per point): F^-1 H^T dlambda, the
    response to a change of the forces under F, is then a sum of columns instead of a solve,
    and each response solve starts from it.
    """

    def __init__(self, surface: SurfacePoints) -> None:
        self.surface = surface
        self.owner: Factorization | None = None
        self.slot = np.full(surface.count, -1, dtype=np.int64)
        self.count = 0
        self.points = np.zeros(0, dtype=np.int64)
        self.normals = np.zeros((0, 3))
        self.entries = np.zeros((0, 0))
        self.solved_columns = 0
        # A batch of columns handed to the owner's next solve and not yet received.
        self._riding = False
        self._flush: Callable[[], None] = _nothing
        # Row p: the column F^-1 E_p^T n_p of slot p over all dofs (None once too large:
        # dropped for good, as the capacity never shrinks).
        self.columns: NDArray[np.float64] | None = np.zeros((0, 0))

    def matrix(
        self,
        factorization: Factorization,
        points: NDArray[np.int64],
        normals: NDArray[np.float64],
        constrained: NDArray[np.bool_],
    ) -> NDArray[np.float64]:
        """W~ = H F^-1 H^T [m/N] for contacts at ``points`` with ``normals`` (k, 3); (k, k)."""
        self._own(factorization)
        if self._riding:
            # Columns handed to F's next solve (:meth:`prefetch`) that no solve has carried.
            self._flush()
        stale = self._stale(points, normals)
        update = points[stale]
        self._claim(update, normals[stale], constrained.size)
        for start in range(0, update.size, COLUMN_BATCH):
            chunk = update[start : start + COLUMN_BATCH]
            columns = factorization.solve(self._projected_columns(chunk, constrained))
            self._store(factorization, chunk, constrained, np.asarray(columns))
        slots = self.slot[points]
        # As np.ix_ takes it (C order, so that products with it sum as before), without its
        # Python layers.
        return self.entries.take(slots, axis=0).take(slots, axis=1)

    def prefetch(
        self,
        factorization: Factorization,
        points: NDArray[np.int64],
        normals: NDArray[np.float64],
        constrained: NDArray[np.bool_],
    ) -> None:
        """Have the columns that :meth:`matrix` would solve for ``points`` solved in
        ``factorization``'s next solve, beside its own right-hand side, where it can carry
        them (Pardiso's ``ride_along``). LM calls it before the free step's solve with the
        points likely to enter its LCP: at 173,229 tets nearly every step of a press needs a
        few new columns, and their own call (45 ms plus about 8 ms a column) becomes about 8
        ms a column."""
        ride_along = getattr(factorization, "ride_along", None)
        flush = getattr(factorization, "flush", None)
        if ride_along is None or flush is None:
            return
        self._own(factorization)
        if self._riding:
            return  # one batch in flight at a time
        chosen = np.flatnonzero(self._stale(points, normals))[:COLUMN_BATCH]
        if chosen.size == 0:
            return
        update = points[chosen]
        self._claim(update, normals[chosen], constrained.size)
        embedding = self._projected_columns(update, constrained)
        self._riding, self._flush = True, flush

        def receive(columns: NDArray[np.float64]) -> None:
            if factorization is self.owner:
                self._riding, self._flush = False, _nothing
            self._store(factorization, update, constrained, columns)

        ride_along(embedding, receive)

    def _own(self, factorization: Factorization) -> None:
        """Start afresh for a new F (its columns still riding on the old one are dropped)."""
        if factorization is not self.owner:
            self.owner = factorization
            self.slot[:] = -1
            self.count = 0
            self._riding, self._flush = False, _nothing

    def _stale(self, points: NDArray[np.int64], normals: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Which of ``points`` (with current ``normals``) are unseen under F or have a normal
        turned by more than :data:`_NORMAL_TURN_COS` since their entries were computed."""
        slots = self.slot[points]
        stale = slots < 0
        known = ~stale
        if np.any(known):
            cosine = np.einsum("ij,ij->i", self.normals[slots[known]], normals[known])
            stale[known] = cosine < _NORMAL_TURN_COS
        return stale

    def _claim(self, update: NDArray[np.int64], normals: NDArray[np.float64], dofs: int) -> None:
        """Slots for the unseen of ``update`` (distinct points) and the ``normals`` (u, 3)
        their entries are to be computed with."""
        if update.size == 0:
            return
        new = update[self.slot[update] < 0]
        self._reserve(new.size, dofs)
        self.slot[new] = np.arange(self.count, self.count + new.size)
        self.points[self.count : self.count + new.size] = new
        self.count += new.size
        self.normals[self.slot[update]] = normals

    def _reserve(self, extra: int, dofs: int) -> None:
        """Room for ``extra`` more points (capacity doubled, so that growing is amortised),
        and for their columns over ``dofs`` while those are kept."""
        needed = self.count + extra
        k = self.count
        if needed > self.points.size:
            capacity = max(needed, 2 * self.points.size, 64)
            points = np.zeros(capacity, dtype=np.int64)
            normals = np.zeros((capacity, 3))
            entries = np.zeros((capacity, capacity))
            points[:k] = self.points[:k]
            normals[:k] = self.normals[:k]
            entries[:k, :k] = self.entries[:k, :k]
            self.points, self.normals, self.entries = points, normals, entries
        if self.columns is not None and self.columns.shape[0] < self.points.size:
            if self.points.size * dofs * 8 > _KEPT_COLUMNS_BYTES:
                self.columns = None
            else:
                columns = np.zeros((self.points.size, dofs))
                if k:
                    columns[:k] = self.columns[:k]
                self.columns = columns

    def response(
        self, points: NDArray[np.int64], change: NDArray[np.float64]
    ) -> NDArray[np.float64] | None:
        """F^-1 H^T dlambda [m] (dofs,) for force changes ``change`` [N] at ``points`` (all
        seen under the current F), with the normals kept; None when the columns are not kept."""
        if self.columns is None or points.size == 0:
            return None
        out = np.zeros(self.columns.shape[1])
        _add_scaled_rows(self.columns, self.slot[points], change, out)
        return out

    def _embedding_parts(
        self, points: NDArray[np.int64], constrained: NDArray[np.bool_]
    ) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float64]]:
        """The entries of the rows n_p^T E_p of ``points`` with their kept normals: (row,
        dof, value) each, constrained dofs left out. Each is one weight times one normal
        component, and no two share a (row, dof): a tet's four nodes differ."""
        count = points.size
        nodes = self.surface.embedding.tet_nodes[points]  # (k, 4)
        weights = self.surface.embedding.weights[points]
        normals = self.normals[self.slot[points]]
        rows = np.broadcast_to(np.arange(count)[:, None, None], (count, 4, 3))
        cols = 3 * nodes[:, :, None] + np.arange(3)
        values = weights[:, :, None] * normals[:, None, :]
        keep = ~constrained[cols]
        return rows[keep], cols[keep], values[keep]

    def _projected_columns(
        self, points: NDArray[np.int64], constrained: NDArray[np.bool_]
    ) -> NDArray[np.float64]:
        """The rows n_p^T E_p of ``points`` with their kept normals, transposed, dense and
        column-major, (dofs, k):
        the right-hand sides of the points' solves, written entry by entry (a sparse matrix
        and its dense transpose took ~150 Python-level calls a step)."""
        rows, cols, values = self._embedding_parts(points, constrained)
        dense = np.zeros((constrained.size, points.size), order="F")
        dense[cols, rows] = values
        return dense

    def _store(
        self,
        factorization: Factorization,
        update: NDArray[np.int64],
        constrained: NDArray[np.bool_],
        solved: NDArray[np.float64],
    ) -> None:
        """Keep the columns F^-1 E_u^T n_u of ``update`` (points with slots and normals),
        solved as ``solved`` (dofs, u), and their rows and columns of the entries; nothing if
        F has been replaced since they were asked for."""
        if factorization is not self.owner:
            return
        columns = solved.reshape(constrained.size, -1)  # (dofs, u)
        self.solved_columns += columns.shape[1]
        k = self.count
        if self.columns is not None:
            self.columns[self.slot[update]] = columns.T
        # cross[q, u] = n_q^T E_q F^-1 E_u^T n_u for every kept point q and updated point u.
        kept = self.points[:k]
        cross = np.zeros((k, columns.shape[1]))
        _embedded_rows_times(
            self.surface.embedding.tet_nodes[kept],
            self.surface.embedding.weights[kept],
            self.normals[:k],
            constrained,
            np.ascontiguousarray(columns),
            cross,
        )
        slots = self.slot[update]
        self.entries[:k, slots] = cross
        self.entries[slots, :k] = cross.T
        own = cross[slots]
        self.entries[np.ix_(slots, slots)] = 0.5 * (own + own.T)


@numba.njit(cache=True)
def _embedded_rows_times(
    tet_nodes, weights, normals, constrained, columns, out
):  # pragma: no cover - compiled
    """out[q] = n_q^T E_q ``columns`` for each point q of tets ``tet_nodes`` (k, 4) with
    barycentric ``weights`` (k, 4) and ``normals`` (k, 3), E_q zero at ``constrained`` dofs;
    ``columns`` (dofs, u), ``out`` (k, u), zero on entry. The entries of a row are added in
    increasing dof order, as a sparse row times ``columns`` adds them (a sparse matrix built
    for it took most of a column update's time at 1,303 tets)."""
    dofs = np.empty(12, dtype=np.int64)
    values = np.empty(12)
    for q in range(tet_nodes.shape[0]):
        count = 0
        for a in range(4):
            for i in range(3):
                dof = 3 * tet_nodes[q, a] + i
                if constrained[dof]:
                    continue
                dofs[count] = dof
                values[count] = weights[q, a] * normals[q, i]
                count += 1
        order = np.argsort(dofs[:count])
        for j in order:
            row = columns[dofs[j]]
            value = values[j]
            for u in range(out.shape[1]):
                out[q, u] += value * row[u]


@numba.njit(cache=True)
def _add_scaled_rows(rows, which, scales, out):  # pragma: no cover - compiled
    """out += sum_i scales[i] rows[which[i]], in one serial loop (a BLAS product of a tall
    matrix wakes OpenBLAS's threads: see tissue.sim.solvers.subtract_columns)."""
    for i in range(which.shape[0]):
        scale = scales[i]
        if scale == 0.0:
            continue
        row = rows[which[i]]
        for j in range(out.shape[0]):
            out[j] += scale * row[j]


def _nothing() -> None:
    """What :attr:`KeptCompliance._flush` is while no columns ride along."""
