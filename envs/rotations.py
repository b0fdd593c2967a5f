"""Rotations the environments share: rotation matrices from quaternions and rotation
vectors, the angle between two orientations, and the probe pointing down."""

from __future__ import annotations

import mujoco
import numpy as np
from numpy.typing import NDArray

from envs.controller import rotation_vector


def pointing_down() -> NDArray[np.float64]:
    """Probe x along world x, pressing (+y) down."""
    return np.column_stack([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


def axis_angle(vector: NDArray[np.float64]) -> tuple[NDArray[np.float64], float]:
    angle = float(np.linalg.norm(vector))
    if angle < 1e-15:
        return np.array([1.0, 0.0, 0.0]), 0.0
    return vector / angle, angle


def rotation_angle(a: NDArray[np.float64], b: NDArray[np.float64]) -> float:
    """The angle between two rotation matrices [rad]."""
    return float(np.linalg.norm(rotation_vector(a @ b.T)))


def quat_matrix(quat: NDArray[np.float64]) -> NDArray[np.float64]:
    """The rotation matrix (3, 3) of a unit quaternion (w, x, y, z)."""
    matrix = np.empty(9)
    mujoco.mju_quat2Mat(matrix, np.asarray(quat, dtype=np.float64))
    return matrix.reshape(3, 3)


def turn_matrix(vector: NDArray[np.float64]) -> NDArray[np.float64]:
    """The rotation matrix (3, 3) of a rotation vector [rad]."""
    angle = float(np.linalg.norm(vector))
    if angle == 0.0:
        return np.eye(3)
    quat = np.empty(4)
    mujoco.mju_axisAngle2Quat(quat, vector / angle, angle)
    return quat_matrix(quat)
