"""The rigid probe: tool geometry with an exact signed distance, and its pose.

The probe never deforms; it moves. Contact strategies ask it one question, the signed
distance from points (tissue surface vertices) to its surface with the direction that
pushes a penetrating point out, and hand back contact forces for the wrench.

Frame convention (every shape): the probe frame's origin is the centre of the contact face
(or the point of first contact of a round shape), the face lies in the y = 0 plane, the
body extends to y < 0 (the handle side), and the probe presses along its +y axis. So the
probe's position is where it touches the skin, and the world image of the probe's +y axis
is the pressing direction. For the default linear probe face, x is the long axis (the US
image's lateral axis) and z the short one (elevation), as in ``us_probe_collision.stl``.

Shapes:

- :class:`LinearProbeFace` (default): the linear probe's face, a rounded slab about
  52.9 x 2.7 x 13.2 mm (x, y, z) whose extents match the published collision STL.
- :class:`BoxProbe`, :class:`SphereProbe`, :class:`CylinderProbe`: analytic shapes with
  exact signed distances (the cylinder is a flat circular punch, axis along y).
- :class:`MeshProbe`: any closed triangle mesh, exact point-triangle distance (numba), the
  sign from the nearest face's normal or, near edges and vertices, the winding number.

Build one from a command-line spec with :func:`parse_probe_spec`; pose it with
:class:`Probe`. A pose is probe-to-world (p_world = R p_probe + position), which is how the
published ``ground_truth/tumorN/Transform*.txt`` files read: with them the probe moves
along its own +y axis into the phantom from level 0 to level 4.
"""

from __future__ import annotations

import abc
import math
from dataclasses import dataclass, field
from pathlib import Path

import numba as nb
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import ConvexHull

from tissue.errors import ConfigError, MeshError
from tissue.threads import parallel_kernel

# Default face of the linear probe [m], fitted to ../shared/paper-scene/us_probe_collision.stl
# (extents 52.89 x 2.69 x 13.20 mm; flat face about 48 x 10.4 mm; stadium-like outline).
FACE_LENGTH_M = 0.0529
FACE_THICKNESS_M = 0.0027
FACE_WIDTH_M = 0.0132
# The STL's face edge curves away over its whole thickness, so the edge radius is the
# half-thickness; its ends are nearly semicircular in plan, so the plan corner radius is
# the half-width (a least-squares scan of both radii against the STL picked these).
FACE_EDGE_RADIUS_M = 0.00135
FACE_CORNER_RADIUS_M = 0.0066
# Depth of the probe's body behind the face used for contact [m] (see linear_probe): the
# housing and the start of the handle. Deeper than any compression the study makes (30 mm),
# so tissue pressed around the probe cannot reach its back: with a 30 mm body, a probe
# teleported 30 mm into the 623-tet phantom (robust LM, the step split into sub-motions) let
# the rebounding skin fold over the body's back, which then pulled the probe in.
PROBE_BODY_DEPTH_M = 0.08

# Any probe dimension above this [m] was almost certainly given in millimetres.
_LARGEST_PLAUSIBLE_SIZE_M = 1.0
# A pose rotation whose R R^T differs from I by more than this is not a rotation at all
# (published 4x4 files carry about 1e-5 of round-off, which is re-orthonormalised away).
_ROTATION_TOLERANCE = 1e-3
# Tessellation of the drawing/collision surfaces of the analytic shapes.
_ARC_SEGMENTS = 8
_CIRCLE_SEGMENTS = 48
_SPHERE_RINGS = 12
_MESH_SUFFIXES = (".stl", ".obj", ".ply", ".off", ".glb", ".gltf")

PROBE_SPEC_FORMS = (
    "face",
    "sphere:RADIUS",
    "box:LX,LY,LZ",
    "cylinder:RADIUS,HEIGHT",
    "PATH (a closed .stl/.obj/.ply mesh in the probe frame, metres)",
)


# ----------------------------------------------------------------------------------------
# Shapes


# Central-difference step of :meth:`ProbeShape.distance_hessian` [m]: far below the smallest
# radius of the built-in shapes (the face's 1.35 mm edge) and far above round-off in the
# normal.
_HESSIAN_STEP_M = 1e-6
# How much ProbeShape.local_bounds_m widens the box of the surface's vertices, as a fraction
# of the bounding radius (0.3 mm for the default face).
_LOCAL_BOUNDS_PAD = 0.01


class ProbeShape(abc.ABC):
    """Rigid probe geometry in the probe frame (see the module docstring for the frame).

    Attributes:
        name: short human-readable description, e.g. ``"sphere:0.01"``.
        bounding_radius_m: radius [m] of a ball about the probe origin that holds the
            whole shape (a cheap broad-phase test for contact strategies).
    """

    name: str
    bounding_radius_m: float

    @abc.abstractmethod
    def signed_distance(
        self, points: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Signed distance to the probe surface and the outward normal at the closest point.

        Args:
            points: query points in the probe frame [m], shape (n, 3).

        Returns:
            distance: signed distance [m], shape (n,); negative inside the probe.
            normal: unit outward normal of the probe surface at the closest point, shape
                (n, 3), the gradient of the distance: moving a penetrating point along it
                by -distance puts it on the surface.
        """

    def distance_hessian(self, points: NDArray[np.float64]) -> NDArray[np.float64]:
        """Hessian of the signed distance at ``points`` (probe frame) [1/m], shape (n, 3, 3).

        It is the surface's curvature seen from the point: for a point at distance d from a
        rounded edge of radius r, 1 / (r + d) across the edge and 0 along it; 0 over flat
        faces. Contact strategies need it for the exact Newton tangent of a contact gap
        (the force lambda along a normal that turns as the point slides adds the stiffness
        -lambda times this). Central differences of :meth:`signed_distance`'s normal, whose
        step (:data:`_HESSIAN_STEP_M`) is far below any radius of the built-in shapes;
        shapes whose distance is not smooth override it.
        """
        points = _as_points(points)
        hessian = np.empty((points.shape[0], 3, 3))
        for axis in range(3):
            offset = np.zeros(3)
            offset[axis] = _HESSIAN_STEP_M
            _, ahead = self.signed_distance(points + offset)
            _, behind = self.signed_distance(points - offset)
            hessian[:, :, axis] = (ahead - behind) / (2.0 * _HESSIAN_STEP_M)
        return 0.5 * (hessian + hessian.transpose(0, 2, 1))

    def local_bounds_m(self) -> NDArray[np.float64]:
        """An axis-aligned box in the probe frame that holds the whole shape [m], shape
        (2, 3): its lowest and highest corner. A cheap, tighter broad phase than
        ``bounding_radius_m`` for an elongated probe (the default face is 53 mm long and 13
        mm wide: at 4,126 tets, 6 mm into the apex press, the ball about it holds 571 of PBD's
        contact points and its box 54).

        The box of :meth:`surface`'s vertices, widened on every side by
        :data:`_LOCAL_BOUNDS_PAD` of the bounding radius: the built-in shapes' surfaces
        include their extreme points, and the pad covers round-off. A subclass whose surface
        is inscribed in the shape by more than the pad must override this.
        """
        cached = getattr(self, "_local_bounds", None)
        if cached is None:
            vertices, _ = self.surface()
            pad = _LOCAL_BOUNDS_PAD * self.bounding_radius_m
            cached = np.array([vertices.min(axis=0) - pad, vertices.max(axis=0) + pad])
            self._local_bounds = cached
        return cached.copy()

    @abc.abstractmethod
    def surface(self) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        """Triangle surface in the probe frame, for drawing, MuJoCo geometry and PBD.

        Returns:
            vertices: positions [m], shape (v, 3).
            triangles: vertex indices, shape (t, 3), counter-clockwise seen from outside.
        """

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.name})"


def _as_points(points: ArrayLike) -> NDArray[np.float64]:
    """Points as a C-contiguous float64 (n, 3) array, or a clear error."""
    array = np.ascontiguousarray(points, dtype=np.float64)
    if array.ndim == 1 and array.shape[0] == 3:
        array = array[None, :]
    if array.ndim != 2 or array.shape[1] != 3:
        raise ConfigError(f"points must have shape (n, 3) in metres; got shape {array.shape}")
    return array


def _positive_size(value: float, what: str) -> float:
    """A finite, positive, plausible size in metres, or a ConfigError saying which."""
    number = float(value)
    if not math.isfinite(number) or number <= 0.0:
        raise ConfigError(f"{what} must be a positive number of metres; got {value!r}")
    if number > _LARGEST_PLAUSIBLE_SIZE_M:
        raise ConfigError(
            f"{what} = {number} m is larger than any probe; sizes are in metres "
            f"(did you give millimetres? divide by 1000)"
        )
    return number


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
def _extruded_offset_point(
    d2: float, g2x: float, g2z: float, y_rel: float, half_height: float, radius: float
) -> tuple[float, float, float, float]:
    """One point of :func:`_extruded_offset_sdf`: (distance, normal x, y, z)."""
    # In (w_x, w_y): the profile's distance and the distance past the extrusion's ends.
    corner, gx, gy = _offset_box_distance(d2, abs(y_rel) - half_height)
    sy = 1.0 if y_rel >= 0.0 else -1.0
    return corner - radius, gx * g2x, gy * sy, gx * g2z


@nb.njit(cache=True, inline="always")
def _rounded_rectangle_point(
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
def _extruded_offset_sdf(d2, g2, y_rel, half_height, radius):  # pragma: no cover - compiled
    """Exact SDF of a 2D x-z profile extruded along y, then offset outwards by ``radius``.

    The extrusion of an exact 2D SDF is exact (Quilez's construction), and offsetting an
    exact SDF by a constant stays exact, so rounded boxes and capped cylinders share this.
    Compiled, point by point: called from every contact detection (60 times a step by the
    robust PBD), where the whole-array numpy version's dozen temporaries cost more than
    the maths on the few points near the probe.

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
        distance[i], normal[i, 0], normal[i, 1], normal[i, 2] = _extruded_offset_point(
            d2[i], g2[i, 0], g2[i, 1], y_rel[i], half_height, radius
        )
    return distance, normal


@nb.njit(cache=True)
def _rounded_slab_sdf(
    points, half_x, half_z, corner_radius, mid_offset, half_height, radius
):  # pragma: no cover - compiled
    """:func:`_extruded_offset_sdf` of a rounded rectangle's SDF, in one pass over
    ``points`` (n, 3) [m]: y relative to the mid-plane is y + ``mid_offset``. One compiled
    call instead of two, and no column copies: PBD calls it every substep (at 4,126 tets
    about 50 points a call)."""
    count = points.shape[0]
    distance = np.empty(count)
    normal = np.empty((count, 3))
    for i in range(count):
        d2, g2x, g2z = _rounded_rectangle_point(
            points[i, 0], points[i, 2], half_x, half_z, corner_radius
        )
        distance[i], normal[i, 0], normal[i, 1], normal[i, 2] = _extruded_offset_point(
            d2, g2x, g2z, points[i, 1] + mid_offset, half_height, radius
        )
    return distance, normal


def _oriented_hull(points: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Convex hull of points as an outward-oriented triangle mesh without unused vertices."""
    hull = ConvexHull(points)
    used = np.unique(hull.simplices)
    remap = np.full(points.shape[0], -1, dtype=np.int64)
    remap[used] = np.arange(used.shape[0])
    vertices = points[used]
    triangles = remap[hull.simplices]
    # Qhull does not orient its facets; flip those whose normal points at the interior.
    interior = vertices.mean(axis=0)
    a, b, c = (vertices[triangles[:, k]] for k in range(3))
    inward = np.einsum("ij,ij->i", np.cross(b - a, c - a), a - interior) < 0.0
    triangles[inward] = triangles[inward][:, ::-1]
    return vertices, np.ascontiguousarray(triangles)


def _unit_sphere_directions(rings: int) -> NDArray[np.float64]:
    """Directions on a latitude-longitude grid that include +-x, +-y and +-z exactly."""
    # Longitudes in multiples of 4 and an even ring count put points on every axis, so the
    # flat faces of offset shapes come out exactly flat in the hull.
    polar = np.linspace(0.0, np.pi, rings + 1)[1:-1]
    azimuth = np.linspace(0.0, 2.0 * np.pi, 2 * rings, endpoint=False)
    p, a = np.meshgrid(polar, azimuth, indexing="ij")
    ring = np.column_stack(
        [(np.sin(p) * np.cos(a)).ravel(), np.cos(p).ravel(), (np.sin(p) * np.sin(a)).ravel()]
    )
    return np.vstack([[0.0, 1.0, 0.0], ring, [0.0, -1.0, 0.0]])


class _RoundedSlab(ProbeShape):
    """A box in the probe frame, face at y = 0, with rounded edges and plan-view corners.

    The solid is {p : dist(p, S) <= edge_radius} for S the inner slab: a rounded rectangle
    (corner radius ``corner_radius - edge_radius``) shrunk by ``edge_radius`` on every side
    and extruded in y. Its SDF is exact everywhere, inside included.
    """

    def __init__(
        self,
        size_m: tuple[float, float, float],
        edge_radius_m: float,
        corner_radius_m: float,
        name: str,
    ) -> None:
        self.size_m = tuple(float(s) for s in size_m)
        self.edge_radius_m = float(edge_radius_m)
        self.corner_radius_m = float(corner_radius_m)
        self.name = name
        hx, hy, hz = (0.5 * s for s in self.size_m)
        if not 0.0 <= self.edge_radius_m <= min(hx, hy, hz):
            raise ConfigError(
                f"edge radius {self.edge_radius_m} m must lie in [0, half the smallest size "
                f"= {min(hx, hy, hz)} m] for a box of size {self.size_m} m"
            )
        if not self.edge_radius_m <= self.corner_radius_m <= min(hx, hz):
            raise ConfigError(
                f"plan corner radius {self.corner_radius_m} m must lie in [edge radius "
                f"{self.edge_radius_m} m, {min(hx, hz)} m] for a box of size {self.size_m} m"
            )
        self._half = (hx, hy, hz)
        self.bounding_radius_m = float(math.sqrt(hx * hx + (2.0 * hy) ** 2 + hz * hz))
        self._surface: tuple[NDArray[np.float64], NDArray[np.int64]] | None = None

    def signed_distance(
        self, points: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        p = _as_points(points)
        hx, hy, hz = self._half
        r = self.edge_radius_m
        # The body's mid-plane is at y = -hy, so the face (top) lies at y = 0.
        return _rounded_slab_sdf(p, hx - r, hz - r, self.corner_radius_m - r, hy, hy - r, r)

    def surface(self) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        if self._surface is None:
            self._surface = self._build_surface()
        return self._surface

    def _build_surface(self) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        hx, hy, hz = self._half
        r = self.edge_radius_m
        inner_corner = self.corner_radius_m - r
        # Outline of the inner (shrunk) rounded rectangle, then both inner y levels; the
        # solid is the hull of those points swept by a ball of radius r.
        outline = []
        for sx, sz, start in ((1, 1, 0.0), (-1, 1, 0.5), (-1, -1, 1.0), (1, -1, 1.5)):
            centre = np.array([sx * (hx - self.corner_radius_m), sz * (hz - self.corner_radius_m)])
            if inner_corner > 0.0:
                angles = np.pi * (start + np.linspace(0.0, 0.5, _ARC_SEGMENTS + 1))
                arc = centre + inner_corner * np.column_stack([np.cos(angles), np.sin(angles)])
                outline.append(arc)
            else:
                outline.append(centre[None, :])
        ring = np.vstack(outline)
        levels = [-r, -2.0 * hy + r] if hy - r > 0.0 else [-hy]
        core = np.vstack(
            [np.column_stack([ring[:, 0], np.full(len(ring), y), ring[:, 1]]) for y in levels]
        )
        if r > 0.0:
            swept = (core[:, None, :] + r * _unit_sphere_directions(_SPHERE_RINGS)[None]).reshape(
                -1, 3
            )
        else:
            swept = core
        vertices, triangles = _oriented_hull(swept)
        # Between the sampled outline points the hull cuts chords a few micrometres inside
        # the rounded surface; project its vertices onto the exact surface.
        distance, normal = self.signed_distance(vertices)
        return vertices - distance[:, None] * normal, triangles


class LinearProbeFace(_RoundedSlab):
    """The linear US probe's face (default): a rounded slab matching the published STL.

    Axes: x is the long (lateral) axis, y the thickness with the face at y = 0 and the
    body at -thickness <= y <= 0, z the short (elevation) axis, as in
    ``us_probe_collision.stl``. The plan outline is a stadium (corner radius = half the
    width) and the face edges are rounded over the whole thickness.

    Against the STL (same extents): over the face they agree within 0.15 mm (the STL's
    face undulates by about 0.1 mm); the STL's sides lean in towards the face (widest at
    its back) where ours bulge (widest at mid-thickness), so within 4 mm of the probe the
    two signed distances differ by 0.4 mm rms and 1.3 mm at most, at the rim. Use
    ``load_probe_mesh`` for the STL itself.

    Args:
        length_m: extent along x [m].
        thickness_m: extent along y [m].
        width_m: extent along z [m].
        edge_radius_m: radius of the rounded face edges [m], at most half the thickness.
        corner_radius_m: plan-view (x-z) corner radius [m], at least the edge radius.
    """

    def __init__(
        self,
        length_m: float = FACE_LENGTH_M,
        thickness_m: float = FACE_THICKNESS_M,
        width_m: float = FACE_WIDTH_M,
        edge_radius_m: float = FACE_EDGE_RADIUS_M,
        corner_radius_m: float = FACE_CORNER_RADIUS_M,
    ) -> None:
        size = (
            _positive_size(length_m, "face length"),
            _positive_size(thickness_m, "face thickness"),
            _positive_size(width_m, "face width"),
        )
        super().__init__(
            size,
            edge_radius_m,
            corner_radius_m,
            name=f"face:{size[0]:g}x{size[1]:g}x{size[2]:g}",
        )


def linear_probe() -> LinearProbeFace:
    """The default probe for contact: the published face backed by the probe's housing.

    The published collision STL is only the 2.7 mm thick face plate. Under deep
    compressions tissue bulging around a plate that thin can reach its back and be pushed
    through it (the closest surface is then the back), so contact uses the same face
    extended PROBE_BODY_DEPTH_M behind it, as a real probe's body is.
    """
    return LinearProbeFace(thickness_m=PROBE_BODY_DEPTH_M)


class BoxProbe(_RoundedSlab):
    """A sharp-edged box: x in [-LX/2, LX/2], y in [-LY, 0], z in [-LZ/2, LZ/2].

    Args:
        size_m: (LX, LY, LZ) extents [m]; LY is the depth behind the face.
    """

    def __init__(self, size_m: ArrayLike) -> None:
        values = np.asarray(size_m, dtype=np.float64).ravel()
        if values.shape != (3,):
            raise ConfigError(f"a box needs 3 sizes (LX, LY, LZ) in metres; got {size_m!r}")
        sx, sy, sz = (
            _positive_size(v, f"box size {axis}") for v, axis in zip(values, "xyz", strict=True)
        )
        size = (sx, sy, sz)
        super().__init__(size, 0.0, 0.0, name="box:{:g},{:g},{:g}".format(*size))


class SphereProbe(ProbeShape):
    """A ball of radius R centred at (0, -R, 0): first contact at the probe origin.

    Args:
        radius_m: radius R [m].
    """

    def __init__(self, radius_m: float) -> None:
        self.radius_m = _positive_size(radius_m, "sphere radius")
        self.name = f"sphere:{self.radius_m:g}"
        self.bounding_radius_m = 2.0 * self.radius_m
        self._centre = np.array([0.0, -self.radius_m, 0.0])
        self._surface: tuple[NDArray[np.float64], NDArray[np.int64]] | None = None

    def signed_distance(
        self, points: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        offset = _as_points(points) - self._centre
        length = np.linalg.norm(offset, axis=1)
        # At the centre every direction is a gradient; +y (out of the face) is the useful one.
        at_centre = length == 0.0
        normal = offset / np.where(at_centre, 1.0, length)[:, None]
        normal[at_centre] = (0.0, 1.0, 0.0)
        return length - self.radius_m, normal

    def surface(self) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        if self._surface is None:
            points = self._centre + self.radius_m * _unit_sphere_directions(2 * _SPHERE_RINGS)
            self._surface = _oriented_hull(points)
        return self._surface


class CylinderProbe(ProbeShape):
    """A flat circular punch: axis along y, face disc at y = 0, body down to y = -height.

    Args:
        radius_m: radius of the face disc [m].
        height_m: length of the cylinder along y [m].
    """

    def __init__(self, radius_m: float, height_m: float) -> None:
        self.radius_m = _positive_size(radius_m, "cylinder radius")
        self.height_m = _positive_size(height_m, "cylinder height")
        self.name = f"cylinder:{self.radius_m:g},{self.height_m:g}"
        self.bounding_radius_m = float(math.hypot(self.radius_m, self.height_m))
        self._surface: tuple[NDArray[np.float64], NDArray[np.int64]] | None = None

    def signed_distance(
        self, points: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        p = _as_points(points)
        rho = np.hypot(p[:, 0], p[:, 2])
        on_axis = rho == 0.0
        safe = np.where(on_axis, 1.0, rho)
        # On the axis the radial direction is arbitrary; +x keeps the normal a unit vector.
        radial = np.column_stack([np.where(on_axis, 1.0, p[:, 0] / safe), p[:, 2] / safe])
        half = 0.5 * self.height_m
        return _extruded_offset_sdf(rho - self.radius_m, radial, p[:, 1] + half, half, 0.0)

    def surface(self) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        if self._surface is None:
            angles = np.linspace(0.0, 2.0 * np.pi, _CIRCLE_SEGMENTS, endpoint=False)
            ring = self.radius_m * np.column_stack([np.cos(angles), np.sin(angles)])
            points = np.vstack(
                [
                    np.column_stack([ring[:, 0], np.full(len(ring), y), ring[:, 1]])
                    for y in (0.0, -self.height_m)
                ]
            )
            self._surface = _oriented_hull(points)
        return self._surface


# ----------------------------------------------------------------------------------------
# Closed triangle meshes


@nb.njit(cache=True, inline="always")
def _closest_on_triangle(px, py, pz, t, corners):  # pragma: no cover - compiled
    """Closest point (x, y, z) to p on triangle t, and whether it lies inside the face.

    Ericson, Real-Time Collision Detection, 5.1.5, in scalars: small array temporaries
    would dominate the cost in numba.
    """
    ax, ay, az = corners[t, 0, 0], corners[t, 0, 1], corners[t, 0, 2]
    bx, by, bz = corners[t, 1, 0], corners[t, 1, 1], corners[t, 1, 2]
    cx, cy, cz = corners[t, 2, 0], corners[t, 2, 1], corners[t, 2, 2]
    abx, aby, abz = bx - ax, by - ay, bz - az
    acx, acy, acz = cx - ax, cy - ay, cz - az
    apx, apy, apz = px - ax, py - ay, pz - az
    d1 = abx * apx + aby * apy + abz * apz
    d2 = acx * apx + acy * apy + acz * apz
    if d1 <= 0.0 and d2 <= 0.0:
        return ax, ay, az, False
    bpx, bpy, bpz = px - bx, py - by, pz - bz
    d3 = abx * bpx + aby * bpy + abz * bpz
    d4 = acx * bpx + acy * bpy + acz * bpz
    if d3 >= 0.0 and d4 <= d3:
        return bx, by, bz, False
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        s = d1 / (d1 - d3)
        return ax + s * abx, ay + s * aby, az + s * abz, False
    cpx, cpy, cpz = px - cx, py - cy, pz - cz
    d5 = abx * cpx + aby * cpy + abz * cpz
    d6 = acx * cpx + acy * cpy + acz * cpz
    if d6 >= 0.0 and d5 <= d6:
        return cx, cy, cz, False
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        s = d2 / (d2 - d6)
        return ax + s * acx, ay + s * acy, az + s * acz, False
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        s = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return bx + s * (cx - bx), by + s * (cy - by), bz + s * (cz - bz), False
    inv = 1.0 / (va + vb + vc)
    v = vb * inv
    w = vc * inv
    return (
        ax + v * abx + w * acx,
        ay + v * aby + w * acy,
        az + v * abz + w * acz,
        True,
    )


@nb.njit(cache=True, inline="always")
def _solid_angle(px, py, pz, t, corners):  # pragma: no cover - compiled
    """Signed solid angle of triangle t seen from p (Van Oosterom and Strackee, 1983)."""
    ax, ay, az = corners[t, 0, 0] - px, corners[t, 0, 1] - py, corners[t, 0, 2] - pz
    bx, by, bz = corners[t, 1, 0] - px, corners[t, 1, 1] - py, corners[t, 1, 2] - pz
    cx, cy, cz = corners[t, 2, 0] - px, corners[t, 2, 1] - py, corners[t, 2, 2] - pz
    la = math.sqrt(ax * ax + ay * ay + az * az)
    lb = math.sqrt(bx * bx + by * by + bz * bz)
    lc = math.sqrt(cx * cx + cy * cy + cz * cz)
    triple = ax * (by * cz - bz * cy) - ay * (bx * cz - bz * cx) + az * (bx * cy - by * cx)
    below = (
        la * lb * lc
        + (ax * bx + ay * by + az * bz) * lc
        + (ax * cx + ay * cy + az * cz) * lb
        + (bx * cx + by * cy + bz * cz) * la
    )
    return 2.0 * math.atan2(triple, below)


@parallel_kernel
def _mesh_signed_distance(
    points, corners, face_normals, lower, upper, distance, normal
):  # pragma: no cover
    """Exact unsigned distance by brute force over triangles; sign by winding number.

    ``corners`` is (t, 3, 3). The winding number (sum of signed solid angles over 4 pi) is
    1 inside a closed outward mesh and 0 outside; unlike a pseudo-normal test it does not
    depend on which feature (face, edge, vertex) the closest point lies on. It is only
    needed for points nearest an edge or a vertex and inside the bounding box
    [lower, upper]: the solid angles cost as much as the distances.
    """
    triangle_count = corners.shape[0]
    for i in nb.prange(points.shape[0]):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        best = np.inf
        qx, qy, qz = px, py, pz
        best_triangle = 0
        best_in_face = False
        solid_angle = 0.0
        for t in range(triangle_count):
            cx, cy, cz, in_face = _closest_on_triangle(px, py, pz, t, corners)
            squared = (px - cx) ** 2 + (py - cy) ** 2 + (pz - cz) ** 2
            if squared < best:
                best = squared
                qx, qy, qz = cx, cy, cz
                best_triangle = t
                best_in_face = in_face
        inside = False
        if best_in_face:
            # Nearest to a face's interior: the segment to it crosses no surface, so that
            # face's normal gives the side exactly and the winding number is not needed.
            inside = (
                (px - qx) * face_normals[best_triangle, 0]
                + (py - qy) * face_normals[best_triangle, 1]
                + (pz - qz) * face_normals[best_triangle, 2]
            ) < 0.0
        elif (
            lower[0] <= px <= upper[0] and lower[1] <= py <= upper[1] and lower[2] <= pz <= upper[2]
        ):
            for t in range(triangle_count):
                solid_angle += _solid_angle(px, py, pz, t, corners)
            inside = solid_angle > 2.0 * math.pi
        length = math.sqrt(best)
        distance[i] = -length if inside else length
        # The SDF's gradient: away from the closest point outside, towards it inside. On
        # the surface itself that direction is undefined, so take the triangle's normal.
        if length > 1e-12:
            scale = (-1.0 if inside else 1.0) / length
            normal[i, 0] = scale * (px - qx)
            normal[i, 1] = scale * (py - qy)
            normal[i, 2] = scale * (pz - qz)
        else:
            normal[i, 0] = face_normals[best_triangle, 0]
            normal[i, 1] = face_normals[best_triangle, 1]
            normal[i, 2] = face_normals[best_triangle, 2]


class MeshProbe(ProbeShape):
    """Any closed (watertight) triangle mesh, given in the probe frame.

    The mesh is used in its own coordinates: it should follow the frame convention (contact
    face at y = 0, body at y < 0, pressing along +y), as ``us_probe_collision.stl`` does.
    An inside-out mesh (negative volume) is flipped. Signed distance is exact: the distance
    to the nearest triangle (brute force, O(points x triangles), meant for small tool
    meshes of tens to a few thousand triangles) signed by the winding number.

    Args:
        vertices: positions [m], shape (v, 3).
        triangles: vertex indices, shape (t, 3).
        name: description for messages; defaults to the triangle count.

    Raises:
        MeshError: wrong shapes, non-finite values, a mesh that is not closed or encloses
            no volume, or one far too large to be in metres.
    """

    def __init__(self, vertices: ArrayLike, triangles: ArrayLike, name: str | None = None) -> None:
        import trimesh

        v = np.asarray(vertices, dtype=np.float64)
        f = np.asarray(triangles)
        if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
            raise MeshError(
                f"a probe mesh needs vertices of shape (v, 3) and triangles of shape (t, 3); "
                f"got {v.shape} and {f.shape}"
            )
        if not np.all(np.isfinite(v)):
            raise MeshError("probe mesh vertices contain NaN or infinite values")
        if not np.issubdtype(f.dtype, np.integer) or f.min() < 0 or f.max() >= len(v):
            raise MeshError(
                f"probe mesh triangles must be integer indices in [0, {len(v) - 1}]; "
                f"got dtype {f.dtype} and range [{f.min()}, {f.max()}]"
            )
        label = name or f"mesh:{len(f)} triangles"
        # process=True merges the duplicated corners that STL files store per triangle, so
        # the watertightness test sees shared edges.
        mesh = trimesh.Trimesh(vertices=v, faces=f, process=True)
        if not mesh.is_watertight:
            open_edges = len(trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1))
            raise MeshError(
                f"probe mesh {label} is not closed: {open_edges} edges belong to a single "
                f"triangle (or edges are shared by more than two). A probe mesh must be "
                f"watertight so that inside and outside are defined; close it (for example "
                f"trimesh.repair.fill_holes) or use an analytic probe: "
                f"{', '.join(PROBE_SPEC_FORMS[:4])}"
            )
        if not mesh.is_winding_consistent:
            trimesh.repair.fix_winding(mesh)
        if abs(mesh.volume) <= 0.0:
            raise MeshError(f"probe mesh {label} encloses no volume")
        if mesh.volume < 0.0:
            mesh.invert()
        extent = float(np.max(mesh.extents))
        if extent > _LARGEST_PLAUSIBLE_SIZE_M:
            raise MeshError(
                f"probe mesh {label} is {extent:g} units across; probe meshes are in metres "
                f"(a millimetre file needs scale=0.001)"
            )
        self.name = label
        self.vertices = np.ascontiguousarray(mesh.vertices, dtype=np.float64)
        self.triangles = np.ascontiguousarray(mesh.faces, dtype=np.int64)
        self._corners = np.ascontiguousarray(self.vertices[self.triangles])
        self._face_normals = np.ascontiguousarray(mesh.face_normals, dtype=np.float64)
        self.bounding_radius_m = float(np.max(np.linalg.norm(self.vertices, axis=1)))
        self._lower = self.vertices.min(axis=0)
        self._upper = self.vertices.max(axis=0)

    @property
    def triangle_count(self) -> int:
        return int(self.triangles.shape[0])

    def signed_distance(
        self, points: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        p = _as_points(points)
        distance = np.empty(p.shape[0])
        normal = np.empty((p.shape[0], 3))
        if p.shape[0]:
            _mesh_signed_distance(
                p, self._corners, self._face_normals, self._lower, self._upper, distance, normal
            )
        return distance, normal

    def distance_hessian(self, points: NDArray[np.float64]) -> NDArray[np.float64]:
        """Zeros, shape (n, 3, 3): the normal is the nearest triangle's, constant over a face
        and jumping at edges, so a triangle mesh has no curvature to give (a contact on one
        of its edges converges linearly in Newton, as any contact did before curvature)."""
        return np.zeros((_as_points(points).shape[0], 3, 3))

    def surface(self) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        return self.vertices, self.triangles


def load_probe_mesh(path: str | Path, scale: float = 1.0) -> MeshProbe:
    """Load a closed probe mesh (STL, OBJ, PLY, ...) with trimesh.

    Args:
        path: mesh file, coordinates in the probe frame.
        scale: factor to metres (0.001 for a file in millimetres).

    Returns:
        the mesh probe, vertices [m].

    Raises:
        ConfigError: the file is missing or is not a single triangle mesh.
        MeshError: the mesh is not closed or not in metres (see :class:`MeshProbe`).
    """
    import trimesh

    file = Path(path)
    if not file.is_file():
        raise ConfigError(f"probe mesh file {str(path)!r} does not exist")
    factor = float(scale)
    if not math.isfinite(factor) or factor <= 0.0:
        raise ConfigError(f"probe mesh scale must be a positive number; got {scale!r}")
    try:
        loaded = trimesh.load(file, force="mesh")
    except Exception as error:  # trimesh raises many types for unreadable files
        raise ConfigError(f"cannot read probe mesh {str(path)!r}: {error}") from error
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise ConfigError(f"probe mesh {str(path)!r} holds no triangles")
    return MeshProbe(loaded.vertices * factor, loaded.faces, name=f"mesh:{file.name}")


def _parse_numbers(spec: str, body: str, count: int) -> list[float]:
    """Exactly ``count`` comma-separated numbers from a spec body, or a ConfigError."""
    parts = [part.strip() for part in body.split(",")]
    try:
        values = [float(part) for part in parts]
    except ValueError:
        values = []
    if len(values) != count or len(parts) != count:
        raise ConfigError(_spec_message(spec, f"expected {count} number(s) after the colon"))
    for value in values:
        if not math.isfinite(value) or value <= 0.0:
            raise ConfigError(_spec_message(spec, "sizes must be positive, finite metres"))
        if value > _LARGEST_PLAUSIBLE_SIZE_M:
            raise ConfigError(
                _spec_message(spec, "sizes are in metres (did you give millimetres?)")
            )
    return values


def _spec_message(spec: str, problem: str) -> str:
    forms = "; ".join(PROBE_SPEC_FORMS)
    return f"probe spec {spec!r}: {problem}. Valid forms (metres): {forms}"


def parse_probe_spec(spec: str) -> ProbeShape:
    """A probe shape from a command-line spec.

    Args:
        spec: one of ``face``, ``sphere:RADIUS``, ``box:LX,LY,LZ``,
            ``cylinder:RADIUS,HEIGHT`` (sizes in metres), or a path to a closed mesh file
            in the probe frame, in metres.

    Returns:
        the shape.

    Raises:
        ConfigError: an unknown form, a wrong count of numbers, or a zero, negative,
            non-numeric or implausibly large size; the message lists the valid forms.
        MeshError: a mesh file that is not a closed triangle mesh.
    """
    if not isinstance(spec, str) or not spec.strip():
        raise ConfigError(_spec_message(str(spec), "empty"))
    text = spec.strip()
    kind, colon, body = text.partition(":")
    kind = kind.strip().lower()
    if kind == "face" and not colon:
        return linear_probe()
    if kind in ("sphere", "box", "cylinder") and colon:
        if kind == "sphere":
            return SphereProbe(*_parse_numbers(spec, body, 1))
        if kind == "box":
            return BoxProbe(_parse_numbers(spec, body, 3))
        return CylinderProbe(*_parse_numbers(spec, body, 2))
    # Check files after the named forms, but before rejecting, so "C:\probe.stl" works.
    path = Path(text).expanduser()
    if path.is_file():
        return load_probe_mesh(path)
    if path.suffix.lower() in _MESH_SUFFIXES:
        raise ConfigError(_spec_message(spec, f"mesh file {str(path)!r} does not exist"))
    if kind in ("face", "sphere", "box", "cylinder"):
        raise ConfigError(_spec_message(spec, f"malformed {kind!r} spec"))
    raise ConfigError(_spec_message(spec, "unknown probe shape"))


# ----------------------------------------------------------------------------------------
# Rotations (MuJoCo's quaternion convention: w, x, y, z)


def quat_to_matrix(quat_wxyz: ArrayLike) -> NDArray[np.float64]:
    """Rotation matrix, shape (3, 3), of a quaternion (w, x, y, z); normalised first.

    Raises:
        ConfigError: a quaternion that is zero, non-finite or not of length 4.
    """
    return unit_quat_to_matrix(_normalised_quat(quat_wxyz))


def unit_quat_to_matrix(quat: NDArray[np.float64]) -> NDArray[np.float64]:
    """Rotation matrices, shape (..., 3, 3), of unit quaternions (w, x, y, z), shape (..., 4),
    taken as they are: no check and no normalisation (for inner loops that normalise their
    own; any other caller wants :func:`quat_to_matrix`). Element by element the same
    arithmetic for one quaternion or many, so a batch gives each one's matrix to the bit."""
    quat = np.asarray(quat, dtype=np.float64)
    # One quaternion (the probe's, every step) as Python floats: the same IEEE arithmetic in
    # a fifth of the time (no moveaxis).
    single = quat.ndim == 1
    w, x, y, z = quat.tolist() if single else np.moveaxis(quat, -1, 0)
    matrix = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )
    return matrix if single else np.moveaxis(matrix, (0, 1), (-2, -1))


def matrix_to_quat(rotation: ArrayLike) -> NDArray[np.float64]:
    """Unit quaternion (w, x, y, z), w >= 0, of a rotation matrix, shape (3, 3).

    A matrix within round-off of a rotation (such as a 4x4 pose file printed to 5 digits)
    is first replaced by its nearest rotation.

    Raises:
        ConfigError: not 3 x 3, or not a proper rotation (|R R^T - I| > 1e-3 or det < 0).
    """
    matrix = np.asarray(rotation, dtype=np.float64)
    if matrix.shape != (3, 3) or not np.all(np.isfinite(matrix)):
        raise ConfigError(f"a rotation must be a finite 3 x 3 matrix; got shape {matrix.shape}")
    error = float(np.abs(matrix @ matrix.T - np.eye(3)).max())
    if error > _ROTATION_TOLERANCE or np.linalg.det(matrix) <= 0.0:
        raise ConfigError(
            f"matrix is not a proper rotation (|R R^T - I| = {error:.2g}, det = "
            f"{np.linalg.det(matrix):.4g}); expected orthonormal with det +1"
        )
    u, _, vt = np.linalg.svd(matrix)
    m = u @ vt
    # Shepperd's method: divide by the largest of the four candidates for accuracy.
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    candidates = (trace, m[0, 0], m[1, 1], m[2, 2])
    k = int(np.argmax(candidates))
    if k == 0:
        s = 2.0 * math.sqrt(1.0 + trace)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif k == 1:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif k == 2:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    quat = np.array(q)
    quat /= np.linalg.norm(quat)
    return -quat if quat[0] < 0.0 else quat


@nb.njit(cache=True)
def _in_box(points, origin, rotation, bounds, margin, out):  # pragma: no cover - compiled
    """out[i]: point i [m] lies in the probe-frame box ``bounds`` widened by ``margin``."""
    for i in range(points.shape[0]):
        inside = True
        for axis in range(3):
            value = (
                (points[i, 0] - origin[0]) * rotation[0, axis]
                + (points[i, 1] - origin[1]) * rotation[1, axis]
                + (points[i, 2] - origin[2]) * rotation[2, axis]
            )
            if value < bounds[0, axis] - margin or value > bounds[1, axis] + margin:
                inside = False
                break
        out[i] = inside


def _normalised_quat(quat_wxyz: ArrayLike) -> NDArray[np.float64]:
    quat = np.asarray(quat_wxyz, dtype=np.float64).ravel()
    if quat.shape != (4,) or not np.isfinite(quat).all():
        raise ConfigError(f"a quaternion must be 4 finite numbers (w, x, y, z); got {quat_wxyz!r}")
    # What np.linalg.norm computes for a vector (the same bits), without its Python layers.
    norm = math.sqrt(float(quat.dot(quat)))
    if norm < 1e-12:
        raise ConfigError(
            f"quaternion {quat_wxyz!r} is zero and has no rotation; the identity is (1, 0, 0, 0)"
        )
    return quat / norm


# ----------------------------------------------------------------------------------------
# The posed probe


def _identity_quat() -> NDArray[np.float64]:
    return np.array([1.0, 0.0, 0.0, 0.0])


@dataclass(eq=False)
class Probe:
    """A probe shape with a pose in the world.

    The pose maps the probe frame to the world: p_world = R p_probe + position_world.
    Mutable (the probe moves every step); compared by identity, as arrays have no ``==``.

    Attributes:
        shape: the geometry, in the probe frame.
        position_world: probe origin (centre of the contact face) [m], shape (3,).
        quat_wxyz: orientation (w, x, y, z), MuJoCo's convention, kept normalised.
    """

    shape: ProbeShape
    position_world: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    quat_wxyz: NDArray[np.float64] = field(default_factory=_identity_quat)

    def __post_init__(self) -> None:
        self._bounds: NDArray[np.float64] | None = None
        if not isinstance(self.shape, ProbeShape):
            raise ConfigError(
                f"probe shape must be a ProbeShape (see parse_probe_spec); got {self.shape!r}"
            )
        self.set_pose(self.position_world, self.quat_wxyz)

    def set_pose(self, position_world: ArrayLike, quat_wxyz: ArrayLike) -> None:
        """Move the probe.

        Args:
            position_world: probe origin [m], shape (3,).
            quat_wxyz: orientation (w, x, y, z); normalised here.

        Raises:
            ConfigError: a non-finite position or a zero quaternion.
        """
        position = np.array(position_world, dtype=np.float64).ravel()
        if position.shape != (3,) or not np.all(np.isfinite(position)):
            raise ConfigError(f"probe position must be 3 finite metres; got {position_world!r}")
        self.quat_wxyz = _normalised_quat(quat_wxyz)
        self.position_world = position
        self._rotation = quat_to_matrix(self.quat_wxyz)

    def rotation_world(self) -> NDArray[np.float64]:
        """Rotation from the probe frame to the world, shape (3, 3) (columns: probe axes)."""
        return self._rotation.copy()

    def pose_matrix(self) -> NDArray[np.float64]:
        """Homogeneous probe-to-world transform, shape (4, 4), position in metres."""
        transform = np.eye(4)
        transform[:3, :3] = self._rotation
        transform[:3, 3] = self.position_world
        return transform

    def to_probe_frame(self, points_world: ArrayLike) -> NDArray[np.float64]:
        """Points [m], shape (n, 3), from the world to the probe frame."""
        # Row vectors: (R^T (p - c))^T = (p - c)^T R.
        return (_as_points(points_world) - self.position_world) @ self._rotation

    def to_world_frame(self, points_probe: ArrayLike) -> NDArray[np.float64]:
        """Points [m], shape (n, 3), from the probe frame to the world."""
        return _as_points(points_probe) @ self._rotation.T + self.position_world

    def near(self, points_world: NDArray[np.float64], margin_m: float = 0.0) -> NDArray[np.bool_]:
        """Which points [m] (n, 3) lie within the shape's local bounding box
        (:meth:`ProbeShape.local_bounds_m`), widened by ``margin_m`` [m]: only those can be
        inside the probe or within ``margin_m`` of it. Per-step checks evaluate the signed
        distance for those alone (a few dozen of the ~500 skin points at the phantom's
        apex). A box, not a ball about the origin: the probe's body reaches 80 mm behind
        the face, and a ball holding it would hold most of the phantom."""
        if self._bounds is None:
            self._bounds = self.shape.local_bounds_m()
        out = np.empty(points_world.shape[0], dtype=np.bool_)
        _in_box(
            np.ascontiguousarray(points_world, dtype=np.float64),
            self.position_world,
            self._rotation,
            self._bounds,
            float(margin_m),
            out,
        )
        return out

    def deepest_inside_m(self, points_world: NDArray[np.float64]) -> float:
        """How deep the deepest of ``points_world`` [m] (n, 3) lies inside the probe [m]
        (0 if none is inside). Only points within the bounding sphere can be: the signed
        distance is evaluated for those alone (a few dozen of ~500 skin points)."""
        near = self.near(points_world)
        if not np.any(near):
            return 0.0
        distance, _ = self.signed_distance_world(points_world[near])
        return float(max(0.0, -float(distance.min())))

    def signed_distance_world(
        self, points_world: ArrayLike
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Signed distance [m], shape (n,), negative inside, and outward normals (n, 3).

        Args:
            points_world: query points in the world [m], shape (n, 3).

        Returns:
            distance [m], shape (n,), and the probe surface's unit outward normal at the
            closest point, in the world frame, shape (n, 3).
        """
        distance, normal = self.shape.signed_distance(self.to_probe_frame(points_world))
        return distance, normal @ self._rotation.T

    def distance_hessian_world(self, points_world: ArrayLike) -> NDArray[np.float64]:
        """Hessian of the signed distance [1/m] at points in the world [m], shape (n, 3, 3),
        in the world frame (see :meth:`ProbeShape.distance_hessian`)."""
        local = self.shape.distance_hessian(self.to_probe_frame(points_world))
        return self._rotation @ local @ self._rotation.T

    def pressing_direction_world(self) -> NDArray[np.float64]:
        """The probe's +y axis in the world, shape (3,): the direction it presses."""
        return self._rotation[:, 1].copy()

    def surface_world(self) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        """The shape's triangle surface in the world: vertices [m] (v, 3), triangles (t, 3)."""
        vertices, triangles = self.shape.surface()
        return self.to_world_frame(vertices), triangles

    def wrench_about_origin(
        self, points_world: ArrayLike, forces_world: ArrayLike
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Resultant of point forces on the probe, about the probe origin, world frame.

        Args:
            points_world: application points [m], shape (n, 3).
            forces_world: forces on the probe [N], shape (n, 3).

        Returns:
            force [N], shape (3,): the sum of the forces; torque [N m], shape (3,): the sum
            of (p - position_world) x f.
        """
        points = _as_points(points_world)
        forces = _as_points(forces_world)
        if points.shape != forces.shape:
            raise ConfigError(
                f"points {points.shape} and forces {forces.shape} must have the same shape"
            )
        arms = points - self.position_world
        # arms x forces, component by component as np.cross computes it (the same bits),
        # without its ~80 Python-level calls: this runs once a step.
        torques = np.empty_like(arms)
        torques[:, 0] = arms[:, 1] * forces[:, 2] - arms[:, 2] * forces[:, 1]
        torques[:, 1] = arms[:, 2] * forces[:, 0] - arms[:, 0] * forces[:, 2]
        torques[:, 2] = arms[:, 0] * forces[:, 1] - arms[:, 1] * forces[:, 0]
        return forces.sum(axis=0), torques.sum(axis=0)

    @staticmethod
    def pose_from_matrix(transform: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Position [m] (3,) and quaternion (w, x, y, z) of a 4 x 4 probe-to-world transform.

        Reads the published ``Transform*.txt`` poses (``np.loadtxt`` gives the matrix).

        Raises:
            ConfigError: not 4 x 4, a bottom row other than (0, 0, 0, 1), or a rotation
                block that is not a rotation.
        """
        matrix = np.asarray(transform, dtype=np.float64)
        if matrix.shape != (4, 4) or not np.all(np.isfinite(matrix)):
            raise ConfigError(f"a pose must be a finite 4 x 4 matrix; got shape {matrix.shape}")
        if not np.allclose(matrix[3], (0.0, 0.0, 0.0, 1.0), atol=1e-9):
            raise ConfigError(f"a pose matrix's last row must be 0 0 0 1; got {matrix[3]}")
        return matrix[:3, 3].copy(), matrix_to_quat(matrix[:3, :3])

    @classmethod
    def looking_along(
        cls,
        shape: ProbeShape,
        contact_point_world: ArrayLike,
        direction_world: ArrayLike,
        roll_rad: float = 0.0,
    ) -> Probe:
        """A probe whose face centre is at a point and which presses along a direction.

        The probe's +y axis is ``direction_world``. At zero roll its x axis (the linear
        face's long axis) is the world x axis projected onto the plane normal to the
        direction, or the world z axis when the direction is within about 25 degrees of
        world x. ``roll_rad`` then turns the probe about its own +y axis (right-handed).

        Args:
            shape: the geometry.
            contact_point_world: where the probe origin goes [m], shape (3,).
            direction_world: pressing direction, shape (3,), any non-zero length.
            roll_rad: rotation about the pressing direction [rad].

        Raises:
            ConfigError: a zero or non-finite direction.
        """
        y_axis = np.asarray(direction_world, dtype=np.float64).ravel()
        length = float(np.linalg.norm(y_axis)) if y_axis.shape == (3,) else 0.0
        if not math.isfinite(length) or length < 1e-12:
            raise ConfigError(
                f"pressing direction must be a non-zero 3-vector; got {direction_world!r}"
            )
        y_axis = y_axis / length
        reference = np.array([1.0, 0.0, 0.0])
        if abs(y_axis @ reference) > 0.9:
            reference = np.array([0.0, 0.0, 1.0])
        x_axis = reference - (reference @ y_axis) * y_axis
        x_axis /= np.linalg.norm(x_axis)
        z_axis = np.cross(x_axis, y_axis)
        cos_roll, sin_roll = math.cos(roll_rad), math.sin(roll_rad)
        # Right-handed roll about y takes x to cos x - sin z (and z to sin x + cos z).
        x_rolled = cos_roll * x_axis - sin_roll * z_axis
        z_rolled = sin_roll * x_axis + cos_roll * z_axis
        rotation = np.column_stack([x_rolled, y_axis, z_rolled])
        return cls(
            shape, np.asarray(contact_point_world, dtype=np.float64), matrix_to_quat(rotation)
        )
