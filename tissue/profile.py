"""The two profiles, ``paper`` and ``robust``: what each decides, in one place.

- ``paper``: as Tagliabue et al. 2020 -- one linearised backward-Euler solve per step, CG
  capped at 25 iterations; prescribed displacement with the node set chosen at first contact
  (on the published scene, its own set for the lesion); penalty with plain springs; the
  10-substep XPBD baseline.
- ``robust``: Newton to a tolerance with line search, PSD-projected tangents, step
  subdivision and an inversion barrier; penalty augmented to 0.1 mm of penetration;
  prescribed displacement with an online, sliding (frictionless) node set on the volume's
  boundary and the skin between its nodes kept out of the probe
  (:class:`tissue.contact.prescribed.PrescribedParams`, ``skin_guard``); the 60-substep XPBD
  tissue with a volume floor.

Either way a PBD tissue's compliance scales are calibrated for the mesh it runs on
(:func:`tissue.pbd.calibration.calibrated_pbd_config`, cached on disk).

:func:`tissue.spec.resolve_spec` asks each contact strategy for its settings under the
spec's profile (:meth:`tissue.contact.base.ContactModel.settings_for`); the strategies read
the profile's choices from here.
"""

from __future__ import annotations

from tissue.choices import Choice
from tissue.errors import ConfigError

#: The paper's tissue time step h [s] (Tagliabue et al. 2020, section 3: the same for every
#: simulation).
PAPER_TISSUE_DT_S = 0.02
#: The paper's probe speed [m/s] (section 3: "the US probe moves at fixed velocity").
PAPER_PROBE_SPEED_M_S = 0.01


def check_tissue_dt(value: object) -> float:
    """``value`` as a tissue time step [s]; a ConfigError naming it unless it is a number in
    (0, 1]."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(f"tissue_dt must be a number of seconds; got {value!r}")
    if not 0.0 < float(value) <= 1.0:
        raise ConfigError(
            f"tissue_dt must be a time step in seconds in (0, 1]; got {value!r} (the paper "
            f"uses {PAPER_TISSUE_DT_S})"
        )
    return float(value)


class Profile(Choice):
    """How faithfully to the paper, or how robustly, a tissue is simulated (module docstring)."""

    PAPER = "paper"
    ROBUST = "robust"

    @classmethod
    def noun(cls) -> str:
        return "profile"
