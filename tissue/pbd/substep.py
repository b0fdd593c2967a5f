"""A substep's start and end, each one compiled call: prediction, velocity, force sums.

:func:`start_substep` damps and predicts (x <- x + h v) and zeroes the substep's multipliers;
:func:`end_substep` updates the velocities from the positions and adds the substep's support
and contact impulses to the step's sums.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numpy.typing import NDArray


@nb.njit(cache=True)
def predict(
    x: NDArray[np.float64],
    v: NDArray[np.float64],
    x_previous: NDArray[np.float64],
    damping: float,
    h: float,
) -> None:
    """A substep's prediction, in place: v <- damping v, x_previous <- x, x <- x + h v
    (shapes (node_count, 3); h [s]). One pass instead of three whole-array numpy passes and
    a copy, each substep."""
    for i in range(x.shape[0]):
        for a in range(3):
            v[i, a] *= damping
            x_previous[i, a] = x[i, a]
            x[i, a] += h * v[i, a]


@nb.njit(cache=True)
def update_velocity(
    x: NDArray[np.float64], x_previous: NDArray[np.float64], v: NDArray[np.float64], h: float
) -> None:
    """v <- (x - x_previous) / h in place [m/s], (node_count, 3)."""
    for i in range(x.shape[0]):
        for a in range(3):
            v[i, a] = (x[i, a] - x_previous[i, a]) / h


@nb.njit(cache=True)
def start_substep(
    x: NDArray[np.float64],
    v: NDArray[np.float64],
    x_previous: NDArray[np.float64],
    damping: float,
    h: float,
    lam_dev: NDArray[np.float64],
    lam_hyd: NDArray[np.float64],
    support_step: NDArray[np.float64],
) -> None:
    """A substep's start in one compiled call: :func:`predict` (arguments ``x`` .. ``h`` as
    there), and the substep's tet multipliers ``lam_dev``, ``lam_hyd`` (tet_count,) and
    fixed-node support ``support_step`` (node_count, 3) set to zero."""
    predict(x, v, x_previous, damping, h)
    lam_dev[:] = 0.0
    lam_hyd[:] = 0.0
    support_step[:] = 0.0


@nb.njit(cache=True)
def end_substep(
    x: NDArray[np.float64],
    x_previous: NDArray[np.float64],
    v: NDArray[np.float64],
    h: float,
    support_step: NDArray[np.float64],
    support: NDArray[np.float64],
    points: NDArray[np.int64],
    normals: NDArray[np.float64],
    lam: NDArray[np.float64],
    impulse: NDArray[np.float64],
) -> int:
    """A substep's end in one compiled call (after its sweeps and volume floor): the
    velocity update (:func:`update_velocity`), the step's support sum ``support`` +=
    ``support_step`` / h [N s] (node_count, 3), and each contact's impulse n lambda / h [N s]
    added to its point's row of ``impulse`` (point_count, 3), ``points``, ``normals`` and
    ``lam`` as :func:`~tissue.pbd.contact.project_contacts`'. Returns how many contacts
    carry a force. The arithmetic is numpy's (``support += support_step / h``,
    ``np.add.at``), to the bit."""
    update_velocity(x, x_previous, v, h)
    for i in range(support.shape[0]):
        for a in range(3):
            support[i, a] += support_step[i, a] / h
    pressing = 0
    for k in range(points.shape[0]):
        scale = lam[k] / h
        for a in range(3):
            impulse[points[k], a] += normals[k, a] * scale
        if lam[k] != 0.0:
            pressing += 1
    return pressing
