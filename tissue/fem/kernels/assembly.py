"""Row-parallel assembly of the nodal forces and the node-blocked CSR stiffness matrix.

The stiffness matrix is CSR with 3x3 node blocks laid out row by row: node row b owns the
CSR rows 3b..3b+2, and its ``nb`` block columns (sorted node indices) give every one of
those rows the columns 3c, 3c+1, 3c+2 for each neighbour c. Entry (i, k) of the block at
position p of node row b therefore sits at ``9 * block_ptr[b] + i * 3 * nb + 3 * p + k`` in
the data array.

Assembly is a GATHER over node rows (``prange`` over nodes, visited in a spatially coherent
order, with the tets sorted to match, so that the per-tet data stays in cache while its four
nodes are visited): each node row sums the contributions of the tets (and ANP patches)
touching it, so no two threads ever write the same entry and no atomics are needed. Each
3x3 block is summed in registers over its list of tet contributions (the tets holding both
nodes, in element order) and stored once. The per-tet quantities the gather needs (cof F
G_a, F (G_a x G_c), three scalars) are computed once per tet by the element pass
(:mod:`~tissue.fem.kernels.element`). Because every block is summed in the same (sorted)
element order and the block formulas are exactly antisymmetric/symmetric under swapping the
two nodes, the assembled matrix is bitwise symmetric; fastmath is therefore off (FMA
contraction would break that).
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numpy.typing import NDArray

from tissue.fem.kernels.geometry import CHUNK, PAIR_INDEX, upper_index
from tissue.threads import parallel_kernel

# The gather's tables over local nodes (a, c): offset of the pair's vector, its sign (w_ca =
# -w_ac, w_aa = 0: multiplying is exact and avoids unpredictable branches), and the column
# of G_a . G_c in ``rest_grad_dots``.
_PAIR_OFFSET = 3 * PAIR_INDEX
_PAIR_SIGN = np.array(
    [[0.0 if a == c else (1.0 if a < c else -1.0) for c in range(4)] for a in range(4)]
)
_DOT_COLUMN = np.array(
    [[upper_index(min(a, c), max(a, c)) for c in range(4)] for a in range(4)], dtype=np.int64
)


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
    for chunk in nb.prange((node_count + CHUNK - 1) // CHUNK):
        for ordinal in range(chunk * CHUNK, min(node_count, (chunk + 1) * CHUNK)):
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
    index a) and c (see :func:`block_contributions`): the formula of
    :mod:`~tissue.fem.kernels.element` from the element pass's per-tet quantities (G_a . G_c,
    cof F G_a, V psi' F (G_a x G_c)) plus, with ``project``, the mode corrections
    c_m,a c_m,c^T. Summed in registers and stored once, not added to memory contribution
    by contribution. The diagonal block's
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
    for chunk in nb.prange((node_count + CHUNK - 1) // CHUNK):
        for ordinal in range(chunk * CHUNK, min(node_count, (chunk + 1) * CHUNK)):
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
