"""The two profiles, ``paper`` and ``robust``: what each decides, in one place.

A profile is a bundle of choices, one per layer, listed in :data:`PROFILES` as
:class:`ProfileChoices`. The layers below read the choice they act on by name
(``profile_choices(config.mode).newton``); no module outside this one compares profiles.

- ``paper``: as Tagliabue et al. 2020 -- one linearised backward-Euler solve per step, CG
  capped at 25 iterations; prescribed displacement with the node set chosen at first contact
  (on the published scene, its own set for the lesion); penalty with plain springs; the
  10-substep XPBD baseline.
- ``robust``: Newton to a tolerance with line search, PSD-projected tangents, step
  subdivision and an inversion barrier; penalty augmented to 0.1 mm of penetration;
  prescribed displacement with an online, sliding (frictionless) node set on the volume's
  boundary and the skin between its nodes kept out of the probe
  (:class:`tissue.contact.prescribed.PrescribedParams`, ``skin_guard``); the 60-substep XPBD
  tissue with a volume floor and contact points on the skin between the boundary nodes.

Either way a PBD tissue's compliance scales are calibrated for the mesh it runs on
(:func:`tissue.pbd.calibration.calibrated_pbd_config`, cached on disk).
"""

from __future__ import annotations

from dataclasses import dataclass

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


@dataclass(frozen=True)
class ProfileChoices:
    """What a profile decides, each choice read by name where it acts.

    Attributes:
        newton: solve each step's nonlinear problem to the Newton tolerance, with line
            search and step subdivision (LM: its Newton-LCP iteration), instead of the
            paper's one linearised backward-Euler solve (LM: one free motion and one
            response) (:mod:`tissue.sim.integrator`, :mod:`tissue.contact.lagrange`).
        linear_solver: the default linear solver: ``cg`` (capped at 25 iterations, as the
            paper) or ``reuse`` (a kept factorisation preconditioning CG)
            (:mod:`tissue.sim.solvers`).
        project_psd: project element tangents to positive semi-definite.
        inversion_barrier: the volume ratio J below which a barrier keeps tets from
            inverting; 0 leaves the law as published (:class:`tissue.fem.elasticity.Elasticity`).
            A tissue tet at nu = 0.49 keeps far more than a tenth of its volume under any
            physical compression, so 0.1 leaves those untouched; it acts where a Dirichlet
            condition or a point-like contact on a coarse mesh flattens a tet (on the 1,363-tet
            phantom, prescribed displacement with one node in contact at 29 mm, the stable
            law alone let a tet invert).
        fine_boundary_contact: FE contact acts on the volume's boundary where it is finer than
            the collision surface (:func:`tissue.contact.fe_model.model_surface`); otherwise on
            the collision surface, as the paper.
        augmented_penalty: penalty's springs are augmented (re-solved) until no point is
            deeper than their tolerance (:mod:`tissue.contact.penalty`).
        online_prescribed: prescribed displacement picks its node set online each step,
            sliding, with the skin between its nodes guarded; otherwise the set chosen at
            first contact (:mod:`tissue.contact.prescribed`).
        pbd_preset: the XPBD tissue's settings: ``baseline`` (10 substeps, FleX-like) or
            ``robust`` (60 substeps, a volume floor) (:meth:`tissue.pbd.PBDConfig.preset`).
        pbd_skin_contact: a PBD tissue built through the front door also takes contact points
            on the skin between the boundary nodes (the study runs the presets alone).
    """

    newton: bool
    linear_solver: str
    project_psd: bool
    inversion_barrier: float
    fine_boundary_contact: bool
    augmented_penalty: bool
    online_prescribed: bool
    pbd_preset: str
    pbd_skin_contact: bool


#: Every profile's choices (the module docstring says why).
PROFILES: dict[Profile, ProfileChoices] = {
    Profile.PAPER: ProfileChoices(
        newton=False,
        linear_solver="cg",
        project_psd=False,
        inversion_barrier=0.0,
        fine_boundary_contact=False,
        augmented_penalty=False,
        online_prescribed=False,
        pbd_preset="baseline",
        pbd_skin_contact=False,
    ),
    Profile.ROBUST: ProfileChoices(
        newton=True,
        linear_solver="reuse",
        project_psd=True,
        inversion_barrier=0.1,
        fine_boundary_contact=True,
        augmented_penalty=True,
        online_prescribed=True,
        pbd_preset="robust",
        pbd_skin_contact=True,
    ),
}


def profile_choices(profile: Profile | str) -> ProfileChoices:
    """The choices of ``profile`` (a :class:`Profile` or its name)."""
    return PROFILES[Profile.parse(profile)]
