"""LM contact leaves the skin points on the fixed base out of its constraints.

The collision surface closes the phantom's base with points on the fixed chest-wall plane
z = 0: their embedding has no weight on a free node, so no contact force can move them. As
Lagrange-multiplier constraints their compliance H A^-1 H^T is 0, and once the probe overlapped
one (a trained LesionSearch policy slid the probe down the breast's side to the base, seed 1)
the LCP had no solution: PGS returned the penetration over its regularisation, 9e7 N on the
probe from a 0.029 mm overlap beside a 2 N contact. The robust step could not converge (that
point's penetration never shrank), split four times and reported not_converged with that force;
the paper step reported it as ok.

The probe approaching that pose from rest in six steps reproduces it (before the fix, the last
step: robust not_converged 4.2e8 N, paper ok 9.6e6 N, on this level; now ok, 7 N).
"""

from __future__ import annotations

import numpy as np
import pytest

import tissue
from tissue.contact.fe_model import movable_points

LEVEL = 623
# The end of the bad step (the probe's face beside the base's rim, at y = 54 mm, z = 9 mm).
END_POSITION = np.array([0.01668746, 0.05383355, 0.00925502])
END_QUAT = np.array([0.16875517, -0.52410586, -0.16709996, 0.81787061])
BACK_M = 0.003  # the approach starts this far back along the pressing direction
STEPS = 6
# The contact at the end (forces of 2-3 N in the episode; 7 N here, from rest).
FORCE_BOUND_N = 20.0


def test_the_immovable_points_are_the_fixed_base() -> None:
    t = tissue.make_tissue(mesh=LEVEL, contact="lm", profile="robust")
    model = t.contact_model
    movable = movable_points(model.surface, t.fixed_nodes)
    base = model.surface.positions(t.rest_nodes_m)[~movable]
    assert 100 < base.shape[0] < model.surface.count // 2
    assert np.max(np.abs(base[:, 2])) < 1e-12  # all on the chest-wall plane z = 0
    np.testing.assert_array_equal(model._movable, movable)


@pytest.mark.parametrize("profile", ["robust", "paper"])
def test_a_probe_overlapping_the_fixed_base_gets_a_sane_force(profile: str) -> None:
    t = tissue.make_tissue(mesh=LEVEL, contact="lm", profile=profile)
    quat = END_QUAT / np.linalg.norm(END_QUAT)
    back = BACK_M * tissue.pressing_direction(quat)
    t.reset(END_POSITION - back, quat)
    for k in range(1, STEPS + 1):
        step = t.step(END_POSITION - back * (1.0 - k / STEPS), quat)
        assert step.status is tissue.StepStatus.OK, (k, step.status, step.diagnostics)
        assert np.linalg.norm(step.force_world_n) < FORCE_BOUND_N, (k, step.force_world_n)
    # The case is exercised: the probe's face overlaps a base point at the end ...
    assert step.skin_penetration_m > 1e-5
    assert step.diagnostics.contact_count > 0
    assert step.diagnostics.subdivisions == 0
    # ... which carries no force (no constraint on it), while the skin beside it pushes back.
    model = t.contact_model
    assert not np.any(model._warm[~model._movable])
    assert np.any(model._warm[model._movable] > 0.0)
