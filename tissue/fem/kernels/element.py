"""The element pass: per-tet energy, nodal forces and tangent terms of the two material
laws (stable and classic neo-Hookean), with the stable law's inversion barrier.

Energy structure shared by both laws: W(F) = mu/2 (I_C - 3) + psi(J), so that

    P = mu F + psi'(J) cof F,
    dP/dF = mu I_9 + psi''(J) vec(cof F) vec(cof F)^T + psi'(J) d2J/dF2,

and the element block of nodes a, c is (V = rest volume)

    K_ac = V [mu (G_a . G_c) I_3 + psi'' (cof F G_a)(cof F G_c)^T + psi' S(F (G_a x G_c))],

with S(w)_ik = eps_ikm w_m, since d2J/dF_ij dF_kl = eps_ikm eps_jln F_mn. The pass stores
the per-tet factors of K_ac (and, with ``project``, the negative modes of dP/dF from
:mod:`~tissue.fem.kernels.projection`); the 12x12 element matrices are never formed:
:mod:`~tissue.fem.kernels.assembly` sums the blocks straight into the stiffness matrix.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from tissue.fem.kernels.geometry import CHUNK, PAIRS, deformation_gradient
from tissue.fem.kernels.projection import MAX_NEGATIVE_MODES, negative_modes
from tissue.threads import parallel_kernel

LAW_STABLE = 0
LAW_CLASSIC = 1

# What an element pass computes: energy and det F only, also the nodal forces, or also
# what the tangent gather needs.
STAGE_ENERGY = 0
STAGE_FORCES = 1
STAGE_TANGENT = 2


@nb.njit(inline="always", cache=True, fastmath=False)
def _log1p_excess(d: float) -> float:
    """d - ln(1 + d) without cancellation for small d (its series d^2/2 - d^3/3 + ...)."""
    if abs(d) > 0.05:
        return d - math.log1p(d)
    total = 0.0
    power = d
    for k in range(2, 16):
        power *= -d
        total -= power / k
    return total


@parallel_kernel(fastmath=False)
def element_pass(
    x: np.ndarray,
    tets: np.ndarray,
    grads: np.ndarray,
    volume: np.ndarray,
    mu: np.ndarray,
    lam: np.ndarray,
    pressure: np.ndarray,
    law: int,
    barrier_ratio: float,
    barrier_modulus: np.ndarray,
    project: bool,
    stage: int,
    coef: np.ndarray,
    energy: np.ndarray,
    ratio: np.ndarray,
    tet_forces: np.ndarray,
    cofactor_grads: np.ndarray,
    pair_vector: np.ndarray,
    mode_count: np.ndarray,
    mode_vector: np.ndarray,
) -> None:
    """Per-tet energy and det F; with ``stage`` >= STAGE_FORCES the nodal forces; with
    STAGE_TANGENT what the tangent gather needs.

    Energy density W = mu/2 (I_C - 3) + psi(J) with

    * stable: psi = lam'/2 (J - alpha)^2 - mu^2/(2 lam'), lam' = lam + mu,
      alpha = 1 + mu/lam' (the constant makes W(I) = 0; it changes no force);
    * classic: psi = -mu ln J + lam/2 (ln J)^2; J <= 0 gives W = inf and a zero
      contribution (coef = 0) instead of NaN.

    With ``barrier_ratio`` J_b > 0 the stable law gains, below J_b, the inversion barrier
    k (-(J - J_b)^2 ln(J / J_b)) (k = ``barrier_modulus[e]`` [Pa]; C2 at J_b, where it and
    its first two derivatives vanish; convex; infinite as J -> 0+), and J <= 0 gives W = inf
    as for the classic law. Above J_b nothing changes.

    ``pressure`` [Pa] is added to psi'(J) (ANP's averaged nodal pressure; zeros otherwise).

    Writes, per tet e: energy[e] = V W [J], ratio[e] = J; from STAGE_FORCES on,
    tet_forces[e, 3 a + i] = V (mu F + psi' cof F) G_a [N] (minus the force on local node a);
    at STAGE_TANGENT coef[e] = (V mu, V (psi' + pressure), V psi'') [J],
    cofactor_grads[e, 3 a + i] = (cof F G_a)_i [1/m], pair_vector[e, 3 p + i] =
    V psi' (F (G_a x G_c))_i for the pairs p = (a, c) of PAIRS, and with ``project`` the
    negative modes m of dP/dF (eigenvalue l_m < 0, unit eigen-matrix Q_m) as mode_count[e]
    and the 12-vectors mode_vector[e, m, 3 a + i] = sqrt(-V l_m) (Q_m G_a)_i, so that the
    projected element matrix is K_e + sum_m c_m c_m^T.
    """
    tet_count = tets.shape[0]
    chunk_count = (tet_count + CHUNK - 1) // CHUNK
    for chunk in nb.prange(chunk_count):
        scratch = np.empty((6, 3, 3))
        vec = np.empty((3, 3))
        values = np.empty(MAX_NEGATIVE_MODES)
        matrices = np.empty((MAX_NEGATIVE_MODES, 9))
        f = np.empty(9)
        for e in range(chunk * CHUNK, min(tet_count, (chunk + 1) * CHUNK)):
            deformation_gradient(x, tets, grads, e, f)
            # cof F: columns are f1 x f2, f2 x f0, f0 x f1 (f_j the columns of F).
            c00 = f[4] * f[8] - f[7] * f[5]
            c10 = f[7] * f[2] - f[1] * f[8]
            c20 = f[1] * f[5] - f[4] * f[2]
            c01 = f[5] * f[6] - f[8] * f[3]
            c11 = f[8] * f[0] - f[2] * f[6]
            c21 = f[2] * f[3] - f[5] * f[0]
            c02 = f[3] * f[7] - f[6] * f[4]
            c12 = f[6] * f[1] - f[0] * f[7]
            c22 = f[0] * f[4] - f[3] * f[1]
            # The energy is written in H = F - I so that its terms are O(|H|^2) and do not
            # cancel: with F itself (I_C - 3 and (J - alpha)^2 - mu^2/lam'^2 each O(|H|)) a
            # tet at 1e-4 strain keeps only ~8 digits, too few for an energy line search to
            # compare the small energy changes of converging steps.
            h0 = f[0] - 1.0
            h4 = f[4] - 1.0
            h8 = f[8] - 1.0
            h_square = (
                h0 * h0
                + h4 * h4
                + h8 * h8
                + f[1] * f[1]
                + f[2] * f[2]
                + f[3] * f[3]
                + f[5] * f[5]
                + f[6] * f[6]
                + f[7] * f[7]
            )
            # J - 1 = tr H + i2(H) + det H, i2 the sum of the principal 2x2 minors.
            minors = h0 * h4 - f[1] * f[3] + h0 * h8 - f[2] * f[6] + h4 * h8 - f[5] * f[7]
            det_h = (
                h0 * (h4 * h8 - f[5] * f[7])
                - f[1] * (f[3] * h8 - f[5] * f[6])
                + f[2] * (f[3] * f[7] - h4 * f[6])
            )
            excess = minors + det_h  # J - 1 - tr H
            dj = h0 + h4 + h8 + excess  # J - 1
            jac = 1.0 + dj
            m = mu[e]
            lm = lam[e]
            vol = volume[e]
            if law == LAW_STABLE:
                lp = lm + m
                # = mu/2 (I_C - 3) + lam'/2 (J - alpha)^2 - mu^2/(2 lam'), expanded in H.
                w = 0.5 * m * h_square + 0.5 * lp * dj * dj - m * excess
                dpsi = lp * dj - m + pressure[e]
                ddpsi = lp
                mm = m
                if barrier_ratio > 0.0 and jac < barrier_ratio:
                    if jac > 0.0:
                        k = barrier_modulus[e]
                        d = jac - barrier_ratio
                        ln_ratio = math.log(jac / barrier_ratio)
                        w -= k * d * d * ln_ratio
                        dpsi -= k * (2.0 * d * ln_ratio + d * d / jac)
                        ddpsi -= k * (2.0 * ln_ratio + 4.0 * d / jac - d * d / (jac * jac))
                    else:
                        w = np.inf
                        dpsi = 0.0
                        ddpsi = 0.0
                        mm = 0.0
            elif jac > 0.0:
                lnj = math.log1p(dj)
                # = mu/2 (I_C - 3) - mu ln J + lam/2 (ln J)^2, expanded in H.
                w = 0.5 * m * h_square + m * (_log1p_excess(dj) - excess) + 0.5 * lm * lnj * lnj
                dpsi = (lm * lnj - m) / jac + pressure[e]
                ddpsi = (lm * (1.0 - lnj) + m) / (jac * jac)
                mm = m
            else:
                w = np.inf
                dpsi = 0.0
                ddpsi = 0.0
                mm = 0.0
            energy[e] = vol * w
            ratio[e] = jac
            if stage == STAGE_ENERGY:
                continue
            vmu = vol * mm
            vdpsi = vol * dpsi
            for a in range(4):
                ga0 = grads[e, a, 0]
                ga1 = grads[e, a, 1]
                ga2 = grads[e, a, 2]
                cga0 = c00 * ga0 + c01 * ga1 + c02 * ga2
                cga1 = c10 * ga0 + c11 * ga1 + c12 * ga2
                cga2 = c20 * ga0 + c21 * ga1 + c22 * ga2
                fga0 = f[0] * ga0 + f[1] * ga1 + f[2] * ga2
                fga1 = f[3] * ga0 + f[4] * ga1 + f[5] * ga2
                fga2 = f[6] * ga0 + f[7] * ga1 + f[8] * ga2
                tet_forces[e, 3 * a] = vmu * fga0 + vdpsi * cga0
                tet_forces[e, 3 * a + 1] = vmu * fga1 + vdpsi * cga1
                tet_forces[e, 3 * a + 2] = vmu * fga2 + vdpsi * cga2
                if stage == STAGE_TANGENT:
                    cofactor_grads[e, 3 * a] = cga0
                    cofactor_grads[e, 3 * a + 1] = cga1
                    cofactor_grads[e, 3 * a + 2] = cga2
            if stage != STAGE_TANGENT:
                continue
            coef[e, 0] = vmu
            coef[e, 1] = vdpsi
            coef[e, 2] = vol * ddpsi
            for pair in range(6):
                a = PAIRS[pair, 0]
                c = PAIRS[pair, 1]
                ga0 = grads[e, a, 0]
                ga1 = grads[e, a, 1]
                ga2 = grads[e, a, 2]
                gc0 = grads[e, c, 0]
                gc1 = grads[e, c, 1]
                gc2 = grads[e, c, 2]
                # w = F (G_a x G_c); zero when a == c, negated when a and c swap.
                x0 = ga1 * gc2 - ga2 * gc1
                x1 = ga2 * gc0 - ga0 * gc2
                x2 = ga0 * gc1 - ga1 * gc0
                pair_vector[e, 3 * pair] = vdpsi * (f[0] * x0 + f[1] * x1 + f[2] * x2)
                pair_vector[e, 3 * pair + 1] = vdpsi * (f[3] * x0 + f[4] * x1 + f[5] * x2)
                pair_vector[e, 3 * pair + 2] = vdpsi * (f[6] * x0 + f[7] * x1 + f[8] * x2)
            if project:
                count = 0
                if mm > 0.0:
                    count = negative_modes(f, mm, dpsi, ddpsi, scratch, vec, values, matrices)
                mode_count[e] = count
                for k in range(count):
                    amp = math.sqrt(-vol * values[k])
                    for a in range(4):
                        g0 = grads[e, a, 0]
                        g1 = grads[e, a, 1]
                        g2 = grads[e, a, 2]
                        for i in range(3):
                            mode_vector[e, k, 3 * a + i] = amp * (
                                matrices[k, 3 * i] * g0
                                + matrices[k, 3 * i + 1] * g1
                                + matrices[k, 3 * i + 2] * g2
                            )
