"""Numba kernels for linear-tet hyperelasticity: element pass, row-parallel assembly, ANP.

The hot loops behind :class:`tissue.fem.elasticity.Elasticity`; the package has no public
API of its own (the class is the contract). Every kernel runs with fastmath off, which keeps
the assembled matrix bitwise symmetric (see :mod:`~tissue.fem.kernels.assembly`).

Modules, one concept each:

* :mod:`~tissue.fem.kernels.geometry`: rest shape-function gradients, the deformation
  gradient and det F, the local node-pair tables; the layout conventions all kernels share.
* :mod:`~tissue.fem.kernels.eigen`: symmetric 3x3 eigen-solvers (closed form, Jacobi).
* :mod:`~tissue.fem.kernels.projection`: the negative eigenpairs of dP/dF, for the PSD
  projection of the element tangents.
* :mod:`~tissue.fem.kernels.element`: the element pass: energy, nodal forces and tangent
  terms of the stable and classic neo-Hookean laws per tet, with the inversion barrier.
* :mod:`~tissue.fem.kernels.assembly`: the row-parallel gathers of the nodal forces and of
  the node-blocked CSR stiffness matrix.
* :mod:`~tissue.fem.kernels.anp`: average nodal pressure (anti-locking) patch kernels.

References: Smith, de Goes & Kim 2018, Stable Neo-Hookean Flesh Simulation, ACM TOG
37(2):12 (the stable law; the eigensystem of dP/dF); O. K. Smith 1961, Eigenvalues of a
symmetric 3x3 matrix, Commun. ACM 4(4):168 (the closed-form eigenvalues); Bonet & Burton
1998, Commun. Numer. Meth. Eng. 14:437-449 (average nodal pressure).
"""

from __future__ import annotations

from tissue.fem.kernels.anp import (
    anp_gather_blocks,
    anp_patch_gradients,
    anp_patch_pass,
    patch_pair_positions,
)
from tissue.fem.kernels.assembly import block_contributions, gather_elements, gather_forces
from tissue.fem.kernels.eigen import CLOSED_FORM_GAP as CLOSED_FORM_GAP
from tissue.fem.kernels.eigen import sym3_eigen_fast as sym3_eigen_fast
from tissue.fem.kernels.element import (
    LAW_CLASSIC,
    LAW_STABLE,
    STAGE_ENERGY,
    STAGE_FORCES,
    STAGE_TANGENT,
    element_pass,
)
from tissue.fem.kernels.geometry import (
    PAIR_INDEX,
    PAIRS,
    rest_grad_dots,
    shape_gradients,
    volume_ratios,
)
from tissue.fem.kernels.projection import MAX_NEGATIVE_MODES
from tissue.fem.kernels.projection import negative_modes as negative_modes

__all__ = [
    "LAW_CLASSIC",
    "LAW_STABLE",
    "MAX_NEGATIVE_MODES",
    "PAIRS",
    "PAIR_INDEX",
    "STAGE_ENERGY",
    "STAGE_FORCES",
    "STAGE_TANGENT",
    "anp_gather_blocks",
    "anp_patch_gradients",
    "anp_patch_pass",
    "block_contributions",
    "element_pass",
    "gather_elements",
    "gather_forces",
    "patch_pair_positions",
    "rest_grad_dots",
    "shape_gradients",
    "volume_ratios",
]
