"""Projected Gauss-Seidel for the contact LCP (Signorini's conditions on the compliance W).

The LCP is gap = offset + W lambda >= 0, lambda >= 0, gap . lambda = 0 (Tagliabue et al.
2020, eq. 10), solved as SOFA's ``GenericConstraintSolver`` does: one constraint at a time,
each force set to what closes its gap given the others, clamped at zero (a contact pushes,
never pulls). It converges for a symmetric positive-definite W (Cottle, Pang & Stone, *The
Linear Complementarity Problem*, 1992, ch. 5); the caller regularises W so that redundant
constraints (several points of a flat face) keep it definite. Dense W: for the tens to
hundreds of constraints a press has, not thousands.
"""

from __future__ import annotations

import numba


@numba.njit(cache=True)
def projected_gauss_seidel(matrix, offset, force, tolerance, max_iterations):  # pragma: no cover
    """Solve gap = offset + matrix @ force >= 0, force >= 0, gap . force = 0 in place.

    Returns (sweeps, largest change of the last sweep expressed as a gap).
    """
    count = offset.shape[0]
    change = 0.0
    for sweep in range(1, max_iterations + 1):
        change = 0.0
        for i in range(count):
            gap = offset[i]
            for j in range(count):
                gap += matrix[i, j] * force[j]
            new = force[i] - gap / matrix[i, i]
            if new < 0.0:
                new = 0.0
            delta = abs(new - force[i]) * matrix[i, i]
            if delta > change:
                change = delta
            force[i] = new
        if change <= tolerance:
            return sweep, change
    return max_iterations, change
