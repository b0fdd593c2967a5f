"""Both profiles integrate the tissue's inertia and Rayleigh damping (what the ``damping``
effect of a scene means, envs/effects.py): pressed 10 mm and released in one step, the skin
springs back over many steps, as a damped dynamic step does; a quasi-static step would put
it back at rest at once."""

from __future__ import annotations

import numpy as np
import pytest

import tissue


@pytest.mark.parametrize("profile", ["paper", "robust"])
def test_released_skin_returns_over_many_steps_under_either_profile(profile: str) -> None:
    body = tissue.make_tissue(mesh=623, contact="penalty", profile=profile)
    position, quat = body.touching_pose(body.lesions[0].rest_centre_m)
    rest = body.surface().vertices_m.copy()
    body.reset(position, quat)
    inward = tissue.pressing_direction(quat)
    for k in range(1, 26):  # 10 mm at 0.5 mm a step, then held
        body.step(position + inward * min(0.01, 0.0005 * k), quat)

    def displaced() -> float:
        return float(np.abs(body.surface().vertices_m - rest).max())

    pressed = displaced()
    away = position - 0.05 * inward  # released: the probe well clear of the skin
    after = []
    for _ in range(10):
        assert body.step(away, quat).status is tissue.StepStatus.OK
        after.append(displaced())
    assert pressed > 0.009
    # Still most of the way in one step after the release, and moving back every step
    # (damped: no overshoot in ten steps), yet well on its way after ten.
    assert after[0] > 0.5 * pressed
    assert all(b < a for a, b in zip(after, after[1:], strict=False))
    assert after[-1] < 0.4 * pressed
