"""How deep a triangle surface lies inside the probe: the deepest point of its facets.

Contact strategies keep points (a surface's vertices) out of the probe. Between them the
surface's facets can still cut into it: a facet whose three vertices lie outside a convex
probe can pass across the probe's rounded edge, or a corner, by up to about half the facet's
size. :func:`surface_depth` measures the surface itself: the largest depth ``-sdf(p)`` over
every point ``p`` of every triangle, not only over the vertices.

The method, for a triangle surface (vertices in the world) and a posed probe, in one
compiled pass over the triangles:

1. Broad phase: a triangle whose bounding box, in the probe frame, misses the probe's local
   bounding box (:meth:`tissue.probe.ProbeShape.local_bounds_m`) holds no point inside it.
2. The signed distance at the vertices. It is 1-Lipschitz, and every point of a triangle
   lies within L / sqrt(3) of one of its vertices (L its longest edge): a triangle whose
   vertices all lie farther out than that, less the deepest point found so far, is
   skipped. For a convex probe the signed distance is a convex function, which lies above
   its tangent planes: at each vertex, the distance there plus the least the tangent plane
   falls over the triangle bounds the triangle's minimum from below; a triangle whose
   bound is no deeper than what is found is skipped. The bound is exact where the three
   vertices share one outward normal (a facet lying on the probe's flat face).
3. The others are sampled on a barycentric grid (:data:`SAMPLE_ORDER` samples an edge),
   and the best sample is refined by projected descent (a step against the distance's
   gradient projected onto the triangle's plane, back onto the triangle, halved when it
   does not deepen, down to :data:`REFINE_TOLERANCE_M`).

The result is always the depth of a point of the surface, never more than the truth. For a
convex probe the signed distance is convex, and where it is smooth (a point within the
rounded rim's radius of the face: every penetration up to that depth) the descent reaches the
triangle's deepest point. Deeper inside, where the distance has ridges, descent can stop on a
ridge short of it: the exhaustive grid of the tests found at most 0.03 mm more at 3 mm.

The analytic shapes (:meth:`tissue.probe.ProbeShape.compiled_distance`) run entirely
compiled; another shape (a mesh probe) is measured on a finer grid of samples through its own
signed distance, without the descent.

Lengths are metres, the world frame unless said otherwise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np
from numpy.typing import NDArray

from tissue.probe.pose import Probe
from tissue.probe.sdf import extruded_offset_point, rounded_rectangle_point
from tissue.probe.triangle import closest_point_on_triangle

#: Samples per triangle edge of the barycentric grid a candidate triangle is sampled on.
SAMPLE_ORDER = 4
#: Samples per edge where a shape has no compiled distance (no descent follows).
FALLBACK_SAMPLE_ORDER = 12
#: The projected descent stops once its step is below this [m].
REFINE_TOLERANCE_M = 1e-7
#: Iterations of the projected descent at most.
REFINE_ITERATIONS = 40

#: Given the rest lengths, a facet's allowance is that of its edge as deformed, up to this
#: many times its edge at rest: a skin stretched round the probe (the paper's triangles
#: under a 30 mm press) is excused what its stretched facets can reach with their vertices
#: held, a facet dragged across the probe (vertices either side, 7 x its rest length under
#: a jerky policy with penalty at 2 mm) is not.
ALLOWED_STRETCH = 2.0

#: :meth:`tissue.probe.ProbeShape.compiled_distance` kinds.
ROUNDED_SLAB = 0
SPHERE = 1
CYLINDER = 2


def facet_allowance_m(longest_edge_m: float, edge_radius_m: float) -> float:
    """How deep [m] a triangle whose vertices lie outside a convex probe can still reach
    into it, from the triangle's longest edge L [m] and the smallest radius r [m] of the
    probe's rounded edges (0 for a sharp one).

    Every point of the triangle lies within its circumradius R <= L / sqrt(3) of a vertex
    that is outside. Against a sharp edge or corner that bounds the depth: L / sqrt(3).
    Where the probe's surface curves no tighter than r and R < r, the triangle can only
    cut the rounded edge, by at most the sagitta r - sqrt(r^2 - R^2) of a circle of radius
    r (the two agree at R = r). For the default face (r = 1.35 mm): 0.65 mm for a 2 mm
    facet, 0.31 mm for 1.5 mm, 5.7 mm for the paper's median 9.9 mm.
    """
    return float(_allowance(float(longest_edge_m), float(edge_radius_m)))


@dataclass(frozen=True)
class SurfaceDepth:
    """How deep a surface lies inside the probe.

    Attributes:
        depth_m: the deepest point of the surface's facets inside the probe [m], >= 0.
        vertex_depth_m: the deepest of its vertices [m], >= 0 (<= ``depth_m``).
        excess_m: the largest depth of a facet beyond its :func:`facet_allowance_m` [m] (of
            its longest edge as deformed, capped at :data:`ALLOWED_STRETCH` x its rest length
            where :func:`surface_depth` is given the rest lengths): how much deeper than
            its resolution explains, were its vertices held out (<= 0 where every facet
            inside is explained; -inf where none is inside).
        point_world: that deepest point [m], shape (3,), or None where nothing is inside.
        triangle: the triangle holding it, or -1.
    """

    depth_m: float
    vertex_depth_m: float
    excess_m: float
    point_world: NDArray[np.float64] | None
    triangle: int


_CLEAR = SurfaceDepth(0.0, 0.0, -math.inf, None, -1)
# No rest lengths: the kernel takes the facets' as deformed.
_NO_REST = np.zeros(0)


def surface_depth(
    probe: Probe,
    vertices_world: NDArray[np.float64],
    triangles: NDArray[np.int64],
    rest_longest_edge_m: NDArray[np.float64] | None = None,
) -> SurfaceDepth:
    """The deepest point of a triangle surface inside the probe (see the module docstring).

    Args:
        probe: the posed probe.
        vertices_world: the surface's vertices [m], shape (vertex_count, 3).
        triangles: vertex indices, shape (triangle_count, 3).
        rest_longest_edge_m: each triangle's longest edge at rest [m], (triangle_count,):
            the allowances (:func:`facet_allowance_m`) then take a facet's edge as deformed
            up to :data:`ALLOWED_STRETCH` times its rest length (a facet dragged across the
            probe, its vertices either side, would otherwise excuse its own depth); None:
            as deformed.
    """
    vertices = np.ascontiguousarray(vertices_world, dtype=np.float64)
    triangles = np.ascontiguousarray(triangles, dtype=np.int64)
    rotation = probe.rotation_world()
    bounds = _bounds(probe)
    local = np.empty_like(vertices)
    candidates = np.empty(triangles.shape[0], dtype=np.int64)
    count = _overlapping_triangles(
        vertices, triangles, probe.position_world, rotation, bounds, local, candidates
    )
    if count == 0:
        return _CLEAR
    point = np.zeros(3)
    shape = probe.shape
    compiled = shape.compiled_distance()
    if compiled is not None:
        kind, params = compiled
        depth, vertex_depth, triangle, excess = _depth_kernel(
            kind,
            params,
            bool(shape.convex),
            float(shape.edge_radius_m),
            local,
            triangles,
            candidates[:count],
            _NO_REST if rest_longest_edge_m is None else rest_longest_edge_m,
            point,
        )
    else:
        depth, vertex_depth, triangle, excess = _sampled_depth(
            probe, local, triangles, candidates[:count], rest_longest_edge_m, point
        )
    if triangle < 0:
        return _CLEAR
    return SurfaceDepth(
        float(depth),
        float(vertex_depth),
        float(excess),
        probe.to_world_frame(point)[0],
        int(triangle),
    )


def _sampled_depth(
    probe: Probe,
    local: NDArray[np.float64],
    triangles: NDArray[np.int64],
    candidates: NDArray[np.int64],
    rest_longest_edge_m: NDArray[np.float64] | None,
    out_point: NDArray[np.float64],
) -> tuple[float, float, int, float]:
    """The depth for a shape without a compiled distance: the ``candidates`` triangles
    sampled on a grid of :data:`FALLBACK_SAMPLE_ORDER` samples an edge (``local``: the
    vertices in the probe frame [m]). Writes the deepest sample (probe frame) to
    ``out_point``; returns (depth, vertex depth, triangle or -1, excess)."""
    corners = local[triangles[candidates]]
    vertex_distance, _ = probe.shape.signed_distance(corners.reshape(-1, 3))
    grid = barycentric_grid(FALLBACK_SAMPLE_ORDER)
    samples = np.einsum("sk,tkd->tsd", grid, corners)
    distance, _ = probe.shape.signed_distance(samples.reshape(-1, 3))
    distance = distance.reshape(corners.shape[0], -1)
    deepest = int(np.argmin(distance))
    if distance.flat[deepest] >= 0.0:
        return 0.0, 0.0, -1, -math.inf
    out_point[:] = samples.reshape(-1, 3)[deepest]
    edges = corners - np.roll(corners, 1, axis=1)
    longest = np.sqrt((edges * edges).sum(axis=2).max(axis=1))
    if rest_longest_edge_m is not None:
        longest = np.minimum(longest, ALLOWED_STRETCH * rest_longest_edge_m[candidates])
    allowance = np.array([facet_allowance_m(L, probe.shape.edge_radius_m) for L in longest])
    per_triangle = -distance.min(axis=1)
    inside = per_triangle > 0.0
    excess = float(np.max(per_triangle[inside] - allowance[inside]))
    vertex_depth = max(0.0, -float(vertex_distance.min()))
    depth = max(vertex_depth, -float(distance.flat[deepest]))
    return depth, vertex_depth, int(candidates[deepest // grid.shape[0]]), excess


def _bounds(probe: Probe) -> NDArray[np.float64]:
    return np.ascontiguousarray(probe.shape.local_bounds_m(), dtype=np.float64)


def barycentric_grid(order: int) -> NDArray[np.float64]:
    """Barycentric coordinates of a triangle's grid of ``order`` samples an edge, shape
    ((order + 1) (order + 2) / 2, 3), the corners included."""
    rows = [
        (i / order, j / order, (order - i - j) / order)
        for i in range(order + 1)
        for j in range(order + 1 - i)
    ]
    return np.array(rows)


@nb.njit(cache=True, inline="always")
def _point_distance(kind, params, x, y, z):  # pragma: no cover - compiled
    """Signed distance [m] and outward normal (x, y, z) at a probe-frame point, for the
    shape ``kind`` with ``params`` (:meth:`tissue.probe.ProbeShape.compiled_distance`)."""
    if kind == ROUNDED_SLAB:
        d2, g2x, g2z = rounded_rectangle_point(x, z, params[0], params[1], params[2])
        return extruded_offset_point(d2, g2x, g2z, y + params[3], params[4], params[5])
    if kind == SPHERE:
        radius = params[0]
        dy = y + radius
        length = math.sqrt(x * x + dy * dy + z * z)
        if length == 0.0:
            return -radius, 0.0, 1.0, 0.0
        return length - radius, x / length, dy / length, z / length
    # CYLINDER: radius, half height.
    rho = math.hypot(x, z)
    gx = x / rho if rho > 0.0 else 1.0
    gz = z / rho if rho > 0.0 else 0.0
    return extruded_offset_point(rho - params[0], gx, gz, y + params[1], params[1], 0.0)


@nb.njit(cache=True, inline="always")
def _box_misses(local, a, b, c, bounds):  # pragma: no cover - compiled
    """Whether the bounding box of local points a, b, c misses ``bounds`` (2, 3)."""
    for axis in range(3):
        low = min(local[a, axis], local[b, axis], local[c, axis])
        high = max(local[a, axis], local[b, axis], local[c, axis])
        if high < bounds[0, axis] or low > bounds[1, axis]:
            return True
    return False


@nb.njit(cache=True, inline="always")
def _allowance(longest, radius):  # pragma: no cover - compiled
    """:func:`facet_allowance_m` in compiled code."""
    circumradius = longest / math.sqrt(3.0)
    if circumradius < radius:
        return radius - math.sqrt(radius * radius - circumradius * circumradius)
    return circumradius


@nb.njit(cache=True)
def _depth_kernel(
    kind, params, convex, radius, local, triangles, candidates, rest_longest, out_point
):  # pragma: no cover - compiled
    """:func:`surface_depth` over the ``candidates`` triangles (vertices ``local`` in the
    probe frame [m]), for a compiled shape whose smallest edge radius is ``radius`` [m], the
    allowances from ``rest_longest`` [m] (t,) where it is not empty.
    Writes the deepest point (probe frame) to ``out_point``; returns (depth, vertex depth,
    its triangle or -1, the largest excess over a facet's allowance)."""
    vertex_count = local.shape[0]
    distance = np.empty(vertex_count)
    normal = np.empty((vertex_count, 3))
    known = np.zeros(vertex_count, dtype=np.bool_)
    corners = np.empty((1, 3, 3))
    depth = 0.0
    vertex_depth = 0.0
    excess = -np.inf
    best_triangle = -1
    inv_sqrt3 = 1.0 / math.sqrt(3.0)
    # Every point of a triangle lies within this fraction of its longest edge of a sample.
    cell_radius = inv_sqrt3 / SAMPLE_ORDER
    for t in candidates:
        lowest = np.inf
        lowest_corner = 0
        for k in range(3):
            i = triangles[t, k]
            if not known[i]:
                d, nx, ny, nz = _point_distance(kind, params, local[i, 0], local[i, 1], local[i, 2])
                distance[i] = d
                normal[i, 0], normal[i, 1], normal[i, 2] = nx, ny, nz
                known[i] = True
            corners[0, k, 0] = local[i, 0]
            corners[0, k, 1] = local[i, 1]
            corners[0, k, 2] = local[i, 2]
            if distance[i] < lowest:
                lowest = distance[i]
                lowest_corner = k
        longest = 0.0
        for k in range(3):
            ex = corners[0, k, 0] - corners[0, (k + 1) % 3, 0]
            ey = corners[0, k, 1] - corners[0, (k + 1) % 3, 1]
            ez = corners[0, k, 2] - corners[0, (k + 1) % 3, 2]
            longest = max(longest, math.sqrt(ex * ex + ey * ey + ez * ez))
        allowed = longest
        if rest_longest.size:
            allowed = min(longest, ALLOWED_STRETCH * rest_longest[t])
        allowance = _allowance(allowed, radius)
        vertex_deepest = max(0.0, -lowest)
        vertex_depth = max(vertex_depth, vertex_deepest)
        if vertex_deepest > depth:
            depth = vertex_deepest
            best_triangle = t
            for axis in range(3):
                out_point[axis] = corners[0, lowest_corner, axis]
        if vertex_deepest > 0.0:
            excess = max(excess, vertex_deepest - allowance)
        # The deepest any point of it can lie: 1-Lipschitz from its vertices ...
        reach = longest * inv_sqrt3 - lowest
        if convex:
            # ... and, the distance of a convex probe being convex, above its tangent planes:
            # at vertex i, over the triangle, sdf >= d_i + min_j n_i . (v_j - v_i), the best
            # of the three bounding its minimum from below (exact where the three normals
            # agree: a facet lying on a flat face).
            bound = -np.inf
            for k in range(3):
                i = triangles[t, k]
                lowest_on_plane = 0.0
                for m in range(3):
                    along = (
                        normal[i, 0] * (corners[0, m, 0] - corners[0, k, 0])
                        + normal[i, 1] * (corners[0, m, 1] - corners[0, k, 1])
                        + normal[i, 2] * (corners[0, m, 2] - corners[0, k, 2])
                    )
                    lowest_on_plane = min(lowest_on_plane, along)
                bound = max(bound, distance[i] + lowest_on_plane)
            reach = min(reach, -bound)
        if reach <= 0.0 or (reach <= depth and reach - allowance <= excess):
            continue  # nothing inside, or nothing deeper or in more excess than found
        # Grid samples.
        px, py, pz, best = 0.0, 0.0, 0.0, np.inf
        nx, ny, nz = 0.0, 0.0, 0.0
        for i in range(SAMPLE_ORDER + 1):
            for j in range(SAMPLE_ORDER + 1 - i):
                u = i / SAMPLE_ORDER
                v = j / SAMPLE_ORDER
                w = 1.0 - u - v
                x = u * corners[0, 0, 0] + v * corners[0, 1, 0] + w * corners[0, 2, 0]
                y = u * corners[0, 0, 1] + v * corners[0, 1, 1] + w * corners[0, 2, 1]
                z = u * corners[0, 0, 2] + v * corners[0, 1, 2] + w * corners[0, 2, 2]
                d, gx, gy, gz = _point_distance(kind, params, x, y, z)
                if d < best:
                    px, py, pz, best = x, y, z, d
                    nx, ny, nz = gx, gy, gz
        reach = min(reach, longest * cell_radius - best)
        if reach <= 0.0 or (reach <= depth and reach - allowance <= excess):
            continue
        # The triangle's plane, for projecting the gradient.
        e1x = corners[0, 1, 0] - corners[0, 0, 0]
        e1y = corners[0, 1, 1] - corners[0, 0, 1]
        e1z = corners[0, 1, 2] - corners[0, 0, 2]
        e2x = corners[0, 2, 0] - corners[0, 0, 0]
        e2y = corners[0, 2, 1] - corners[0, 0, 1]
        e2z = corners[0, 2, 2] - corners[0, 0, 2]
        mx = e1y * e2z - e1z * e2y
        my = e1z * e2x - e1x * e2z
        mz = e1x * e2y - e1y * e2x
        area = math.sqrt(mx * mx + my * my + mz * mz)
        if area > 0.0:
            mx, my, mz = mx / area, my / area, mz / area
        step = longest / SAMPLE_ORDER
        for _ in range(REFINE_ITERATIONS):
            along = nx * mx + ny * my + nz * mz
            tx, ty, tz = nx - along * mx, ny - along * my, nz - along * mz
            length = math.sqrt(tx * tx + ty * ty + tz * tz)
            if length == 0.0:
                break
            qx, qy, qz, _inside = closest_point_on_triangle(
                px - step * tx / length,
                py - step * ty / length,
                pz - step * tz / length,
                0,
                corners,
            )
            d, gx, gy, gz = _point_distance(kind, params, qx, qy, qz)
            if d < best:
                px, py, pz, best = qx, qy, qz, d
                nx, ny, nz = gx, gy, gz
            else:
                step *= 0.5
                if step < REFINE_TOLERANCE_M:
                    break
        if best < 0.0:
            excess = max(excess, -best - allowance)
        if -best > depth:
            depth = -best
            best_triangle = t
            out_point[0], out_point[1], out_point[2] = px, py, pz
    return depth, vertex_depth, best_triangle, excess


@nb.njit(cache=True)
def _overlapping_triangles(
    vertices, triangles, origin, rotation, bounds, local, out
):  # pragma: no cover - compiled
    """Writes the vertices in the probe frame to ``local`` and the indices of the triangles
    whose probe-frame bounding box meets ``bounds`` (2, 3) to ``out``; returns their count."""
    for i in range(vertices.shape[0]):
        for axis in range(3):
            local[i, axis] = (
                (vertices[i, 0] - origin[0]) * rotation[0, axis]
                + (vertices[i, 1] - origin[1]) * rotation[1, axis]
                + (vertices[i, 2] - origin[2]) * rotation[2, axis]
            )
    count = 0
    for t in range(triangles.shape[0]):
        if not _box_misses(local, triangles[t, 0], triangles[t, 1], triangles[t, 2], bounds):
            out[count] = t
            count += 1
    return count
