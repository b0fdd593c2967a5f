"""Tet volumes: the robust profile's volume floor and the step's inversion check.

:func:`enforce_volume_floor` lifts every tet whose det F fell below the floor back to it (a
hard one-sided constraint, the tets below it projected together), after a substep's sweeps;
:func:`count_below_volume_floor` is its screen on two threads for large meshes;
:func:`min_volume_ratio` is the smallest det F a step reports (<= 0: inverted). The floor is
a guard, not a cure: a tet held at it is far from the FE's answer there.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numpy.typing import NDArray

#: Rounds of the floor's joint projection per substep (each a Newton step on every tet below
#: the floor; see :func:`enforce_volume_floor`).
FLOOR_ROUNDS = 8
#: How far above the floor the projection aims (relative).
FLOOR_MARGIN = 1e-3
#: At most this many tets are lifted together (one dense solve); more are taken in blocks.
FLOOR_BLOCK = 64
#: From this many tets a step on two threads screens for the volume floor on both first;
#: below it, waking the second thread costs more than the screen saves.
PARALLEL_SCREEN_TETS = 100_000


@nb.njit(cache=True, inline="always")
def _deformation(
    x: NDArray[np.float64],
    tets: NDArray[np.int64],
    dm_inv: NDArray[np.float64],
    t: int,
    f: NDArray[np.float64],
    cof: NDArray[np.float64],
) -> float:
    """Fill ``f`` with tet ``t``'s deformation gradient F = Ds Dm^-1 and ``cof`` with its
    cofactor d det F / dF (both (3, 3)); return det F."""
    i0, i1, i2, i3 = tets[t, 0], tets[t, 1], tets[t, 2], tets[t, 3]
    # Ds columns are the edges from node 0.
    for a in range(3):
        e1 = x[i1, a] - x[i0, a]
        e2 = x[i2, a] - x[i0, a]
        e3 = x[i3, a] - x[i0, a]
        for b in range(3):
            f[a, b] = e1 * dm_inv[t, 0, b] + e2 * dm_inv[t, 1, b] + e3 * dm_inv[t, 2, b]
    # Column b of the cofactor is the cross product of the other two columns of F.
    for b in range(3):
        c1 = (b + 1) % 3
        c2 = (b + 2) % 3
        cof[0, b] = f[1, c1] * f[2, c2] - f[2, c1] * f[1, c2]
        cof[1, b] = f[2, c1] * f[0, c2] - f[0, c1] * f[2, c2]
        cof[2, b] = f[0, c1] * f[1, c2] - f[1, c1] * f[0, c2]
    return f[0, 0] * cof[0, 0] + f[1, 0] * cof[1, 0] + f[2, 0] * cof[2, 0]


@nb.njit(cache=True, inline="always")
def _edge_determinant(x: NDArray[np.float64], tets: NDArray[np.int64], t: int) -> float:
    """det Ds of tet ``t`` [m^3]: the triple product of its edges from node 0 (6 x its signed
    volume)."""
    i0, i1, i2, i3 = tets[t, 0], tets[t, 1], tets[t, 2], tets[t, 3]
    a0, a1, a2 = x[i1, 0] - x[i0, 0], x[i1, 1] - x[i0, 1], x[i1, 2] - x[i0, 2]
    b0, b1, b2 = x[i2, 0] - x[i0, 0], x[i2, 1] - x[i0, 1], x[i2, 2] - x[i0, 2]
    c0, c1, c2 = x[i3, 0] - x[i0, 0], x[i3, 1] - x[i0, 1], x[i3, 2] - x[i0, 2]
    return a0 * (b1 * c2 - b2 * c1) - a1 * (b0 * c2 - b2 * c0) + a2 * (b0 * c1 - b1 * c0)


@nb.njit(cache=True, inline="always")
def _node_gradients(
    d_dF: NDArray[np.float64],
    dm_inv: NDArray[np.float64],
    t: int,
    scale: float,
    out: NDArray[np.float64],
) -> None:
    """Node gradients of a constraint of tet ``t`` with dC/dF = scale * ``d_dF``, (4, 3):
    row j = 1..3 is (dC/dF) Dm^-T column j, row 0 minus their sum."""
    for j in range(3):
        for a in range(3):
            s = 0.0
            for b in range(3):
                s += d_dF[a, b] * dm_inv[t, j, b]
            out[j + 1, a] = s * scale
    for a in range(3):
        out[0, a] = -(out[1, a] + out[2, a] + out[3, a])


@nb.njit(parallel=True, cache=True)
def count_below_volume_floor(
    x: NDArray[np.float64],
    tets: NDArray[np.int64],
    inv_det_dm: NDArray[np.float64],
    volume_floor: float,
) -> int:
    """How many tets have det F < ``volume_floor``: :func:`enforce_volume_floor`'s screen on
    two threads, run first on large meshes (from :data:`PARALLEL_SCREEN_TETS` tets), where
    no tet is below the floor in nearly every substep; it reads every tet every substep.
    ``x``: node positions [m], (node_count, 3); ``tets`` (tet_count, 4); ``inv_det_dm``:
    1 / det Dm per tet [1/m^3], (tet_count,); ``volume_floor``: a det F (dimensionless)."""
    count = 0
    for t in nb.prange(tets.shape[0]):
        if _edge_determinant(x, tets, t) * inv_det_dm[t] < volume_floor:
            count += 1
    return count


@nb.njit(cache=True)
def enforce_volume_floor(
    x: NDArray[np.float64],
    inv_mass: NDArray[np.float64],
    tets: NDArray[np.int64],
    dm_inv: NDArray[np.float64],
    inv_det_dm: NDArray[np.float64],
    volume_floor: float,
    support: NDArray[np.float64],
) -> int:
    """Lift every tet with det F below ``volume_floor`` back to it; returns the projections.

    A hard one-sided constraint (zero compliance), run after a substep's sweeps: within a
    sweep a tet's own projection can lift it while its neighbours' push it back below, so
    the floor must come last (after the contacts too: a node it moves may end the substep a
    little inside the probe, which the next substep's contacts correct and the step's
    penetration reports). The tets below the floor are projected together, one Newton step
    on all their constraints at once (C_i = det F_i - floor, the 4-node gradients G_i,
    (G W G^T) mu = -C, W the inverse masses), repeated while any tet is below (at most
    :data:`FLOOR_ROUNDS` rounds): projected one at a time, two slivers sharing a face undo
    each other's lift. ``inv_det_dm``: 1 / det Dm per tet [1/m^3], (tet_count,); the other
    arguments as :func:`~tissue.pbd.sweep.project_tets`. Returns the tets projected, summed
    over the rounds (0: none was below the floor).
    """
    f = np.empty((3, 3))
    cof = np.empty((3, 3))
    hits = 0
    for _ in range(FLOOR_ROUNDS):
        # A cheap screen first: det F = det Ds / det Dm from the edges alone.
        active = np.empty(tets.shape[0], dtype=np.int64)
        count = 0
        for t in range(tets.shape[0]):
            if _edge_determinant(x, tets, t) * inv_det_dm[t] < volume_floor:
                active[count] = t
                count += 1
        if count == 0:
            break
        # Joint projections of up to FLOOR_BLOCK tets at a time (a dense solve each).
        for first in range(0, count, FLOOR_BLOCK):
            _lift_together(
                x, inv_mass, tets, dm_inv, active[first : min(first + FLOOR_BLOCK, count)],
                volume_floor * (1.0 + FLOOR_MARGIN), support, f, cof,
            )  # fmt: skip
        hits += count
    return hits


@nb.njit(cache=True)
def _lift_together(
    x: NDArray[np.float64],
    inv_mass: NDArray[np.float64],
    tets: NDArray[np.int64],
    dm_inv: NDArray[np.float64],
    active: NDArray[np.int64],
    target: float,
    support: NDArray[np.float64],
    f: NDArray[np.float64],
    cof: NDArray[np.float64],
) -> None:
    """One Newton step of the constraints det F_i = ``target`` of the tets ``active`` at once
    (see :func:`enforce_volume_floor`); ``f`` and ``cof`` are (3, 3) scratch."""
    count = active.shape[0]
    grads = np.empty((count, 4, 3))
    lift = np.empty(count)
    for i in range(count):
        det = _deformation(x, tets, dm_inv, active[i], f, cof)
        _node_gradients(cof, dm_inv, active[i], 1.0, grads[i])
        lift[i] = target - det
    # G W G^T: tets i and j couple through the free nodes they share.
    system = np.zeros((count, count))
    for i in range(count):
        for j in range(i, count):
            entry = 0.0
            for a in range(4):
                node = tets[active[i], a]
                w = inv_mass[node]
                if w == 0.0:
                    continue
                for b in range(4):
                    if tets[active[j], b] == node:
                        for c in range(3):
                            entry += w * grads[i, a, c] * grads[j, b, c]
            system[i, j] = entry
            system[j, i] = entry
    largest = 0.0
    for i in range(count):
        largest = max(largest, system[i, i])
    if largest == 0.0:
        return  # only fixed nodes: nothing can move
    for i in range(count):
        system[i, i] += 1e-12 * largest  # for tets whose constraints coincide
    multipliers = np.linalg.solve(system, lift)
    for i in range(count):
        _apply(x, inv_mass, tets, active[i], grads[i], 0.0, grads[i], multipliers[i], support)


@nb.njit(cache=True, inline="always")
def _apply(
    x: NDArray[np.float64],
    inv_mass: NDArray[np.float64],
    tets: NDArray[np.int64],
    t: int,
    g: NDArray[np.float64],
    d_dev: float,
    gh: NDArray[np.float64],
    d_hyd: float,
    support: NDArray[np.float64],
) -> None:
    """Move tet ``t``'s free nodes by M^-1 (g d_dev + gh d_hyd); a fixed node's share goes to
    ``support`` (see :func:`~tissue.pbd.sweep.project_tets`)."""
    for local in range(4):
        node = tets[t, local]
        w = inv_mass[node]
        for a in range(3):
            step = g[local, a] * d_dev + gh[local, a] * d_hyd
            if w == 0.0:
                support[node, a] += step
            else:
                x[node, a] += w * step


@nb.njit(cache=True)
def min_volume_ratio(
    x: NDArray[np.float64], tets: NDArray[np.int64], rest_volume: NDArray[np.float64]
) -> float:
    """Smallest deformed / rest signed tet volume (det F); <= 0 means an inverted tet.

    ``x``: node positions [m], (node_count, 3); ``tets`` (tet_count, 4); ``rest_volume``:
    rest tet volumes [m^3], (tet_count,)."""
    smallest = np.inf
    for t in range(tets.shape[0]):
        ratio = _edge_determinant(x, tets, t) / 6.0 / rest_volume[t]
        if not ratio >= smallest:  # also catches NaN
            smallest = ratio
    return smallest
