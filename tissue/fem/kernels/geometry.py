"""Rest geometry and deformation gradient of linear tets, and the conventions shared by
every kernel of :mod:`tissue.fem.kernels`:

* ``grads[e, a]`` is the rest gradient of shape function a of tet e, dN_a/dX [1/m], so
  that F = sum_a x_a grads[e, a]^T (one integration point).
* 3x3 matrices are stored flat, row-major: ``M[3 i + j] = M_ij``.
* Local node pairs (a, c), a < c, are numbered as in :data:`PAIRS`; per-tet dot products
  G_a . G_c follow the row-major upper triangle of a 4x4 matrix (:func:`rest_grad_dots`).
* Parallel loops run over chunks of :data:`CHUNK` tets (or nodes).
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numpy.typing import NDArray

from tissue.threads import parallel_kernel

# Tets per parallel chunk: scratch arrays are allocated once per chunk, not per tet.
CHUNK = 256


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


@nb.njit(inline="always", cache=True, fastmath=False)
def deformation_gradient(
    x: np.ndarray, tets: np.ndarray, grads: np.ndarray, e: int, f: np.ndarray
) -> None:
    for i in range(9):
        f[i] = 0.0
    for a in range(4):
        n = tets[e, a]
        for i in range(3):
            xi = x[n, i]
            for j in range(3):
                f[3 * i + j] += xi * grads[e, a, j]


@parallel_kernel(fastmath=False)
def volume_ratios(x: np.ndarray, tets: np.ndarray, grads: np.ndarray, out: np.ndarray) -> None:
    """J = det F per tet into ``out`` (tet_count,), from positions x [m] (node_count, 3)."""
    tet_count = tets.shape[0]
    for chunk in nb.prange((tet_count + CHUNK - 1) // CHUNK):
        f = np.empty(9)
        for e in range(chunk * CHUNK, min(tet_count, (chunk + 1) * CHUNK)):
            deformation_gradient(x, tets, grads, e, f)
            out[e] = (
                f[0] * (f[4] * f[8] - f[5] * f[7])
                - f[1] * (f[3] * f[8] - f[5] * f[6])
                + f[2] * (f[3] * f[7] - f[4] * f[6])
            )


# Local node pairs (a, c), a < c, in the order of the element pass's ``pair_vector``;
# PAIR_INDEX[a, c] is the pair of a != c.
PAIRS = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]], dtype=np.int64)
PAIR_INDEX = np.array([[0, 0, 1, 2], [0, 0, 3, 4], [1, 3, 0, 5], [2, 4, 5, 0]], dtype=np.int64)


def upper_index(a: int, c: int) -> int:
    """Position of (a, c), a <= c, in the row-major upper triangle of a 4x4 matrix."""
    return 4 * a - a * (a - 1) // 2 + c - a


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
