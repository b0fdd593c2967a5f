"""Projected Gauss-Seidel for the contact LCP (Signorini's conditions on the compliance W).

The LCP is gap = offset + W lambda >= 0, lambda >= 0, gap . lambda = 0 (Tagliabue et al.
2020, eq. 10), solved as SOFA's ``GenericConstraintSolver`` does: one constraint at a time,
each force set to what closes its gap given the others, clamped at zero (a contact pushes,
never pulls). It converges for a symmetric positive-definite W (Cottle, Pang & Stone, *The
Linear Complementarity Problem*, 1992, ch. 5); the caller regularises W so that redundant
constraints (several points of a flat face) keep it definite. Dense W: for the tens to
hundreds of constraints a press has, not thousands.

A constraint's gap sums W's row over the forces that are not zero only, kept as an ascending
list of their indices: a press has tens of candidate constraints and a handful pressing, so
a sweep costs (candidates x pressing) multiply-adds instead of candidates squared, and the
sums are the full row's, term for term in the same order (a zero force adds an exact zero),
so the forces are bit for bit those of the dense sweep.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True)
def projected_gauss_seidel(matrix, offset, force, tolerance, max_iterations):  # pragma: no cover
    """Solve gap = offset + matrix @ force >= 0, force >= 0, gap . force = 0 in place.

    ``matrix`` (n, n), ``offset`` (n,) [m], ``force`` (n,) [N]: the start, overwritten with
    the solution. Sweeps until no force changes by more than ``tolerance`` expressed as a gap
    [m], at most ``max_iterations`` sweeps. Returns (sweeps, largest change of the last sweep
    expressed as a gap).
    """
    count = offset.shape[0]
    # The indices of the non-zero forces, ascending (live[:pressing]).
    live = np.empty(count, dtype=np.int64)
    pressing = 0
    for j in range(count):
        if force[j] != 0.0:
            live[pressing] = j
            pressing += 1
    change = 0.0
    for sweep in range(1, max_iterations + 1):
        change = 0.0
        for i in range(count):
            gap = offset[i]
            for k in range(pressing):
                j = live[k]
                gap += matrix[i, j] * force[j]
            old = force[i]
            new = old - gap / matrix[i, i]
            if new < 0.0:
                new = 0.0
            delta = abs(new - old) * matrix[i, i]
            if delta > change:
                change = delta
            force[i] = new
            if (old != 0.0) != (new != 0.0):
                pressing = _toggle(live, pressing, i, new != 0.0)
        if change <= tolerance:
            return sweep, change
    return max_iterations, change


@numba.njit(cache=True)
def _toggle(live, pressing, index, joins):  # pragma: no cover
    """Insert ``index`` into (``joins``) or remove it from the ascending ``live[:pressing]``;
    returns the new count."""
    if joins:
        k = pressing
        while k > 0 and live[k - 1] > index:
            live[k] = live[k - 1]
            k -= 1
        live[k] = index
        return pressing + 1
    k = 0
    while live[k] != index:
        k += 1
    for m in range(k, pressing - 1):
        live[m] = live[m + 1]
    return pressing - 1
