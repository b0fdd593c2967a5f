"""Rotations in MuJoCo's quaternion convention (w, x, y, z): quaternion <-> matrix.

A pose rotation maps the probe frame to the world (p_world = R p_probe + position), so a
matrix's columns are the probe's axes in the world. Quaternions are normalised on the way
in (:func:`quat_to_matrix`); :func:`unit_quat_to_matrix` is the unchecked inner-loop form.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tissue.errors import ConfigError

# A pose rotation whose R R^T differs from I by more than this is not a rotation at all
# (published 4x4 files carry about 1e-5 of round-off, which is re-orthonormalised away).
_ROTATION_TOLERANCE = 1e-3


def quat_to_matrix(quat_wxyz: ArrayLike) -> NDArray[np.float64]:
    """Rotation matrix, shape (3, 3), of a quaternion (w, x, y, z); normalised first.

    Raises:
        ConfigError: a quaternion that is zero, non-finite or not of length 4.
    """
    return unit_quat_to_matrix(normalised_quat(quat_wxyz))


def unit_quat_to_matrix(quat: NDArray[np.float64]) -> NDArray[np.float64]:
    """Rotation matrices, shape (..., 3, 3), of unit quaternions (w, x, y, z), shape (..., 4),
    taken as they are: no check and no normalisation (for inner loops that normalise their
    own; any other caller wants :func:`quat_to_matrix`). Element by element the same
    arithmetic for one quaternion or many, so a batch gives each one's matrix to the bit."""
    quat = np.asarray(quat, dtype=np.float64)
    # One quaternion (the probe's, every step) as Python floats: the same IEEE arithmetic,
    # faster than moveaxis.
    single = quat.ndim == 1
    w, x, y, z = quat.tolist() if single else np.moveaxis(quat, -1, 0)
    matrix = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )
    return matrix if single else np.moveaxis(matrix, (0, 1), (-2, -1))


def matrix_to_quat(rotation: ArrayLike) -> NDArray[np.float64]:
    """Unit quaternion (w, x, y, z), w >= 0, of a rotation matrix, shape (3, 3).

    A matrix within round-off of a rotation (such as a 4x4 pose file printed to 5 digits)
    is first replaced by its nearest rotation.

    Raises:
        ConfigError: not 3 x 3, or not a proper rotation (|R R^T - I| > 1e-3 or det < 0).
    """
    matrix = np.asarray(rotation, dtype=np.float64)
    if matrix.shape != (3, 3) or not np.all(np.isfinite(matrix)):
        raise ConfigError(f"a rotation must be a finite 3 x 3 matrix; got shape {matrix.shape}")
    error = float(np.abs(matrix @ matrix.T - np.eye(3)).max())
    if error > _ROTATION_TOLERANCE or np.linalg.det(matrix) <= 0.0:
        raise ConfigError(
            f"matrix is not a proper rotation (|R R^T - I| = {error:.2g}, det = "
            f"{np.linalg.det(matrix):.4g}); expected orthonormal with det +1"
        )
    u, _, vt = np.linalg.svd(matrix)
    m = u @ vt
    # Shepperd's method: divide by the largest of the four candidates for accuracy.
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    candidates = (trace, m[0, 0], m[1, 1], m[2, 2])
    k = int(np.argmax(candidates))
    if k == 0:
        s = 2.0 * math.sqrt(1.0 + trace)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif k == 1:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif k == 2:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    quat = np.array(q)
    quat /= np.linalg.norm(quat)
    return -quat if quat[0] < 0.0 else quat


def normalised_quat(quat_wxyz: ArrayLike) -> NDArray[np.float64]:
    """The unit quaternion (w, x, y, z), shape (4,), of ``quat_wxyz``, or a ConfigError for
    one that is not 4 finite numbers or is (nearly) zero."""
    quat = np.asarray(quat_wxyz, dtype=np.float64).ravel()
    if quat.shape != (4,) or not np.isfinite(quat).all():
        raise ConfigError(f"a quaternion must be 4 finite numbers (w, x, y, z); got {quat_wxyz!r}")
    # What np.linalg.norm computes for a vector (the same bits), without its Python layers.
    norm = math.sqrt(float(quat.dot(quat)))
    if norm < 1e-12:
        raise ConfigError(
            f"quaternion {quat_wxyz!r} is zero and has no rotation; the identity is (1, 0, 0, 0)"
        )
    return quat / norm
