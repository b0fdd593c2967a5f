"""Meshing the phantom with gmsh: the volume with its conforming lesions, and the collision
surface.

The dome is built in gmsh's OCC kernel and fragmented with the lesions, so each lesion is a
conforming sub-volume (region k; region 0 is the tissue). The collision surface is a separate
2D mesh of the whole closed boundary (dome and base), calibrated to
``PhantomSpec.collision_triangle_target`` triangles and wound outwards. Lengths are metres.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from tissue.errors import MeshError
from tissue.mesh.phantom.calibration import calibrate_size
from tissue.mesh.phantom.gmsh_backend import (
    RawMesh,
    extract_surface_mesh,
    extract_volume_mesh,
    gmsh_session,
)
from tissue.mesh.phantom.lesion_shapes import (
    SPHERE_SIZE_PER_RADIUS,
    add_convex_polyhedron,
    lesion_polyhedron,
    match_lesion_volumes,
    volume_keeping_radius,
)
from tissue.mesh.phantom.spec import PhantomSpec

# Collision-surface characteristic length [m] calibrated for the default PhantomSpec and
# 1,000 triangles with this gmsh version; other specs and targets start from it and iterate.
CALIBRATED_COLLISION_SIZE_M = 0.0095


def add_dome(occ: Any, spec: PhantomSpec) -> int:
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


def mesh_phantom_volume(spec: PhantomSpec, shape: str, size: float, verbose: bool) -> RawMesh:
    centres = spec.lesion_centres_m()
    radii = spec.lesion_radii_m()
    meshed_radii = radii
    if shape == "sphere":
        meshed_radii = np.array([volume_keeping_radius(r, size, verbose) for r in radii])
    with gmsh_session(verbose) as gmsh:
        occ = gmsh.model.occ
        dome = add_dome(occ, spec)
        lesion_tags = []
        edge_lengths = []
        for centre, radius, meshed in zip(centres, radii, meshed_radii, strict=True):
            if shape == "sphere":
                lesion_tags.append(occ.addSphere(*centre, meshed))
            else:
                vertices = lesion_polyhedron(centre, radius, shape)
                edge_lengths.append(
                    float(np.min(np.linalg.norm(vertices[1:] - vertices[0], axis=1)))
                )
                lesion_tags.append(add_convex_polyhedron(occ, vertices))
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
                lesion_size = min(size, SPHERE_SIZE_PER_RADIUS * meshed_radii[k - 1])
            else:
                # Do not split the polyhedron's edges: it stays a handful of tets.
                lesion_size = 1.001 * edge_lengths[k - 1] * math.sqrt(2.0)
            gmsh.model.mesh.setSize(points, lesion_size)
        gmsh.model.mesh.generate(3)
        region_of_volume = {volume: k for k, volume in volume_of_region.items()}
        raw = extract_volume_mesh(gmsh, region_of_volume)
    if shape == "sphere":
        match_lesion_volumes(raw, centres, radii)
    return raw


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
    initial = CALIBRATED_COLLISION_SIZE_M * (spec.volume_m3 / PhantomSpec().volume_m3) ** (1 / 3)
    initial *= math.sqrt(1000 / target)

    def mesh_at(size: float) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        with gmsh_session(verbose) as gmsh:
            add_dome(gmsh.model.occ, spec)
            gmsh.model.occ.synchronize()
            gmsh.option.setNumber("Mesh.MeshSizeMax", size)
            gmsh.model.mesh.generate(2)
            return extract_surface_mesh(gmsh)

    (vertices, triangles), _, _ = calibrate_size(
        mesh_at, lambda r: r[1].shape[0], target, initial, "the collision surface", dimension=2
    )
    return vertices, orient_outward(spec, vertices, triangles)


#: The phantom's base, which the probe never reaches, is meshed this coarse [m] under a
#: finer skin (:func:`phantom_skin_at`), grading from the skin's edge at the rim over
#: :data:`_BASE_GRADING_M`.
_BASE_EDGE_M = CALIBRATED_COLLISION_SIZE_M
_BASE_GRADING_M = 0.02


def phantom_skin_at(
    spec: PhantomSpec, edge_m: float, verbose: bool = False
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """The phantom's closed outer surface meshed by gmsh with its dome's edges about
    ``edge_m`` [m] long (a collision surface at the probe's scale; see
    :mod:`tissue.mesh.skin`). The base, never touched, keeps the coarse size of the
    default surface away from the rim.

    Returns:
        vertices [m], shape (vertex_count, 3), and triangles, shape (triangle_count, 3),
        counter-clockwise seen from outside.
    """
    edge_m = float(edge_m)
    coarse = max(edge_m, _BASE_EDGE_M)
    with gmsh_session(verbose) as gmsh:
        add_dome(gmsh.model.occ, spec)
        gmsh.model.occ.synchronize()
        surfaces = [tag for _, tag in gmsh.model.getEntities(2)]
        base = [tag for tag in surfaces if gmsh.model.getType(2, tag) == "Plane"]
        dome = [tag for tag in surfaces if tag not in base]
        rim = [tag for _, tag in gmsh.model.getBoundary([(2, t) for t in base], oriented=False)]
        field = gmsh.model.mesh.field
        on_dome = field.add("Constant")
        field.setNumber(on_dome, "VIn", edge_m)
        field.setNumber(on_dome, "VOut", coarse)
        field.setNumbers(on_dome, "SurfacesList", dome)
        field.setNumbers(on_dome, "CurvesList", rim)
        from_rim = field.add("Distance")
        field.setNumbers(from_rim, "CurvesList", rim)
        graded = field.add("Threshold")
        field.setNumber(graded, "InField", from_rim)
        field.setNumber(graded, "SizeMin", edge_m)
        field.setNumber(graded, "SizeMax", coarse)
        field.setNumber(graded, "DistMin", 0.0)
        field.setNumber(graded, "DistMax", _BASE_GRADING_M)
        smallest = field.add("Min")
        field.setNumbers(smallest, "FieldsList", [on_dome, graded])
        field.setAsBackgroundMesh(smallest)
        gmsh.option.setNumber("Mesh.MeshSizeMax", coarse)
        gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
        gmsh.model.mesh.generate(2)
        vertices, triangles = extract_surface_mesh(gmsh)
    return vertices, orient_outward(spec, vertices, triangles)


def orient_outward(
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
