"""What the three FE contact strategies share: the simulator, and finding contacts."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numba
import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from tissue.contact.base import ContactModel
from tissue.contact.surface_points import SurfacePoints, boundary_surface, contact_surface
from tissue.contact.wrench_stiffness import ContactConstraints
from tissue.errors import ConfigError
from tissue.fem.material import TissueMaterials
from tissue.mesh import TetMesh, node_dofs
from tissue.probe import Probe, ProbeShape
from tissue.profile import profile_choices
from tissue.sim.integrator import IncrementalPotential
from tissue.sim.simulator import SimulationConfig, TissueSimulator
from tissue.sim.solvers import DirectFactorizer, Factorization

# In robust mode, contact acts on the volume's boundary nodes instead of the collision
# surface once the boundary has this many times more points. The collision surface (~500
# points, as the paper's 1,004 triangles) embedded in a fine volume hands each point's force
# to the four nodes of one small tet, the likely reason why on the 105k-tet phantom LM and
# penalty both inverted a tet at the same step, 19 mm deep (fine_105k); with the boundary's
# 5,558 points both passed all 20 mm (LM 1.2 s per step, measured here). The same happened
# on the 26k-tet level (2,126 boundary points, 4.2 x) at 25-30 mm on the study's paths: LM
# and penalty inverted a surface tet at the probe's edge at the same step (lesion 2: 87 %);
# on the boundary both finish (penalty lesion 2, LM lesion 1: 100 %; LM's median step 1.29
# s against 1.09 s, two runs on a differently loaded machine, so a rough price only). The
# 26k, 105k and 176k levels reach the ratio; 12,861 (2.3 x) does not.
FINE_BOUNDARY_RATIO = 4.0


def model_surface(mesh: TetMesh, config: SimulationConfig) -> SurfacePoints:
    """The points an FE contact model (LM, penalty) acts on for ``mesh`` under ``config``:
    the collision surface, or where the profile chooses ``fine_boundary_contact`` the volume's
    boundary where it is at least :data:`FINE_BOUNDARY_RATIO` times finer.
    """
    surface = contact_surface(mesh)
    if not profile_choices(config.mode).fine_boundary_contact or mesh.collision_surface is None:
        return surface
    boundary = boundary_surface(mesh)
    return boundary if boundary.count >= FINE_BOUNDARY_RATIO * surface.count else surface


@dataclass(frozen=True)
class Contacts:
    """Collision-surface points near or inside the probe.

    Attributes:
        points: indices into the surface points, (k,).
        positions: their positions [m], (k, 3).
        distance: signed distance to the probe surface [m], (k,) (negative inside).
        normal: the probe's outward normal at the closest point, (k, 3).
    """

    points: NDArray[np.int64]
    positions: NDArray[np.float64]
    distance: NDArray[np.float64]
    normal: NDArray[np.float64]

    @property
    def count(self) -> int:
        return int(self.points.size)


#: A surface point whose embedding weights on free (not fixed) nodes sum, in magnitude, to no
#: more than this is immovable (:func:`movable_points`). Its compliance in an LM contact is
#: then below w^2 ~ 1e-6 of its nodes', near the LCP's regularisation (1e-8 of the mean
#: compliance), which would set its force instead of the tissue. On every phantom level
#: (623-26,220 tets) the points below it are the collision surface's points on the fixed
#: chest-wall plane z = 0 (about 190 of 512), with free weights 0 or round-off (<= 1e-9);
#: every other point's is >= 0.18.
IMMOVABLE_WEIGHT = 1e-3


def movable_points(surface: SurfacePoints, fixed_nodes: NDArray[np.int64]) -> NDArray[np.bool_]:
    """Which surface points the free dofs can move, (point_count,) bool: those whose
    embedding weights on the nodes not in ``fixed_nodes`` sum, in magnitude, to more than
    :data:`IMMOVABLE_WEIGHT`.

    An immovable point's gap row (:func:`constraint_rows`) is empty (or all but): no
    contact force can push it out of the probe. As a Lagrange-multiplier constraint its
    compliance H A^-1 H^T is 0, so once the probe overlaps it the LCP has no solution and
    PGS returns the penetration over the regularisation, a force that acts on nothing (9e7
    N for 0.029 mm on the 1,363-tet phantom) and a step that cannot converge. LM leaves
    such points out of its constraints, as prescribed displacement leaves the fixed nodes
    out of its node set.
    """
    nodes, weights = surface.embedding.tet_nodes, surface.embedding.weights
    free_weight = np.abs(np.where(np.isin(nodes, fixed_nodes), 0.0, weights)).sum(axis=1)
    return free_weight > IMMOVABLE_WEIGHT


def detect_contacts(
    surface: SurfacePoints,
    node_positions: NDArray[np.float64],
    probe: Probe,
    alarm_distance_m: float,
    movable: NDArray[np.bool_] | None = None,
) -> Contacts:
    """Collision detection: surface points closer to the probe than ``alarm_distance_m`` [m].

    Points outside the probe's bounding sphere (plus the alarm distance) are skipped before
    the signed distance is evaluated: the probe touches a small part of the skin.
    ``movable`` (point_count,) bool, if given: only those points (:func:`movable_points`).
    """
    near, positions = surface.near(node_positions, probe, alarm_distance_m)
    if movable is not None:
        chosen = movable[near]
        near, positions = near[chosen], positions[chosen]
    if near.size == 0:
        empty = np.zeros((0, 3))
        return Contacts(near, empty, np.zeros(0), empty)
    distance, normal = probe.signed_distance_world(positions)
    keep = distance < alarm_distance_m
    return Contacts(near[keep], positions[keep], distance[keep], normal[keep])


def constraint_rows(
    surface: SurfacePoints, contacts: Contacts, dof_count: int, constrained: NDArray[np.bool_]
) -> sp.csr_matrix:
    """Jacobian of the contact gaps: row i is n_i^T times the embedding of point i.

    Shape (k, dof_count); entries at constrained dofs are dropped (they cannot move).
    """
    count = contacts.count
    indptr = np.empty(count + 1, dtype=np.int32)
    indices = np.empty(12 * count, dtype=np.int32)
    data = np.empty(12 * count)
    _gap_rows(
        surface.embedding.tet_nodes,
        surface.embedding.weights,
        contacts.points,
        contacts.normal,
        constrained,
        indptr,
        indices,
        data,
    )
    stored = int(indptr[-1])
    matrix = sp.csr_matrix(
        (data[:stored], indices[:stored], indptr), shape=(count, dof_count), copy=False
    )
    matrix.has_sorted_indices = True  # and no duplicates: a tet's four nodes differ
    return matrix


def dense_transpose(rows: sp.csr_matrix) -> NDArray[np.float64]:
    """rows^T, dense and column-major, (n, k), for the gap rows (k, n) of
    :func:`constraint_rows`: ``rows.T.toarray()``, whose entries it writes (the rows hold no
    duplicates) without scipy's transpose and conversion (~90 Python-level calls)."""
    count, size = rows.shape
    dense = np.zeros((size, count), order="F")
    row_of_entry = np.repeat(np.arange(count), np.diff(rows.indptr))
    dense[rows.indices, row_of_entry] = rows.data
    return dense


def transpose_product(rows: sp.csr_matrix, values: NDArray[np.float64]) -> NDArray[np.float64]:
    """rows^T @ values for CSR ``rows`` (k, n) and ``values`` (k,): shape (n,).

    The same sums in the same order as scipy's product with ``rows.T`` (bitwise), without
    building the transposed matrix (~13 us a call, several calls a step).
    """
    out = np.zeros(rows.shape[1])
    _add_transpose_product(rows.indptr, rows.indices, rows.data, values, out)
    return out


@numba.njit(cache=True)
def _add_transpose_product(indptr, indices, data, values, out):  # pragma: no cover - compiled
    for r in range(indptr.shape[0] - 1):
        for k in range(indptr[r], indptr[r + 1]):
            out[indices[k]] += data[k] * values[r]


@numba.njit(cache=True)
def _gap_rows(
    tet_nodes, weights, points, normals, constrained, indptr, indices, data
):  # pragma: no cover - compiled
    """CSR rows of :func:`constraint_rows`, columns sorted in each row (a compiled loop: a
    sparse matrix built from triplets with scipy took ~60 us, a few times a step).

    Row r holds w_a n_i at dof 3 t_a + i for the four nodes t_a of point ``points[r]``'s tet,
    leaving out constrained dofs.
    """
    stored = 0
    indptr[0] = 0
    for r in range(points.shape[0]):
        p = points[r]
        start = stored
        for a in range(4):
            for i in range(3):
                dof = 3 * tet_nodes[p, a] + i
                if constrained[dof]:
                    continue
                value = weights[p, a] * normals[r, i]
                # Insertion into the row's sorted columns (at most 12).
                k = stored
                while k > start and indices[k - 1] > dof:
                    indices[k] = indices[k - 1]
                    data[k] = data[k - 1]
                    k -= 1
                indices[k] = dof
                data[k] = value
                stored += 1
        indptr[r + 1] = stored


class FEContactModel(ContactModel):
    """A contact strategy on the FE tissue simulator.

    Args:
        mesh: the tissue mesh.
        probe_shape: the rigid tool.
        materials: per-region materials (defaults as the published scene).
        config: how the tissue is simulated (``mode="paper"`` or ``"robust"``).
        params: the strategy's parameters (its ``params_type``), or None for defaults.
    """

    #: The strategy's parameter dataclass; ``params=None`` builds its defaults.
    params_type: ClassVar[type] = type(None)
    has_tangent: ClassVar[bool] = True

    def __init__(
        self,
        mesh: TetMesh,
        probe_shape: ProbeShape,
        materials: TissueMaterials | None = None,
        config: SimulationConfig | None = None,
        params: Any = None,
    ) -> None:
        super().__init__(mesh, probe_shape)
        self.sim = TissueSimulator(mesh, materials, config)
        self.surface = model_surface(mesh, self.sim.config)
        if params is not None and not isinstance(params, self.params_type):
            raise ConfigError(
                f"{type(self).__name__} takes {self.params_type.__name__} parameters; "
                f"got {type(params).__name__}"
            )
        self.params = params if params is not None else self.params_type()
        self._tangent_factorizer: DirectFactorizer | None = None

    @property
    def node_positions(self) -> NDArray[np.float64]:
        return self.sim.positions

    @property
    def node_velocities(self) -> NDArray[np.float64]:
        return self.sim.velocities

    @property
    def dt(self) -> float:
        return self.sim.config.tissue_dt

    def _reset_tissue(self) -> None:
        self.sim.reset()

    def drop_caches(self) -> None:
        self.sim.integrator.drop_caches()

    def _loaded(self) -> bool:
        gravity = self.sim.config.gravity_m_s2
        return gravity is not None and any(g != 0.0 for g in gravity)

    def _advance_asleep(self, h: float, pieces: int) -> None:
        # The simulator's clock runs on as the sub-motions' commits would run it.
        sim = self.sim
        time_s = sim.time_s
        for _ in range(pieces):
            time_s += h
        sim.set_clock(time_s)

    def step_tangent(self) -> tuple[Factorization, NDArray[np.bool_]]:
        """A factorisation of the tissue's static tangent at the present state (the elastic
        stiffness K(x), contact left out, the fixed base eliminated) and the eliminated dofs,
        (3N,) bool: for :func:`tissue.contact.wrench_stiffness.wrench_stiffness`. Leaves the
        step's own solver untouched."""
        sim = self.sim
        integrator = sim.integrator
        fixed = node_dofs(self.mesh.fixed_nodes)
        x = sim.positions.copy()
        potential = IncrementalPotential(
            integrator,
            x,
            sim.velocities.copy(),
            self.dt,
            fixed,
            x.reshape(-1)[fixed],
            (),
            quasi_static=True,
        )
        system = potential.hessian_system(x.reshape(-1), np.zeros(x.size), project=False)
        if self._tangent_factorizer is None:
            self._tangent_factorizer = DirectFactorizer(integrator.solver.config.direct_backend)
        factorization, _ = self._tangent_factorizer.factorize(system.matrix, system.constrained)
        return factorization, system.constrained

    def _constraint_rows(
        self,
        surface: SurfacePoints,
        points: NDArray[np.int64],
        directions: NDArray[np.float64],
        compliance_m_per_n: float,
    ) -> ContactConstraints:
        """Constraints at surface ``points`` (indices) along ``directions`` (k, 3)."""
        positions = surface.positions_of(self.sim.positions, points)
        contacts = Contacts(points, positions, np.zeros(points.size), directions)
        constrained = np.zeros(self.mesh.dof_count, dtype=bool)
        constrained[node_dofs(self.mesh.fixed_nodes)] = True
        rows = constraint_rows(surface, contacts, self.mesh.dof_count, constrained)
        return ContactConstraints(
            rows, positions, directions, np.full(points.size, compliance_m_per_n)
        )

    def _snapshot_tissue(self) -> dict[str, Any]:
        sim = self.sim
        return {
            "positions": sim.positions.copy(),
            "velocities": sim.velocities.copy(),
            "tissue_time_s": sim.time_s,
            "boundary": sim.boundary_state(),
            **self._snapshot_contact(),
        }

    def _restore_tissue(self, snapshot: dict[str, Any]) -> None:
        sim = self.sim
        sim.set_state(snapshot["positions"], snapshot["velocities"], snapshot["tissue_time_s"])
        sim.set_boundary_state(snapshot["boundary"])
        self._restore_contact(snapshot)

    def _snapshot_contact(self) -> dict[str, Any]:
        """The strategy's own state beyond the tissue's (copied); none by default."""
        return {}

    def _restore_contact(self, snapshot: dict[str, Any]) -> None:
        """Adopt what :meth:`_snapshot_contact` returned."""

    def surface_points_on_probe(
        self, contacts: Contacts, magnitudes: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Contact points [m] and forces on the probe [N] from force magnitudes on the tissue."""
        active = magnitudes > 0.0
        forces_on_probe = -magnitudes[active, None] * contacts.normal[active]
        return contacts.positions[active], forces_on_probe
