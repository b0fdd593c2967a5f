"""The B-mode imager (``envs.ultrasound``): its geometry against the lesion observation,
speckle that moves with the tissue, and its contract (no contact, dtype, determinism, bad
settings). On the 1,363-tet phantom (1,303 tets), where each lesion is four tets."""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np
import pytest
from numpy.lib.stride_tricks import sliding_window_view
from numpy.typing import NDArray

import tissue
from envs.errors import EnvConfigError
from envs.observations import ImagingConfig, lesion_in_image
from envs.ultrasound import LESION_FIRST_LABEL, OUTSIDE, TISSUE, BModeConfig, BModeImager

LESIONS = (0, 2, 5)  # 4.0, 5.0 and 4.5 mm radius; 15, 14 and 21 mm deep under the probe
PRESS_M = 0.005
STEP_M = 0.0002  # 0.2 mm a tissue step: 10 mm/s at 20 ms


@pytest.fixture(scope="module")
def phantom() -> tissue.Tissue:
    return tissue.make_tissue(tissue.TissueSpec(mesh=1363, contact="lm", profile="robust"))


@pytest.fixture(scope="module")
def imager(phantom: tissue.Tissue) -> BModeImager:
    return BModeImager(phantom)


def _rotation(quat: NDArray[np.float64]) -> NDArray[np.float64]:
    """Probe-to-world rotation, by MuJoCo (independent of the imager's own conversion)."""
    matrix = np.empty(9)
    mujoco.mju_quat2Mat(matrix, np.asarray(quat, dtype=np.float64))
    return matrix.reshape(3, 3)


def _press(t: tissue.Tissue, start: NDArray, quat: NDArray, depth_m: float) -> tissue.TissueStep:
    """Step the probe from ``start`` along its pressing direction by ``depth_m``."""
    direction = tissue.pressing_direction(quat)
    steps = max(1, round(depth_m / STEP_M))
    for k in range(1, steps + 1):
        step = t.step(start + depth_m * k / steps * direction, quat)
        assert step.ok, step.status
    return step


def _lesion_centroid(imager: BModeImager, labels: NDArray, index: int) -> tuple[float, float]:
    """(lateral, depth) [m] of lesion ``index``'s labelled pixels."""
    rows, cols = np.nonzero(labels == LESION_FIRST_LABEL + index)
    assert rows.size > 50, f"lesion {index} has only {rows.size} pixels in the image"
    return float(imager.lateral_m[cols].mean()), float(imager.depth_m[rows].mean())


@dataclass(frozen=True)
class Pressed:
    """Lesion ``index``'s centroid in the image and in the observation, at the touching
    pose and 5 mm deeper: (lateral, depth) [m] each."""

    index: int
    image_rest: tuple[float, float]
    observed_rest: tuple[float, float]
    image_pressed: tuple[float, float]
    observed_pressed: tuple[float, float]
    labels_rest: NDArray[np.int32]


@pytest.fixture(scope="module", params=LESIONS)
def pressed(request: pytest.FixtureRequest, phantom: tissue.Tissue, imager: BModeImager) -> Pressed:
    index = request.param
    lesion = phantom.lesions[index]
    position, quat = phantom.touching_pose(lesion.rest_centre_m)
    phantom.reset(position, quat)
    rotation = _rotation(quat)
    imaging = ImagingConfig()

    def observed(centroid: NDArray, probe: NDArray) -> tuple[float, float]:
        seen = lesion_in_image(centroid, lesion.radius_m, probe, rotation, 1.0, imaging)
        return seen.true_lateral_m, seen.true_depth_m

    labels_rest = imager.labels(phantom, position, quat)
    step = _press(phantom, position, quat, PRESS_M)
    probe = position + PRESS_M * tissue.pressing_direction(quat)
    return Pressed(
        index,
        _lesion_centroid(imager, labels_rest, index),
        observed(lesion.rest_centre_m, position),
        _lesion_centroid(imager, imager.labels(phantom, probe, quat), index),
        observed(step.lesion_centroids_world_m[index], probe),
        labels_rest,
    )


def test_the_lesion_lies_where_the_observation_says_at_rest_and_pressed(
    pressed: Pressed,
) -> None:
    """The lesion's labelled pixels (its rest sphere through the deformation) centre on
    ``lesion_in_image``'s (lateral, depth) of its deformed volume centroid within 1 mm."""
    for image, observed in (
        (pressed.image_rest, pressed.observed_rest),
        (pressed.image_pressed, pressed.observed_pressed),
    ):
        error = np.hypot(image[0] - observed[0], image[1] - observed[1])
        assert error < 1e-3, (pressed.index, image, observed)


def test_pressing_moves_the_lesion_up_the_image(pressed: Pressed) -> None:
    """A 5 mm press brings the lesion closer to the face, by less than the press (the
    tissue above it is compressed too)."""
    rise = pressed.image_rest[1] - pressed.image_pressed[1]
    assert 0.5e-3 < rise < PRESS_M, (pressed.index, rise)


def test_a_lesion_of_four_tets_shows_round_and_of_its_size(
    pressed: Pressed, imager: BModeImager, phantom: tissue.Tissue
) -> None:
    """At rest the plane passes through the lesion's centre: its pixels cover a disc of its
    radius (area within 5 %, as wide as deep within two pixels)."""
    radius = phantom.lesions[pressed.index].radius_m
    rows, cols = np.nonzero(pressed.labels_rest == LESION_FIRST_LABEL + pressed.index)
    config = imager.config
    area = rows.size * config.lateral_pitch_m * config.axial_pitch_m
    assert area == pytest.approx(np.pi * radius**2, rel=0.05)
    width = (np.ptp(cols) + 1) * config.lateral_pitch_m
    height = (np.ptp(rows) + 1) * config.axial_pitch_m
    assert abs(width - height) < 2 * config.axial_pitch_m, (width, height)


# ---------------------------------------------------------------------- speckle tracking


WINDOW = 16
SEARCH = 8


def _block_match(before: NDArray, after: NDArray, row: int, col: int) -> tuple[float, float]:
    """Where the 16 x 16 window at (row, col) of ``before`` went in ``after`` [pixels]
    (rows, cols): normalised cross-correlation over +-8 pixels, sub-pixel by a parabola
    through the peak and its neighbours along each axis."""
    template = before[row : row + WINDOW, col : col + WINDOW].astype(np.float64)
    template = (template - template.mean()) / template.std()
    region = after[
        row - SEARCH : row + SEARCH + WINDOW, col - SEARCH : col + SEARCH + WINDOW
    ].astype(np.float64)
    windows = sliding_window_view(region, (WINDOW, WINDOW))  # (17, 17, 16, 16)
    centred = windows - windows.mean(axis=(2, 3), keepdims=True)
    spread = np.sqrt((centred**2).mean(axis=(2, 3))) + 1e-12
    score = (centred * template).mean(axis=(2, 3)) / spread
    peak_r, peak_c = np.unravel_index(np.argmax(score), score.shape)

    def vertex(minus: float, centre: float, plus: float) -> float:
        curvature = minus - 2.0 * centre + plus
        return 0.0 if curvature >= 0.0 else 0.5 * (minus - plus) / curvature

    last = 2 * SEARCH
    d_r = vertex(*score[peak_r - 1 : peak_r + 2, peak_c]) if 0 < peak_r < last else 0.0
    d_c = vertex(*score[peak_r, peak_c - 1 : peak_c + 2]) if 0 < peak_c < last else 0.0
    return peak_r - SEARCH + d_r, peak_c - SEARCH + d_c


def _where_now(phantom: tissue.Tissue, material: NDArray, positions: NDArray) -> NDArray:
    """Where material points [m] (p, 3) are with the nodes at ``positions`` [m]: each found
    in the rest mesh (the tet where its least barycentric coordinate is greatest) and
    mapped through that tet's deformation."""
    rest, tets = phantom.rest_nodes_m, phantom.tets
    edges = rest[tets[:, 1:]] - rest[tets[:, :1]]  # (t, 3 edges, 3)
    inverse = np.linalg.inv(edges.transpose(0, 2, 1))
    local = np.einsum("tij,ptj->pti", inverse, material[:, None, :] - rest[tets[:, 0]][None])
    bary = np.concatenate([1.0 - local.sum(axis=2, keepdims=True), local], axis=2)
    best = np.argmax(bary.min(axis=2), axis=1)
    weights = bary[np.arange(material.shape[0]), best]
    assert weights.min() > -1e-9, "a material point outside the rest mesh"
    return np.einsum("pk,pkd->pd", weights, positions[tets[best]])


@dataclass(frozen=True)
class Frames:
    """Two frames of a small press and the FE motion under tracking windows.

    Attributes:
        before, after: the images (rows, cols) uint8 before and after the press.
        fresh_noise: ``after`` imaged with another speckle seed (noise made anew each frame).
        corners: (row, col) of each 16 x 16 window's top-left pixel.
        fe_shift_m: each window's mean in-plane motion of its material points, (lateral,
            depth) [m], (windows, 2).
    """

    before: NDArray[np.uint8]
    after: NDArray[np.uint8]
    fresh_noise: NDArray[np.uint8]
    corners: list[tuple[int, int]]
    fe_shift_m: NDArray[np.float64]


@pytest.fixture(scope="module")
def frames(phantom: tissue.Tissue, imager: BModeImager) -> Frames:
    """2 mm into the skin above lesion 0, then 0.4 mm deeper."""
    position, quat = phantom.touching_pose(phantom.lesions[0].rest_centre_m)
    phantom.reset(position, quat)
    direction = tissue.pressing_direction(quat)
    _press(phantom, position, quat, 0.002)
    first = position + 0.002 * direction
    before = imager.image(phantom, first, quat, True)
    sample = imager.locate(phantom, first, quat)
    _press(phantom, first, quat, 0.0004)
    second = first + 0.0004 * direction
    after = imager.image(phantom, second, quat, True)
    fresh_noise = BModeImager(phantom, BModeConfig(seed=1)).image(phantom, second, quat, True)
    rotation = _rotation(quat)
    corners, shifts = [], []
    rows, cols = before.shape
    for row in range(SEARCH + 2, rows - WINDOW - SEARCH, 12):
        for col in range(SEARCH + 2, cols - WINDOW - SEARCH, 12):
            # Tissue under the window and its search region: no lesion, skin or air.
            reach = (
                slice(row - SEARCH, row + WINDOW + SEARCH),
                slice(col - SEARCH, col + WINDOW + SEARCH),
            )
            if not np.all(sample.labels[reach] == TISSUE):
                continue
            material = sample.material_m[row : row + WINDOW, col : col + WINDOW].reshape(-1, 3)
            now = (_where_now(phantom, material, phantom.positions_m) - second) @ rotation
            lateral, depth = np.meshgrid(
                imager.lateral_m[col : col + WINDOW], imager.depth_m[row : row + WINDOW]
            )
            shifts.append(
                [np.mean(now[:, 0] - lateral.ravel()), np.mean(now[:, 1] - depth.ravel())]
            )
            corners.append((row, col))
    assert len(corners) >= 10, f"only {len(corners)} windows in tissue"
    return Frames(before, after, fresh_noise, corners, np.array(shifts))


def _tracking_errors(imager: BModeImager, frames: Frames, after: NDArray) -> NDArray:
    """|block-matched shift - FE shift| [m] per window, (windows,)."""
    pitch = np.array([imager.config.lateral_pitch_m, imager.config.axial_pitch_m])
    measured = []
    for row, col in frames.corners:
        d_row, d_col = _block_match(frames.before, after, row, col)
        measured.append(np.array([d_col, d_row]) * pitch)
    return np.linalg.norm(np.array(measured) - frames.fe_shift_m, axis=1)


def _tracks_the_tissue(errors: NDArray, fe_shift_m: NDArray) -> bool:
    """Every window within 0.5 mm of the FE motion, and the typical error under a third of
    the typical motion (a speckle that stayed put would be off by the whole motion)."""
    typical_motion = float(np.median(np.linalg.norm(fe_shift_m, axis=1)))
    return bool(errors.max() < 0.5e-3 and np.median(errors) < typical_motion / 3.0)


def test_speckle_moves_with_the_tissue(imager: BModeImager, frames: Frames) -> None:
    errors = _tracking_errors(imager, frames, frames.after)
    motion = np.linalg.norm(frames.fe_shift_m, axis=1)
    assert _tracks_the_tissue(errors, frames.fe_shift_m), (
        f"tracking errors {np.round(1e3 * errors, 3)} mm; FE motion {np.round(1e3 * motion, 3)} mm"
    )


def test_the_speckle_check_fails_for_fresh_noise_and_for_a_still_pattern(
    imager: BModeImager, frames: Frames
) -> None:
    """The check above can fail: noise drawn anew for the second frame, or a speckle that
    does not move (the first frame again), are told apart from the tissue's motion."""
    fresh = _tracking_errors(imager, frames, frames.fresh_noise)
    assert not _tracks_the_tissue(fresh, frames.fe_shift_m), np.round(1e3 * fresh, 3)
    assert np.median(fresh) > 0.5e-3
    still = _tracking_errors(imager, frames, frames.before)
    assert not _tracks_the_tissue(still, frames.fe_shift_m), np.round(1e3 * still, 3)


# ---------------------------------------------------------------------- the contract


def test_image_is_uint8_black_without_contact_and_outside_the_breast(
    phantom: tissue.Tissue, imager: BModeImager
) -> None:
    position, quat = phantom.touching_pose(phantom.lesions[0].rest_centre_m)
    phantom.reset(position, quat)
    image = imager.image(phantom, position, quat, True)
    config = imager.config
    assert image.dtype == np.uint8 and image.shape == (config.rows, config.cols)
    labels = imager.labels(phantom, position, quat)
    assert np.all(image[labels == OUTSIDE] == 0)
    assert np.mean(image[labels == TISSUE]) > 50  # tissue echoes
    assert (labels == OUTSIDE).any() and (labels == TISSUE).any()
    dark = imager.image(phantom, position, quat, False)
    assert dark.dtype == np.uint8 and dark.shape == image.shape and not dark.any()


def test_same_pose_and_state_give_the_same_image(
    phantom: tissue.Tissue, imager: BModeImager
) -> None:
    position, quat = phantom.touching_pose(phantom.lesions[2].rest_centre_m)
    phantom.reset(position, quat)
    _press(phantom, position, quat, 0.002)
    probe = position + 0.002 * tissue.pressing_direction(quat)
    first = imager.image(phantom, probe, quat, True)
    again = imager.image(phantom.positions_m.copy(), probe, quat, True)
    rebuilt = BModeImager(phantom).image(phantom, probe, quat, True)
    np.testing.assert_array_equal(first, again)
    np.testing.assert_array_equal(first, rebuilt)
    other_seed = BModeImager(phantom, BModeConfig(seed=7)).image(phantom, probe, quat, True)
    assert np.mean(other_seed != first) > 0.5


def test_without_tgc_the_image_darkens_with_depth(phantom: tissue.Tissue) -> None:
    """Two-way attenuation at 0.75 dB/(cm MHz) and 7.5 MHz: 11 dB a cm of depth. With
    time-gain compensation the tissue's mean level is the same at every depth."""
    position, quat = phantom.touching_pose(phantom.lesions[0].rest_centre_m)
    phantom.reset(position, quat)
    rows = slice(8, 24), slice(40, 56)  # 3-9 mm and 16-22 mm deep

    def band_means(config: BModeConfig) -> list[float]:
        imager = BModeImager(phantom, config)
        image = imager.image(phantom, position, quat, True).astype(np.float64)
        labels = imager.labels(phantom, position, quat)
        return [float(image[band][labels[band] == TISSUE].mean()) for band in rows]

    shallow, deep = band_means(BModeConfig(tgc=False))
    # 14 dB more loss at the deep band's centre: 73 of 255 grey levels over 50 dB, less
    # what clipping at black takes from the deep band's speckle.
    assert deep < shallow - 40, (shallow, deep)
    shallow, deep = band_means(BModeConfig(tgc=True))
    assert abs(deep - shallow) < 10


@pytest.mark.parametrize(
    ("setting", "value"),
    [
        ("rows", 0),
        ("cols", 64.5),
        ("rows", True),
        ("aperture_m", -0.04),
        ("psf_lateral_m", 0.0),
        ("psf_axial_m", float("nan")),
        ("dynamic_range_db", 0.0),
        ("scatterer_spacing_m", "0.4 mm"),
        ("attenuation_db_cm_mhz", -0.5),
        ("lesion_echogenicity", float("inf")),
        ("tgc", 1),
        ("seed", -1),
    ],
)
def test_bad_settings_are_refused_by_name(setting: str, value: object) -> None:
    with pytest.raises(EnvConfigError, match=setting):
        BModeConfig(**{setting: value})  # type: ignore[arg-type]


def test_bad_frame_input_is_refused(phantom: tissue.Tissue, imager: BModeImager) -> None:
    position, quat = phantom.touching_pose(phantom.lesions[0].rest_centre_m)
    assert issubclass(EnvConfigError, tissue.TissueInputError)
    with pytest.raises(EnvConfigError, match="quaternion"):
        imager.image(phantom, position, np.zeros(4), True)
    with pytest.raises(EnvConfigError, match="position"):
        imager.labels(phantom, [0.0, np.nan, 0.1], quat)
    with pytest.raises(EnvConfigError, match="node positions"):
        imager.image(phantom.positions_m[:-1], position, quat, True)
    with pytest.raises(EnvConfigError, match="in_contact"):
        imager.image(phantom, position, quat, "yes")  # type: ignore[arg-type]
    with pytest.raises(EnvConfigError, match="tissue.Tissue"):
        BModeImager(phantom.positions_m)  # type: ignore[arg-type]
    with pytest.raises(EnvConfigError, match="BModeConfig"):
        BModeImager(phantom, {"rows": 64})  # type: ignore[arg-type]


def test_the_environment_observes_the_image_only_when_asked() -> None:
    """``image=True`` adds a uint8 B-mode image to the observation (black before the probe
    touches, the deformed slice once it presses) and the checkers still pass; without it
    there is no image and no imager."""
    import gymnasium as gym
    from gymnasium.utils.env_checker import check_env

    import envs  # noqa: F401 - registers the environments

    plain = gym.make("probegym/BreastCompress-v0", mesh=623)
    assert "image" not in plain.observation_space.spaces and plain.unwrapped.imager is None
    plain.close()
    env = gym.make("probegym/BreastCompress-v0", mesh=623, image=True)
    space = env.observation_space["image"]
    assert (space.shape, space.dtype) == ((128, 128, 1), np.uint8)
    obs, _ = env.reset(seed=0)
    assert obs["image"].shape == (128, 128, 1) and not obs["image"].any()  # not touching yet
    for _ in range(10):
        obs, *_ = env.step(np.array([0.0, 0.3, 0.0, 0.0, 0.0, 0.0], dtype=np.float32))
    assert obs["image"].dtype == np.uint8 and obs["image"].mean() > 20  # pressed: an image
    check_env(env.unwrapped, skip_render_check=True)
    env.close()
    with pytest.raises(EnvConfigError, match="image must be True, False or"):
        gym.make("probegym/BreastCompress-v0", mesh=623, image="yes")


def test_rgb_array_frames_show_the_image_beside_the_scene() -> None:
    """With ``image=True`` an ``rgb_array`` frame is the 3D view with the B-mode image to its
    right, at the frame's height and the image's aspect (40 x 50 mm): grey, and the pressed
    slice, not black."""
    import gymnasium as gym

    import envs  # noqa: F401 - registers the environments

    env = gym.make(
        "probegym/BreastCompress-v0", mesh=623, image=True, render_mode="rgb_array",
        width=160, height=200,
    )  # fmt: skip
    env.reset(seed=0)
    for _ in range(10):
        env.step(np.array([0.0, 0.3, 0.0, 0.0, 0.0, 0.0], dtype=np.float32))
    frame = env.render()
    env.close()
    assert frame.shape == (200, 160 + 160, 3) and frame.dtype == np.uint8
    image = frame[:, 160:]
    assert np.array_equal(image[..., 0], image[..., 1]) and image.mean() > 20
