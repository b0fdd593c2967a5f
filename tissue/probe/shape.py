"""The abstract rigid probe shape and the input checks every shape shares.

A :class:`ProbeShape` lives in the probe frame (see :mod:`tissue.probe`) and answers one
question exactly: the signed distance from points to its surface and the outward normal
there. Its curvature (:meth:`ProbeShape.distance_hessian`) and a local bounding box
(:meth:`ProbeShape.local_bounds_m`) follow from that and from its triangle surface.
"""

from __future__ import annotations

import abc
import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tissue.errors import ConfigError

# Any probe dimension above this [m] was almost certainly given in millimetres.
LARGEST_PLAUSIBLE_SIZE_M = 1.0

# The command-line spec forms (parse_probe_spec); here because MeshProbe's errors list them.
PROBE_SPEC_FORMS = (
    "face",
    "sphere:RADIUS",
    "box:LX,LY,LZ",
    "cylinder:RADIUS,HEIGHT",
    "PATH (a closed .stl/.obj/.ply mesh in the probe frame, metres)",
)

# Central-difference step of :meth:`ProbeShape.distance_hessian` [m]: far below the smallest
# radius of the built-in shapes (the face's 1.35 mm edge) and far above round-off in the
# normal.
_HESSIAN_STEP_M = 1e-6
# How much ProbeShape.local_bounds_m widens the box of the surface's vertices, as a fraction
# of the bounding radius (0.3 mm for the default face).
_LOCAL_BOUNDS_PAD = 0.01


class ProbeShape(abc.ABC):
    """Rigid probe geometry in the probe frame (the frame: see :mod:`tissue.probe`).

    Attributes:
        name: short human-readable description, e.g. ``"sphere:0.01"``.
        bounding_radius_m: radius [m] of a ball about the probe origin that holds the
            whole shape (a cheap broad-phase test for contact strategies).
        convex: whether the solid is convex.
        edge_radius_m: the smallest radius of its rounded edges [m] (0: sharp).
    """

    name: str
    bounding_radius_m: float
    #: Whether the solid is convex (its signed distance is then a convex function): surface
    #: depth measurement (:mod:`tissue.probe.surface_depth`) relies on it to skip facets and
    #: to find each facet's deepest point. False unless a shape knows better.
    convex: bool = False
    #: The smallest radius [m] of the solid's rounded edges and corners (0: a sharp one):
    #: how closely a skin kept out of it at its vertices can follow it
    #: (:func:`tissue.probe.surface_depth.facet_allowance_m`). 0 unless a shape knows better.
    edge_radius_m: float = 0.0

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
        points = as_points(points)
        hessian = np.empty((points.shape[0], 3, 3))
        for axis in range(3):
            offset = np.zeros(3)
            offset[axis] = _HESSIAN_STEP_M
            _, ahead = self.signed_distance(points + offset)
            _, behind = self.signed_distance(points - offset)
            hessian[:, :, axis] = (ahead - behind) / (2.0 * _HESSIAN_STEP_M)
        return 0.5 * (hessian + hessian.transpose(0, 2, 1))

    def compiled_distance(self) -> tuple[int, NDArray[np.float64]] | None:
        """The shape as :mod:`tissue.probe.surface_depth`'s compiled kernels take it: a
        kind and its parameters, or None (the default) for a shape they do not know, which
        is then measured through :meth:`signed_distance`."""
        return None

    def local_bounds_m(self) -> NDArray[np.float64]:
        """An axis-aligned box in the probe frame that holds the whole shape [m], shape
        (2, 3): its lowest and highest corner. A cheap, tighter broad phase than
        ``bounding_radius_m`` for an elongated probe such as the 53 x 13 mm default face,
        whose ball holds about ten times as many tissue points as its box.

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


def as_points(points: ArrayLike) -> NDArray[np.float64]:
    """Points as a C-contiguous float64 (n, 3) array, or a clear error."""
    array = np.ascontiguousarray(points, dtype=np.float64)
    if array.ndim == 1 and array.shape[0] == 3:
        array = array[None, :]
    if array.ndim != 2 or array.shape[1] != 3:
        raise ConfigError(f"points must have shape (n, 3) in metres; got shape {array.shape}")
    return array


def positive_size(value: float, what: str) -> float:
    """A finite, positive, plausible size in metres, or a ConfigError saying which."""
    number = float(value)
    if not math.isfinite(number) or number <= 0.0:
        raise ConfigError(f"{what} must be a positive number of metres; got {value!r}")
    if number > LARGEST_PLAUSIBLE_SIZE_M:
        raise ConfigError(
            f"{what} = {number} m is larger than any probe; sizes are in metres "
            f"(did you give millimetres? divide by 1000)"
        )
    return number
