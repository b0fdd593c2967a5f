"""The tetrahedral tissue mesh: nodes, tets, regions, fixed nodes, collision surface, landmarks.

A :class:`TetMesh` is immutable data checked once when built. Everything that simulates
reads it; nothing mutates it. Units are SI (metres) throughout: loaders convert once.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from tissue.errors import MeshError
from tissue.mesh.embedding import BarycentricEmbedding, embed_points

# A tissue phantom larger than this [m] is almost certainly given in millimetres.
_LARGEST_PLAUSIBLE_EXTENT_M = 2.0
# A tet whose volume is below this fraction of the mean volume is treated as degenerate.
_DEGENERATE_VOLUME_FRACTION = 1e-8


@dataclass(frozen=True)
class CollisionSurface:
    """A triangle surface used for collision detection, embedded in the volume mesh.

    Attributes:
        rest_vertices: vertex positions at rest [m], shape (vertex_count, 3).
        triangles: vertex indices, shape (triangle_count, 3), counter-clockwise seen from
            outside (outward normals).
        embedding: barycentric map from the volume's nodes to the vertices.
    """

    rest_vertices: NDArray[np.float64]
    triangles: NDArray[np.int64]
    embedding: BarycentricEmbedding

    @property
    def vertex_count(self) -> int:
        return int(self.rest_vertices.shape[0])

    @property
    def triangle_count(self) -> int:
        return int(self.triangles.shape[0])

    def vertices(self, node_positions: NDArray[np.float64]) -> NDArray[np.float64]:
        """Deformed vertex positions [m], shape (vertex_count, 3), from node positions [m]."""
        return self.embedding.interpolate(node_positions)


@dataclass(frozen=True)
class Landmarks:
    """Named points embedded in the volume (lesion tracked points, centroids, ...).

    Attributes:
        names: one name per point.
        rest_positions: positions at rest [m], shape (point_count, 3).
        embedding: barycentric map from the volume's nodes to the points.
    """

    names: tuple[str, ...]
    rest_positions: NDArray[np.float64]
    embedding: BarycentricEmbedding

    @property
    def count(self) -> int:
        return len(self.names)

    def positions(self, node_positions: NDArray[np.float64]) -> NDArray[np.float64]:
        """Current positions [m], shape (point_count, 3), from node positions [m]."""
        return self.embedding.interpolate(node_positions)


@dataclass(frozen=True)
class TetMesh:
    """A linear tetrahedral mesh of the tissue, with everything a simulation needs.

    Attributes:
        nodes: rest node positions [m], shape (node_count, 3), float64.
        tets: node indices, shape (tet_count, 4), int64, positively oriented
            (det[x1-x0, x2-x0, x3-x0] > 0).
        region: region label per tet, shape (tet_count,), int64: 0 is the bulk tissue,
            k >= 1 is lesion k.
        fixed_nodes: indices of nodes held fixed in all directions (the chest wall), sorted.
        collision_surface: the surface used for contact, or None.
        landmarks: tracked points (lesion points), or None.
        region_names: a name per region label, index = label.
        name: a short description (level, source file).
    """

    nodes: NDArray[np.float64]
    tets: NDArray[np.int64]
    region: NDArray[np.int64]
    fixed_nodes: NDArray[np.int64]
    collision_surface: CollisionSurface | None = None
    landmarks: Landmarks | None = None
    region_names: tuple[str, ...] = ("tissue",)
    name: str = "mesh"
    metadata: dict[str, object] = field(default_factory=dict, compare=False)

    def __post_init__(self) -> None:
        nodes = np.ascontiguousarray(self.nodes, dtype=np.float64)
        tets = np.ascontiguousarray(self.tets, dtype=np.int64)
        region = np.ascontiguousarray(self.region, dtype=np.int64)
        fixed = np.unique(np.asarray(self.fixed_nodes, dtype=np.int64))
        object.__setattr__(self, "nodes", nodes)
        object.__setattr__(self, "tets", tets)
        object.__setattr__(self, "region", region)
        object.__setattr__(self, "fixed_nodes", fixed)
        _check_mesh(self)

    @property
    def node_count(self) -> int:
        return int(self.nodes.shape[0])

    @property
    def tet_count(self) -> int:
        return int(self.tets.shape[0])

    @property
    def dof_count(self) -> int:
        return 3 * self.node_count

    @property
    def lesion_count(self) -> int:
        return int(len(self.region_names) - 1)

    def tet_volumes(self, positions: NDArray[np.float64] | None = None) -> NDArray[np.float64]:
        """Signed tet volumes [m^3], shape (tet_count,), at rest or at ``positions`` [m]."""
        return signed_tet_volumes(self.nodes if positions is None else positions, self.tets)

    def with_fixed_nodes(self, fixed_nodes: NDArray[np.int64]) -> TetMesh:
        """A copy with another fixed-node set (checked again)."""
        return _replace(self, fixed_nodes=fixed_nodes)

    def with_collision_surface(
        self, rest_vertices: NDArray[np.float64], triangles: NDArray[np.int64]
    ) -> TetMesh:
        """A copy with a collision surface embedded barycentrically in this volume."""
        rest_vertices = np.asarray(rest_vertices, dtype=np.float64)
        surface = CollisionSurface(
            rest_vertices=rest_vertices,
            triangles=np.asarray(triangles, dtype=np.int64),
            embedding=embed_points(self.nodes, self.tets, rest_vertices),
        )
        return _replace(self, collision_surface=surface)

    def with_landmarks(
        self, names: tuple[str, ...], rest_positions: NDArray[np.float64]
    ) -> TetMesh:
        """A copy with tracked points embedded barycentrically in this volume."""
        rest_positions = np.asarray(rest_positions, dtype=np.float64).reshape(-1, 3)
        if len(names) != rest_positions.shape[0]:
            raise MeshError(
                f"got {len(names)} landmark names for {rest_positions.shape[0]} points; "
                "give one name per point"
            )
        landmarks = Landmarks(
            names=tuple(names),
            rest_positions=rest_positions,
            embedding=embed_points(self.nodes, self.tets, rest_positions),
        )
        return _replace(self, landmarks=landmarks)

    def boundary_triangles(self) -> NDArray[np.int64]:
        """Faces used by exactly one tet, shape (face_count, 3), outward-oriented."""
        return boundary_faces(self.tets)


def _replace(mesh: TetMesh, **changes: object) -> TetMesh:
    values: dict[str, object] = {
        "nodes": mesh.nodes,
        "tets": mesh.tets,
        "region": mesh.region,
        "fixed_nodes": mesh.fixed_nodes,
        "collision_surface": mesh.collision_surface,
        "landmarks": mesh.landmarks,
        "region_names": mesh.region_names,
        "name": mesh.name,
        "metadata": dict(mesh.metadata),
    }
    values.update(changes)
    return TetMesh(**values)  # type: ignore[arg-type]


def signed_tet_volumes(
    positions: NDArray[np.float64], tets: NDArray[np.int64]
) -> NDArray[np.float64]:
    """Signed volumes [m^3], shape (tet_count,), of tets over positions [m], (node_count, 3)."""
    x0 = positions[tets[:, 0]]
    e1 = positions[tets[:, 1]] - x0
    e2 = positions[tets[:, 2]] - x0
    e3 = positions[tets[:, 3]] - x0
    return np.einsum("ij,ij->i", e1, np.cross(e2, e3)) / 6.0


def boundary_faces(tets: NDArray[np.int64]) -> NDArray[np.int64]:
    """Faces of a positively oriented tet mesh used by one tet only, outward-oriented.

    Returns:
        triangles, shape (face_count, 3), int64, counter-clockwise seen from outside.
    """
    # Local faces ordered so that their normal points away from the opposite vertex
    # for a positively oriented tet.
    local = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])
    faces = tets[:, local].reshape(-1, 3)
    key = np.sort(faces, axis=1)
    _, first, counts = np.unique(key, axis=0, return_index=True, return_counts=True)
    return faces[first[counts == 1]]


def triangle_grid(divisions: int, interior: bool = False) -> NDArray[np.float64]:
    """Barycentric weights of the regular grid dividing each edge of a triangle into
    ``divisions`` parts, shape (k, 3); with ``interior``, only the points strictly inside
    (none for fewer than 3 divisions)."""
    steps = [(i, j) for i in range(divisions + 1) for j in range(divisions + 1 - i)]
    if interior:
        steps = [(i, j) for i, j in steps if i > 0 and j > 0 and i + j < divisions]
    weights = [(i / divisions, j / divisions, 1.0 - (i + j) / divisions) for i, j in steps]
    return np.array(weights, dtype=np.float64).reshape(-1, 3)


def _check_mesh(mesh: TetMesh) -> None:
    nodes, tets = mesh.nodes, mesh.tets
    if nodes.ndim != 2 or nodes.shape[1] != 3 or nodes.shape[0] < 4:
        raise MeshError(f"nodes must have shape (node_count >= 4, 3); got {nodes.shape}")
    if not np.all(np.isfinite(nodes)):
        raise MeshError("nodes contain NaN or Inf; check the mesh file")
    if tets.ndim != 2 or tets.shape[1] != 4 or tets.shape[0] < 1:
        raise MeshError(f"tets must have shape (tet_count >= 1, 4); got {tets.shape}")
    if tets.min() < 0 or tets.max() >= nodes.shape[0]:
        raise MeshError(
            f"tet node indices must lie in [0, {nodes.shape[0] - 1}]; "
            f"got range [{tets.min()}, {tets.max()}]"
        )
    extent = float(np.max(nodes.max(axis=0) - nodes.min(axis=0)))
    if extent > _LARGEST_PLAUSIBLE_EXTENT_M:
        raise MeshError(
            f"mesh '{mesh.name}' spans {extent:g} units, but lengths are in metres and tissue "
            f"phantoms are below {_LARGEST_PLAUSIBLE_EXTENT_M} m; the file is probably in "
            f"millimetres: scale it by 0.001 (probegym compress --scale 0.001, "
            f"TissueSpec(mesh_scale=0.001), load_tet_mesh(scale=0.001))"
        )
    volumes = signed_tet_volumes(nodes, tets)
    mean_volume = float(np.mean(np.abs(volumes)))
    degenerate = np.flatnonzero(np.abs(volumes) <= _DEGENERATE_VOLUME_FRACTION * mean_volume)
    if degenerate.size:
        raise MeshError(
            f"mesh '{mesh.name}' has {degenerate.size} degenerate (zero-volume) tets, "
            f"first indices {degenerate[:5].tolist()}; remove or re-mesh them"
        )
    inverted = np.flatnonzero(volumes < 0)
    if inverted.size:
        raise MeshError(
            f"mesh '{mesh.name}' has {inverted.size} inverted tets (negative volume), first "
            f"indices {inverted[:5].tolist()}; reorder their nodes (swap two) or re-mesh "
            "(loaders do this with orient=True)"
        )
    if mesh.region.shape != (tets.shape[0],):
        raise MeshError(f"region must have shape ({tets.shape[0]},); got {mesh.region.shape}")
    if mesh.region.min() < 0 or mesh.region.max() >= len(mesh.region_names):
        raise MeshError(
            f"region labels must lie in [0, {len(mesh.region_names) - 1}] "
            f"(one per name in region_names); got [{mesh.region.min()}, {mesh.region.max()}]"
        )
    fixed = mesh.fixed_nodes
    if fixed.size and (fixed.min() < 0 or fixed.max() >= nodes.shape[0]):
        raise MeshError(
            f"fixed node indices must lie in [0, {nodes.shape[0] - 1}]; "
            f"got range [{fixed.min()}, {fixed.max()}]"
        )


def node_dofs(nodes: NDArray[np.int64], axes: tuple[int, ...] = (0, 1, 2)) -> NDArray[np.int64]:
    """Dof indices (3·node + axis), node-major, of ``nodes`` along ``axes``.

    Returns:
        shape (len(nodes)·len(axes),).
    """
    nodes = np.asarray(nodes, dtype=np.int64)
    return (3 * nodes[:, None] + np.asarray(axes, dtype=np.int64)).reshape(-1)


def check_rigid_motion_removed(
    mesh: TetMesh,
    constrained_dofs: NDArray[np.int64],
    directions: NDArray[np.float64] | None = None,
) -> None:
    """Raise MeshError unless the constrained dofs remove all six rigid motions.

    Quasi-static problems are singular otherwise. The rigid modes (three translations, three
    rotations about the centroid) restricted to the constrained dofs must have rank six.
    ``directions`` (k, 3), unit: the direction each dof constrains, where not its world axis
    (a node sliding on a plane is held along the plane's normal only).
    """
    constrained_dofs = np.asarray(constrained_dofs, dtype=np.int64)
    nodes = constrained_dofs // 3
    if directions is None:
        directions = np.eye(3)[constrained_dofs % 3]
    relative = mesh.nodes[nodes] - mesh.nodes.mean(axis=0)
    modes = np.zeros((constrained_dofs.size, 6))
    # Translation t moves every point by t: its component along d is t . d; rotation w moves
    # r by w x r, whose component along d is w . (r x d).
    modes[:, :3] = directions
    modes[:, 3:] = np.cross(relative, directions)
    extent = float(np.max(np.ptp(mesh.nodes, axis=0)))
    if constrained_dofs.size >= 6:
        singular = np.linalg.svd(
            modes * np.array([1, 1, 1, 1 / extent, 1 / extent, 1 / extent]), compute_uv=False
        )
        if singular[-1] > 1e-9:
            return
    raise MeshError(
        f"the constraints of '{mesh.name}' ({constrained_dofs.size} constrained dofs) leave rigid "
        "motion free, so a quasi-static step is singular: fix at least three non-collinear nodes "
        "(for example the base plane, fixed_plane='z=min'), or simulate dynamically"
    )


def top_surface_nodes(
    mesh: TetMesh,
    center_xy: tuple[float, float],
    half_size_xy: tuple[float, float],
    depth_m: float = 0.002,
) -> NDArray[np.int64]:
    """Boundary nodes a flat, horizontal probe face pressing down at ``center_xy`` first meets.

    Args:
        mesh: the tissue mesh (z up).
        center_xy: centre of the rectangular face in plan view [m].
        half_size_xy: half sizes of the face along x and y [m].
        depth_m: nodes within this height below the highest node under the face are taken [m].

    Returns:
        node indices, sorted.
    """
    boundary = np.unique(boundary_faces(mesh.tets))
    xy = mesh.nodes[boundary, :2] - np.asarray(center_xy)
    inside = np.all(np.abs(xy) <= np.asarray(half_size_xy), axis=1)
    candidates = boundary[inside]
    if candidates.size == 0:
        raise MeshError(
            f"no surface node lies under a face at {center_xy} of half size {half_size_xy}"
        )
    top = mesh.nodes[candidates, 2].max()
    return np.sort(candidates[mesh.nodes[candidates, 2] >= top - depth_m])
