"""Compiled kernels the integrator assembles its systems with: inertia and damping added to a
gradient, a scaled matrix plus a diagonal, rows of a CSR product, COO triplets added in place."""

from __future__ import annotations

import numba
import numpy as np

from tissue.sim.frames import find_column
from tissue.threads import parallel_kernel


@numba.njit(cache=True)
def add_inertia_and_damping(
    y, inertia_target, x0, mass, h, rayleigh_mass, rayleigh_stiffness, damped, gradient
):  # pragma: no cover - compiled
    """Add inertia and Rayleigh damping to ``gradient`` (in place).

    With d = y - (x + h v), dx = y - x: inertial force m d / h^2 and damping force
    (r_M m dx + r_K D_K dx) / h, ``damped`` = D_K dx. Returns (their energy
    d.m d / (2 h^2) + dx.damping / 2 [J], ||inertial force||^2 [N^2]).
    """
    energy = 0.0
    inertial_square = 0.0
    for i in range(y.shape[0]):
        d = y[i] - inertia_target[i]
        inertial = mass[i] * d / (h * h)
        dx = y[i] - x0[i]
        damping = rayleigh_mass * mass[i] * dx / h + rayleigh_stiffness * damped[i] / h
        energy += 0.5 * (d * inertial + dx * damping)
        gradient[i] += inertial + damping
        inertial_square += inertial * inertial
    return energy, inertial_square


@parallel_kernel
def scale_add_diagonal(
    data, scale, other, other_scale, diagonal, diagonal_add
):  # pragma: no cover - compiled
    """data = scale data + other_scale other; then data[diagonal[i]] += diagonal_add[i]."""
    if scale != 1.0 or other_scale != 0.0:
        for k in numba.prange(data.shape[0]):
            data[k] = scale * data[k] + other_scale * other[k]
    for i in numba.prange(diagonal.shape[0]):
        data[diagonal[i]] += diagonal_add[i]


@numba.njit(cache=True)
def row_products(indptr, indices, data, rows, x):  # pragma: no cover - compiled
    """(A x)[rows] for a CSR matrix."""
    out = np.zeros(rows.shape[0])
    for i in range(rows.shape[0]):
        row = rows[i]
        acc = 0.0
        for k in range(indptr[row], indptr[row + 1]):
            acc += data[k] * x[indices[k]]
        out[i] = acc
    return out


@numba.njit(cache=True)
def add_triplets(indptr, indices, data, rows, cols, values):  # pragma: no cover - compiled
    """data[(rows[k], cols[k])] += values[k] in order, each entry found by bisection in its
    row's sorted columns; False (data partly updated) if one is outside the pattern.

    (Searching the whole pattern's keys with numpy and ``np.add.at`` took ~0.1 ms for a
    few contact points' 144 entries each at 4,126 tets.)"""
    for k in range(rows.shape[0]):
        position = find_column(indices, indptr[rows[k]], indptr[rows[k] + 1], cols[k])
        if position < 0:
            return False
        data[position] += values[k]
    return True
