"""The Lagrange-multiplier contact model, :class:`LagrangeContact`.

It composes the package's pieces: the state kept between steps (:mod:`.state`), the contact
response (:mod:`.response`), ``paper`` mode's step (:mod:`.paper`) and ``robust`` mode's
Newton-LCP step (:mod:`.newton`) with its fallbacks (:mod:`.fallbacks`), and picks the step
by the simulation's mode.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from tissue.contact.lagrange.fallbacks import RobustFallbacks
from tissue.contact.lagrange.paper import PaperSteps
from tissue.contact.registry import register_contact
from tissue.profile import profile_choices
from tissue.status import StepStatus


@register_contact
class LagrangeContact(PaperSteps, RobustFallbacks):
    """Frictionless contact as constraints, solved for their Lagrange multipliers.

    ``paper`` mode follows Tagliabue et al. 2020, section 2.1.2, as written (one linearised
    free motion, collision detection and exact response a step); ``robust`` mode solves the
    same Signorini problem on the nonlinear incremental potential to the Newton tolerance.
    Settings: :class:`~tissue.contact.lagrange.LagrangeParams`. Limitation: frictionless.
    """

    name = "lm"
    label = "LM"
    colour = "tab:blue"
    #: Constraints enforce contact: 0.5 mm, as the hard-cases catalogue asks.
    penetration_bound_m = 0.0005

    def _advance(
        self, h: float
    ) -> tuple[StepStatus, NDArray[np.float64], NDArray[np.float64], dict[str, Any]]:
        if profile_choices(self.sim.config.mode).newton:
            outcome = self._subdivided_robust_step(h, 0)
        else:
            outcome = self._paper_step(h)
        self._pose_before = (self.probe.position_world.copy(), self.probe.quat_wxyz.copy())
        return outcome
