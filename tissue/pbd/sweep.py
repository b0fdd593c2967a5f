"""The elastic sweep: one Gauss-Seidel pass of the neo-Hookean constraint pair over the tets.

:func:`project_tets` projects each tet's deviatoric and hydrostatic constraints together (the
coupled 2 x 2 solve of Macklin & Mueller 2021); :func:`project_tets_two_domains` runs the same
sweep as two node-disjoint domains on two threads, then their separator, in the order
:func:`two_domain_order` gives, the same bits as the one-thread sweep in that order.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from numpy.typing import NDArray

# A deviatoric constraint whose sqrt(I_C) falls below this is skipped: its gradient F / |F| is
# undefined at F = 0 (a tet collapsed to a point), and the hydrostatic constraint restores it.
_MIN_DEVIATORIC_NORM = 1e-9
# A 2 x 2 system whose determinant is below this fraction of the product of its diagonal is
# treated as singular (both gradients parallel with zero compliance) and skipped.
_SINGULAR_FRACTION = 1e-14

#: The sweep's floating-point freedoms: fused multiply-adds and reassociated sums (and no
#: signed zeros; about 10 % faster), never "no NaN" or "no Inf", so a diverging state still
#: reaches the step's finiteness check.
_SWEEP_FASTMATH = {"contract", "reassoc", "nsz"}


@nb.njit(cache=True, fastmath=_SWEEP_FASTMATH)
def project_tets(
    x: NDArray[np.float64],
    inv_mass: NDArray[np.float64],
    tets: NDArray[np.int64],
    dm_inv: NDArray[np.float64],
    alpha_dev: NDArray[np.float64],
    alpha_hyd: NDArray[np.float64],
    gamma: NDArray[np.float64],
    lam_dev: NDArray[np.float64],
    lam_hyd: NDArray[np.float64],
    support: NDArray[np.float64],
    tet_ids: NDArray[np.int64],
) -> None:
    """One Gauss-Seidel sweep of the coupled neo-Hookean constraint pair over ``tet_ids``.

    Args:
        x: node positions [m], (node_count, 3), updated in place.
        inv_mass: inverse lumped masses [1/kg], (node_count,), 0 at fixed nodes.
        tets: (tet_count, 4). dm_inv: inverse rest edge matrices [1/m], (tet_count, 3, 3).
        alpha_dev, alpha_hyd: time-scaled compliances alpha / h^2 [1/(kg m^2)] (the
            constraints are dimensionless, alpha in 1/J), (tet_count,).
        gamma: rest offset 1 + mu / lambda' of the hydrostatic constraint, (tet_count,).
        lam_dev, lam_hyd: this substep's multipliers [kg m^2], (tet_count,), updated.
        support: per-node sum of grad C * d lambda at fixed nodes, (node_count, 3), updated;
            divided by h^2 it is the elastic force on the fixed nodes.
        tet_ids: the tets to project, in this order (all of them, or the contact zone's).
    """
    # Written out in scalars, which stay in registers: faster than (4, 3) scratch arrays and
    # helpers taking arrays (tests hold it to the projection in numpy matrix operations).
    for t in tet_ids:
        i0, i1, i2, i3 = tets[t, 0], tets[t, 1], tets[t, 2], tets[t, 3]
        d00, d01, d02 = dm_inv[t, 0, 0], dm_inv[t, 0, 1], dm_inv[t, 0, 2]
        d10, d11, d12 = dm_inv[t, 1, 0], dm_inv[t, 1, 1], dm_inv[t, 1, 2]
        d20, d21, d22 = dm_inv[t, 2, 0], dm_inv[t, 2, 1], dm_inv[t, 2, 2]
        # F = Ds Dm^-1, row by row (Ds's columns are the edges from node 0).
        e1, e2, e3 = x[i1, 0] - x[i0, 0], x[i2, 0] - x[i0, 0], x[i3, 0] - x[i0, 0]
        f00 = e1 * d00 + e2 * d10 + e3 * d20
        f01 = e1 * d01 + e2 * d11 + e3 * d21
        f02 = e1 * d02 + e2 * d12 + e3 * d22
        e1, e2, e3 = x[i1, 1] - x[i0, 1], x[i2, 1] - x[i0, 1], x[i3, 1] - x[i0, 1]
        f10 = e1 * d00 + e2 * d10 + e3 * d20
        f11 = e1 * d01 + e2 * d11 + e3 * d21
        f12 = e1 * d02 + e2 * d12 + e3 * d22
        e1, e2, e3 = x[i1, 2] - x[i0, 2], x[i2, 2] - x[i0, 2], x[i3, 2] - x[i0, 2]
        f20 = e1 * d00 + e2 * d10 + e3 * d20
        f21 = e1 * d01 + e2 * d11 + e3 * d21
        f22 = e1 * d02 + e2 * d12 + e3 * d22
        # The cofactor d det F / dF: column b is the cross product of F's other two columns.
        c00, c10, c20 = f11 * f22 - f21 * f12, f21 * f02 - f01 * f22, f01 * f12 - f11 * f02
        c01, c11, c21 = f12 * f20 - f22 * f10, f22 * f00 - f02 * f20, f02 * f10 - f12 * f00
        c02, c12, c22 = f10 * f21 - f20 * f11, f20 * f01 - f00 * f21, f00 * f11 - f10 * f01
        det = f00 * c00 + f10 * c10 + f20 * c20
        norm = math.sqrt(
            f00 * f00 + f01 * f01 + f02 * f02
            + f10 * f10 + f11 * f11 + f12 * f12
            + f20 * f20 + f21 * f21 + f22 * f22
        )  # fmt: skip
        has_dev = norm > _MIN_DEVIATORIC_NORM
        scale = 1.0 / norm if has_dev else 0.0
        # Node gradients of C_D = |F| (g) and C_H = det F (h): node j = 1..3 is (dC/dF) Dm^-T
        # column j, node 0 minus their sum.
        g1x = (f00 * d00 + f01 * d01 + f02 * d02) * scale
        g1y = (f10 * d00 + f11 * d01 + f12 * d02) * scale
        g1z = (f20 * d00 + f21 * d01 + f22 * d02) * scale
        g2x = (f00 * d10 + f01 * d11 + f02 * d12) * scale
        g2y = (f10 * d10 + f11 * d11 + f12 * d12) * scale
        g2z = (f20 * d10 + f21 * d11 + f22 * d12) * scale
        g3x = (f00 * d20 + f01 * d21 + f02 * d22) * scale
        g3y = (f10 * d20 + f11 * d21 + f12 * d22) * scale
        g3z = (f20 * d20 + f21 * d21 + f22 * d22) * scale
        g0x, g0y, g0z = -(g1x + g2x + g3x), -(g1y + g2y + g3y), -(g1z + g2z + g3z)
        h1x = c00 * d00 + c01 * d01 + c02 * d02
        h1y = c10 * d00 + c11 * d01 + c12 * d02
        h1z = c20 * d00 + c21 * d01 + c22 * d02
        h2x = c00 * d10 + c01 * d11 + c02 * d12
        h2y = c10 * d10 + c11 * d11 + c12 * d12
        h2z = c20 * d10 + c21 * d11 + c22 * d12
        h3x = c00 * d20 + c01 * d21 + c02 * d22
        h3y = c10 * d20 + c11 * d21 + c12 * d22
        h3z = c20 * d20 + c21 * d21 + c22 * d22
        h0x, h0y, h0z = -(h1x + h2x + h3x), -(h1y + h2y + h3y), -(h1z + h2z + h3z)
        # The 2 x 2 system's entries grad C_i M^-1 grad C_j (a fixed node has w = 0).
        w0, w1, w2, w3 = inv_mass[i0], inv_mass[i1], inv_mass[i2], inv_mass[i3]
        k_dd = (
            w0 * (g0x * g0x + g0y * g0y + g0z * g0z)
            + w1 * (g1x * g1x + g1y * g1y + g1z * g1z)
            + w2 * (g2x * g2x + g2y * g2y + g2z * g2z)
            + w3 * (g3x * g3x + g3y * g3y + g3z * g3z)
        )
        k_dh = (
            w0 * (g0x * h0x + g0y * h0y + g0z * h0z)
            + w1 * (g1x * h1x + g1y * h1y + g1z * h1z)
            + w2 * (g2x * h2x + g2y * h2y + g2z * h2z)
            + w3 * (g3x * h3x + g3y * h3y + g3z * h3z)
        )
        k_hh = (
            w0 * (h0x * h0x + h0y * h0y + h0z * h0z)
            + w1 * (h1x * h1x + h1y * h1y + h1z * h1z)
            + w2 * (h2x * h2x + h2y * h2y + h2z * h2z)
            + w3 * (h3x * h3x + h3y * h3y + h3z * h3z)
        )
        a_dd = k_dd + alpha_dev[t]
        a_hh = k_hh + alpha_hyd[t]
        rhs_h = -(det - gamma[t]) - alpha_hyd[t] * lam_hyd[t]
        if has_dev:
            rhs_d = -norm - alpha_dev[t] * lam_dev[t]
            determinant = a_dd * a_hh - k_dh * k_dh
            if determinant <= _SINGULAR_FRACTION * a_dd * a_hh:
                continue
            d_dev = (a_hh * rhs_d - k_dh * rhs_h) / determinant
            d_hyd = (a_dd * rhs_h - k_dh * rhs_d) / determinant
        else:
            if a_hh <= 0.0:
                continue
            d_dev = 0.0
            d_hyd = rhs_h / a_hh
        lam_dev[t] += d_dev
        lam_hyd[t] += d_hyd
        # Move each free node by w (g d_dev + h d_hyd); a fixed node's share goes to support.
        # (A loop over tuples: as fast as the four blocks written out; not a helper taking x
        # and support, which made the whole sweep more than twice as slow.)
        nodes = (i0, i1, i2, i3)
        masses = (w0, w1, w2, w3)
        steps = (
            (g0x * d_dev + h0x * d_hyd, g0y * d_dev + h0y * d_hyd, g0z * d_dev + h0z * d_hyd),
            (g1x * d_dev + h1x * d_hyd, g1y * d_dev + h1y * d_hyd, g1z * d_dev + h1z * d_hyd),
            (g2x * d_dev + h2x * d_hyd, g2y * d_dev + h2y * d_hyd, g2z * d_dev + h2z * d_hyd),
            (g3x * d_dev + h3x * d_hyd, g3y * d_dev + h3y * d_hyd, g3z * d_dev + h3z * d_hyd),
        )
        for local in range(4):
            node, w, step = nodes[local], masses[local], steps[local]
            for a in range(3):
                if w == 0.0:
                    support[node, a] += step[a]
                else:
                    x[node, a] += w * step[a]


@nb.njit(parallel=True, cache=True, fastmath=False)
def project_tets_two_domains(
    x: NDArray[np.float64],
    inv_mass: NDArray[np.float64],
    tets: NDArray[np.int64],
    dm_inv: NDArray[np.float64],
    alpha_dev: NDArray[np.float64],
    alpha_hyd: NDArray[np.float64],
    gamma: NDArray[np.float64],
    lam_dev: NDArray[np.float64],
    lam_hyd: NDArray[np.float64],
    support: NDArray[np.float64],
    order: NDArray[np.int64],
    bounds: NDArray[np.int64],
) -> None:
    """One Gauss-Seidel sweep of every tet in ``order``, its two domains on two threads.

    ``order[bounds[0]:bounds[1]]`` and ``order[bounds[1]:bounds[2]]`` share no node (see
    :func:`two_domain_order`), so projecting them at the same time is the same, bit for bit,
    as projecting one after the other; the separator ``order[bounds[2]:bounds[3]]`` follows
    on one thread. The result is that of :func:`project_tets` over ``order`` whatever the
    thread count. Arguments ``x`` .. ``support`` as :func:`project_tets`; ``order``
    (tet_count,) and ``bounds`` (4,) as :func:`two_domain_order` returns them.
    """
    for part in nb.prange(2):
        project_tets(
            x, inv_mass, tets, dm_inv, alpha_dev, alpha_hyd, gamma, lam_dev, lam_hyd,
            support, order[bounds[part] : bounds[part + 1]],
        )  # fmt: skip
    project_tets(
        x, inv_mass, tets, dm_inv, alpha_dev, alpha_hyd, gamma, lam_dev, lam_hyd, support,
        order[bounds[2] : bounds[3]],
    )  # fmt: skip


def two_domain_order(
    nodes: NDArray[np.float64], tets: NDArray[np.int64], domains: int = 2
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """A sweep order of the tets as two node-disjoint domains and a separator.

    The tets are cut by their centroids across the mesh's longest extent: domain 0 is the
    tets below the cut, domain 1 the tets above it with no node of domain 0, and the
    separator the rest (one layer of tets along the cut). The cut is placed so the two
    domains hold as many tets as each other. Within each part the tets keep mesh order.

    Args:
        nodes: node positions [m], (node_count, 3).
        tets: (tet_count, 4) node indices.
        domains: 2, or 1 for mesh order as a single domain (bounds (0, n, n, n)).

    Returns:
        ``order`` (tet_count,), a permutation of the tets, and ``bounds`` (4,): the parts are
        ``order[bounds[i]:bounds[i + 1]]`` for domain 0, domain 1 and the separator.
    """
    count = tets.shape[0]
    if domains == 1:
        return np.arange(count, dtype=np.int64), np.array([0, count, count, count])
    centroids = nodes[tets].mean(axis=1)
    axis = int(np.argmax(np.ptp(nodes, axis=0)))
    by_axis = np.argsort(centroids[:, axis], kind="stable")

    def parts(cut: int) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
        below = np.zeros(count, dtype=bool)
        below[by_axis[:cut]] = True
        touched = np.zeros(nodes.shape[0], dtype=bool)
        touched[tets[below].ravel()] = True
        shares = touched[tets].any(axis=1)
        return (
            np.flatnonzero(below),
            np.flatnonzero(~below & ~shares),
            np.flatnonzero(~below & shares),
        )

    # Domain 0 grows and domain 1 shrinks with the cut: bisect for equal sizes.
    low, high = 0, count
    while high - low > 1:
        middle = (low + high) // 2
        first, second, _ = parts(middle)
        if first.size < second.size:
            low = middle
        else:
            high = middle
    first, second, separator = parts(low)
    order = np.concatenate([first, second, separator]).astype(np.int64)
    bounds = np.cumsum([0, first.size, second.size, separator.size]).astype(np.int64)
    return order, bounds
