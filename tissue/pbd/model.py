"""The XPBD tissue as a contact model: :class:`PBDContact` builds the constraints and runs a step.

Construction renumbers tets and nodes for the sweep (see
:func:`~tissue.pbd.two_domain_order`), builds masses, compliances and contact points (the
:class:`SweepArrays` the step's kernels read, :attr:`PBDContact.arrays`), and loads every
compiled kernel; :meth:`PBDContact._advance` runs a tissue step's substeps and turns the
contact multipliers into forces (see :mod:`tissue.pbd`).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from typing import Any

import numba as nb
import numpy as np
from numpy.typing import NDArray

from tissue.contact.base import ContactModel
from tissue.contact.registry import register_contact
from tissue.errors import ConfigError, TissueInputError
from tissue.fem.material import TissueMaterials
from tissue.mesh import TetMesh

# The sweep kernels' module: the step looks project_tets and project_tets_two_domains up on it
# at each step, so replacing them there (as the failure tests do) reaches a built model.
from tissue.pbd import sweep as sweep_kernels
from tissue.pbd.config import PBDConfig
from tissue.pbd.contact import (
    choose_contact_points,
    contact_zone_sweeps,
    points_near,
    project_contacts,
)
from tissue.pbd.substep import end_substep, start_substep
from tissue.pbd.sweep import two_domain_order
from tissue.pbd.volume import (
    PARALLEL_SCREEN_TETS,
    count_below_volume_floor,
    enforce_volume_floor,
    min_volume_ratio,
)
from tissue.probe import ProbeShape, unit_quat_to_matrix
from tissue.profile import profile_choices
from tissue.status import StepStatus


@dataclass(frozen=True)
class SweepArrays:
    """The arrays a :class:`PBDContact` step's compiled kernels read, in step numbering.

    Step numbering: the tets in sweep order (:func:`~tissue.pbd.two_domain_order`), the nodes
    in the order those tets first use them; ``node_order`` maps back to the mesh's. Built
    once with the model; the step never writes them. They are the model's own arrays, not copies
    (a kernel given read-only arrays would compile another specialisation): read them, pass
    them to the kernels of :mod:`tissue.pbd.sweep`, :mod:`~tissue.pbd.contact`,
    :mod:`~tissue.pbd.volume` and :mod:`~tissue.pbd.substep`, never write them.

    Attributes:
        node_order: mesh node of each step node, (node_count,) int64.
        step_node_of_mesh: step node of each mesh node (the inverse), (node_count,) int64.
        tets: node indices (step numbering) of each tet in sweep order, (tet_count, 4) int64.
        all_tets: ``arange(tet_count)``, every tet in sweep order (int64).
        sweep_bounds: the two domains' and the separator's limits in ``all_tets``, (4,)
            int64 (:func:`~tissue.pbd.two_domain_order`'s ``bounds``).
        dm_inv: inverse rest edge matrices D_m^-1 [1/m], (tet_count, 3, 3).
        inv_det_dm: 1 / det D_m [1/m^3], (tet_count,).
        rest_volume: rest tet volumes [m^3], (tet_count,).
        inv_mass: inverse lumped masses [1/kg], (node_count,), 0 at fixed nodes.
        alpha_dev, alpha_hyd: the deviatoric and hydrostatic compliances divided by the
            nominal substep squared, alpha / h^2 [1/(kg m^2)], (tet_count,) each.
        gamma: rest offset 1 + mu / lambda' of the hydrostatic constraint, (tet_count,).
        contact_alpha: the contact compliance divided by the nominal substep squared [1/kg].
        point_nodes, point_weights: the contact points' embedding (step numbering),
            (point_count, 4) int64 and float64.
        node_tet_start, node_tets: node -> incident tets (CSR): step node n's tets are
            ``node_tets[node_tet_start[n]:node_tet_start[n + 1]]``, (node_count + 1,) and
            (4 tet_count,) int64.
    """

    node_order: NDArray[np.int64]
    step_node_of_mesh: NDArray[np.int64]
    tets: NDArray[np.int64]
    all_tets: NDArray[np.int64]
    sweep_bounds: NDArray[np.int64]
    dm_inv: NDArray[np.float64]
    inv_det_dm: NDArray[np.float64]
    rest_volume: NDArray[np.float64]
    inv_mass: NDArray[np.float64]
    alpha_dev: NDArray[np.float64]
    alpha_hyd: NDArray[np.float64]
    gamma: NDArray[np.float64]
    contact_alpha: float
    point_nodes: NDArray[np.int64]
    point_weights: NDArray[np.float64]
    node_tet_start: NDArray[np.int64]
    node_tets: NDArray[np.int64]


@register_contact
class PBDContact(ContactModel):
    """An XPBD tetrahedral tissue pressed by a rigid probe (the paper's PBD baseline).

    A second tissue backend behind the contact-model step interface: :meth:`step` moves the
    probe, runs ``substeps`` XPBD substeps and returns the contact wrench from the contact
    multipliers (see :mod:`tissue.pbd` for the model, the force and the calibration).

    Args:
        mesh: the tissue mesh; its fixed nodes are pinned.
        probe_shape: the rigid probe's geometry.
        materials: per-region materials (mu, lambda, density); default tissue E = 2850 Pa,
            nu = 0.49, lesions 4 x stiffer.
        config: the XPBD settings; default the calibrated :class:`PBDConfig`.

    Limitations:
        Not converged per step: XPBD with a few sweeps is softer than the material and only
        approaches the FE through the calibrated compliance scales, which hold for the
        calibration's mesh resolution, substep count and loading; other meshes or settings
        need :func:`~tissue.pbd.calibration.calibrate_pbd` again (changing the substeps alone
        moves the force by tens of percent). Too few substeps let the hard contact crush the
        surface tets (5 substeps end INVERTED at level 4126). With the defaults contact acts
        on the volume's boundary nodes, so a collision surface that bulges between them (or
        lies outside the volume) is not held; ``contact_spacing_m`` and ``skin_contact`` add
        points between them. Contact planes are taken once per substep from the exact SDF at
        the predicted positions, so the probe must move less than about half its thickness
        per substep (1.3 mm for the linear face, i.e. about 0.6 m/s at the defaults) or
        points can tunnel through it. Frictionless only. Forces are time averages over the
        step and include inertia during fast motion. Stresses are not reported. About 3 ms
        per step at 4.1k tets with the defaults (one thread); the robust configuration's
        sweep uses two threads.
    """

    name = "pbd"
    label = "PBD"
    colour = "tab:red"
    params_type = PBDConfig
    #: PBD projects contacts; 1 mm covers its contact margin.
    penetration_bound_m = 0.001

    @classmethod
    def settings_for(cls, spec: Any, mesh: TetMesh, materials: Any) -> tuple[Any, Any]:
        """PBD's own tissue settings (``config``; no separate ``params``): the given
        :class:`PBDConfig`, else the profile's (:meth:`PBDConfig.for_profile`) at the spec's
        time step, calibrated for ``mesh`` against robust LM
        (:func:`tissue.pbd.calibration.calibrated_pbd_config`, cached on disk), with contact
        points on the skin between the boundary nodes where the profile chooses them."""
        if spec.contact_params is not None:
            return spec.contact_params, None
        from tissue.pbd.calibration import calibrated_pbd_config

        base = replace(
            PBDConfig.for_profile(spec.profile),
            tissue_dt=spec.tissue_dt,
            skin_contact=profile_choices(spec.profile).pbd_skin_contact,
        )
        return calibrated_pbd_config(mesh, materials, base), None

    @classmethod
    def settings_for_variant(cls, resolved: Any, mesh: TetMesh, materials: Any) -> tuple[Any, Any]:
        """The nominal tissue's settings, calibration included: the compliance scales correct
        XPBD's resolution- and iteration-dependent stiffness and multiply ``1 / (mu V)``, so
        they carry over to other materials and to lesions moved by a few millimetres
        (fitting them again would cost a calibration per variant)."""
        return resolved.config, resolved.params

    def __init__(
        self,
        mesh: TetMesh,
        probe_shape: ProbeShape,
        materials: TissueMaterials | None = None,
        config: PBDConfig | None = None,
    ) -> None:
        if not isinstance(mesh, TetMesh):
            raise TissueInputError(
                f"mesh must be a tissue.TetMesh; got {type(mesh).__name__} "
                "(load files with tissue.load_tet_mesh)"
            )
        if config is not None and not isinstance(config, PBDConfig):
            raise ConfigError(f"config must be a PBDConfig; got {type(config).__name__}")
        super().__init__(mesh, probe_shape)
        self.materials = materials or TissueMaterials()
        self.config = config or PBDConfig()
        cfg = self.config

        # The step runs in its own numbering (see two_domain_order): the tets in sweep order,
        # two node-disjoint domains and their separator, and the nodes in the order the tets
        # first use them, so that the two threads sweeping the domains write to separate
        # memory (in mesh numbering they share cache lines, and two threads were slower than
        # one). The state (_x, _v) and everything public stay in mesh numbering.
        order, sweep_bounds = two_domain_order(mesh.nodes, mesh.tets, cfg.sweep_domains)
        first_use = np.unique(mesh.tets[order].ravel(), return_index=True)
        used_in_order = first_use[0][np.argsort(first_use[1])]
        unused = np.setdiff1d(np.arange(mesh.node_count), used_in_order)
        node_order = np.concatenate([used_in_order, unused]).astype(np.int64)
        step_node_of_mesh = np.empty(mesh.node_count, dtype=np.int64)
        step_node_of_mesh[node_order] = np.arange(mesh.node_count)
        nodes = mesh.nodes[node_order]
        tets = np.ascontiguousarray(step_node_of_mesh[mesh.tets[order]])

        edges = np.stack([nodes[tets[:, k]] - nodes[tets[:, 0]] for k in (1, 2, 3)], axis=2)
        rest_volume = mesh.tet_volumes()[order]
        mu, lam, rho = self.materials.per_tet(mesh.region[order])
        lam_stable = lam + mu
        mass = np.bincount(
            tets.ravel(),
            weights=np.repeat(rho * rest_volume / 4.0, 4),
            minlength=mesh.node_count,
        )
        self.lumped_mass = mass[step_node_of_mesh]  # mesh numbering
        inv_mass = np.zeros(mesh.node_count)
        free = mass > 0.0
        inv_mass[free] = 1.0 / mass[free]
        inv_mass[step_node_of_mesh[mesh.fixed_nodes]] = 0.0
        h = cfg.substep_dt
        mu_model = mu / cfg.deviatoric_compliance_scale
        lam_model = lam_stable / cfg.volume_compliance_scale
        point_nodes, point_weights = choose_contact_points(
            mesh, self.surface, cfg.contact_spacing_m, cfg.skin_contact
        )
        self._point_nodes = point_nodes  # mesh numbering, for the public positions
        self._arrays = SweepArrays(
            node_order=node_order,
            step_node_of_mesh=step_node_of_mesh,
            tets=tets,
            all_tets=np.arange(mesh.tet_count, dtype=np.int64),
            sweep_bounds=sweep_bounds,
            dm_inv=np.ascontiguousarray(np.linalg.inv(edges)),
            inv_det_dm=1.0 / np.linalg.det(edges),
            rest_volume=rest_volume,
            inv_mass=inv_mass,
            alpha_dev=1.0 / (mu_model * rest_volume) / h**2,
            alpha_hyd=1.0 / (lam_model * rest_volume) / h**2,
            # The rest offset must use the scaled moduli too: only then do the two
            # constraints' forces cancel at rest (mu I + lambda' (1 - gamma) I = 0).
            gamma=1.0 + mu_model / lam_model,
            contact_alpha=cfg.contact_compliance_m_per_n / h**2,
            point_nodes=np.ascontiguousarray(step_node_of_mesh[point_nodes]),
            point_weights=point_weights,
            # Node -> incident tets (CSR, step numbering), for the contact zone.
            node_tets=np.argsort(tets.ravel(), kind="stable").astype(np.int64) // 4,
            node_tet_start=np.concatenate(
                [[0], np.cumsum(np.bincount(tets.ravel(), minlength=mesh.node_count))]
            ).astype(np.int64),
        )
        self._lam_dev = np.zeros(mesh.tet_count)
        self._lam_hyd = np.zeros(mesh.tet_count)
        self._reset_tissue()
        self._load_kernels()

    def _load_kernels(self) -> None:
        """Call every compiled kernel of a step once, on scratch arrays of the types the step
        passes, so that the one-time work of a process's first call (numba loading the
        kernel from its cache, OpenMP starting the sweep's second thread; the probe shape's
        cached bounds) is done here, when the model is built, as the FE methods' integrator
        does in ``prepare``: otherwise the first step takes many times the later ones.
        Nothing of the model's state is touched."""
        cfg = self.config
        arrays = self._arrays
        x = self._x[arrays.node_order]
        v, x_previous, support_step, support = (np.zeros_like(x) for _ in range(4))
        lam_dev, lam_hyd = np.zeros_like(self._lam_dev), np.zeros_like(self._lam_hyd)
        h = cfg.substep_dt
        start_substep(x, v, x_previous, 1.0, h, lam_dev, lam_hyd, support_step)
        points = self._point_nodes.shape[0]
        near, near_positions = np.empty(points, dtype=np.int64), np.empty((points, 3))
        origin, rotation = np.zeros(3), np.eye(3)
        points_near(
            x, arrays.point_nodes, arrays.point_weights, origin, 0.0, rotation, origin,
            origin, near, near_positions,
        )  # fmt: skip
        self.probe.shape.signed_distance(np.zeros((1, 3)))
        self.probe.shape.local_bounds_m()  # cached on the shape (built from its surface)
        tissue_args = (
            x, arrays.inv_mass, arrays.tets, arrays.dm_inv, arrays.alpha_dev, arrays.alpha_hyd,
            arrays.gamma, lam_dev, lam_hyd, support_step,
        )  # fmt: skip
        no_tets = arrays.all_tets[:0]
        sweep_kernels.project_tets(*tissue_args, no_tets)
        sweep_kernels.project_tets_two_domains(*tissue_args, no_tets, np.zeros(4, dtype=np.int64))
        no_contacts = np.zeros(0, dtype=np.int64)
        contact_args = (
            arrays.point_nodes, arrays.point_weights, no_contacts, np.zeros((0, 3)),
            np.zeros((0, 3)), arrays.contact_alpha, np.zeros(0),
        )  # fmt: skip
        project_contacts(x, arrays.inv_mass, *contact_args)
        contact_zone_sweeps(
            *tissue_args, *contact_args, arrays.node_tet_start, arrays.node_tets, arrays.all_tets,
            cfg.contact_zone_iterations,
        )  # fmt: skip
        count_below_volume_floor(x, arrays.tets, arrays.inv_det_dm, cfg.volume_floor)
        enforce_volume_floor(
            x, arrays.inv_mass, arrays.tets, arrays.dm_inv, arrays.inv_det_dm, 0.0, support_step
        )
        end_substep(
            x, x_previous, v, h, support_step, support, no_contacts, np.zeros((0, 3)),
            np.zeros(0), np.zeros((points, 3)),
        )  # fmt: skip
        min_volume_ratio(x, arrays.tets, arrays.rest_volume)

    # ------------------------------------------------------------------ interface

    @property
    def arrays(self) -> SweepArrays:
        """The arrays the step's kernels read, in step numbering (:class:`SweepArrays`: the
        model's own, read them, never write them)."""
        return self._arrays

    def contact_points_world(self) -> NDArray[np.float64]:
        """The points PBD contact acts on [m], (k, 3) (see :func:`choose_contact_points`)."""
        return np.einsum("kj,kjd->kd", self._arrays.point_weights, self._x[self._point_nodes])

    def contact_points_near(self) -> NDArray[np.float64]:
        return self.contact_points_world()

    @property
    def node_positions(self) -> NDArray[np.float64]:
        """Current node positions [m], (node_count, 3) (a read-only view)."""
        view = self._x.view()
        view.flags.writeable = False
        return view

    @property
    def node_velocities(self) -> NDArray[np.float64]:
        """Current node velocities [m/s], (node_count, 3) (a read-only view)."""
        view = self._v.view()
        view.flags.writeable = False
        return view

    @property
    def dt(self) -> float:
        return self.config.tissue_dt

    def _reset_tissue(self) -> None:
        self._x = self.mesh.nodes.copy()
        self._v = np.zeros_like(self._x)
        self._previous_pose: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None
        self._support_force_n = np.zeros(3)

    @property
    def support_force_n(self) -> NDArray[np.float64]:
        """The fixed base's force on the tissue over the last step [N], (3,), world frame:
        minus the elastic constraint forces at the fixed nodes, averaged over the step; it
        equals the force on the probe at static equilibrium. NaN after a diverged step,
        zero after a reset."""
        return self._support_force_n.copy()

    def kinetic_energy_j(self) -> float:
        """Kinetic energy of the tissue now [J]."""
        return 0.5 * float(np.sum(self.lumped_mass[:, None] * self._v**2))

    def _snapshot_tissue(self) -> dict[str, Any]:
        before = self._previous_pose
        return {
            "x": self._x.copy(),
            "v": self._v.copy(),
            "previous_pose": None if before is None else (before[0].copy(), before[1].copy()),
            "lam_dev": self._lam_dev.copy(),
            "lam_hyd": self._lam_hyd.copy(),
        }

    def _restore_tissue(self, snapshot: dict[str, Any]) -> None:
        self._x = np.array(snapshot["x"], dtype=np.float64)
        self._v = np.array(snapshot["v"], dtype=np.float64)
        before = snapshot["previous_pose"]
        self._previous_pose = None if before is None else (before[0].copy(), before[1].copy())
        self._lam_dev[:] = snapshot["lam_dev"]
        self._lam_hyd[:] = snapshot["lam_hyd"]

    def sleep_reach_m(self) -> float:
        """The contact margin [m]: a substep projects the points closer than it."""
        return self.config.contact_margin_m

    def _advance_asleep(self, h: float, pieces: int) -> None:
        # The next step's substeps move the probe from here (see _advance).
        self._previous_pose = (self.probe.position_world.copy(), self.probe.quat_wxyz.copy())

    def place_probe(self, position_world: Any, quat_wxyz: Any) -> None:
        """Put the probe at a start pose (:meth:`ContactModel.place_probe`); the next step's
        substeps move it from here.

        Without this the first step after ``reset(pose)`` started its substeps at the step's
        end pose: the whole step's motion fell in the first substep (1/60 of the step), the
        hard contact threw the skin off the probe at up to 60 times the probe's speed, and
        that step reported the impulse (2-5 times the next step's force on a 0.5 mm step
        from touching, then a fall of 45-80 %: not a tissue that pressing resists)."""
        super().place_probe(position_world, quat_wxyz)
        self._previous_pose = (self.probe.position_world.copy(), self.probe.quat_wxyz.copy())

    def _advance(
        self, step_s: float
    ) -> tuple[StepStatus, NDArray[np.float64], NDArray[np.float64], dict[str, Any]]:
        cfg = self.config
        arrays = self._arrays
        h = step_s / cfg.substeps
        # The compliances were divided by the nominal substep squared when the model was
        # built; a shorter step (a sub-motion, see ContactModel.step) rescales them.
        scale = 1.0 if step_s == cfg.tissue_dt else (cfg.substep_dt / h) ** 2
        alpha_dev = arrays.alpha_dev if scale == 1.0 else arrays.alpha_dev * scale
        alpha_hyd = arrays.alpha_hyd if scale == 1.0 else arrays.alpha_hyd * scale
        contact_alpha = arrays.contact_alpha * scale
        end_position = self.probe.position_world.copy()
        end_quat = self.probe.quat_wxyz.copy()
        start_position, start_quat = self._previous_pose or (end_position, end_quat)
        if float(np.dot(start_quat, end_quat)) < 0.0:
            start_quat = -start_quat  # the short way round for nlerp
        x = self._x[arrays.node_order]  # step numbering (a copy)
        v = self._v[arrays.node_order]
        x_previous = np.empty_like(x)
        point_count = self._point_nodes.shape[0]
        near = np.empty(point_count, dtype=np.int64)
        near_positions = np.empty((point_count, 3))
        damping = math.exp(-cfg.damping_per_s * h)
        impulse = np.zeros((point_count, 3))  # sum over substeps of n lambda / h [N s]
        support = np.zeros((self.mesh.node_count, 3))
        support_step = np.zeros_like(support)
        shape = self.probe.shape
        broad_phase = self._broad_phase(shape)
        max_contacts = 0
        detect_s = 0.0
        floor_hits = 0
        # The two-domain sweep is the one-thread sweep in the same order, bit for bit; on one
        # thread the plain kernel skips the parallel launch.
        project_tets = sweep_kernels.project_tets
        project_tets_two_domains = sweep_kernels.project_tets_two_domains
        two_threads = cfg.sweep_domains == 2 and nb.get_num_threads() > 1
        screen_first = two_threads and self.mesh.tet_count >= PARALLEL_SCREEN_TETS
        tissue_args = (
            x, arrays.inv_mass, arrays.tets, arrays.dm_inv, alpha_dev, alpha_hyd,
            arrays.gamma, self._lam_dev, self._lam_hyd, support_step,
        )  # fmt: skip
        # The probe's pose at each substep's end, all at once (nlerp, each quaternion
        # normalised as quat_to_matrix does). The norms stay one 4-vector at a time:
        # np.linalg.norm over rows rounds differently in the last bit.
        fractions = np.arange(1, cfg.substeps + 1) / cfg.substeps
        positions = (1.0 - fractions)[:, None] * start_position + fractions[:, None] * end_position
        quats = (1.0 - fractions)[:, None] * start_quat + fractions[:, None] * end_quat
        norms = np.array([np.linalg.norm(quat) for quat in quats])
        rotations = np.ascontiguousarray(unit_quat_to_matrix(quats / norms[:, None]))
        for substep in range(cfg.substeps):
            position, rotation = positions[substep], rotations[substep]
            start_substep(x, v, x_previous, damping, h, self._lam_dev, self._lam_hyd, support_step)
            tic = time.perf_counter()
            contact_points, normals, anchors = self._detect(
                x, position, rotation, shape, broad_phase, near, near_positions
            )
            detect_s += time.perf_counter() - tic
            lam_contact = np.zeros(contact_points.shape[0])
            contact_args = (
                arrays.point_nodes, arrays.point_weights, contact_points, normals, anchors,
                contact_alpha, lam_contact,
            )  # fmt: skip
            for sweep in range(cfg.iterations):
                if two_threads:
                    project_tets_two_domains(*tissue_args, arrays.all_tets, arrays.sweep_bounds)
                else:
                    project_tets(*tissue_args, arrays.all_tets)
                if sweep < cfg.iterations - 1 and contact_points.size:
                    project_contacts(x, arrays.inv_mass, *contact_args)
            if contact_points.size:
                # The last full sweep's contacts, then the zone's sweeps and contacts.
                contact_zone_sweeps(
                    *tissue_args, *contact_args, arrays.node_tet_start, arrays.node_tets,
                    arrays.all_tets, cfg.contact_zone_iterations,
                )  # fmt: skip
            if cfg.volume_floor > 0.0 and not (
                screen_first
                and count_below_volume_floor(x, arrays.tets, arrays.inv_det_dm, cfg.volume_floor)
                == 0
            ):
                floor_hits += enforce_volume_floor(
                    x,
                    arrays.inv_mass,
                    arrays.tets,
                    arrays.dm_inv,
                    arrays.inv_det_dm,
                    cfg.volume_floor,
                    support_step,
                )
            pressing = end_substep(
                x, x_previous, v, h, support_step, support, contact_points, normals,
                lam_contact, impulse,
            )  # fmt: skip
            max_contacts = max(max_contacts, pressing)

        diagnostics: dict[str, Any] = {
            "substeps": cfg.substeps,
            "iterations": cfg.iterations,
            "active_contacts_max": max_contacts,
            "contact_detection_ms": 1e3 * detect_s,
            "volume_floor_projections": floor_hits,
        }
        self._previous_pose = (end_position, end_quat)
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(v))):
            self._support_force_n = np.full(3, np.nan)
            # Nothing non-finite is stored: the state before the step stays.
            return StepStatus.DIVERGED, np.zeros((0, 3)), np.zeros((0, 3)), diagnostics
        min_ratio = float(min_volume_ratio(x, arrays.tets, arrays.rest_volume))
        self._x = x[arrays.step_node_of_mesh]  # back to mesh numbering
        self._v = v[arrays.step_node_of_mesh]
        diagnostics["min_volume_ratio"] = min_ratio
        # Force of the base on the tissue: minus the elastic constraint forces at fixed nodes,
        # averaged over the step (impulse / tissue_dt).
        self._support_force_n = -support.sum(axis=0) / step_s
        in_contact = np.flatnonzero(np.any(impulse != 0.0, axis=1))
        points_world = self._positions(self._x)[in_contact]
        forces = -impulse[in_contact] / step_s
        status = StepStatus.INVERTED if not min_ratio > 0.0 else StepStatus.OK
        return status, points_world, forces, diagnostics

    @property
    def contact_point_positions(self) -> NDArray[np.float64]:
        """Current positions of the points the PBD contact acts on [m], (k, 3)."""
        return self._positions(self._x)

    def _positions(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.einsum("pk,pka->pa", self._arrays.point_weights, x[self._point_nodes])

    def detect_contacts(
        self, x: NDArray[np.float64], position: NDArray[np.float64], rotation: NDArray[np.float64]
    ) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]]:
        """The contacts a substep projects for node positions ``x`` and this model's probe
        at ``position`` [m] (3,) with ``rotation`` (3, 3) (probe to world), world frame: the
        step's own detection (broad phase, then the probe's exact SDF within the contact
        margin).

        Args:
            x: node positions [m], (node_count, 3), in step numbering
                (``x_mesh[arrays.node_order]``, see :attr:`arrays`).

        Returns:
            contact point indices (k,) (rows of ``arrays.point_nodes``), probe outward
            normals (k, 3) and tangent-plane anchor points [m] (k, 3) (the closest probe
            surface points): :func:`~tissue.pbd.contact.project_contacts`' ``points``,
            ``normals`` and ``anchors``.
        """
        shape = self.probe.shape
        count = self._arrays.point_nodes.shape[0]
        near, near_positions = np.empty(count, dtype=np.int64), np.empty((count, 3))
        return self._detect(
            x, position, rotation, shape, self._broad_phase(shape), near, near_positions
        )

    def _broad_phase(
        self, shape: ProbeShape
    ) -> tuple[float, NDArray[np.float64], NDArray[np.float64]]:
        """:func:`points_near`'s reach [m] and probe-frame box (low, high [m], (3,) each) for
        ``shape``, both grown by the contact margin."""
        margin = self.config.contact_margin_m
        bounds = shape.local_bounds_m()
        return shape.bounding_radius_m + margin, bounds[0] - margin, bounds[1] + margin

    def _detect(
        self,
        x: NDArray[np.float64],
        position: NDArray[np.float64],
        rotation: NDArray[np.float64],
        shape: ProbeShape,
        broad_phase: tuple[float, NDArray[np.float64], NDArray[np.float64]],
        near: NDArray[np.int64],
        near_positions: NDArray[np.float64],
    ) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]]:
        """Contact candidates at predicted positions, for a probe at (position, rotation).

        ``broad_phase``: :meth:`_broad_phase`'s reach and box. ``near`` (point_count,) and
        ``near_positions`` (point_count, 3) are scratch for :func:`points_near`, allocated
        once per step.

        Returns:
            surface point indices (k,), probe outward normals (k, 3) and tangent-plane anchor
            points [m] (k, 3) (the closest probe surface points), world frame.
        """
        reach, low, high = broad_phase
        arrays = self._arrays
        count = points_near(
            x, arrays.point_nodes, arrays.point_weights, position, reach, rotation, low, high,
            near, near_positions,
        )  # fmt: skip
        if count == 0:
            return np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros((0, 3))
        points = near_positions[:count]
        local = (points - position) @ rotation
        distance, normal_local = shape.signed_distance(local)
        close = distance < self.config.contact_margin_m
        normals = np.ascontiguousarray(normal_local[close] @ rotation.T)
        anchors = points[close] - distance[close, None] * normals
        return near[:count][close], normals, np.ascontiguousarray(anchors)
