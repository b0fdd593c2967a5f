"""Average nodal pressure (Bonet & Burton 1998): the anti-locking patch kernels.

The volumetric energy moves from the tets to the nodes: each patch a (the tets of one region
around a node) has the volume ratio J_a = sum_e w_e J_e (w_e = V_e / (4 V_a)) and the energy
V_a U(J_a), U carrying lam. A tet's share, the mean of its nodes' U'(J_a), enters the
element pass as its ``pressure``; the nodal tangent V_a U''(J_a) gJ_a gJ_a^T is added to the
assembled matrix node row by node row. :class:`tissue.fem.elasticity.Elasticity` derives
the split.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from tissue.fem.kernels.element import LAW_STABLE
from tissue.threads import parallel_kernel


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
