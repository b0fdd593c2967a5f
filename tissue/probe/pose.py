"""The posed probe: a shape with a probe-to-world pose, its broad phase and its wrench.

A pose maps the probe frame to the world, p_world = R p_probe + position, which is how the
published ``ground_truth/tumorN/Transform*.txt`` files read (see
:meth:`Probe.pose_from_matrix`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numba as nb
import numpy as np
from numpy.typing import ArrayLike, NDArray

from tissue.errors import ConfigError
from tissue.probe.rotation import matrix_to_quat, normalised_quat, quat_to_matrix
from tissue.probe.shape import ProbeShape, as_points


@nb.njit(cache=True, inline="always")
def point_in_box(points, i, origin, rotation, bounds, margin):  # pragma: no cover - compiled
    """Whether point i [m] lies in the probe-frame box ``bounds`` widened by ``margin``."""
    for axis in range(3):
        value = (
            (points[i, 0] - origin[0]) * rotation[0, axis]
            + (points[i, 1] - origin[1]) * rotation[1, axis]
            + (points[i, 2] - origin[2]) * rotation[2, axis]
        )
        if value < bounds[0, axis] - margin or value > bounds[1, axis] + margin:
            return False
    return True


@nb.njit(cache=True)
def _in_box(points, origin, rotation, bounds, margin, out):  # pragma: no cover - compiled
    """out[i]: point i [m] lies in the probe-frame box ``bounds`` widened by ``margin``."""
    for i in range(points.shape[0]):
        out[i] = point_in_box(points, i, origin, rotation, bounds, margin)


@nb.njit(cache=True)
def _any_in_box(points, origin, rotation, bounds, margin):  # pragma: no cover - compiled
    """Whether any point [m] lies in the probe-frame box ``bounds`` widened by ``margin``
    (:func:`_in_box`'s test, stopping at the first)."""
    for i in range(points.shape[0]):
        if point_in_box(points, i, origin, rotation, bounds, margin):
            return True
    return False


def _identity_quat() -> NDArray[np.float64]:
    """The identity rotation (w, x, y, z) = (1, 0, 0, 0): a fresh array per probe."""
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
        self.quat_wxyz = normalised_quat(quat_wxyz)
        self.position_world = position
        self._rotation = quat_to_matrix(self.quat_wxyz)

    def set_normalised_pose(
        self,
        position_world: NDArray[np.float64],
        quat_wxyz: NDArray[np.float64],
        rotation: NDArray[np.float64],
    ) -> None:
        """Move the probe to a pose its caller has checked and normalised: a finite position
        [m] (3,), a unit quaternion (4,) and its rotation matrix (3, 3), each what
        :meth:`set_pose` would hold, to the bit, and each the probe's own from now on (no
        check, no copy). For the sleeping tissue step
        (:meth:`tissue.contact.base.ContactModel.sleep_if_clear`), which has worked them out
        in its compiled checks; anything else wants :meth:`set_pose`."""
        self.position_world = position_world
        self.quat_wxyz = quat_wxyz
        self._rotation = rotation

    def local_bounds_m(self) -> NDArray[np.float64]:
        """The shape's local bounding box [m], (2, 3), probe frame
        (:meth:`ProbeShape.local_bounds_m`), kept: read it, never write it."""
        if self._bounds is None:
            self._bounds = self.shape.local_bounds_m()
        return self._bounds

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
        return (as_points(points_world) - self.position_world) @ self._rotation

    def to_world_frame(self, points_probe: ArrayLike) -> NDArray[np.float64]:
        """Points [m], shape (n, 3), from the probe frame to the world."""
        return as_points(points_probe) @ self._rotation.T + self.position_world

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
        (0 if none is inside). Only points within the local bounding box (:meth:`near`) can
        be: the signed distance is evaluated for those alone (a few dozen of ~500 skin
        points)."""
        near = self.near(points_world)
        if not np.any(near):
            return 0.0
        distance, _ = self.signed_distance_world(points_world[near])
        return float(max(0.0, -float(distance.min())))

    def clearance_m(self, points_world: NDArray[np.float64], within_m: float) -> float:
        """The smallest signed distance [m] from ``points_world`` [m] (n, 3) to the probe's
        surface (negative: a point inside the probe), over the points within ``within_m``
        [m] (>= 0) of the probe; ``inf`` when there is none (every point lies farther than
        ``within_m`` from the probe).

        A point outside the local bounding box widened by ``within_m`` (:meth:`near`) lies
        farther than that from the box, and so from the probe inside it: the exact signed
        distance is evaluated only for the points inside the widened box. So
        ``clearance_m(points, d) > d`` says exactly that every point is farther than ``d``
        from the probe, at the cost of one compiled pass over the points when none is near
        (3-4 us for the 512 skin points of the 1,363-tet phantom, most of it the call).
        """
        points = np.ascontiguousarray(points_world, dtype=np.float64)
        if not self.any_near(points, within_m):
            return math.inf
        near = self.near(points, within_m)
        distance, _ = self.signed_distance_world(points[near])
        return float(distance.min())

    def any_near(self, points_world: NDArray[np.float64], margin_m: float = 0.0) -> bool:
        """Whether any of ``points_world`` [m] (n, 3) lies within the local bounding box
        widened by ``margin_m`` [m]: ``np.any(near(points_world, margin_m))``, stopping at
        the first such point."""
        if self._bounds is None:
            self._bounds = self.shape.local_bounds_m()
        return bool(
            _any_in_box(
                np.ascontiguousarray(points_world, dtype=np.float64),
                self.position_world,
                self._rotation,
                self._bounds,
                float(margin_m),
            )
        )

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
        points = as_points(points_world)
        forces = as_points(forces_world)
        if points.shape != forces.shape:
            raise ConfigError(
                f"points {points.shape} and forces {forces.shape} must have the same shape"
            )
        arms = points - self.position_world
        # arms x forces, component by component as np.cross computes it (the same bits),
        # without its Python-level overhead: this runs once a step.
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
