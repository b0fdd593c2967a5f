"""Compiled vector loops: dot products, norms, a CSR product, subtracting weighted columns.

Vector reductions run in these compiled loops rather than through numpy's BLAS (``@`` and
``np.linalg.norm`` on 1-D arrays, a tall matrix times a vector): OpenBLAS hands vectors of more
than about 10^4 entries to its worker threads, and on a small, busy machine waking them costs
milliseconds a call, more than the rest of a Newton step on the phantom's middle meshes; a
serial loop over the same entries takes microseconds.

Arrays are 1-D float64 of one length n (a system's unknowns) unless said otherwise;
``constrained`` is an (n,) bool mask of the known dofs.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numpy.typing import NDArray

from tissue.threads import parallel_kernel


@parallel_kernel
def spmv(indptr, indices, data, x, out):  # pragma: no cover - compiled
    """out = A x for a CSR matrix A (n, n) given by its three arrays."""
    for row in numba.prange(indptr.shape[0] - 1):
        acc = 0.0
        for k in range(indptr[row], indptr[row + 1]):
            acc += data[k] * x[indices[k]]
        out[row] = acc


@numba.njit(cache=True)
def dot(a, b):  # pragma: no cover - compiled
    """a . b, summed in index order."""
    acc = 0.0
    for i in range(a.shape[0]):
        acc += a[i] * b[i]
    return acc


def vector_norm(x: NDArray[np.float64]) -> float:
    """Euclidean norm of a 1-D float64 array, in a serial loop (not BLAS: see the module
    docstring)."""
    return math.sqrt(dot(x, x))


@numba.njit(cache=True)
def free_square_norm(x, constrained):  # pragma: no cover - compiled
    """Sum of x_i^2 over the free (not constrained) entries."""
    acc = 0.0
    for i in range(x.shape[0]):
        if not constrained[i]:
            acc += x[i] * x[i]
    return acc


@numba.njit(cache=True)
def subtract_columns(z, columns, slots, weights):  # pragma: no cover - compiled
    """z -= columns[:, slots] @ weights, column by column (contiguous in a column-major
    array), in one serial loop: a BLAS product of the tall matrix would wake OpenBLAS's
    threads, and gathering the columns would copy them. Shapes: z (n,), columns (n, m)
    column-major, slots (k,) int, weights (k,)."""
    for j in range(slots.shape[0]):
        column = slots[j]
        weight = weights[j]
        for i in range(z.shape[0]):
            z[i] -= columns[i, column] * weight
