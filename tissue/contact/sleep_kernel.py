"""The sleeping step's checks in one compiled call (:meth:`ContactModel.sleep_if_clear
<tissue.contact.base.ContactModel.sleep_if_clear>`): the probe's travel since the last pose
and the sub-motions it counts, its rotation matrix at the new pose, and that no point that
must stay clear of the probe, and no point of the volume's boundary, lies within the probe's
local bounding box widened by the distance it must be clear by.

What decides a step is what the Python path decides (:meth:`ContactModel.probe_travel_m
<tissue.contact.base.ContactModel.probe_travel_m>`, :meth:`tissue.probe.Probe.clearance_m`,
:meth:`tissue.probe.Probe.any_near`), and the matrix is the one :meth:`tissue.probe.Probe.set_pose`
computes, to the bit (the same IEEE operations in the same order, no fused multiply-adds).
The travel here is summed in another order than numpy's dot products (BLAS, which may fuse),
so it is taken as a bound, :data:`TRAVEL_SLACK_M` either way: the box is widened by the upper
bound, and a travel whose bounds count different sub-motions is not decided here. Nor is a
point inside a widened box (the exact signed distance is the Python path's). The caller then
takes the full path, which decides exactly.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba as nb
import numpy as np
from numpy.typing import NDArray

from tissue.probe.pose import point_in_box

#: Bounds on how far the travel summed here may lie from the Python path's: the sums differ
#: by a few units in the last place (about 1e-15 relative: TRAVEL_SLACK_M [m] per metre of
#: travel, and absolute), and acos near 1 turns 1e-15 in the cosine into up to 1e-7 rad of
#: angle (ANGLE_SLACK_RAD [rad], times the bounding radius); each is ten times that.
TRAVEL_SLACK_M = 1e-14
ANGLE_SLACK_RAD = 1e-6

#: Points per block of :class:`BlockedPoints`: a block whose box lies clear of the probe's
#: widened box skips its points' tests.
BLOCK_POINTS = 16

#: How much wider [m] a block's test takes the probe's box than its points' tests do: the
#: two are rounded differently, by about 1e-16 m at these coordinates (tenths of a metre).
BLOCK_SLACK_M = 1e-9


class BlockedPoints(NamedTuple):
    """Points [m] (n, 3) reordered so that each run of :data:`BLOCK_POINTS` lies close
    together (Morton order), with each run's axis-aligned box: ``lo``, ``hi`` [m]
    (ceil(n / BLOCK_POINTS), 3)."""

    points: NDArray[np.float64]
    lo: NDArray[np.float64]
    hi: NDArray[np.float64]


def _spread_bits(values: NDArray[np.int64]) -> NDArray[np.int64]:
    """10-bit integers with two zero bits put between each of their bits (Morton codes)."""
    values = values & 0x3FF
    values = (values | (values << 16)) & 0x30000FF
    values = (values | (values << 8)) & 0x300F00F
    values = (values | (values << 4)) & 0x30C30C3
    return (values | (values << 2)) & 0x9249249


def blocked_points(points: NDArray[np.float64]) -> BlockedPoints:
    """``points`` [m] (n, 3) as :class:`BlockedPoints` (any order is as good to the checks,
    which ask whether any point lies in a box)."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    if points.shape[0] == 0:
        empty = np.zeros((0, 3))
        return BlockedPoints(points, empty, empty.copy())
    low = points.min(axis=0)
    span = float((points.max(axis=0) - low).max())
    cells = np.floor((points - low) * (1023.0 / span if span > 0.0 else 0.0)).astype(np.int64)
    x, y, z = (_spread_bits(cells[:, axis]) for axis in range(3))
    code = x | (y << 1) | (z << 2)
    ordered = np.ascontiguousarray(points[np.argsort(code, kind="stable")])
    starts = np.arange(0, ordered.shape[0], BLOCK_POINTS)
    return BlockedPoints(
        ordered,
        np.ascontiguousarray(np.minimum.reduceat(ordered, starts, axis=0)),
        np.ascontiguousarray(np.maximum.reduceat(ordered, starts, axis=0)),
    )


@nb.njit(cache=True, inline="always")
def _rotation(quat, out):  # pragma: no cover - compiled
    """The rotation matrix of the unit quaternion (w, x, y, z) into ``out`` (3, 3):
    :func:`tissue.probe.rotation.unit_quat_to_matrix`'s arithmetic, operation by operation."""
    w, x, y, z = quat[0], quat[1], quat[2], quat[3]
    out[0, 0] = 1.0 - 2.0 * (y * y + z * z)
    out[0, 1] = 2.0 * (x * y - w * z)
    out[0, 2] = 2.0 * (x * z + w * y)
    out[1, 0] = 2.0 * (x * y + w * z)
    out[1, 1] = 1.0 - 2.0 * (x * x + z * z)
    out[1, 2] = 2.0 * (y * z - w * x)
    out[2, 0] = 2.0 * (x * z - w * y)
    out[2, 1] = 2.0 * (y * z + w * x)
    out[2, 2] = 1.0 - 2.0 * (x * x + y * y)


@nb.njit(cache=True)
def _any_in_box(points, lo, hi, origin, rotation, bounds, margin):  # pragma: no cover - compiled
    """Whether any of the :class:`BlockedPoints` ``points``, ``lo``, ``hi`` [m] lies in the
    probe-frame box ``bounds`` widened by ``margin`` [m] (the probe at ``origin`` [m],
    ``rotation``): :func:`tissue.probe.pose._any_in_box`'s answer, to the bit, testing the
    points of the blocks whose boxes do not lie clear of that box (by :data:`BLOCK_SLACK_M`
    more) along one of the probe's axes."""
    count = points.shape[0]
    for block in range(lo.shape[0]):
        clear = False
        for axis in range(3):
            centre = 0.0
            extent = 0.0
            for j in range(3):
                half = 0.5 * (hi[block, j] - lo[block, j])
                middle = lo[block, j] + half
                centre += (middle - origin[j]) * rotation[j, axis]
                extent += half * abs(rotation[j, axis])
            widen = margin + BLOCK_SLACK_M
            if (
                centre + extent < bounds[0, axis] - widen
                or centre - extent > bounds[1, axis] + widen
            ):
                clear = True
                break
        if clear:
            continue
        for i in range(block * BLOCK_POINTS, min(count, (block + 1) * BLOCK_POINTS)):
            if point_in_box(points, i, origin, rotation, bounds, margin):
                return True
    return False


@nb.njit(cache=True, inline="always")
def _pieces(ratio, max_pieces):  # pragma: no cover - compiled
    """``ContactModel._sub_motions`` of a travel / sub-motion ``ratio``."""
    return min(max_pieces, max(1, math.ceil(ratio - 1e-12)))


@nb.njit(cache=True)
def clear_of_probe(
    position,
    quat,
    check_quat,
    begin_position,
    begin_quat,
    has_begin,
    rotation,
    bounding_radius,
    max_sub_motion,
    max_pieces,
    bounds,
    reach,
    points,
    points_lo,
    points_hi,
    boundary,
    boundary_lo,
    boundary_hi,
):  # pragma: no cover - compiled
    """The sub-motions of a sleeping step whose checks pass without an exact signed
    distance; 0 where this does not decide.

    Args:
        position: the probe's new position [m], (3,).
        quat: its unit quaternion (w, x, y, z), (4,), as :meth:`Probe.set_pose` keeps it.
        check_quat: ``quat`` normalised again, (4,): the one whose matrix the probe holds
            at that pose (:meth:`Probe.set_pose` has :func:`quat_to_matrix` normalise it).
        begin_position: the pose the tissue last saw [m], (3,) (ignored without one).
        begin_quat: its quaternion, (4,).
        has_begin: whether the tissue has seen a pose (else no travel, one sub-motion).
        rotation: out, (3, 3): the matrix of ``check_quat`` (after several sub-motions
            the probe holds another: see :func:`rotation_matrix`).
        bounding_radius: the probe shape's bounding radius [m].
        max_sub_motion: the longest probe motion of one sub-motion [m].
        max_pieces: the most sub-motions a step is split into.
        bounds: the probe's local bounding box [m], (2, 3): min and max corners.
        reach: the distance [m] ``points`` must be clear by, beyond the probe's travel.
        points, points_lo, points_hi: the points that must stay clear of the probe [m],
            as :class:`BlockedPoints`.
        boundary, boundary_lo, boundary_hi: the volume's boundary points [m], as
            :class:`BlockedPoints`.

    Returns:
        The sub-motions (>= 1) where the position is finite, the travel's bounds count the
        same sub-motions, no point lies in the box widened by ``reach`` plus the travel (so
        every point is farther than that from the probe) and no boundary point in the box
        widened by ``max_sub_motion`` (so the probe is not behind the skin); 0 otherwise.
    """
    for axis in range(3):
        if not math.isfinite(position[axis]):
            return 0
    travel = 0.0
    slack = 0.0
    pieces = 1
    if has_begin:
        dx = position[0] - begin_position[0]
        dy = position[1] - begin_position[1]
        dz = position[2] - begin_position[2]
        cosine = (
            begin_quat[0] * quat[0]
            + begin_quat[1] * quat[1]
            + begin_quat[2] * quat[2]
            + begin_quat[3] * quat[3]
        )
        angle = 2.0 * math.acos(min(1.0, abs(cosine)))
        travel = math.sqrt(dx * dx + dy * dy + dz * dz) + angle * bounding_radius
        slack = TRAVEL_SLACK_M + TRAVEL_SLACK_M * travel + ANGLE_SLACK_RAD * bounding_radius
        pieces = _pieces((travel + slack) / max_sub_motion, max_pieces)
        if _pieces(max(0.0, travel - slack) / max_sub_motion, max_pieces) != pieces:
            return 0
    _rotation(check_quat, rotation)
    margin = reach + (travel + slack)
    if _any_in_box(points, points_lo, points_hi, position, rotation, bounds, margin):
        return 0
    if _any_in_box(boundary, boundary_lo, boundary_hi, position, rotation, bounds, max_sub_motion):
        return 0
    return pieces


@nb.njit(cache=True)
def rotation_matrix(quat, out):  # pragma: no cover - compiled
    """The rotation matrix of the unit quaternion ``quat`` (4,) into ``out`` (3, 3), as
    :func:`tissue.probe.rotation.unit_quat_to_matrix` computes it (the same bits)."""
    _rotation(quat, out)
