"""The settings of Lagrange-multiplier contact (:class:`LagrangeParams`).

Most fields are tuning choices of robust mode's Newton-LCP iteration (see
:mod:`tissue.contact.lagrange.newton`), its kept factorisation
(:mod:`tissue.contact.lagrange.response`) and its fallbacks
(:mod:`tissue.contact.lagrange.fallbacks`); the defaults were chosen on the breast phantom's
apex press and the study's references, from 623 to 176,506 tets.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tissue.errors import ConfigError


@dataclass(frozen=True)
class LagrangeParams:
    """Lagrange-multiplier contact settings.

    The defaults give the published scene's behaviour in ``paper`` mode (only the first five
    fields act there) and robust mode's tuned iteration. Units are in each field's name or
    description.

    Attributes:
        alarm_distance_m: points closer than this to the probe become constraints [m]
            (the published scene used 2 mm).
        contact_distance_m: the gap kept between tissue and probe [m] (0: touching).
        pgs_tolerance_m: PGS stops when no gap or force changes by more than this
            (expressed as a gap) [m].
        pgs_max_iterations: PGS sweep cap (1000 as SOFA's default).
        regularization: eps on W's diagonal, relative to its mean diagonal.
        max_iterations: (robust mode) Newton-LCP iterations before giving up.
        max_response_iterations: contact-response rounds whose W~ prediction misses the
            exact gaps before the kept factorisation is refreshed within the response (and
            one more, exact, round taken).
        stalled_penetration_m: (robust mode) an iterate is converged when its KKT residual
            is below the Newton tolerance and no point lies deeper than the contact
            tolerance (:attr:`LagrangeContact.gap_tolerance_m`, ~0.1 um); if the penetration
            then stops shrinking (:attr:`stalled_iterations` iterations without halving),
            the iterate is accepted when no point is deeper than this [m], and the step
            fails (and is subdivided) otherwise. A linearised gap misses the probe's
            curvature, so one point's exact gap can stay a fraction of a micron negative
            while the linearised gaps are met to the PGS tolerance; 1 um accepts that and
            nothing a display or a force could notice.
        stalled_iterations: (robust mode) converged-residual iterations whose penetration
            does not halve before it counts as stalled (see
            :attr:`stalled_penetration_m`). Three: a genuinely shrinking penetration halves
            in one or two.
        keep_factorization_unknowns: (robust mode) systems with at least this many unknowns
            (3 x nodes) keep a single-precision factorisation F across Newton iterations and
            steps (CG preconditioned by F, compliance W~ = H F^-1 H^T); smaller ones
            refactorise every iteration. What a refactorisation costs grows with the
            contact's compliance columns, one solve each: on the environments' 2 mm skin
            (about 100 candidate points under the probe) keeping doubles BreastCompress's
            LM rate at the coarsest phantom level (623 tets, 417 unknowns: 72 -> 148 steps/s
            pressing, 109 -> 207 exploring), while on the paper's 512-vertex skin it costs
            a steady press a fifth there (219 -> 173) and gains an exploring step an eighth
            (242 -> 272). From 1,363 tets (834 unknowns) up keeping wins on either skin, by
            nearly a factor of two from a few thousand unknowns up. 400 keeps every phantom
            level; only small test blocks refactorise.
        kept_projected_iterations: (robust mode, kept factorisation, quasi-static) Newton
            iterations of a step on the projected (PSD) tangent before the exact one with
            the contact terms is taken. A change of tangent costs a refactorisation (F must
            be of the tangent W~ is built from), which a step converging within these never
            pays; without inertia the projected tangent alone crawls (it contracts the
            residual by only 0.5-0.94 an iteration on a fine reference), while the exact one
            converges quadratically in about five.
        augmentation_stiffnesses: (robust mode, quasi-static) the augmented-Lagrangian
            stiffnesses rho of the exact tangent's contact terms, in mean diagonal
            stiffnesses of the dofs they touch, tried in turn until the tangent is definite
            (then the projected tangent). As small as will do: the LCP's multipliers stand
            for lambda - rho H dx, and rho times what the linearised gaps miss of the true
            ones ends up in the forces (100 alone put a sphere's forces 0.4-0.9 % off where
            1 gave a tight solve's to six digits); 100 is the fallback where 1 leaves the
            tangent indefinite on a deep press.
        refresh_after_missed_rounds: (robust mode, kept factorisation) a response whose W~
            prediction missed the exact gaps in this many rounds refreshes F after it, so
            that the next response starts from an accurate W~.
        lazy_gap_m: (robust mode, kept factorisation) constraints carrying no force whose
            gap after the free step is larger than this [m] stay out of the response's LCP
            (and so cost no column of W~) until a round's exact gaps bring them within it.
            Most of the columns a fine mesh's press spent were of such points, approaching
            the probe's rounded rim with turning normals; 0.5 mm is above a step's advance
            at the paper's speed (0.2 mm), so a point rarely joins late. ``inf`` takes every
            constraint at once.
        prefetch_gap_m: (robust mode, kept factorisation) the W~ columns solved beside the
            free step's first solve (in the same solver call) are those of the points
            pressing or within this gap [m] before it. The free step moves points by about
            the probe's advance, so those within :attr:`lazy_gap_m` after it are within
            this before; with :attr:`lazy_gap_m` itself some steps still needed a call of
            their own for one or two columns, with 0.75 mm none did.
        response_tolerance_cap: (robust mode, kept factorisation) the loosest relative
            tolerance of a response solve: one CG iteration's worth, so that the exact gaps
            it yields still check W~'s prediction.
        max_relaxation_steps: (robust mode, quasi-static) relaxation steps a step that does
            not converge even when split may take (see
            :meth:`LagrangeContact._relaxed_step`) before it is reported not converged.
        max_relaxation_time_steps: (robust mode, quasi-static) the largest pseudo time step
            of a relaxation, in tissue time steps: its pseudo time step starts at the
            tissue's and doubles after each relaxation step that converges (pseudo-transient
            continuation) up to this.
        relaxed_inertia_fraction: (robust mode, quasi-static) the static solve is tried
            again once the inertial force of the last relaxation step is below this
            fraction of the contact load (each failed try divides it by ten).
        relaxation_iterations: (robust mode, quasi-static) Newton iterations a relaxation
            step may take before its pseudo time step is quartered. Relaxation steps that
            converge take 2-16; one with too long a pseudo time step runs to the cap without
            converging, and 20 stops it early where a shorter one converges in a few.
    """

    alarm_distance_m: float = 0.002
    contact_distance_m: float = 0.0
    pgs_tolerance_m: float = 1e-8
    pgs_max_iterations: int = 1000
    regularization: float = 1e-8
    max_iterations: int = 30
    max_response_iterations: int = 4
    stalled_penetration_m: float = 1e-6
    stalled_iterations: int = 3
    keep_factorization_unknowns: int = 400
    kept_projected_iterations: int = 6
    augmentation_stiffnesses: tuple[float, ...] = (1.0, 100.0)
    refresh_after_missed_rounds: int = 2
    lazy_gap_m: float = 0.5e-3
    prefetch_gap_m: float = 0.00075
    response_tolerance_cap: float = 0.1
    max_relaxation_steps: int = 60
    max_relaxation_time_steps: float = 1024.0
    relaxed_inertia_fraction: float = 1e-2
    relaxation_iterations: int = 20

    def __post_init__(self) -> None:
        for name in (
            "alarm_distance_m",
            "contact_distance_m",
            "pgs_tolerance_m",
            "stalled_penetration_m",
            "prefetch_gap_m",
            "relaxed_inertia_fraction",
        ):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise ConfigError(f"{name} must be >= 0; got {value!r}")
        if self.alarm_distance_m < self.contact_distance_m:
            raise ConfigError(
                f"alarm_distance_m ({self.alarm_distance_m}) must be >= contact_distance_m "
                f"({self.contact_distance_m})"
            )
        if min(self.pgs_max_iterations, self.max_iterations, self.max_response_iterations) < 1:
            raise ConfigError(
                "pgs_max_iterations, max_iterations and max_response_iterations must be >= 1"
            )
        if not (np.isfinite(self.regularization) and self.regularization >= 0):
            raise ConfigError(f"regularization must be >= 0; got {self.regularization!r}")
        self._check_robust_tuning()

    def _check_robust_tuning(self) -> None:
        """Validate the robust-mode tuning fields."""
        counts = {
            "stalled_iterations": 1,
            "keep_factorization_unknowns": 0,
            "kept_projected_iterations": 0,
            "refresh_after_missed_rounds": 1,
            "max_relaxation_steps": 1,
            "relaxation_iterations": 1,
        }
        for name, least in counts.items():
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
                raise ConfigError(f"{name} must be an integer; got {value!r}")
            if value < least:
                raise ConfigError(f"{name} must be >= {least}; got {value!r}")
        if not (self.lazy_gap_m >= 0):  # inf allowed: every constraint at once
            raise ConfigError(f"lazy_gap_m must be >= 0; got {self.lazy_gap_m!r}")
        stiffnesses = self.augmentation_stiffnesses
        if (
            not isinstance(stiffnesses, tuple)
            or not stiffnesses
            or not all(np.isfinite(s) and s > 0 for s in stiffnesses)
        ):
            raise ConfigError(
                f"augmentation_stiffnesses must be a non-empty tuple of numbers > 0; got "
                f"{stiffnesses!r}"
            )
        if not (np.isfinite(self.response_tolerance_cap) and self.response_tolerance_cap > 0):
            raise ConfigError(
                f"response_tolerance_cap must be > 0; got {self.response_tolerance_cap!r}"
            )
        if not (np.isfinite(self.max_relaxation_time_steps) and self.max_relaxation_time_steps > 0):
            raise ConfigError(
                f"max_relaxation_time_steps must be > 0; got {self.max_relaxation_time_steps!r}"
            )
