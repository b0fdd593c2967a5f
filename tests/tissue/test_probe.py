"""The rigid probe: exact signed distances, surfaces, the published probe mesh, poses."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from tissue.errors import ConfigError, MeshError
from tissue.probe import (
    BoxProbe,
    CylinderProbe,
    LinearProbeFace,
    MeshProbe,
    Probe,
    ProbeShape,
    SphereProbe,
    load_probe_mesh,
    matrix_to_quat,
    parse_probe_spec,
    quat_to_matrix,
    unit_quat_to_matrix,
)

PUBLISHED_PROBE = (
    Path(__file__).resolve().parents[3] / "shared" / "paper-scene" / "us_probe_collision.stl"
)
PUBLISHED_POSES = PUBLISHED_PROBE.parent / "ground_truth"


def analytic_shapes() -> list[ProbeShape]:
    return [
        LinearProbeFace(),
        # A thick rounded slab, so the inner box is a solid (not a plate) and the
        # plan corners are rounder than the edges.
        LinearProbeFace(0.04, 0.01, 0.02, edge_radius_m=0.002, corner_radius_m=0.005),
        BoxProbe((0.03, 0.02, 0.01)),
        SphereProbe(0.01),
        CylinderProbe(0.008, 0.02),
    ]


def random_points(shape: ProbeShape, count: int, seed: int = 0) -> np.ndarray:
    r = shape.bounding_radius_m
    return np.random.default_rng(seed).uniform(-1.3 * r, 1.3 * r, (count, 3))


def finite_difference_gradient(shape: ProbeShape, points: np.ndarray, step: float = 1e-7):
    columns = []
    for axis in range(3):
        offset = np.zeros(3)
        offset[axis] = step
        plus, _ = shape.signed_distance(points + offset)
        minus, _ = shape.signed_distance(points - offset)
        columns.append((plus - minus) / (2.0 * step))
    return np.column_stack(columns)


# ----------------------------------------------------------------------------------------
# Analytic shapes against closed forms and brute force


def box_reference(points, half, centre):
    q = np.abs(points - centre) - half
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
    return np.where(np.all(q <= 0.0, axis=1), q.max(axis=1), outside)


def cylinder_reference(points, radius, height):
    rho = np.hypot(points[:, 0], points[:, 2])
    y = points[:, 1]
    radial_gap = rho - radius
    below, above = -height - y, y
    axial_gap = np.maximum(below, above)
    inside = (radial_gap <= 0) & (axial_gap <= 0)
    out_radial = np.maximum(radial_gap, 0.0)
    out_axial = np.maximum(axial_gap, 0.0)
    return np.where(inside, np.maximum(radial_gap, axial_gap), np.hypot(out_radial, out_axial))


def test_box_sphere_cylinder_match_closed_forms():
    box = BoxProbe((0.03, 0.02, 0.01))
    points = random_points(box, 4000)
    distance, _ = box.signed_distance(points)
    expected = box_reference(points, np.array([0.015, 0.01, 0.005]), np.array([0.0, -0.01, 0.0]))
    np.testing.assert_allclose(distance, expected, atol=1e-15)

    sphere = SphereProbe(0.01)
    points = random_points(sphere, 4000)
    distance, normal = sphere.signed_distance(points)
    centre = np.array([0.0, -0.01, 0.0])
    np.testing.assert_allclose(distance, np.linalg.norm(points - centre, axis=1) - 0.01)
    np.testing.assert_allclose(
        normal, (points - centre) / np.linalg.norm(points - centre, axis=1)[:, None]
    )

    cylinder = CylinderProbe(0.008, 0.02)
    points = random_points(cylinder, 4000)
    distance, _ = cylinder.signed_distance(points)
    np.testing.assert_allclose(distance, cylinder_reference(points, 0.008, 0.02), atol=1e-15)


def rounded_slab_brute_force(points, size, edge, corner, spacing=1e-4):
    """SDF of {dist(p, K) <= edge} with K the inner slab, by dense sampling of K's boundary.

    K is a rounded rectangle (half extents size/2 - edge, corner radius corner - edge)
    extruded over y in [-size_y + edge, -edge]. Inside K the distance to the rounded solid's
    surface is edge + dist(p, boundary of K); outside it is dist(p, K) - edge.
    """
    ax, az = size[0] / 2 - edge, size[2] / 2 - edge
    rc = corner - edge
    y_top, y_bottom = -edge, -size[1] + edge

    def inside_2d(x, z):
        corners_x, corners_z = np.abs(x) - (ax - rc), np.abs(z) - (az - rc)
        in_cross = ((corners_x <= 0) & (np.abs(z) <= az)) | ((corners_z <= 0) & (np.abs(x) <= ax))
        in_corner = np.hypot(np.maximum(corners_x, 0), np.maximum(corners_z, 0)) <= rc
        return in_cross | (in_corner & (np.abs(x) <= ax) & (np.abs(z) <= az))

    gx = np.arange(-ax, ax + spacing / 2, spacing)
    gz = np.arange(-az, az + spacing / 2, spacing)
    X, Z = np.meshgrid(gx, gz, indexing="ij")
    keep = inside_2d(X.ravel(), Z.ravel())
    plate = np.column_stack([X.ravel()[keep], Z.ravel()[keep]])
    # The rim of the 2D outline, sampled finely, then swept over the y range.
    t = np.linspace(0, 1, 4000)
    rim = []
    for sx, sz in ((1, 1), (-1, 1), (-1, -1), (1, -1)):
        angle = np.linspace(0, np.pi / 2, 200)
        rim.append(
            np.column_stack(
                [sx * (ax - rc + rc * np.cos(angle)), sz * (az - rc + rc * np.sin(angle))]
            )
        )
    rim.append(np.column_stack([(2 * t - 1) * (ax - rc), np.full_like(t, az)]))
    rim.append(np.column_stack([(2 * t - 1) * (ax - rc), np.full_like(t, -az)]))
    rim.append(np.column_stack([np.full_like(t, ax), (2 * t - 1) * (az - rc)]))
    rim.append(np.column_stack([np.full_like(t, -ax), (2 * t - 1) * (az - rc)]))
    rim = np.vstack(rim)
    samples = [
        np.column_stack([plate[:, 0], np.full(len(plate), y), plate[:, 1]])
        for y in {y_top, y_bottom}
    ]
    for y in np.arange(y_bottom, y_top + spacing / 2, spacing):
        samples.append(np.column_stack([rim[:, 0], np.full(len(rim), y), rim[:, 1]]))
    boundary = np.vstack(samples)
    gap, _ = cKDTree(boundary).query(points)
    inside = (
        inside_2d(points[:, 0], points[:, 2]) & (points[:, 1] <= y_top) & (points[:, 1] >= y_bottom)
    )
    return np.where(inside, -gap, gap) - edge


@pytest.mark.parametrize(
    "size, edge, corner",
    [
        ((0.0529, 0.0027, 0.0132), 0.00135, 0.0066),  # the default face
        ((0.04, 0.01, 0.02), 0.002, 0.005),
    ],
)
def test_rounded_slab_matches_brute_force(size, edge, corner):
    shape = LinearProbeFace(*size, edge_radius_m=edge, corner_radius_m=corner)
    points = random_points(shape, 1500, seed=1)
    distance, _ = shape.signed_distance(points)
    reference = rounded_slab_brute_force(points, size, edge, corner)
    # Sampling K's boundary every 0.1 mm overestimates distances to it by < 0.071 mm.
    np.testing.assert_allclose(distance, reference, atol=7.1e-5)
    clear = np.abs(reference) > 7.1e-5
    assert np.all(np.sign(distance[clear]) == np.sign(reference[clear]))


@pytest.mark.parametrize("shape", analytic_shapes(), ids=lambda s: s.name)
def test_normals_are_the_unit_gradient_and_project_onto_the_surface(shape):
    points = random_points(shape, 3000, seed=2)
    distance, normal = shape.signed_distance(points)
    np.testing.assert_allclose(np.linalg.norm(normal, axis=1), 1.0, atol=1e-12)
    gradient = finite_difference_gradient(shape, points)
    # Away from creases and the medial axis the SDF is smooth, |grad| = 1 there.
    smooth = np.abs(np.linalg.norm(gradient, axis=1) - 1.0) < 1e-6
    assert smooth.mean() > 0.9
    np.testing.assert_allclose(normal[smooth], gradient[smooth], atol=1e-5)
    # Stepping back along the normal by the distance lands on the surface.
    projected, _ = shape.signed_distance(points - distance[:, None] * normal)
    np.testing.assert_allclose(projected, 0.0, atol=1e-12)


def test_distance_hessian_of_a_sphere_is_its_curvature_seen_from_the_point():
    """For |p| - R the Hessian is (I - p p^T / |p|^2) / |p|: 1 / (R + d) across, 0 along n."""
    sphere = SphereProbe(0.01)
    rng = np.random.default_rng(3)
    directions = rng.normal(size=(200, 3))
    directions /= np.linalg.norm(directions, axis=1)[:, None]
    offset = directions * rng.uniform(0.0101, 0.013, 200)[:, None]  # from the centre
    points = offset - [0.0, 0.01, 0.0]  # the centre sits one radius behind the face (y = -R)
    length = np.linalg.norm(offset, axis=1)
    unit = offset / length[:, None]
    expected = (np.eye(3) - unit[:, :, None] * unit[:, None, :]) / length[:, None, None]
    np.testing.assert_allclose(sphere.distance_hessian(points), expected, atol=1e-4 / 0.01)


@pytest.mark.parametrize("shape", analytic_shapes(), ids=lambda s: s.name)
def test_distance_hessian_is_symmetric_flat_along_the_normal_and_convex(shape):
    """Near any analytic shape (all convex): symmetric, H n = 0, eigenvalues between 0 and
    the largest curvature 1 / (smallest radius + d); 0 in front of a flat face."""
    points = random_points(shape, 2000, seed=9)
    distance, normal = shape.signed_distance(points)
    near = (distance > 1e-4) & (distance < 3e-3)
    assert near.sum() > 20
    hessian = shape.distance_hessian(points[near])
    np.testing.assert_allclose(hessian, hessian.transpose(0, 2, 1), atol=1e-9)
    # [1/m]; curvatures here reach 1 / d = 1e4 (a box's sharp edge seen from 0.1 mm)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", hessian, normal[near]), 0.0, atol=1.0)
    eigenvalues = np.linalg.eigvalsh(hessian)
    assert eigenvalues.min() > -1.0
    # A convex shape's rim of radius r >= 0 seen from d curves by 1 / (r + d) <= 1 / d.
    assert np.all(eigenvalues.max(axis=1) <= 1.0 / distance[near] * (1 + 1e-3) + 1.0)
    assert eigenvalues.max() > 10.0  # and some points do see a curved rim
    in_front = shape.distance_hessian(np.array([[0.0, 2e-3, 0.0]]))
    if not isinstance(shape, SphereProbe):  # every other shape has a flat face there
        np.testing.assert_allclose(in_front, 0.0, atol=1e-3)


def test_distance_hessian_of_the_face_rim_is_one_over_edge_radius_plus_distance():
    """Beside the middle of the face's long side, level with the rounded edge's centre: the
    edge curves across (in the y-z plane) with radius r + d, and not along x."""
    face = LinearProbeFace(0.04, 0.01, 0.02, edge_radius_m=0.002, corner_radius_m=0.005)
    d = 1e-3
    # The long side at z = +w/2; the face edge's circle is centred at y = -r, z = w/2 - r.
    angle = 0.5  # from the side (z) towards the face (y), within the edge's quarter circle
    point = np.array(
        [[0.0, -0.002 + (0.002 + d) * math.sin(angle), 0.008 + (0.002 + d) * math.cos(angle)]]
    )
    distance, normal = face.signed_distance(point)
    assert distance[0] == pytest.approx(d, abs=1e-9)
    hessian = face.distance_hessian(point)[0]
    across = np.array([0.0, math.cos(angle), -math.sin(angle)])  # tangent of the edge's circle
    assert across @ hessian @ across == pytest.approx(1.0 / (0.002 + d), rel=1e-4)
    assert hessian[0, 0] == pytest.approx(0.0, abs=1e-3)


def test_mesh_probe_has_no_curvature_to_give():
    box = trimesh.creation.box(extents=(0.03, 0.02, 0.01))
    probe = MeshProbe(box.vertices, box.faces)
    np.testing.assert_array_equal(probe.distance_hessian(np.ones((5, 3))), np.zeros((5, 3, 3)))


def test_distance_hessian_world_is_the_shape_hessian_carried_by_the_pose():
    face = LinearProbeFace()
    probe = Probe(face, [0.1, 0.0, 0.05], [0.3, 0.2, -0.9, 0.1])
    local = random_points(face, 300, seed=11)
    world = probe.to_world_frame(local)
    rotation = probe.rotation_world()
    expected = rotation @ face.distance_hessian(local) @ rotation.T
    np.testing.assert_allclose(probe.distance_hessian_world(world), expected, atol=1e-6)


@pytest.mark.parametrize("shape", analytic_shapes(), ids=lambda s: s.name)
def test_frame_convention_face_at_y0_body_behind(shape):
    distance, normal = shape.signed_distance(np.array([[0.0, 0.0, 0.0], [0.0, 1e-3, 0.0]]))
    assert abs(distance[0]) < 1e-15  # the probe origin is the centre of the contact face
    assert distance[1] == pytest.approx(1e-3)
    np.testing.assert_allclose(normal[1], [0.0, 1.0, 0.0], atol=1e-12)
    assert shape.signed_distance(np.array([[0.0, -1e-4, 0.0]]))[0][0] < 0.0


@pytest.mark.parametrize("shape", analytic_shapes(), ids=lambda s: s.name)
def test_surface_is_closed_outward_and_on_the_zero_level(shape):
    vertices, triangles = shape.surface()
    mesh = trimesh.Trimesh(vertices, triangles, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume > 0.0
    distance, _ = shape.signed_distance(vertices)
    np.testing.assert_allclose(distance, 0.0, atol=1e-12)
    assert vertices[:, 1].max() == pytest.approx(0.0, abs=1e-12)
    assert np.linalg.norm(vertices, axis=1).max() <= shape.bounding_radius_m + 1e-12


@pytest.mark.parametrize("shape", analytic_shapes(), ids=lambda s: s.name)
def test_local_bounds_hold_the_shape_and_are_tight(shape):
    """Every point inside the probe (SDF < 0) lies in its local box, and the box is no
    larger than the shape's extent plus its documented pad (a broad phase that missed a
    point would miss a contact; one far too large would be no broad phase)."""
    low, high = shape.local_bounds_m()
    points = random_points(shape, 200_000, seed=11)
    distance, _ = shape.signed_distance(points)
    inside = points[distance < 0.0]
    assert inside.shape[0] > 500
    assert np.all(inside >= low) and np.all(inside <= high)
    # The points projected onto the surface reach within two pads of every side of the box.
    surface = points - distance[:, None] * shape.signed_distance(points)[1]
    pad = 0.01 * shape.bounding_radius_m
    assert np.all(surface.min(axis=0) >= low) and np.all(surface.max(axis=0) <= high)
    assert np.all(surface.min(axis=0) - low <= 2 * pad)
    assert np.all(high - surface.max(axis=0) <= 2 * pad)


# ----------------------------------------------------------------------------------------
# Meshes


def box_mesh(size):
    mesh = trimesh.creation.box(extents=size)
    mesh.apply_translation([0.0, -size[1] / 2, 0.0])
    return mesh


def test_mesh_probe_agrees_with_box_probe():
    size = (0.03, 0.02, 0.01)
    mesh_probe = MeshProbe(box_mesh(size).vertices, box_mesh(size).faces)
    box = BoxProbe(size)
    points = random_points(box, 5000, seed=3)
    d_mesh, n_mesh = mesh_probe.signed_distance(points)
    d_box, n_box = box.signed_distance(points)
    np.testing.assert_allclose(d_mesh, d_box, atol=1e-13)
    # Normals are unique except on the inner medial planes, where two walls tie.
    walls = np.sort(np.abs(np.abs(points - [0.0, -0.01, 0.0]) - [0.015, 0.01, 0.005]), axis=1)
    unique = (d_box > 0) | (walls[:, 1] - walls[:, 0] > 1e-9)
    np.testing.assert_allclose(n_mesh[unique], n_box[unique], atol=1e-9)
    # An inside-out copy is flipped, not trusted.
    flipped = MeshProbe(box_mesh(size).vertices, box_mesh(size).faces[:, ::-1])
    np.testing.assert_allclose(flipped.signed_distance(points)[0], d_box, atol=1e-13)


def test_mesh_probe_signs_a_non_convex_mesh():
    # A torus (axis z) has holes and saddles: the sign cannot come from convexity.
    major, minor = 0.02, 0.006
    torus = trimesh.creation.torus(major, minor, major_sections=64, minor_sections=32)
    probe = MeshProbe(torus.vertices, torus.faces)
    points = np.random.default_rng(8).uniform(-0.03, 0.03, (4000, 3)) * [1.0, 1.0, 0.4]
    exact = np.hypot(np.hypot(points[:, 0], points[:, 1]) - major, points[:, 2]) - minor
    distance, normal = probe.signed_distance(points)
    # The 64 x 32 facets sit inside the true torus by at most ~0.2 mm (chord sag).
    np.testing.assert_allclose(distance, exact, atol=2.5e-4)
    clear = np.abs(exact) > 2.5e-4
    assert np.all(np.sign(distance[clear]) == np.sign(exact[clear]))
    np.testing.assert_allclose(np.linalg.norm(normal, axis=1), 1.0, atol=1e-12)


def test_open_mesh_is_rejected_with_a_clear_message(tmp_path):
    mesh = box_mesh((0.03, 0.02, 0.01))
    with pytest.raises(MeshError, match="not closed.*watertight"):
        MeshProbe(mesh.vertices, mesh.faces[:-1])
    open_file = tmp_path / "open.stl"
    trimesh.Trimesh(mesh.vertices, mesh.faces[:-1]).export(open_file)
    with pytest.raises(MeshError, match="not closed"):
        parse_probe_spec(str(open_file))


def test_millimetre_mesh_needs_a_scale(tmp_path):
    file = tmp_path / "mm.stl"
    box_mesh((30.0, 20.0, 10.0)).export(file)
    with pytest.raises(MeshError, match="scale=0.001"):
        load_probe_mesh(file)
    probe = load_probe_mesh(file, scale=0.001)
    np.testing.assert_allclose(np.ptp(probe.vertices, axis=0), [0.03, 0.02, 0.01])


@pytest.fixture
def published_probe() -> MeshProbe:
    if not PUBLISHED_PROBE.is_file():
        pytest.skip(f"the published probe mesh is not present at {PUBLISHED_PROBE} (test data)")
    return load_probe_mesh(PUBLISHED_PROBE)


def test_published_probe_loads_and_matches_the_face(published_probe):
    assert published_probe.triangle_count == 70
    extents_mm = np.ptp(published_probe.vertices, axis=0) * 1e3
    np.testing.assert_allclose(extents_mm, [52.9, 2.7, 13.2], atol=0.2)
    face = LinearProbeFace()
    np.testing.assert_allclose(np.ptp(face.surface()[0], axis=0) * 1e3, extents_mm, atol=0.2)

    rng = np.random.default_rng(4)
    # In front of the face, over and around its footprint: both outside.
    front = rng.uniform([-0.03, 2e-4, -0.009], [0.03, 0.004, 0.009], (3000, 3))
    # Inside the body, away from the tapered rim: both inside.
    body = rng.uniform([-0.02, -0.0024, -0.004], [0.02, -0.0003, 0.004], (3000, 3))
    for points, sign in ((front, 1.0), (body, -1.0)):
        assert np.all(np.sign(published_probe.signed_distance(points)[0]) == sign)
        assert np.all(np.sign(face.signed_distance(points)[0]) == sign)
    # Near the whole probe the two differ by the STL's taper (its sides lean in towards
    # the face, ours are round): about 1.3 mm at most, so signs differ only in that band.
    near = rng.uniform([-0.03, -0.004, -0.009], [0.03, 0.004, 0.009], (5000, 3))
    d_mesh, n_mesh = published_probe.signed_distance(near)
    d_face, n_face = face.signed_distance(near)
    assert np.abs(d_mesh - d_face).max() < 1.4e-3
    disagree = np.sign(d_mesh) != np.sign(d_face)
    assert np.all(np.abs(d_face[disagree]) < 1.4e-3)
    # Above the middle of the face both push straight out along +y.
    over = (near[:, 1] > 5e-4) & (np.abs(near[:, 0]) < 0.015) & (np.abs(near[:, 2]) < 0.003)
    assert np.all(n_mesh[over, 1] > 0.999) and np.all(n_face[over, 1] > 0.999)


# ----------------------------------------------------------------------------------------
# Rotations and poses


def random_rotations(count, seed=5):
    quats = np.random.default_rng(seed).normal(size=(count, 4))
    # Half-turns exercise every branch of the matrix -> quaternion conversion.
    quats[:4] = [[0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1], [1e-9, 0.6, 0.8, 0]]
    return quats / np.linalg.norm(quats, axis=1)[:, None]


def test_quaternion_matrix_round_trip():
    for quat in random_rotations(50):
        rotation = quat_to_matrix(quat)
        np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-14)
        assert np.linalg.det(rotation) == pytest.approx(1.0)
        back = matrix_to_quat(rotation)
        assert back[0] >= 0.0
        np.testing.assert_allclose(back, quat if quat[0] >= 0 else -quat, atol=1e-12)
    # MuJoCo's (w, x, y, z): a quarter turn about z takes x to y.
    quarter = quat_to_matrix([math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)])
    np.testing.assert_allclose(quarter @ [1, 0, 0], [0, 1, 0], atol=1e-15)


def test_a_batch_of_quaternions_gives_each_ones_matrix_to_the_bit():
    """PBD turns a step's 60 substep poses into matrices at once; each must be the matrix
    one quaternion at a time gives (the trajectories depend on it to the bit)."""
    quats = np.array(random_rotations(50))
    batch = unit_quat_to_matrix(quats)
    assert batch.shape == (50, 3, 3)
    for quat, matrix in zip(quats, batch, strict=True):
        np.testing.assert_array_equal(matrix, unit_quat_to_matrix(quat))
        np.testing.assert_allclose(matrix, quat_to_matrix(quat), atol=1e-15)


def test_bad_rotations_and_quaternions_are_rejected():
    with pytest.raises(ConfigError, match="zero"):
        Probe(SphereProbe(0.01), np.zeros(3), np.zeros(4))
    with pytest.raises(ConfigError, match="proper rotation"):
        matrix_to_quat(np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(ConfigError, match="last row"):
        Probe.pose_from_matrix(np.ones((4, 4)))


def test_probe_normalises_and_maps_between_frames():
    probe = Probe(SphereProbe(0.01), [0.1, -0.2, 0.3], [2.0, 0.4, -0.6, 1.0])
    assert np.linalg.norm(probe.quat_wxyz) == pytest.approx(1.0)
    points = np.random.default_rng(6).normal(size=(100, 3))
    np.testing.assert_allclose(probe.to_world_frame(probe.to_probe_frame(points)), points)
    np.testing.assert_allclose(probe.to_world_frame(np.zeros((1, 3)))[0], [0.1, -0.2, 0.3])
    np.testing.assert_allclose(probe.pressing_direction_world(), probe.rotation_world()[:, 1])
    position, quat = Probe.pose_from_matrix(probe.pose_matrix())
    np.testing.assert_allclose(position, probe.position_world)
    np.testing.assert_allclose(quat, probe.quat_wxyz * np.sign(probe.quat_wxyz[0]), atol=1e-12)


def test_signed_distance_world_is_the_shape_sdf_carried_by_the_pose():
    sphere = SphereProbe(0.01)
    probe = Probe(sphere, [0.1, 0.0, 0.05], [0.3, 0.2, -0.9, 0.1])
    points = np.random.default_rng(7).normal(0.0, 0.02, (500, 3)) + probe.position_world
    distance, normal = probe.signed_distance_world(points)
    centre = probe.to_world_frame([[0.0, -0.01, 0.0]])[0]
    np.testing.assert_allclose(distance, np.linalg.norm(points - centre, axis=1) - 0.01)
    np.testing.assert_allclose(
        normal, (points - centre) / np.linalg.norm(points - centre, axis=1)[:, None]
    )
    vertices, _ = probe.surface_world()
    np.testing.assert_allclose(probe.signed_distance_world(vertices)[0], 0.0, atol=1e-12)


def test_wrench_about_origin():
    probe = Probe(BoxProbe((0.05, 0.01, 0.01)), [1.0, 2.0, 3.0])
    points = np.array([[1.1, 2.0, 3.0], [0.9, 2.0, 3.0]])
    force, torque = probe.wrench_about_origin(points, [[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]])
    np.testing.assert_allclose(force, 0.0, atol=1e-15)
    np.testing.assert_allclose(torque, [0.0, 0.0, 0.2], atol=1e-12)  # a pure couple
    force, torque = probe.wrench_about_origin(points[:1], [[0.0, 0.0, 2.0]])
    np.testing.assert_allclose(force, [0.0, 0.0, 2.0])
    np.testing.assert_allclose(torque, [0.0, -0.2, 0.0], atol=1e-12)  # r x f = x x z = -y
    # Many points: the sum of (p - c) x f, bit for bit as np.cross gives it.
    rng = np.random.default_rng(3)
    points, forces = rng.normal(size=(50, 3)), rng.normal(size=(50, 3))
    force, torque = probe.wrench_about_origin(points, forces)
    np.testing.assert_array_equal(force, forces.sum(axis=0))
    np.testing.assert_array_equal(torque, np.cross(points - probe.position_world, forces).sum(0))


def test_looking_along_places_the_face_and_presses_along_the_direction():
    for direction in ([0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.3, -0.5, 0.8]):
        probe = Probe.looking_along(LinearProbeFace(), [0.1, 0.2, 0.3], direction)
        unit = np.asarray(direction) / np.linalg.norm(direction)
        np.testing.assert_allclose(probe.pressing_direction_world(), unit, atol=1e-12)
        np.testing.assert_allclose(probe.position_world, [0.1, 0.2, 0.3])
        # The body lies behind the contact point, against the pressing direction.
        vertices, _ = probe.surface_world()
        assert np.max((vertices - probe.position_world) @ unit) < 1e-12
    down = Probe.looking_along(LinearProbeFace(), np.zeros(3), [0.0, 0.0, -1.0])
    np.testing.assert_allclose(down.rotation_world()[:, 0], [1.0, 0.0, 0.0], atol=1e-12)
    rolled = Probe.looking_along(LinearProbeFace(), np.zeros(3), [0.0, 0.0, -1.0], math.pi / 2)
    np.testing.assert_allclose(rolled.pressing_direction_world(), [0.0, 0.0, -1.0], atol=1e-12)
    # A quarter roll about the pressing axis (-z) takes the long axis from +x to -y.
    np.testing.assert_allclose(rolled.rotation_world()[:, 0], [0.0, -1.0, 0.0], atol=1e-12)
    with pytest.raises(ConfigError, match="non-zero"):
        Probe.looking_along(LinearProbeFace(), np.zeros(3), np.zeros(3))


def test_published_poses_load():
    if not PUBLISHED_POSES.is_dir():
        pytest.skip(f"the published poses are not present at {PUBLISHED_POSES} (test data)")
    for file in sorted(PUBLISHED_POSES.glob("tumor*/Transform*.txt")):
        transform = np.loadtxt(file)
        position, quat = Probe.pose_from_matrix(transform)
        probe = Probe(LinearProbeFace(), position, quat)
        # The files carry ~1e-5 of round-off; the pose keeps the nearest rotation.
        np.testing.assert_allclose(probe.pose_matrix(), transform, atol=1e-4)


# ----------------------------------------------------------------------------------------
# Specs


def test_valid_specs(tmp_path):
    assert isinstance(parse_probe_spec("face"), LinearProbeFace)
    sphere = parse_probe_spec(" Sphere:0.01 ")
    assert isinstance(sphere, SphereProbe) and sphere.radius_m == 0.01
    box = parse_probe_spec("box:0.05,0.02,0.01")
    assert isinstance(box, BoxProbe) and box.size_m == (0.05, 0.02, 0.01)
    cylinder = parse_probe_spec("cylinder:0.005, 0.02")
    assert isinstance(cylinder, CylinderProbe)
    assert (cylinder.radius_m, cylinder.height_m) == (0.005, 0.02)
    file = tmp_path / "box.stl"
    box_mesh((0.03, 0.02, 0.01)).export(file)
    assert isinstance(parse_probe_spec(str(file)), MeshProbe)


@pytest.mark.parametrize(
    "spec",
    [
        "cube:0.01",
        "sphere:0",
        "sphere:-0.01",
        "sphere:",
        "sphere:0.01,0.02",
        "sphere:nan",
        "sphere:10",  # millimetres by mistake
        "box:0.01,0.02",
        "box:0.01,0,0.02",
        "cylinder:abc,0.1",
        "face:0.05",
        "missing_probe.stl",
        "",
    ],
)
def test_invalid_specs_name_the_spec_and_list_the_forms(spec):
    with pytest.raises(ConfigError) as error:
        parse_probe_spec(spec)
    message = str(error.value)
    assert repr(spec) in message
    for form in ("face", "sphere:RADIUS", "box:LX,LY,LZ", "cylinder:RADIUS,HEIGHT", "PATH"):
        assert form in message


def test_near_holds_every_point_inside_or_within_the_margin():
    """Probe.near (the bounding-sphere filter of the per-step checks) keeps every point whose
    signed distance is below the margin, and drops points far outside the sphere."""
    probe = Probe.looking_along(LinearProbeFace(), [0.01, 0.02, 0.03], [0.3, -0.5, 0.8])
    rng = np.random.default_rng(11)
    points = probe.position_world + rng.uniform(-0.06, 0.06, size=(4000, 3))
    distance, _ = probe.signed_distance_world(points)
    for margin in (0.0, 0.002):
        near = probe.near(points, margin)
        assert np.all(near[distance < margin])
        assert 0 < np.count_nonzero(near) < points.shape[0]
    far = probe.position_world + [0.0, 0.0, 2.0 * probe.shape.bounding_radius_m]
    assert not probe.near(far[None, :])[0]
