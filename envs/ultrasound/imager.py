"""The B-mode imager: the image plane located in the deformed mesh, then speckle, the
convolution model and log compression (the package docstring)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.ndimage
import scipy.spatial
from numpy.typing import ArrayLike, NDArray

import tissue
from envs.errors import EnvConfigError
from envs.ultrasound.config import LESION_FIRST_LABEL, OUTSIDE, SKIN, TISSUE, BModeConfig
from envs.ultrasound.kernels import TABLE_BITS, label_pixels, locate_pixels, reflectivity

#: FWHM of a Gaussian over its standard deviation: 2 sqrt(2 ln 2).
_FWHM_PER_SIGMA = 2.0 * math.sqrt(2.0 * math.log(2.0))
#: The display's top (255), above the RMS envelope of unit-echogenicity tissue [dB]: the
#: tissue's mean level sits mid-grey and the skin's speckle peaks (4 x: +12 dB, and a
#: Rayleigh envelope's 99th percentile is 6.6 dB above its RMS) below it.
_DISPLAY_TOP_DB = 18.0
#: Each node's distance to the rest skin [m]: samples on the skin this far apart for nodes
#: within _SKIN_NEAR_M of it, _SKIN_FAR_SAMPLE_M apart for the others.
_SKIN_SAMPLE_M = 0.5e-3
_SKIN_NEAR_M = 4e-3
_SKIN_FAR_SAMPLE_M = 2e-3


@dataclass(frozen=True)
class PlaneSample:
    """What lies under each pixel of the image plane (:meth:`BModeImager.locate`).

    Attributes:
        labels: (rows, cols) int32: ``OUTSIDE``, ``TISSUE``, ``SKIN`` or
            ``LESION_FIRST_LABEL + i`` for lesion i.
        tets: (rows, cols) int64: the deformed tet holding the pixel's centre, -1 outside.
        material_m: (rows, cols, 3): the pixel centre's rest (material) coordinate [m],
            NaN outside.
    """

    labels: NDArray[np.int32]
    tets: NDArray[np.int64]
    material_m: NDArray[np.float64]


class BModeImager:
    """B-mode images of one tissue's image plane (the ``envs.ultrasound`` docstring).

    Built once per tissue (its rest mesh, lesions and skin); each frame takes the current
    node positions and the probe's pose.

    Args:
        model: the tissue (``tissue.Tissue``): its rest nodes, tets and lesions are read.
        config: the image's settings; default ``BModeConfig()``.

    Raises:
        EnvConfigError: ``model`` is not a tissue or ``config`` not a ``BModeConfig``.
    """

    def __init__(self, model: tissue.Tissue, config: BModeConfig | None = None) -> None:
        if not isinstance(model, tissue.Tissue):
            raise EnvConfigError(
                f"BModeImager takes a tissue.Tissue (tissue.make_tissue(...)); got "
                f"{type(model).__name__}"
            )
        config = BModeConfig() if config is None else config
        if not isinstance(config, BModeConfig):
            raise EnvConfigError(
                f"config must be a BModeConfig; got {type(config).__name__}: build one with "
                "envs.ultrasound.BModeConfig(...)"
            )
        self.config = config
        self._rest = np.ascontiguousarray(model.rest_nodes_m, dtype=np.float64)
        self._tets = np.ascontiguousarray(model.tets, dtype=np.int64)
        lesions = list(model.lesions)
        self._lesion_centres = np.array(
            [lesion.rest_centre_m for lesion in lesions], dtype=np.float64
        ).reshape(-1, 3)
        self._lesion_radii = np.array([lesion.radius_m for lesion in lesions], dtype=np.float64)
        self._skin_depth = _node_skin_depth(self._rest, self._tets, model.fixed_nodes)
        table = np.random.default_rng(config.seed).standard_normal((2, 1 << TABLE_BITS))
        self._table = np.ascontiguousarray(table / math.sqrt(2.0))  # E|z|^2 = 1
        du, dv = config.lateral_pitch_m, config.axial_pitch_m
        self._kernel_lateral = _gaussian_taps(config.psf_lateral_m / du)
        self._kernel_axial = _gaussian_taps(config.psf_axial_m / dv)
        # Pixels are located on a grid padded by the kernels' half-widths, so that the
        # convolution sees the tissue beyond the image's edges.
        self._pad_cols = self._kernel_lateral.size // 2
        self._pad_rows = self._kernel_axial.size // 2
        self.lateral_m = -0.5 * config.aperture_m + (np.arange(config.cols) + 0.5) * du
        self.depth_m = (np.arange(config.rows) + 0.5) * dv
        self._lateral_padded = (
            -0.5 * config.aperture_m
            + (np.arange(-self._pad_cols, config.cols + self._pad_cols) + 0.5) * du
        )
        self._depth_padded = (np.arange(-self._pad_rows, config.rows + self._pad_rows) + 0.5) * dv
        # Two-way amplitude attenuation exp(-2 alpha f d) per row, alpha in Np/(cm MHz).
        alpha_np = config.attenuation_db_cm_mhz * math.log(10.0) / 20.0
        attenuation = np.exp(-2.0 * alpha_np * config.centre_frequency_mhz * 100.0 * self.depth_m)
        self._row_gain = np.ones_like(attenuation) if config.tgc else attenuation
        self._reference = self._reference_level()

    # ------------------------------------------------------------------ frames

    def locate(
        self,
        tissue_or_positions: tissue.Tissue | ArrayLike,
        probe_position_m: ArrayLike,
        probe_quat_wxyz: ArrayLike,
    ) -> PlaneSample:
        """Which tet, material point and label lies under each pixel centre.

        Args:
            tissue_or_positions: the tissue (its current node positions are read) or the
                node positions [m], (node_count, 3).
            probe_position_m: the probe origin (face centre) [m], (3,), world frame.
            probe_quat_wxyz: its orientation (w, x, y, z), (4,), any non-zero norm.
        """
        padded = self._locate_padded(tissue_or_positions, probe_position_m, probe_quat_wxyz)
        crop = self._crop
        return PlaneSample(padded.labels[crop], padded.tets[crop], padded.material_m[crop])

    def labels(
        self,
        tissue_or_positions: tissue.Tissue | ArrayLike,
        probe_position_m: ArrayLike,
        probe_quat_wxyz: ArrayLike,
    ) -> NDArray[np.int32]:
        """The label image used before speckle, (rows, cols) int32 (:meth:`locate`)."""
        return self.locate(tissue_or_positions, probe_position_m, probe_quat_wxyz).labels

    def image(
        self,
        tissue_or_positions: tissue.Tissue | ArrayLike,
        probe_position_m: ArrayLike,
        probe_quat_wxyz: ArrayLike,
        in_contact: bool,
    ) -> NDArray[np.uint8]:
        """The B-mode image, (rows, cols) uint8, row 0 at the face (the package docstring).

        Args:
            tissue_or_positions, probe_position_m, probe_quat_wxyz: as for :meth:`locate`.
            in_contact: whether the face touches the skin; without contact the image is
                black (no coupling).
        """
        if not isinstance(in_contact, (bool, np.bool_)):
            raise EnvConfigError(f"in_contact must be True or False; got {in_contact!r}")
        config = self.config
        if not in_contact:
            self._positions(tissue_or_positions)  # bad input is refused all the same
            _pose(probe_position_m, probe_quat_wxyz)
            return np.zeros((config.rows, config.cols), dtype=np.uint8)
        sample = self._locate_padded(tissue_or_positions, probe_position_m, probe_quat_wxyz)
        echo = np.zeros(LESION_FIRST_LABEL + 1)
        echo[TISSUE] = config.tissue_echogenicity
        echo[SKIN] = config.skin_echogenicity
        echo[LESION_FIRST_LABEL] = config.lesion_echogenicity  # every lesion alike
        labels = np.minimum(sample.labels, LESION_FIRST_LABEL)
        envelope = self._envelope(sample.material_m, echo[labels])
        envelope *= self._row_gain[:, None] / self._reference
        level_db = 20.0 * np.log10(np.maximum(envelope, 1e-12))
        scale = (level_db - (_DISPLAY_TOP_DB - config.dynamic_range_db)) / config.dynamic_range_db
        gray = np.rint(255.0 * np.clip(scale, 0.0, 1.0))
        gray[sample.labels[self._crop] == OUTSIDE] = 0.0
        return gray.astype(np.uint8)

    # ------------------------------------------------------------------ internals

    @property
    def _crop(self) -> tuple[slice, slice]:
        rows, cols = self.config.rows, self.config.cols
        return (
            slice(self._pad_rows, self._pad_rows + rows),
            slice(self._pad_cols, self._pad_cols + cols),
        )

    def _locate_padded(
        self,
        tissue_or_positions: tissue.Tissue | ArrayLike,
        probe_position_m: ArrayLike,
        probe_quat_wxyz: ArrayLike,
    ) -> PlaneSample:
        positions = self._positions(tissue_or_positions)
        origin, rotation = _pose(probe_position_m, probe_quat_wxyz)
        local = np.ascontiguousarray((positions - origin) @ rotation)  # probe frame
        rows, cols = self._depth_padded.size, self._lateral_padded.size
        tets = np.empty((rows, cols), dtype=np.int64)
        weights = np.empty((rows, cols, 4), dtype=np.float64)
        locate_pixels(local, self._tets, self._lateral_padded, self._depth_padded, tets, weights)
        labels = np.empty((rows, cols), dtype=np.int32)
        material = np.empty((rows, cols, 3), dtype=np.float64)
        label_pixels(
            tets,
            weights,
            self._tets,
            self._rest,
            self._skin_depth,
            self._lesion_centres,
            self._lesion_radii,
            self.config.skin_thickness_m,
            labels,
            material,
        )
        return PlaneSample(labels, tets, material)

    def _positions(self, tissue_or_positions: tissue.Tissue | ArrayLike) -> NDArray[np.float64]:
        if isinstance(tissue_or_positions, tissue.Tissue):
            return np.asarray(tissue_or_positions.positions_m, dtype=np.float64)
        positions = np.asarray(tissue_or_positions, dtype=np.float64)
        if positions.shape != self._rest.shape or not np.all(np.isfinite(positions)):
            raise EnvConfigError(
                f"node positions must be finite, shape {self._rest.shape} [m] (this tissue's "
                f"nodes); got shape {positions.shape}: pass the tissue or its positions_m"
            )
        return positions

    def _envelope(
        self, material: NDArray[np.float64], echogenicity: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        """|reflectivity * PSF envelope| on the image (cropped), from the padded grid's
        material coordinates [m] (r, c, 3) (NaN: no tissue) and echogenicities (r, c)."""
        real = np.empty(echogenicity.shape)
        imag = np.empty(echogenicity.shape)
        reflectivity(
            material, echogenicity, self.config.scatterer_spacing_m, self._table, real, imag
        )
        signal = real + 1j * imag
        # The separable PSF envelope: along the rows (lateral), then down the columns (axial).
        signal = scipy.ndimage.correlate1d(signal, self._kernel_lateral, axis=1, mode="constant")
        signal = scipy.ndimage.correlate1d(signal, self._kernel_axial, axis=0, mode="constant")
        return np.abs(signal[self._crop])

    def _reference_level(self) -> float:
        """RMS envelope of unit-echogenicity tissue, unstrained and unattenuated: 0 dB."""
        rows, cols = self._depth_padded.size, self._lateral_padded.size
        lateral, depth = np.meshgrid(self._lateral_padded, self._depth_padded)
        power = []
        for plane in range(4):  # four planes apart in the lattice: a steadier estimate
            material = np.stack(
                [lateral + 0.1 * plane, depth, np.full_like(depth, 0.0123 * plane)], axis=-1
            )
            power.append(np.mean(self._envelope(material, np.ones((rows, cols))) ** 2))
        return float(np.sqrt(np.mean(power)))


def _pose(
    position: ArrayLike, quat_wxyz: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The probe's origin [m] (3,) and rotation (3, 3) (columns: its axes in the world)."""
    origin = np.asarray(position, dtype=np.float64).reshape(-1)
    if origin.shape != (3,) or not np.all(np.isfinite(origin)):
        raise EnvConfigError(f"probe position must be 3 finite numbers [m]; got {position!r}")
    quat = np.asarray(quat_wxyz, dtype=np.float64).reshape(-1)
    norm = float(np.linalg.norm(quat)) if quat.shape == (4,) else 0.0
    if not (np.isfinite(norm) and norm > 0.0):
        raise EnvConfigError(
            f"probe quaternion must be 4 finite numbers (w, x, y, z), not all zero; got "
            f"{quat_wxyz!r}"
        )
    w, x, y, z = quat / norm
    rotation = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )
    return origin, rotation


def _gaussian_taps(fwhm_pixels: float) -> NDArray[np.float64]:
    """Gaussian taps of a FWHM [pixels], out to 3 standard deviations, peak 1."""
    sigma = fwhm_pixels / _FWHM_PER_SIGMA
    half = max(1, math.ceil(3.0 * sigma))
    offsets = np.arange(-half, half + 1, dtype=np.float64)
    return np.exp(-0.5 * (offsets / sigma) ** 2)


def _node_skin_depth(
    rest: NDArray[np.float64], tets: NDArray[np.int64], fixed: NDArray[np.int64]
) -> NDArray[np.float64]:
    """Each rest node's distance to the skin [m], (node_count,): the skin is the tet mesh's
    boundary less the faces on the fixed chest wall.

    The distance to the nearest of points sampled on the skin: every ``_SKIN_SAMPLE_M``
    for nodes within ``_SKIN_NEAR_M`` of it, every ``_SKIN_FAR_SAMPLE_M`` beyond (a
    nearest-neighbour query among dense samples is slow far from the surface: many samples
    lie nearly as far). A skin point is at most spacing / sqrt(3) from a sample: the far
    nodes' distances are then at most 0.2 mm too long, the near ones' 0.1 mm at 0.5 mm deep.
    """
    faces = np.sort(tets[:, [[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]]].reshape(-1, 3), axis=1)
    unique, counts = np.unique(faces, axis=0, return_counts=True)
    boundary = unique[counts == 1]
    on_wall = np.isin(boundary, np.asarray(fixed)).all(axis=1)
    corners = rest[boundary[~on_wall]]  # (skin triangles, 3 corners, 3)
    if corners.size == 0:
        return np.full(rest.shape[0], np.inf)
    near = scipy.spatial.cKDTree(_triangle_samples(corners, _SKIN_SAMPLE_M))
    depth, _ = near.query(rest, distance_upper_bound=_SKIN_NEAR_M)
    far = ~np.isfinite(depth)
    if far.any():
        coarse = scipy.spatial.cKDTree(_triangle_samples(corners, _SKIN_FAR_SAMPLE_M))
        depth[far], _ = coarse.query(rest[far])
    return np.asarray(depth, dtype=np.float64)


def _triangle_samples(corners: NDArray[np.float64], spacing: float) -> NDArray[np.float64]:
    """Points on triangles (t, 3 corners, 3) [m], their edges split every ``spacing`` [m]
    at most (corners included), (samples, 3)."""
    longest = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2).max(axis=1)
    splits = np.maximum(1, np.ceil(longest / spacing)).astype(np.int64)
    samples = []
    for split in np.unique(splits):
        i, j = np.meshgrid(np.arange(split + 1), np.arange(split + 1), indexing="ij")
        keep = i + j <= split
        bary = np.stack([i[keep], j[keep], split - i[keep] - j[keep]], axis=1) / split
        samples.append(np.einsum("sk,fkd->fsd", bary, corners[splits == split]).reshape(-1, 3))
    return np.concatenate(samples)
