"""A uniform grid over a fixed triangle set, for the first hit of a ray (the skin at rest).

The rest skin is queried every step of a scanning task (the normal under the probe, twice a
ForceScan step) and along a path at reset. Testing every triangle is one compiled pass
(about 0.25 ms over the 2 mm skin's 16,710 triangles); the grid tests only the triangles of
the cells the ray crosses, nearest first, and stops at the first cell whose far side lies
beyond the nearest hit found (Amanatides & Woo, "A fast voxel traversal algorithm for ray
tracing", Eurographics 1987). Each triangle is listed in every cell its bounding box
overlaps, and each is tested with the same Möller-Trumbore arithmetic as the full pass
(:func:`triangle_hit`, which the full pass uses too), so both give the same hit, bit for
bit.

Limitations: the grid is built once for triangles that do not move (the skin at rest); its
cells are cubes, so a triangle set much longer than wide wastes cells, bounded by
``MAX_CELLS``.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numpy.typing import NDArray

#: A cell's side is this many times the median of the triangles' largest bounding-box side:
#: a few triangles a cell, a ray crossing few cells.
CELL_PER_TRIANGLE = 2.0
#: Cells at most (the side grows to keep within it).
MAX_CELLS = 1_000_000


class TriangleGrid:
    """Triangles given by a corner and two edges, (t, 3) each [m], binned in cubic cells.

    Args:
        corner: each triangle's first corner, (t, 3) [m].
        edge1, edge2: its second and third corners less the first, (t, 3) [m].
    """

    def __init__(
        self,
        corner: NDArray[np.float64],
        edge1: NDArray[np.float64],
        edge2: NDArray[np.float64],
    ) -> None:
        self.corner = np.ascontiguousarray(corner, dtype=np.float64)
        self.edge1 = np.ascontiguousarray(edge1, dtype=np.float64)
        self.edge2 = np.ascontiguousarray(edge2, dtype=np.float64)
        corners = np.stack([self.corner, self.corner + self.edge1, self.corner + self.edge2])
        low, high = corners.min(axis=0), corners.max(axis=0)  # per triangle, (t, 3)
        self.low = low.min(axis=0) if low.size else np.zeros(3)
        extent = (high.max(axis=0) - self.low) if low.size else np.zeros(3)
        side = CELL_PER_TRIANGLE * float(np.median(np.max(high - low, axis=1))) if low.size else 1.0
        side = max(side, 1e-9, float(np.prod(np.maximum(extent, 1e-12)) / MAX_CELLS) ** (1 / 3))
        self.side = side
        self.dims = np.maximum(np.ceil(extent / side).astype(np.int64), 1)
        while int(np.prod(self.dims)) > MAX_CELLS:  # round-up can overshoot the bound
            self.side *= 1.1
            self.dims = np.maximum(np.ceil(extent / self.side).astype(np.int64), 1)
        # Padded by a millionth of a cell: a hit on a cell's face is in both cells' lists.
        pad = 1e-6 * self.side
        first = _cell_of(low - pad, self.low, self.side, self.dims)
        last = _cell_of(high + pad, self.low, self.side, self.dims)
        self.starts, self.items = _bin(first, last, self.dims)

    def nearest_hit(self, origin: NDArray[np.float64], direction: NDArray[np.float64]) -> float:
        """The smallest t > 0 with ``origin`` + t ``direction`` on a triangle, inf if none
        (``direction`` need not be a unit vector; t is in its units)."""
        return float(
            _grid_nearest_hit(
                self.corner, self.edge1, self.edge2, self.low, self.side, self.dims,
                self.starts, self.items,
                np.ascontiguousarray(origin, dtype=np.float64),
                np.ascontiguousarray(direction, dtype=np.float64),
            )
        )  # fmt: skip


def _cell_of(
    points: NDArray[np.float64], low: NDArray[np.float64], side: float, dims: NDArray[np.int64]
) -> NDArray[np.int64]:
    """The cell (i, j, k) holding each point, (t, 3), clamped into the grid."""
    return np.clip(np.floor((points - low) / side).astype(np.int64), 0, dims - 1)


@nb.njit(cache=True)
def _bin(first, last, dims):  # pragma: no cover - compiled
    """CSR lists of the triangles in each cell: triangle p lies in every cell from ``first[p]``
    to ``last[p]`` (inclusive, (t, 3) each); returns (starts (cells + 1,), items)."""
    cells = dims[0] * dims[1] * dims[2]
    counts = np.zeros(cells + 1, dtype=np.int64)
    for p in range(first.shape[0]):
        for i in range(first[p, 0], last[p, 0] + 1):
            for j in range(first[p, 1], last[p, 1] + 1):
                for k in range(first[p, 2], last[p, 2] + 1):
                    counts[(i * dims[1] + j) * dims[2] + k + 1] += 1
    starts = np.cumsum(counts)
    fill = starts[:-1].copy()
    items = np.empty(starts[-1], dtype=np.int64)
    for p in range(first.shape[0]):
        for i in range(first[p, 0], last[p, 0] + 1):
            for j in range(first[p, 1], last[p, 1] + 1):
                for k in range(first[p, 2], last[p, 2] + 1):
                    cell = (i * dims[1] + j) * dims[2] + k
                    items[fill[cell]] = p
                    fill[cell] += 1
    return starts, items


@nb.njit(cache=True)
def triangle_hit(corner, edge1, edge2, k, origin, direction):  # pragma: no cover - compiled
    """The t > 0 with origin + t direction on triangle ``k`` (Möller & Trumbore, "Fast,
    minimum storage ray-triangle intersection", 1997), inf if none."""
    dx, dy, dz = direction[0], direction[1], direction[2]
    e1x, e1y, e1z = edge1[k, 0], edge1[k, 1], edge1[k, 2]
    e2x, e2y, e2z = edge2[k, 0], edge2[k, 1], edge2[k, 2]
    px, py, pz = dy * e2z - dz * e2y, dz * e2x - dx * e2z, dx * e2y - dy * e2x
    det = e1x * px + e1y * py + e1z * pz
    if abs(det) <= 1e-18:
        return np.inf
    inv = 1.0 / det
    sx, sy, sz = origin[0] - corner[k, 0], origin[1] - corner[k, 1], origin[2] - corner[k, 2]
    u = (sx * px + sy * py + sz * pz) * inv
    if u < 0.0 or u > 1.0:
        return np.inf
    qx, qy, qz = sy * e1z - sz * e1y, sz * e1x - sx * e1z, sx * e1y - sy * e1x
    v = (qx * dx + qy * dy + qz * dz) * inv
    if v < 0.0 or u + v > 1.0:
        return np.inf
    t = (e2x * qx + e2y * qy + e2z * qz) * inv
    return t if t > 0.0 else np.inf


@nb.njit(cache=True)
def _grid_nearest_hit(
    corner, edge1, edge2, low, side, dims, starts, items, origin, direction
):  # pragma: no cover - compiled
    """:meth:`TriangleGrid.nearest_hit`: the ray clipped to the grid's box, then its cells
    walked in order, each cell's triangles tested, until the nearest hit lies within the
    cells walked."""
    enter, leave = 0.0, np.inf
    for axis in range(3):
        high = low[axis] + dims[axis] * side
        if direction[axis] == 0.0:
            if origin[axis] < low[axis] or origin[axis] > high:
                return np.inf
            continue
        a = (low[axis] - origin[axis]) / direction[axis]
        b = (high - origin[axis]) / direction[axis]
        enter = max(enter, min(a, b))
        leave = min(leave, max(a, b))
    if enter > leave:
        return np.inf
    cell = np.empty(3, dtype=np.int64)
    step = np.empty(3, dtype=np.int64)
    next_t = np.empty(3)
    delta_t = np.empty(3)
    for axis in range(3):
        at = origin[axis] + enter * direction[axis]
        index = int(np.floor((at - low[axis]) / side))
        cell[axis] = min(max(index, 0), dims[axis] - 1)
        if direction[axis] > 0.0:
            step[axis] = 1
            next_t[axis] = (low[axis] + (cell[axis] + 1) * side - origin[axis]) / direction[axis]
            delta_t[axis] = side / direction[axis]
        elif direction[axis] < 0.0:
            step[axis] = -1
            next_t[axis] = (low[axis] + cell[axis] * side - origin[axis]) / direction[axis]
            delta_t[axis] = -side / direction[axis]
        else:
            step[axis] = 0
            next_t[axis] = np.inf
            delta_t[axis] = np.inf
    best = np.inf
    while True:
        flat = (cell[0] * dims[1] + cell[1]) * dims[2] + cell[2]
        for slot in range(starts[flat], starts[flat + 1]):
            best = min(best, triangle_hit(corner, edge1, edge2, items[slot], origin, direction))
        axis = 0
        if next_t[1] < next_t[axis]:
            axis = 1
        if next_t[2] < next_t[axis]:
            axis = 2
        if best <= next_t[axis] or next_t[axis] > leave:
            return best
        cell[axis] += step[axis]
        if cell[axis] < 0 or cell[axis] >= dims[axis]:
            return best
        next_t[axis] += delta_t[axis]
