"""A scripted policy for ``probegym/BreastCompress-v0``: press until the lesion is at depth.

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
