"""What a lesion is in the mesh: a volume-keeping regular polyhedron or an inflated sphere.

Ten conforming spheres need at least about 3k tets, so the coarse levels mesh each lesion as
a regular polyhedron (:func:`lesion_polyhedron`) with the sphere's centre and exactly its
volume, one vertex straight up over the tracked point. Finer levels mesh a sphere; a meshed
sphere is an inscribed polyhedron holding as little as 65 % of the volume at 2 radii per
edge, so gmsh gets a sphere inflated by :func:`volume_keeping_radius` (at most 25 % in
radius) and :func:`match_lesion_volumes` scales the lesion's nodes by the last few % so that
its tets hold exactly the sphere's volume. Lengths are metres.
"""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from tissue.mesh import signed_tet_volumes
from tissue.mesh.phantom.gmsh_backend import RawMesh, extract_surface_mesh, gmsh_session

# A spherical lesion's mesh size relative to its radius when the global size is coarser:
# about 30 tets per lesion, the fewest that still look round.
SPHERE_SIZE_PER_RADIUS = 2.0
# A coarse sphere is inflated by at most this factor in radius to keep its volume.
LARGEST_INFLATION = 1.25


def lesion_polyhedron(
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


def add_convex_polyhedron(occ: Any, vertices: NDArray[np.float64]) -> int:
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


# A lesion's volume correction is skipped if it would leave a neighbouring tet with less
# than this fraction of its volume.
SMALLEST_KEPT_VOLUME_FRACTION = 0.5


def match_lesion_volumes(
    raw: RawMesh, centres: NDArray[np.float64], radii: NDArray[np.float64]
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
        if np.all(after > SMALLEST_KEPT_VOLUME_FRACTION * before):
            raw.nodes[:] = moved


def volume_keeping_radius(radius: float, size: float, verbose: bool = False) -> float:
    """The radius [m] to give gmsh so that a sphere meshed at ``size`` [m] (capped at
    ``SPHERE_SIZE_PER_RADIUS`` radii) encloses the volume of a sphere of ``radius`` [m].

    A meshed sphere is an inscribed polyhedron: at two radii per edge it holds about 65 %
    of the sphere's volume, which would soften a coarse mesh's lesion. The polyhedron's
    volume ratio depends only on size / radius, so it is measured once on a unit sphere.
    """
    meshed = radius
    for _ in range(3):  # a fixed point: the ratio changes little with the inflation
        relative = min(size / meshed, SPHERE_SIZE_PER_RADIUS)
        ratio = meshed_unit_sphere_volume_ratio(round(relative, 6), verbose)
        meshed = radius * min(ratio ** (-1 / 3), LARGEST_INFLATION)
    return meshed


@functools.lru_cache(maxsize=256)
def meshed_unit_sphere_volume_ratio(relative_size: float, verbose: bool) -> float:
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
