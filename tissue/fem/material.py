"""Hyperelastic material laws and per-region parameters (Pa, kg/m^3).

Two compressible neo-Hookean laws are offered, both parameterised by Young's modulus E and
Poisson's ratio nu so that their small-strain response is linear elasticity with Lamé
parameters mu = E / (2 (1 + nu)) and lambda = E nu / ((1 + nu)(1 - 2 nu)):

* ``stable`` (default): the stable neo-Hookean energy of Smith, de Goes & Kim (2018, ACM TOG
  37(2):12) with the origin barrier removed as in Kim & Eberle (2022, SIGGRAPH course
  "Dynamic deformables"):

      W = mu/2 (I_C - 3) + lambda'/2 (J - alpha)^2,   lambda' = lambda + mu,
      alpha = 1 + mu / lambda'.

  It is finite and restoring for inverted tets (J <= 0); at rest the stress vanishes and the
  linearisation gives Lamé (mu, lambda) exactly.
* ``classic``: the form of SOFA's ``NeoHookean`` used by the paper (Bonet & Wood),
  W = mu/2 (I_C - 3) - mu ln J + lambda/2 (ln J)^2. Undefined for J <= 0: an inverted tet
  is reported as a step failure, as the paper's framework would fail there.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from tissue.choices import Choice
from tissue.errors import MaterialError, TissueInputError


class MaterialLaw(Choice):
    """The hyperelastic energy used for every tet."""

    STABLE = "stable"
    CLASSIC = "classic"

    @classmethod
    def noun(cls) -> str:
        return "material law"

    @classmethod
    def error(cls) -> type[TissueInputError]:
        return MaterialError


# Moduli beyond these [Pa] are not a tissue (and their energies and forces overflow double
# precision on a mesh): steel's E is 2e11 Pa.
_STIFFEST_PA = 1e12
_LARGEST_LAMBDA_PA = 1e15


@dataclass(frozen=True)
class NeoHookean:
    """Isotropic compressible neo-Hookean parameters of one region.

    Attributes:
        young_pa: Young's modulus E [Pa], > 0.
        poisson: Poisson's ratio nu, in (-1, 0.5).
        density_kg_m3: mass density [kg/m^3], > 0.
    """

    young_pa: float = 2850.0
    poisson: float = 0.49
    density_kg_m3: float = 1075.0

    def __post_init__(self) -> None:
        if not np.isfinite(self.young_pa) or self.young_pa <= 0:
            raise MaterialError(
                f"Young's modulus must be a positive number of pascals; got {self.young_pa!r} "
                "(breast tissue is about 3e3 Pa)"
            )
        if not np.isfinite(self.poisson) or not -1.0 < self.poisson < 0.5:
            raise MaterialError(
                f"Poisson's ratio must lie in (-1, 0.5); got {self.poisson!r} "
                "(near-incompressible tissue: 0.45 to 0.499)"
            )
        if self.young_pa > _STIFFEST_PA:
            raise MaterialError(
                f"Young's modulus {self.young_pa:g} Pa is stiffer than any solid (steel: 2e11 "
                f"Pa; the limit here is {_STIFFEST_PA:g}); give pascals (tissue: about 3e3)"
            )
        lame = self.lambda_pa
        if not (np.isfinite(lame) and np.isfinite(self.mu_pa)) or lame > _LARGEST_LAMBDA_PA:
            raise MaterialError(
                f"E = {self.young_pa:g} Pa with nu = {self.poisson!r} gives a first Lame "
                f"parameter of {lame:g} Pa, beyond {_LARGEST_LAMBDA_PA:g}: forces would overflow; "
                "lower nu (0.49 models near-incompressible tissue) or E"
            )
        if not np.isfinite(self.density_kg_m3) or self.density_kg_m3 <= 0:
            raise MaterialError(
                f"density must be a positive number of kg/m^3; got {self.density_kg_m3!r} "
                "(soft tissue is about 1075 kg/m^3)"
            )

    @property
    def mu_pa(self) -> float:
        """Shear modulus mu [Pa]."""
        return self.young_pa / (2.0 * (1.0 + self.poisson))

    @property
    def lambda_pa(self) -> float:
        """First Lamé parameter lambda [Pa]."""
        return self.young_pa * self.poisson / ((1.0 + self.poisson) * (1.0 - 2.0 * self.poisson))

    def scaled(self, stiffness_ratio: float) -> NeoHookean:
        """The same material with E multiplied by ``stiffness_ratio``."""
        return NeoHookean(self.young_pa * stiffness_ratio, self.poisson, self.density_kg_m3)


@dataclass(frozen=True)
class TissueMaterials:
    """Materials of every region: bulk tissue (label 0) and lesions (labels 1..).

    Defaults follow the authors' public scene (E = 2850 Pa, nu = 0.49, 1075 kg/m^3), with
    lesions 4 x stiffer than the tissue (Samani et al. 2007, Phys Med Biol 52:1565, report
    3-6 x for fibrocystic and malignant tumours).

    Attributes:
        tissue: the bulk material.
        lesion_stiffness_ratio: E_lesion / E_tissue for lesions without an override.
        lesion_overrides: explicit materials per lesion label (1-based), as pairs.
        law: the hyperelastic energy.
    """

    tissue: NeoHookean = field(default_factory=NeoHookean)
    lesion_stiffness_ratio: float = 4.0
    lesion_overrides: tuple[tuple[int, NeoHookean], ...] = ()
    law: MaterialLaw | str = MaterialLaw.STABLE

    def __post_init__(self) -> None:
        object.__setattr__(self, "law", MaterialLaw.parse(self.law))
        if not np.isfinite(self.lesion_stiffness_ratio) or self.lesion_stiffness_ratio <= 0:
            raise MaterialError(
                "lesion_stiffness_ratio must be a positive number; got "
                f"{self.lesion_stiffness_ratio!r} (tumours are 3-6 x stiffer than tissue)"
            )
        for label, _ in self.lesion_overrides:
            if label < 1:
                raise MaterialError(
                    f"lesion override labels start at 1 (0 is the bulk tissue); got {label}"
                )

    def region_material(self, label: int) -> NeoHookean:
        """The material of region ``label`` (0 = tissue, k = lesion k)."""
        if label == 0:
            return self.tissue
        for override_label, material in self.lesion_overrides:
            if override_label == label:
                return material
        return self.tissue.scaled(self.lesion_stiffness_ratio)

    def per_tet(self, region: NDArray[np.int64]) -> tuple[NDArray[np.float64], ...]:
        """Per-tet (mu [Pa], lambda [Pa], density [kg/m^3]), each shape (tet_count,)."""
        labels = np.unique(region)
        mu = np.empty(region.shape[0])
        lam = np.empty(region.shape[0])
        rho = np.empty(region.shape[0])
        for label in labels:
            material = self.region_material(int(label))
            mask = region == label
            mu[mask] = material.mu_pa
            lam[mask] = material.lambda_pa
            rho[mask] = material.density_kg_m3
        return mu, lam, rho
