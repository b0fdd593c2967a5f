"""The integrator's settings: :class:`IntegratorConfig`, Newton's tuning included."""

from __future__ import annotations

from dataclasses import dataclass

from tissue.errors import ConfigError
from tissue.profile import Profile, profile_choices
from tissue.sim.solvers import LinearSolverConfig, LinearSolverKind


@dataclass(frozen=True)
class IntegratorConfig:
    """Settings of the implicit integrator.

    Attributes:
        mode: the profile (:mod:`tissue.profile`): its ``newton`` choice picks one linearised
            solve a step (paper) or Newton with line search (robust).
        quasi_static: seek static equilibrium each step (no inertia, no damping).
        rayleigh_mass: r_M [1/s], mass-proportional damping.
        rayleigh_stiffness: r_K [s], stiffness-proportional damping.
        linear_solver: the linear solver; None picks the mode's default (``paper``: CG capped
            at 25 iterations as the paper; ``robust``: factorisation reused as preconditioner).
        project_psd: project element tangents to PSD; None means True in ``robust`` and False
            in ``paper`` (as the paper's framework).
        newton_tolerance: relative residual at which Newton stops (residual norm over the
            norm of the forces acting).
        newton_max_iterations: Newton iterations before a step is declared not converged.
        max_subdivisions: how many times a failed robust step may be halved (0 disables).
        blow_up_extents: a step that leaves a node further than this many mesh extents
            (largest side of the rest bounding box) from its rest position diverged [-]. Two
            extents is far beyond any compression of the tissue, so only a runaway step trips it.
        residual_scale_floor: floor of the force scale Newton's residual is relative to, as a
            fraction of (mu + lambda)_max x extent^2 [-]. A tissue at rest with nothing acting
            has round-off forces only (1e-14 of that unit on the published mesh), which must
            read as converged; 1e-10 lies well above round-off and far below any load.
        min_step_fraction: the shortest line-search step, as a fraction of the Newton step
            [-]; backtracking halves down to it, then keeps it if finite (2^-12: twelve
            halvings).
        extrapolate_below: a full Newton step along which the energy still falls at more
            than this fraction of its initial rate (directional derivative at the end over
            the one at the start) was too short, and the secant step is tried [-]. One half:
            Newton's step on a quadratic ends at slope 0, a linearly converging one (penalty
            contact's frozen normal) well short of it.
        max_extrapolation: the longest such secant step, in full Newton steps [-]; taken where
            the directional derivative does not rise along the step (no secant zero), so 4
            keeps that guess within a few Newton steps.
        projection_switch: relative Newton residual below which a robust step that projects
            (quasi-static, or dynamic without stiffness damping) tries the exact tangent
            first [-]; 0.1 is near enough to the solution for the exact tangent's quadratic
            convergence to pay.
        linear_share_of_tolerance: a Newton direction's linear solve may stop once its
            absolute residual is this fraction of the Newton tolerance times the force scale
            [-]: to first order the new Newton residual is the linear one, so more accuracy
            is wasted; one half leaves the other half to the nonlinearity.
        chord_backoff_max_steps: the longest pause [steps] of the chord hand-over
            (:class:`~tissue.sim.integrator.chords.ChordHandOver`) after handed chords that
            needed a second iteration; at 16, a hand-over that keeps failing (a contact set
            changing every step) is retried once in 16 steps, at the cost of one iteration.
    """

    mode: Profile | str = Profile.PAPER
    quasi_static: bool = False
    rayleigh_mass: float = 0.1
    rayleigh_stiffness: float = 0.1
    linear_solver: LinearSolverConfig | None = None
    project_psd: bool | None = None
    newton_tolerance: float = 1e-4
    newton_max_iterations: int = 30
    max_subdivisions: int = 4
    blow_up_extents: float = 2.0
    residual_scale_floor: float = 1e-10
    min_step_fraction: float = 2.0**-12
    extrapolate_below: float = 0.5
    max_extrapolation: float = 4.0
    projection_switch: float = 1e-1
    linear_share_of_tolerance: float = 0.5
    chord_backoff_max_steps: int = 16

    def __post_init__(self) -> None:
        object.__setattr__(self, "mode", Profile.parse(self.mode))
        if self.rayleigh_mass < 0 or self.rayleigh_stiffness < 0:
            raise ConfigError(
                "Rayleigh damping factors must be >= 0; got rayleigh_mass="
                f"{self.rayleigh_mass}, rayleigh_stiffness={self.rayleigh_stiffness}"
            )
        if not 0 < self.newton_tolerance < 1:
            raise ConfigError(f"newton_tolerance must lie in (0, 1); got {self.newton_tolerance}")
        if self.newton_max_iterations < 1:
            raise ConfigError(
                f"newton_max_iterations must be >= 1; got {self.newton_max_iterations}"
            )
        if self.max_subdivisions < 0:
            raise ConfigError(f"max_subdivisions must be >= 0; got {self.max_subdivisions}")
        self._check_tuning()
        choices = profile_choices(self.mode)
        if self.linear_solver is None:
            kind = LinearSolverKind.parse(choices.linear_solver)
            object.__setattr__(self, "linear_solver", LinearSolverConfig(kind=kind))
        if self.project_psd is None:
            object.__setattr__(self, "project_psd", choices.project_psd)

    def _check_tuning(self) -> None:
        """Refuse Newton tuning outside the range where it means what its docstring says."""
        ranges = (
            ("blow_up_extents", self.blow_up_extents > 0, "> 0"),
            ("residual_scale_floor", self.residual_scale_floor > 0, "> 0"),
            ("min_step_fraction", 0 < self.min_step_fraction <= 1, "in (0, 1]"),
            ("extrapolate_below", 0 < self.extrapolate_below < 1, "in (0, 1)"),
            ("max_extrapolation", self.max_extrapolation >= 1, ">= 1"),
            ("projection_switch", self.projection_switch >= 0, ">= 0"),
            (
                "linear_share_of_tolerance",
                0 <= self.linear_share_of_tolerance <= 1,
                "in [0, 1]",
            ),
            ("chord_backoff_max_steps", self.chord_backoff_max_steps >= 0, ">= 0"),
        )
        for name, ok, wanted in ranges:
            if not ok:
                raise ConfigError(f"{name} must be {wanted}; got {getattr(self, name)}")
