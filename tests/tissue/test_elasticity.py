"""Invariants of the hyperelastic tets (tissue.fem.elasticity): derivatives, patch test,
PSD, ANP."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import scipy.sparse.linalg as spla

from tissue.errors import ConfigError
from tissue.fem.elasticity import AntiLocking, Elasticity
from tissue.fem.material import MaterialLaw, NeoHookean, TissueMaterials
from tissue.mesh import TetMesh

LAWS = [MaterialLaw.STABLE, MaterialLaw.CLASSIC]
ANTI_LOCKING = [AntiLocking.NONE, AntiLocking.ANP]


def box_mesh(
    cells: tuple[int, int, int] = (2, 2, 2),
    size: tuple[float, float, float] = (0.03, 0.03, 0.03),
    jitter: float = 0.0,
    seed: int = 0,
    two_regions: bool = False,
) -> TetMesh:
    """A box split into cubes of 6 tets (Kuhn split), interior nodes optionally jittered.

    Args:
        cells: cubes per axis.
        size: box edge lengths [m].
        jitter: interior node displacement as a fraction of the smallest cell edge.
        seed: jitter seed.
        two_regions: label the tets with centroid x > half the box as region 1 (a lesion).
    """
    axes = [np.linspace(0.0, s, k + 1) for s, k in zip(size, cells, strict=True)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
    nodes = grid.reshape(-1, 3).copy()
    nx, ny, nz = cells
    index = np.arange(nodes.shape[0]).reshape(nx + 1, ny + 1, nz + 1)
    if jitter:
        h = min(s / k for s, k in zip(size, cells, strict=True))
        interior = np.zeros(index.shape, dtype=bool)
        interior[1:-1, 1:-1, 1:-1] = True
        rng = np.random.default_rng(seed)
        nodes[interior.ravel()] += rng.uniform(-jitter * h, jitter * h, (interior.sum(), 3))
    corner = {}
    for bits in range(8):
        dx, dy, dz = bits & 1, (bits >> 1) & 1, (bits >> 2) & 1
        corner[bits] = index[dx : nx + dx, dy : ny + dy, dz : nz + dz].ravel()
    tets = []
    for order in itertools.permutations((1, 2, 4)):
        path = (0, order[0], order[0] + order[1], 7)
        tets.append(np.stack([corner[p] for p in path], axis=1))
    tets = np.concatenate(tets)
    x0 = nodes[tets[:, 0]]
    volume = np.einsum(
        "ij,ij->i", nodes[tets[:, 1]] - x0, np.cross(nodes[tets[:, 2]] - x0, nodes[tets[:, 3]] - x0)
    )
    flip = volume < 0
    tets[flip, 2], tets[flip, 3] = tets[flip, 3].copy(), tets[flip, 2].copy()
    region = np.zeros(tets.shape[0], dtype=np.int64)
    names: tuple[str, ...] = ("tissue",)
    if two_regions:
        region = (nodes[tets].mean(axis=1)[:, 0] > 0.5 * size[0]).astype(np.int64)
        names = ("tissue", "lesion 1")
    return TetMesh(
        nodes=nodes, tets=tets, region=region, fixed_nodes=np.zeros(0, np.int64), region_names=names
    )


def materials(law: MaterialLaw, poisson: float = 0.45) -> TissueMaterials:
    return TissueMaterials(tissue=NeoHookean(3000.0, poisson), law=law)


def boundary_mask(mesh: TetMesh) -> np.ndarray:
    low, high = mesh.nodes.min(axis=0), mesh.nodes.max(axis=0)
    tol = 1e-9
    return np.any((mesh.nodes < low + tol) | (mesh.nodes > high - tol), axis=1)


def squash_node(
    el: Elasticity, x: np.ndarray, ratio: float, others_above: float = 0.2
) -> tuple[np.ndarray, int]:
    """Move one node towards (or through) the opposite face of one of its tets.

    Tries tets and vertices in turn until the chosen tet gets J = ``ratio`` while every
    other tet keeps J > ``others_above``.

    Returns:
        the new positions [m] and the moved node.
    """
    tets = el.mesh.tets
    for tet, vertex in itertools.product(range(tets.shape[0]), range(4)):
        nodes = np.roll(tets[tet], -vertex)
        apex, face = x[nodes[0]], x[nodes[1:]]
        normal = np.cross(face[1] - face[0], face[2] - face[0])
        normal /= np.linalg.norm(normal)
        height = np.dot(apex - face[0], normal)
        out = x.copy()
        out[nodes[0]] = apex - (1.0 - ratio / el.volume_ratios(x)[tet]) * height * normal
        ratios = el.volume_ratios(out)
        if abs(ratios[tet] - ratio) < 1e-9 and np.delete(ratios, tet).min() > others_above:
            return out, int(nodes[0])
    raise AssertionError("no node could be moved without flattening another tet")


def central_difference_check(el: Elasticity, x: np.ndarray, step: float) -> tuple[float, float]:
    """Relative max errors of forces vs -grad E and of K vs -d forces/dx."""
    state = el.evaluate(x)
    grad = np.zeros(x.size)
    jac = np.zeros((x.size, x.size))
    for i in range(x.size):
        plus, minus = x.copy(), x.copy()
        plus.flat[i] += step
        minus.flat[i] -= step
        sp_, sm = el.evaluate(plus, tangent=False), el.evaluate(minus, tangent=False)
        grad[i] = (sp_.energy_j - sm.energy_j) / (2 * step)
        jac[:, i] = -(sp_.forces - sm.forces).ravel() / (2 * step)
    forces = state.forces.ravel()
    stiffness = state.stiffness.toarray()
    force_error = np.abs(grad + forces).max() / np.abs(forces).max()
    stiffness_error = np.abs(jac - stiffness).max() / np.abs(stiffness).max()
    return float(force_error), float(stiffness_error)


# ----------------------------------------------------------------------------------------
# Configuration


def test_anti_locking_parse_accepts_names_and_rejects_unknown() -> None:
    assert AntiLocking.parse("anp") is AntiLocking.ANP
    assert AntiLocking.parse(AntiLocking.NONE) is AntiLocking.NONE
    with pytest.raises(ConfigError, match="'none', 'anp'"):
        AntiLocking.parse("fbar")
    with pytest.raises(ConfigError, match="fbar"):
        Elasticity(box_mesh((1, 1, 1)), materials(MaterialLaw.STABLE), "fbar")


def test_positions_of_wrong_shape_are_rejected() -> None:
    el = Elasticity(box_mesh((1, 1, 1)), materials(MaterialLaw.STABLE))
    with pytest.raises(ValueError, match="node_count, 3"):
        el.evaluate(np.zeros((3, 3)))


# ----------------------------------------------------------------------------------------
# Derivatives


@pytest.mark.parametrize("anti_locking", ANTI_LOCKING)
@pytest.mark.parametrize("law", LAWS)
def test_forces_and_stiffness_match_finite_differences(
    law: MaterialLaw, anti_locking: AntiLocking
) -> None:
    mesh = box_mesh((2, 2, 2), jitter=0.2, two_regions=True)
    el = Elasticity(mesh, materials(law), anti_locking)
    rng = np.random.default_rng(3)
    x = mesh.nodes @ np.array([[1.05, 0.1, 0.0], [0.0, 0.9, 0.05], [0.02, 0.0, 0.95]])
    x += rng.normal(0.0, 1e-3, x.shape)
    # One nearly flat tet (J = 0.05).
    x, _ = squash_node(el, x, 0.05)
    assert el.volume_ratios(x).min() == pytest.approx(0.05)
    force_error, stiffness_error = central_difference_check(el, x, step=1e-8)
    assert force_error < 1e-6
    assert stiffness_error < 1e-6
    # The gather stores each upper block's transpose as its lower block: bitwise symmetric.
    stiffness = el.evaluate(x).stiffness
    assert (stiffness != stiffness.T).nnz == 0


@pytest.mark.parametrize("anti_locking", ANTI_LOCKING)
def test_stable_law_inverted_tet_is_finite_exact_and_restoring(anti_locking: AntiLocking) -> None:
    mesh = box_mesh((2, 2, 2), jitter=0.1)
    el = Elasticity(mesh, materials(MaterialLaw.STABLE), anti_locking)
    x, moved = squash_node(el, mesh.nodes, -0.3)
    state = el.evaluate(x)
    assert state.inverted_count >= 1 and state.min_volume_ratio < 0.0
    assert math.isfinite(state.energy_j)
    assert np.all(np.isfinite(state.forces)) and np.all(np.isfinite(state.stiffness.data))
    # Restoring: the force on the pushed node points back to where it came from, and a
    # small step along the forces lowers the energy.
    back = mesh.nodes[moved] - x[moved]
    assert np.dot(state.forces[moved], back) > 0.0
    step = 1e-3 * 0.015 / np.abs(state.forces).max()
    assert el.energy(x + step * state.forces) < state.energy_j
    force_error, stiffness_error = central_difference_check(el, x, step=1e-8)
    assert force_error < 1e-6 and stiffness_error < 1e-6


@pytest.mark.parametrize("anti_locking", ANTI_LOCKING)
def test_classic_law_inverted_tet_gives_inf_energy_and_finite_zeroed_element(
    anti_locking: AntiLocking,
) -> None:
    mesh = box_mesh((2, 2, 2), jitter=0.1)
    el = Elasticity(mesh, materials(MaterialLaw.CLASSIC), anti_locking)
    x, _ = squash_node(el, mesh.nodes, -0.3)
    state = el.evaluate(x, project_psd=True)
    assert state.energy_j == math.inf and el.energy(x) == math.inf
    assert state.inverted_count == int(np.count_nonzero(el.volume_ratios(x) <= 0))
    assert state.inverted_count >= 1
    assert np.all(np.isfinite(state.forces)) and np.all(np.isfinite(state.stiffness.data))


@pytest.mark.parametrize("anti_locking", ANTI_LOCKING)
def test_inversion_barrier_is_exact_below_its_ratio_and_absent_above(
    anti_locking: AntiLocking,
) -> None:
    mesh = box_mesh((2, 2, 2), jitter=0.1)
    plain = Elasticity(mesh, materials(MaterialLaw.STABLE), anti_locking)
    barred = Elasticity(mesh, materials(MaterialLaw.STABLE), anti_locking, inversion_barrier=0.1)
    # Above the barrier ratio the law is untouched, to the last bit.
    x, _ = squash_node(plain, mesh.nodes, 0.2)
    a, b = plain.evaluate(x, project_psd=True), barred.evaluate(x, project_psd=True)
    assert a.energy_j == b.energy_j
    assert np.array_equal(a.forces, b.forces)
    assert np.array_equal(a.stiffness.data, b.stiffness.data)
    # Below it the energy rises, its derivatives stay exact and the projected tangent PSD.
    x, moved = squash_node(plain, mesh.nodes, 0.02)
    state = barred.evaluate(x)
    assert state.energy_j > plain.energy(x)
    force_error, stiffness_error = central_difference_check(barred, x, step=1e-9)
    assert force_error < 1e-6 and stiffness_error < 1e-6
    projected = barred.evaluate(x, project_psd=True).stiffness.toarray()
    assert (
        np.linalg.eigvalsh(0.5 * (projected + projected.T)).min() > -1e-9 * np.abs(projected).max()
    )
    # The barrier pushes the flattened tet's apex back harder than the law alone.
    back = mesh.nodes[moved] - x[moved]
    assert np.dot(state.forces[moved], back) > np.dot(plain.forces(x)[moved], back) > 0.0


def test_inversion_barrier_makes_an_inverted_tet_an_infinite_energy() -> None:
    mesh = box_mesh((2, 2, 2), jitter=0.1)
    el = Elasticity(mesh, materials(MaterialLaw.STABLE), inversion_barrier=0.1)
    x, _ = squash_node(el, mesh.nodes, -0.3)
    state = el.evaluate(x, project_psd=True)
    assert state.energy_j == math.inf and state.inverted_count >= 1
    assert np.all(np.isfinite(state.forces)) and np.all(np.isfinite(state.stiffness.data))
    for bad in (-0.1, 1.0, math.nan):
        with pytest.raises(ValueError, match="inversion_barrier"):
            Elasticity(mesh, materials(MaterialLaw.STABLE), inversion_barrier=bad)


# ----------------------------------------------------------------------------------------
# Rest state and small strain


def linear_elastic_stiffness(mesh: TetMesh, mu: float, lam: float) -> np.ndarray:
    """Dense small-strain stiffness sum_e V B^T D B (Voigt, engineering shear strains)."""
    dof = 3 * mesh.node_count
    stiffness = np.zeros((dof, dof))
    d = np.zeros((6, 6))
    d[:3, :3] = lam
    d[:3, :3] += 2 * mu * np.eye(3)
    d[3:, 3:] = mu * np.eye(3)
    for tet in mesh.tets:
        x = mesh.nodes[tet]
        dm = (x[1:] - x[0]).T
        grads = np.vstack([-np.linalg.inv(dm).sum(axis=0), np.linalg.inv(dm)])
        volume = np.linalg.det(dm) / 6
        b = np.zeros((6, 12))
        for a, (gx, gy, gz) in enumerate(grads):
            b[:, 3 * a : 3 * a + 3] = [
                [gx, 0, 0],
                [0, gy, 0],
                [0, 0, gz],
                [gy, gx, 0],
                [0, gz, gy],
                [gz, 0, gx],
            ]
        dofs = (3 * tet[:, None] + np.arange(3)).ravel()
        stiffness[np.ix_(dofs, dofs)] += volume * b.T @ d @ b
    return stiffness


@pytest.mark.parametrize("anti_locking", ANTI_LOCKING)
@pytest.mark.parametrize("law", LAWS)
def test_rest_state_is_stress_free_and_linearises_to_lame(
    law: MaterialLaw, anti_locking: AntiLocking
) -> None:
    mesh = box_mesh((2, 2, 2), jitter=0.2)
    mat = materials(law, poisson=0.45)
    el = Elasticity(mesh, mat, anti_locking)
    state = el.evaluate(mesh.nodes)
    stiffness = state.stiffness.toarray()
    scale = np.abs(stiffness).max()
    assert abs(state.energy_j) < 1e-12 * scale * 0.03**2
    assert np.abs(state.forces).max() < 1e-12 * scale * 0.03
    assert np.array_equal(stiffness, stiffness.T)
    reference = linear_elastic_stiffness(mesh, mat.tissue.mu_pa, mat.tissue.lambda_pa)
    if anti_locking is AntiLocking.NONE:
        np.testing.assert_allclose(stiffness, reference, atol=1e-10 * scale)
    # Any law and anti-locking: homogeneous small strain gives linear elasticity, including
    # the boundary nodes (tractions sigma n with sigma = 2 mu eps + lam tr(eps) I).
    gradient = np.array([[1.0, 0.3, -0.2], [0.1, -0.5, 0.4], [0.25, 0.0, 0.7]])
    u = (mesh.nodes @ gradient.T).ravel()
    np.testing.assert_allclose(stiffness @ u, reference @ u, atol=1e-10 * scale * 0.03)
    # The same from the nonlinear forces at a small affine strain.
    eps = 1e-7
    forces = el.forces(mesh.nodes + eps * (mesh.nodes @ gradient.T))
    np.testing.assert_allclose(
        -forces.ravel(), eps * reference @ u, rtol=0, atol=1e-5 * eps * scale * 0.03
    )


@pytest.mark.parametrize("law", LAWS)
def test_small_strain_energy_keeps_its_digits(law: MaterialLaw) -> None:
    """At 1e-6 and 1e-7 strain the energy is the linear-elastic u^T K u / 2 to 10 x strain.

    The energy is O(strain^2) while the invariants are O(strain): written with F (I_C - 3,
    (J - alpha)^2) the terms cancel and ~1e-4 relative round-off was left at 1e-7 strain,
    enough to stall an energy line search near convergence.
    """
    mesh = box_mesh((2, 2, 2), jitter=0.2)
    mat = materials(law, poisson=0.49)
    el = Elasticity(mesh, mat)
    reference = linear_elastic_stiffness(mesh, mat.tissue.mu_pa, mat.tissue.lambda_pa)
    gradient = np.array([[1.0, 0.3, -0.2], [0.1, -0.5, 0.4], [0.25, 0.0, 0.7]])
    for eps in (1e-6, 1e-7):
        u = eps * (mesh.nodes @ gradient.T)
        expected = 0.5 * u.ravel() @ reference @ u.ravel()
        energy = el.evaluate(mesh.nodes + u, tangent=False).energy_j
        assert energy == pytest.approx(expected, rel=10 * eps + 1e-9, abs=0.0)


def test_lumped_mass_volume_and_pattern_reuse() -> None:
    mesh = box_mesh((2, 3, 2), size=(0.02, 0.03, 0.02), jitter=0.1)
    el = Elasticity(mesh, materials(MaterialLaw.STABLE))
    assert el.node_count == mesh.node_count and el.dof_count == 3 * mesh.node_count
    assert el.rest_volume_m3 == pytest.approx(0.02 * 0.03 * 0.02, rel=1e-12)
    assert el.lumped_mass.sum() == pytest.approx(1075.0 * el.rest_volume_m3, rel=1e-12)
    first = el.evaluate(mesh.nodes).stiffness
    second = el.evaluate(mesh.nodes * 1.01).stiffness
    assert first.indices is second.indices and first.indptr is second.indptr
    assert first.data is not second.data
    np.testing.assert_allclose(el.volume_ratios(mesh.nodes * 1.01), 1.01**3)


# ----------------------------------------------------------------------------------------
# Patch test


@pytest.mark.parametrize("anti_locking", ANTI_LOCKING)
@pytest.mark.parametrize("law", LAWS)
def test_patch_test_interior_follows_affine_map(
    law: MaterialLaw, anti_locking: AntiLocking
) -> None:
    mesh = box_mesh((3, 3, 3), jitter=0.25, seed=4)
    el = Elasticity(mesh, materials(law), anti_locking)
    gradient = np.array([[1.2, 0.15, 0.0], [-0.1, 0.85, 0.1], [0.05, 0.0, 1.1]])
    affine = mesh.nodes @ gradient.T + np.array([0.01, -0.02, 0.005])
    interior = ~boundary_mask(mesh)
    assert interior.sum() == 8
    # Interior forces vanish under the affine map itself.
    forces = el.forces(affine)
    scale = np.abs(forces[~interior]).max()
    assert np.abs(forces[interior]).max() < 1e-10 * scale
    # Newton from perturbed interior positions converges back to the affine map.
    x = affine.copy()
    x[interior] += np.random.default_rng(5).uniform(-1e-3, 1e-3, (interior.sum(), 3))
    free = (3 * np.flatnonzero(interior)[:, None] + np.arange(3)).ravel()
    for _ in range(30):
        state = el.evaluate(x)
        residual = state.forces.ravel()[free]
        if np.abs(residual).max() < 1e-13 * scale:
            break
        k = state.stiffness[free][:, free].tocsc()
        x.flat[free] += spla.spsolve(k, residual)
    extent = 0.03
    assert np.abs(x - affine).max() < 1e-8 * extent


# ----------------------------------------------------------------------------------------
# PSD projection


@pytest.mark.parametrize("gap", [0.5, 2e-3, 1e-3, 5e-4, 1e-8, 0.0])
def test_closed_form_eigen_solver_is_accurate_near_repeated_eigenvalues(gap: float) -> None:
    """The projection's 3 x 3 eigen-solver (closed form, Jacobi for near-repeated roots):
    A v = lambda v to round-off and V orthonormal, for two eigenvalues ``gap`` apart
    (relative) on random bases, signs mixed as in the scaling block. Where the gap is wide
    enough for the closed form it also returns them sorted largest first, which the Jacobi
    iteration does not (so the closed form is what ran there)."""
    from tissue.fem import kernels as kern

    rng = np.random.default_rng(3)
    count = 400
    basis, _ = np.linalg.qr(rng.normal(size=(count, 3, 3)))
    values = rng.normal(size=(count, 3))
    values[:, 1] = values[:, 0] * (1.0 + gap)
    matrices = np.einsum("nij,nj,nkj->nik", basis, values, basis)
    matrices = 0.5 * (matrices + matrices.transpose(0, 2, 1))
    w, v, r = np.empty(3), np.empty((3, 3)), np.empty((3, 3))
    descending = 0
    for a in matrices:
        kern.sym3_eigen_fast(a.copy(), w, v, r)
        scale = np.abs(w).max()
        assert np.abs(a @ v - v * w).max() < 1e-12 * scale
        assert np.abs(v.T @ v - np.eye(3)).max() < 1e-13
        descending += int(w[0] >= w[1] >= w[2])
    if gap >= 0.1:  # far above kern.CLOSED_FORM_GAP for almost every sample
        assert descending >= 0.9 * count


@pytest.mark.parametrize("anti_locking", ANTI_LOCKING)
@pytest.mark.parametrize("law", LAWS)
def test_projected_tangent_is_psd_where_the_exact_one_is_not(
    law: MaterialLaw, anti_locking: AntiLocking
) -> None:
    mesh = box_mesh((2, 2, 2), jitter=0.2, two_regions=True)
    el = Elasticity(mesh, materials(law, poisson=0.45), anti_locking)
    rng = np.random.default_rng(7)
    x = mesh.nodes * np.array([1.1, 1.0, 0.55])
    x += rng.normal(0.0, 1.5e-3, x.shape)
    exact = el.evaluate(x)
    projected = el.evaluate(x, project_psd=True)
    assert exact.inverted_count == 0
    np.testing.assert_array_equal(exact.forces, projected.forces)
    assert exact.energy_j == projected.energy_j
    k_exact = exact.stiffness.toarray()
    k_proj = projected.stiffness.toarray()
    assert np.array_equal(k_proj, k_proj.T)
    scale = np.abs(np.linalg.eigvalsh(k_exact)).max()
    assert np.linalg.eigvalsh(k_exact).min() < -1e-3 * scale
    assert np.linalg.eigvalsh(k_proj).min() > -1e-10 * scale


@pytest.mark.parametrize("law", LAWS)
def test_projection_equals_explicit_clamp_of_dp_df(law: MaterialLaw) -> None:
    """One tet: K_proj = V B^T clamp(dP/dF) B, dP/dF built and eigen-decomposed densely."""
    rest = np.array([[0, 0, 0], [0.01, 0, 0], [0, 0.012, 0], [0.001, 0.002, 0.009]])
    mesh = TetMesh(
        nodes=rest,
        tets=np.array([[0, 1, 2, 3]]),
        region=np.zeros(1, np.int64),
        fixed_nodes=np.zeros(0, np.int64),
    )
    mat = materials(law)
    mu, lam = mat.tissue.mu_pa, mat.tissue.lambda_pa
    el = Elasticity(mesh, mat)
    levi = np.zeros((3, 3, 3))
    for i, j, k in itertools.permutations(range(3)):
        levi[i, j, k] = np.linalg.det(np.eye(3)[[i, j, k]])
    dm = (rest[1:] - rest[0]).T
    grads = np.vstack([-np.linalg.inv(dm).sum(axis=0), np.linalg.inv(dm)])
    volume = np.linalg.det(dm) / 6
    b = np.zeros((9, 12))
    for i, j, a in itertools.product(range(3), range(3), range(4)):
        b[3 * i + j, 3 * a + i] = grads[a, j]
    rng = np.random.default_rng(11)
    gradients = [np.eye(3) + rng.normal(0.0, 0.4, (3, 3)) for _ in range(12)]
    gradients += [np.diag([0.6, 1.3, 1.3]), np.diag([1.2, 1.2, 1.2]), np.diag([0.7, 0.7, 1.0])]
    if law is MaterialLaw.STABLE:
        gradients.append(np.diag([0.8, 1.1, -0.2]))  # inverted
    for gradient in gradients:
        jac = np.linalg.det(gradient)
        if jac <= 0 and law is MaterialLaw.CLASSIC:
            continue
        cof = jac * np.linalg.inv(gradient).T
        if law is MaterialLaw.STABLE:
            dpsi, ddpsi = (lam + mu) * (jac - 1 - mu / (lam + mu)), lam + mu
        else:
            dpsi = (lam * np.log(jac) - mu) / jac
            ddpsi = (lam * (1 - np.log(jac)) + mu) / jac**2
        hessian_j = np.einsum("ikm,jln,mn->ijkl", levi, levi, gradient).reshape(9, 9)
        dp_df = mu * np.eye(9) + ddpsi * np.outer(cof, cof) + dpsi * hessian_j
        values, vectors = np.linalg.eigh(dp_df)
        expected = volume * b.T @ ((vectors * np.maximum(values, 0)) @ vectors.T) @ b
        got = el.evaluate(rest @ gradient.T, project_psd=True).stiffness.toarray()
        np.testing.assert_allclose(got, expected, atol=1e-12 * np.abs(expected).max())


def test_projection_changes_nothing_where_elements_are_convex() -> None:
    # Uniform stretch with J ~ alpha: psi' ~ 0, every dP/dF is positive definite.
    mesh = box_mesh((2, 2, 2), jitter=0.2)
    mat = materials(MaterialLaw.STABLE)
    el = Elasticity(mesh, mat)
    mu, lam = mat.tissue.mu_pa, mat.tissue.lambda_pa
    alpha = 1.0 + mu / (lam + mu)
    x = mesh.nodes * alpha ** (1.0 / 3.0)
    exact = el.evaluate(x).stiffness.toarray()
    projected = el.evaluate(x, project_psd=True).stiffness.toarray()
    np.testing.assert_array_equal(exact, projected)


# ----------------------------------------------------------------------------------------
# Anti-locking


def cantilever_tip_deflection(cells: tuple[int, int, int], anti_locking: AntiLocking) -> float:
    """Tip deflection [m] of a clamped beam (0.1 x 0.02 x 0.02 m, nu = 0.49) under 0.1 mN."""
    length, height = 0.1, 0.02
    mesh = box_mesh(cells, size=(length, height, height))
    el = Elasticity(mesh, TissueMaterials(tissue=NeoHookean(3000.0, 0.49)), anti_locking)
    stiffness = el.evaluate(mesh.nodes).stiffness
    clamped = np.flatnonzero(mesh.nodes[:, 0] < 1e-12)
    tip = np.flatnonzero(mesh.nodes[:, 0] > length - 1e-12)
    load = np.zeros((mesh.node_count, 3))
    load[tip, 2] = -1e-4 / tip.size
    free = np.setdiff1d(np.arange(el.dof_count), (3 * clamped[:, None] + np.arange(3)).ravel())
    u = np.zeros(el.dof_count)
    u[free] = spla.spsolve(stiffness[free][:, free].tocsc(), load.ravel()[free])
    return float(-u.reshape(-1, 3)[tip, 2].mean())


def timoshenko_tip_deflection() -> float:
    length, height, young, poisson, load = 0.1, 0.02, 3000.0, 0.49, 1e-4
    shear = young / (2 * (1 + poisson))
    kappa = 10 * (1 + poisson) / (12 + 11 * poisson)
    inertia = height**4 / 12
    return load * length**3 / (3 * young * inertia) + load * length / (kappa * shear * height**2)


def test_anp_relieves_volumetric_locking_in_bending() -> None:
    reference = timoshenko_tip_deflection()
    plain = cantilever_tip_deflection((10, 2, 2), AntiLocking.NONE)
    anp = cantilever_tip_deflection((10, 2, 2), AntiLocking.ANP)
    # Plain tets lock (deflect ~1/8 of the beam theory); ANP recovers about four times more.
    assert plain < anp < reference
    assert reference - anp < 0.6 * (reference - plain)


def test_anp_converges_to_the_refined_reference_faster() -> None:
    reference = cantilever_tip_deflection((40, 8, 8), AntiLocking.ANP)
    assert reference == pytest.approx(timoshenko_tip_deflection(), rel=0.15)
    plain = cantilever_tip_deflection((20, 4, 4), AntiLocking.NONE)
    anp = cantilever_tip_deflection((20, 4, 4), AntiLocking.ANP)
    assert abs(reference - anp) < 0.3 * abs(reference - plain)
