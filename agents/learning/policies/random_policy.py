"""The random baseline: uniform actions, for the success rate a task gives by chance."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray


class RandomPolicy:
    """Actions drawn uniformly from [-1, 1]^6, from its own seeded generator.

    Args:
        seed: seeds the generator (the same seed, the same actions).
    """

    def __init__(self, seed: int = 0) -> None:
        self._rng = np.random.default_rng(seed)

    def __call__(self, observation: dict[str, Any]) -> NDArray[np.float32]:
        return self._rng.uniform(-1.0, 1.0, 6).astype(np.float32)
