"""A scripted policy for ``probegym/ForceScan-v0``: press, then sweep to the path's end.

Reads only the policy's observation: the F/T wrench (the one on the probe from outside, in
the probe frame: the normal force is ``-wrench[1]``) and the ``path`` (the path's end from
the probe's centre and the rest skin's normal under the probe, both in the probe frame). It
keeps the normal force near a target by moving along the pressing axis in proportion to
the force error; it turns the pressing axis toward the skin's normal by a share of the
angle each step (optionally also about x and z so that the contact's centre of pressure
comes to the face's centre: a force at +z makes a torque +x, a force at +x a torque -z;
off by default, as it fights the normal's lead on this curved skin); once the force is
above ``min_sweep_force_n`` it moves along the skin (the end's offset less its part along
the normal) toward the path's end, at most ``sweep_m`` per step.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

#: The environment's translation at action 1 [m per step] (``max_translation_m``).
MAX_TRANSLATION_M = 0.005
#: And its rotation at action 1 [rad per step] (``max_rotation_rad``).
MAX_ROTATION_RAD = 0.05


@dataclass
class ForceScanPolicy:
    """Force control along y, alignment about x and z, a sweep along the skin.

    Attributes:
        target_force_n: the normal contact force it holds [N].
        force_gain: action along y per newton of force error.
        max_press_action: the largest action it takes along y.
        sweep_m: the largest move along the skin per step [m].
        min_sweep_force_n: below this force it does not sweep yet (it presses first).
        align_gain: turn action per metre of the centre of pressure's offset (0: off).
        max_align_action: the largest turn action.
        normal_gain: the share of the angle between the pressing axis and the rest skin's
            normal under the probe (observed) it turns per step.
        max_translation_m: the environment's ``max_translation_m``.
        max_rotation_rad: the environment's ``max_rotation_rad``.
    """

    target_force_n: float = 1.8
    force_gain: float = 0.3
    max_press_action: float = 0.3
    sweep_m: float = 0.001
    min_sweep_force_n: float = 1.2
    align_gain: float = 0.0
    max_align_action: float = 0.3
    normal_gain: float = 1.0
    max_translation_m: float = MAX_TRANSLATION_M
    max_rotation_rad: float = MAX_ROTATION_RAD

    def reset(self) -> None:
        """Nothing to forget (kept for the policies' common interface)."""

    def __call__(self, observation: dict[str, NDArray[np.float32]]) -> NDArray[np.float32]:
        action = np.zeros(6, dtype=np.float32)
        wrench = observation["wrench"]
        normal = -float(wrench[1])
        action[1] = float(
            np.clip(
                self.force_gain * (self.target_force_n - normal),
                -self.max_press_action,
                self.max_press_action,
            )
        )
        if normal > 0.2:
            # Centre of pressure: x at -torque_z / N, z at torque_x / N; turning about +x
            # lifts the face's +z end, about -z its +x end.
            for index, torque in ((3, float(wrench[3])), (5, float(wrench[5]))):
                action[index] = float(
                    np.clip(
                        self.align_gain * torque / normal,
                        -self.max_align_action,
                        self.max_align_action,
                    )
                )
        path = np.asarray(observation["path"], dtype=np.float64)
        if normal >= self.min_sweep_force_n:
            # The end's offset along the skin: less its part along the skin's normal.
            offset = path[:3] - float(path[:3] @ path[3:6]) * path[3:6]
            along = np.array([offset[0], offset[2]])
            distance = float(np.linalg.norm(along))
            if distance > 0.0:
                move = along * min(1.0, self.sweep_m / distance) / self.max_translation_m
                action[0], action[2] = float(move[0]), float(move[1])
        if normal > 0.2:
            # Turn the pressing axis toward the rest skin's normal under the probe.
            axis = np.cross([0.0, 1.0, 0.0], path[3:6])
            sine = float(np.linalg.norm(axis))
            if sine > 1e-9:
                angle = float(np.arcsin(min(1.0, sine)))
                turn = axis / sine * angle * self.normal_gain / self.max_rotation_rad
                action[3] += float(turn[0])
                action[5] += float(turn[2])
        return np.clip(action, -1.0, 1.0).astype(np.float32)
