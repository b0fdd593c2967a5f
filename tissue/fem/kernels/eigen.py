"""Eigen-decomposition of symmetric 3x3 matrices, for the PSD projection.

:func:`sym3_eigen_fast` solves in closed form (Smith 1961) where the eigenvalues are well
apart and falls back to the cyclic Jacobi iteration :func:`_sym3_eigen`, robust for
repeated eigenvalues, where they are not.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np


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
CLOSED_FORM_GAP = 1e-3


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
def sym3_eigen_fast(a: np.ndarray, w: np.ndarray, v: np.ndarray, r: np.ndarray) -> None:
    """As :func:`_sym3_eigen` (same arguments; ``a`` destroyed), in closed form where the
    eigenvalues are well apart: the trigonometric solution of the characteristic cubic
    (Smith 1961), eigenvectors as cross products of rows of a - lambda I for the largest and
    smallest, the middle one completing a right-handed basis. Near-repeated eigenvalues
    (within :data:`CLOSED_FORM_GAP`, where those cross products lose accuracy: every tet
    near rest) go to the Jacobi iteration, which takes several sweeps per matrix."""
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
    if gap < CLOSED_FORM_GAP * scale:
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
