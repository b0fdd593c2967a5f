"""The stiffness of the tissue's wrench on the probe with respect to the probe's motion.

A robot holding the probe steps many times (2 ms) between two tissue steps (20 ms). Held
constant in between, the tissue's wrench gives the robot no stiffness to feel; linearised in
the probe's displacement, F(q) ~ F0 - K (q - q0), it acts as the spring it is. This module
computes K for the FE strategies.

How: the contact at the end of the last step is a set of c constraints on the tissue, row i
of H (c x 3N) measuring point i's motion along a direction n_i (a contact normal, or a held
node's axis), each with a compliance s_i [m/N] (0 for Lagrange multipliers and prescribed
nodes, 1 / k_s for penalty springs). A probe motion q = (translation, rotation) moves the
probe's surface at point r_i by N_i q, N_i = [n_i^T, (r_i x n_i)^T]. The tissue's static
response at the present state has the tangent A = K(x) (the fixed base eliminated). The
constraint forces then change by dlambda = (W + S)^-1 N dq, with W = H A^-1 H^T the
contacts' compliance and S = diag(s_i), and the wrench on the probe by -N^T dlambda:

    K = N^T (H A^-1 H^T + S)^-1 N      (6 x 6, symmetric positive semi-definite).

Static, not the tangent of one dynamic step (M / dt^2 + damping + K(x)): the inertia term
made K several times stiffer than the force's change from one tissue step to the next
(measured: pressing the 1,303-tet phantom at 0.2 and 1 mm a step, w0 - K dq with the dynamic
tangent predicted the next step's force to 0.12 and 0.35 N, worse than holding w0, 0.04 and
0.12 N; with the static one to 0.018 and 0.058 N, twice better than holding).

Cost: one factorisation of A and c solves (c: the contact points, or 3 per held node for
sticking prescribed displacement), dense algebra on c x c: about a tissue step at 1,303
tets (2 ms here). Limitations: the contact set is frozen (a point about to touch is not
counted), the probe's curvature term is left out (exact for flat parts of the face), and
PBD has no tangent (None).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from tissue.contact.base import ContactModel


@dataclass(frozen=True)
class ContactConstraints:
    """The contact at the end of a step, as linear constraints on the tissue.

    Attributes:
        rows: H, (c, 3N) CSR: row i is direction_i^T times point i's embedding.
        points_world_m: where each acts [m], (c, 3).
        directions_world: the unit direction each measures, (c, 3) (the probe's outward
            normal for contacts, an axis for a held node).
        compliance_m_per_n: s_i [m/N], (c,) (0: exact).
    """

    rows: sp.csr_matrix
    points_world_m: NDArray[np.float64]
    directions_world: NDArray[np.float64]
    compliance_m_per_n: NDArray[np.float64]

    @property
    def count(self) -> int:
        return int(self.rows.shape[0])


def wrench_stiffness(model: ContactModel) -> NDArray[np.float64] | None:
    """K, (6, 6), world frame about the probe origin (see the module docstring); zeros out
    of contact; None for a strategy without a tangent (PBD)."""
    if not model.has_tangent:
        return None
    constraints_of = model.contact_constraints  # type: ignore[attr-defined]
    constraints: ContactConstraints = constraints_of()
    if constraints.count == 0:
        return np.zeros((6, 6))
    factorization, constrained = model.step_tangent()  # type: ignore[attr-defined]
    columns = constraints.rows.T.toarray()
    columns[constrained] = 0.0
    solved = np.asarray(factorization.solve(np.asfortranarray(columns)))
    solved = solved.reshape(columns.shape)
    compliance = constraints.rows @ solved
    compliance = 0.5 * (compliance + compliance.T)
    compliance[np.diag_indices_from(compliance)] += constraints.compliance_m_per_n
    arms = constraints.points_world_m - model.probe.position_world
    directions = constraints.directions_world
    motion = np.concatenate([directions, np.cross(arms, directions)], axis=1)  # (c, 6)
    stiffness = motion.T @ np.linalg.lstsq(compliance, motion, rcond=None)[0]
    return 0.5 * (stiffness + stiffness.T)
