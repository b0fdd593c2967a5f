"""``probegym evaluate``'s arguments and its run from the parsed arguments."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from tissue import ConfigError, TissueInputError


def add_evaluate_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Add the ``evaluate`` subcommand to an ``add_subparsers()`` object; returns it."""
    parser: argparse.ArgumentParser = subparsers.add_parser(
        "evaluate",
        help="run a policy for N seeded episodes: per-episode JSON and CSV, summary, plots",
        description="Run a scripted or trained policy for N episodes of one environment "
        "(episode k reset with seed S + k) and write episodes.json, episodes.csv, "
        "summary.json, summary.md and PNG plots into --out. See docs/evaluate.md.",
    )
    parser.add_argument(
        "env_id",
        metavar="ENV_ID",
        help="probegym/BreastCompress-v0, probegym/LesionSearch-v0 or probegym/ForceScan-v0",
    )
    parser.add_argument(
        "--policy",
        required=True,
        help="'scripted' (the task's scripted policy), 'random' (uniform actions, the chance "
        "baseline) or PATH: a probegym train folder or a model .zip in one",
    )
    parser.add_argument("--episodes", type=int, default=10, help="episodes to run (default 10)")
    parser.add_argument("--seed", type=int, default=0, help="episode k's seed is SEED + k")
    parser.add_argument(
        "--out",
        type=Path,
        default=None,
        help="output folder (default probegym-out/evaluate/<env name>)",
    )
    parser.add_argument(
        "--contact",
        default=None,
        help="penalty | lm | prescribed | pbd (default: the env's, or the trained model's)",
    )
    parser.add_argument(
        "--mesh",
        default=None,
        help="phantom level (tet count, e.g. 623) or a tet-mesh file (default: the env's, or "
        "the trained model's)",
    )
    parser.add_argument(
        "--profile", default=None, help="paper | robust (default: the env's, or the model's)"
    )
    parser.add_argument(
        "--domain-randomization",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="draw a patient at each reset (default: off, or as the model was trained)",
    )
    return parser


def env_options(args: argparse.Namespace) -> dict[str, Any]:
    """The ``gymnasium.make`` keyword arguments given on the command line, checked (those
    not given are left out, so a trained model's own apply)."""
    from tissue import Profile
    from tissue.lab import contact_method

    kwargs: dict[str, Any] = {}
    if args.contact is not None:
        contact_method(args.contact)  # a ConfigError naming the valid ones
        kwargs["contact"] = args.contact
    if args.profile is not None:
        kwargs["profile"] = Profile.parse(args.profile).value
    if args.mesh is not None:
        kwargs["mesh"] = mesh_option(args.mesh)
    if args.domain_randomization is not None:
        kwargs["domain_randomization"] = bool(args.domain_randomization)
    return kwargs


def mesh_option(value: str) -> int | str:
    """``--mesh``: a phantom level (a whole number) or an existing mesh file."""
    from tissue.lab import parse_level

    if value.strip().isdigit():
        return parse_level(value)
    if not Path(value).is_file():
        raise ConfigError(
            f"--mesh {value}: neither a phantom level (a tet count such as 623 or 1363) nor "
            "an existing mesh file"
        )
    return value


def run_evaluate(args: argparse.Namespace) -> int:
    """Run ``probegym evaluate`` from its parsed arguments; the exit status (0 when the
    evaluation ran, whatever its success rate; 2 with a one-line error on bad input)."""
    from agents.learning.evaluation.report import wilson_interval
    from agents.learning.evaluation.run import check_counts, check_env_id, default_out, evaluate

    try:
        check_env_id(args.env_id)
        check_counts(args.episodes, args.seed)
        kwargs = env_options(args)
        out = args.out if args.out is not None else default_out(args.env_id)
        from agents.lab.first_use import announce_compilation

        announce_compilation()
        records = evaluate(
            args.env_id,
            args.policy,
            args.episodes,
            args.seed,
            kwargs,
            out,
            command=getattr(args, "command_line", None),
        )
    except TissueInputError as error:
        print(f"probegym: error: {error}", file=sys.stderr)
        return 2
    n = len(records)
    successes = sum(1 for record in records if record["success"])
    low, high = wilson_interval(successes, n)
    print(
        f"{args.env_id}, policy {args.policy}: {successes}/{n} episodes succeeded "
        f"(95 % interval {100 * low:.0f}-{100 * high:.0f} %); written to {out}/ "
        "(summary.md, episodes.csv, episodes.json, plots)"
    )
    return 0
