"""The B-mode image's settings (:class:`BModeConfig`) and its pixel labels."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from envs.errors import EnvConfigError
from envs.observations import ImagingConfig

#: Pixel labels (:meth:`BModeImager.locate`): no tissue, tissue, skin; lesion i (its index in
#: ``tissue.Tissue.lesions``) is ``LESION_FIRST_LABEL + i``.
OUTSIDE = 0
TISSUE = 1
SKIN = 2
LESION_FIRST_LABEL = 3

#: The observation's imaging geometry, whose aperture and depth the image shares.
_IMAGING = ImagingConfig()


@dataclass(frozen=True)
class BModeConfig:
    """How the B-mode image is made. Lengths in metres.

    Attributes:
        rows: image rows (depth samples), row 0 at the face.
        cols: image columns (lateral samples), from -aperture/2 to +aperture/2.
        aperture_m: image width, centred on the probe (default: ImagingConfig's, 40 mm).
        imaging_depth_m: deepest point imaged, from the face (default: ImagingConfig's, 50 mm).
        centre_frequency_mhz: the pulse's centre frequency [MHz] (7.5: inside the Telemed
            L12-5N40's 5-12 MHz band). It sets the attenuation with depth; the carrier
            itself enters as the reflectivity's phase (the package docstring).
        attenuation_db_cm_mhz: amplitude attenuation [dB/(cm MHz)], one way (breast tissue:
            about 0.75).
        tgc: time-gain compensation on: the mean attenuation is amplified back with depth.
        psf_lateral_m: lateral full width at half maximum of the point-spread function.
        psf_axial_m: axial full width at half maximum of the pulse envelope. The defaults
            span 3.2 and 1.5 of the default image's 0.31 x 0.39 mm pixels: a narrower PSF
            cannot be sampled on them.
        dynamic_range_db: the range of envelope levels log-compressed onto 0-255 [dB].
        scatterer_spacing_m: lattice spacing of the material-attached reflectivity: the
            speckle's grain before blurring. Below the pixel pitch the speckle aliases and
            no longer moves smoothly with sub-pixel motion.
        skin_thickness_m: depth below the rest skin drawn as skin.
        tissue_echogenicity: reflectivity scale of the breast tissue.
        lesion_echogenicity: of the lesions (below the tissue's: hypoechoic).
        skin_echogenicity: of the skin (above the tissue's: the bright line at the top).
        seed: which speckle pattern (the lattice's Gaussian values).
    """

    rows: int = 128
    cols: int = 128
    aperture_m: float = _IMAGING.aperture_m
    imaging_depth_m: float = _IMAGING.imaging_depth_m
    centre_frequency_mhz: float = 7.5
    attenuation_db_cm_mhz: float = 0.75
    tgc: bool = True
    psf_lateral_m: float = 1.0e-3
    psf_axial_m: float = 0.6e-3
    dynamic_range_db: float = 50.0
    scatterer_spacing_m: float = 0.4e-3
    skin_thickness_m: float = 1.5e-3
    tissue_echogenicity: float = 1.0
    lesion_echogenicity: float = 0.12
    skin_echogenicity: float = 4.0
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("rows", "cols"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
                raise EnvConfigError(f"BModeConfig.{name} must be an integer; got {value!r}")
            if not 8 <= value <= 4096:
                raise EnvConfigError(
                    f"BModeConfig.{name} must be between 8 and 4096 pixels; got {value!r}"
                )
        positive = (
            "aperture_m",
            "imaging_depth_m",
            "centre_frequency_mhz",
            "psf_lateral_m",
            "psf_axial_m",
            "dynamic_range_db",
            "scatterer_spacing_m",
        )
        non_negative = (
            "attenuation_db_cm_mhz",
            "skin_thickness_m",
            "tissue_echogenicity",
            "lesion_echogenicity",
            "skin_echogenicity",
        )
        for name in positive + non_negative:
            value = getattr(self, name)
            number = isinstance(value, (int, float, np.integer, np.floating))
            if isinstance(value, bool) or not number or not np.isfinite(value):
                raise EnvConfigError(f"BModeConfig.{name} must be a finite number; got {value!r}")
            if name in positive and value <= 0:
                raise EnvConfigError(
                    f"BModeConfig.{name} must be positive; got {value!r} (units: see "
                    "BModeConfig's docstring, lengths in metres)"
                )
            if value < 0:
                raise EnvConfigError(f"BModeConfig.{name} must be >= 0; got {value!r}")
        if not isinstance(self.tgc, bool):
            raise EnvConfigError(f"BModeConfig.tgc must be True or False; got {self.tgc!r}")
        seed = self.seed
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise EnvConfigError(f"BModeConfig.seed must be an integer >= 0; got {seed!r}")

    @property
    def lateral_pitch_m(self) -> float:
        """Column spacing [m]."""
        return self.aperture_m / self.cols

    @property
    def axial_pitch_m(self) -> float:
        """Row spacing [m]."""
        return self.imaging_depth_m / self.rows
