"""The published breast-phantom scene of Tagliabue et al. (2020), loaded as laid out.

The authors published their SOFA scene data (CT-segmented CIRS 073 phantom, collision
surface, fixed nodes, probe geometry, tracked probe poses for two lesions). probegym does
not ship them (no licence is stated); where a copy exists -- ``../shared/paper-scene`` in
this project -- :func:`load_paper_scene` reads it exactly as laid out, and
:func:`remesh_paper_scene` re-meshes its closed surface at the 9 levels of
:data:`tissue.mesh.phantom.PHANTOM_LEVELS`. All lengths are metres in the phantom's CT frame,
where the flat base (the chest wall) is at the *largest* z and the skin faces -z.

Layout read (file names are fixed)::

    breast_13k.msh              gmsh 2.2 volume mesh, 2,469 nodes, 9,295 tets
    fixednodes_13k.txt          822 0-based node indices of breast_13k.msh (the base)
    breast.stl                  closed surface, 4,016 triangles (for re-meshing)
    breast_500.stl              collision surface, 1,004 triangles, 504 vertices
    us_probe_collision.stl      the probe face's collision mesh, in the probe frame
    ground_truth/tumorN/Fiducial0.txt         lesion N's tracked point at rest (x y z)
    ground_truth/tumorN/Transform0..4.txt     4x4 probe poses: rest, then compression 1-4
    ground_truth/tumorN/springnodes_500.txt   breast_500 vertex indices under the probe

STL vertices are merged (exactly equal coordinates) in order of first appearance, as
SOFA's loader numbers them: ``springnodes_500.txt`` indexes vertices in that order.
"""

from __future__ import annotations

import hashlib
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from tissue.errors import MeshError
from tissue.mesh import TetMesh, boundary_faces
from tissue.mesh.io import load_tet_mesh
from tissue.mesh.phantom import (
    GENERATOR_VERSION,
    LEVEL_TOLERANCE,
    cached_mesh,
    calibrate_size,
    extract_volume_mesh,
    gmsh_session,
    mesh_cache_dir,
    parse_level,
)

VOLUME_MESH_FILE = "breast_13k.msh"
FIXED_NODES_FILE = "fixednodes_13k.txt"
SURFACE_FILE = "breast.stl"
COLLISION_FILE = "breast_500.stl"
PROBE_FILE = "us_probe_collision.stl"
GROUND_TRUTH_DIR = "ground_truth"
POSE_COUNT = 5

# Surface-mesh edges sharper than this split breast.stl into patches (base and skin) when
# it is reparametrised for re-meshing.
_FEATURE_ANGLE_RAD = math.radians(40.0)
# Characteristic lengths [m] calibrated on the published breast.stl (sha256 prefix below).
_CALIBRATED_STL_SHA = "9b854cbcf0dbddaf"
CALIBRATED_SIZE_M: dict[int, float] = {
    623: 0.02004795364174102,
    1363: 0.014579664411196628,
    2539: 0.011732048810989737,
    4126: 0.009646616231054136,
    7369: 0.0078431293865723,
    12861: 0.006198081816612305,
    26220: 0.004826156549180195,
    105004: 0.002933721632290663,
    176506: 0.0024469735799901777,
}
_TUMOUR_DIR = re.compile(r"^tumou?r(\d+)$")


@dataclass(frozen=True)
class PaperScene:
    """The published scene.

    Attributes:
        mesh: ``breast_13k.msh`` with the 822 base nodes fixed, ``breast_500.stl`` as
            embedded collision surface and each lesion's tracked point as landmark
            ``"tumorN"``.
        probe_poses: per lesion number N, the probe poses in the CT frame, shape (5, 4, 4):
            homogeneous transforms (probe frame to CT frame, translation [m]); index 0 at
            rest touching the skin, 1-4 the experiment's compression levels.
        spring_nodes: per lesion number N, indices into the collision surface's vertices
            under the probe (the prescribed-displacement method's nodes).
        probe_vertices: the probe face's collision vertices [m] in the probe frame, shape
            (vertex_count, 3); the face is y ~ 0 and the probe presses along +y.
        probe_triangles: the probe's triangles, shape (triangle_count, 3).
        lesion_points: per lesion number N, its tracked point at rest [m], shape (3,).
        directory: where the scene was read from.
    """

    mesh: TetMesh
    probe_poses: dict[int, NDArray[np.float64]]
    spring_nodes: dict[int, NDArray[np.int64]]
    probe_vertices: NDArray[np.float64]
    probe_triangles: NDArray[np.int64]
    lesion_points: dict[int, NDArray[np.float64]] = field(default_factory=dict)
    directory: Path = Path()

    @property
    def tumour_ids(self) -> tuple[int, ...]:
        """The lesion numbers N with ground truth, sorted."""
        return tuple(sorted(self.probe_poses))


def read_stl(path: str | Path) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Read an STL (ASCII or binary) with exactly-equal vertices merged in first-appearance
    order (as SOFA numbers them).

    Returns:
        vertices, shape (vertex_count, 3), in the file's units, and triangles,
        shape (triangle_count, 3), wound as in the file.
    """
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise MeshError(f"STL file {str(path)!r} does not exist")
    raw: Any = trimesh.load(path, file_type="stl", process=False, force="mesh")
    corners = np.asarray(raw.vertices, dtype=np.float64)[np.asarray(raw.faces)].reshape(-1, 3)
    _, first, inverse = np.unique(corners, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    # Renumber the sorted unique vertices by the position of their first appearance.
    order = np.argsort(first, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    vertices = corners[first[order]]
    return vertices, rank[inverse].reshape(-1, 3).astype(np.int64)


def _require(directory: Path, relative: list[str]) -> None:
    missing = [name for name in relative if not (directory / name).is_file()]
    if missing:
        raise MeshError(
            f"the paper scene in {str(directory)!r} is incomplete: missing "
            f"{', '.join(missing)}; give the directory laid out as shared/paper-scene "
            "(see its README)"
        )


def _tumour_dirs(directory: Path) -> dict[int, Path]:
    root = directory / GROUND_TRUTH_DIR
    if not root.is_dir():
        raise MeshError(
            f"the paper scene in {str(directory)!r} is incomplete: missing {GROUND_TRUTH_DIR}/ "
            "(with tumor1/, tumor2/, ...)"
        )
    found = {}
    for child in root.iterdir():
        match = _TUMOUR_DIR.match(child.name)
        if match and child.is_dir():
            found[int(match.group(1))] = child
    if not found:
        raise MeshError(f"{str(root)!r} holds no tumorN/ directories")
    return dict(sorted(found.items()))


def load_paper_scene(directory: str | Path) -> PaperScene:
    """Load the published scene from ``directory`` (laid out as ``shared/paper-scene``).

    Raises:
        MeshError: the directory or one of its files is missing (named), or malformed.
    """
    directory = Path(directory)
    if not directory.is_dir():
        raise MeshError(f"paper-scene directory {str(directory)!r} does not exist")
    _require(directory, [VOLUME_MESH_FILE, FIXED_NODES_FILE, COLLISION_FILE, PROBE_FILE])
    tumours = _tumour_dirs(directory)
    for folder in tumours.values():
        names = ["Fiducial0.txt", "springnodes_500.txt"]
        names += [f"Transform{i}.txt" for i in range(POSE_COUNT)]
        _require(directory, [f"{GROUND_TRUTH_DIR}/{folder.name}/{name}" for name in names])

    mesh = load_tet_mesh(
        directory / VOLUME_MESH_FILE,
        fixed_nodes_file=directory / FIXED_NODES_FILE,
        name="paper_scene_13k",
    )
    collision_vertices, collision_triangles = read_stl(directory / COLLISION_FILE)
    mesh = mesh.with_collision_surface(collision_vertices, collision_triangles)
    probe_poses, spring_nodes, lesion_points = {}, {}, {}
    for number, folder in tumours.items():
        lesion_points[number] = _read_matrix(folder / "Fiducial0.txt", (3,))
        probe_poses[number] = np.stack(
            [_read_matrix(folder / f"Transform{i}.txt", (4, 4)) for i in range(POSE_COUNT)]
        )
        nodes = np.loadtxt(folder / "springnodes_500.txt", dtype=np.int64, ndmin=1)
        if nodes.size and (nodes.min() < 0 or nodes.max() >= collision_vertices.shape[0]):
            raise MeshError(
                f"{str(folder / 'springnodes_500.txt')!r} indexes vertices up to {nodes.max()}, "
                f"but {COLLISION_FILE} has {collision_vertices.shape[0]}"
            )
        spring_nodes[number] = nodes
    landmark_names = tuple(f"tumor{number}" for number in lesion_points)
    mesh = mesh.with_landmarks(landmark_names, np.array(list(lesion_points.values())))
    probe_vertices, probe_triangles = read_stl(directory / PROBE_FILE)
    return PaperScene(
        mesh=mesh,
        probe_poses=probe_poses,
        spring_nodes=spring_nodes,
        probe_vertices=probe_vertices,
        probe_triangles=probe_triangles,
        lesion_points=lesion_points,
        directory=directory,
    )


def spring_nodes_to_volume(mesh: TetMesh, spring_vertices: NDArray[np.int64]) -> tuple[int, ...]:
    """The volume boundary nodes nearest the published spring vertices (collision surface).

    The paper attaches the probe to collision-surface vertices; our prescribed displacement
    acts on volume nodes, so each vertex is replaced by the nearest boundary node.
    """
    from scipy.spatial import cKDTree

    if mesh.collision_surface is None:
        raise MeshError("the published node sets index a collision surface; this mesh has none")
    boundary = np.unique(boundary_faces(mesh.tets))
    points = mesh.collision_surface.rest_vertices[np.asarray(spring_vertices)]
    _, nearest = cKDTree(mesh.nodes[boundary]).query(points)
    return tuple(int(n) for n in np.unique(boundary[nearest]))


def _read_matrix(path: Path, shape: tuple[int, ...]) -> NDArray[np.float64]:
    values = np.loadtxt(path, dtype=np.float64)
    if values.size != math.prod(shape):
        raise MeshError(f"{str(path)!r} holds {values.size} numbers; expected shape {shape}")
    return values.reshape(shape)


def base_threshold_z(directory: str | Path) -> float:
    """z [m] above which a node is on the base (the chest wall, at the largest z).

    The published base is not perfectly flat (its fixed nodes span 2.4 mm of z), so the
    threshold is recovered from the published fixed set: midway between the lowest fixed
    node and the highest free node of ``breast_13k.msh``. Every remeshed level fixes the
    nodes above it, the same region the authors fixed.
    """
    directory = Path(directory)
    mesh = load_tet_mesh(
        directory / VOLUME_MESH_FILE, fixed_nodes_file=directory / FIXED_NODES_FILE
    )
    z = mesh.nodes[:, 2]
    free = np.setdiff1d(np.arange(mesh.node_count), mesh.fixed_nodes)
    return float(0.5 * (z[mesh.fixed_nodes].min() + z[free].max()))


def remesh_paper_scene(
    directory: str | Path,
    level: int | str,
    cache_dir: str | Path | None = None,
    *,
    verbose: bool = False,
) -> TetMesh:
    """Re-mesh the published closed surface ``breast.stl`` at one level of the ladder.

    gmsh classifies ``breast.stl`` into smooth patches (edges sharper than 40 degrees split
    them: the skin and the base), reparametrises them and meshes the volume with a
    characteristic length calibrated to the level's tet count (within 10 %). The base
    nodes (see :func:`base_threshold_z`) are fixed; the collision surface
    (``breast_500.stl``) and the lesions' tracked points (``tumorN``) are embedded as in
    :func:`load_paper_scene`. Cached like the phantom, keyed by the generator version, the
    level and a hash of the files used.

    Raises:
        ConfigError: unknown level.
        MeshError: missing files, or gmsh cannot hit the count.
    """
    directory = Path(directory)
    level = parse_level(level)
    if not directory.is_dir():
        raise MeshError(f"paper-scene directory {str(directory)!r} does not exist")
    _require(directory, [SURFACE_FILE, VOLUME_MESH_FILE, FIXED_NODES_FILE, COLLISION_FILE])
    tumours = _tumour_dirs(directory)
    _require(
        directory,
        [f"{GROUND_TRUTH_DIR}/{folder.name}/Fiducial0.txt" for folder in tumours.values()],
    )
    digest = hashlib.sha256()
    for path in [
        directory / SURFACE_FILE,
        directory / VOLUME_MESH_FILE,
        directory / FIXED_NODES_FILE,
        directory / COLLISION_FILE,
    ] + [folder / "Fiducial0.txt" for folder in tumours.values()]:
        digest.update(path.read_bytes())
    stl_sha = hashlib.sha256((directory / SURFACE_FILE).read_bytes()).hexdigest()
    key = f"paper-scene-g{GENERATOR_VERSION}-{level}-{digest.hexdigest()[:16]}.npz"

    def generate() -> TetMesh:
        return _generate_remesh(directory, level, tumours, stl_sha, verbose)

    return cached_mesh(mesh_cache_dir(cache_dir) / key, generate)


def _generate_remesh(
    directory: Path, level: int, tumours: dict[int, Path], stl_sha: str, verbose: bool
) -> TetMesh:
    import time

    started = time.perf_counter()
    surface = directory / SURFACE_FILE
    initial = CALIBRATED_SIZE_M.get(level) if stl_sha.startswith(_CALIBRATED_STL_SHA) else None
    trusted = initial is not None
    if initial is None:
        volume = _closed_surface_volume(*read_stl(surface))
        initial = 1.1 * (6 * math.sqrt(2) * volume / level) ** (1 / 3)

    def mesh_at(size: float):
        with gmsh_session(verbose) as gmsh:
            gmsh.merge(str(surface))
            gmsh.model.mesh.classifySurfaces(_FEATURE_ANGLE_RAD, True, True, math.pi)
            gmsh.model.mesh.createGeometry()
            surfaces = [tag for _, tag in gmsh.model.getEntities(2)]
            loop = gmsh.model.geo.addSurfaceLoop(surfaces)
            volume_tag = gmsh.model.geo.addVolume([loop])
            gmsh.model.geo.synchronize()
            gmsh.option.setNumber("Mesh.MeshSizeMax", size)
            gmsh.model.mesh.generate(3)
            return extract_volume_mesh(gmsh, {volume_tag: 0})

    raw, size, attempts = calibrate_size(
        mesh_at,
        lambda r: r.tet_count,
        level,
        initial,
        f"breast.stl at level {level}",
        trusted_initial=trusted,
    )
    fixed = np.flatnonzero(raw.nodes[:, 2] >= base_threshold_z(directory))
    mesh = TetMesh(
        nodes=raw.nodes,
        tets=raw.tets,
        region=raw.region,
        fixed_nodes=fixed,
        name=f"paper_scene_{level}",
        metadata={
            "generator": "tissue.mesh.paper_scene.remesh_paper_scene",
            "generator_version": GENERATOR_VERSION,
            "level": level,
            "surface_sha256": stl_sha,
            "characteristic_length_m": size,
            "calibration_attempts": attempts,
            "level_tolerance": LEVEL_TOLERANCE,
            "generation_s": time.perf_counter() - started,
        },
    )
    vertices, triangles = read_stl(directory / COLLISION_FILE)
    mesh = mesh.with_collision_surface(vertices, triangles)
    points = np.array([_read_matrix(f / "Fiducial0.txt", (3,)) for f in tumours.values()])
    return mesh.with_landmarks(tuple(f"tumor{n}" for n in tumours), points)


def _closed_surface_volume(vertices: NDArray[np.float64], triangles: NDArray[np.int64]) -> float:
    """Enclosed volume [m^3] of a closed triangle surface (divergence theorem)."""
    corners = vertices[triangles]
    triple = np.einsum("ij,ij->i", corners[:, 0], np.cross(corners[:, 1], corners[:, 2]))
    return abs(float(triple.sum())) / 6.0
