"""The B-mode imager's compiled kernels: pixels located in the deformed tets, labelled by
their material coordinates, and the material-attached complex reflectivity."""

from __future__ import annotations

import math

import numba
import numpy as np

from envs.ultrasound.config import LESION_FIRST_LABEL, OUTSIDE, SKIN, TISSUE

#: Hashed lattice values: a table of ``1 << TABLE_BITS`` complex Gaussians.
TABLE_BITS = 16


@numba.njit(cache=True)
def locate_pixels(local, tets, lateral, depth, tet_of, weights):  # pragma: no cover
    """For each pixel (lateral[j], depth[i], 0) of the probe frame, the tet holding it
    (tet_of[i, j], -1 if none) and its barycentric weights there; ``local`` are the node
    positions in the probe frame. Only tets cut by the plane z = 0 are visited."""
    tet_of[:] = -1
    u0, du = lateral[0], lateral[1] - lateral[0]
    v0, dv = depth[0], depth[1] - depth[0]
    cols, rows = lateral.size, depth.size
    tolerance = 1e-10
    for t in range(tets.shape[0]):
        n0, n1, n2, n3 = tets[t, 0], tets[t, 1], tets[t, 2], tets[t, 3]
        z0, z1, z2, z3 = local[n0, 2], local[n1, 2], local[n2, 2], local[n3, 2]
        if min(z0, z1, z2, z3) > 0.0 or max(z0, z1, z2, z3) < 0.0:
            continue
        # Bounding box of the cut polygon: nodes on the plane and edge crossings.
        umin, umax, vmin, vmax = np.inf, -np.inf, np.inf, -np.inf
        for a in range(4):
            na = tets[t, a]
            za = local[na, 2]
            if za == 0.0:
                umin, umax = min(umin, local[na, 0]), max(umax, local[na, 0])
                vmin, vmax = min(vmin, local[na, 1]), max(vmax, local[na, 1])
            for b in range(a + 1, 4):
                nb = tets[t, b]
                zb = local[nb, 2]
                if (za < 0.0 < zb) or (zb < 0.0 < za):
                    s = za / (za - zb)
                    u = local[na, 0] + s * (local[nb, 0] - local[na, 0])
                    v = local[na, 1] + s * (local[nb, 1] - local[na, 1])
                    umin, umax = min(umin, u), max(umax, u)
                    vmin, vmax = min(vmin, v), max(vmax, v)
        j_lo = max(0, math.ceil((umin - u0) / du - 1e-9))
        j_hi = min(cols - 1, math.floor((umax - u0) / du + 1e-9))
        i_lo = max(0, math.ceil((vmin - v0) / dv - 1e-9))
        i_hi = min(rows - 1, math.floor((vmax - v0) / dv + 1e-9))
        if j_lo > j_hi or i_lo > i_hi:
            continue
        # Rows of the inverse of the edge matrix [e1 e2 e3]: barycentrics 1-3.
        e = np.empty((3, 3))
        for k in range(3):
            for d in range(3):
                e[k, d] = local[tets[t, k + 1], d] - local[n0, d]
        c1 = np.cross(e[1], e[2])
        c2 = np.cross(e[2], e[0])
        c3 = np.cross(e[0], e[1])
        det = e[0, 0] * c1[0] + e[0, 1] * c1[1] + e[0, 2] * c1[2]
        if abs(det) < 1e-30:
            continue
        for i in range(i_lo, i_hi + 1):
            ry = depth[i] - local[n0, 1]
            for j in range(j_lo, j_hi + 1):
                if tet_of[i, j] >= 0:
                    continue
                rx = lateral[j] - local[n0, 0]
                rz = -local[n0, 2]
                b1 = (rx * c1[0] + ry * c1[1] + rz * c1[2]) / det
                b2 = (rx * c2[0] + ry * c2[1] + rz * c2[2]) / det
                b3 = (rx * c3[0] + ry * c3[1] + rz * c3[2]) / det
                b0 = 1.0 - b1 - b2 - b3
                if min(b0, b1, b2, b3) >= -tolerance:
                    tet_of[i, j] = t
                    weights[i, j, 0] = b0
                    weights[i, j, 1] = b1
                    weights[i, j, 2] = b2
                    weights[i, j, 3] = b3


@numba.njit(cache=True)
def label_pixels(
    tet_of, weights, tets, rest, skin_depth, centres, radii, skin_thickness, labels, material
):  # pragma: no cover
    """Each located pixel's material coordinate X (weights times rest nodes) and label:
    lesion i where X is inside its rest sphere, skin where X is within ``skin_thickness``
    of the rest skin, tissue elsewhere; outside (material NaN) where no tet holds it."""
    rows, cols = tet_of.shape
    for i in range(rows):
        for j in range(cols):
            t = tet_of[i, j]
            if t < 0:
                labels[i, j] = OUTSIDE
                material[i, j, :] = np.nan
                continue
            depth = 0.0
            for d in range(3):
                material[i, j, d] = 0.0
            for a in range(4):
                w = weights[i, j, a]
                node = tets[t, a]
                depth += w * skin_depth[node]
                for d in range(3):
                    material[i, j, d] += w * rest[node, d]
            label = SKIN if depth < skin_thickness else TISSUE
            for k in range(radii.size):
                distance2 = 0.0
                for d in range(3):
                    distance2 += (material[i, j, d] - centres[k, d]) ** 2
                if distance2 <= radii[k] * radii[k]:
                    label = LESION_FIRST_LABEL + k
                    break
            labels[i, j] = label


_MIX1 = np.uint64(0xBF58476D1CE4E5B9)
_MIX2 = np.uint64(0x94D049BB133111EB)
_SHIFT_KEY = (np.uint64(21), np.uint64(42))
_SHIFT_MIX = (np.uint64(30), np.uint64(27), np.uint64(31), np.uint64(64 - TABLE_BITS))
_LOW21 = 0x1FFFFF


@numba.njit(cache=True, inline="always")
def _lattice_index(ix, iy, iz):  # pragma: no cover
    """A table index hashed from a lattice node: 21 bits of each integer coordinate
    packed and mixed by splitmix64's finaliser (Steele et al. 2014)."""
    key = (
        np.uint64(ix & _LOW21)
        | (np.uint64(iy & _LOW21) << _SHIFT_KEY[0])
        | (np.uint64(iz & _LOW21) << _SHIFT_KEY[1])
    )
    key = (key ^ (key >> _SHIFT_MIX[0])) * _MIX1
    key = (key ^ (key >> _SHIFT_MIX[1])) * _MIX2
    key = key ^ (key >> _SHIFT_MIX[2])
    return key >> _SHIFT_MIX[3]


@numba.njit(cache=True)
def reflectivity(material, echogenicity, spacing, table, real, imag):  # pragma: no cover
    """Complex reflectivity per pixel: echogenicity times the lattice's complex Gaussians
    interpolated trilinearly at the material coordinate, divided by the root of the sum of
    the squared weights: its variance is then 1 (times the echogenicity squared) anywhere in
    a cell, where plain trilinear weights would make it 8 times smaller at a cell's centre
    than at a lattice node and show the lattice."""
    rows, cols = echogenicity.shape
    for i in range(rows):
        for j in range(cols):
            scale = echogenicity[i, j]
            if scale == 0.0 or np.isnan(material[i, j, 0]):
                real[i, j] = 0.0
                imag[i, j] = 0.0
                continue
            gx = material[i, j, 0] / spacing
            gy = material[i, j, 1] / spacing
            gz = material[i, j, 2] / spacing
            ix, iy, iz = math.floor(gx), math.floor(gy), math.floor(gz)
            fx, fy, fz = gx - ix, gy - iy, gz - iz
            acc_re, acc_im, norm = 0.0, 0.0, 0.0
            for corner in range(8):
                cx, cy, cz = corner & 1, (corner >> 1) & 1, (corner >> 2) & 1
                w = (fx if cx else 1.0 - fx) * (fy if cy else 1.0 - fy) * (fz if cz else 1.0 - fz)
                index = _lattice_index(int(ix) + cx, int(iy) + cy, int(iz) + cz)
                acc_re += w * table[0, index]
                acc_im += w * table[1, index]
                norm += w * w
            scale /= math.sqrt(norm)
            real[i, j] = scale * acc_re
            imag[i, j] = scale * acc_im
