"""What a compression study runs: its specification and its cells.

A *cell* is one experiment of Tagliabue et al. (2020), section 2.2-3: one contact method,
one mesh level, one lesion and one configuration; the probe is placed on the skin above the
lesion and pressed through the increasing depths, settling at each.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from agents.lab.compress import ACCURATE_SETTLE_STEPS
from tissue import ConfigError, Profile
from tissue.lab import PAPER_PROBE_SPEED_M_S, PHANTOM_LEVELS, Choice, contact_method, parse_level

#: The published scene's own volume mesh (9,295 tets), as a level of the study.
NATIVE_LEVEL = 0
#: Synthetic default depths past first contact [m]: 10, 20, 25, 30 mm (the published
#: poses reach 9-29 mm).
DEFAULT_DEPTHS_M = (0.01, 0.02, 0.025, 0.03)
#: Steps a cell may hold still at each depth to settle; it stops earlier once no node moves
#: faster than 0.1 mm/s (see :data:`agents.lab.compress.ACCURATE_SETTLE_STEPS`).
STUDY_SETTLE_STEPS = ACCURATE_SETTLE_STEPS
#: ``--quick``: levels up to 4,126 tets, three lesions; the reference on the next level up,
#: 7,369 tets, to keep the run within minutes (a 176,506-tet reference takes an hour here), so
#: quick errors near 4,126 tets are underestimates.
QUICK_LEVELS = (623, 1363, 2539, 4126)
# The dome's top (1), an intermediate (10, skin tilted 26 degrees) and a flank lesion (3, 45
# degrees); lesions 4-9 sit where the skin is tilted 52-56 degrees, and pressed 25-30 mm
# along the normal the tissue slips or is pinched against the base (the full study runs them).
QUICK_LESIONS = (1, 3, 10)
QUICK_REFERENCE_LEVEL = 7369


#: The contact methods a study runs unless told otherwise (the paper's three and PBD).
STUDY_METHODS = ("lm", "penalty", "prescribed", "pbd")


class ReferenceKind(Choice):
    """How the converged reference reaches each depth (see :mod:`agents.lab.study.reference`).

    ``dynamic`` (the default): the cells' own experiment -- the probe driven at the study's
    speed and time step, held at each depth as long as the cells -- on the reference level,
    with Newton to a tight tolerance. ``quasi-static``: static equilibrium at every probe
    pose, the probe advanced in 1 mm increments.
    """

    DYNAMIC = "dynamic"
    QUASI_STATIC = "quasi-static"

    @classmethod
    def noun(cls) -> str:
        return "reference kind"


def level_label(level: int) -> str:
    """How a level is written in tables: ``published`` or its target tet count."""
    return "published" if level == NATIVE_LEVEL else f"{level:,}"


def parse_study_level(value: str | int) -> int:
    """A ladder level (target tet count) or ``native``/``published`` (the scene's own mesh)."""
    if isinstance(value, str) and value.strip().lower() in ("native", "published"):
        return NATIVE_LEVEL
    if value == NATIVE_LEVEL and not isinstance(value, bool):  # already parsed (a copy)
        return NATIVE_LEVEL
    return parse_level(value)


@dataclass(frozen=True)
class Cell:
    """One experiment: a method on a level, pressing above a lesion, in a configuration."""

    config: Profile
    method: str
    level: int
    lesion: int

    @property
    def key(self) -> str:
        """A stable identifier, the key of ``results.jsonl`` records."""
        return f"{self.config.value}/{self.method}/{self.level}/{self.lesion}"


@dataclass(frozen=True)
class StudySpec:
    """Everything that decides a study's results (the output directory aside).

    Attributes:
        scene: ``synthetic`` (the built-in phantom), ``paper`` (../shared/paper-scene) or a
            directory laid out like it.
        methods: contact methods to run (registered names; :data:`STUDY_METHODS`).
        levels: mesh levels (target tet counts; :data:`NATIVE_LEVEL` is the published mesh).
        lesions: lesion numbers (1-based); None: every lesion of the scene.
        configs: the profiles to run each method in (:mod:`tissue.profile`).
        depths_m: depths past first contact [m] (synthetic scene only; the published scene's
            poses fix its own), increasing.
        reference_level: the level the converged reference runs on.
        reference_kind: how the reference reaches each depth (:class:`ReferenceKind`).
        speed_m_s: probe speed [m/s].
        settle_steps: the most steps a cell holds still at each depth to settle (see
            :data:`STUDY_SETTLE_STEPS`).
        measured_csv: measured lesion positions to score against instead of the reference.
        collision_edge_m: the skin's resolution, its collision surface's edge [m]
            (:attr:`tissue.TissueSpec.collision_edge_m`); None (default): the scene's own
            surface, the paper's 1,004 triangles, as Table 1 was made with.
    """

    scene: str = "synthetic"
    methods: tuple[str, ...] = STUDY_METHODS
    levels: tuple[int, ...] = PHANTOM_LEVELS
    lesions: tuple[int, ...] | None = None
    configs: tuple[Profile, ...] = (Profile.PAPER, Profile.ROBUST)
    depths_m: tuple[float, ...] = DEFAULT_DEPTHS_M
    reference_level: int = PHANTOM_LEVELS[-1]
    speed_m_s: float = PAPER_PROBE_SPEED_M_S
    measured_csv: Path | None = field(default=None)
    settle_steps: int = STUDY_SETTLE_STEPS
    reference_kind: ReferenceKind = ReferenceKind.DYNAMIC
    collision_edge_m: float | None = None

    def __post_init__(self) -> None:
        if self.collision_edge_m is not None:
            edge = self.collision_edge_m
            if isinstance(edge, bool) or not isinstance(edge, (int, float, np.floating)):
                raise ConfigError(f"--skin is an edge in mm or 'paper'; got {edge!r}")
            if not (np.isfinite(edge) and edge > 0.0):
                raise ConfigError(f"--skin must be a positive edge; got {edge!r} m")
            object.__setattr__(self, "collision_edge_m", float(edge))
        object.__setattr__(self, "methods", tuple(contact_method(m) for m in self.methods))
        object.__setattr__(self, "configs", tuple(Profile.parse(c) for c in self.configs))
        object.__setattr__(self, "levels", tuple(parse_study_level(v) for v in self.levels))
        object.__setattr__(self, "reference_level", parse_study_level(self.reference_level))
        object.__setattr__(self, "reference_kind", ReferenceKind.parse(self.reference_kind))
        for name in ("methods", "levels", "configs"):
            values = getattr(self, name)
            if not values:
                raise ConfigError(f"the study needs at least one of {name}")
            if len(set(values)) != len(values):
                raise ConfigError(f"{name} repeats a value: {list(values)}")
        if self.lesions is not None:
            lesions = tuple(int(n) for n in self.lesions)
            if not lesions or min(lesions) < 1 or len(set(lesions)) != len(lesions):
                raise ConfigError(f"lesions are distinct numbers from 1; got {list(self.lesions)}")
            object.__setattr__(self, "lesions", lesions)
        depths = np.asarray(self.depths_m, dtype=np.float64)
        if depths.size == 0 or not np.all(np.isfinite(depths)) or np.any(depths <= 0):
            raise ConfigError(f"--depths must be positive metres; got {list(self.depths_m)}")
        if np.any(np.diff(depths) <= 0):
            raise ConfigError(f"--depths must increase; got {list(self.depths_m)}")
        if depths.max() > 0.1:
            raise ConfigError(
                f"--depths are metres; {depths.max():g} m is deeper than the phantom "
                "(30 mm is 0.03)"
            )
        object.__setattr__(self, "depths_m", tuple(float(d) for d in depths))
        if not (np.isfinite(self.speed_m_s) and self.speed_m_s > 0):
            raise ConfigError(f"the probe speed must be > 0 m/s; got {self.speed_m_s!r}")
        steps = self.settle_steps
        if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or steps < 1:
            raise ConfigError(
                f"settle_steps must be a whole number of steps >= 1; got {steps!r} (default "
                f"{STUDY_SETTLE_STEPS}: a hold of up to 5 s at each depth)"
            )
        object.__setattr__(self, "settle_steps", int(steps))
        if self.scene == "synthetic" and NATIVE_LEVEL in (*self.levels, self.reference_level):
            raise ConfigError(
                "the 'published' level is the published scene's own mesh; use it with "
                "--scene paper or DIR"
            )

    def cells(self, lesion_ids: tuple[int, ...]) -> list[Cell]:
        """Every cell, coarse levels first (results arrive early)."""
        cells = []
        for level in self.levels:
            for lesion in lesion_ids:
                for config in self.configs:
                    for method in self.methods:
                        cells.append(Cell(config, method, level, lesion))
        return cells

    def as_json(self) -> dict[str, object]:
        return {
            "scene": self.scene,
            "methods": list(self.methods),
            "levels": list(self.levels),
            "lesions": None if self.lesions is None else list(self.lesions),
            "configs": [c.value for c in self.configs],
            "depths_m": list(self.depths_m),
            "reference_level": self.reference_level,
            "reference_kind": self.reference_kind.value,
            "speed_m_s": self.speed_m_s,
            "settle_steps": self.settle_steps,
            "measured_csv": None if self.measured_csv is None else str(self.measured_csv),
            "collision_edge_m": self.collision_edge_m,
        }


def quick_spec(scene: str = "synthetic") -> StudySpec:
    """The README's main command: small levels, all methods, three lesions, both configs."""
    return StudySpec(
        scene=scene,
        levels=QUICK_LEVELS,
        lesions=QUICK_LESIONS,
        reference_level=QUICK_REFERENCE_LEVEL,
    )
