"""LM's projected Gauss-Seidel: the sweep that sums over the pressing forces only gives the
dense sweep's forces bit for bit, and solves the LCP."""

from __future__ import annotations

import numpy as np
import pytest

from tissue.contact.lagrange import projected_gauss_seidel


def _dense_pgs(matrix, offset, force, tolerance, max_iterations):
    """The textbook sweep (every row summed in full), as the reference."""
    count = offset.shape[0]
    change = 0.0
    for sweep in range(1, max_iterations + 1):
        change = 0.0
        for i in range(count):
            gap = offset[i]
            for j in range(count):
                gap += matrix[i, j] * force[j]
            new = max(force[i] - gap / matrix[i, i], 0.0)
            change = max(change, abs(new - force[i]) * matrix[i, i])
            force[i] = new
        if change <= tolerance:
            return sweep, change
    return max_iterations, change


def _flat_face_lcp(rng: np.random.Generator, count: int):
    """A compliance like a probe face's: points a few mm apart, strongly coupled (nearly
    redundant), most of them clear of the probe, a few pressed into it."""
    points = rng.uniform(-0.01, 0.01, size=(count, 2))
    distance = np.linalg.norm(points[:, None] - points[None], axis=-1)
    matrix = 1e-3 * np.exp(-distance / 0.005) + 1e-9 * np.eye(count)
    offset = rng.uniform(-2e-4, 2e-3, size=count)  # [m]; negative: pressed in
    return matrix, offset


@pytest.mark.parametrize("seed", range(6))
def test_sparse_sweep_matches_the_dense_sweep_bit_for_bit(seed: int) -> None:
    rng = np.random.default_rng(seed)
    matrix, offset = _flat_face_lcp(rng, int(rng.integers(5, 60)))
    start = np.where(rng.random(offset.size) < 0.2, rng.uniform(0, 0.5, offset.size), 0.0)
    for tolerance, sweeps_cap in ((1e-8, 1000), (1e-12, 7)):
        ours, reference = start.copy(), start.copy()
        sweeps, change = projected_gauss_seidel(matrix, offset, ours, tolerance, sweeps_cap)
        ref_sweeps, ref_change = _dense_pgs(matrix, offset, reference, tolerance, sweeps_cap)
        assert (sweeps, change) == (ref_sweeps, ref_change)
        np.testing.assert_array_equal(ours, reference)


def test_the_forces_solve_the_lcp() -> None:
    matrix, offset = _flat_face_lcp(np.random.default_rng(7), 40)
    force = np.zeros(offset.size)
    sweeps, _ = projected_gauss_seidel(matrix, offset, force, 1e-13, 100_000)
    assert sweeps < 100_000
    gap = offset + matrix @ force
    assert np.any(force > 0.0) and np.any(force == 0.0)
    assert np.all(force >= 0.0)
    assert gap.min() > -1e-9  # [m]: no point left pressed in
    assert np.max(np.abs(gap[force > 0.0])) < 1e-9  # a pressing point touches
