"""``Tissue.rest_skin_normal``: where a ray leaves the rest skin and the skin's normal there."""

from __future__ import annotations

import numpy as np
import pytest

import tissue
from tissue.mesh.phantom import PhantomSpec


@pytest.fixture(scope="module")
def model() -> tissue.Tissue:
    return tissue.make_tissue(mesh=1363, contact="penalty")


def test_vertical_rays_leave_the_skin_on_the_phantom_dome(model) -> None:
    spec = PhantomSpec()
    rng = np.random.default_rng(0)
    plan = rng.uniform(-0.03, 0.03, size=(25, 2))
    for x, y in plan:
        hit, normal = model.rest_skin_normal([x, y, 0.01])
        assert hit[:2] == pytest.approx([x, y], abs=1e-12)
        # The skin is a dome triangulated with its vertices on it: the hit lies just under
        # the analytic dome, by at most the triangles' chordal error.
        dome = float(spec.skin_height_m(x, y))
        assert dome - 1e-3 < hit[2] <= dome + 1e-9
        assert np.linalg.norm(normal) == pytest.approx(1.0)
        assert normal[2] < -0.5  # inward: down into the dome
    _, apex = model.rest_skin_normal([0.0, 0.0, 0.01])
    assert apex @ np.array([0.0, 0.0, -1.0]) > np.cos(np.radians(3.0))


def test_it_is_the_normal_the_probe_presses_along(model) -> None:
    for lesion in model.lesions[:4]:
        _, quat = model.touching_pose(lesion.rest_centre_m)
        _, normal = model.rest_skin_normal(lesion.rest_centre_m)
        np.testing.assert_allclose(tissue.pressing_direction(quat), normal, atol=1e-12)


def test_a_slanted_ray_hits_where_the_line_crosses_the_skin(model) -> None:
    origin = np.array([0.01, -0.005, 0.02])
    direction = np.array([0.3, 0.2, 1.0])
    hit, _ = model.rest_skin_normal(origin, direction)
    along = (hit - origin) / np.linalg.norm(hit - origin)
    np.testing.assert_allclose(along, direction / np.linalg.norm(direction), atol=1e-9)
    # Just short of the hit is inside the dome, just beyond is outside.
    spec = PhantomSpec()
    before, beyond = hit - 1e-3 * along, hit + 1e-3 * along
    assert before[2] < spec.skin_height_m(before[0], before[1])
    assert beyond[2] > spec.skin_height_m(beyond[0], beyond[1])


def test_bad_queries_are_named(model) -> None:
    with pytest.raises(tissue.TissueInputError, match="no skin"):
        model.rest_skin_normal([0.0, 0.0, 0.5])  # above the breast, looking up
    with pytest.raises(tissue.TissueInputError, match="3 finite numbers"):
        model.rest_skin_normal([0.0, np.nan, 0.01])
    with pytest.raises(tissue.TissueInputError, match="not all zero"):
        model.rest_skin_normal([0.0, 0.0, 0.01], [0.0, 0.0, 0.0])
