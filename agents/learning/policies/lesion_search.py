"""A scripted policy for ``probegym/LesionSearch-v0`` and v1: press, sweep, centre, hold.

Reads only the policy's observation: the F/T wrench (the one on the probe from outside, in
the probe frame, so the tissue pushing back reads negative along +y: the normal force is
``-wrench[1]``), the probe's orientation and the lesion in the image. It keeps the normal
force near a target by moving along the pressing axis in proportion to the force error,
and turns the probe about its elevation axis (z) so that the contact's centre of pressure
comes to the face's centre (the face follows the skin's slope). While the lesion is out of
view it sweeps along the scan line (the probe's x axis) at a fixed speed, first uphill
(toward the breast's apex, away from its edge), past a set distance from where it started
back the other way (it tracks how far it went by integrating its own actions); once the
lesion is in view it moves along x in proportion to the lesion's lateral offset to centre
it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

#: The environment's translation at action 1 [m per step] (``max_translation_m``).
MAX_TRANSLATION_M = 0.005
#: And its rotation [rad per step] (``max_rotation_rad``), which the gains were tuned for.
MAX_ROTATION_RAD = 0.05


def lesion_search_v1_policy() -> LesionSearchPolicy:
    """The scripted policy for ``probegym/LesionSearch-v1`` (2 mm and 0.02 rad a step)."""
    from envs.tasks.lesion_search_v1 import V1_MAX_ROTATION_RAD, V1_MAX_TRANSLATION_M

    return LesionSearchPolicy.for_scale(V1_MAX_TRANSLATION_M, V1_MAX_ROTATION_RAD)


@dataclass
class LesionSearchPolicy:
    """Force control along y, alignment about z, a sweep or proportional centring along x.

    Attributes:
        target_force_n: the normal contact force it holds [N] once the lesion is in view.
        search_force_n: and while it sweeps (lighter: a deep press drags the tissue along).
        force_gain: action along y per newton of force error.
        max_press_action: the largest action it takes along y.
        sweep_action: the action along x while the lesion is out of view.
        sweep_distance_m: how far from the start it sweeps before turning back [m].
        centre_gain: action along x per metre of the lesion's lateral offset.
        max_centre_action: the largest action it takes along x while centring.
        min_sweep_force_n: below this force it does not sweep yet (it presses first, as no
            image is formed without contact).
        align_gain: action about z per metre of the centre of pressure's offset along x
            (0: the probe keeps its orientation).
        max_align_action: the largest action it takes about z.
        max_translation_m: the environment's ``max_translation_m`` (to integrate its
            actions into a distance).
    """

    target_force_n: float = 1.5
    search_force_n: float = 0.6
    force_gain: float = 0.15
    max_press_action: float = 0.2
    sweep_action: float = 0.2
    sweep_distance_m: float = 0.025
    centre_gain: float = 20.0
    max_centre_action: float = 0.3
    min_sweep_force_n: float = 0.2
    align_gain: float = 40.0
    max_align_action: float = 0.3
    max_translation_m: float = MAX_TRANSLATION_M
    _travelled_m: float = field(default=0.0, init=False, repr=False)
    _direction: float = field(default=0.0, init=False, repr=False)

    @classmethod
    def for_scale(cls, max_translation_m: float, max_rotation_rad: float) -> LesionSearchPolicy:
        """The policy for an environment whose action moves the probe ``max_translation_m``
        [m] and turns it ``max_rotation_rad`` [rad] at 1: the same motions in metres and
        radians as the defaults make at v0's 5 mm and 0.05 rad (gains and limits rescaled,
        limits at most 1)."""
        move = MAX_TRANSLATION_M / max_translation_m
        turn = MAX_ROTATION_RAD / max_rotation_rad
        base = cls()
        return cls(
            force_gain=base.force_gain * move,
            max_press_action=min(1.0, base.max_press_action * move),
            sweep_action=min(1.0, base.sweep_action * move),
            centre_gain=base.centre_gain * move,
            max_centre_action=min(1.0, base.max_centre_action * move),
            align_gain=base.align_gain * turn,
            max_align_action=min(1.0, base.max_align_action * turn),
            max_translation_m=max_translation_m,
        )

    def reset(self) -> None:
        """Forget the sweep (call at each episode's start)."""
        self._travelled_m = 0.0
        self._direction = 0.0

    def __call__(self, observation: dict[str, NDArray[np.float32]]) -> NDArray[np.float32]:
        action = np.zeros(6, dtype=np.float32)
        wrench = observation["wrench"]
        normal = -float(wrench[1])
        lateral, _, _, visible = (float(v) for v in observation["lesion"])
        target = self.target_force_n if visible >= 0.5 else self.search_force_n
        action[1] = float(
            np.clip(
                self.force_gain * (target - normal), -self.max_press_action, self.max_press_action
            )
        )
        if normal > self.min_sweep_force_n:
            # The centre of pressure along x is -torque_z / normal force; turning about -z
            # lifts the face's +x end, so turn about z in proportion to torque_z / force.
            action[5] = float(
                np.clip(
                    self.align_gain * float(wrench[5]) / normal,
                    -self.max_align_action,
                    self.max_align_action,
                )
            )
        if visible >= 0.5:
            # The lesion at +x in the image: the probe moves +x to bring it to the centre.
            move = float(
                np.clip(self.centre_gain * lateral, -self.max_centre_action, self.max_centre_action)
            )
        elif normal < self.min_sweep_force_n:
            move = 0.0
        else:
            if self._direction == 0.0:
                self._direction = 1.0 if _x_axis_rises(observation["probe_pose"]) else -1.0
            if self._direction * self._travelled_m >= self.sweep_distance_m:
                self._direction = -self._direction
            move = self._direction * self.sweep_action
        action[0] = move
        self._travelled_m += move * self.max_translation_m
        return action


def _x_axis_rises(pose: NDArray[np.float32]) -> bool:
    """Whether the probe's +x axis points up (world z) for a pose (position, wxyz)."""
    w, x, y, z = (float(v) for v in pose[3:7])
    return 2.0 * (x * z - w * y) >= 0.0
