"""The scriptable tissue simulator: build or load a mesh, fix nodes, prescribe, step, read.

Example::

    from tissue import TissueSimulator, SimulationConfig, breast_phantom

    sim = TissueSimulator(breast_phantom(4126), config=SimulationConfig(mode="robust"))
    top = sim.nodes_near_point([0.0, 0.0, 0.08], radius_m=0.01)
    for step in range(50):
        sim.prescribe(top, sim.rest_positions[top] + [0, 0, -0.0002 * (step + 1)])
        result = sim.step()
        print(result.status, result.reaction_force_n(top))
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tissue.errors import ConfigError, TissueInputError, check_setting_names
from tissue.fem.elasticity import AntiLocking, Elasticity
from tissue.fem.material import TissueMaterials
from tissue.mesh import TetMesh, check_rigid_motion_removed, node_dofs
from tissue.profile import PAPER_TISSUE_DT_S, Profile, check_tissue_dt, profile_choices
from tissue.sim.frames import NodeFrames
from tissue.sim.integrator import (
    EnergyTerm,
    ImplicitIntegrator,
    IntegratorConfig,
    StepOutcome,
)
from tissue.sim.solvers import SERIAL_STEP_UNKNOWNS, LinearSolverConfig
from tissue.status import StepStatus
from tissue.threads import one_thread_below, thread_policy


@dataclass(frozen=True)
class SimulationConfig:
    """Everything that decides how the tissue is simulated.

    Attributes:
        tissue_dt: the tissue time step h [s] (the paper's by default).
        mode: the profile, ``paper`` (one linearised backward-Euler solve per step, eq. 5 of
            the paper) or ``robust`` (Newton with line search, PSD tangents, step
            subdivision); the defaults below marked "the profile's" are its choices
            (:data:`tissue.profile.PROFILES`).
        quasi_static: seek static equilibrium every step instead of integrating dynamics.
        linear_solver: ``cg``, ``direct`` or ``reuse``; None: the profile's.
        cg_max_iterations: cap of the CG solver (25 as the paper).
        anti_locking: ``none`` or ``anp`` (average nodal pressure against volumetric locking).
        project_psd: project element tangents to PSD; None: the profile's.
        inversion_barrier: the volume ratio J below which a barrier keeps tets from
            inverting (see :class:`tissue.fem.elasticity.Elasticity`); None: the profile's
            (robust 0.1; paper 0, the law as published).
        rayleigh_mass: r_M [1/s]. rayleigh_stiffness: r_K [s].
        newton_tolerance: relative residual of a converged robust step.
        newton_max_iterations: Newton iterations before a step is not converged.
        max_subdivisions: times a failed robust step may be halved.
        gravity_m_s2: gravity vector [m/s^2] or None (the paper's phantom is segmented under
            gravity, so gravity is off by default).
    """

    tissue_dt: float = PAPER_TISSUE_DT_S
    mode: Profile | str = Profile.PAPER
    quasi_static: bool = False
    linear_solver: str | None = None
    cg_max_iterations: int = 25
    anti_locking: AntiLocking | str = AntiLocking.NONE
    project_psd: bool | None = None
    inversion_barrier: float | None = None
    rayleigh_mass: float = 0.1
    rayleigh_stiffness: float = 0.1
    newton_tolerance: float = 1e-4
    newton_max_iterations: int = 30
    max_subdivisions: int = 4
    gravity_m_s2: tuple[float, float, float] | None = None

    def __post_init__(self) -> None:
        check_tissue_dt(self.tissue_dt)
        object.__setattr__(self, "mode", Profile.parse(self.mode))
        object.__setattr__(self, "anti_locking", AntiLocking.parse(self.anti_locking))
        if self.inversion_barrier is None:
            barrier = profile_choices(self.mode).inversion_barrier
            object.__setattr__(self, "inversion_barrier", barrier)
        elif not (
            isinstance(self.inversion_barrier, (int, float)) and 0.0 <= self.inversion_barrier < 1.0
        ):
            raise ConfigError(
                "inversion_barrier is a volume ratio J in [0, 1) (0: off); got "
                f"{self.inversion_barrier!r}"
            )
        if self.gravity_m_s2 is not None:
            gravity = tuple(float(g) for g in self.gravity_m_s2)
            if len(gravity) != 3:
                raise ConfigError(f"gravity_m_s2 must have 3 components; got {self.gravity_m_s2!r}")
            object.__setattr__(self, "gravity_m_s2", gravity)
        self.integrator_config()  # validates the remaining fields

    @classmethod
    def from_overrides(cls, **overrides: Any) -> SimulationConfig:
        """Build from keyword overrides, rejecting unknown keys with the valid ones listed."""
        check_setting_names(overrides, (f.name for f in fields(cls)), "simulation")
        return cls(**overrides)

    def integrator_config(self) -> IntegratorConfig:
        linear = None
        if self.linear_solver is not None or self.cg_max_iterations != 25:
            base = IntegratorConfig(mode=self.mode).linear_solver
            assert base is not None
            linear = LinearSolverConfig(
                kind=self.linear_solver or base.kind, cg_max_iterations=self.cg_max_iterations
            )
        return IntegratorConfig(
            mode=self.mode,
            quasi_static=self.quasi_static,
            rayleigh_mass=self.rayleigh_mass,
            rayleigh_stiffness=self.rayleigh_stiffness,
            linear_solver=linear,
            project_psd=self.project_psd,
            newton_tolerance=self.newton_tolerance,
            newton_max_iterations=self.newton_max_iterations,
            max_subdivisions=self.max_subdivisions,
        )


@dataclass(frozen=True)
class StepResult:
    """What one tissue step did (a copy: later steps do not change it).

    Attributes:
        status: ``ok`` or the instability met (see :class:`tissue.status.StepStatus`).
        time_s: simulated time after the step [s].
        positions: node positions [m], (node_count, 3).
        reaction_forces: force applied by the constraints on the tissue [N],
            (node_count, 3), non-zero only at constrained nodes.
        elastic_energy_j: strain energy [J].
        landmarks: landmark positions [m], (landmark_count, 3) (empty if none).
        compute_ms: wall time of the step [ms].
        newton_iterations, linear_iterations, linear_residual, newton_residual,
        subdivisions, factorizations, min_volume_ratio, newton_residuals: solver
        diagnostics (newton_residuals: relative residual at each Newton iteration).
    """

    status: StepStatus
    time_s: float
    positions: NDArray[np.float64]
    reaction_forces: NDArray[np.float64]
    elastic_energy_j: float
    landmarks: NDArray[np.float64]
    compute_ms: float
    newton_iterations: int
    linear_iterations: int
    linear_residual: float
    newton_residual: float
    subdivisions: int
    factorizations: int
    min_volume_ratio: float
    newton_residuals: tuple[float, ...] = ()

    def reaction_force_n(self, nodes: ArrayLike) -> NDArray[np.float64]:
        """Total force [N], shape (3,), the constraints apply to the tissue at ``nodes``."""
        return self.reaction_forces[np.asarray(nodes, dtype=np.int64)].sum(axis=0)


class TissueSimulator:
    """A hyperelastic tet mesh with fixed nodes, prescribed nodes and implicit stepping.

    Args:
        mesh: the tissue mesh (rest positions, tets, regions, fixed nodes, landmarks).
        materials: per-region materials; default tissue E = 2850 Pa, nu = 0.49.
        config: how to simulate; default the paper's configuration.
    """

    def __init__(
        self,
        mesh: TetMesh,
        materials: TissueMaterials | None = None,
        config: SimulationConfig | None = None,
    ) -> None:
        if not isinstance(mesh, TetMesh):
            raise TissueInputError(
                f"mesh must be a tissue.TetMesh; got {type(mesh).__name__} "
                "(load files with tissue.load_tet_mesh)"
            )
        self.mesh = mesh
        self.materials = materials or TissueMaterials()
        self.config = config or SimulationConfig()
        # The build runs under the step's thread rule: parallel sums in the rest stiffness and
        # the node blocks' partition would otherwise follow the thread count (tissue.threads).
        thread_policy()
        with one_thread_below(3 * mesh.node_count, SERIAL_STEP_UNKNOWNS):
            self._build()

    def _build(self) -> None:
        mesh = self.mesh
        assert self.config.inversion_barrier is not None  # resolved by SimulationConfig
        self.elasticity = Elasticity(
            mesh, self.materials, self.config.anti_locking, self.config.inversion_barrier
        )
        external = None
        if self.config.gravity_m_s2 is not None:
            external = (
                self.elasticity.lumped_mass[:, None] * np.asarray(self.config.gravity_m_s2)[None, :]
            )
        self.integrator = ImplicitIntegrator(
            self.elasticity, self.config.integrator_config(), external
        )
        self._fixed_dofs = node_dofs(mesh.fixed_nodes)
        self.integrator.prepare(self._fixed_dofs)
        self._prescribed_dofs = np.zeros(0, dtype=np.int64)
        self._prescribed_targets = np.zeros(0)
        self._frames: NodeFrames | None = None
        self._checked_dofs: NDArray[np.int64] | None = None
        self.reset()

    # ------------------------------------------------------------------ state

    @property
    def rest_positions(self) -> NDArray[np.float64]:
        """Rest node positions [m], (node_count, 3)."""
        return self.mesh.nodes

    @property
    def positions(self) -> NDArray[np.float64]:
        """Current node positions [m], (node_count, 3) (a read-only view)."""
        view = self._positions.view()
        view.flags.writeable = False
        return view

    @property
    def velocities(self) -> NDArray[np.float64]:
        """Current node velocities [m/s], (node_count, 3) (a read-only view)."""
        view = self._velocities.view()
        view.flags.writeable = False
        return view

    @property
    def time_s(self) -> float:
        return self._time

    def reset(self) -> None:
        """Back to rest: positions at rest, zero velocity, time 0, nothing prescribed."""
        self._positions = self.mesh.nodes.copy()
        self._velocities = np.zeros_like(self._positions)
        self._time = 0.0
        self.clear_prescribed()
        self.integrator.solver.forget()
        self.integrator.forget_last_step()

    def set_state(
        self,
        positions: ArrayLike,
        velocities: ArrayLike | None = None,
        time_s: float | None = None,
    ) -> None:
        """Overwrite the state (for warm starts and restoring a checkpoint); ``time_s``
        [s], if given, resets the clock too."""
        positions = np.array(positions, dtype=np.float64)
        if positions.shape != self._positions.shape or not np.all(np.isfinite(positions)):
            raise TissueInputError(
                f"positions must be finite with shape {self._positions.shape}; "
                f"got {positions.shape}"
            )
        self._positions = positions
        self._velocities = (
            np.zeros_like(positions)
            if velocities is None
            else np.array(velocities, dtype=np.float64)
        )
        if time_s is not None:
            self._time = float(time_s)
        self.integrator.forget_last_step()

    def set_clock(self, time_s: float) -> None:
        """Set the clock to ``time_s`` [s], the state untouched (a sleeping step's time:
        :mod:`tissue.contact.sleep`)."""
        self._time = float(time_s)

    # ------------------------------------------------------------------ boundary conditions

    def prescribe(
        self, nodes: ArrayLike, targets: ArrayLike, axes: Sequence[int] = (0, 1, 2)
    ) -> None:
        """Prescribe where ``nodes`` are at the end of the next step(s), replacing any earlier set.

        Args:
            nodes: node indices, (k,), unique.
            targets: their positions [m], (k, 3), or (3,) for all alike. They stay prescribed
                (at these targets) until changed or cleared.
            axes: the coordinates prescribed (0 = x, 1 = y, 2 = z); the others stay free, as
                on a frictionless platen pressing along z with ``axes=(2,)``.
        """
        nodes = np.asarray(nodes, dtype=np.int64).reshape(-1)
        targets = np.asarray(targets, dtype=np.float64)
        if targets.shape == (3,):
            targets = np.broadcast_to(targets, (nodes.size, 3))
        if targets.shape != (nodes.size, 3):
            raise TissueInputError(
                f"targets must have shape ({nodes.size}, 3) for {nodes.size} nodes; "
                f"got {targets.shape}"
            )
        self._check_nodes(nodes)
        axes_array = np.asarray(axes, dtype=np.int64)
        if (
            axes_array.size == 0
            or np.any((axes_array < 0) | (axes_array > 2))
            or np.unique(axes_array).size != axes_array.size
        ):
            raise TissueInputError(f"axes must be distinct values among 0, 1, 2; got {list(axes)}")
        self.prescribe_dofs(node_dofs(nodes, tuple(axes_array)), targets[:, axes_array].reshape(-1))

    def prescribe_normal(self, nodes: ArrayLike, points: ArrayLike, normals: ArrayLike) -> None:
        """Prescribe each node's coordinate along a normal only, replacing any earlier set.

        Node i ends the next step(s) on the plane through ``points[i]`` with normal
        ``normals[i]`` and is free to slide within it: a frictionless contact with that plane
        (the integrator solves the step in frames whose first axis is the normal; see
        :mod:`tissue.sim.frames`). The reaction at such a node lies along its normal.

        Args:
            nodes: node indices, (k,), unique, none of them fixed.
            points: a point of each plane [m], (k, 3).
            normals: each plane's normal, (k, 3), non-zero (normalised here).
        """
        nodes = np.asarray(nodes, dtype=np.int64).reshape(-1)
        points = np.asarray(points, dtype=np.float64)
        if points.shape != (nodes.size, 3) or not np.all(np.isfinite(points)):
            raise TissueInputError(
                f"points must be finite with shape ({nodes.size}, 3) for {nodes.size} nodes; "
                f"got {points.shape}"
            )
        self._check_nodes(nodes)
        if np.any(np.isin(nodes, self.mesh.fixed_nodes)):
            raise TissueInputError(
                "a fixed node cannot slide on a plane; leave the fixed nodes out of the set"
            )
        frames = NodeFrames.from_normals(
            nodes, np.asarray(normals, dtype=np.float64), self.mesh.node_count
        )
        self._prescribed_dofs = 3 * nodes
        self._prescribed_targets = np.einsum("ij,ij->i", frames.axes[:, 0], points)
        self._frames = frames if nodes.size else None

    def _check_nodes(self, nodes: NDArray[np.int64]) -> None:
        """Raise TissueInputError unless ``nodes`` are unique indices of this mesh's nodes."""
        if nodes.size and (nodes.min() < 0 or nodes.max() >= self.mesh.node_count):
            raise TissueInputError(
                f"node indices must lie in [0, {self.mesh.node_count - 1}]; "
                f"got [{nodes.min()}, {nodes.max()}]"
            )
        if np.unique(nodes).size != nodes.size:
            raise TissueInputError("prescribed nodes must be unique; remove the repeated indices")

    def prescribe_dofs(self, dofs: ArrayLike, targets: ArrayLike) -> None:
        """Prescribe individual coordinates, replacing any earlier prescribed set.

        Args:
            dofs: degrees of freedom 3·node + axis, (k,), unique.
            targets: their coordinates at the end of the next step(s) [m], (k,).
        """
        dofs = np.asarray(dofs, dtype=np.int64).reshape(-1)
        targets = np.asarray(targets, dtype=np.float64).reshape(-1)
        if targets.shape != dofs.shape:
            raise TissueInputError(
                f"got {targets.size} targets for {dofs.size} dofs; give one each"
            )
        if dofs.size and (dofs.min() < 0 or dofs.max() >= self.mesh.dof_count):
            raise TissueInputError(
                f"dofs must lie in [0, {self.mesh.dof_count - 1}]; got [{dofs.min()}, {dofs.max()}]"
            )
        if np.unique(dofs).size != dofs.size:
            raise TissueInputError("prescribed dofs must be unique; remove the repeated indices")
        if not np.all(np.isfinite(targets)):
            raise TissueInputError("prescribed targets contain NaN or Inf")
        self._prescribed_dofs = dofs.copy()
        self._prescribed_targets = targets.copy()
        self._frames = None

    def boundary_state(self) -> dict[str, Any]:
        """The prescribed set (dofs, targets [m], node frames), for snapshots."""
        return {
            "dofs": self._prescribed_dofs.copy(),
            "targets": self._prescribed_targets.copy(),
            "frames": self._frames,  # immutable once built
        }

    def set_boundary_state(self, state: dict[str, Any]) -> None:
        """Adopt a :meth:`boundary_state`."""
        self._prescribed_dofs = np.array(state["dofs"], dtype=np.int64)
        self._prescribed_targets = np.array(state["targets"], dtype=np.float64)
        self._frames = state["frames"]

    def clear_prescribed(self) -> None:
        """Release every prescribed node (fixed nodes stay fixed)."""
        self._prescribed_dofs = np.zeros(0, dtype=np.int64)
        self._prescribed_targets = np.zeros(0)
        self._frames = None

    def nodes_near_point(self, point: ArrayLike, radius_m: float) -> NDArray[np.int64]:
        """Indices of rest nodes within ``radius_m`` [m] of ``point`` [m]."""
        distance = np.linalg.norm(self.mesh.nodes - np.asarray(point, dtype=np.float64), axis=1)
        return np.flatnonzero(distance <= radius_m)

    # ------------------------------------------------------------------ stepping

    def step(self, terms: Sequence[EnergyTerm] = (), dt: float | None = None) -> StepResult:
        """Advance one step of ``tissue_dt`` (or ``dt``) [s].

        Never raises for a physical failure: a diverged or failed step keeps the previous
        state and says so in ``status``.
        """
        dt = self.config.tissue_dt if dt is None else float(dt)
        start = time.perf_counter()
        dofs, targets = self.constraints()
        with one_thread_below(3 * self.mesh.node_count, SERIAL_STEP_UNKNOWNS):
            outcome = self.integrator.step(
                self._positions, self._velocities, dt, dofs, targets, terms, self._frames
            )
        return self.commit(outcome, dt, start)

    def commit(self, outcome: StepOutcome, dt: float, started: float) -> StepResult:
        """Adopt the state of an integrator outcome (unless it failed); the step's result.

        For contact solvers that drive the integrator's pieces themselves. ``started`` is
        the ``time.perf_counter()`` value when the step began.
        """
        if outcome.status not in (StepStatus.DIVERGED, StepStatus.SOLVER_FAILED):
            self._positions = outcome.positions
            self._velocities = outcome.velocities
            self._time += dt
        elapsed_ms = 1e3 * (time.perf_counter() - started)
        return self._result(outcome, elapsed_ms)

    def constraints(self) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """The constrained dofs of the next step (fixed, then prescribed) and their targets [m]."""
        dofs, targets = self._constraints()
        if self.config.quasi_static and (
            self._checked_dofs is None or not np.array_equal(dofs, self._checked_dofs)
        ):
            frames = self._frames
            directions = None
            if frames is not None:  # a framed node's dof lies along its frame's axis
                directions = np.eye(3)[dofs % 3]
                slots = frames.node_slots()[dofs // 3]
                framed = slots >= 0
                directions[framed] = frames.axes[slots[framed], dofs[framed] % 3]
            check_rigid_motion_removed(self.mesh, dofs, directions)
            self._checked_dofs = dofs
        return dofs, targets

    def _constraints(self) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        fixed = self._fixed_dofs
        prescribed = self._prescribed_dofs
        if prescribed.size:
            # A prescribed target overrides "fixed" (a mask: np.isin sorts, every step).
            overridden = np.zeros(self.mesh.dof_count, dtype=bool)
            overridden[prescribed] = True
            fixed = fixed[~overridden[fixed]]
        dofs = np.concatenate([fixed, prescribed])
        targets = np.concatenate([self.mesh.nodes.reshape(-1)[fixed], self._prescribed_targets])
        return dofs, targets

    def _result(self, outcome: StepOutcome, elapsed_ms: float) -> StepResult:
        landmarks = (
            self.mesh.landmarks.positions(self._positions)
            if self.mesh.landmarks is not None
            else np.zeros((0, 3))
        )
        return StepResult(
            status=outcome.status,
            time_s=self._time,
            positions=self._positions.copy(),
            reaction_forces=outcome.reaction_forces,
            elastic_energy_j=outcome.elastic_energy_j,
            landmarks=landmarks,
            compute_ms=elapsed_ms,
            newton_iterations=outcome.newton_iterations,
            linear_iterations=outcome.linear_iterations,
            linear_residual=outcome.linear_residual,
            newton_residual=outcome.newton_residual,
            subdivisions=outcome.subdivisions,
            factorizations=outcome.factorizations,
            min_volume_ratio=outcome.min_volume_ratio,
            newton_residuals=tuple(outcome.newton_residuals),
        )

    # ------------------------------------------------------------------ reading

    def landmark_positions(self) -> NDArray[np.float64]:
        """Current landmark positions [m], (landmark_count, 3)."""
        if self.mesh.landmarks is None:
            return np.zeros((0, 3))
        return self.mesh.landmarks.positions(self._positions)

    def internal_forces(self) -> NDArray[np.float64]:
        """Elastic forces on the nodes at the current state [N], (node_count, 3)."""
        return self.elasticity.forces(self._positions)

    def elastic_energy_j(self) -> float:
        """Strain energy at the current state [J]."""
        return float(self.elasticity.energy(self._positions))

    def kinetic_energy_j(self) -> float:
        """Kinetic energy at the current state [J]."""
        return 0.5 * float(np.sum(self.elasticity.lumped_mass[:, None] * self._velocities**2))

    def export_vtu(self, path: str | Path) -> Path:
        """Write the deformed mesh (displacement as point data) for ParaView; returns the path."""
        from tissue.mesh.io import write_mesh

        return write_mesh(self.mesh, path, positions=self._positions)


def settle(sim: TissueSimulator, max_steps: int = 200, speed_tol_m_s: float = 1e-5) -> StepResult:
    """Step with the current constraints until the fastest node is slower than ``speed_tol``."""
    result = sim.step()
    for _ in range(max_steps - 1):
        if result.status in (StepStatus.DIVERGED, StepStatus.SOLVER_FAILED):
            break
        if float(np.max(np.abs(sim.velocities))) < speed_tol_m_s or math.isclose(
            sim.kinetic_energy_j(), 0.0
        ):
            break
        result = sim.step()
    return result
