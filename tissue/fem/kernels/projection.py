"""PSD projection of the element tangents: the negative eigenpairs of dP/dF.

The element pass (:func:`~tissue.fem.kernels.element.element_pass`) turns each negative
mode (eigenvalue l < 0, unit eigen-matrix Q) into the 12-vector c = sqrt(-V l) Q G, and the
assembly adds c c^T, which lifts that eigenvalue of the element matrix to zero.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from tissue.fem.kernels.eigen import sym3_eigen_fast

# At most 3 twist/flip modes (one per pair can be negative) and 3 scaling modes.
MAX_NEGATIVE_MODES = 6
# Eigenvalues of dP/dF below -this * mu are clamped; smaller ones are round-off.
_CLAMP_TOLERANCE = 1e-12


@nb.njit(cache=True, fastmath=False)
def negative_modes(
    f: np.ndarray,
    mu: float,
    dpsi: float,
    ddpsi: float,
    scratch: np.ndarray,
    vec: np.ndarray,
    out_value: np.ndarray,
    out_matrix: np.ndarray,
) -> int:
    """Negative eigenpairs of dP/dF for W = mu/2 (I_C - 3) + psi(J) (Smith et al. 2018).

    In the rotation-variant SVD F = U diag(s) V^T (U, V rotations, s_2 signed), dP/dF is
    block diagonal (Smith, de Goes & Kim 2018, ACM TOG 37(2):12, sec. 4-5):

    * for each pair (i, j) with third index k, a twist mode Q = (u_i v_j^T - u_j v_i^T)/sqrt2
      with eigenvalue mu + psi' s_k and a flip mode Q = (u_i v_j^T + u_j v_i^T)/sqrt2 with
      eigenvalue mu - psi' s_k;
    * three scaling modes Q = sum_k z_k u_k v_k^T, z the eigenvectors of the 3x3 matrix
      mu I + psi'' g g^T + psi' A, g = (s1 s2, s0 s2, s0 s1), A = [[0,s2,s1],[s2,0,s0],[s1,s0,0]].

    A sufficient PSD test runs first: with psi'' >= 0 all eigenvalues are >= mu - 2 |psi'|
    s_max (Gershgorin on A), and s_max^2 <= the Gershgorin bound of C = F^T F. Near rest
    the twist eigenvalues mu (1 - s_k) are ~0 and of either sign, so most deformed tets
    need the (cheap, 3x3 Jacobi) decomposition anyway.

    Args:
        f: F, flat row-major (9,).
        mu, dpsi, ddpsi: mu [Pa], psi'(J) [Pa], psi''(J) [Pa].
        scratch: (6, 3, 3) and vec: (3, 3) work space.
        out_value: eigenvalues < 0 [Pa], (MAX_NEGATIVE_MODES,).
        out_matrix: their unit eigen-matrices Q, flat row-major, (MAX_NEGATIVE_MODES, 9).

    Returns:
        the number of negative modes written.
    """
    c = scratch[0]
    vm = scratch[1]
    um = scratch[2]
    r = scratch[3]
    sblock = scratch[4]
    zm = scratch[5]
    for i in range(3):
        for j in range(3):
            c[i, j] = f[i] * f[j] + f[3 + i] * f[3 + j] + f[6 + i] * f[6 + j]
    gersh = 0.0
    for i in range(3):
        row = abs(c[i, 0]) + abs(c[i, 1]) + abs(c[i, 2])
        gersh = max(gersh, row)
    if ddpsi >= 0.0 and 2.0 * abs(dpsi) * math.sqrt(gersh) <= mu:
        return 0
    w = vec[0]
    sym3_eigen_fast(c, w, vm, r)
    # Sort descending (insertion sort on 3 entries), carrying the eigenvector columns.
    for i in range(1, 3):
        j = i
        while j > 0 and w[j] > w[j - 1]:
            w[j], w[j - 1] = w[j - 1], w[j]
            for k in range(3):
                vm[k, j], vm[k, j - 1] = vm[k, j - 1], vm[k, j]
            j -= 1
    det_v = (
        vm[0, 0] * (vm[1, 1] * vm[2, 2] - vm[1, 2] * vm[2, 1])
        - vm[0, 1] * (vm[1, 0] * vm[2, 2] - vm[1, 2] * vm[2, 0])
        + vm[0, 2] * (vm[1, 0] * vm[2, 1] - vm[1, 1] * vm[2, 0])
    )
    if det_v < 0.0:
        for k in range(3):
            vm[k, 2] = -vm[k, 2]
    # F v_k, columns of r.
    for k in range(3):
        for i in range(3):
            r[i, k] = f[3 * i] * vm[0, k] + f[3 * i + 1] * vm[1, k] + f[3 * i + 2] * vm[2, k]
    scale = math.sqrt(max(w[0], 0.0) + max(w[1], 0.0) + max(w[2], 0.0))
    s = vec[1]
    s[0] = 0.0
    s[1] = 0.0
    s[2] = 0.0
    if scale == 0.0:
        for i in range(3):
            for j in range(3):
                um[i, j] = vm[i, j]
    else:
        n0 = math.sqrt(r[0, 0] ** 2 + r[1, 0] ** 2 + r[2, 0] ** 2)
        for i in range(3):
            um[i, 0] = r[i, 0] / n0
        s[0] = n0
        d = um[0, 0] * r[0, 1] + um[1, 0] * r[1, 1] + um[2, 0] * r[2, 1]
        for i in range(3):
            um[i, 1] = r[i, 1] - d * um[i, 0]
        n1 = math.sqrt(um[0, 1] ** 2 + um[1, 1] ** 2 + um[2, 1] ** 2)
        if n1 > 1e-12 * scale:
            for i in range(3):
                um[i, 1] /= n1
            s[1] = n1
        else:
            # F is (nearly) rank one: any unit vector orthogonal to u0 completes U.
            k = 0
            if abs(um[1, 0]) < abs(um[k, 0]):
                k = 1
            if abs(um[2, 0]) < abs(um[k, 0]):
                k = 2
            e = vec[2]
            e[0] = 0.0
            e[1] = 0.0
            e[2] = 0.0
            e[k] = 1.0
            d = um[k, 0]
            for i in range(3):
                um[i, 1] = e[i] - d * um[i, 0]
            n1 = math.sqrt(um[0, 1] ** 2 + um[1, 1] ** 2 + um[2, 1] ** 2)
            for i in range(3):
                um[i, 1] /= n1
            s[1] = 0.0
        um[0, 2] = um[1, 0] * um[2, 1] - um[2, 0] * um[1, 1]
        um[1, 2] = um[2, 0] * um[0, 1] - um[0, 0] * um[2, 1]
        um[2, 2] = um[0, 0] * um[1, 1] - um[1, 0] * um[0, 1]
        # Signed: negative for an inverted tet, so that J = s0 s1 s2 with U, V rotations.
        s[2] = um[0, 2] * r[0, 2] + um[1, 2] * r[1, 2] + um[2, 2] * r[2, 2]

    tol = -_CLAMP_TOLERANCE * mu
    count = 0
    inv_sqrt2 = 1.0 / math.sqrt(2.0)
    for pair in range(3):
        i = 0 if pair < 2 else 1
        j = 1 if pair == 0 else 2
        k = 3 - i - j
        for sign in (-1.0, 1.0):
            # sign -1: twist (antisymmetric), eigenvalue mu + psi' s_k; +1: flip.
            lam = mu - sign * dpsi * s[k]
            if lam < tol and count < MAX_NEGATIVE_MODES:
                out_value[count] = lam
                for p in range(3):
                    for q in range(3):
                        out_matrix[count, 3 * p + q] = inv_sqrt2 * (
                            um[p, i] * vm[q, j] + sign * um[p, j] * vm[q, i]
                        )
                count += 1
    g0 = s[1] * s[2]
    g1 = s[0] * s[2]
    g2 = s[0] * s[1]
    sblock[0, 0] = mu + ddpsi * g0 * g0
    sblock[1, 1] = mu + ddpsi * g1 * g1
    sblock[2, 2] = mu + ddpsi * g2 * g2
    sblock[0, 1] = sblock[1, 0] = ddpsi * g0 * g1 + dpsi * s[2]
    sblock[0, 2] = sblock[2, 0] = ddpsi * g0 * g2 + dpsi * s[1]
    sblock[1, 2] = sblock[2, 1] = ddpsi * g1 * g2 + dpsi * s[0]
    # Sylvester: positive leading minors mean positive definite, nothing to clamp.
    minor2 = sblock[0, 0] * sblock[1, 1] - sblock[0, 1] * sblock[0, 1]
    minor3 = (
        sblock[0, 0] * (sblock[1, 1] * sblock[2, 2] - sblock[1, 2] * sblock[1, 2])
        - sblock[0, 1] * (sblock[0, 1] * sblock[2, 2] - sblock[1, 2] * sblock[0, 2])
        + sblock[0, 2] * (sblock[0, 1] * sblock[1, 2] - sblock[1, 1] * sblock[0, 2])
    )
    if sblock[0, 0] > 0.0 and minor2 > 0.0 and minor3 > 0.0:
        return count
    sym3_eigen_fast(sblock, w, zm, r)
    for m in range(3):
        if w[m] < tol and count < MAX_NEGATIVE_MODES:
            out_value[count] = w[m]
            for p in range(3):
                for q in range(3):
                    out_matrix[count, 3 * p + q] = (
                        zm[0, m] * um[p, 0] * vm[q, 0]
                        + zm[1, m] * um[p, 1] * vm[q, 1]
                        + zm[2, m] * um[p, 2] * vm[q, 2]
                    )
            count += 1
    return count
