"""The parametric breast phantom and its mesh ladder (generated with gmsh, cached on disk).

The phantom imitates the CIRS Model 073 breast phantom of Tagliabue et al. (2020): a dome on
a flat base, 140 x 120 x 80 mm by default, 541 cm^3 like the published CT scene (measured at
142 x 123 x 79 mm, 541 cm^3), with 10 stiff spherical lesions of 5-10 mm diameter whose
centres lie 10-45 mm below the skin. Frame: the base lies on the plane z = 0, the dome
points up (+z), so a probe presses along -z; the footprint is centred on the origin, length
along x, width along y. Lengths are metres.

Geometry. The dome is the cap of an ellipsoid of semi-axes (a, b, c) centred at
(0, 0, -d), cut by z = 0, with ``dome_truncation`` t = d / c. t = 0 gives a half-ellipsoid
(sides vertical at the base, 704 cm^3 for the default size); t -> 1 gives an elliptic
paraboloid (528 cm^3). The default t = 0.8625 matches the published 541 cm^3; the skin then
meets the base at about 68 degrees, a wedge that meshes well.

Lesions. Lesion k (k = 1..10) is given in :class:`LesionSpec` by its plan position (x, y),
its ``depth_m`` (vertical distance from the skin straight above the centre down to the
centre) and its diameter. Its tracked point -- "the lesion contour point closest to the skin
above it", the point the paper tracks -- is defined exactly as the lesion's top,
``centre + radius * (0, 0, 1)``: of all the sphere's points, the nearest to the skin point
straight above the centre, where a probe pressing along -z sits over the lesion. It is the
same physical point at every level, whatever the lesion's mesh.

Mesh ladder. :data:`PHANTOM_LEVELS` are the paper's 9 resolutions (tet counts). Every level
is meshed by gmsh (OCC kernel, boolean fragments, so each lesion is a conforming sub-volume
labelled k, region name ``"lesion_k"``; region 0 is ``"tissue"``), with a characteristic
length calibrated to hit the count within +-10 %. Ten conforming spheres need at least
about 3k tets (a sphere needs about 25 tets and its surroundings grade out from it), so the
coarse levels use regular polyhedra. What a lesion is at each level:

========  ========================================================================
level     lesion representation (tets per lesion, measured with the default spec)
========  ========================================================================
623       regular tetrahedron: 1 tet (the level's tets are ~25 mm across)
1,363     regular octahedron: 4 tets
2,539     regular icosahedron: 16-17 tets
4,126+    sphere meshed at min(global size, 2 radii): 21-30 tets up to 12,861,
          23-52 at 26,220, 48-171 at 105,004, 50-262 at 176,506
========  ========================================================================

Every polyhedron has the sphere's centre and exactly its volume, with one vertex straight
up, so it contains the tracked point. A meshed sphere is an inscribed polyhedron holding
as little as 65 % of the volume at 2 radii per edge, so gmsh is given an inflated sphere
(by the volume ratio of a unit sphere meshed alike, at most 25 % in radius) and the lesion's
nodes are then scaled about its centre by the last few % so that its tets hold exactly the
sphere's volume. Stiffness, volume and landmark thus keep their meaning at every level.

Other parts of each level: fixed nodes are the nodes on the base (z = 0); the collision
surface is a separate gmsh surface mesh of the whole closed boundary (dome and base, about
1,000 triangles like the paper's 1,004; the base is never touched but keeps the surface
closed), outward-oriented and embedded barycentrically in the volume; landmarks are the 10
tracked points named ``"lesion_1"``...; ``mesh.metadata`` holds the lesion centres [m],
radii [m], tracked points [m], the representation, the characteristic length and the
generator version.

Determinism and cache. gmsh runs single-threaded with fixed options (no user config files),
so the same spec and level give identical arrays. Each level is stored as ``.npz`` in
:func:`mesh_cache_dir` (``PROBEGYM_CACHE_DIR`` or the user cache directory ``probegym``),
keyed by :data:`GENERATOR_VERSION`, a hash of the spec and the level, written atomically.
"""

from __future__ import annotations

import contextlib
import ctypes
import dataclasses
import functools
import hashlib
import json
import math
import os
import signal
import threading
import time
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from tissue.errors import ConfigError, MeshError
from tissue.mesh import TetMesh, signed_tet_volumes

#: Bump when anything that changes generated meshes changes (geometry, options, calibration).
GENERATOR_VERSION = 1

#: The paper's 9 mesh resolutions, in tets.
PHANTOM_LEVELS: tuple[int, ...] = (623, 1363, 2539, 4126, 7369, 12861, 26220, 105004, 176506)

#: Relative tolerance on a level's tet count.
LEVEL_TOLERANCE = 0.10

#: Environment variable that overrides the cache directory.
CACHE_ENV_VAR = "PROBEGYM_CACHE_DIR"

# Calibration stops once within this of the target; 10 % is the contract, 3 % leaves room
# for small platform differences in gmsh when a stored size is reused elsewhere.
_CALIBRATION_ACCEPT = 0.03
_CALIBRATION_MAX_ITERATIONS = 10

# Lesion representation per level (see the module docstring).
_LESION_SHAPE_BY_LEVEL = {623: "tetrahedron", 1363: "octahedron", 2539: "icosahedron"}

# Characteristic lengths [m] calibrated for the default PhantomSpec with this gmsh version;
# other specs (or a gmsh giving other counts) start from these and iterate.
_CALIBRATED_SIZE_M: dict[int, float] = {
    623: 0.028926726215092957,
    1363: 0.02288304341675446,
    2539: 0.03419015372941661,
    4126: 0.01717612294317282,
    7369: 0.009393287583158834,
    12861: 0.00649183735105791,
    26220: 0.004769338985136691,
    105004: 0.0029311549218313322,
    176506: 0.00244790474153558,
}
_CALIBRATED_COLLISION_SIZE_M = 0.0095


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
#: the probe laid radially) leaves at least 13 mm between the probe and the fixed base: a
#: layout reaching 45 mm from the centre put four lesions' 30 mm poses into the base
#: (clearances -3.5 to -1.4 mm at 26,220 tets), an experiment no method can finish.
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


def parse_level(value: int | str) -> int:
    """A mesh level (tet count) from an int or a string such as ``"4126"`` or ``"4,126"``.

    Raises:
        ConfigError: the value is not one of :data:`PHANTOM_LEVELS` (all are listed).
    """
    valid = ", ".join(str(level) for level in PHANTOM_LEVELS)
    level: int | None = None
    if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
        level = int(value)
    elif isinstance(value, str):
        text = value.strip().replace(",", "").replace("_", "")
        if text.isdigit():
            level = int(text)
    if level not in PHANTOM_LEVELS:
        raise ConfigError(f"unknown mesh level {value!r}; valid levels (tet counts) are {valid}")
    return level


def mesh_cache_dir(cache_dir: str | Path | None = None) -> Path:
    """The directory generated meshes are cached in.

    ``cache_dir`` if given, else ``$PROBEGYM_CACHE_DIR`` if set, else the platform's user
    cache directory for ``probegym`` (``~/.cache/probegym`` on Linux).
    """
    if cache_dir is not None:
        return Path(cache_dir)
    from_env = os.environ.get(CACHE_ENV_VAR)
    if from_env:
        return Path(from_env)
    import platformdirs

    return Path(platformdirs.user_cache_dir("probegym"))


def breast_phantom(
    level: int | str = 4126,
    spec: PhantomSpec | None = None,
    cache_dir: str | Path | None = None,
    *,
    verbose: bool = False,
) -> TetMesh:
    """The breast phantom meshed at one level of the ladder, from the cache or generated.

    Args:
        level: one of :data:`PHANTOM_LEVELS` (tet count), as int or string.
        spec: the phantom's shape and lesions; default :class:`PhantomSpec()`.
        cache_dir: cache directory; default :func:`mesh_cache_dir`.
        verbose: let gmsh print its log.

    Returns:
        The mesh: nodes [m], tets (count within 10 % of ``level``), region labels (0 tissue,
        k lesion k), base nodes fixed, collision surface, lesion landmarks, metadata.

    Raises:
        ConfigError: unknown level or invalid spec.
        MeshError: gmsh cannot hit the level's count within 10 % for this spec.
    """
    level = parse_level(level)
    spec = PhantomSpec() if spec is None else spec
    if not isinstance(spec, PhantomSpec):
        raise ConfigError(f"spec must be a PhantomSpec; got {type(spec).__name__}")
    key = f"phantom-g{GENERATOR_VERSION}-{level}-{spec.content_hash()[:16]}.npz"
    return cached_mesh(
        mesh_cache_dir(cache_dir) / key, lambda: _generate_phantom(level, spec, verbose)
    )


def cached_mesh(path: Path, generate: Callable[[], TetMesh]) -> TetMesh:
    """Load ``path`` if present, else generate, store atomically and return the stored copy.

    Returning what was read back makes a fresh mesh and a cache hit identical. A cache
    directory that cannot be written costs the cache, not the mesh (a warning says so).
    """
    from tissue.mesh.io import load_mesh_npz, save_mesh_npz

    if path.is_file():
        try:
            return load_mesh_npz(path)
        except MeshError:
            pass  # stale or damaged entry: regenerate and overwrite it
    mesh = generate()
    try:
        save_mesh_npz(mesh, path)
    except OSError as error:
        warnings.warn(f"cannot cache mesh in {str(path)!r}: {error}", stacklevel=3)
        return mesh
    return load_mesh_npz(path)


def describe_mesh(mesh: TetMesh) -> str:
    """One line for people: nodes, tets, lesions, collision triangles, fixed nodes."""
    triangles = mesh.collision_surface.triangle_count if mesh.collision_surface else 0
    return (
        f"{mesh.name}: {mesh.node_count} nodes, {mesh.tet_count} tets, "
        f"{mesh.lesion_count} lesions, {triangles} collision triangles, "
        f"{mesh.fixed_nodes.size} fixed nodes"
    )


# gmsh plumbing ---------------------------------------------------------------------------


def _set_sigpipe(action: Any) -> None:
    """Put SIGPIPE's action back after gmsh's initialisation, which sets the OS-level action
    to the default (end the process) behind Python's back: Python ignores SIGPIPE so that a
    write to a closed pipe raises ``BrokenPipeError``, and a study whose workers' pipes closed
    on Ctrl-C was killed by the signal instead of saying what it kept."""
    if action is None:
        return
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGPIPE, action)
    elif action in (signal.SIG_IGN, signal.SIG_DFL):  # off the main thread: through libc
        ctypes.CDLL(None).signal(int(signal.SIGPIPE), int(action))


@contextlib.contextmanager
def gmsh_session(verbose: bool = False) -> Iterator[Any]:
    """gmsh initialised with fixed, deterministic options; finalised on exit.

    User configuration files are not read (they could change the mesh); meshing is single
    threaded (thread scheduling would reorder nodes). If the caller already had gmsh
    initialised, a fresh model is used and removed and gmsh is left initialised, with the
    options above left set.
    """
    import gmsh

    owned = not gmsh.isInitialized()
    if owned:
        pipe_action = signal.getsignal(signal.SIGPIPE)
        gmsh.initialize(readConfigFiles=False, interruptible=False)
        _set_sigpipe(pipe_action)
    try:
        gmsh.model.add(f"probegym-{time.monotonic_ns()}")
        options = {
            "General.Terminal": 1 if verbose else 0,
            "General.Verbosity": 5 if verbose else 0,
            "General.NumThreads": 1,
            "Mesh.MaxNumThreads1D": 1,
            "Mesh.MaxNumThreads2D": 1,
            "Mesh.MaxNumThreads3D": 1,
            "Geometry.OCCParallel": 0,
            "Mesh.RandomSeed": 1,
            "Mesh.RandomFactor": 1e-9,
            "Mesh.RandomFactor3D": 1e-12,
            "Mesh.Algorithm": 6,
            "Mesh.Algorithm3D": 1,
            "Mesh.Optimize": 1,
            "Mesh.OptimizeNetgen": 0,
            "Mesh.ElementOrder": 1,
            "Mesh.MeshSizeFromCurvature": 0,
            "Mesh.MeshSizeFromPoints": 1,
            "Mesh.MeshSizeExtendFromBoundary": 1,
            "Mesh.MeshSizeMin": 0.0,
        }
        for name, value in options.items():
            gmsh.option.setNumber(name, value)
        yield gmsh
    finally:
        if owned:
            gmsh.finalize()
        else:
            with contextlib.suppress(Exception):
                gmsh.model.remove()


@dataclass
class _RawMesh:
    nodes: NDArray[np.float64]
    tets: NDArray[np.int64]
    region: NDArray[np.int64]

    @property
    def tet_count(self) -> int:
        return int(self.tets.shape[0])


def extract_volume_mesh(gmsh: Any, region_of_volume: dict[int, int]) -> _RawMesh:
    """Tets of the current gmsh model, nodes renumbered compactly in tag order, tets
    positively oriented, region label from the volume entity each tet belongs to."""
    tag_blocks, region_blocks = [], []
    for volume, label in sorted(region_of_volume.items()):
        types, _, node_tags = gmsh.model.mesh.getElements(3, volume)
        for element_type, tags in zip(types, node_tags, strict=True):
            if element_type != 4:  # 4 = 4-node tetrahedron
                raise MeshError(f"gmsh produced element type {element_type}; expected tets")
            block = np.asarray(tags, dtype=np.int64).reshape(-1, 4)
            tag_blocks.append(block)
            region_blocks.append(np.full(block.shape[0], label, dtype=np.int64))
    if not tag_blocks:
        raise MeshError("gmsh produced no tetrahedra")
    region = np.concatenate(region_blocks)
    nodes, tets = _compact(gmsh, np.concatenate(tag_blocks))
    negative = signed_tet_volumes(nodes, tets) < 0
    tets[negative, 2], tets[negative, 3] = tets[negative, 3], tets[negative, 2].copy()
    return _RawMesh(nodes=nodes, tets=tets, region=region)


def extract_surface_mesh(gmsh: Any) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """All triangles of the current gmsh model's 2D mesh, nodes renumbered compactly."""
    blocks = []
    for _, surface in gmsh.model.getEntities(2):
        types, _, node_tags = gmsh.model.mesh.getElements(2, surface)
        for element_type, tags in zip(types, node_tags, strict=True):
            if element_type != 2:  # 2 = 3-node triangle
                raise MeshError(f"gmsh produced element type {element_type}; expected triangles")
            blocks.append(np.asarray(tags, dtype=np.int64).reshape(-1, 3))
    return _compact(gmsh, np.concatenate(blocks))


def _compact(
    gmsh: Any, element_tags: NDArray[np.int64]
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Positions [m] of the nodes the elements use, and the elements renumbered onto them.

    Args:
        element_tags: gmsh node tags per element, (element_count, k).
    """
    node_tags, coordinates, _ = gmsh.model.mesh.getNodes()
    coordinates = np.asarray(coordinates, dtype=np.float64).reshape(-1, 3)
    node_tags = np.asarray(node_tags, dtype=np.int64)
    used, elements = np.unique(element_tags, return_inverse=True)
    position_of_tag = np.full(int(node_tags.max()) + 1, -1, dtype=np.int64)
    position_of_tag[node_tags] = np.arange(node_tags.size)
    return coordinates[position_of_tag[used]], elements.reshape(element_tags.shape).astype(np.int64)


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
    for _ in range(_CALIBRATION_MAX_ITERATIONS):
        result = mesh_at(size)
        count = count_of(result)
        error = abs(count / target - 1.0)
        if best is None or error < best[0]:
            best = (error, result, size)
        if error <= _CALIBRATION_ACCEPT or (
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


# The phantom ------------------------------------------------------------------------------


def _generate_phantom(level: int, spec: PhantomSpec, verbose: bool) -> TetMesh:
    started = time.perf_counter()
    shape = _LESION_SHAPE_BY_LEVEL.get(level, "sphere")
    is_default = spec == PhantomSpec()
    initial = _CALIBRATED_SIZE_M.get(level) if is_default else None
    trusted = initial is not None
    if initial is None:
        # Regular tets of volume V / N have edge (6 sqrt(2) V / N)^(1/3); gmsh's are a bit
        # smaller for the same size setting.
        initial = 1.1 * (6 * math.sqrt(2) * spec.volume_m3 / level) ** (1 / 3)
    tracked = spec.lesion_tracked_points_m()

    raw, size, attempts = calibrate_size(
        lambda h: _mesh_phantom_volume(spec, shape, h, verbose),
        lambda r: r.tet_count,
        level,
        initial,
        f"the phantom at level {level}",
        trusted_initial=trusted,
    )
    vertices, triangles = phantom_collision_surface(spec, verbose=verbose)
    fixed = np.flatnonzero(np.abs(raw.nodes[:, 2]) <= 1e-9 * spec.length_m)
    names = ("tissue",) + tuple(f"lesion_{k}" for k in range(1, len(spec.lesions) + 1))
    mesh = TetMesh(
        nodes=raw.nodes,
        tets=raw.tets,
        region=raw.region,
        fixed_nodes=fixed,
        region_names=names,
        name=f"breast_phantom_{level}",
        metadata={
            "generator": "tissue.mesh.phantom.breast_phantom",
            "generator_version": GENERATOR_VERSION,
            "level": level,
            "spec_hash": spec.content_hash(),
            "lesion_shape": shape,
            "characteristic_length_m": size,
            "calibration_attempts": attempts,
            "lesion_centres_m": spec.lesion_centres_m(),
            "lesion_radii_m": spec.lesion_radii_m(),
            "lesion_tracked_points_m": tracked,
            "collision_surface": "closed: dome and base",
            "generation_s": time.perf_counter() - started,
        },
    )
    mesh = mesh.with_collision_surface(vertices, triangles)
    if len(spec.lesions):
        mesh = mesh.with_landmarks(tuple(names[1:]), tracked)
    return mesh


def _add_dome(occ: Any, spec: PhantomSpec) -> int:
    """The dome solid in the OCC kernel; returns its volume tag."""
    a, b, c = spec.semi_axes_m
    zc = spec.ellipsoid_centre_z_m
    # OCC's sphere has its poles on z: after the dilation one pole is the dome's top.
    sphere = occ.addSphere(0.0, 0.0, zc, 1.0)
    occ.dilate([(3, sphere)], 0.0, 0.0, zc, a, b, c)
    box = occ.addBox(-a, -b, 0.0, 2 * a, 2 * b, c)
    result, _ = occ.intersect([(3, sphere)], [(3, box)])
    if len(result) != 1:
        raise MeshError(f"building the dome gave {len(result)} volumes; expected 1")
    return int(result[0][1])


def _lesion_polyhedron(
    centre: NDArray[np.float64], radius: float, shape: str
) -> NDArray[np.float64]:
    """Vertices [m] of a regular polyhedron (``shape``: tetrahedron, octahedron or
    icosahedron) with the volume of the sphere, centred at ``centre``, one vertex up (+z)."""
    from scipy.spatial import ConvexHull

    golden = (1.0 + math.sqrt(5.0)) / 2.0
    if shape == "tetrahedron":
        unit = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], dtype=np.float64)
    elif shape == "octahedron":
        unit = np.vstack([np.eye(3), -np.eye(3)])
    elif shape == "icosahedron":
        unit = np.array(
            [
                point
                for s1 in (-1.0, 1.0)
                for s2 in (-1.0, 1.0)
                for point in ([0, s1, s2 * golden], [s1, s2 * golden, 0], [s2 * golden, 0, s1])
            ]
        )
    else:
        raise ValueError(f"unknown lesion polyhedron {shape!r}")
    unit = unit / np.linalg.norm(unit[0])
    # Rotate vertex 0 onto +z (Rodrigues), so the top vertex lies above the tracked point.
    top = unit[0]
    axis = np.cross(top, [0.0, 0.0, 1.0])
    sin_angle, cos_angle = float(np.linalg.norm(axis)), float(top[2])
    if sin_angle > 1e-12:
        k = axis / sin_angle
        cross = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        rotation = np.eye(3) + sin_angle * cross + (1 - cos_angle) * cross @ cross
        unit = unit @ rotation.T
    scale = (4.0 / 3.0 * math.pi * radius**3 / ConvexHull(unit).volume) ** (1 / 3)
    return centre + scale * unit


def _add_convex_polyhedron(occ: Any, vertices: NDArray[np.float64]) -> int:
    """A convex polyhedron (flat triangular faces) in the OCC kernel; returns its volume tag."""
    from scipy.spatial import ConvexHull

    hull = ConvexHull(vertices)
    points = [occ.addPoint(*vertex) for vertex in vertices]
    lines: dict[tuple[int, int], int] = {}

    def line(i: int, j: int) -> int:
        key = (min(i, j), max(i, j))
        if key not in lines:
            lines[key] = occ.addLine(points[key[0]], points[key[1]])
        return lines[key] if i < j else -lines[key]

    faces = []
    for simplex in np.sort(hull.simplices, axis=1):
        i, j, k = (int(n) for n in simplex)
        loop = occ.addCurveLoop([line(i, j), line(j, k), line(k, i)])
        faces.append(occ.addPlaneSurface([loop]))
    return int(occ.addVolume([occ.addSurfaceLoop(faces)]))


def _mesh_phantom_volume(spec: PhantomSpec, shape: str, size: float, verbose: bool) -> _RawMesh:
    centres = spec.lesion_centres_m()
    radii = spec.lesion_radii_m()
    meshed_radii = radii
    if shape == "sphere":
        meshed_radii = np.array([volume_keeping_radius(r, size, verbose) for r in radii])
    with gmsh_session(verbose) as gmsh:
        occ = gmsh.model.occ
        dome = _add_dome(occ, spec)
        lesion_tags = []
        edge_lengths = []
        for centre, radius, meshed in zip(centres, radii, meshed_radii, strict=True):
            if shape == "sphere":
                lesion_tags.append(occ.addSphere(*centre, meshed))
            else:
                vertices = _lesion_polyhedron(centre, radius, shape)
                edge_lengths.append(
                    float(np.min(np.linalg.norm(vertices[1:] - vertices[0], axis=1)))
                )
                lesion_tags.append(_add_convex_polyhedron(occ, vertices))
        volume_of_region = {0: dome}
        if lesion_tags:
            _, children = occ.fragment([(3, dome)], [(3, tag) for tag in lesion_tags])
            lesion_volumes = []
            for k, pieces in enumerate(children[1:], start=1):
                if len(pieces) != 1:
                    raise MeshError(f"lesion {k} was cut into {len(pieces)} pieces by the dome")
                lesion_volumes.append(int(pieces[0][1]))
            tissue = [int(t) for _, t in children[0] if int(t) not in lesion_volumes]
            if len(tissue) != 1:
                raise MeshError(f"the tissue volume came out in {len(tissue)} pieces")
            volume_of_region = {0: tissue[0]}
            volume_of_region.update({k: v for k, v in enumerate(lesion_volumes, start=1)})
        occ.synchronize()

        gmsh.option.setNumber("Mesh.MeshSizeMax", size)
        for k, volume in sorted(volume_of_region.items()):
            if k == 0:
                continue
            points = gmsh.model.getBoundary([(3, volume)], recursive=True)
            if shape == "sphere":
                lesion_size = min(size, _SPHERE_SIZE_PER_RADIUS * meshed_radii[k - 1])
            else:
                # Do not split the polyhedron's edges: it stays a handful of tets.
                lesion_size = 1.001 * edge_lengths[k - 1] * math.sqrt(2.0)
            gmsh.model.mesh.setSize(points, lesion_size)
        gmsh.model.mesh.generate(3)
        region_of_volume = {volume: k for k, volume in volume_of_region.items()}
        raw = extract_volume_mesh(gmsh, region_of_volume)
    if shape == "sphere":
        _match_lesion_volumes(raw, centres, radii)
    return raw


# A lesion's volume correction is skipped if it would leave a neighbouring tet with less
# than this fraction of its volume.
_SMALLEST_KEPT_VOLUME_FRACTION = 0.5


def _match_lesion_volumes(
    raw: _RawMesh, centres: NDArray[np.float64], radii: NDArray[np.float64]
) -> None:
    """Scale each spherical lesion's nodes about its centre so that its tets hold exactly the
    sphere's volume (the inflation before meshing gets within about 10 %; this removes the
    rest with node moves of a few % of the radius). Tissue tets touching a lesion only
    stretch or shrink slightly; a correction that would squash one is skipped."""
    for k, (centre, radius) in enumerate(zip(centres, radii, strict=True), start=1):
        lesion_tets = raw.tets[raw.region == k]
        lesion_nodes = np.unique(lesion_tets)
        volume = float(signed_tet_volumes(raw.nodes, lesion_tets).sum())
        scale = (4.0 / 3.0 * math.pi * radius**3 / volume) ** (1 / 3)
        moved = raw.nodes.copy()
        moved[lesion_nodes] = centre + scale * (raw.nodes[lesion_nodes] - centre)
        touching = np.any(np.isin(raw.tets, lesion_nodes), axis=1)
        before = signed_tet_volumes(raw.nodes, raw.tets[touching])
        after = signed_tet_volumes(moved, raw.tets[touching])
        if np.all(after > _SMALLEST_KEPT_VOLUME_FRACTION * before):
            raw.nodes[:] = moved


# A spherical lesion's mesh size relative to its radius when the global size is coarser:
# about 30 tets per lesion, the fewest that still look round.
_SPHERE_SIZE_PER_RADIUS = 2.0
# A coarse sphere is inflated by at most this factor in radius to keep its volume.
_LARGEST_INFLATION = 1.25


def volume_keeping_radius(radius: float, size: float, verbose: bool = False) -> float:
    """The radius [m] to give gmsh so that a sphere meshed at ``size`` [m] (capped at
    ``_SPHERE_SIZE_PER_RADIUS`` radii) encloses the volume of a sphere of ``radius`` [m].

    A meshed sphere is an inscribed polyhedron: at two radii per edge it holds about 65 %
    of the sphere's volume, which would soften a coarse mesh's lesion. The polyhedron's
    volume ratio depends only on size / radius, so it is measured once on a unit sphere.
    """
    meshed = radius
    for _ in range(3):  # a fixed point: the ratio changes little with the inflation
        relative = min(size / meshed, _SPHERE_SIZE_PER_RADIUS)
        ratio = _meshed_unit_sphere_volume_ratio(round(relative, 6), verbose)
        meshed = radius * min(ratio ** (-1 / 3), _LARGEST_INFLATION)
    return meshed


@functools.lru_cache(maxsize=256)
def _meshed_unit_sphere_volume_ratio(relative_size: float, verbose: bool) -> float:
    with gmsh_session(verbose) as gmsh:
        gmsh.model.occ.addSphere(0.0, 0.0, 0.0, 1.0)
        gmsh.model.occ.synchronize()
        gmsh.option.setNumber("Mesh.MeshSizeMax", relative_size)
        gmsh.model.mesh.setSize(gmsh.model.getEntities(0), relative_size)
        gmsh.model.mesh.generate(2)
        vertices, triangles = extract_surface_mesh(gmsh)
    corners = vertices[triangles]
    volume = abs(np.einsum("ij,ij->i", corners[:, 0], np.cross(corners[:, 1], corners[:, 2])).sum())
    return float(volume / 6.0 / (4.0 / 3.0 * math.pi))


def phantom_collision_surface(
    spec: PhantomSpec, verbose: bool = False
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """The phantom's closed outer surface (dome and base) meshed by gmsh in 2D.

    Returns:
        vertices [m], shape (vertex_count, 3), and triangles, shape (triangle_count, 3),
        counter-clockwise seen from outside; the count is within 10 % of
        ``spec.collision_triangle_target``.
    """
    target = int(spec.collision_triangle_target)
    initial = _CALIBRATED_COLLISION_SIZE_M * (spec.volume_m3 / PhantomSpec().volume_m3) ** (1 / 3)
    initial *= math.sqrt(1000 / target)

    def mesh_at(size: float) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        with gmsh_session(verbose) as gmsh:
            _add_dome(gmsh.model.occ, spec)
            gmsh.model.occ.synchronize()
            gmsh.option.setNumber("Mesh.MeshSizeMax", size)
            gmsh.model.mesh.generate(2)
            return extract_surface_mesh(gmsh)

    (vertices, triangles), _, _ = calibrate_size(
        mesh_at, lambda r: r[1].shape[0], target, initial, "the collision surface", dimension=2
    )
    return vertices, _orient_outward(spec, vertices, triangles)


def _orient_outward(
    spec: PhantomSpec, vertices: NDArray[np.float64], triangles: NDArray[np.int64]
) -> NDArray[np.int64]:
    """Triangles wound so that normals point out: down on the base, away from the
    ellipsoid's centre on the dome (an ellipsoid is star-shaped about its centre)."""
    corners = vertices[triangles]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    centroids = corners.mean(axis=1)
    on_base = np.all(np.abs(corners[:, :, 2]) <= 1e-9 * spec.length_m, axis=1)
    outward = np.where(
        on_base[:, None],
        np.array([0.0, 0.0, -1.0]),
        centroids - np.array([0.0, 0.0, spec.ellipsoid_centre_z_m]),
    )
    flip = np.einsum("ij,ij->i", normals, outward) < 0
    triangles = triangles.copy()
    triangles[flip, 1], triangles[flip, 2] = triangles[flip, 2], triangles[flip, 1].copy()
    return triangles
