"""Tissue variants for domain randomisation: lesions moved at rest without remeshing
(:mod:`tissue.mesh.lesion_shift`) and :meth:`tissue.Tissue.varied`."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

import tissue
from tissue.errors import MeshError
from tissue.mesh import boundary_faces
from tissue.mesh.lesion_shift import MIN_VOLUME_RATIO, lesion_shift_limits, shift_lesions
from tissue.mesh.phantom import breast_phantom

MESH = 1363


@pytest.fixture(scope="module")
def mesh():
    return breast_phantom(MESH)


def _press(model: tissue.Tissue, lesion: int, depth_m: float = 0.006) -> tissue.TissueStep:
    """A 6 mm press over lesion ``lesion``'s nominal place, 0.2 mm a step."""
    position, quat = model.touching_pose(model.lesions[lesion].rest_centre_m)
    direction = tissue.pressing_direction(quat)
    model.reset(position, quat)
    steps = round(depth_m / 0.0002)
    for k in range(1, steps + 1):
        result = model.step(position + 0.0002 * k * direction, quat)
    return result


def test_a_shifted_lesion_moves_exactly_and_nothing_else_does(mesh) -> None:
    limits = lesion_shift_limits(mesh)
    offsets = np.zeros((mesh.lesion_count, 3))
    offsets[0] = 0.8 * limits[0] * np.array([0.6, 0.0, 0.8])
    moved = shift_lesions(mesh, offsets)
    assert moved.node_count == mesh.node_count
    assert np.array_equal(moved.tets, mesh.tets) and np.array_equal(moved.region, mesh.region)
    before = tissue.make_tissue(mesh=mesh).lesions
    after = tissue.make_tissue(mesh=moved).lesions
    np.testing.assert_allclose(
        after[0].rest_centre_m - before[0].rest_centre_m, offsets[0], atol=1e-12
    )
    for k in range(1, len(before)):
        np.testing.assert_array_equal(after[k].rest_centre_m, before[k].rest_centre_m)
    # The skin, the chest wall and every other lesion's nodes stay where they were.
    boundary = np.unique(boundary_faces(mesh.tets))
    np.testing.assert_array_equal(moved.nodes[boundary], mesh.nodes[boundary])
    np.testing.assert_array_equal(
        moved.collision_surface.rest_vertices, mesh.collision_surface.rest_vertices
    )
    ratio = moved.tet_volumes() / mesh.tet_volumes()
    assert ratio.min() >= MIN_VOLUME_RATIO
    # The tracked point moved with the material around it.
    shift = moved.landmarks.rest_positions[0] - mesh.landmarks.rest_positions[0]
    assert np.linalg.norm(shift) > 0.5 * np.linalg.norm(offsets[0])
    np.testing.assert_array_equal(moved.metadata["lesion_offsets_m"], offsets)


def test_an_offset_beyond_the_lesion_room_is_refused_with_the_limit(mesh) -> None:
    limits = lesion_shift_limits(mesh)
    assert np.all(limits > 0.0) and np.all(limits < 0.01)
    offsets = np.zeros((mesh.lesion_count, 3))
    offsets[1, 2] = 3.0 * limits[1] + 0.002  # far beyond: a tet would be squeezed
    with pytest.raises(MeshError, match=r"lesion_2: .* mm asked, .* mm allowed"):
        shift_lesions(mesh, offsets)
    with pytest.raises(MeshError, match="one per lesion"):
        shift_lesions(mesh, np.zeros((2, 3)))


def test_a_stiffer_variant_pushes_back_harder_and_the_nominal_is_untouched() -> None:
    nominal = tissue.make_tissue(mesh=MESH, contact="lm")
    first = _press(nominal, 0)
    base = nominal.resolved.materials
    stiffer = replace(base, tissue=replace(base.tissue, young_pa=1.5 * base.tissue.young_pa))
    variant = nominal.varied(materials=stiffer)
    assert variant.resolved.materials.tissue.young_pa == pytest.approx(4275.0)
    ratio = np.linalg.norm(_press(variant, 0).force_world_n) / np.linalg.norm(first.force_world_n)
    # Neo-Hookean forces scale with the moduli at a given deformation (same geometry).
    assert ratio == pytest.approx(1.5, rel=0.02)
    again = _press(nominal, 0)
    np.testing.assert_array_equal(again.force_world_n, first.force_world_n)


def test_a_variant_with_a_moved_lesion_carries_it_and_rejects_what_does_not_fit() -> None:
    nominal = tissue.make_tissue(mesh=MESH, contact="penalty")
    limits = nominal.lesion_shift_limits_m()
    offsets = np.zeros((len(nominal.lesions), 3))
    offsets[0, 0] = 0.9 * limits[0]
    variant = nominal.varied(lesion_offsets_m=offsets)
    np.testing.assert_allclose(
        variant.lesions[0].rest_centre_m - nominal.lesions[0].rest_centre_m, offsets[0], atol=1e-12
    )
    assert _press(variant, 0).ok
    offsets[0, 0] = 0.05
    with pytest.raises(tissue.TissueInputError, match="allowed"):
        nominal.varied(lesion_offsets_m=offsets)
    with pytest.raises(tissue.TissueInputError, match="TissueMaterials"):
        nominal.varied(materials="soft")  # type: ignore[arg-type]


def test_pbd_variants_keep_the_calibration(monkeypatch) -> None:
    nominal = tissue.make_tissue(mesh=MESH, contact="pbd")
    import tissue.pbd.calibration as calibration

    def refuse(*args, **kwargs):
        raise AssertionError("a variant must not calibrate PBD again")

    monkeypatch.setattr(calibration, "fit_force_scale", refuse)
    base = nominal.resolved.materials
    variant = nominal.varied(materials=replace(base, lesion_stiffness_ratio=6.0))
    assert variant.resolved.config == nominal.resolved.config
    assert variant.resolved.materials.lesion_stiffness_ratio == 6.0
