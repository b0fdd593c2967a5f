"""Argument handling of ``probegym study`` (the work is in :mod:`agents.lab.study.runner`)."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from agents.lab.study.spec import (
    DEFAULT_DEPTHS_M,
    QUICK_LESIONS,
    QUICK_LEVELS,
    QUICK_REFERENCE_LEVEL,
    STUDY_SETTLE_STEPS,
    StudySpec,
)
from tissue import ConfigError
from tissue.lab import PHANTOM_LEVELS, contact_method


def add_study_arguments(study: argparse.ArgumentParser) -> None:
    """The options of ``probegym study``."""
    study.add_argument(
        "--contact",
        "--methods",
        dest="methods",
        default=None,
        help="comma-separated contact methods (default lm,penalty,prescribed,pbd)",
    )
    study.add_argument(
        "--levels",
        default=None,
        help="comma-separated tet-count levels (and 'published' with --scene paper); "
        "default all 9 (--quick: 623..4126)",
    )
    study.add_argument("--lesions", default=None, help="comma-separated numbers; default all")
    study.add_argument(
        "--scene", default="synthetic", help="synthetic | paper | DIR (published layout)"
    )
    study.add_argument(
        "--depths", default=None, help="D1,D2,... [m] past first contact (default 10,20,25,30 mm)"
    )
    study.add_argument(
        "--profile",
        "--config",
        dest="config",
        default=None,
        help="paper | robust | paper,robust (default both; --robot --quick: robust)",
    )
    study.add_argument("--reference-level", default=None, help="level of the converged reference")
    study.add_argument(
        "--reference-kind",
        default="dynamic",
        help="dynamic (the cells' own experiment, default) | quasi-static (1 mm increments)",
    )
    study.add_argument(
        "--skin",
        default="paper",
        help="the skin's resolution: 'paper' (the scene's own 1,004 triangles, default: "
        "Table 1 as published) or a collision edge in mm, e.g. 2 (the environments')",
    )
    study.add_argument("--measured", type=Path, default=None, help="CSV of measured positions")
    study.add_argument("--speed", type=float, default=0.01, help="probe speed [m/s]")
    study.add_argument(
        "--settle-steps",
        type=int,
        default=STUDY_SETTLE_STEPS,
        help=f"most steps held still at each depth to settle (default {STUDY_SETTLE_STEPS})",
    )
    study.add_argument("--workers", type=int, default=1, help="local worker processes")
    study.add_argument("--ray", default=None, help="Ray address (auto, local or host:port)")
    study.add_argument(
        "--out", type=Path, default=None, help="output folder (default probegym-out/study)"
    )
    study.add_argument(
        "--quick",
        action="store_true",
        help=f"levels {','.join(map(str, QUICK_LEVELS))}, lesions "
        f"{','.join(map(str, QUICK_LESIONS))}, reference {QUICK_REFERENCE_LEVEL} (about 5 min)",
    )
    study.add_argument("--no-progress", action="store_true", help="no progress bar")
    study.add_argument(
        "--robot",
        action="store_true",
        help="hold the probe with the arm (probegym/BreastCompress-v0) and compare each cell "
        "with the kinematic one; writes to OUT/robot (--quick: levels 623,1363, lesions 1,10, "
        "robust; about two minutes)",
    )


def _split(value: str, what: str) -> list[str]:
    parts = [part.strip() for part in value.split(",") if part.strip()]
    if not parts:
        raise ConfigError(f"--{what} is empty; give a comma-separated list")
    return parts


def spec_from_args(args: argparse.Namespace) -> StudySpec:
    """Validate every argument into a :class:`StudySpec` before any work starts."""
    robot = bool(getattr(args, "robot", False))
    quick_levels: tuple[int | str, ...] = QUICK_LEVELS
    quick_lesions: tuple[int, ...] = QUICK_LESIONS
    if robot:
        from agents.lab.study.robot import ROBOT_QUICK_LESIONS, ROBOT_QUICK_LEVELS

        quick_levels, quick_lesions = ROBOT_QUICK_LEVELS, ROBOT_QUICK_LESIONS
    default_levels: tuple[int | str, ...] = quick_levels if args.quick else PHANTOM_LEVELS
    levels = _split(args.levels, "levels") if args.levels else list(default_levels)
    if args.lesions:
        try:
            lesions: tuple[int, ...] | None = tuple(int(v) for v in _split(args.lesions, "lesions"))
        except ValueError:
            raise ConfigError(f"--lesions are numbers; got {args.lesions!r}") from None
    else:
        lesions = quick_lesions if args.quick and args.scene == "synthetic" else None
    if args.depths is not None:
        if args.scene != "synthetic":
            raise ConfigError(
                "--depths applies to --scene synthetic; the published poses fix their own"
            )
        try:
            depths = tuple(float(v) for v in _split(args.depths, "depths"))
        except ValueError:
            raise ConfigError(f"--depths are numbers in metres; got {args.depths!r}") from None
    else:
        depths = DEFAULT_DEPTHS_M
    reference = args.reference_level or (
        QUICK_REFERENCE_LEVEL if args.quick else PHANTOM_LEVELS[-1]
    )
    methods = args.methods or "lm,penalty,prescribed,pbd"
    configs = args.config or ("robust" if robot and args.quick else "paper,robust")
    return StudySpec(
        scene=args.scene,
        methods=tuple(contact_method(m) for m in _split(methods, "methods")),
        levels=tuple(levels),  # type: ignore[arg-type]  # parsed in __post_init__
        lesions=lesions,
        configs=tuple(_split(configs, "config")),  # type: ignore[arg-type]
        depths_m=depths,
        reference_level=reference,
        reference_kind=args.reference_kind,
        speed_m_s=args.speed,
        settle_steps=args.settle_steps,
        measured_csv=args.measured,
        collision_edge_m=_skin(args.skin),
    )


def _skin(value: str) -> float | None:
    """``--skin``: ``paper`` (None) or an edge in mm, to metres."""
    if value.strip().lower() == "paper":
        return None
    try:
        edge_mm = float(value)
    except ValueError:
        raise ConfigError(f"--skin is 'paper' or an edge in mm; got {value!r}") from None
    if not (math.isfinite(edge_mm) and edge_mm > 0.0):
        raise ConfigError(f"--skin must be a positive edge in mm; got {value!r}")
    return edge_mm * 1e-3


def run_study_command(args: argparse.Namespace) -> int:
    """Validate, run, and say where the outputs are; returns the exit code."""
    spec = spec_from_args(args)
    if getattr(args, "robot", False):
        return run_robot_command(args, spec)
    if args.workers < 1:
        raise ConfigError(f"--workers must be >= 1; got {args.workers}")
    from agents.lab.study.runner import run_study

    outcome = run_study(
        spec, args.out, workers=args.workers, ray_address=args.ray, progress=not args.no_progress
    )
    unstable = sum(1 for record in outcome.records if record["status"] != "ok")
    print(
        f"study: {outcome.ran_now} cells run now, {outcome.skipped} from an earlier run, "
        f"{unstable} unstable; {outcome.references_computed} references computed"
    )
    for name in ("results.jsonl", "stability.md", "errors.png", "times.png",
                 "accuracy_vs_time.png", "report.md", "report.html"):  # fmt: skip
        print(f"written: {args.out / name}")
    for failure in outcome.failed:
        print(f"failed (a bug, please report it; rerun to retry): {failure}", file=sys.stderr)
    return 1 if outcome.failed else 0


def run_robot_command(args: argparse.Namespace, spec: StudySpec) -> int:
    """``probegym study --robot``: run the cells with the arm holding the probe, into
    ``OUT/robot`` (see :mod:`agents.lab.study.robot`); returns the exit code."""
    from agents.lab.study.robot import ROBOT_DIR, check_robot_spec
    from agents.lab.study.robot_runner import run_robot_study

    if args.workers != 1 or args.ray is not None:
        raise ConfigError(
            "--robot runs its cells one after another in this process; drop --workers and --ray"
        )
    if args.measured is not None or args.reference_level is not None:
        raise ConfigError(
            "--robot compares each cell with the kinematic one, not with a reference or "
            "measured positions; drop --measured and --reference-level"
        )
    check_robot_spec(spec)
    outcome = run_robot_study(spec, args.out, progress=not args.no_progress)
    unstable = sum(1 for record in outcome.records if record["status"] != "ok")
    print(
        f"study --robot: {outcome.ran_now} cells run now, {outcome.skipped} from an earlier "
        f"run, {unstable} unstable"
    )
    for name in ("results.jsonl", "robot.md", "stability.md", "robot_vs_kinematic.png",
                 "tracking.png", "summary.json"):  # fmt: skip
        print(f"written: {args.out / ROBOT_DIR / name}")
    for failure in outcome.failed:
        print(f"failed (a bug, please report it; rerun to retry): {failure}", file=sys.stderr)
    return 1 if outcome.failed else 0
