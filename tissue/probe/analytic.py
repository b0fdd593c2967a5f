"""The analytic probe shapes: the linear probe face, box, sphere and cylinder.

Each has an exact signed distance (inside included) and a tessellated surface for drawing,
MuJoCo geometry and PBD. The default face's sizes are fitted to the published collision
STL (``../shared/paper-scene/us_probe_collision.stl``).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import ConvexHull

from tissue.errors import ConfigError
from tissue.probe.sdf import extruded_offset_sdf, rounded_slab_sdf
from tissue.probe.shape import ProbeShape, as_points, positive_size
from tissue.probe.surface_depth import CYLINDER, ROUNDED_SLAB, SPHERE

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
# housing and the start of the handle. Well beyond any compression the study makes (30
# mm), so tissue pressed around the probe cannot fold over its back and pull it in.
PROBE_BODY_DEPTH_M = 0.08

# Tessellation of the drawing/collision surfaces of the analytic shapes.
_ARC_SEGMENTS = 8
_CIRCLE_SEGMENTS = 48
_SPHERE_RINGS = 12


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

    convex = True

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
        p = as_points(points)
        hx, hy, hz = self._half
        r = self.edge_radius_m
        # The body's mid-plane is at y = -hy, so the face (top) lies at y = 0.
        return rounded_slab_sdf(p, hx - r, hz - r, self.corner_radius_m - r, hy, hy - r, r)

    def compiled_distance(self) -> tuple[int, NDArray[np.float64]]:
        hx, hy, hz = self._half
        r = self.edge_radius_m
        params = np.array([hx - r, hz - r, self.corner_radius_m - r, hy, hy - r, r])
        return ROUNDED_SLAB, params

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
            positive_size(length_m, "face length"),
            positive_size(thickness_m, "face thickness"),
            positive_size(width_m, "face width"),
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
            positive_size(v, f"box size {axis}") for v, axis in zip(values, "xyz", strict=True)
        )
        size = (sx, sy, sz)
        super().__init__(size, 0.0, 0.0, name="box:{:g},{:g},{:g}".format(*size))


class SphereProbe(ProbeShape):
    """A ball of radius R centred at (0, -R, 0): first contact at the probe origin.

    Args:
        radius_m: radius R [m].
    """

    convex = True

    def __init__(self, radius_m: float) -> None:
        self.radius_m = positive_size(radius_m, "sphere radius")
        self.edge_radius_m = self.radius_m
        self.name = f"sphere:{self.radius_m:g}"
        self.bounding_radius_m = 2.0 * self.radius_m
        self._centre = np.array([0.0, -self.radius_m, 0.0])
        self._surface: tuple[NDArray[np.float64], NDArray[np.int64]] | None = None

    def signed_distance(
        self, points: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        offset = as_points(points) - self._centre
        length = np.linalg.norm(offset, axis=1)
        # At the centre every direction is a gradient; +y (out of the face) is the useful one.
        at_centre = length == 0.0
        normal = offset / np.where(at_centre, 1.0, length)[:, None]
        normal[at_centre] = (0.0, 1.0, 0.0)
        return length - self.radius_m, normal

    def compiled_distance(self) -> tuple[int, NDArray[np.float64]]:
        return SPHERE, np.array([self.radius_m])

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

    convex = True

    def __init__(self, radius_m: float, height_m: float) -> None:
        self.radius_m = positive_size(radius_m, "cylinder radius")
        self.height_m = positive_size(height_m, "cylinder height")
        self.name = f"cylinder:{self.radius_m:g},{self.height_m:g}"
        self.bounding_radius_m = float(math.hypot(self.radius_m, self.height_m))
        self._surface: tuple[NDArray[np.float64], NDArray[np.int64]] | None = None

    def signed_distance(
        self, points: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        p = as_points(points)
        rho = np.hypot(p[:, 0], p[:, 2])
        on_axis = rho == 0.0
        safe = np.where(on_axis, 1.0, rho)
        # On the axis the radial direction is arbitrary; +x keeps the normal a unit vector.
        radial = np.column_stack([np.where(on_axis, 1.0, p[:, 0] / safe), p[:, 2] / safe])
        half = 0.5 * self.height_m
        return extruded_offset_sdf(rho - self.radius_m, radial, p[:, 1] + half, half, 0.0)

    def compiled_distance(self) -> tuple[int, NDArray[np.float64]]:
        return CYLINDER, np.array([self.radius_m, 0.5 * self.height_m])

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
