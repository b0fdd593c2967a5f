"""A scripted policy for ``probegym/BreastCompress``: press until the lesion is at depth.

Reads only the policy's observation: the lesion's depth in the image and the target depth.
While the lesion is out of view it presses gently (the probe starts just touching the skin,
so a light press brings the lesion into view); once in view it moves the probe along its
pressing axis in proportion to the depth error, capped, and holds when within the band.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray


@dataclass
class CompressionPolicy:
    """Proportional depth control along the probe's axis.

    Attributes:
        gain: action per metre of depth error (the action's +1 is 5 mm a step).
        max_action: the largest action it takes along the axis.
        search_action: the action while the lesion is out of view.
    """

    gain: float = 60.0
    max_action: float = 0.15
    search_action: float = 0.05

    @classmethod
    def for_scale(cls, max_translation_m: float) -> CompressionPolicy:
        """The same motion in metres for an environment whose action's +1 is
        ``max_translation_m`` a step (the defaults are for 5 mm)."""
        factor = 0.005 / max_translation_m
        return cls(60.0 * factor, 0.15 * factor, 0.05 * factor)

    def __call__(self, observation: dict[str, NDArray[np.float32]]) -> NDArray[np.float32]:
        action = np.zeros(6, dtype=np.float32)
        _, depth, _, visible = (float(v) for v in observation["lesion"])
        target = float(observation["target_depth"][0])
        if visible < 0.5:
            action[1] = self.search_action
            return action
        # Depth above the target: the lesion must come up, the probe goes in (+y).
        action[1] = float(np.clip(self.gain * (depth - target), -self.max_action, self.max_action))
        return action


def compression_v2_policy() -> CompressionPolicy:
    """The scripted policy for ``probegym/BreastCompress-v2`` (3 mm a step)."""
    from envs.tasks.breast_compress_v2 import V2_MAX_TRANSLATION_M

    return CompressionPolicy.for_scale(V2_MAX_TRANSLATION_M)
