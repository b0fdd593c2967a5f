"""Domain randomisation: what varies between episodes, drawn from the reset's seed.

``gymnasium.make(ENV_ID, domain_randomization=True)`` varies everything below with the
default ranges; a dict or a :class:`DomainRandomization` chooses (a zero range, or 0, switches
one part off). Off by default. Two kinds of variation:

- **The patient** (drawn at each reset; a new tissue is built from the nominal one with
  :meth:`tissue.Tissue.varied`, no remeshing: a reset takes 45-50 ms at 1,303 tets): the
  bulk tissue's Young's modulus, the lesions' stiffness ratio, and each lesion's place.
- **The robot's senses** (what the policy observes; rewards, success and ``info`` keep the
  simulated truth): the F/T sensor's bias (drawn at each reset) and noise (each step), and
  noise on the probe pose the arm reports (each step).

The draws come from a generator of their own, seeded from the reset's seed, so a task draws
its own start (lesion, offset, path) the same with and without randomisation, and the same
seed gives the same episode.

Default ranges and why: the tissue's E is scaled by 0.6-1.6 around the published scene's
2,850 Pa (1.7-4.6 kPa, about the in-vivo aspiration prior of 3.0 +- 1.2 kPa for fatty and
fibroglandular tissue); E_lesion / E_tissue in 2-6 (Samani et al. 2007: fibroadenomas about
2 x, fibrocystic and malignant tumours 3-6 x); each lesion moves up to 1 mm (never beyond
the room its mesh leaves it, :meth:`tissue.Tissue.lesion_shift_limits_m`; near the skin and on
the coarse levels that room is 0.5-4 mm). The sensor defaults are plausible orders of
magnitude for a small six-axis F/T sensor and a calibrated arm, not a particular product's
data sheet: set them to your hardware's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

import tissue
from envs.errors import EnvConfigError, finite_number, number_pair

#: Stream number mixed into the reset's seed for the randomisation's own generator.
_STREAM = 0x0D0_2A4D


@dataclass(frozen=True)
class DomainRandomization:
    """What varies between episodes (see the module docstring).

    Attributes:
        tissue_stiffness_scale: (low, high) factor on the bulk tissue's Young's modulus,
            drawn log-uniformly; (1, 1) keeps it.
        lesion_stiffness_ratio: (low, high) E_lesion / E_tissue, drawn log-uniformly; None
            keeps the tissue's.
        lesion_jitter_m: each lesion moves at rest by an offset drawn uniformly in a ball of
            this radius [m] (capped per lesion at 90 % of its room in the mesh); 0: no move.
        force_noise_n: standard deviation of the F/T force's noise per axis and step [N].
        torque_noise_nm: standard deviation of the F/T torque's noise [N m].
        force_bias_n: the force's bias per axis, uniform in +- this, drawn each reset [N].
        torque_bias_nm: the torque's bias per axis, as the force's [N m].
        position_noise_m: standard deviation of the observed probe position's noise per
            axis and step [m].
        rotation_noise_rad: standard deviation of the observed probe orientation's noise, a
            rotation vector's per-axis spread [rad].
    """

    tissue_stiffness_scale: tuple[float, float] = (0.6, 1.6)
    lesion_stiffness_ratio: tuple[float, float] | None = (2.0, 6.0)
    lesion_jitter_m: float = 0.001
    force_noise_n: float = 0.05
    torque_noise_nm: float = 0.002
    force_bias_n: float = 0.2
    torque_bias_nm: float = 0.01
    position_noise_m: float = 0.0005
    rotation_noise_rad: float = 0.005

    def __post_init__(self) -> None:
        self._check_range("tissue_stiffness_scale", 0.05, 20.0)
        if self.lesion_stiffness_ratio is not None:
            self._check_range("lesion_stiffness_ratio", 0.1, 100.0, " or None")
        for f in fields(self)[2:]:
            value = getattr(self, f.name)
            if not finite_number(value) or value < 0.0:
                raise EnvConfigError(
                    f"{f.name} must be a number >= 0 in SI units (0 switches it off); got {value!r}"
                )
            object.__setattr__(self, f.name, float(value))
        if self.lesion_jitter_m > 0.01:
            raise EnvConfigError(
                f"lesion_jitter_m must be at most 0.01 m (a lesion's room in the mesh is a few "
                f"millimetres); got {self.lesion_jitter_m!r}"
            )

    def _check_range(self, name: str, least: float, most: float, alternative: str = "") -> None:
        """Field ``name`` as (low, high) with least <= low <= high <= most, stored as floats."""
        value = getattr(self, name)
        pair = number_pair(value)
        low, high = pair if pair is not None else (math.nan, math.nan)
        if not least <= low <= high <= most:
            raise EnvConfigError(
                f"{name} must be (low, high) with {least:g} <= low <= high <= {most:g}"
                f"{alternative}; got {value!r}"
            )
        object.__setattr__(self, name, (low, high))

    @classmethod
    def parse(cls, value: Any) -> DomainRandomization | None:
        """From ``domain_randomization=``: False/None (off), True (the defaults), a dict of
        field names, or an instance."""
        if value is None or value is False:
            return None
        if value is True:
            return cls()
        if isinstance(value, cls):
            return value
        if isinstance(value, dict):
            valid = {f.name for f in fields(cls)}
            unknown = sorted(set(value) - valid)
            if unknown:
                raise EnvConfigError(
                    f"unknown domain_randomization setting(s) {unknown}; valid ones: "
                    f"{', '.join(sorted(valid))}"
                )
            return cls(**value)
        raise EnvConfigError(
            "domain_randomization must be True, False, a dict of settings or an "
            f"envs.DomainRandomization; got {value!r}"
        )

    @property
    def varies_tissue(self) -> bool:
        """Whether a reset builds a new tissue (stiffness or lesions vary)."""
        low, high = self.tissue_stiffness_scale
        return (
            low != high
            or low != 1.0
            or self.lesion_stiffness_ratio is not None
            or (self.lesion_jitter_m > 0.0)
        )


@dataclass(frozen=True)
class Variation:
    """One episode's draw (``info["variation"]`` at reset).

    Attributes:
        young_pa: the bulk tissue's Young's modulus [Pa].
        lesion_stiffness_ratio: E_lesion / E_tissue.
        lesion_offsets_m: each lesion's move at rest [m], (lesion_count, 3).
        force_bias_n: the F/T force's bias in the probe frame [N], (3,).
        torque_bias_nm: the F/T torque's bias [N m], (3,).
    """

    young_pa: float
    lesion_stiffness_ratio: float
    lesion_offsets_m: NDArray[np.float64]
    force_bias_n: NDArray[np.float64]
    torque_bias_nm: NDArray[np.float64]

    def as_info(self) -> dict[str, Any]:
        """Plain numbers and lists, for ``info``."""
        return {
            "young_pa": self.young_pa,
            "lesion_stiffness_ratio": self.lesion_stiffness_ratio,
            "lesion_offsets_m": self.lesion_offsets_m.tolist(),
            "force_bias_n": self.force_bias_n.tolist(),
            "torque_bias_nm": self.torque_bias_nm.tolist(),
        }


class Randomizer:
    """Draws the variations of :class:`DomainRandomization` for one environment.

    Args:
        settings: what varies.
        nominal: the tissue the environment was made with; variants are built from it.
    """

    def __init__(self, settings: DomainRandomization, nominal: tissue.Tissue) -> None:
        self.settings = settings
        self.nominal = nominal
        self._rng = np.random.default_rng(_STREAM)
        self._seeded = False
        self._room: NDArray[np.float64] | None = None
        self.variation: Variation | None = None

    def seed(self, seed: int | None) -> None:
        """Reseed from the reset's seed; without one, from fresh entropy the first time
        (later resets continue the stream, as Gymnasium's own generator does)."""
        if seed is not None:
            self._rng = np.random.default_rng([int(seed) & (2**63 - 1), _STREAM])
        elif not self._seeded:
            self._rng = np.random.default_rng()
        self._seeded = True

    def draw(self) -> tuple[Variation, tissue.Tissue]:
        """This episode's variation and its tissue (the nominal one where nothing of the
        tissue varies)."""
        s, rng = self.settings, self._rng
        base = self.nominal.resolved.materials
        scale = _log_uniform(rng, *s.tissue_stiffness_scale)
        young = base.tissue.young_pa * scale
        ratio = base.lesion_stiffness_ratio
        if s.lesion_stiffness_ratio is not None:
            ratio = _log_uniform(rng, *s.lesion_stiffness_ratio)
        count = len(self.nominal.lesions)
        offsets = np.zeros((count, 3))
        if s.lesion_jitter_m > 0.0 and count:
            radius = np.minimum(s.lesion_jitter_m, 0.9 * self._lesion_room())
            offsets = _in_ball(rng, count) * radius[:, None]
        force_bias = rng.uniform(-1.0, 1.0, 3) * s.force_bias_n
        torque_bias = rng.uniform(-1.0, 1.0, 3) * s.torque_bias_nm
        variation = Variation(young, ratio, offsets, force_bias, torque_bias)
        self.variation = variation
        if not s.varies_tissue:
            return variation, self.nominal
        materials = replace(base, tissue=replace(base.tissue, young_pa=young))
        materials = replace(materials, lesion_stiffness_ratio=ratio)
        # Where the lesions' blends overlap beyond the mesh's floor (rare: each lesion's own
        # room is respected), the same draw at half the size, then a quarter, then none:
        # deterministic, and never an error at reset.
        for share in (1.0, 0.5, 0.25, 0.0):
            shifted = share * offsets
            try:
                variant = self.nominal.varied(materials, shifted if np.any(shifted) else None)
            except tissue.TissueInputError:
                continue
            variation = Variation(young, ratio, shifted, force_bias, torque_bias)
            self.variation = variation
            return variation, variant
        raise AssertionError("unreachable: a variant without lesion offsets always builds")

    def noisy_wrench(self, wrench: NDArray[np.float64]) -> NDArray[np.float64]:
        """The F/T reading the policy sees: ``wrench`` (probe frame, (6,)) plus this episode's
        bias and fresh noise."""
        s, variation = self.settings, self.variation
        assert variation is not None
        noise = self._rng.standard_normal(6) * np.repeat([s.force_noise_n, s.torque_noise_nm], 3)
        bias = np.concatenate([variation.force_bias_n, variation.torque_bias_nm])
        return np.asarray(wrench + bias + noise)

    def pose_noise(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Fresh noise for the probe pose the arm reports: a position offset [m], (3,), and a
        rotation vector [rad], (3,), applied in the world frame."""
        s = self.settings
        position = self._rng.standard_normal(3) * s.position_noise_m
        return position, self._rng.standard_normal(3) * s.rotation_noise_rad

    def _lesion_room(self) -> NDArray[np.float64]:
        if self._room is None:
            self._room = self.nominal.lesion_shift_limits_m()
        return self._room


def _log_uniform(rng: np.random.Generator, low: float, high: float) -> float:
    if low == high:
        return float(low)
    return float(math.exp(rng.uniform(math.log(low), math.log(high))))


def _in_ball(rng: np.random.Generator, count: int) -> NDArray[np.float64]:
    """``count`` points uniform in the unit ball, (count, 3)."""
    direction = rng.standard_normal((count, 3))
    direction /= np.maximum(np.linalg.norm(direction, axis=1), 1e-12)[:, None]
    return np.asarray(direction * rng.uniform(0.0, 1.0, count)[:, None] ** (1.0 / 3.0))
