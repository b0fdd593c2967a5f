"""Thread counts and bits: the thread policy's calls, and the kernels of tissues above the
one-thread step size (``SERIAL_STEP_UNKNOWNS``) but below ``SERIAL_CG_UNKNOWNS``, which run in
parallel yet must give the same bits on one thread and on several (tissue.threads)."""

from __future__ import annotations

from collections.abc import Iterator

import numba
import numpy as np
import pytest
import scipy.sparse as sp

import tissue.sim.solvers as solvers
from tissue.errors import ConfigError
from tissue.fem.elasticity import Elasticity
from tissue.fem.material import TissueMaterials
from tissue.mesh.block import block_mesh
from tissue.sim.solvers.node_blocks import NodeBlocks, matrix_product
from tissue.threads import configure_threads, running_on_one_thread, thread_policy

POOL_THREADS = int(numba.config.NUMBA_NUM_THREADS)  # type: ignore[attr-defined]

needs_two_threads = pytest.mark.skipif(
    POOL_THREADS < 2, reason="numba has one thread here (NUMBA_NUM_THREADS or one core)"
)


@pytest.fixture
def restored_policy() -> Iterator[None]:
    """The process's thread policy and numba's thread count, as they were, afterwards."""
    policy = thread_policy()
    threads = numba.get_num_threads()
    try:
        yield
    finally:
        configure_threads(threads=policy.threads or POOL_THREADS)
        numba.set_num_threads(threads)


def _elasticity() -> tuple[Elasticity, np.ndarray]:
    """A block of 1,521 nodes (4,563 unknowns: above SERIAL_STEP_UNKNOWNS, below
    SERIAL_CG_UNKNOWNS) and deformed positions [m], (node_count, 3)."""
    mesh = block_mesh((0.06, 0.06, 0.04), (12, 12, 8), fix="z=min")
    unknowns = 3 * mesh.node_count
    assert solvers.SERIAL_STEP_UNKNOWNS <= unknowns < solvers.SERIAL_CG_UNKNOWNS
    rng = np.random.default_rng(11)
    positions = mesh.nodes + 2e-4 * rng.standard_normal(mesh.nodes.shape)
    return Elasticity(mesh, TissueMaterials()), positions


def _on_threads(threads: int, run):  # noqa: ANN001, ANN202 - a test helper
    """``run()`` with numba on ``threads`` threads (the parallel builds: no one_thread_below)."""
    previous = numba.get_num_threads()
    numba.set_num_threads(threads)
    try:
        assert not running_on_one_thread()
        return run()
    finally:
        numba.set_num_threads(previous)


@needs_two_threads
def test_node_block_products_below_the_cg_threshold_give_the_same_bits_on_any_thread_count() -> (
    None
):
    """Blocks built and multiplied in a parallel step (``LinearSolver.product``, the
    integrator's damping product) on one thread and on all: the same bits, and A x."""
    elasticity, positions = _elasticity()
    stiffness = elasticity.evaluate(positions).stiffness
    assert stiffness is not None
    matrix = (stiffness + 10.0 * sp.eye(stiffness.shape[0], format="csr")).tocsr()
    matrix.sort_indices()
    # Several vectors: a reduction split in two may round as the serial sum by chance.
    vectors = np.random.default_rng(12).standard_normal((4, matrix.shape[0]))

    def products(node_blocks: bool) -> tuple[np.ndarray, list[float]]:
        blocks = NodeBlocks.of(matrix) if node_blocks else None
        if node_blocks:
            assert blocks is not None
            blocks.fill(matrix.data)
            assert blocks.partial.shape[0] == 1  # one part below SERIAL_CG_UNKNOWNS
        out = np.empty_like(vectors)
        totals = [matrix_product(matrix, blocks, x, y) for x, y in zip(vectors, out, strict=True)]
        for x, y, total in zip(vectors, out, totals, strict=True):
            np.testing.assert_allclose(y, matrix @ x, rtol=1e-12, atol=1e-12 * np.abs(y).max())
            assert total == pytest.approx(float(x @ (matrix @ x)), rel=1e-12)
        return out, totals

    for node_blocks in (True, False):  # the block product and the CSR one
        one, one_totals = _on_threads(1, lambda node_blocks=node_blocks: products(node_blocks))
        every, every_totals = _on_threads(
            POOL_THREADS, lambda node_blocks=node_blocks: products(node_blocks)
        )
        differing = int(np.count_nonzero(one != every))
        assert differing == 0, f"node_blocks={node_blocks}: {differing} entries differ"
        assert one_totals == every_totals, f"node_blocks={node_blocks}"


@needs_two_threads
def test_element_pass_and_assembly_give_the_same_bits_on_any_thread_count() -> None:
    """Energy, forces and the (projected) stiffness, parallel on one thread and on all."""
    elasticity, positions = _elasticity()

    def evaluate() -> tuple[float, np.ndarray, np.ndarray]:
        state = elasticity.evaluate(positions, project_psd=True)
        assert state.stiffness is not None
        return state.energy_j, state.forces, state.stiffness.data

    one, every = _on_threads(1, evaluate), _on_threads(POOL_THREADS, evaluate)
    assert one[0] == every[0]
    np.testing.assert_array_equal(one[1], every[1])
    np.testing.assert_array_equal(one[2], every[2])


@pytest.mark.usefixtures("restored_policy")
def test_configure_threads_keeps_what_a_call_leaves_out() -> None:
    """An environment calls ``configure_threads()``: it keeps a policy its user set."""
    set_by_user = configure_threads(threads=1)
    assert set_by_user.threads == 1 and numba.get_num_threads() == 1
    kept = configure_threads()
    assert kept == set_by_user == thread_policy()
    assert numba.get_num_threads() == 1
    assert configure_threads(layer=kept.layer, mkl_sequential=kept.mkl_sequential) == kept
    with pytest.raises(ConfigError, match="already in force"):
        configure_threads(mkl_sequential=not kept.mkl_sequential)
    assert thread_policy() == kept
    with pytest.raises(ConfigError, match="threads must be"):
        configure_threads(threads=0)
