"""The phantom's shape and lesions: :class:`PhantomSpec` and :class:`LesionSpec`.

The phantom is a dome on a flat base: the cap of an ellipsoid of semi-axes (a, b, c) centred
at (0, 0, -d), cut by z = 0, with ``dome_truncation`` t = d / c. t = 0 gives a
half-ellipsoid (sides vertical at the base, 704 cm^3 for the default size); t -> 1 gives an
elliptic paraboloid (528 cm^3). The default t = 0.8625 matches the 541 cm^3 of the published
CT scene (Tagliabue et al. 2020); the skin then meets the base at about 68 degrees, a wedge
that meshes well. Frame: base on z = 0, dome up (+z), footprint centred on the origin,
length along x, width along y. Lengths are metres.

A lesion is a sphere given by its plan position, its depth below the skin straight above its
centre and its diameter; its tracked point is its top, ``centre + radius * (0, 0, 1)`` (see
:mod:`tissue.mesh.phantom`). Both specs validate themselves on construction
(:class:`~tissue.errors.ConfigError` says what to change).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from tissue.errors import ConfigError


@dataclass(frozen=True)
class LesionSpec:
    """One spherical lesion.

    Attributes:
        x_m: plan position along the length [m].
        y_m: plan position along the width [m].
        depth_m: vertical distance from the skin straight above the centre to the centre [m].
        diameter_m: sphere diameter [m].
    """

    x_m: float
    y_m: float
    depth_m: float
    diameter_m: float

    def __post_init__(self) -> None:
        for field_name in ("x_m", "y_m", "depth_m", "diameter_m"):
            value = getattr(self, field_name)
            if not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ConfigError(f"LesionSpec.{field_name}={value!r} must be a finite number")
        if not 0.0 < self.diameter_m < 0.05:
            raise ConfigError(
                f"LesionSpec.diameter_m={self.diameter_m!r} must lie in (0, 0.05) m; lesions "
                "are millimetres across (0.008 is 8 mm)"
            )
        if self.depth_m <= self.diameter_m / 2:
            raise ConfigError(
                f"LesionSpec.depth_m={self.depth_m!r} must exceed the radius "
                f"{self.diameter_m / 2!r} m so that the lesion lies under the skin"
            )


#: The default lesions: depths 10-45 mm, diameters 5-10 mm, spread over the plan view.
#: Placed so that the study's deepest pose (30 mm along the skin normal above each lesion,
#: the probe laid radially) leaves at least 13 mm between the probe and the fixed base; a
#: wider layout drove some of those poses into the base.
DEFAULT_LESIONS: tuple[LesionSpec, ...] = (
    LesionSpec(0.000, 0.000, 0.015, 0.008),
    LesionSpec(-0.025, 0.015, 0.010, 0.006),
    LesionSpec(0.025, -0.015, 0.020, 0.010),
    LesionSpec(-0.021, -0.0175, 0.025, 0.007),
    LesionSpec(0.028, 0.016, 0.012, 0.005),
    LesionSpec(0.000, 0.024, 0.030, 0.009),
    LesionSpec(0.000, -0.0224, 0.035, 0.006),
    LesionSpec(-0.0315, 0.000, 0.018, 0.007),
    LesionSpec(0.0315, -0.0035, 0.022, 0.008),
    LesionSpec(0.012, 0.010, 0.045, 0.010),
)


@dataclass(frozen=True)
class PhantomSpec:
    """Shape and lesions of the parametric breast phantom (lengths in metres).

    Attributes:
        length_m: footprint length along x [m].
        width_m: footprint width along y [m].
        height_m: dome height above the base [m].
        dome_truncation: d / c of the ellipsoid cap in [0, 0.95]: 0 is a half-ellipsoid,
            towards 1 a paraboloid (see the module docstring).
        lesions: the lesions, labelled 1.. in this order.
        skin_clearance_m: least distance from a lesion to the skin [m].
        base_clearance_m: least height of a lesion's bottom above the base [m].
        lesion_gap_m: least distance between two lesions' surfaces [m].
        collision_triangle_target: triangles wanted in the collision surface.
    """

    length_m: float = 0.140
    width_m: float = 0.120
    height_m: float = 0.080
    dome_truncation: float = 0.8625
    lesions: tuple[LesionSpec, ...] = DEFAULT_LESIONS
    skin_clearance_m: float = 0.002
    base_clearance_m: float = 0.004
    lesion_gap_m: float = 0.004
    collision_triangle_target: int = 1000

    def __post_init__(self) -> None:
        for field_name in ("length_m", "width_m", "height_m"):
            value = getattr(self, field_name)
            if not isinstance(value, (int, float)) or not 0.01 <= value <= 1.0:
                raise ConfigError(
                    f"PhantomSpec.{field_name}={value!r} must lie in [0.01, 1] m "
                    "(lengths are metres: 0.14 for 140 mm)"
                )
        if not 0.0 <= self.dome_truncation <= 0.95:
            raise ConfigError(
                f"PhantomSpec.dome_truncation={self.dome_truncation!r} must lie in [0, 0.95]"
            )
        if not isinstance(self.lesions, tuple) or not all(
            isinstance(lesion, LesionSpec) for lesion in self.lesions
        ):
            raise ConfigError("PhantomSpec.lesions must be a tuple of LesionSpec")
        if not 100 <= int(self.collision_triangle_target) <= 100_000:
            raise ConfigError(
                f"PhantomSpec.collision_triangle_target={self.collision_triangle_target!r} "
                "must lie in [100, 100000]"
            )
        for field_name in ("skin_clearance_m", "base_clearance_m", "lesion_gap_m"):
            if getattr(self, field_name) < 0:
                raise ConfigError(f"PhantomSpec.{field_name} must be >= 0")
        self._check_lesions()

    # Geometry of the ellipsoid cap -------------------------------------------------------

    @property
    def semi_axes_m(self) -> tuple[float, float, float]:
        """Ellipsoid semi-axes (a, b, c) [m]."""
        t = self.dome_truncation
        c = self.height_m / (1.0 - t)
        shrink = math.sqrt(1.0 - t * t)
        return self.length_m / 2 / shrink, self.width_m / 2 / shrink, c

    @property
    def ellipsoid_centre_z_m(self) -> float:
        """z of the ellipsoid's centre [m] (-d, below the base)."""
        return -self.dome_truncation * self.semi_axes_m[2]

    @property
    def volume_m3(self) -> float:
        """Exact phantom volume [m^3]."""
        t = self.dome_truncation
        return math.pi * self.length_m * self.width_m / 4 * self.height_m * (2 + t) / (3 * (1 + t))

    def skin_height_m(self, x_m: NDArray[np.float64] | float, y_m: NDArray[np.float64] | float):
        """Height of the skin above the base [m] at plan points; NaN outside the footprint."""
        a, b, c = self.semi_axes_m
        inside = 1.0 - (np.asarray(x_m) / a) ** 2 - (np.asarray(y_m) / b) ** 2
        with np.errstate(invalid="ignore"):
            height = c * np.sqrt(inside) + self.ellipsoid_centre_z_m
        return np.where(height >= 0, height, np.nan)

    def lesion_centres_m(self) -> NDArray[np.float64]:
        """Lesion centres [m], shape (lesion_count, 3)."""
        centres = np.array([[lesion.x_m, lesion.y_m, 0.0] for lesion in self.lesions])
        centres = centres.reshape(-1, 3)
        if centres.size:
            skin = self.skin_height_m(centres[:, 0], centres[:, 1])
            centres[:, 2] = skin - np.array([lesion.depth_m for lesion in self.lesions])
        return centres

    def lesion_radii_m(self) -> NDArray[np.float64]:
        """Lesion radii [m], shape (lesion_count,)."""
        return np.array([lesion.diameter_m / 2 for lesion in self.lesions], dtype=np.float64)

    def lesion_tracked_points_m(self) -> NDArray[np.float64]:
        """Tracked points [m], shape (lesion_count, 3): each lesion's top, centre + radius
        * (0, 0, 1), the lesion point nearest to the skin straight above its centre."""
        return self.lesion_centres_m() + self.lesion_radii_m()[:, None] * np.array([0, 0, 1.0])

    def content_hash(self) -> str:
        """Hex SHA-256 of every field, for cache keys."""
        text = json.dumps(dataclasses.asdict(self), sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()

    def _surface_point(self, theta: float, phi: float) -> NDArray[np.float64]:
        a, b, c = self.semi_axes_m
        return np.array(
            [
                a * math.sin(theta) * math.cos(phi),
                b * math.sin(theta) * math.sin(phi),
                self.ellipsoid_centre_z_m + c * math.cos(theta),
            ]
        )

    def _nearest_skin_point(self, point: NDArray[np.float64]) -> NDArray[np.float64]:
        from scipy.optimize import minimize

        # Only used to validate clearances: sample the dome, then polish the closest sample.
        a, b, c = self.semi_axes_m
        theta_max = math.acos(self.dome_truncation)  # the rim, z = 0
        theta = np.linspace(0.0, theta_max, 121)
        phi = np.linspace(-math.pi, math.pi, 241)
        tt, pp = np.meshgrid(theta, phi, indexing="ij")
        samples = np.stack(
            [
                a * np.sin(tt) * np.cos(pp),
                b * np.sin(tt) * np.sin(pp),
                self.ellipsoid_centre_z_m + c * np.cos(tt),
            ],
            axis=-1,
        ).reshape(-1, 3)
        best = int(np.argmin(np.sum((samples - point) ** 2, axis=1)))
        start = np.array([tt.reshape(-1)[best], pp.reshape(-1)[best]])

        def squared_distance(angles: NDArray[np.float64]) -> float:
            t = min(max(float(angles[0]), 0.0), theta_max)
            return float(np.sum((self._surface_point(t, float(angles[1])) - point) ** 2))

        result = minimize(
            squared_distance, start, method="Nelder-Mead", options={"xatol": 1e-10, "fatol": 1e-16}
        )
        t = min(max(float(result.x[0]), 0.0), theta_max)
        return self._surface_point(t, float(result.x[1]))

    def _check_lesions(self) -> None:
        if not self.lesions:
            return
        centres = self.lesion_centres_m()
        radii = self.lesion_radii_m()
        for k, (lesion, centre, radius) in enumerate(
            zip(self.lesions, centres, radii, strict=True), start=1
        ):
            if not np.isfinite(centre[2]):
                raise ConfigError(
                    f"lesion {k} at plan position ({lesion.x_m}, {lesion.y_m}) m lies outside "
                    f"the {self.length_m} x {self.width_m} m footprint; move it inwards"
                )
            if centre[2] - radius < self.base_clearance_m:
                raise ConfigError(
                    f"lesion {k} (depth {lesion.depth_m} m, diameter {lesion.diameter_m} m) "
                    f"reaches {centre[2] - radius:.4f} m above the base, less than "
                    f"base_clearance_m={self.base_clearance_m}; make it shallower or move it "
                    "towards the centre where the dome is higher"
                )
            skin_distance = float(np.linalg.norm(self._nearest_skin_point(centre) - centre))
            if skin_distance - radius < self.skin_clearance_m:
                raise ConfigError(
                    f"lesion {k} comes within {skin_distance - radius:.4f} m of the skin, less "
                    f"than skin_clearance_m={self.skin_clearance_m}; make it deeper or smaller"
                )
        for i in range(len(radii)):
            for j in range(i + 1, len(radii)):
                gap = float(np.linalg.norm(centres[i] - centres[j])) - radii[i] - radii[j]
                if gap < self.lesion_gap_m:
                    raise ConfigError(
                        f"lesions {i + 1} and {j + 1} are {gap:.4f} m apart, less than "
                        f"lesion_gap_m={self.lesion_gap_m}; move them apart"
                    )
