"""Compiled exact signed-distance kernels of the rounded analytic shapes.

Rounded boxes and capped cylinders are 2D x-z profiles extruded along y and offset
outwards; the kernels here evaluate such SDFs point by point (numba), returning the
distance [m] and its unit gradient, the outward normal.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np


@nb.njit(cache=True, inline="always")
def _larger(a: float, b: float) -> float:
    """np.maximum of two floats, NaN and signed zeros included (a wins ties)."""
    return a if (a >= b or a != a) else b


@nb.njit(cache=True, inline="always")
def _offset_box_distance(u: float, v: float) -> tuple[float, float, float]:
    """Signed distance [m] of a point (u, v) from the quadrant u, v <= 0 (the corner a box's
    or an extrusion's exact SDF reduces to) and its unit gradient (g_u, g_v): radial from
    the corner outside, else the nearer wall. Shared by the SDF kernels below."""
    ou = _larger(u, 0.0)
    ov = _larger(v, 0.0)
    outer = math.hypot(ou, ov)
    if outer > 0.0:
        return outer, ou / outer, ov / outer
    return _larger(u, v), 1.0 if u >= v else 0.0, 1.0 if u < v else 0.0


@nb.njit(cache=True, inline="always")
def extruded_offset_point(
    d2: float, g2x: float, g2z: float, y_rel: float, half_height: float, radius: float
) -> tuple[float, float, float, float]:
    """One point of :func:`extruded_offset_sdf`: (distance, normal x, y, z)."""
    # In (w_x, w_y): the profile's distance and the distance past the extrusion's ends.
    corner, gx, gy = _offset_box_distance(d2, abs(y_rel) - half_height)
    sy = 1.0 if y_rel >= 0.0 else -1.0
    return corner - radius, gx * g2x, gy * sy, gx * g2z


@nb.njit(cache=True, inline="always")
def rounded_rectangle_point(
    x: float, z: float, half_x: float, half_z: float, corner_radius: float
) -> tuple[float, float, float]:
    """Exact 2D SDF [m] and unit gradient (g_x, g_z) at (x, z) [m] of a rounded rectangle
    centred at 0 (half sizes and corner radius [m])."""
    sx = 1.0 if x >= 0.0 else -1.0
    sz = 1.0 if z >= 0.0 else -1.0
    corner, gx, gz = _offset_box_distance(
        abs(x) - (half_x - corner_radius), abs(z) - (half_z - corner_radius)
    )
    return corner - corner_radius, gx * sx, gz * sz


@nb.njit(cache=True)
def extruded_offset_sdf(d2, g2, y_rel, half_height, radius):  # pragma: no cover - compiled
    """Exact SDF of a 2D x-z profile extruded along y, then offset outwards by ``radius``.

    The extrusion of an exact 2D SDF is exact (Quilez's construction), and offsetting an
    exact SDF by a constant stays exact, so rounded boxes and capped cylinders share this.
    Compiled point by point: it runs in every contact detection on the few points near the
    probe, where a whole-array numpy version's temporaries cost more than the maths.

    Args:
        d2: exact 2D signed distance of the (shrunk) profile in the x-z plane [m], (n,).
        g2: its unit gradient, shape (n, 2) as (x, z) components.
        y_rel: y relative to the mid-plane of the extrusion [m], shape (n,).
        half_height: half the height of the (shrunk) extrusion [m], >= 0.
        radius: outward offset [m], >= 0.

    Returns:
        distance [m], shape (n,), and the unit gradient (outward normal), shape (n, 3).
    """
    count = d2.shape[0]
    distance = np.empty(count)
    normal = np.empty((count, 3))
    for i in range(count):
        distance[i], normal[i, 0], normal[i, 1], normal[i, 2] = extruded_offset_point(
            d2[i], g2[i, 0], g2[i, 1], y_rel[i], half_height, radius
        )
    return distance, normal


@nb.njit(cache=True)
def rounded_slab_sdf(
    points, half_x, half_z, corner_radius, mid_offset, half_height, radius
):  # pragma: no cover - compiled
    """:func:`extruded_offset_sdf` of a rounded rectangle's SDF, in one pass over
    ``points`` (n, 3) [m]: y relative to the mid-plane is y + ``mid_offset``. One compiled
    call and no column copies, as PBD calls it every substep on a few dozen points."""
    count = points.shape[0]
    distance = np.empty(count)
    normal = np.empty((count, 3))
    for i in range(count):
        d2, g2x, g2z = rounded_rectangle_point(
            points[i, 0], points[i, 2], half_x, half_z, corner_radius
        )
        distance[i], normal[i, 0], normal[i, 1], normal[i, 2] = extruded_offset_point(
            d2, g2x, g2z, points[i, 1] + mid_offset, half_height, radius
        )
    return distance, normal
