"""Contact strategies against closed-form contact mechanics at small strain (issue 3).

Closed forms (frictionless rigid indenter on an elastic half-space, E* = E / (1 - nu^2)):

- Hertz (Johnson, *Contact Mechanics*, 1985, section 4.2): a sphere of radius R pressed a
  depth delta past first contact carries F = (4/3) E* sqrt(R) delta^(3/2) over a contact
  circle of radius a = sqrt(R delta).
- Sneddon (1965, Int. J. Engng Sci. 3:47-57; Johnson 1985, chapter 3): a flat-ended
  cylindrical punch of radius a pressed flat carries F = 2 a E* delta.

What the set-up does about the ways a finite-element check comes out too stiff (a 48k-tet
graded box once gave LM 12 % above Hertz); the numbers are LM's force error, measured:

- Finite block. A block on a fixed base is stiffer than the half-space by about a / L (L its
  half size: +4.6 % at L = 40 a, +3.1 % at 100 a, +2.4 % at 500 a on one mesh). The blocks
  here are 500 contact radii wide and deep (about 0.2 %): ``half_space_mesh`` grows its
  shells with the distance from the contact, so such a block costs tens of thousands of
  tets, where a tensor-product graded grid needs hundreds of thousands.
- Resolution under the contact. Uniform cells of a / 3 (fast) or a / 5 (slow) cover the
  contact and a little more; each cell's split is mirrored by parity, so the mesh has the
  problem's mirror symmetry instead of the one preferred diagonal of a plain Kuhn split
  (which was 1.5 % stiffer).
- Stiff linear tets. Average nodal pressure (``anti_locking="anp"``) takes 1 % of the excess
  stiffness away at nu = 0.3. What is left is discretisation: +2.5 % at a / 3 cells, +1.3 %
  at a / 5 with a core twice as wide; it also swings by about a per cent with where the
  contact edge falls between rings of nodes (the first ring outside a joins the contact).
- Equilibrium. Every step is quasi-static (``SimulationConfig(quasi_static=True)``), robust
  Newton to a relative residual of 1e-5; LM and penalty reach the depth in one step.
- Depth. delta / R = 0.01: finite-strain and exact-sphere corrections are below 0.1 % (the
  same mesh scaled to delta / R = 0.0025 gives the same error to 0.02 %).

Methods: Lagrange multipliers (frictionless, exact non-penetration); penalty with plain
(not augmented) springs of k_s = 1000 E h per point (h the core's cell; penetration a few
1e-4 of the depth); online prescribed displacement, whose contact nodes stick to the
probe (``prescribed``), and its frictionless variant, whose nodes are held along the
probe's normal only and slide (``sliding``). Sticking makes it the no-slip contact problem,
stiffer than the frictionless one for nu < 1/2: for a bonded flat punch by the factor
(1 - nu) ln(3 - 4 nu) / (1 - 2 nu) = 1.029 at nu = 0.3 (Mossakovskii 1954; Spence 1968).
The slow Hertz test says what that costs it.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import pytest

from tissue import TissueStep
from tissue.contact import make_contact_model
from tissue.contact.base import ContactModel
from tissue.contact.lagrange import LagrangeParams
from tissue.contact.penalty import PenaltyParams
from tissue.contact.placement import first_contact_pose
from tissue.contact.prescribed import PrescribedContact, PrescribedParams
from tissue.errors import MeshError
from tissue.fem.material import NeoHookean, TissueMaterials
from tissue.mesh import TetMesh, boundary_faces
from tissue.mesh.block import centred_ticks, graded_ticks, half_space_mesh
from tissue.probe import CylinderProbe, ProbeShape, SphereProbe, parse_probe_spec
from tissue.sim.simulator import SimulationConfig
from tissue.status import StepStatus

E_PA, NU = 3000.0, 0.3
E_STAR = E_PA / (1.0 - NU**2)
MATERIALS = TissueMaterials(tissue=NeoHookean(E_PA, NU))
# Quasi-static robust Newton to a relative residual of 1e-5 for every method. (Online
# prescribed displacement's first steps move a node or a few by microns and store ~1e-11 J
# in a 0.5 m^3 block; the energy line search confirms such decreases because the kernels
# write the energy in F - I, without cancelling terms.)
CONFIG = SimulationConfig(
    mode="robust", quasi_static=True, newton_tolerance=1e-5, anti_locking="anp"
)
DOWN = np.array([0.0, 0.0, -1.0])
# "sliding" is online prescribed displacement with PrescribedParams(sliding=True).
METHODS = ["lm", "penalty", "prescribed", "sliding"]

# Hertz: R = 10 mm pressed 0.1 mm, contact radius a = 1 mm.
SPHERE_RADIUS_M = 0.01
HERTZ_DEPTH_M = 1e-4
# Online prescribed displacement takes a node in once the probe has passed it and projects it
# onto the probe: the press is split into this many quasi-static steps (10 steps: +0.6 %).
PRESCRIBED_STEPS = 20
# Penalty springs per point, as a multiple of E times the core's cell size.
PENALTY_STIFFNESS_RATIO = 1000.0


@dataclass(frozen=True)
class Block:
    """A half-space block in units of the contact radius a.

    Attributes:
        cells_per_radius: a / h, h the core's cell size.
        core_cells: the uniform core's half width, in cells.
        growth: shell-to-shell growth of the radial cell size.
        coarsen_ratio: halve the shells' face grid at these radius ratios (None: never).
        extent_radii: the block's half width and depth, in contact radii.
    """

    cells_per_radius: float
    core_cells: int
    growth: float
    coarsen_ratio: float | None = None
    extent_radii: float = 500.0


# Fast tier: 29k tets, a few seconds per method. Slow tier: 124k tets, about 1.5 minutes.
FAST = Block(cells_per_radius=3.0, core_cells=4, growth=1.3)
REFINED = Block(cells_per_radius=5.0, core_cells=10, growth=1.25, coarsen_ratio=2.5)
# The punch's radius is the one whose disc has the area of the 37 nodes it covers (37 h^2 =
# pi a^2): a ring of nodes on the rim would otherwise let round-off decide the contact area.
PUNCH_NODES = 37
PUNCH = Block(
    cells_per_radius=math.sqrt(PUNCH_NODES / math.pi), core_cells=4, growth=1.3, extent_radii=200.0
)


@lru_cache(maxsize=4)
def _mesh(block: Block, radius_m: float) -> TetMesh:
    cell = radius_m / block.cells_per_radius
    return half_space_mesh(
        cell,
        block.core_cells * cell,
        block.extent_radii * radius_m,
        block.growth,
        coarsen_ratio=block.coarsen_ratio,
    )


def _press(
    method: str, mesh: TetMesh, shape: ProbeShape, depth_m: float, cell_m: float
) -> tuple[TissueStep, ContactModel]:
    """Press ``shape`` straight down at the block's centre to ``depth_m`` past first contact.

    LM and penalty go there in one quasi-static step; online prescribed displacement (both
    variants) in ``PRESCRIBED_STEPS`` steps, then holds the pose until its node set stops
    changing.
    """
    params = {
        "lm": LagrangeParams(alarm_distance_m=0.1 * depth_m, pgs_tolerance_m=1e-6 * depth_m),
        "penalty": PenaltyParams(
            stiffness_n_per_m=PENALTY_STIFFNESS_RATIO * E_PA * cell_m, augmented=False
        ),
        "prescribed": PrescribedParams(online=True),
        "sliding": PrescribedParams(online=True, sliding=True),
    }[method]
    strategy = "prescribed" if method == "sliding" else method
    model = make_contact_model(
        strategy, mesh, shape, materials=MATERIALS, config=CONFIG, params=params
    )
    position, quat = first_contact_pose(model.surface, mesh.nodes, shape, np.zeros(3), DOWN)
    steps = PRESCRIBED_STEPS if strategy == "prescribed" else 1
    for i in range(1, steps + 1):
        result = model.step(position + depth_m * i / steps * DOWN, quat)
        assert result.status is StepStatus.OK, (method, i, result.status, result.diagnostics)
    if isinstance(model, PrescribedContact):
        for _ in range(5):
            nodes = model.contact_nodes.copy()
            result = model.step(position + depth_m * DOWN, quat)
            assert result.status is StepStatus.OK, (method, result.status)
            if np.array_equal(nodes, model.contact_nodes):
                break
        else:
            pytest.fail("online prescribed contact nodes kept changing at a fixed pose")
    return result, model


def _normal_force(result: TissueStep) -> float:
    """The force the tissue pushes the probe back with [N] (> 0)."""
    return float(-result.force_world_n @ DOWN)


def hertz_force(radius_m: float, depth_m: float) -> float:
    """F = (4/3) E* sqrt(R) delta^(3/2) [N] (Johnson 1985, section 4.2)."""
    return 4.0 / 3.0 * E_STAR * math.sqrt(radius_m) * depth_m**1.5


def sneddon_force(radius_m: float, depth_m: float) -> float:
    """F = 2 a E* delta [N] (Sneddon 1965)."""
    return 2.0 * radius_m * E_STAR * depth_m


def _check_hertz(method: str, block: Block, tolerance: float) -> float:
    """Press the sphere into ``block``; check the force and contact radius; the error."""
    shape = parse_probe_spec(f"sphere:{SPHERE_RADIUS_M}")
    assert isinstance(shape, SphereProbe)
    contact_radius = math.sqrt(SPHERE_RADIUS_M * HERTZ_DEPTH_M)
    cell = contact_radius / block.cells_per_radius
    mesh = _mesh(block, contact_radius)
    start = time.perf_counter()
    result, _ = _press(method, mesh, shape, HERTZ_DEPTH_M, cell)
    seconds = time.perf_counter() - start
    expected = hertz_force(SPHERE_RADIUS_M, HERTZ_DEPTH_M)
    error = _normal_force(result) / expected - 1.0
    print(f"Hertz {method}: {mesh.tet_count} tets, force error {error:+.4f}, {seconds:.1f} s")
    # The force acts along the pressing axis: no net sideways force, no torque.
    assert np.all(np.abs(result.force_world_n[:2]) < 1e-3 * expected)
    assert np.all(np.abs(result.torque_world_nm) < 1e-3 * expected * contact_radius)
    # Contact radius a = sqrt(R delta): the farthest loaded point is within a cell of it.
    reach = float(np.max(np.hypot(*result.contact_points_world_m[:, :2].T)))
    assert abs(reach - contact_radius) <= cell, (method, reach, contact_radius)
    if method == "penalty":  # stiff springs: the probe barely sinks in
        assert result.method_penetration_m < 0.01 * HERTZ_DEPTH_M
    else:
        assert result.method_penetration_m < 1e-4 * HERTZ_DEPTH_M
    assert abs(error) <= tolerance, (method, error)
    return error


@pytest.mark.parametrize("method", METHODS)
def test_sphere_force_follows_hertz(method: str) -> None:
    """Hertz (Johnson 1985, section 4.2), F = (4/3) E* sqrt(R) delta^(3/2), within 5 % on a
    test-sized block (R = 10 mm, delta = 0.1 mm, a / 3 cells under the contact; measured:
    LM +2.5 %, penalty +2.5 %, sliding prescribed +2.5 %, sticking prescribed +3.9 %:
    sticking nodes and stepwise entry)."""
    _check_hertz(method, FAST, 0.05)


@pytest.mark.slow
@pytest.mark.parametrize("method", ["lm", "penalty", "sliding"])
def test_sphere_force_follows_hertz_on_a_refined_block(method: str) -> None:
    """Hertz (Johnson 1985, section 4.2) within 2 % on a refined block (a / 5 cells under the
    contact, 124k tets; measured: LM +1.33 %, penalty +1.31 %, online prescribed
    displacement with sliding nodes +1.33 %)."""
    _check_hertz(method, REFINED, 0.02)


@pytest.mark.slow
def test_sticking_prescribed_sphere_force_on_a_refined_block() -> None:
    """Online prescribed displacement with sticking nodes (the default; ``sliding`` meets 2 %,
    above) against Hertz on the refined block: within 5 %, and an expected failure at 2 %
    (measured +3.2 %; +3.7 % before the entry fix below) for a reason of physics and one of
    the method.

    Its nodes stick to the probe: that is the no-slip contact, stiffer than frictionless
    Hertz for nu < 1/2. And a node enters only once the probe has passed it (it then joins
    where the probe first touched it), so the steps' size adds a stiffening that falls
    slowly with more steps. On the fast block the excess over LM is +1.3 % with 20 steps
    (it was +1.8 %, +1.3 % and +1.1 % with 20, 40 and 80 steps when entering nodes were
    projected onto the nearest probe point instead), so the no-slip part is about 1 % at
    most; with LM's +1.3 % discretisation error here, sticking comes to about 2 %.
    """
    error = _check_hertz("prescribed", REFINED, 0.05)
    if abs(error) > 0.02:
        pytest.xfail(f"prescribed (no-slip, stepwise entry) is {error:+.1%} off Hertz; see doc")


@pytest.mark.parametrize("method", METHODS)
def test_flat_punch_force_follows_sneddon(method: str) -> None:
    """Sneddon (1965), F = 2 a E* delta, within 5 % for a flat cylindrical punch pressed
    flat to delta = a / 100 (a = 1 mm; 26k tets, a / 3.4 cells).

    Online prescribed nodes stick to the face, which makes it the bonded punch, stiffer by
    (1 - nu) ln(3 - 4 nu) / (1 - 2 nu) = 1.029 (Mossakovskii 1954; Spence 1968); measured:
    LM +0.7 %, penalty +0.7 %, sticking prescribed +3.3 %, sliding prescribed +0.7 %.
    """
    radius = 1e-3
    depth = 0.01 * radius
    cell = radius / PUNCH.cells_per_radius
    shape = parse_probe_spec(f"cylinder:{radius},{radius}")
    assert isinstance(shape, CylinderProbe)
    mesh = _mesh(PUNCH, radius)
    result, _ = _press(method, mesh, shape, depth, cell)
    expected = sneddon_force(radius, depth)
    error = _normal_force(result) / expected - 1.0
    print(f"Sneddon {method}: {mesh.tet_count} tets, force error {error:+.4f}")
    # The face carries the load: every loaded point lies under it, and all of its nodes.
    assert np.hypot(*result.contact_points_world_m[:, :2].T).max() < radius
    assert result.contact_count == PUNCH_NODES
    assert abs(result.torque_world_nm).max() < 1e-3 * expected * radius
    assert abs(error) <= 0.05, (method, error)


def test_half_space_mesh_is_conforming_symmetric_and_fills_the_block() -> None:
    """The shell mesher: positive tets that exactly fill the box, no internal faces left
    unmatched (every boundary face lies on the box's surface), mirror symmetry."""
    extent = 0.05
    for coarsen in (None, 2.0):
        mesh = half_space_mesh(0.001, 0.008, extent, 1.5, coarsen_ratio=coarsen)
        volumes = mesh.tet_volumes()
        assert volumes.min() > 0.0
        assert volumes.sum() == pytest.approx(4.0 * extent**3, rel=1e-12)
        centres = mesh.nodes[boundary_faces(mesh.tets)].mean(axis=1)
        on_surface = (
            np.isclose(centres[:, 2], 0.0, atol=1e-12)
            | np.isclose(centres[:, 2], -extent)
            | np.isclose(np.abs(centres[:, 0]), extent)
            | np.isclose(np.abs(centres[:, 1]), extent)
        )
        assert on_surface.all()
        assert np.allclose(mesh.nodes[mesh.fixed_nodes, 2], -extent)
        tet_centres = np.round(mesh.nodes[mesh.tets].mean(axis=1) / 1e-9).astype(np.int64)
        mirrored = tet_centres * np.array([-1, 1, 1])
        assert {tuple(c) for c in tet_centres} == {tuple(c) for c in mirrored}
    coarse = half_space_mesh(0.001, 0.008, extent, 1.5, coarsen_ratio=2.0)
    fine = half_space_mesh(0.001, 0.008, extent, 1.5)
    assert coarse.tet_count < fine.tet_count
    with pytest.raises(MeshError):
        half_space_mesh(0.001, 0.05, 0.04)


def test_graded_ticks_keep_the_uniform_part_and_land_on_the_ends() -> None:
    ticks = graded_ticks(0.05, 0.001, 0.01, 1.3, uniform_m=0.004)
    np.testing.assert_allclose(ticks[:5], [0.0, 0.001, 0.002, 0.003, 0.004])
    assert ticks[-1] == pytest.approx(0.05)
    widths = np.diff(ticks)[4:]  # the graded part grows until it reaches the cap
    assert np.all(widths[1:] >= widths[:-1] * (1 - 1e-12))
    assert widths.max() <= 0.01
    centred = centred_ticks(0.05, 0.001, 0.01, 1.3, uniform_half_m=0.004)
    np.testing.assert_allclose(centred, np.concatenate([-ticks[:0:-1], ticks]))
