"""A scripted policy for ``probegym/ForceScan-v0``: press, then sweep to the path's end.

Reads only the policy's observation: the probe's pose, the F/T wrench (the one on the
probe from outside, in the probe frame: the normal force is ``-wrench[1]``) and the
``path`` (the path's end from the probe's centre and the rest skin's normal under the
probe, both in the probe frame).

The action moves the arm's impedance target, which the probe follows some 5-7 steps
behind. A policy that adds a correction of what it sees to the target each step winds up:
the target runs millimetres and degrees ahead of the probe, and the probe overshoots
(the force past the band or the 10 N limit, the face rocking about the normal, the probe
hunting back and forth at the path's end). So the policy keeps its own copy of the target
(the probe's pose at the episode's first observation, moved by each of its actions as the
environment moves it) and places the target relative to the probe it sees:

- along the pressing axis (y) it moves the target in proportion to the (smoothed) normal
  force's error, at most ``max_press_m`` per step, and keeps the target between
  ``min_press_lead_m`` and ``max_press_lead_m`` from the probe (no wind-up);
- it turns the target to the rest skin's normal under the probe, plus the angle that
  normal has been turning per step times ``turn_lead_steps`` (the probe lags the target),
  at most ``max_turn_rad`` a step (not before the force reaches ``min_turn_force_n``);
- once the (smoothed) force is above ``min_sweep_force_n``, it moves the target along the
  skin toward the path's end, ``sweep_m`` a step, but never more than ``sweep_lead_m``
  ahead of the probe nor more than ``sweep_gain`` times the distance left (so it pushes
  through the tissue piled up ahead of the face, and near the end it slows down and stops
  there instead of hunting back and forth).

Measured (seeds 0-29, the 1,363-tet phantom, robust profile): 30 of 30 for each of LM,
penalty, prescribed displacement and PBD.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

#: The environment's translation at action 1 [m per step] (``max_translation_m``).
MAX_TRANSLATION_M = 0.005
#: And its rotation at action 1 [rad per step] (``max_rotation_rad``).
MAX_ROTATION_RAD = 0.05


def _quat_matrix(quat: NDArray[np.float64]) -> NDArray[np.float64]:
    """The rotation matrix of a unit quaternion (w, x, y, z)."""
    w, x, y, z = quat / np.linalg.norm(quat)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _rotation(vector: NDArray[np.float64]) -> NDArray[np.float64]:
    """The rotation matrix of a rotation vector (axis times angle [rad]), Rodrigues."""
    angle = float(np.linalg.norm(vector))
    if angle < 1e-12:
        return np.eye(3)
    k = vector / angle
    cross = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle) * cross + (1.0 - np.cos(angle)) * cross @ cross


def _rotation_vector(rotation: NDArray[np.float64]) -> NDArray[np.float64]:
    """The rotation vector (axis times angle [rad]) of a rotation matrix."""
    cosine = float(np.clip((np.trace(rotation) - 1.0) / 2.0, -1.0, 1.0))
    angle = float(np.arccos(cosine))
    axial = np.array(
        [
            rotation[2, 1] - rotation[1, 2],
            rotation[0, 2] - rotation[2, 0],
            rotation[1, 0] - rotation[0, 1],
        ]
    )
    if angle < 1e-9:
        return axial / 2.0
    return axial * angle / (2.0 * np.sin(angle))


def _turn(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """The rotation vector that turns unit vector ``a`` onto unit vector ``b``."""
    axis = np.cross(a, b)
    sine = float(np.linalg.norm(axis))
    if sine < 1e-12:
        return np.zeros(3)
    return axis / sine * float(np.arctan2(sine, float(a @ b)))


@dataclass
class ForceScanPolicy:
    """Force control along y, the face turned to the skin's normal, a sweep along the skin.

    Attributes:
        target_force_n: the normal contact force it holds [N].
        force_gain_m_per_n: target move along y per newton of force error [m/N].
        force_smoothing: weight of the newest reading in the smoothed force (1: raw).
        max_press_m: the largest target move along y per step [m].
        min_press_lead_m: the target's least lead over the probe along y [m] (negative:
            behind it, pulling back).
        max_press_lead_m: and its largest [m] (bounds the wind-up while the probe lags).
        min_sweep_force_n: below this force it does not sweep yet (it presses first).
        sweep_m: how far the target moves along the skin per step [m] (0: no sweep).
        sweep_gain: the target's largest lead along the skin as a share of the distance
            left to the path's end.
        sweep_lead_m: the target's largest lead along the skin [m].
        turn_lead_steps: how many steps of the normal's turning rate the target's
            orientation leads the normal by (the probe lags the target).
        rate_smoothing: weight of the newest step in the normal's smoothed turning rate.
        min_turn_force_n: below this (raw) force it keeps the target's orientation.
        max_turn_rad: the largest turn of the target per step [rad].
        max_translation_m: the environment's ``max_translation_m`` [m per step].
        max_rotation_rad: the environment's ``max_rotation_rad`` [rad per step].
    """

    target_force_n: float = 1.8
    force_gain_m_per_n: float = 0.0005
    force_smoothing: float = 0.5
    max_press_m: float = 0.001
    min_press_lead_m: float = -0.003
    max_press_lead_m: float = 0.004
    min_sweep_force_n: float = 1.2
    sweep_m: float = 0.0003
    sweep_gain: float = 0.7
    sweep_lead_m: float = 0.003
    turn_lead_steps: float = 6.0
    rate_smoothing: float = 0.2
    min_turn_force_n: float = 0.2
    max_turn_rad: float = 0.05
    max_translation_m: float = MAX_TRANSLATION_M
    max_rotation_rad: float = MAX_ROTATION_RAD
    _target_pos: NDArray[np.float64] | None = field(default=None, init=False, repr=False)
    _target_rot: NDArray[np.float64] = field(
        default_factory=lambda: np.eye(3), init=False, repr=False
    )
    _force_n: float = field(default=0.0, init=False, repr=False)
    _normal: NDArray[np.float64] | None = field(default=None, init=False, repr=False)
    _rate: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3), init=False, repr=False)

    def reset(self) -> None:
        """Forget the target and the filters (call at each episode's start)."""
        self._target_pos = None
        self._target_rot = np.eye(3)
        self._force_n = 0.0
        self._normal = None
        self._rate = np.zeros(3)

    def __call__(self, observation: dict[str, NDArray[np.float32]]) -> NDArray[np.float32]:
        pose = np.asarray(observation["probe_pose"], dtype=np.float64)
        position, rotation = pose[:3], _quat_matrix(pose[3:7])
        if self._target_pos is None:
            # The episode's first observation: the target is where the probe is.
            self._target_pos, self._target_rot = position.copy(), rotation.copy()
        path = np.asarray(observation["path"], dtype=np.float64)
        force = -float(observation["wrench"][1])
        self._force_n += self.force_smoothing * (force - self._force_n)

        # The target's position in the probe's frame (its lead over the probe).
        lead = rotation.T @ (self._target_pos - position)
        wanted = lead.copy()
        press = self.force_gain_m_per_n * (self.target_force_n - self._force_n)
        press = float(np.clip(press, -self.max_press_m, self.max_press_m))
        wanted[1] = float(np.clip(lead[1] + press, self.min_press_lead_m, self.max_press_lead_m))
        # Never let the clamp push the target the wrong way.
        if press >= 0.0:
            wanted[1] = max(wanted[1], min(lead[1], self.max_press_lead_m))
        else:
            wanted[1] = min(wanted[1], max(lead[1], self.min_press_lead_m))

        normal = path[3:6] / max(float(np.linalg.norm(path[3:6])), 1e-12)
        along = np.zeros(3)
        if self._force_n >= self.min_sweep_force_n:
            # The end's offset along the skin: less its part along the skin's normal.
            offset = path[:3] - float(path[:3] @ normal) * normal
            offset[1] = 0.0
            distance = float(np.linalg.norm(offset))
            if distance > 0.0:
                heading = offset / distance
                ahead = float(lead @ heading) + self.sweep_m
                ahead = min(ahead, self.sweep_lead_m, self.sweep_gain * distance)
                along = heading * max(ahead, 0.0)
        wanted[0], wanted[2] = along[0], along[2]

        # The orientation: the probe's y onto the normal, led by the normal's turning.
        world_normal = rotation @ normal
        if self._normal is not None:
            step_turn = _turn(self._normal, world_normal)
            self._rate += self.rate_smoothing * (step_turn - self._rate)
        self._normal = world_normal
        aim = _rotation(rotation @ _turn(np.array([0.0, 1.0, 0.0]), normal))
        aim = _rotation(self._rate * self.turn_lead_steps) @ aim @ rotation
        if force < self.min_turn_force_n:
            aim = self._target_rot
        # Turn from the target's orientation to the aim (in the target's frame), bounded.
        turn = _rotation_vector(self._target_rot.T @ aim)
        angle = float(np.linalg.norm(turn))
        if angle > self.max_turn_rad:
            turn *= self.max_turn_rad / angle

        move = self._target_rot.T @ (position + rotation @ wanted - self._target_pos)
        action = np.concatenate([move / self.max_translation_m, turn / self.max_rotation_rad])
        action = np.clip(action, -1.0, 1.0).astype(np.float32)
        # Move the copy of the target as the environment moves the target.
        self._target_pos = self._target_pos + self._target_rot @ (
            action[:3].astype(np.float64) * self.max_translation_m
        )
        self._target_rot = self._target_rot @ _rotation(
            action[3:].astype(np.float64) * self.max_rotation_rad
        )
        return action


def force_scan_v1_policy() -> ForceScanPolicy:
    """The scripted policy for ``probegym/ForceScan-v1`` (2 mm a step at full action)."""
    from envs.tasks.force_scan_v1 import V1_MAX_TRANSLATION_M

    return ForceScanPolicy(max_translation_m=V1_MAX_TRANSLATION_M)
