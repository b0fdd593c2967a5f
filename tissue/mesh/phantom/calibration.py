"""Calibration of a characteristic length [m] that makes gmsh produce a wanted element count.

gmsh takes a mesh size, not a count, and the count jumps with the size, so each level of the
ladder (and the collision surface, and :mod:`tissue.mesh.paper_scene`'s levels) is found by
repeated meshing: :func:`calibrate_size`. A count within :data:`LEVEL_TOLERANCE` of its target
is the contract.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from tissue.errors import MeshError

#: Relative tolerance on a level's tet count.
LEVEL_TOLERANCE = 0.10

# Calibration stops once within this of the target; 10 % is the contract, 3 % leaves room
# for small platform differences in gmsh when a stored size is reused elsewhere.
CALIBRATION_ACCEPT = 0.03
CALIBRATION_MAX_ITERATIONS = 10


def calibrate_size(
    mesh_at: Callable[[float], Any],
    count_of: Callable[[Any], int],
    target: int,
    initial_size: float,
    what: str,
    dimension: int = 3,
    trusted_initial: bool = False,
) -> tuple[Any, float, int]:
    """Find a characteristic length giving ``target`` elements, by repeated meshing.

    Each step scales the size by (count / target)^(1 / slope), the slope of log count over
    log size measured on the last two meshes (``-dimension`` at first, clipped to
    [-2 dimension, -dimension / 2] so that the discrete jumps of coarse meshes cannot send
    it far). It stops within 3 % of the target; otherwise it keeps the closest mesh. A
    ``trusted_initial`` size (a stored calibration) is kept if within
    :data:`LEVEL_TOLERANCE`: counts jump with the size, and a stored size was already the
    best found.

    Returns:
        (mesh, size, attempts) for the closest mesh.

    Raises:
        MeshError: no attempt came within :data:`LEVEL_TOLERANCE` of the target.
    """
    size = initial_size
    history: list[tuple[float, int]] = []
    best: tuple[float, Any, float] | None = None
    for _ in range(CALIBRATION_MAX_ITERATIONS):
        result = mesh_at(size)
        count = count_of(result)
        error = abs(count / target - 1.0)
        if best is None or error < best[0]:
            best = (error, result, size)
        if error <= CALIBRATION_ACCEPT or (
            trusted_initial and not history and error <= LEVEL_TOLERANCE
        ):
            break
        history.append((size, count))
        slope = -float(dimension)
        if len(history) >= 2:
            (s0, c0), (s1, c1) = history[-2], history[-1]
            if s0 != s1 and c0 > 0 and c1 > 0 and c0 != c1:
                slope = math.log(c1 / c0) / math.log(s1 / s0)
                slope = min(max(slope, -2.0 * dimension), -dimension / 2.0)
        size *= (max(count, 1) / target) ** (-1.0 / slope)
        if any(abs(size / s - 1.0) < 1e-4 for s, _ in history):
            size *= 1.0 + 0.01 * (1 if count > target else -1)
    assert best is not None
    if best[0] > LEVEL_TOLERANCE:
        raise MeshError(
            f"could not mesh {what} at {target} elements within {LEVEL_TOLERANCE:.0%}: closest "
            f"was {count_of(best[1])} (characteristic length {best[2]:.5g} m)"
        )
    return best[1], best[2], len(history) + 1
