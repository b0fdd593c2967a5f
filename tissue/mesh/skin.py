"""The skin at a chosen resolution: a collision surface whose edges are about a given length.

Contact acts on the collision surface's vertices (:mod:`tissue.contact`). A surface coarser
than the probe lets the probe's edges pass between its vertices; one at the probe's scale
keeps every facet near the probe spanned by several vertices. :func:`with_collision_edge`
gives a mesh such a surface, embedded barycentrically in its volume as before:

- the built-in phantom's dome is meshed again by gmsh at that edge length
  (:func:`tissue.mesh.phantom.breast_phantom`'s ``collision_edge_m``; its base, which the
  probe never reaches, stays coarse);
- any other mesh's collision surface (the published scene's ``breast_500.stl``), or its
  volume's boundary where it has none, is refined by conforming edge bisection
  (:func:`refine_surface`) until no edge is longer.

What is refused, with the numbers and the valid range (:func:`check_collision_edge`): an edge
longer than the volume's own boundary (:func:`boundary_edge_m`: a skin coarser than the tissue
it covers would let the volume's boundary nodes through), and one so short that the surface
would exceed :data:`MAX_COLLISION_VERTICES`. A surface whose points fall outside the volume
(:func:`check_embedded`, a surface in other units or of another body) is refused naming them.

Lengths are metres.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from tissue.errors import ConfigError, MeshError
from tissue.mesh.core import TetMesh, boundary_faces

#: The most vertices a collision surface may have: about a 0.45 mm edge over the phantom's
#: dome. Every step interpolates the whole surface from the volume's nodes and searches it
#: for the probe; beyond this the surface, not the tissue, would set the step's cost.
MAX_COLLISION_VERTICES = 200_000
#: The skin drawn (:meth:`tissue.Tissue.surface`) is no finer than this edge [m], where the
#: volume allows it: MuJoCo draws it with one mocap body per vertex, and at 2 mm (8,357
#: vertices on the phantom) its collision stage overflowed its default arena (143 MB asked)
#: while Studio's viewer would stream about 1 MB a frame; at 4 mm a 480 x 480 frame took 79
#: ms against 29 ms on the paper's surface. Contact uses the skin at its own resolution.
DRAWN_EDGE_M = 0.004
#: A surface point lying farther outside its tet than this fraction of the tet's longest
#: edge is not embedded in the volume (:func:`check_embedded`). The phantom's own surfaces,
#: curved over a faceted volume, lie at most 1.19 of it outside (a 2 mm skin over the
#: 2,539-tet level, whose boundary facets are about 31 mm across: 13 mm out); a surface in
#: other units or of another body lies many times farther.
EMBEDDING_OUTSIDE_FRACTION = 2.0
#: :func:`refine_surface` splits edges longer than this fraction of the edge length asked
#: for: the halves of the shortest split edge are then 2/3 of it.
SPLIT_FRACTION = 4.0 / 3.0
# Vertices of an equilateral mesh per unit area: one per (sqrt(3) / 2) h^2.
_VERTICES_PER_EDGE_SQUARED = 2.0 / math.sqrt(3.0)


def boundary_edge_m(mesh: TetMesh) -> float:
    """The volume's boundary resolution [m]: the median edge of its boundary faces that a
    free node moves (the faces on the fixed base are never touched)."""
    faces = boundary_faces(mesh.tets)
    free = ~np.isin(faces, mesh.fixed_nodes).all(axis=1)
    faces = faces[free] if np.any(free) else faces
    corners = mesh.nodes[faces]
    edges = corners - np.roll(corners, 1, axis=1)
    return float(np.median(np.sqrt((edges * edges).sum(axis=2))))


def movable_area_m2(mesh: TetMesh) -> float:
    """The area [m^2] of the volume's boundary faces that a free node moves."""
    faces = boundary_faces(mesh.tets)
    free = ~np.isin(faces, mesh.fixed_nodes).all(axis=1)
    corners = mesh.nodes[faces[free]]
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    return float(0.5 * np.linalg.norm(cross, axis=1).sum())


def collision_edge_range_m(mesh: TetMesh) -> tuple[float, float]:
    """The collision edge lengths [m] ``mesh`` accepts: (shortest, longest)."""
    longest = boundary_edge_m(mesh)
    area = movable_area_m2(mesh)
    shortest = math.sqrt(_VERTICES_PER_EDGE_SQUARED * area / MAX_COLLISION_VERTICES)
    return shortest, longest


def check_collision_edge(mesh: TetMesh, edge_m: float) -> None:
    """Refuse a collision edge length [m] outside :func:`collision_edge_range_m`, with the
    numbers and the valid range.

    Raises:
        ConfigError: not a positive length, coarser than the volume's boundary, or so fine
            the surface would exceed :data:`MAX_COLLISION_VERTICES`.
    """
    shortest, longest = collision_edge_range_m(mesh)
    valid = f"choose collision_edge_m in [{shortest:.5f}, {longest:.5f}] m for {mesh.name}"
    if edge_m > longest:
        raise ConfigError(
            f"collision_edge_m = {edge_m:g} m is coarser than the volume's boundary "
            f"(median edge {longest * 1e3:.2f} mm): a skin coarser than the tissue it covers "
            f"lets the volume's boundary nodes pass through the probe; {valid}, or None for "
            "the mesh's own surface"
        )
    if edge_m < shortest:
        vertices = _VERTICES_PER_EDGE_SQUARED * movable_area_m2(mesh) / edge_m**2
        raise ConfigError(
            f"collision_edge_m = {edge_m:g} m would give the skin about {vertices:,.0f} "
            f"vertices, more than {MAX_COLLISION_VERTICES:,} (every step interpolates and "
            f"searches them all); {valid}"
        )


def with_collision_edge(
    mesh: TetMesh,
    edge_m: float,
    remesh: Callable[[float], tuple[NDArray[np.float64], NDArray[np.int64]]] | None = None,
) -> TetMesh:
    """``mesh`` with a collision surface whose edges are about ``edge_m`` [m] long.

    Args:
        mesh: the volume (with its own collision surface, or none: then its boundary).
        edge_m: the edge length [m] (:func:`check_collision_edge`).
        remesh: builds the surface at an edge length, where the geometry is known exactly
            (the phantom); None refines the mesh's own surface by edge bisection.

    Raises:
        ConfigError: an edge length outside the valid range.
        MeshError: the surface cannot be embedded in the volume (:func:`check_embedded`).
    """
    check_collision_edge(mesh, edge_m)
    if remesh is not None:
        vertices, triangles = remesh(edge_m)
    else:
        if mesh.collision_surface is not None:
            vertices = mesh.collision_surface.rest_vertices
            triangles = mesh.collision_surface.triangles
        else:
            faces = boundary_faces(mesh.tets)
            used, triangles = np.unique(faces, return_inverse=True)
            vertices, triangles = mesh.nodes[used], triangles.reshape(-1, 3)
        vertices, triangles = refine_surface(vertices, triangles, edge_m)
    refined = mesh.with_collision_surface(vertices, triangles)
    check_embedded(refined)
    refined.metadata["collision_edge_m"] = float(edge_m)  # the copy's own dict
    return refined


def check_embedded(mesh: TetMesh) -> None:
    """Refuse a collision surface whose points lie outside the volume: farther outside their
    tet than :data:`EMBEDDING_OUTSIDE_FRACTION` of its longest edge.

    Raises:
        MeshError: naming the points that fall outside (the first few, with their
            positions) and how far.
    """
    surface = mesh.collision_surface
    if surface is None or surface.vertex_count == 0:
        return
    embedding = surface.embedding
    corners = mesh.nodes[embedding.tet_nodes]  # (p, 4, 3)
    volume = np.abs(
        np.einsum(
            "pi,pi->p",
            corners[:, 1] - corners[:, 0],
            np.cross(corners[:, 2] - corners[:, 0], corners[:, 3] - corners[:, 0]),
        )
    )
    outside = np.zeros(surface.vertex_count)
    size = np.zeros(surface.vertex_count)
    for a in range(4):
        rest = [b for b in range(4) if b != a]
        area2 = np.linalg.norm(
            np.cross(
                corners[:, rest[1]] - corners[:, rest[0]],
                corners[:, rest[2]] - corners[:, rest[0]],
            ),
            axis=1,
        )
        height = volume / area2  # (6 V) / (2 A) = 3 V / A
        outside = np.maximum(outside, -embedding.weights[:, a] * height)
        for b in range(a + 1, 4):
            size = np.maximum(size, np.linalg.norm(corners[:, a] - corners[:, b], axis=1))
    far = np.flatnonzero(outside > EMBEDDING_OUTSIDE_FRACTION * size)
    if far.size:
        shown = ", ".join(
            f"{int(i)} at {np.round(surface.rest_vertices[i] * 1e3, 2).tolist()} mm "
            f"({outside[i] * 1e3:.1f} mm out)"
            for i in far[:5]
        )
        raise MeshError(
            f"{far.size} of the {surface.vertex_count} collision-surface points of "
            f"{mesh.name} fall outside its volume (farther than "
            f"{EMBEDDING_OUTSIDE_FRACTION:g} x their tet's size): {shown}. Check that the "
            "surface and the volume are the same body in the same units"
        )


def refine_surface(
    vertices: NDArray[np.float64], triangles: NDArray[np.int64], edge_m: float
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Split every edge longer than :data:`SPLIT_FRACTION` x ``edge_m`` [m] at its midpoint,
    conformingly, until none is, so that edges end up between 2/3 and 4/3 of ``edge_m``
    where they were longer (the median about ``edge_m``, as gmsh's size means). Each round
    a triangle with three long edges becomes four, with two three (the quadrilateral left
    cut along its shorter diagonal), with one two. Orientation is kept; new vertices lie on
    the old facets (flat refinement).

    Args:
        vertices: positions [m], shape (v, 3).
        triangles: vertex indices, shape (t, 3).
        edge_m: the edge length wanted [m], > 0.

    Returns:
        (vertices [m] (v', 3), triangles (t', 3)); the first v vertices are the old ones.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    triangles = np.asarray(triangles, dtype=np.int64)
    while True:
        local = np.stack(
            [triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]], axis=1
        )  # (t, 3, 2): edge k runs from corner k to corner k + 1
        keys = np.sort(local.reshape(-1, 2), axis=1)
        unique, edge_of = np.unique(keys, axis=0, return_inverse=True)
        lengths = np.linalg.norm(vertices[unique[:, 0]] - vertices[unique[:, 1]], axis=1)
        long = lengths > SPLIT_FRACTION * edge_m
        if not np.any(long):
            return vertices, triangles
        midpoint = np.full(unique.shape[0], -1, dtype=np.int64)
        midpoint[long] = vertices.shape[0] + np.arange(int(long.sum()))
        vertices = np.vstack(
            [vertices, 0.5 * (vertices[unique[long, 0]] + vertices[unique[long, 1]])]
        )
        split = midpoint[edge_of.reshape(-1, 3)]  # (t, 3): -1 where the edge stays
        triangles = _split_triangles(vertices, triangles, split)


def _split_triangles(
    vertices: NDArray[np.float64], triangles: NDArray[np.int64], split: NDArray[np.int64]
) -> NDArray[np.int64]:
    """One round of :func:`refine_surface`: ``split[t, k]`` is the midpoint of triangle t's
    edge k (corner k to k + 1), or -1."""
    marked = split >= 0
    count = marked.sum(axis=1)
    # Rotate each triangle so that its split edges come first (one: edge 0; two: edges 0
    # and 1, the unsplit one last).
    shift = np.zeros(triangles.shape[0], dtype=np.int64)
    one = count == 1
    shift[one] = np.argmax(marked[one], axis=1)
    two = count == 2
    shift[two] = (np.argmin(marked[two], axis=1) + 1) % 3
    order = (shift[:, None] + np.arange(3)[None, :]) % 3
    rows = np.arange(triangles.shape[0])[:, None]
    t = triangles[rows, order]
    m = split[rows, order]
    a, b, c = t[:, 0], t[:, 1], t[:, 2]
    pieces = [np.stack([a, b, c], axis=1)[count == 0]]
    s1 = count == 1
    pieces += [
        np.stack([a[s1], m[s1, 0], c[s1]], axis=1),
        np.stack([m[s1, 0], b[s1], c[s1]], axis=1),
    ]
    s2 = count == 2
    mab, mbc = m[s2, 0], m[s2, 1]
    a2, b2, c2 = a[s2], b[s2], c[s2]
    pieces.append(np.stack([mab, b2, mbc], axis=1))
    # The quadrilateral a, mab, mbc, c: cut along its shorter diagonal.
    first = np.linalg.norm(vertices[a2] - vertices[mbc], axis=1) <= np.linalg.norm(
        vertices[mab] - vertices[c2], axis=1
    )
    pieces += [
        np.where(first[:, None], np.stack([a2, mab, mbc], 1), np.stack([a2, mab, c2], 1)),
        np.where(first[:, None], np.stack([a2, mbc, c2], 1), np.stack([mab, mbc, c2], 1)),
    ]
    s3 = count == 3
    mab, mbc, mca = m[s3, 0], m[s3, 1], m[s3, 2]
    pieces += [
        np.stack([a[s3], mab, mca], axis=1),
        np.stack([mab, b[s3], mbc], axis=1),
        np.stack([mca, mbc, c[s3]], axis=1),
        np.stack([mab, mbc, mca], axis=1),
    ]
    return np.ascontiguousarray(np.vstack(pieces), dtype=np.int64)
