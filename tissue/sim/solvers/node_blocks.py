"""Products with a symmetric matrix through its upper 3x3 node blocks.

Elasticity matrices here are node-blocked (the layout of :mod:`tissue.fem.kernels`): rows
3b, 3b+1, 3b+2 share one column list made of whole triples 3c, 3c+1, 3c+2. Such a matrix is
symmetric block by block, so a product may read its upper blocks only, each off-diagonal
block serving both triangles: half the memory traffic of a CSR product, in double precision.
On large meshes the upper blocks also stay in the last-level cache where the whole CSR matrix
does not. A matrix that is not node-blocked (a test's Laplacian) is multiplied as CSR.

:func:`node_block_product` does either, chosen by its arguments (:data:`NO_BLOCKS` for CSR): CG's
loops (:mod:`~tissue.sim.solvers.jacobi_cg`, :mod:`~tissue.sim.solvers.factor_cg`) call it
for every product. :class:`NodeBlocks` holds the blocks of one pattern; :class:`SymmetricProduct`
is a product with one fixed matrix (the integrator's rest stiffness, for its damping).

Bits: below :data:`~tissue.sim.solvers.limits.SERIAL_CG_UNKNOWNS` unknowns (where CG runs on
one thread) a block product is one part, and x . A x is summed in row order, so a product
gives the same bits whatever the thread count, also when a parallel step calls it. Above, the
blocks are split in one part per numba thread and the parts' sums follow the thread count.
"""

from __future__ import annotations

import numba
import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

import tissue.sim.solvers as solvers
from tissue.threads import parallel_kernel


@numba.njit(cache=True)
def _node_block_columns(indptr, indices, columns):  # pragma: no cover - compiled
    """Whether the pattern is node-blocked (layout of :mod:`tissue.fem.kernels`).

    That is: rows 3b, 3b+1, 3b+2 share one column list made of whole triples 3c, 3c+1,
    3c+2 (c ascending). Writes the first column 3c of each block to ``columns`` (nnz / 9,).
    """
    n = indptr.shape[0] - 1
    if n % 3 != 0 or indices.shape[0] != 9 * columns.shape[0]:
        return False
    for b in range(n // 3):
        start = indptr[3 * b]
        width = indptr[3 * b + 1] - start
        if (
            width % 3 != 0
            or indptr[3 * b + 2] - indptr[3 * b + 1] != width
            or indptr[3 * b + 3] - indptr[3 * b + 2] != width
        ):
            return False
        for block in range(width // 3):
            c = indices[start + 3 * block]
            if c % 3 != 0:
                return False
            for i in range(3):
                for k in range(3):
                    if indices[start + i * width + 3 * block + k] != c + k:
                        return False
            columns[start // 9 + block] = c
    return True


@numba.njit(cache=True)
def _count_upper_blocks(indptr, columns, upper_ptr):  # pragma: no cover - compiled
    """upper_ptr[b]: first upper block (column >= row) of node row b; returns their count."""
    count = 0
    for b in range(upper_ptr.shape[0] - 1):
        start = indptr[3 * b]
        upper_ptr[b] = count
        for block in range((indptr[3 * b + 1] - start) // 3):
            if columns[start // 9 + block] >= 3 * b:
                count += 1
    upper_ptr[upper_ptr.shape[0] - 1] = count
    return count


@parallel_kernel
def _fill_upper_blocks(
    indptr, columns, data, upper_ptr, upper_cols, upper
):  # pragma: no cover - compiled
    """Copy the upper 3x3 blocks of node row b, row-major, to upper[9 q : 9 q + 9]."""
    for b in numba.prange(upper_ptr.shape[0] - 1):
        start = indptr[3 * b]
        width = indptr[3 * b + 1] - start
        q = upper_ptr[b]
        for block in range(width // 3):
            c = columns[start // 9 + block]
            if c < 3 * b:
                continue
            upper_cols[q] = c
            for i in range(3):
                for k in range(3):
                    upper[9 * q + 3 * i + k] = data[start + i * width + 3 * block + k]
            q += 1


@parallel_kernel
def node_block_product(
    indptr, indices, data, upper_ptr, upper_cols, upper, bounds, partial, x, out
):  # pragma: no cover - compiled
    """out = A x; returns x . out.

    With node blocks (``upper_ptr`` longer than 1) only the upper 3x3 blocks are read (see
    :class:`NodeBlocks`): block (b, c) adds B x_c to row b and, off the diagonal, B^T x_b to
    row c, each of the ``partial`` rows summing its own range of node rows. Else plain CSR.
    With one part, or as CSR, the result is the same bits on any number of threads (x . A x
    is then summed serially, in row order); with several, the parts' split sets the bits.
    """
    n = out.shape[0]
    if upper_ptr.shape[0] > 1:
        parts = partial.shape[0]
        for part in numba.prange(parts):
            y = partial[part]
            y[:] = 0.0
            for b in range(bounds[part], bounds[part + 1]):
                xb0 = x[3 * b]
                xb1 = x[3 * b + 1]
                xb2 = x[3 * b + 2]
                a0 = 0.0
                a1 = 0.0
                a2 = 0.0
                for q in range(upper_ptr[b], upper_ptr[b + 1]):
                    c = upper_cols[q]
                    o = 9 * q
                    x0 = x[c]
                    x1 = x[c + 1]
                    x2 = x[c + 2]
                    a0 += upper[o] * x0 + upper[o + 1] * x1 + upper[o + 2] * x2
                    a1 += upper[o + 3] * x0 + upper[o + 4] * x1 + upper[o + 5] * x2
                    a2 += upper[o + 6] * x0 + upper[o + 7] * x1 + upper[o + 8] * x2
                    if c != 3 * b:
                        y[c] += upper[o] * xb0 + upper[o + 3] * xb1 + upper[o + 6] * xb2
                        y[c + 1] += upper[o + 1] * xb0 + upper[o + 4] * xb1 + upper[o + 7] * xb2
                        y[c + 2] += upper[o + 2] * xb0 + upper[o + 5] * xb1 + upper[o + 8] * xb2
                y[3 * b] += a0
                y[3 * b + 1] += a1
                y[3 * b + 2] += a2
        total = 0.0
        if parts == 1:
            # One part (a small system): x . A x in row order, not a parallel reduction
            # whose per-thread sums would follow the thread count.
            y = partial[0]
            for i in range(n):
                out[i] = y[i]
                total += x[i] * y[i]
            return total
        for i in numba.prange(n):
            acc = 0.0
            for part in range(parts):
                acc += partial[part, i]
            out[i] = acc
            total += x[i] * acc
        return total
    for row in numba.prange(n):
        acc = 0.0
        for k in range(indptr[row], indptr[row + 1]):
            acc += data[k] * x[indices[k]]
        out[row] = acc
    # x . A x in row order, whatever the thread count (a parallel reduction's would not be).
    total = 0.0
    for row in range(n):
        total += x[row] * out[row]
    return total


class NodeBlocks:
    """The upper 3x3 blocks of a symmetric node-blocked matrix, for the products of CG.

    A product then reads half the matrix (each off-diagonal block serves both triangles; see
    the module docstring). Built once per pattern; the values are copied from the CSR data
    before each solve (about the cost of one CSR product).

    Attributes:
        indptr: the CSR row pointers of the pattern, (n + 1,).
        columns: the first column 3c of each 3x3 block of the CSR pattern, (nnz / 9,).
        upper_ptr: the first upper block (column >= row) of each node row, (n / 3 + 1,).
        upper_cols: the first column 3c of each upper block, (number of upper blocks,).
        upper: the upper blocks' values, row-major, 9 per block.
        bounds: the node rows each part of a product sums, parts + 1 boundaries (one part
            below :data:`~tissue.sim.solvers.limits.SERIAL_CG_UNKNOWNS` unknowns, else one per
            numba thread when built; parts hold about the same number of blocks).
        partial: each part's partial result, (parts, n).
    """

    def __init__(self, indptr: NDArray[np.integer], columns: NDArray[np.int32]) -> None:
        node_count = (indptr.shape[0] - 1) // 3
        self.indptr = indptr
        self.columns = columns
        self.upper_ptr = np.empty(node_count + 1, dtype=np.int64)
        count = _count_upper_blocks(indptr, columns, self.upper_ptr)
        self.upper_cols = np.empty(count, dtype=np.int32)
        self.upper = np.empty(9 * count)
        # One partial result per part; parts hold about the same number of blocks. A system
        # small enough for CG to run on one thread gets one part: its products then give the
        # same bits on any number of threads (a split sums each row in pieces, and the pieces
        # would follow the thread count), and CG's serial products skip summing the parts.
        if 3 * node_count < solvers.SERIAL_CG_UNKNOWNS:
            parts = 1
        else:
            parts = max(1, min(numba.get_num_threads(), node_count))
        self.bounds = np.searchsorted(self.upper_ptr, np.linspace(0, count, parts + 1))
        self.bounds = np.clip(self.bounds, 0, node_count).astype(np.int64)
        self.bounds[0], self.bounds[-1] = 0, node_count
        self.partial = np.empty((parts, 3 * node_count))

    @classmethod
    def of(cls, matrix: sp.csr_matrix) -> NodeBlocks | None:
        """The blocks of ``matrix``'s pattern, or None if it is not node-blocked."""
        if matrix.indices.shape[0] % 9 != 0:
            return None
        columns = np.empty(matrix.indices.shape[0] // 9, dtype=np.int32)
        if not _node_block_columns(matrix.indptr, matrix.indices, columns):
            return None
        return cls(matrix.indptr, columns)

    def fill(self, data: NDArray[np.float64]) -> None:
        """Copy the upper blocks' values from the CSR ``data`` (nnz,) of the pattern."""
        _fill_upper_blocks(
            self.indptr, self.columns, data, self.upper_ptr, self.upper_cols, self.upper
        )

    def arguments(self) -> tuple[NDArray, NDArray, NDArray, NDArray, NDArray]:
        """The block arguments of :func:`node_block_product` (as :data:`NO_BLOCKS` for CSR)."""
        return self.upper_ptr, self.upper_cols, self.upper, self.bounds, self.partial


class SymmetricProduct:
    """y = A x for a symmetric CSR matrix whose values do not change after this is built,
    through its upper node blocks where it is node-blocked (about 3x faster than a CSR
    product), else as CSR.

    Args:
        matrix: the matrix, (n, n), sorted indices; its values are copied now.
    """

    def __init__(self, matrix: sp.csr_matrix) -> None:
        self.matrix = matrix
        self.blocks = NodeBlocks.of(matrix)
        if self.blocks is not None:
            self.blocks.fill(matrix.data)

    def __call__(self, x: NDArray[np.float64], out: NDArray[np.float64]) -> float:
        """Write A x to ``out`` (n,); returns x . A x."""
        return matrix_product(self.matrix, self.blocks, x, out)


def matrix_product(
    matrix: sp.csr_matrix,
    blocks: NodeBlocks | None,
    x: NDArray[np.float64],
    out: NDArray[np.float64],
) -> float:
    """out = A x through ``blocks`` (holding A's values) where given, else as CSR; x . A x."""
    upper_ptr, upper_cols, upper, bounds, partial = (
        blocks.arguments() if blocks is not None else NO_BLOCKS
    )
    return float(
        node_block_product(
            matrix.indptr,
            matrix.indices,
            matrix.data,
            upper_ptr,
            upper_cols,
            upper,
            bounds,
            partial,
            x,
            out,
        )
    )


# The block arguments of node_block_product when there are no blocks (plain CSR products).
NO_BLOCKS = (
    np.zeros(1, dtype=np.int64),
    np.zeros(0, dtype=np.int32),
    np.zeros(0),
    np.zeros(1, dtype=np.int64),
    np.zeros((1, 1)),
)
