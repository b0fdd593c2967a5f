"""The parametric breast phantom and its mesh ladder (generated with gmsh, cached on disk).

The phantom imitates the CIRS Model 073 breast phantom of Tagliabue et al. (2020): a dome on
a flat base, 140 x 120 x 80 mm by default, 541 cm^3 like the published CT scene (measured at
142 x 123 x 79 mm, 541 cm^3), with 10 stiff spherical lesions of 5-10 mm diameter whose
centres lie 10-45 mm below the skin. Frame: the base lies on the plane z = 0, the dome
points up (+z), so a probe presses along -z; the footprint is centred on the origin, length
along x, width along y. Lengths are metres.

Geometry. The dome is the cap of an ellipsoid cut by the base plane, its truncation chosen
so that the default volume is the published 541 cm^3 (:mod:`~tissue.mesh.phantom.spec`).

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
up, so it contains the tracked point; a meshed sphere is inflated before meshing and scaled
after so that its tets hold exactly the sphere's volume
(:mod:`~tissue.mesh.phantom.lesion_shapes`). Stiffness, volume and landmark thus keep their
meaning at every level.

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

Modules: :mod:`~tissue.mesh.phantom.spec` (shape and lesions),
:mod:`~tissue.mesh.phantom.ladder` (levels and :func:`breast_phantom`),
:mod:`~tissue.mesh.phantom.meshing` (volume and collision surface),
:mod:`~tissue.mesh.phantom.lesion_shapes` (polyhedra and volume-keeping spheres),
:mod:`~tissue.mesh.phantom.calibration` (mesh size for a count),
:mod:`~tissue.mesh.phantom.gmsh_backend` (deterministic gmsh session, mesh extraction),
:mod:`~tissue.mesh.phantom.cache` (the on-disk cache).
"""

from tissue.mesh.phantom.cache import CACHE_ENV_VAR, cached_mesh, mesh_cache_dir
from tissue.mesh.phantom.calibration import CALIBRATION_ACCEPT as CALIBRATION_ACCEPT
from tissue.mesh.phantom.calibration import (
    CALIBRATION_MAX_ITERATIONS as CALIBRATION_MAX_ITERATIONS,
)
from tissue.mesh.phantom.calibration import LEVEL_TOLERANCE, calibrate_size
from tissue.mesh.phantom.gmsh_backend import RawMesh as RawMesh
from tissue.mesh.phantom.gmsh_backend import compact as compact
from tissue.mesh.phantom.gmsh_backend import (
    extract_surface_mesh,
    extract_volume_mesh,
    gmsh_session,
)
from tissue.mesh.phantom.gmsh_backend import set_sigpipe as set_sigpipe
from tissue.mesh.phantom.ladder import CALIBRATED_SIZE_M as CALIBRATED_SIZE_M
from tissue.mesh.phantom.ladder import (
    GENERATOR_VERSION,
    PHANTOM_LEVELS,
    breast_phantom,
    describe_mesh,
    parse_level,
)
from tissue.mesh.phantom.ladder import LESION_SHAPE_BY_LEVEL as LESION_SHAPE_BY_LEVEL
from tissue.mesh.phantom.ladder import generate_phantom as generate_phantom
from tissue.mesh.phantom.lesion_shapes import LARGEST_INFLATION as LARGEST_INFLATION
from tissue.mesh.phantom.lesion_shapes import (
    SMALLEST_KEPT_VOLUME_FRACTION as SMALLEST_KEPT_VOLUME_FRACTION,
)
from tissue.mesh.phantom.lesion_shapes import SPHERE_SIZE_PER_RADIUS as SPHERE_SIZE_PER_RADIUS
from tissue.mesh.phantom.lesion_shapes import add_convex_polyhedron as add_convex_polyhedron
from tissue.mesh.phantom.lesion_shapes import lesion_polyhedron as lesion_polyhedron
from tissue.mesh.phantom.lesion_shapes import match_lesion_volumes as match_lesion_volumes
from tissue.mesh.phantom.lesion_shapes import (
    meshed_unit_sphere_volume_ratio as meshed_unit_sphere_volume_ratio,
)
from tissue.mesh.phantom.lesion_shapes import volume_keeping_radius
from tissue.mesh.phantom.meshing import (
    CALIBRATED_COLLISION_SIZE_M as CALIBRATED_COLLISION_SIZE_M,
)
from tissue.mesh.phantom.meshing import add_dome as add_dome
from tissue.mesh.phantom.meshing import mesh_phantom_volume as mesh_phantom_volume
from tissue.mesh.phantom.meshing import orient_outward as orient_outward
from tissue.mesh.phantom.meshing import phantom_collision_surface
from tissue.mesh.phantom.spec import DEFAULT_LESIONS, LesionSpec, PhantomSpec

__all__ = [
    "CACHE_ENV_VAR",
    "DEFAULT_LESIONS",
    "GENERATOR_VERSION",
    "LEVEL_TOLERANCE",
    "PHANTOM_LEVELS",
    "LesionSpec",
    "PhantomSpec",
    "breast_phantom",
    "cached_mesh",
    "calibrate_size",
    "describe_mesh",
    "extract_surface_mesh",
    "extract_volume_mesh",
    "gmsh_session",
    "mesh_cache_dir",
    "parse_level",
    "phantom_collision_surface",
    "volume_keeping_radius",
]
