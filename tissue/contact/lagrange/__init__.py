"""Lagrange-multiplier contact (Tagliabue et al. 2020, section 2.1.2; SOFA's
``FreeMotionAnimationLoop`` with a Gauss-Seidel constraint solver and
``LinearSolverConstraintCorrection``).

Contact is a set of unilateral constraints, one per collision-surface point within the
alarm distance of the probe, and the contact forces lambda [N] are their multipliers, found
by projected Gauss-Seidel on Signorini's conditions (gap >= 0, lambda >= 0, gap . lambda =
0) with the compliance W = H A^-1 H^T of the step's linear system A.

- ``paper`` mode (:mod:`.paper`) follows the paper's three phases as written: a free
  motion, collision detection at the free positions, one exact response; A factorised every
  step.
- ``robust`` mode (:mod:`.newton`) solves the same problem on the nonlinear incremental
  potential: each Newton iteration linearises the potential and the gaps and solves that
  LCP, until the KKT residual is below the Newton tolerance; on all but the smallest systems
  with a kept factorisation and an approximate compliance iterated to the exact one
  (:mod:`.response`). Steps that do not converge are split, and quasi-static ones relaxed
  (:mod:`.fallbacks`).

The modules: :mod:`.params` (:class:`LagrangeParams`), :mod:`.pgs` (the LCP kernel),
:mod:`.state` (what the model keeps between steps), :mod:`.response`, :mod:`.tangent` (the
contact's terms of the exact tangent), :mod:`.paper`, :mod:`.iterate` (what robust mode's
iteration carries), :mod:`.newton`, :mod:`.fallbacks` and
:mod:`.model` (:class:`LagrangeContact`, composing them).

Limitations: frictionless; W is dense over the constraints an LCP takes (tens to hundreds
in a press, not thousands).
"""

from __future__ import annotations

from tissue.contact.lagrange.model import LagrangeContact
from tissue.contact.lagrange.params import LagrangeParams
from tissue.contact.lagrange.pgs import projected_gauss_seidel

__all__ = ["LagrangeContact", "LagrangeParams", "projected_gauss_seidel"]
