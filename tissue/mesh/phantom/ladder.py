"""The mesh ladder: the paper's nine levels, what a lesion is at each, and the cached
generator :func:`breast_phantom`.

A level is a tet count of :data:`PHANTOM_LEVELS`; each is meshed at a characteristic length
calibrated (:func:`~tissue.mesh.phantom.calibration.calibrate_size`) to hit the count within
10 %, starting from :data:`CALIBRATED_SIZE_M` for the default spec. The three coarsest
levels represent lesions as regular polyhedra, the others as spheres (see
:mod:`tissue.mesh.phantom`).
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np

from tissue.errors import ConfigError
from tissue.mesh import TetMesh
from tissue.mesh.phantom.cache import mesh_cache_dir
from tissue.mesh.phantom.calibration import calibrate_size
from tissue.mesh.phantom.meshing import (
    mesh_phantom_volume,
    phantom_collision_surface,
    phantom_skin_at,
)
from tissue.mesh.phantom.spec import PhantomSpec
from tissue.mesh.skin import check_collision_edge, with_collision_edge

#: Bump when anything that changes generated meshes changes (geometry, options, calibration).
GENERATOR_VERSION = 1

#: The paper's 9 mesh resolutions, in tets.
PHANTOM_LEVELS: tuple[int, ...] = (623, 1363, 2539, 4126, 7369, 12861, 26220, 105004, 176506)

# Lesion representation per level (see the package docstring).
LESION_SHAPE_BY_LEVEL = {623: "tetrahedron", 1363: "octahedron", 2539: "icosahedron"}

# Characteristic lengths [m] calibrated for the default PhantomSpec with this gmsh version;
# other specs (or a gmsh giving other counts) start from these and iterate.
CALIBRATED_SIZE_M: dict[int, float] = {
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


def breast_phantom(
    level: int | str = 4126,
    spec: PhantomSpec | None = None,
    cache_dir: str | Path | None = None,
    *,
    collision_edge_m: float | None = None,
    verbose: bool = False,
) -> TetMesh:
    """The breast phantom meshed at one level of the ladder, from the cache or generated.

    Args:
        level: one of :data:`PHANTOM_LEVELS` (tet count), as int or string.
        spec: the phantom's shape and lesions; default :class:`PhantomSpec()`.
        cache_dir: cache directory; default :func:`mesh_cache_dir`.
        collision_edge_m: the skin's edge length [m]: the dome meshed again by gmsh at it
            (:mod:`tissue.mesh.skin`), cached beside the level; None (default): the
            surface of about 1,000 triangles of the paper.
        verbose: let gmsh print its log.

    Returns:
        The mesh: nodes [m], tets (count within 10 % of ``level``), region labels (0 tissue,
        k lesion k), base nodes fixed, collision surface, lesion landmarks, metadata.

    Raises:
        ConfigError: unknown level, invalid spec, or a collision edge outside the level's
            range (:func:`tissue.mesh.skin.check_collision_edge`).
        MeshError: gmsh cannot hit the level's count within 10 % for this spec.
    """
    level = parse_level(level)
    spec = PhantomSpec() if spec is None else spec
    if not isinstance(spec, PhantomSpec):
        raise ConfigError(f"spec must be a PhantomSpec; got {type(spec).__name__}")
    key = f"phantom-g{GENERATOR_VERSION}-{level}-{spec.content_hash()[:16]}.npz"
    # Via the package at call time, so patching its cached_mesh/generate_phantom takes effect.
    from tissue.mesh import phantom

    mesh = phantom.cached_mesh(
        mesh_cache_dir(cache_dir) / key, lambda: phantom.generate_phantom(level, spec, verbose)
    )
    if collision_edge_m is None:
        return mesh
    edge_m = float(collision_edge_m)
    check_collision_edge(mesh, edge_m)
    skin_key = key.replace(".npz", f"-skin{round(edge_m * 1e6)}um.npz")
    return phantom.cached_mesh(
        mesh_cache_dir(cache_dir) / skin_key,
        lambda: with_collision_edge(mesh, edge_m, lambda e: phantom_skin_at(spec, e, verbose)),
    )


def describe_mesh(mesh: TetMesh) -> str:
    """One line for people: nodes, tets, lesions, collision triangles, fixed nodes."""
    triangles = mesh.collision_surface.triangle_count if mesh.collision_surface else 0
    return (
        f"{mesh.name}: {mesh.node_count} nodes, {mesh.tet_count} tets, "
        f"{mesh.lesion_count} lesions, {triangles} collision triangles, "
        f"{mesh.fixed_nodes.size} fixed nodes"
    )


def generate_phantom(level: int, spec: PhantomSpec, verbose: bool) -> TetMesh:
    started = time.perf_counter()
    shape = LESION_SHAPE_BY_LEVEL.get(level, "sphere")
    is_default = spec == PhantomSpec()
    initial = CALIBRATED_SIZE_M.get(level) if is_default else None
    trusted = initial is not None
    if initial is None:
        # Regular tets of volume V / N have edge (6 sqrt(2) V / N)^(1/3); gmsh's are a bit
        # smaller for the same size setting.
        initial = 1.1 * (6 * math.sqrt(2) * spec.volume_m3 / level) ** (1 / 3)
    tracked = spec.lesion_tracked_points_m()

    raw, size, attempts = calibrate_size(
        lambda h: mesh_phantom_volume(spec, shape, h, verbose),
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
