"""Numba kernels for linear-tet hyperelasticity: element pass, row-parallel assembly, ANP.

This module holds the hot loops behind :class:`tissue.fem.elasticity.Elasticity`; it has no
public API of its own (the class is the contract). Conventions:

* ``grads[e, a]`` is the rest gradient of shape function a of tet e, dN_a/dX [1/m], so
  that F = sum_a x_a grads[e, a]^T (one integration point).
* 3x3 matrices are stored flat, row-major: ``M[3 i + j] = M_ij``.
* The stiffness matrix is CSR with 3x3 node blocks laid out row by row: node row b owns
  the CSR rows 3b..3b+2, and its ``nb`` block columns (sorted node indices) give every one
  of those rows the columns 3c, 3c+1, 3c+2 for each neighbour c. Entry (i, k) of the
  block at position p of node row b therefore sits at
  ``9 * block_ptr[b] + i * 3 * nb + 3 * p + k`` in the data array.

Assembly is a GATHER over node rows (``prange`` over nodes, visited in a spatially
coherent order, with the tets sorted to match, which halves the time on large meshes by
keeping the per-tet data in cache while its four nodes are visited): each node row sums the
contributions of the tets (and ANP patches) touching it, so no two threads ever write the
same entry and no atomics are needed. Each 3x3 block is summed in registers over its list
of tet contributions (the tets holding both nodes, in element order) and stored once. The
per-tet quantities the gather needs (cof F G_a, F (G_a x G_c), three scalars) are computed
once per tet by the element pass; the 12x12 element matrices are never stored. Because
every block is summed in the same (sorted) element order and the block formulas are
exactly antisymmetric/symmetric under swapping the two nodes, the assembled matrix is
bitwise symmetric; fastmath is therefore off (FMA contraction would break that).

Energy structure shared by both laws: W(F) = mu/2 (I_C - 3) + psi(J), so that

    P = mu F + psi'(J) cof F,
    dP/dF = mu I_9 + psi''(J) vec(cof F) vec(cof F)^T + psi'(J) d2J/dF2,

and the element block of nodes a, c is (V = rest volume)

    K_ac = V [mu (G_a . G_c) I_3 + psi'' (cof F G_a)(cof F G_c)^T + psi' S(F (G_a x G_c))],

with S(w)_ik = eps_ikm w_m, since d2J/dF_ij dF_kl = eps_ikm eps_jln F_mn.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from numpy.typing import NDArray

from tissue.threads import parallel_kernel

LAW_STABLE = 0
LAW_CLASSIC = 1

# At most 3 twist/flip modes (one per pair can be negative) and 3 scaling modes.
MAX_NEGATIVE_MODES = 6
# Eigenvalues of dP/dF below -this * mu are clamped; smaller ones are round-off.
_CLAMP_TOLERANCE = 1e-12
# Tets per parallel chunk: scratch arrays are allocated once per chunk, not per tet.
_CHUNK = 256


def shape_gradients(
    nodes: NDArray[np.float64], tets: NDArray[np.int64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Rest shape-function gradients and volumes of linear tets.

    Args:
        nodes: rest positions [m], shape (node_count, 3).
        tets: positively oriented node indices, shape (tet_count, 4).

    Returns:
        grads: dN_a/dX [1/m], shape (tet_count, 4, 3).
        volumes: rest volumes V [m^3], shape (tet_count,).
    """
    x0 = nodes[tets[:, 0]]
    # Dm has the edge vectors as columns; F = Ds Dm^-1, so row a-1 of Dm^-1 is grad N_a.
    dm = np.stack([nodes[tets[:, k]] - x0 for k in (1, 2, 3)], axis=2)
    dm_inv = np.linalg.inv(dm)
    grads = np.empty((tets.shape[0], 4, 3))
    grads[:, 1:, :] = dm_inv
    grads[:, 0, :] = -dm_inv.sum(axis=1)
    volumes = np.linalg.det(dm) / 6.0
    return grads, volumes


# ----------------------------------------------------------------------------------------
# Small dense helpers (3x3)


@nb.njit(cache=True, fastmath=False)
def _sym3_eigen(a: np.ndarray, w: np.ndarray, v: np.ndarray, r: np.ndarray) -> None:
    """Cyclic Jacobi eigen-decomposition of a symmetric 3x3 ``a`` (destroyed).

    Robust for repeated eigenvalues (near the rest state all singular values are 1), which
    closed-form cubic solutions are not. Writes eigenvalues to ``w`` (3,), unsorted, and
    eigenvectors as the columns of ``v`` (3, 3); ``r`` is (3, 3) scratch.
    """
    for i in range(3):
        for j in range(3):
            v[i, j] = 1.0 if i == j else 0.0
    for _sweep in range(50):
        off = a[0, 1] * a[0, 1] + a[0, 2] * a[0, 2] + a[1, 2] * a[1, 2]
        diag = a[0, 0] * a[0, 0] + a[1, 1] * a[1, 1] + a[2, 2] * a[2, 2]
        if off <= 1e-32 * diag or off == 0.0:
            break
        for pair in range(3):
            p = 0 if pair < 2 else 1
            q = 1 if pair == 0 else 2
            apq = a[p, q]
            if apq == 0.0:
                continue
            theta = (a[q, q] - a[p, p]) / (2.0 * apq)
            t = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
            if theta < 0.0:
                t = -t
            c = 1.0 / math.sqrt(t * t + 1.0)
            s = t * c
            # a <- R^T a R and v <- v R, R the plane rotation that zeroes a[p, q].
            for i in range(3):
                aip = a[i, p]
                aiq = a[i, q]
                r[i, p] = c * aip - s * aiq
                r[i, q] = s * aip + c * aiq
                r[i, 3 - p - q] = a[i, 3 - p - q]
            for j in range(3):
                rpj = r[p, j]
                rqj = r[q, j]
                a[p, j] = c * rpj - s * rqj
                a[q, j] = s * rpj + c * rqj
                a[3 - p - q, j] = r[3 - p - q, j]
            a[p, q] = 0.0
            a[q, p] = 0.0
            for i in range(3):
                vip = v[i, p]
                viq = v[i, q]
                v[i, p] = c * vip - s * viq
                v[i, q] = s * vip + c * viq
    for i in range(3):
        w[i] = a[i, i]


# The closed-form 3x3 eigen-solver below is used when every eigenvalue gap is at least this
# fraction of the largest |eigenvalue|; closer ones go to the Jacobi iteration.
_CLOSED_FORM_GAP = 1e-3


@nb.njit(inline="always", cache=True, fastmath=False)
def _eigenvector(a: np.ndarray, lam: float, v: np.ndarray, column: int) -> bool:
    """Unit eigenvector of symmetric 3x3 ``a`` for the simple eigenvalue ``lam`` into column
    ``column`` of ``v``: the longest cross product of two rows of a - lam I (each row is
    orthogonal to it). Returns False when every cross product vanishes."""
    best = 0.0
    b0 = 0.0
    b1 = 0.0
    b2 = 0.0
    for pair in range(3):
        i = 0 if pair < 2 else 1
        j = 1 if pair == 0 else 2
        r0 = a[i, 0] - (lam if i == 0 else 0.0)
        r1 = a[i, 1] - (lam if i == 1 else 0.0)
        r2 = a[i, 2] - (lam if i == 2 else 0.0)
        s0 = a[j, 0] - (lam if j == 0 else 0.0)
        s1 = a[j, 1] - (lam if j == 1 else 0.0)
        s2 = a[j, 2] - (lam if j == 2 else 0.0)
        c0 = r1 * s2 - r2 * s1
        c1 = r2 * s0 - r0 * s2
        c2 = r0 * s1 - r1 * s0
        size = c0 * c0 + c1 * c1 + c2 * c2
        if size > best:
            best = size
            b0 = c0
            b1 = c1
            b2 = c2
    if best <= 0.0:
        return False
    norm = math.sqrt(best)
    v[0, column] = b0 / norm
    v[1, column] = b1 / norm
    v[2, column] = b2 / norm
    return True


@nb.njit(cache=True, fastmath=False)
def _sym3_eigen_fast(a: np.ndarray, w: np.ndarray, v: np.ndarray, r: np.ndarray) -> None:
    """As :func:`_sym3_eigen` (same arguments; ``a`` destroyed), in closed form where the
    eigenvalues are well apart: the trigonometric solution of the characteristic cubic
    (Smith 1961), eigenvectors as cross products of rows of a - lambda I for the largest and
    smallest, the middle one completing a right-handed basis. Near-repeated eigenvalues
    (within :data:`_CLOSED_FORM_GAP`, where those cross products lose accuracy: every tet
    near rest) go to the Jacobi iteration. Measured on 26,854 deformation gradients 5 %
    from identity: the Jacobi iteration took 33 ms for all, 3-4 sweeps each."""
    off = a[0, 1] * a[0, 1] + a[0, 2] * a[0, 2] + a[1, 2] * a[1, 2]
    q = (a[0, 0] + a[1, 1] + a[2, 2]) / 3.0
    d0 = a[0, 0] - q
    d1 = a[1, 1] - q
    d2 = a[2, 2] - q
    spread = d0 * d0 + d1 * d1 + d2 * d2 + 2.0 * off
    if off == 0.0 or spread == 0.0:
        _sym3_eigen(a, w, v, r)
        return
    p = math.sqrt(spread / 6.0)
    # det((a - q I) / p) / 2, the cosine of three times the angle of the largest root.
    det = (
        d0 * (d1 * d2 - a[1, 2] * a[1, 2])
        - a[0, 1] * (a[0, 1] * d2 - a[1, 2] * a[0, 2])
        + a[0, 2] * (a[0, 1] * a[1, 2] - d1 * a[0, 2])
    ) / (2.0 * p * p * p)
    det = min(1.0, max(-1.0, det))
    phi = math.acos(det) / 3.0
    largest = q + 2.0 * p * math.cos(phi)
    smallest = q + 2.0 * p * math.cos(phi + 2.0 * math.pi / 3.0)
    middle = 3.0 * q - largest - smallest
    scale = max(abs(largest), abs(smallest))
    gap = min(largest - middle, middle - smallest)
    if gap < _CLOSED_FORM_GAP * scale:
        _sym3_eigen(a, w, v, r)
        return
    if not (_eigenvector(a, largest, v, 0) and _eigenvector(a, smallest, v, 2)):
        _sym3_eigen(a, w, v, r)
        return
    # Re-orthogonalise the smallest against the largest, then v1 = v2 x v0 (det +1).
    dot = v[0, 0] * v[0, 2] + v[1, 0] * v[1, 2] + v[2, 0] * v[2, 2]
    for i in range(3):
        v[i, 2] -= dot * v[i, 0]
    norm = math.sqrt(v[0, 2] ** 2 + v[1, 2] ** 2 + v[2, 2] ** 2)
    for i in range(3):
        v[i, 2] /= norm
    v[0, 1] = v[1, 2] * v[2, 0] - v[2, 2] * v[1, 0]
    v[1, 1] = v[2, 2] * v[0, 0] - v[0, 2] * v[2, 0]
    v[2, 1] = v[0, 2] * v[1, 0] - v[1, 2] * v[0, 0]
    w[0] = largest
    w[1] = middle
    w[2] = smallest


@nb.njit(cache=True, fastmath=False)
def _negative_modes(
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
    _sym3_eigen_fast(c, w, vm, r)
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
    _sym3_eigen_fast(sblock, w, zm, r)
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


# ----------------------------------------------------------------------------------------
# Element pass


@parallel_kernel(fastmath=False)
def volume_ratios(x: np.ndarray, tets: np.ndarray, grads: np.ndarray, out: np.ndarray) -> None:
    """J = det F per tet into ``out`` (tet_count,), from positions x [m] (node_count, 3)."""
    tet_count = tets.shape[0]
    for chunk in nb.prange((tet_count + _CHUNK - 1) // _CHUNK):
        f = np.empty(9)
        for e in range(chunk * _CHUNK, min(tet_count, (chunk + 1) * _CHUNK)):
            _deformation(x, tets, grads, e, f)
            out[e] = (
                f[0] * (f[4] * f[8] - f[5] * f[7])
                - f[1] * (f[3] * f[8] - f[5] * f[6])
                + f[2] * (f[3] * f[7] - f[4] * f[6])
            )


@nb.njit(inline="always", cache=True, fastmath=False)
def _deformation(x: np.ndarray, tets: np.ndarray, grads: np.ndarray, e: int, f: np.ndarray) -> None:
    for i in range(9):
        f[i] = 0.0
    for a in range(4):
        n = tets[e, a]
        for i in range(3):
            xi = x[n, i]
            for j in range(3):
                f[3 * i + j] += xi * grads[e, a, j]


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


# What an element pass computes: energy and det F only, also the nodal forces, or also
# what the tangent gather needs.
STAGE_ENERGY = 0
STAGE_FORCES = 1
STAGE_TANGENT = 2
# Local node pairs (a, c), a < c, in the order of ``pair_vector``; PAIR_INDEX[a, c] is the
# pair of a != c.
PAIRS = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]], dtype=np.int64)
PAIR_INDEX = np.array([[0, 0, 1, 2], [0, 0, 3, 4], [1, 3, 0, 5], [2, 4, 5, 0]], dtype=np.int64)


def _upper_index(a: int, c: int) -> int:
    """Position of (a, c), a <= c, in the row-major upper triangle of a 4x4 matrix."""
    return 4 * a - a * (a - 1) // 2 + c - a


# The gather's tables over local nodes (a, c): offset of the pair's vector, its sign (w_ca =
# -w_ac, w_aa = 0: multiplying is exact and avoids unpredictable branches, ~15 % of the
# gather), and the column of G_a . G_c in ``rest_grad_dots``.
_PAIR_OFFSET = 3 * PAIR_INDEX
_PAIR_SIGN = np.array(
    [[0.0 if a == c else (1.0 if a < c else -1.0) for c in range(4)] for a in range(4)]
)
_DOT_COLUMN = np.array(
    [[_upper_index(min(a, c), max(a, c)) for c in range(4)] for a in range(4)], dtype=np.int64
)


def rest_grad_dots(grads: NDArray[np.float64]) -> NDArray[np.float64]:
    """G_a . G_c per tet for a <= c, row-major over the upper triangle, shape (tet_count, 10).

    Summed as (x0 y0 + x1 y1) + x2 y2, as the element blocks use it.
    """
    out = np.empty((grads.shape[0], 10))
    k = 0
    for a in range(4):
        for c in range(a, 4):
            ga, gc = grads[:, a], grads[:, c]
            out[:, k] = ga[:, 0] * gc[:, 0] + ga[:, 1] * gc[:, 1] + ga[:, 2] * gc[:, 2]
            k += 1
    return out


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
    chunk_count = (tet_count + _CHUNK - 1) // _CHUNK
    for chunk in nb.prange(chunk_count):
        scratch = np.empty((6, 3, 3))
        vec = np.empty((3, 3))
        values = np.empty(MAX_NEGATIVE_MODES)
        matrices = np.empty((MAX_NEGATIVE_MODES, 9))
        f = np.empty(9)
        for e in range(chunk * _CHUNK, min(tet_count, (chunk + 1) * _CHUNK)):
            _deformation(x, tets, grads, e, f)
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
            # tet at 1e-4 strain kept only ~8 digits, and an energy line search on a large
            # block stalled once the step's energy changes fell below that noise.
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
                    count = _negative_modes(f, mm, dpsi, ddpsi, scratch, vec, values, matrices)
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


# ----------------------------------------------------------------------------------------
# Row-parallel gathers


@parallel_kernel(fastmath=False)
def gather_forces(
    incidence_ptr: np.ndarray,
    incidence_tet: np.ndarray,
    incidence_local: np.ndarray,
    tet_forces: np.ndarray,
    node_order: np.ndarray,
    forces: np.ndarray,
) -> None:
    """Nodal forces -dE/dx [N] into ``forces``: minus the tets' contributions, summed in
    incidence order."""
    node_count = incidence_ptr.shape[0] - 1
    for chunk in nb.prange((node_count + _CHUNK - 1) // _CHUNK):
        for ordinal in range(chunk * _CHUNK, min(node_count, (chunk + 1) * _CHUNK)):
            b = node_order[ordinal]
            fx = 0.0
            fy = 0.0
            fz = 0.0
            for k in range(incidence_ptr[b], incidence_ptr[b + 1]):
                e = incidence_tet[k]
                base = 3 * incidence_local[k]
                fx -= tet_forces[e, base]
                fy -= tet_forces[e, base + 1]
                fz -= tet_forces[e, base + 2]
            forces[b, 0] = fx
            forces[b, 1] = fy
            forces[b, 2] = fz


def block_contributions(
    tets: NDArray[np.int64], block_ptr: NDArray[np.int64], tet_block_pos: NDArray[np.integer]
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Per stiffness block, the tet contributions to it, for :func:`gather_elements`.

    Args:
        tets: node indices (tet_count, 4). block_ptr: first block of each node row.
        tet_block_pos: position of node c's block in node a's row, (tet_count, 4, 4).

    Returns:
        ptr (block_count + 1,) and codes (int32 where they fit): the contributions to block q are
        codes[ptr[q]:ptr[q + 1]], each 16 e + 4 a + c (tet e, local row a, local column c),
        in increasing e.
    """
    tet_count = tets.shape[0]
    tet = np.repeat(np.arange(tet_count, dtype=np.int64), 16)
    local_row = np.tile(np.repeat(np.arange(4, dtype=np.int64), 4), tet_count)
    local_col = np.tile(np.arange(4, dtype=np.int64), 4 * tet_count)
    block = block_ptr[tets[tet, local_row]] + tet_block_pos.reshape(-1)
    order = np.argsort(block * tet_count + tet, kind="stable")
    codes = 16 * tet[order] + 4 * local_row[order] + local_col[order]
    if 16 * tet_count < 2**31:
        codes = codes.astype(np.int32)  # half the memory the gather streams through
    block_count = int(block_ptr[-1])
    ptr = np.zeros(block_count + 1, dtype=np.int64)
    np.cumsum(np.bincount(block, minlength=block_count), out=ptr[1:])
    return ptr, codes


@nb.njit(cache=True, inline="always")
def _store_block(data, pos, stride, a00, a01, a02, a10, a11, a12, a20, a21, a22):
    """Store the 3x3 block (a_ij) at ``pos`` of a node row whose CSR rows are ``stride``
    entries apart (the layout of the module docstring)."""
    data[pos] = a00
    data[pos + 1] = a01
    data[pos + 2] = a02
    pos += stride
    data[pos] = a10
    data[pos + 1] = a11
    data[pos + 2] = a12
    pos += stride
    data[pos] = a20
    data[pos + 1] = a21
    data[pos + 2] = a22


@parallel_kernel(fastmath=False)
def gather_elements(
    block_ptr: np.ndarray,
    block_cols: np.ndarray,
    mirror: np.ndarray,
    node_order: np.ndarray,
    contribution_ptr: np.ndarray,
    contributions: np.ndarray,
    grad_dots: np.ndarray,
    coef: np.ndarray,
    cofactor_grads: np.ndarray,
    pair_vector: np.ndarray,
    project: bool,
    mode_count: np.ndarray,
    mode_vector: np.ndarray,
    tet_forces: np.ndarray,
    forces: np.ndarray,
    data: np.ndarray,
) -> None:
    """Element blocks [N/m] written to ``data`` (every entry) and nodal forces -dE/dx [N]
    to ``forces``, one node row per iteration.

    Each block (b, c) is the sum, in element order, of K_ac over the tets e holding b (local
    index a) and c (see :func:`block_contributions`): the module docstring's formula from
    the element pass's per-tet quantities (G_a . G_c, cof F G_a, V psi' F (G_a x G_c)) plus,
    with ``project``, the mode corrections c_m,a c_m,c^T. Summed in registers and stored
    once (adding each contribution to memory cost ~15 % more here). The diagonal block's
    contributions (a = c) are the node's incidences in element order: its force is summed
    there, as :func:`gather_forces` does (bitwise the same).

    Only the diagonal and upper blocks (c >= b; ``block_cols[q]`` is block q's column node)
    are summed; each upper block is also stored transposed as block ``mirror[q]`` = (c, b).
    That is exactly what summing (c, b) would give: its contributions are the same tets in
    the same order and each term is the transpose of (b, c)'s (products commute, the skew
    part changes sign twice), so the matrix stays bitwise symmetric, for 10 block terms a
    tet instead of 16.
    """
    node_count = block_ptr.shape[0] - 1
    for chunk in nb.prange((node_count + _CHUNK - 1) // _CHUNK):
        for ordinal in range(chunk * _CHUNK, min(node_count, (chunk + 1) * _CHUNK)):
            b = node_order[ordinal]
            first = block_ptr[b]
            row_base = 9 * first
            stride = 3 * (block_ptr[b + 1] - first)
            fx = 0.0
            fy = 0.0
            fz = 0.0
            for q in range(first, block_ptr[b + 1]):
                c = block_cols[q]
                if c < b:
                    continue  # the mirror of (c, b), stored by row c
                k00 = 0.0
                k01 = 0.0
                k02 = 0.0
                k10 = 0.0
                k11 = 0.0
                k12 = 0.0
                k20 = 0.0
                k21 = 0.0
                k22 = 0.0
                for j in range(contribution_ptr[q], contribution_ptr[q + 1]):
                    code = contributions[j]
                    e = code >> 4
                    la = (code >> 2) & 3
                    lc = code & 3
                    if la == lc:
                        fx -= tet_forces[e, 3 * la]
                        fy -= tet_forces[e, 3 * la + 1]
                        fz -= tet_forces[e, 3 * la + 2]
                    vmu = coef[e, 0]
                    vddpsi = coef[e, 2]
                    cga0 = cofactor_grads[e, 3 * la]
                    cga1 = cofactor_grads[e, 3 * la + 1]
                    cga2 = cofactor_grads[e, 3 * la + 2]
                    cgc0 = cofactor_grads[e, 3 * lc]
                    cgc1 = cofactor_grads[e, 3 * lc + 1]
                    cgc2 = cofactor_grads[e, 3 * lc + 2]
                    dot = vmu * grad_dots[e, _DOT_COLUMN[la, lc]]
                    sign = _PAIR_SIGN[la, lc]
                    pair = _PAIR_OFFSET[la, lc]
                    w0 = sign * pair_vector[e, pair]
                    w1 = sign * pair_vector[e, pair + 1]
                    w2 = sign * pair_vector[e, pair + 2]
                    c00 = dot + vddpsi * (cga0 * cgc0)
                    c01 = vddpsi * (cga0 * cgc1) + w2
                    c02 = vddpsi * (cga0 * cgc2) - w1
                    c10 = vddpsi * (cga1 * cgc0) - w2
                    c11 = dot + vddpsi * (cga1 * cgc1)
                    c12 = vddpsi * (cga1 * cgc2) + w0
                    c20 = vddpsi * (cga2 * cgc0) + w1
                    c21 = vddpsi * (cga2 * cgc1) - w0
                    c22 = dot + vddpsi * (cga2 * cgc2)
                    if project:
                        # Adding c_a c_c^T (c = sqrt(-V l) Q G) removes the negative modes.
                        for mode in range(mode_count[e]):
                            ca0 = mode_vector[e, mode, 3 * la]
                            ca1 = mode_vector[e, mode, 3 * la + 1]
                            ca2 = mode_vector[e, mode, 3 * la + 2]
                            cc0 = mode_vector[e, mode, 3 * lc]
                            cc1 = mode_vector[e, mode, 3 * lc + 1]
                            cc2 = mode_vector[e, mode, 3 * lc + 2]
                            c00 += ca0 * cc0
                            c01 += ca0 * cc1
                            c02 += ca0 * cc2
                            c10 += ca1 * cc0
                            c11 += ca1 * cc1
                            c12 += ca1 * cc2
                            c20 += ca2 * cc0
                            c21 += ca2 * cc1
                            c22 += ca2 * cc2
                    k00 += c00
                    k01 += c01
                    k02 += c02
                    k10 += c10
                    k11 += c11
                    k12 += c12
                    k20 += c20
                    k21 += c21
                    k22 += c22
                pos = row_base + 3 * (q - first)
                _store_block(data, pos, stride, k00, k01, k02, k10, k11, k12, k20, k21, k22)
                if c > b:
                    m = mirror[q]
                    m_first = block_ptr[c]
                    pos = 9 * m_first + 3 * (m - m_first)
                    m_stride = 3 * (block_ptr[c + 1] - m_first)
                    _store_block(data, pos, m_stride, k00, k10, k20, k01, k11, k21, k02, k12, k22)
            forces[b, 0] = fx
            forces[b, 1] = fy
            forces[b, 2] = fz


# ----------------------------------------------------------------------------------------
# Average nodal pressure (Bonet & Burton 1998)


@parallel_kernel(fastmath=False)
def anp_patch_pass(
    ratio: np.ndarray,
    patch_tet_ptr: np.ndarray,
    patch_tet: np.ndarray,
    patch_tet_weight: np.ndarray,
    patch_volume: np.ndarray,
    patch_lam: np.ndarray,
    law: int,
    project: bool,
    patch_ratio: np.ndarray,
    patch_dpsi: np.ndarray,
    patch_ddpsi: np.ndarray,
    patch_energy: np.ndarray,
) -> None:
    """Nodal volume ratio J_a, U'(J_a) [Pa], V_a U''(J_a) [J] and energy V_a U(J_a) [J].

    U(J) = lam/2 (J - 1)^2 (stable) or lam/2 (ln J)^2 (classic; J_a <= 0 gives inf and
    zero derivatives). With ``project`` a negative U'' is clamped to 0 (the nodal term
    V_a U'' gJ gJ^T is then PSD; the U' d2J part is handed to the tets, see the class).
    """
    for a in nb.prange(patch_tet_ptr.shape[0] - 1):
        ja = 0.0
        for k in range(patch_tet_ptr[a], patch_tet_ptr[a + 1]):
            ja += patch_tet_weight[k] * ratio[patch_tet[k]]
        lm = patch_lam[a]
        if law == LAW_STABLE:
            u = 0.5 * lm * (ja - 1.0) ** 2
            du = lm * (ja - 1.0)
            ddu = lm
        elif ja > 0.0:
            lnj = math.log(ja)
            u = 0.5 * lm * lnj * lnj
            du = lm * lnj / ja
            ddu = lm * (1.0 - lnj) / (ja * ja)
        else:
            u = np.inf
            du = 0.0
            ddu = 0.0
        if project and ddu < 0.0:
            ddu = 0.0
        patch_ratio[a] = ja
        patch_dpsi[a] = du
        patch_ddpsi[a] = patch_volume[a] * ddu
        patch_energy[a] = patch_volume[a] * u


@parallel_kernel(fastmath=False)
def anp_patch_gradients(
    cofactor_grads: np.ndarray,
    patch_tet_ptr: np.ndarray,
    patch_tet: np.ndarray,
    patch_tet_weight: np.ndarray,
    patch_tet_local: np.ndarray,
    patch_node_ptr: np.ndarray,
    gradient: np.ndarray,
) -> None:
    """dJ_a/dx over each patch's nodes into ``gradient`` (patch node entries, 3) [1/m].

    J_a = sum_e w_e J_e with w_e = V_e / (4 V_a), and dJ_e/dx_c = cof F_e G_c (the element
    pass's ``cofactor_grads``).
    """
    for a in nb.prange(patch_tet_ptr.shape[0] - 1):
        base = patch_node_ptr[a]
        for k in range(base, patch_node_ptr[a + 1]):
            gradient[k, 0] = 0.0
            gradient[k, 1] = 0.0
            gradient[k, 2] = 0.0
        for k in range(patch_tet_ptr[a], patch_tet_ptr[a + 1]):
            e = patch_tet[k]
            wt = patch_tet_weight[k]
            for lc in range(4):
                row = base + patch_tet_local[k, lc]
                for i in range(3):
                    gradient[row, i] += wt * cofactor_grads[e, 3 * lc + i]


@parallel_kernel(fastmath=False)
def anp_gather_blocks(
    node_patch_ptr: np.ndarray,
    node_patch: np.ndarray,
    node_patch_local: np.ndarray,
    patch_node_ptr: np.ndarray,
    patch_pair_ptr: np.ndarray,
    patch_pair_pos: np.ndarray,
    gradient: np.ndarray,
    patch_ddpsi: np.ndarray,
    block_ptr: np.ndarray,
    node_order: np.ndarray,
    data: np.ndarray,
) -> None:
    """Add the nodal terms V_a U''(J_a) gJ_a gJ_a^T to ``data``, one node row per iteration."""
    for ordinal in nb.prange(node_patch_ptr.shape[0] - 1):
        b = node_order[ordinal]
        row_base = 9 * block_ptr[b]
        stride = 3 * (block_ptr[b + 1] - block_ptr[b])
        for k in range(node_patch_ptr[b], node_patch_ptr[b + 1]):
            a = node_patch[k]
            s = patch_ddpsi[a]
            if s == 0.0:
                continue
            lb = node_patch_local[k]
            base = patch_node_ptr[a]
            n = patch_node_ptr[a + 1] - base
            # s * (ga_i * gc_k), not (s * ga_i) * gc_k: keeps K bitwise symmetric.
            ga0 = gradient[base + lb, 0]
            ga1 = gradient[base + lb, 1]
            ga2 = gradient[base + lb, 2]
            pair_base = patch_pair_ptr[a] + lb * n
            for lc in range(n):
                gc0 = gradient[base + lc, 0]
                gc1 = gradient[base + lc, 1]
                gc2 = gradient[base + lc, 2]
                pos = row_base + 3 * patch_pair_pos[pair_base + lc]
                data[pos] += s * (ga0 * gc0)
                data[pos + 1] += s * (ga0 * gc1)
                data[pos + 2] += s * (ga0 * gc2)
                data[pos + stride] += s * (ga1 * gc0)
                data[pos + stride + 1] += s * (ga1 * gc1)
                data[pos + stride + 2] += s * (ga1 * gc2)
                data[pos + 2 * stride] += s * (ga2 * gc0)
                data[pos + 2 * stride + 1] += s * (ga2 * gc1)
                data[pos + 2 * stride + 2] += s * (ga2 * gc2)


@nb.njit(cache=True)
def patch_pair_positions(
    patch_node_ptr: np.ndarray,
    patch_nodes: np.ndarray,
    block_ptr: np.ndarray,
    block_cols: np.ndarray,
    patch_pair_ptr: np.ndarray,
    out: np.ndarray,
) -> None:
    """Block position in node row patch_nodes[lb] of column patch_nodes[lc], per patch pair."""
    for a in range(patch_node_ptr.shape[0] - 1):
        base = patch_node_ptr[a]
        n = patch_node_ptr[a + 1] - base
        for lb in range(n):
            b = patch_nodes[base + lb]
            row = block_cols[block_ptr[b] : block_ptr[b + 1]]
            for lc in range(n):
                out[patch_pair_ptr[a] + lb * n + lc] = np.searchsorted(row, patch_nodes[base + lc])
