"""Local frames at nodes: Dirichlet conditions on coordinates other than the world axes.

A frictionless contact prescribes only the coordinate of a node along the contact normal
and leaves it free to slide in the tangent plane. Written in world coordinates that is a
linear constraint n . x = c mixing three dofs; in a frame whose first axis is n it is one
dof, a plain Dirichlet condition. The integrator therefore runs such steps in the rotated
coordinates z = Q y, where Q is block-diagonal with one orthonormal 3 x 3 block per framed
node (rows: the frame's axes in world coordinates; the identity elsewhere). Energies are
unchanged, gradients become Q g and tangents Q H Q^T: an orthogonal change of basis, so
definiteness, residual norms and descent directions are unchanged too.

Q H Q^T mixes the three rows and the three columns of each framed node only, so it keeps the
sparsity pattern of a matrix stored in full 3 x 3 node blocks (every FE tangent here), and
the rotation is done in place on the CSR values.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from tissue.errors import TissueInputError


@dataclass(frozen=True)
class NodeFrames:
    """Orthonormal frames at some nodes.

    Attributes:
        nodes: the framed nodes, (k,), unique.
        axes: each frame's axes as rows, in world coordinates, (k, 3, 3); a right-handed
            orthonormal basis per node.
        node_count: nodes in the mesh.
    """

    nodes: NDArray[np.int64]
    axes: NDArray[np.float64]
    node_count: int

    @classmethod
    def from_normals(
        cls, nodes: NDArray[np.int64], normals: NDArray[np.float64], node_count: int
    ) -> NodeFrames:
        """Frames whose first axis is each node's unit normal [-], (k, 3).

        The two tangents are any orthonormal completion (they carry no condition).
        """
        nodes = np.asarray(nodes, dtype=np.int64).reshape(-1)
        normals = np.asarray(normals, dtype=np.float64)
        if normals.shape != (nodes.size, 3):
            raise TissueInputError(
                f"normals must have shape ({nodes.size}, 3) for {nodes.size} nodes; "
                f"got {normals.shape}"
            )
        length = np.linalg.norm(normals, axis=1)
        if not np.all(np.isfinite(length)) or np.any(length < 1e-12):
            raise TissueInputError("normals must be finite and non-zero")
        normal = normals / length[:, None]
        # A helper axis far from each normal: the world axis along its smallest component.
        helper = np.zeros_like(normal)
        helper[np.arange(nodes.size), np.argmin(np.abs(normal), axis=1)] = 1.0
        first = np.cross(normal, helper)
        first /= np.linalg.norm(first, axis=1)[:, None]
        second = np.cross(normal, first)
        return cls(nodes, np.stack([normal, first, second], axis=1), int(node_count))

    def node_slots(self) -> NDArray[np.int64]:
        """Each mesh node's index into ``axes``, or -1 where it has no frame, (node_count,)."""
        slots = np.full(self.node_count, -1, dtype=np.int64)
        slots[self.nodes] = np.arange(self.nodes.size)
        return slots

    def to_local(self, vector: NDArray[np.float64]) -> NDArray[np.float64]:
        """Q v: a flat world vector (3 node_count,) in the frames' coordinates (a new array)."""
        out = np.array(vector, dtype=np.float64, copy=True)
        blocks = out.reshape(-1, 3)
        blocks[self.nodes] = np.einsum("kij,kj->ki", self.axes, blocks[self.nodes])
        return out

    def to_world(self, vector: NDArray[np.float64]) -> NDArray[np.float64]:
        """Q^T z: a flat vector in the frames' coordinates back in world ones (a new array)."""
        out = np.array(vector, dtype=np.float64, copy=True)
        blocks = out.reshape(-1, 3)
        blocks[self.nodes] = np.einsum("kji,kj->ki", self.axes, blocks[self.nodes])
        return out

    def rotate_matrix(self, matrix: sp.csr_matrix) -> None:
        """Q A Q^T in place, for a CSR matrix stored in full, sorted 3 x 3 node blocks.

        Raises:
            ValueError: the matrix's pattern is not made of full node blocks.
        """
        if not matrix.has_sorted_indices:
            matrix.sort_indices()
        whole = _full_node_blocks(matrix.indptr, matrix.indices, self.nodes) and _rotate_blocks(
            matrix.indptr, matrix.indices, matrix.data, self.nodes, self.node_slots(), self.axes
        )
        if not whole:
            raise ValueError("rotating node frames needs a matrix stored in full 3 x 3 blocks")


@numba.njit(cache=True)
def _full_node_blocks(indptr, indices, nodes):  # pragma: no cover - compiled
    """Whether the three rows of each node in ``nodes`` share one pattern of whole blocks."""
    for a in nodes:
        start = indptr[3 * a]
        length = indptr[3 * a + 1] - start
        if length % 3 != 0:
            return False
        for i in range(1, 3):
            other = indptr[3 * a + i]
            if indptr[3 * a + i + 1] - other != length:
                return False
            for p in range(length):
                if indices[other + p] != indices[start + p]:
                    return False
        for p in range(0, length, 3):
            column = indices[start + p]
            if column % 3 != 0 or indices[start + p + 1] != column + 1:
                return False
            if indices[start + p + 2] != column + 2:
                return False
    return True


@numba.njit(cache=True)
def find_column(indices, start, stop, column):  # pragma: no cover - compiled
    """Position of ``column`` in the sorted slice indices[start:stop] of a CSR row, or -1."""
    low, high = start, stop
    while low < high:
        middle = (low + high) // 2
        if indices[middle] < column:
            low = middle + 1
        else:
            high = middle
    if low < stop and indices[low] == column:
        return low
    return -1


@numba.njit(cache=True)
def _rotate_blocks(indptr, indices, data, nodes, slots, axes):  # pragma: no cover - compiled
    """A_ab <- R_a A_ab R_b^T for every block touching a framed node (R = I elsewhere).

    Blocks in a framed node's rows are rotated on both sides there; the mirror block in an
    unframed neighbour's rows only on the right (a framed neighbour's own rows rotate it).
    Returns False (the matrix then half rotated) if a mirror block is missing.
    """
    block = np.empty((3, 3))
    left = np.empty((3, 3))
    for k in range(nodes.shape[0]):
        a = nodes[k]
        ra = axes[k]
        start = indptr[3 * a]
        length = indptr[3 * a + 1] - start
        for p in range(0, length, 3):
            b = indices[start + p] // 3
            for i in range(3):
                row = indptr[3 * a + i] + p
                for j in range(3):
                    block[i, j] = data[row + j]
            # left = R_a A_ab
            for i in range(3):
                for j in range(3):
                    s = 0.0
                    for m in range(3):
                        s += ra[i, m] * block[m, j]
                    left[i, j] = s
            slot = slots[b]
            for i in range(3):
                row = indptr[3 * a + i] + p
                for j in range(3):
                    if slot >= 0:
                        s = 0.0
                        for m in range(3):
                            s += left[i, m] * axes[slot, j, m]
                        data[row + j] = s
                    else:
                        data[row + j] = left[i, j]
            if slot >= 0:
                continue
            # The mirror block A_ba in b's rows: A_ba R_a^T.
            for i in range(3):
                q = find_column(indices, indptr[3 * b + i], indptr[3 * b + i + 1], 3 * a)
                if q < 0 or q + 2 >= indptr[3 * b + i + 1] or indices[q + 2] != 3 * a + 2:
                    return False
                for j in range(3):
                    block[i, j] = data[q + j]
                for j in range(3):
                    s = 0.0
                    for m in range(3):
                        s += block[i, m] * ra[j, m]
                    left[i, j] = s
                for j in range(3):
                    data[q + j] = left[i, j]
    return True


@dataclass(frozen=True)
class FrameChange:
    """The change of coordinates from one set of node frames to another, P = Q_new Q_old^T.

    P is the identity except at ``nodes``, where it is ``blocks`` (k, 3, 3): R_new R_old^T,
    R the node's frame (the identity for a node without one).
    """

    nodes: NDArray[np.int64]
    blocks: NDArray[np.float64]

    @classmethod
    def between(cls, old: NodeFrames | None, new: NodeFrames | None) -> FrameChange | None:
        """P from ``old`` to ``new`` coordinates, or None where no frame differs."""
        if old is new:
            return None
        nodes = np.union1d(
            old.nodes if old is not None else np.zeros(0, dtype=np.int64),
            new.nodes if new is not None else np.zeros(0, dtype=np.int64),
        )
        rotation_old = _rotations(old, nodes)
        rotation_new = _rotations(new, nodes)
        moved = np.abs(rotation_new - rotation_old).max(axis=(1, 2)) > 0.0
        if not np.any(moved):
            return None
        nodes = nodes[moved]
        blocks = np.einsum("kij,klj->kil", rotation_new[moved], rotation_old[moved])
        return cls(nodes, blocks)

    def apply(self, array: NDArray[np.float64], transpose: bool = False) -> NDArray[np.float64]:
        """P a (or P^T a) for a flat vector (3 node_count,) or a stack of columns (3 node_count,
        m); a new array."""
        out = np.array(array, dtype=np.float64, order="C", copy=True)
        blocks = out.reshape(-1, 3, *out.shape[1:])  # a view of the C-ordered copy
        rotation = np.swapaxes(self.blocks, 1, 2) if transpose else self.blocks
        if out.ndim == 1:
            blocks[self.nodes] = np.einsum("kij,kj->ki", rotation, blocks[self.nodes])
        else:
            blocks[self.nodes] = np.einsum("kij,kjm->kim", rotation, blocks[self.nodes])
        return out


def _rotations(frames: NodeFrames | None, nodes: NDArray[np.int64]) -> NDArray[np.float64]:
    """Each listed node's frame, (k, 3, 3) (the identity where it has none)."""
    out = np.broadcast_to(np.eye(3), (nodes.size, 3, 3)).copy()
    if frames is not None:
        slots = frames.node_slots()[nodes]
        framed = slots >= 0
        out[framed] = frames.axes[slots[framed]]
    return out
