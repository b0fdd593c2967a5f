"""Probe contact of the XPBD tissue: the contact points, their detection and projection.

:func:`choose_contact_points` chooses the points contact acts on (the free boundary nodes, points
embedded in the boundary faces between them, collision-surface vertices);
:func:`points_near` is a substep's broad phase; :func:`project_contacts` projects the
frictionless inequality constraints on the probe's tangent planes; and
:func:`contact_zone_sweeps` runs a substep's contacts and the extra sweeps of the tets around
them.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from tissue.contact.surface_points import SurfacePoints
from tissue.mesh import TetMesh, boundary_faces, triangle_grid
from tissue.pbd.sweep import project_tets


@nb.njit(cache=True)
def project_contacts(
    x: NDArray[np.float64],
    inv_mass: NDArray[np.float64],
    point_nodes: NDArray[np.int64],
    point_weights: NDArray[np.float64],
    points: NDArray[np.int64],
    normals: NDArray[np.float64],
    anchors: NDArray[np.float64],
    alpha: float,
    lam: NDArray[np.float64],
) -> None:
    """One Gauss-Seidel sweep of the contact inequalities n . (p - anchor) >= 0.

    Args:
        x: node positions [m], (node_count, 3), updated in place.
        inv_mass: inverse lumped masses [1/kg], (node_count,).
        point_nodes, point_weights: the contact surface's embedding, (point_count, 4).
        points: surface point index of each active contact, (contact_count,).
        normals: probe outward normal per contact, (contact_count, 3), unit.
        anchors: a point of the probe's tangent plane per contact [m], (contact_count, 3).
        alpha: time-scaled contact compliance alpha / h^2 [1/kg].
        lam: this substep's multipliers [kg m], (contact_count,), kept >= 0.
    """
    for k in range(points.shape[0]):
        p = points[k]
        gap = 0.0
        w_sum = 0.0
        for local in range(4):
            node = point_nodes[p, local]
            wt = point_weights[p, local]
            w_sum += wt * wt * inv_mass[node]
            for a in range(3):
                gap += wt * x[node, a] * normals[k, a]
        for a in range(3):
            gap -= anchors[k, a] * normals[k, a]
        denominator = w_sum + alpha
        if denominator <= 0.0:
            continue
        delta = (-gap - alpha * lam[k]) / denominator
        # Signorini: the multiplier only pushes (lambda >= 0); clamp the accumulated value.
        if lam[k] + delta < 0.0:
            delta = -lam[k]
        if delta == 0.0:
            continue
        lam[k] += delta
        for local in range(4):
            node = point_nodes[p, local]
            scale = inv_mass[node] * point_weights[p, local] * delta
            for a in range(3):
                x[node, a] += scale * normals[k, a]


@nb.njit(cache=True)
def contact_zone_sweeps(
    x: NDArray[np.float64],
    inv_mass: NDArray[np.float64],
    tets: NDArray[np.int64],
    dm_inv: NDArray[np.float64],
    alpha_dev: NDArray[np.float64],
    alpha_hyd: NDArray[np.float64],
    gamma: NDArray[np.float64],
    lam_dev: NDArray[np.float64],
    lam_hyd: NDArray[np.float64],
    support: NDArray[np.float64],
    point_nodes: NDArray[np.int64],
    point_weights: NDArray[np.float64],
    points: NDArray[np.int64],
    normals: NDArray[np.float64],
    anchors: NDArray[np.float64],
    alpha: float,
    lam: NDArray[np.float64],
    node_tet_start: NDArray[np.int64],
    node_tets: NDArray[np.int64],
    order: NDArray[np.int64],
    zone_iterations: int,
) -> None:
    """A substep's contacts after its last full sweep, then ``zone_iterations`` sweeps of the
    contact zone (:func:`contact_zone`, in ``order``) each followed by the contacts again.

    One compiled call (each call checks its arguments' types, a few microseconds). The
    arguments are :func:`~tissue.pbd.sweep.project_tets`' (``x`` .. ``support``), then
    :func:`project_contacts`' after its ``x`` and ``inv_mass`` (``point_nodes`` .. ``lam``),
    then :func:`contact_zone`'s.
    """
    project_contacts(x, inv_mass, point_nodes, point_weights, points, normals, anchors, alpha, lam)
    if zone_iterations == 0:
        return
    zone = contact_zone(point_nodes, point_weights, points, node_tet_start, node_tets, order)
    for _ in range(zone_iterations):
        project_tets(
            x, inv_mass, tets, dm_inv, alpha_dev, alpha_hyd, gamma, lam_dev, lam_hyd, support, zone
        )
        project_contacts(
            x, inv_mass, point_nodes, point_weights, points, normals, anchors, alpha, lam
        )


@nb.njit(cache=True)
def contact_zone(
    point_nodes: NDArray[np.int64],
    point_weights: NDArray[np.float64],
    points: NDArray[np.int64],
    node_tet_start: NDArray[np.int64],
    node_tets: NDArray[np.int64],
    order: NDArray[np.int64],
) -> NDArray[np.int64]:
    """The tets incident to a node that carries a contact point (weight != 0), in ``order``.

    Args:
        point_nodes, point_weights: the contact surface's embedding, (point_count, 4).
        points: surface point index of each active contact, (contact_count,).
        node_tet_start, node_tets: node -> incident tets in CSR form: node n's tets are
            ``node_tets[node_tet_start[n]:node_tet_start[n + 1]]``, (node_count + 1,) and
            (4 tet_count,).
        order: the sweep order of the tets, (tet_count,).

    Returns:
        the zone's tets (zone_count,), int64, in ``order``.
    """
    marked = np.zeros(order.shape[0], dtype=np.bool_)
    count = 0
    for k in range(points.shape[0]):
        p = points[k]
        for local in range(4):
            if point_weights[p, local] == 0.0:
                continue
            node = point_nodes[p, local]
            for j in range(node_tet_start[node], node_tet_start[node + 1]):
                t = node_tets[j]
                if not marked[t]:
                    marked[t] = True
                    count += 1
    zone = np.empty(count, dtype=np.int64)
    count = 0
    for t in order:
        if marked[t]:
            zone[count] = t
            count += 1
    return zone


@nb.njit(cache=True)
def points_near(
    x: NDArray[np.float64],
    point_nodes: NDArray[np.int64],
    point_weights: NDArray[np.float64],
    centre: NDArray[np.float64],
    reach: float,
    rotation: NDArray[np.float64],
    low: NDArray[np.float64],
    high: NDArray[np.float64],
    near: NDArray[np.int64],
    positions: NDArray[np.float64],
) -> int:
    """The contact points (``point_nodes`` and ``point_weights``, the embedding (point_count,
    4) each, of node positions ``x`` [m] (node_count, 3)) within ``reach`` [m] of ``centre``
    [m] (3,) and, in the frame of
    ``rotation`` (3, 3) about ``centre`` (local = (p - centre) R), inside the box from
    ``low`` to ``high`` [m] (3,) each: writes their indices to ``near`` and their positions
    [m] to ``positions`` (both sized for every point) and returns how many.

    One pass over the embedding, no array of all points' positions (this runs every
    substep). The sums are taken in the order numpy takes them (the four weighted nodes in
    turn, then the three squared components), so the points found and their positions are
    those of the whole-array version to the bit. The box (the probe's local bounds grown by
    the contact margin) keeps the exact SDF off points that cannot be near the probe."""
    count = 0
    reach2 = reach * reach
    for p in range(point_nodes.shape[0]):
        p0 = 0.0
        p1 = 0.0
        p2 = 0.0
        for local in range(4):
            node = point_nodes[p, local]
            wt = point_weights[p, local]
            p0 += wt * x[node, 0]
            p1 += wt * x[node, 1]
            p2 += wt * x[node, 2]
        d0 = p0 - centre[0]
        d1 = p1 - centre[1]
        d2 = p2 - centre[2]
        if d0 * d0 + d1 * d1 + d2 * d2 > reach2:
            continue
        inside = True
        for b in range(3):
            along = d0 * rotation[0, b] + d1 * rotation[1, b] + d2 * rotation[2, b]
            if along < low[b] or along > high[b]:
                inside = False
        if inside:
            near[count] = p
            positions[count, 0] = p0
            positions[count, 1] = p1
            positions[count, 2] = p2
            count += 1
    return count


def choose_contact_points(
    mesh: TetMesh, surface: SurfacePoints, spacing_m: float = 0.0, all_skin: bool = False
) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """The points the PBD contact acts on, as an embedding (nodes and weights, (k, 4) each).

    Every free boundary node of the volume (weight 1 on itself). With ``spacing_m`` > 0,
    points between them too, embedded in the boundary faces' nodes, so that no two are
    farther apart than that: a boundary edge of length L gets ceil(L / spacing) - 1 evenly
    spaced points, a face the interior points of its n-grid, n = ceil(longest edge /
    spacing) (none where the boundary is already that fine, or all its nodes are fixed).
    Then each collision-surface point farther than the median boundary edge from every
    boundary node, so a coarse volume under a fine collision surface still has no gaps the
    probe can sink through (``all_skin``: every collision-surface point).
    """
    faces = boundary_faces(mesh.tets)
    boundary = np.unique(faces)
    free = boundary[~np.isin(boundary, mesh.fixed_nodes)]
    nodes = [np.repeat(free[:, None], 4, axis=1)]
    weights = [np.zeros((free.size, 4))]
    weights[0][:, 0] = 1.0
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    if spacing_m > 0.0:
        fixed = np.zeros(mesh.node_count, dtype=bool)
        fixed[mesh.fixed_nodes] = True
        unique_edges = np.unique(np.sort(edges, axis=1), axis=0)
        unique_edges = unique_edges[~fixed[unique_edges].all(axis=1)]
        length = np.linalg.norm(
            mesh.nodes[unique_edges[:, 0]] - mesh.nodes[unique_edges[:, 1]], axis=1
        )
        segments = np.ceil(length / spacing_m).astype(np.int64)
        free_faces = faces[~fixed[faces].all(axis=1)]
        corners = mesh.nodes[free_faces]
        longest = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2).max(axis=1)
        grids = np.ceil(longest / spacing_m).astype(np.int64)
        for n in np.unique(segments[segments > 1]):
            chosen = unique_edges[segments == n]
            t = np.arange(1, n) / n
            pair = np.stack([1.0 - t, t], axis=1)  # (n - 1, 2)
            nodes.append(_pad_embedding(np.repeat(chosen, t.size, axis=0)))
            weights.append(_pad_weights(np.tile(pair, (len(chosen), 1))))
        for n in np.unique(grids[grids > 2]):
            chosen = free_faces[grids == n]
            grid = triangle_grid(int(n), interior=True)
            nodes.append(_pad_embedding(np.repeat(chosen, len(grid), axis=0)))
            weights.append(_pad_weights(np.tile(grid, (len(chosen), 1))))
    if mesh.collision_surface is not None:
        spacing = float(
            np.median(np.linalg.norm(mesh.nodes[edges[:, 0]] - mesh.nodes[edges[:, 1]], axis=1))
        )
        distance, _ = cKDTree(mesh.nodes[boundary]).query(surface.positions(mesh.nodes))
        extra = np.arange(distance.size) if all_skin else np.flatnonzero(distance > spacing)
        nodes.append(surface.embedding.tet_nodes[extra])
        weights.append(surface.embedding.weights[extra])
    return (
        np.ascontiguousarray(np.concatenate(nodes), dtype=np.int64),
        np.ascontiguousarray(np.concatenate(weights)),
    )


def _pad_embedding(nodes: NDArray[np.int64]) -> NDArray[np.int64]:
    """(k, m) node indices, m < 4, padded to (k, 4) by repeating the first node."""
    padded = np.repeat(nodes[:, :1], 4, axis=1)
    padded[:, : nodes.shape[1]] = nodes
    return padded


def _pad_weights(weights: NDArray[np.float64]) -> NDArray[np.float64]:
    """(k, m) weights, m < 4, padded with zeros to (k, 4)."""
    padded = np.zeros((weights.shape[0], 4))
    padded[:, : weights.shape[1]] = weights
    return padded
