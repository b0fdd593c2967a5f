"""Moving a mesh's lesions at rest without remeshing: lesion placement jitter.

:func:`shift_lesions` translates each lesion region by an offset: the lesion's nodes move
by it exactly (the lesion keeps its shape and volume), the mesh's boundary nodes and the
other lesions' nodes stay, and the nodes in between follow a smooth blend of the offset
(a smoothstep in the distance from the lesion, falling to zero at the nearest node that
stays). The skin, the chest wall and every other lesion are untouched, so the scene keeps
its surface, its node count and its topology: a tissue built on the result costs what the
original does, where regenerating the mesh would cost a gmsh run (about a second) and
change what a renderer draws.

The blend is a mapping of the rest configuration, not a mechanical deformation: the moved
mesh is stress-free. Its tets stretch or shrink; :func:`shift_lesions` refuses an offset
that leaves any tet with less than :data:`MIN_VOLUME_RATIO` of its volume, and
:func:`lesion_shift_limits` says, per lesion, the largest offset every direction allows.
Near the skin, and at the coarse levels where a lesion sits among a few big tets, that
limit is small: a lesion 2 mm under the skin cannot move 3 mm towards it.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tissue.errors import MeshError
from tissue.mesh.core import CollisionSurface, TetMesh, boundary_faces, signed_tet_volumes
from tissue.mesh.embedding import BarycentricEmbedding, embed_points

#: The smallest ratio of a tet's volume after a shift to before that :func:`shift_lesions`
#: accepts (a quality floor well away from inversion).
MIN_VOLUME_RATIO = 0.5

# Directions :func:`lesion_shift_limits` tries: the 26 of a cube's faces, edges and corners.
_DIRECTIONS = np.array(
    [
        (i, j, k)
        for i in (-1, 0, 1)
        for j in (-1, 0, 1)
        for k in (-1, 0, 1)
        if (i, j, k) != (0, 0, 0)
    ],
    dtype=np.float64,
)
_DIRECTIONS /= np.linalg.norm(_DIRECTIONS, axis=1)[:, None]


def _outer_nodes(mesh: TetMesh) -> NDArray[np.bool_]:
    """Per node, whether it lies on the mesh's boundary or is fixed: nodes no shift moves."""
    outer = np.zeros(mesh.node_count, dtype=bool)
    outer[np.unique(boundary_faces(mesh.tets))] = True
    outer[mesh.fixed_nodes] = True
    return outer


def _lesion_weights(mesh: TetMesh, label: int, outer: NDArray[np.bool_]) -> NDArray[np.float64]:
    """Per node, the share of lesion ``label``'s offset it takes, (node_count,) in [0, 1];
    ``outer`` from :func:`_outer_nodes`."""
    tets = np.flatnonzero(mesh.region == label)
    if tets.size == 0:
        raise MeshError(
            f"lesion {label} ({mesh.region_names[label]}) has no tets to move: only lesion "
            "regions can be shifted (point lesions are tracked points, not regions)"
        )
    own = np.unique(mesh.tets[tets])
    held = outer.copy()
    held[np.unique(mesh.tets[(mesh.region > 0) & (mesh.region != label)])] = True
    if held[own].any():
        raise MeshError(
            f"lesion {label} ({mesh.region_names[label]}) touches the mesh's boundary or another "
            "lesion, so it cannot move without moving them; use a finer mesh"
        )
    # Distance of every node from the lesion's nodes, and of the nearest held node.
    gaps = mesh.nodes[:, None, :] - mesh.nodes[own][None, :, :]
    distance = np.min(np.linalg.norm(gaps, axis=2), axis=1)
    reach = float(distance[held].min())
    s = np.clip(1.0 - distance / reach, 0.0, 1.0)
    weights = s * s * (3.0 - 2.0 * s)
    weights[own] = 1.0
    weights[held] = 0.0
    return weights


def _volume_ratio(mesh: TetMesh, nodes: NDArray[np.float64]) -> float:
    return float(np.min(signed_tet_volumes(nodes, mesh.tets) / mesh.tet_volumes()))


def shift_lesions(mesh: TetMesh, offsets_m: ArrayLike) -> TetMesh:
    """A copy of ``mesh`` with each lesion region moved by its offset at rest.

    Args:
        mesh: a mesh whose lesions are regions (labels 1..n).
        offsets_m: one offset per lesion [m], (n, 3); zero rows leave a lesion where it is.

    Returns:
        The mesh with moved nodes, the same tets, regions, fixed nodes and skin (its collision
        surface re-embedded at the same rest positions), its tracked points moved with the
        material around them, and ``metadata["lesion_offsets_m"]`` (plus moved
        ``lesion_centres_m`` / ``lesion_tracked_points_m`` where the metadata has them).

    Raises:
        MeshError: the offsets' shape does not match the lesions, a lesion touches the
            boundary or another lesion, or a tet would keep less than
            :data:`MIN_VOLUME_RATIO` of its volume (the message gives the lesion's limit).
    """
    offsets = np.asarray(offsets_m, dtype=np.float64)
    count = mesh.lesion_count
    if offsets.shape != (count, 3) or not np.all(np.isfinite(offsets)):
        raise MeshError(
            f"offsets_m must be {count} finite rows of 3 numbers (one per lesion of {mesh.name}) "
            f"in metres; got shape {offsets.shape}"
        )
    nodes = mesh.nodes.copy()
    outer = _outer_nodes(mesh)
    for label in range(1, count + 1):
        offset = offsets[label - 1]
        if not np.any(offset):
            continue
        nodes += _lesion_weights(mesh, label, outer)[:, None] * offset[None, :]
    ratio = _volume_ratio(mesh, nodes)
    if ratio < MIN_VOLUME_RATIO:
        limits = lesion_shift_limits(mesh)
        worst = [
            f"{mesh.region_names[k + 1]}: {1e3 * np.linalg.norm(offsets[k]):.2f} mm asked, "
            f"{1e3 * limits[k]:.2f} mm allowed"
            for k in range(count)
            if np.linalg.norm(offsets[k]) > limits[k]
        ]
        which = "; ".join(worst) or "the lesions' blends overlap"
        raise MeshError(
            f"these lesion offsets would squeeze a tet of {mesh.name} to {ratio:.2f} of its "
            f"volume (the floor is {MIN_VOLUME_RATIO}): {which}. Use smaller offsets or a "
            "finer mesh"
        )
    moved = _with_nodes(mesh, nodes)
    moved.metadata["lesion_offsets_m"] = offsets.copy()
    if "lesion_centres_m" in mesh.metadata:
        centres = np.asarray(mesh.metadata["lesion_centres_m"], dtype=np.float64)
        moved.metadata["lesion_centres_m"] = centres + offsets
    if moved.landmarks is not None and "lesion_tracked_points_m" in mesh.metadata:
        moved.metadata["lesion_tracked_points_m"] = moved.landmarks.rest_positions.copy()
    return moved


def lesion_shift_limits(mesh: TetMesh) -> NDArray[np.float64]:
    """Per lesion, the largest offset [m] :func:`shift_lesions` accepts in every direction
    (26 directions tried, each bisected to 0.01 mm), (lesion_count,); 0 for a lesion that
    touches the boundary or another lesion."""
    limits = np.zeros(mesh.lesion_count)
    volumes = mesh.tet_volumes()
    outer = _outer_nodes(mesh)
    for label in range(1, mesh.lesion_count + 1):
        try:
            weights = _lesion_weights(mesh, label, outer)
        except MeshError:
            continue
        moving = np.flatnonzero(np.any(weights[mesh.tets] > 0.0, axis=1))
        corners = mesh.nodes[mesh.tets[moving]]
        share = weights[mesh.tets[moving]][..., None]
        local = np.arange(4 * moving.size, dtype=np.int64).reshape(-1, 4)
        best = np.inf
        for direction in _DIRECTIONS:
            low, high = 0.0, 0.05
            while high - low > 1e-5:
                middle = 0.5 * (low + high)
                moved = corners + share * (middle * direction)
                ratio = signed_tet_volumes(moved.reshape(-1, 3), local) / volumes[moving]
                if float(ratio.min()) >= MIN_VOLUME_RATIO:
                    low = middle
                else:
                    high = middle
            best = min(best, low)
        limits[label - 1] = best
    return limits


def surface_after_shift(
    surface: CollisionSurface,
    old_nodes: NDArray[np.float64],
    nodes: NDArray[np.float64],
    tets: NDArray[np.int64],
) -> CollisionSurface:
    """``surface`` embedded at the same rest positions in the volume whose nodes moved from
    ``old_nodes`` to ``nodes`` [m] (n, 3) (same ``tets``): the points whose tet has a moved
    node embedded again, the others keeping their tet and weights (their tet is where it
    was, and the lesions' blends move interior nodes only, so the skin's other tets are
    too). A skin at the probe's scale has thousands of points, few of them over a moved
    node: this keeps a randomised reset's cost off the skin."""
    changed = np.any(nodes != old_nodes, axis=1)
    redo = np.flatnonzero(np.any(changed[surface.embedding.tet_nodes], axis=1))
    tet_nodes = surface.embedding.tet_nodes.copy()
    weights = surface.embedding.weights.copy()
    if redo.size:
        fresh = embed_points(nodes, tets, surface.rest_vertices[redo])
        tet_nodes[redo] = fresh.tet_nodes
        weights[redo] = fresh.weights
    return CollisionSurface(
        rest_vertices=surface.rest_vertices,
        triangles=surface.triangles,
        embedding=BarycentricEmbedding(tet_nodes, weights),
    )


def _with_nodes(mesh: TetMesh, nodes: NDArray[np.float64]) -> TetMesh:
    """``mesh`` with other rest node positions: the skin embedded where it was
    (:func:`surface_after_shift`), the tracked points carried by their barycentric
    embedding."""
    moved = TetMesh(
        nodes=nodes,
        tets=mesh.tets,
        region=mesh.region,
        fixed_nodes=mesh.fixed_nodes,
        region_names=mesh.region_names,
        name=mesh.name,
        metadata=dict(mesh.metadata),
    )
    if mesh.collision_surface is not None:
        skin = surface_after_shift(mesh.collision_surface, mesh.nodes, nodes, mesh.tets)
        moved = replace(moved, collision_surface=skin)
    if mesh.landmarks is not None:
        points = mesh.landmarks.embedding.interpolate(nodes)
        moved = moved.with_landmarks(mesh.landmarks.names, points)
    return moved
