"""The contact's own terms of robust mode's exact Newton tangent.

A quasi-static robust step near its solution takes the exact tangent, completed with two
terms per pressing contact point: the probe's curvature (without it Newton converges only
linearly wherever the probe's rounded rim presses) and an augmented-Lagrangian term that
keeps the tangent definite where the tissue alone is not (see
:meth:`ContactTangent._add_contact_tangent`). The LCP then finds the augmented problem's
multipliers, which :meth:`ContactTangent._unaugmented` turns back into the true ones.
"""

from __future__ import annotations

import numba
import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from tissue.contact.fe_model import Contacts
from tissue.contact.lagrange.state import LagrangeState
from tissue.sim.frames import find_column
from tissue.sim.solvers import ConstrainedSystem


class ContactTangent(LagrangeState):
    """Adds the contact terms to a Newton tangent and undoes their augmentation."""

    def _add_contact_tangent(
        self,
        system: ConstrainedSystem,
        contacts: Contacts,
        forces: NDArray[np.float64],
        stiffness: float,
    ) -> tuple[NDArray[np.bool_], float] | None:
        """Complete the exact Newton tangent with the contacts pressing now (``forces`` > 0
        [N], one per contact), in place in ``system``'s matrix.

        Two terms per such point, in 3 x 3 blocks spread over its tet by its weights:

        - the probe's curvature, -lambda d2g/dx2: a force along a normal that turns as the
          point slides round a rounded edge (g is the signed distance; 0 on flat faces).
          Without it Newton converges only linearly wherever the probe's rim presses;
        - rho n n^T, an augmented-Lagrangian term: the LCP fixes these gaps' change, so it
          moves only the multipliers (by rho times the gap being closed, zero at the
          solution), not the step, and it makes the tangent positive definite where the
          tissue alone is not (a press deep enough that the tissue would buckle sideways
          but for the probe). rho is ``stiffness`` times the mean diagonal stiffness of
          the dofs it touches (:attr:`~LagrangeParams.augmentation_stiffnesses`).

        Returns (the points augmented, a mask over ``contacts``; rho [N/m]), or None when
        nothing was added: the multipliers lambda' the LCP then finds stand for lambda' -
        rho H dx in the true linearisation (:meth:`_unaugmented`).
        """
        pressing = forces > 0.0
        if not np.any(pressing):
            return None
        matrix, constrained = system.matrix, system.constrained
        points = contacts.points[pressing]
        nodes = self.surface.embedding.tet_nodes[points]
        weights = self.surface.embedding.weights[points]
        dofs = (3 * nodes[:, :, None] + np.arange(3)).reshape(-1)
        dofs = dofs[~constrained[dofs]]
        if dofs.size == 0:
            return None
        rho = stiffness * float(np.mean(matrix.diagonal()[dofs]))
        normal = contacts.normal[pressing]
        curvature = self.probe.distance_hessian_world(contacts.positions[pressing])
        turning = forces[pressing, None, None] * curvature
        blocks = rho * normal[:, :, None] * normal[:, None, :] - turning
        _add_point_blocks(
            matrix.indptr, matrix.indices, matrix.data, constrained, nodes, weights, blocks
        )
        system.matrix_modified()
        return pressing, rho

    @staticmethod
    def _unaugmented(
        forces: NDArray[np.float64],
        rows: sp.csr_matrix,
        step: NDArray[np.float64],
        augmented: tuple[NDArray[np.bool_], float] | None,
    ) -> NDArray[np.float64]:
        """The forces [N] of the true linearisation from those of the augmented one:
        (A + rho H_a^T H_a) dx = r + H^T lambda' is A dx = r + H^T lambda with lambda =
        lambda' - rho H_a dx on the augmented points (no pull: at least 0). Without this
        the KKT residual would carry rho times the gap each step closes, and grow."""
        if augmented is None:
            return forces
        mask, rho = augmented
        corrected = forces.copy()
        corrected[mask] = np.maximum(forces[mask] - rho * (rows[mask] @ step), 0.0)
        return corrected


@numba.njit(cache=True)
def _add_point_blocks(
    indptr, indices, data, constrained, nodes, weights, blocks
):  # pragma: no cover - compiled
    """Add, for each contact point c embedded with ``weights`` (4,) in the tet of ``nodes``
    (4,), the 3 x 3 block ``blocks[c]`` times w_a w_b at every node pair (a, b) of its tet, to
    the CSR matrix in place (within its pattern: one tet's nodes are always coupled);
    constrained dofs are skipped (their rows and columns are eliminated)."""
    for c in range(nodes.shape[0]):
        for a in range(4):
            for b in range(4):
                w = weights[c, a] * weights[c, b]
                for k in range(3):
                    i = 3 * nodes[c, a] + k
                    if constrained[i]:
                        continue
                    lo, hi = indptr[i], indptr[i + 1]
                    for m in range(3):
                        j = 3 * nodes[c, b] + m
                        if constrained[j]:
                            continue
                        q = find_column(indices, lo, hi, j)
                        if q >= 0:
                            data[q] += w * blocks[c, k, m]
