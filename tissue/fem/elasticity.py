"""Hyperelastic linear tets: strain energy, internal forces and tangent stiffness.

:class:`Elasticity` owns the element kernels and the assembly of one mesh with one set of
materials. Everything that does not depend on the deformation (shape-function gradients,
rest volumes, lumped masses, the sparse pattern and the maps from tets and ANP patches to
the stiffness entries) is built once in ``__init__``; every call then fills a fresh data
array for the same ``indices``/``indptr`` arrays.

Kinematics: linear tets with one integration point, F = Ds Dm^-1 (Dm^-1 and the rest
volumes stored), node-major DOFs (3 node + axis).

Laws (:class:`tissue.fem.material.MaterialLaw`), both written W(F) = mu/2 (I_C - 3) + psi(J):

* ``stable``: psi = lam'/2 (J - alpha)^2 - mu^2/(2 lam'), lam' = lam + mu,
  alpha = 1 + mu/lam' (Smith, de Goes & Kim 2018, ACM TOG 37(2):12; origin barrier removed
  as in Kim & Eberle 2022, SIGGRAPH course "Dynamic deformables"). The constant
  -mu^2/(2 lam') only shifts the energy so that it vanishes at rest; forces and tangent are
  those of the published energy. Finite and restoring for inverted tets (J <= 0).
* ``classic``: psi = -mu ln J + lam/2 (ln J)^2 (Bonet & Wood; SOFA's ``NeoHookean``).
  A tet with J <= 0 makes the energy ``inf`` and contributes zero force and stiffness
  (never NaN); it is counted in :attr:`ElasticState.inverted_count`.

Both linearise at rest to linear elasticity with Lamé parameters (mu, lam).

Anti-locking (:class:`AntiLocking`): ``anp`` is the average nodal pressure tet of Bonet &
Burton (1998, Commun Numer Meth Eng 14:437-449); see :class:`Elasticity` for the split.

PSD projection (``project_psd=True``): the negative eigenvalues of every tet's dP/dF are
clamped to zero using the analytic eigensystem of Smith et al. (2018), so that each
element Hessian V B^T (dP/dF) B is positive semi-definite; see
:func:`tissue.fem.kernels.negative_modes`.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from tissue.choices import Choice
from tissue.errors import TissueInputError
from tissue.fem import kernels as kern
from tissue.fem.material import MaterialLaw, TissueMaterials
from tissue.mesh import TetMesh


class AntiLocking(Choice):
    """Volumetric anti-locking treatment of the linear tets.

    Attributes:
        NONE: plain constant-strain tets (lock in near-incompressible bending).
        ANP: average nodal pressure (Bonet & Burton 1998): the volumetric energy is
            evaluated at nodes from nodal volume ratios, which relieves locking.
    """

    NONE = "none"
    ANP = "anp"

    @classmethod
    def noun(cls) -> str:
        return "anti-locking method"


@dataclass(frozen=True)
class ElasticState:
    """Strain energy and its derivatives at one configuration.

    Attributes:
        energy_j: total strain energy [J], zero at rest; ``math.inf`` if the classic law
            sees a tet with J <= 0.
        forces: internal elastic forces -dE/dx [N], shape (node_count, 3).
        stiffness: tangent stiffness d2E/dx2 [N/m], CSR, shape (dof_count, dof_count),
            node-major DOFs (3 node + axis); the same ``indices``/``indptr`` arrays on
            every call of one :class:`Elasticity`; ``None`` when not requested.
        min_volume_ratio: smallest J = det F over the tets.
        inverted_count: number of tets with J <= 0.
    """

    energy_j: float
    forces: NDArray[np.float64]
    stiffness: sp.csr_matrix | None
    min_volume_ratio: float
    inverted_count: int


class Elasticity:
    """Hyperelastic energy, forces and tangent of a tet mesh with per-region materials.

    Average nodal pressure (``anti_locking="anp"``). The energy is split into a part
    evaluated per tet and a volumetric part evaluated per node:

        E = sum_e V_e W_dev(F_e) + sum_a V_a U(J_a),
        J_a = sum_{e in a} (V_e/4) J_e / V_a,   V_a = sum_{e in a} V_e / 4,

    where the patch of node a holds the tets around a *of one region* (a node on a lesion
    boundary has one patch per region, so stiff and soft tissue are not averaged
    together). The per-tet part is the same law with lam set to zero, the per-node part
    carries lam:

    * stable: W_dev = stable law with (mu, 0) = mu/2 (I_C - 3) + mu/2 (J - 2)^2 - mu/2,
      U = lam/2 (J - 1)^2. Expanding both around J = 1 shows that for a homogeneous
      deformation (all J_a = J_e = J) the sum equals the stable law with (mu, lam)
      exactly: mu/2 (J-2)^2 - mu/2 + lam/2 (J-1)^2 = lam'/2 (J-alpha)^2 - mu^2/(2 lam').
      W_dev keeps a positive small-strain bulk modulus 2 mu/3 and stays inversion safe.
      (The alternative per-tet split mu/2 (I_C - 3) - mu (J - 1) has bulk modulus -mu/3,
      which makes the volume modes that the nodal average cannot see unstable.)
    * classic: W_dev = mu/2 (I_C - 3) - mu ln J, U = lam/2 (ln J)^2; again the sum is the
      classic law for homogeneous deformation.

    Hence the rest state is stress free, the patch test is passed and the small-strain
    response to homogeneous strain is linear elasticity with (mu, lam). This is a true
    energy, so forces and tangent are its exact derivatives: with dJ_a/dx = sum_e w_e
    cof F_e G_e (w_e = V_e/(4 V_a)),

        forces = -sum_e V_e [mu F_e + (psi_dev'(J_e) + p_e) cof F_e] G_e,
        p_e = (1/4) sum_{a in e} U'(J_a)   (the averaged nodal pressure),
        K = sum_e K_e(psi' = psi_dev' + p_e, psi'' = psi_dev'')
            + sum_a V_a U''(J_a) dJ_a/dx dJ_a/dx^T.

    The d2J_e/dx2 terms of the nodal energy have moved into the tets through p_e, so the
    nodal terms are rank one. The pattern couples nodes that share a patch (two rings).
    With ``project_psd`` each tet's dP/dF (built with psi_dev' + p_e, psi_dev'') is
    projected as for the plain tets and a negative U'' (classic law beyond J_a = e) is
    clamped to zero; the sum is then PSD, though not the nearest PSD matrix of the whole
    patch Hessian.

    Args:
        mesh: the tet mesh (rest positions [m], tets, regions).
        materials: per-region materials and the law.
        anti_locking: ``"none"`` or ``"anp"`` (or an :class:`AntiLocking`).
        inversion_barrier: (stable law) a volume ratio J_b in [0, 1): below it every tet
            gains the barrier (mu + lam) (-(J - J_b)^2 ln(J / J_b)), which grows without
            bound as J -> 0 and makes J <= 0 an infinite energy, so that a line search never
            accepts an inverted tet (see :func:`tissue.fem.kernels.element_pass`); 0 (the
            default) leaves the law as published. The stable law is finite for inverted tets
            by design; the barrier is what keeps a robust solve's tets uninverted when a
            Dirichlet condition or a point-like contact drives a coarse tet flat.

    Attributes:
        node_count, dof_count, tet_count: sizes.
        lumped_mass: lumped nodal masses sum_e rho_e V_e / 4 [kg], shape (node_count,).
        rest_volume_m3: total rest volume [m^3].
        law: the material law; anti_locking: the anti-locking method.
    """

    def __init__(
        self,
        mesh: TetMesh,
        materials: TissueMaterials,
        anti_locking: AntiLocking | str = AntiLocking.NONE,
        inversion_barrier: float = 0.0,
    ) -> None:
        self.anti_locking = AntiLocking.parse(anti_locking)
        if not (math.isfinite(inversion_barrier) and 0.0 <= inversion_barrier < 1.0):
            raise TissueInputError(
                "inversion_barrier is a volume ratio J in [0, 1) (0: off); got "
                f"{inversion_barrier!r}"
            )
        self.inversion_barrier = float(inversion_barrier)
        self.materials = materials
        self.law = MaterialLaw.parse(materials.law)
        self._law_code = kern.LAW_STABLE if self.law is MaterialLaw.STABLE else kern.LAW_CLASSIC
        self.mesh = mesh
        # Internally the tets are sorted along a Morton curve of their nodes and the node
        # rows are gathered in Morton order: the four visits of a tet then fall close in
        # time (cache reuse). Results are returned in the mesh's own tet order.
        rank = _morton_rank(mesh.nodes)
        self._node_order = np.argsort(rank).astype(np.int64)
        self._tet_order = np.argsort(rank[mesh.tets].min(axis=1), kind="stable")
        tets = np.ascontiguousarray(mesh.tets[self._tet_order], dtype=np.int64)
        region = np.asarray(mesh.region, dtype=np.int64)[self._tet_order]
        self._region = region
        self._tets = tets
        self.node_count = mesh.node_count
        self.dof_count = 3 * self.node_count
        self.tet_count = mesh.tet_count
        grads, volume = kern.shape_gradients(mesh.nodes, tets)
        self._grads = grads
        self._volume = volume
        self._grad_dots = kern.rest_grad_dots(grads)
        mu, lam, rho = materials.per_tet(region)
        self._mu = np.ascontiguousarray(mu)
        # ANP moves lam to the nodes: the per-tet law runs with lam = 0.
        anp = self.anti_locking is AntiLocking.ANP
        self._lam_tet = np.zeros_like(lam) if anp else np.ascontiguousarray(lam)
        # The barrier's modulus: the law's own volumetric stiffness lam' = lam + mu.
        self._barrier_modulus = np.ascontiguousarray(mu + lam)
        self.rest_volume_m3 = float(volume.sum())
        self.lumped_mass = np.bincount(
            tets.ravel(), weights=np.repeat(rho * volume / 4.0, 4), minlength=self.node_count
        )

        n = self.node_count
        order = np.argsort(tets.ravel(), kind="stable")
        self._incidence_ptr = _counts_to_ptr(np.bincount(tets.ravel(), minlength=n))
        self._incidence_tet = (order // 4).astype(np.int64)
        self._incidence_local = (order % 4).astype(np.int64)

        if anp:
            self._build_patches(tets, volume, lam)
            block_ptr, block_cols = self._patch_block_pattern()
        else:
            rows = np.repeat(tets, 4, axis=1).ravel()
            cols = np.tile(tets, (1, 4)).ravel()
            keys = np.unique(rows * n + cols)
            block_rows = keys // n
            block_cols = keys % n
            block_ptr = _counts_to_ptr(np.bincount(block_rows, minlength=n))
        self._block_ptr = block_ptr
        self._block_cols = block_cols
        block_rows = np.repeat(np.arange(n, dtype=np.int64), np.diff(block_ptr))
        keys = block_rows * n + block_cols
        # Block (c, b) of each block (b, c): the gather stores upper blocks twice.
        self._block_mirror = np.searchsorted(keys, block_cols * n + block_rows)
        if not np.array_equal(keys[self._block_mirror], block_cols * n + block_rows):
            raise AssertionError("the stiffness block pattern is not symmetric")
        query = np.repeat(tets, 4, axis=1) * n + np.tile(tets, (1, 4))
        pos = np.searchsorted(keys, query) - block_ptr[np.repeat(tets, 4, axis=1)]
        # Each stiffness block's tet contributions (the gather sums them in registers).
        self._contribution_ptr, self._contributions = kern.block_contributions(
            tets, block_ptr, pos.reshape(-1, 4, 4)
        )
        if anp:
            self._patch_pair_pos = np.empty(int(self._patch_pair_ptr[-1]), dtype=np.int32)
            kern.patch_pair_positions(
                self._patch_node_ptr,
                self._patch_nodes,
                block_ptr,
                block_cols,
                self._patch_pair_ptr,
                self._patch_pair_pos,
            )
        self._indices, self._indptr = _block_csr_structure(block_ptr, block_cols)
        self.nnz = int(self._indices.shape[0])
        self._csr_template: sp.csr_matrix | None = None

        # Per-tet work arrays, overwritten by every call (calls hold the GIL: no races).
        t = self.tet_count
        self._coef = np.empty((t, 3))
        self._energy = np.empty(t)
        self._ratio = np.empty(t)
        self._tet_forces = np.empty((t, 12))
        self._cofactor_grads = np.empty((t, 12))
        self._pair_vector = np.empty((t, 18))
        self._no_pressure = np.zeros(t)
        # Mode buffers are large (t x 72 doubles): allocated on the first projected call.
        self._mode_count = np.zeros(1, dtype=np.int64)
        self._mode_vector = np.zeros((1, kern.MAX_NEGATIVE_MODES, 12))

    # ------------------------------------------------------------------------------------
    # Public API

    def evaluate(
        self,
        positions: NDArray[np.float64],
        *,
        tangent: bool = True,
        project_psd: bool = False,
    ) -> ElasticState:
        """Energy, forces and (optionally) the tangent stiffness at ``positions``.

        Args:
            positions: node positions [m], shape (node_count, 3).
            tangent: also assemble the stiffness d2E/dx2 [N/m].
            project_psd: clamp each tet's negative dP/dF eigenvalues (and negative nodal
                U'' with ANP) so that the returned stiffness is positive semi-definite.
                Forces and energy are unchanged.

        Returns:
            the :class:`ElasticState`.
        """
        x = self._check_positions(positions)
        project = bool(project_psd) and bool(tangent)
        stage = kern.STAGE_TANGENT if tangent else kern.STAGE_FORCES
        energy = self._element_stage(x, project, stage)
        forces = np.empty((self.node_count, 3))
        stiffness = None
        if not tangent:
            kern.gather_forces(
                self._incidence_ptr,
                self._incidence_tet,
                self._incidence_local,
                self._tet_forces,
                self._node_order,
                forces,
            )
        else:
            data = np.empty(self.nnz)  # every entry is written
            kern.gather_elements(
                self._block_ptr,
                self._block_cols,
                self._block_mirror,
                self._node_order,
                self._contribution_ptr,
                self._contributions,
                self._grad_dots,
                self._coef,
                self._cofactor_grads,
                self._pair_vector,
                project,
                self._mode_count,
                self._mode_vector,
                self._tet_forces,
                forces,
                data,
            )
            if self.anti_locking is AntiLocking.ANP:
                kern.anp_patch_gradients(
                    self._cofactor_grads,
                    self._patch_tet_ptr,
                    self._patch_tet,
                    self._patch_tet_weight,
                    self._patch_tet_local,
                    self._patch_node_ptr,
                    self._patch_gradient,
                )
                kern.anp_gather_blocks(
                    self._node_patch_ptr,
                    self._node_patch,
                    self._node_patch_local,
                    self._patch_node_ptr,
                    self._patch_pair_ptr,
                    self._patch_pair_pos,
                    self._patch_gradient,
                    self._patch_ddpsi,
                    self._block_ptr,
                    self._node_order,
                    data,
                )
            stiffness = self._csr(data)
        ratio = self._ratio
        return ElasticState(
            energy_j=energy,
            forces=forces,
            stiffness=stiffness,
            min_volume_ratio=float(ratio.min()),
            inverted_count=int(np.count_nonzero(ratio <= 0.0)),
        )

    def energy(self, positions: NDArray[np.float64]) -> float:
        """Total strain energy [J] at node positions [m], shape (node_count, 3)."""
        return self._element_stage(self._check_positions(positions), False, kern.STAGE_ENERGY)

    def energy_and_min_volume_ratio(self, positions: NDArray[np.float64]) -> tuple[float, float]:
        """(total strain energy [J], smallest det F) at node positions [m], in one pass."""
        energy = self._element_stage(self._check_positions(positions), False, kern.STAGE_ENERGY)
        return energy, float(self._ratio.min())

    def forces(self, positions: NDArray[np.float64]) -> NDArray[np.float64]:
        """Internal elastic forces -dE/dx [N], shape (node_count, 3), at positions [m]."""
        return self.evaluate(positions, tangent=False).forces

    def volume_ratios(self, positions: NDArray[np.float64]) -> NDArray[np.float64]:
        """J = det F per tet, shape (tet_count,), at node positions [m] (node_count, 3)."""
        internal = np.empty(self.tet_count)
        kern.volume_ratios(self._check_positions(positions), self._tets, self._grads, internal)
        out = np.empty(self.tet_count)
        out[self._tet_order] = internal
        return out

    # ------------------------------------------------------------------------------------
    # Internals

    def _check_positions(self, positions: NDArray[np.float64]) -> NDArray[np.float64]:
        x = np.ascontiguousarray(positions, dtype=np.float64)
        if x.shape != (self.node_count, 3):
            raise TissueInputError(
                f"positions must have shape (node_count, 3) = ({self.node_count}, 3) in metres; "
                f"got {x.shape}"
            )
        return x

    def _element_stage(self, x: NDArray[np.float64], project: bool, stage: int) -> float:
        """Run the ANP patch pass (if any) and the element pass up to ``stage`` (a
        ``tissue.fem.kernels.STAGE_*``); return the energy [J]."""
        if project and self._mode_count.shape[0] != self.tet_count:
            t = self.tet_count
            self._mode_count = np.zeros(t, dtype=np.int64)
            self._mode_vector = np.zeros((t, kern.MAX_NEGATIVE_MODES, 12))
        energy = 0.0
        pressure = self._no_pressure
        if self.anti_locking is AntiLocking.ANP:
            kern.volume_ratios(x, self._tets, self._grads, self._ratio)
            kern.anp_patch_pass(
                self._ratio,
                self._patch_tet_ptr,
                self._patch_tet,
                self._patch_tet_weight,
                self._patch_volume,
                self._patch_lam,
                self._law_code,
                project,
                self._patch_ratio,
                self._patch_dpsi,
                self._patch_ddpsi,
                self._patch_energy,
            )
            pressure = 0.25 * self._patch_dpsi[self._tet_patch].sum(axis=1)
            energy += float(self._patch_energy.sum())
        kern.element_pass(
            x,
            self._tets,
            self._grads,
            self._volume,
            self._mu,
            self._lam_tet,
            pressure,
            self._law_code,
            self.inversion_barrier,
            self._barrier_modulus,
            project,
            stage,
            self._coef,
            self._energy,
            self._ratio,
            self._tet_forces,
            self._cofactor_grads,
            self._pair_vector,
            self._mode_count,
            self._mode_vector,
        )
        energy += float(self._energy.sum())
        return energy if math.isfinite(energy) else math.inf

    def _csr(self, data: NDArray[np.float64]) -> sp.csr_matrix:
        """A new CSR matrix object with ``data`` on the shared pattern (index arrays shared)."""
        if self._csr_template is None:
            template = sp.csr_matrix(
                (data, self._indices, self._indptr), shape=(self.dof_count, self.dof_count)
            )
            # scipy may not copy index arrays of the right dtype; make the sharing explicit.
            template.indices = self._indices
            template.indptr = self._indptr
            template.has_sorted_indices = True
            template.has_canonical_format = True
            # Only its pattern is copied: holding no values, it keeps no matrix alive.
            template.data = np.zeros(0)
            self._csr_template = template
        # A shallow copy of a checked matrix of this pattern, given the new values: 2 against
        # 12 us for scipy's constructor and its checks, twice a step.
        matrix = copy.copy(self._csr_template)
        matrix.data = data
        return matrix

    def _build_patches(
        self, tets: NDArray[np.int64], volume: NDArray[np.float64], lam: NDArray[np.float64]
    ) -> None:
        """ANP patches (node, region), their tets, nodes and volumes; maps for the gather."""
        n = self.node_count
        region = self._region
        region_count = int(region.max()) + 1
        patch_key = tets * region_count + region[:, None]
        unique_keys, tet_patch = np.unique(patch_key.ravel(), return_inverse=True)
        tet_patch = tet_patch.reshape(-1, 4).astype(np.int64)
        patch_count = unique_keys.shape[0]
        quarter = np.repeat(volume / 4.0, 4)
        patch_volume = np.bincount(tet_patch.ravel(), weights=quarter, minlength=patch_count)
        # lam is constant within a region; the volume average only guards the type.
        patch_lam = (
            np.bincount(tet_patch.ravel(), weights=np.repeat(lam, 4) * quarter) / patch_volume
        )
        order = np.argsort(tet_patch.ravel(), kind="stable")
        patch_tet = (order // 4).astype(np.int64)
        patch_of_entry = tet_patch.ravel()[order]
        self._tet_patch = tet_patch
        self._patch_volume = patch_volume
        self._patch_lam = patch_lam
        self._patch_tet_ptr = _counts_to_ptr(np.bincount(patch_of_entry, minlength=patch_count))
        self._patch_tet = patch_tet
        self._patch_tet_weight = volume[patch_tet] / (4.0 * patch_volume[patch_of_entry])

        # Patch node lists: every node of every tet of the patch, sorted, unique.
        pair_keys = np.unique((np.repeat(tet_patch, 4, axis=1) * n + np.tile(tets, (1, 4))).ravel())
        self._patch_nodes = (pair_keys % n).astype(np.int64)
        node_entry_patch = pair_keys // n
        self._patch_node_ptr = _counts_to_ptr(np.bincount(node_entry_patch, minlength=patch_count))
        local = np.searchsorted(pair_keys, patch_of_entry[:, None] * n + tets[patch_tet])
        self._patch_tet_local = (local - self._patch_node_ptr[patch_of_entry][:, None]).astype(
            np.int64
        )
        by_node = np.argsort(self._patch_nodes, kind="stable")
        self._node_patch_ptr = _counts_to_ptr(np.bincount(self._patch_nodes, minlength=n))
        self._node_patch = node_entry_patch[by_node].astype(np.int64)
        self._node_patch_local = (by_node - self._patch_node_ptr[self._node_patch]).astype(np.int64)
        sizes = np.diff(self._patch_node_ptr)
        self._patch_pair_ptr = _counts_to_ptr(sizes * sizes)
        self._patch_gradient = np.empty((self._patch_nodes.shape[0], 3))
        self._patch_ratio = np.empty(patch_count)
        self._patch_dpsi = np.empty(patch_count)
        self._patch_ddpsi = np.empty(patch_count)
        self._patch_energy = np.empty(patch_count)

    def _patch_block_pattern(self) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """Node graph of ANP: nodes coupled when some patch holds both (P^T P)."""
        entries = self._patch_nodes.shape[0]
        patch_count = self._patch_node_ptr.shape[0] - 1
        incidence = sp.csr_matrix(
            (np.ones(entries), self._patch_nodes, self._patch_node_ptr),
            shape=(patch_count, self.node_count),
        )
        graph = (incidence.T @ incidence).tocsr()
        graph.sort_indices()
        return graph.indptr.astype(np.int64), graph.indices.astype(np.int64)


def _morton_rank(points: NDArray[np.float64]) -> NDArray[np.int64]:
    """Rank of each point [m], shape (count, 3), along a 3-D Morton (Z-order) curve."""
    low = points.min(axis=0)
    extent = max(float(np.max(points.max(axis=0) - low)), 1e-300)
    cells = np.minimum(((points - low) / extent * 1024.0).astype(np.int64), 1023)
    code = np.zeros(points.shape[0], dtype=np.int64)
    for bit in range(10):
        for axis in range(3):
            code |= ((cells[:, axis] >> bit) & 1) << (3 * bit + axis)
    rank = np.empty(points.shape[0], dtype=np.int64)
    rank[np.argsort(code, kind="stable")] = np.arange(points.shape[0])
    return rank


def _counts_to_ptr(counts: NDArray[np.int64]) -> NDArray[np.int64]:
    ptr = np.zeros(counts.shape[0] + 1, dtype=np.int64)
    np.cumsum(counts, out=ptr[1:])
    return ptr


def _block_csr_structure(
    block_ptr: NDArray[np.int64], block_cols: NDArray[np.int64]
) -> tuple[NDArray[np.integer], NDArray[np.integer]]:
    """CSR indices/indptr of a 3x3-block pattern, in the layout of
    :mod:`tissue.fem.kernels.assembly`."""
    node_count = block_ptr.shape[0] - 1
    block_count = block_cols.shape[0]
    width = np.diff(block_ptr)
    index_type = np.int32 if 9 * block_count < 2**31 - 1 else np.int64
    indptr = np.empty(3 * node_count + 1, dtype=index_type)
    for i in range(3):
        indptr[i : 3 * node_count : 3] = 9 * block_ptr[:-1] + 3 * i * width
    indptr[-1] = 9 * block_count
    block_row = np.repeat(np.arange(node_count), width)
    position = np.arange(block_count) - block_ptr[block_row]
    indices = np.empty(9 * block_count, dtype=index_type)
    for i in range(3):
        for k in range(3):
            slot = 9 * block_ptr[block_row] + 3 * i * width[block_row] + 3 * position + k
            indices[slot] = 3 * block_cols + k
    return indices, indptr
