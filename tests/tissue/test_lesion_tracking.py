"""Lesions located only where asked (``Tissue.track_lesions``, ``lesion_centroids_m(which)``):
the same numbers as locating every lesion, no other lesion's tets read."""

from __future__ import annotations

import numpy as np
import pytest

import tissue
from tissue import lesions as lesions_module


def test_a_subset_of_lesions_is_located_as_among_all() -> None:
    t = tissue.make_tissue(mesh=623)
    position, quat = t.touching_pose(t.lesions[1].rest_centre_m)
    direction = tissue.pressing_direction(quat)
    t.reset(position, quat)
    for k in range(1, 11):
        step = t.step(position + 0.0005 * k * direction, quat)
    every = t.lesion_centroids_m()
    assert step.lesion_centroids_world_m.shape == (len(t.lesions), 3)
    assert np.array_equal(t.lesion_centroids_m([2, 1]), every[[2, 1]])
    assert t.lesion_centroids_m(()).shape == (0, 3)
    t.track_lesions([1])
    step = t.step(position + 0.0055 * direction, quat)
    assert t.tracked_lesions == (1,)
    assert np.array_equal(step.lesion_centroids_world_m, t.lesion_centroids_m()[[1]])
    with pytest.raises(tissue.TissueInputError, match="lesion indices must be in 0.."):
        t.track_lesions([len(t.lesions)])


def test_a_step_tracking_no_lesion_reads_none(monkeypatch: pytest.MonkeyPatch) -> None:
    t = tissue.make_tissue(mesh=623)
    t.track_lesions(())
    calls = []
    original = lesions_module._volume_centroids

    def counted(*args):  # type: ignore[no-untyped-def]
        calls.append(args[-1].size)
        return original(*args)

    monkeypatch.setattr(lesions_module, "_volume_centroids", counted)
    position, quat = t.touching_pose(t.lesions[0].rest_centre_m)
    t.reset(position, quat)
    for k in range(1, 6):
        step = t.step(position + 0.0005 * k * tissue.pressing_direction(quat), quat)
    assert step.lesion_centroids_world_m.shape == (0, 3) and calls == []
    t.lesion_centroids_m([0])
    assert calls == [1]
