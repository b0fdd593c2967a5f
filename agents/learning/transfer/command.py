"""``probegym study --transfer``: its options, checked before any training, and its run."""

from __future__ import annotations

import argparse
from pathlib import Path

from agents.learning.train.command import seed_list, step_count
from agents.learning.transfer.spec import (
    EPISODES,
    FULL_STEPS,
    QUICK_CONFIGURATIONS,
    QUICK_ENV_IDS,
    QUICK_EPISODES,
    QUICK_STEPS,
    REFERENCE,
    TransferError,
    TransferSpec,
    check_env_ids,
    configurations,
)

#: Where the transfer study writes under ``--out``.
TRANSFER_DIR = "transfer"


def add_transfer_arguments(study: argparse.ArgumentParser) -> None:
    """The transfer study's options of ``probegym study`` (``--out``, ``--quick``,
    ``--ray`` and ``--no-progress`` are the study's own)."""
    group = study.add_argument_group(
        "transfer study (--transfer): train on a cheap contact model, evaluate on the accurate one"
    )
    group.add_argument(
        "--transfer",
        action="store_true",
        help="the transfer study: a policy per training configuration, evaluated on every "
        "evaluation configuration and the reference; writes to OUT/transfer (--quick: "
        "BreastCompress-v2 and LesionSearch-v1, the four methods at 623 and 1363, one seed)",
    )
    group.add_argument("--env", default=None, help="comma-separated env ids (with --transfer)")
    group.add_argument("--train", default=None, help="METHOD@LEVEL,... trained on")
    group.add_argument("--evaluate", default=None, help="METHOD@LEVEL,... evaluated on")
    group.add_argument(
        "--reference", default=None, help=f"the accurate model (default {REFERENCE})"
    )
    group.add_argument("--algo", default="ppo", help="ppo (default) or sac")
    group.add_argument(
        "--steps", type=step_count, default=None, help="training steps per run (e.g. 50k)"
    )
    group.add_argument(
        "--seeds", type=seed_list, default=None, help="training seeds, e.g. 0,1,2 (default 0)"
    )
    group.add_argument("--episodes", type=int, default=None, help="held-out episodes per cell")


def transfer_spec_from_args(args: argparse.Namespace) -> TransferSpec:
    """The study the options ask for; a :class:`TransferError` naming any bad one."""
    quick = bool(args.quick)
    env_ids = tuple(e.strip() for e in args.env.split(",") if e.strip()) if args.env else None
    env_ids = env_ids or QUICK_ENV_IDS
    check_env_ids(env_ids)
    train = configurations(args.train, QUICK_CONFIGURATIONS, "--train")
    evaluate = configurations(args.evaluate, tuple(c.label for c in train), "--evaluate")
    reference = configurations(args.reference, (REFERENCE,), "--reference")
    if len(reference) != 1:
        raise TransferError(f"--reference is one METHOD@LEVEL; got {args.reference!r}")
    if args.steps is not None:
        budgets = dict.fromkeys(env_ids, int(args.steps))
    else:
        table = QUICK_STEPS if quick else FULL_STEPS
        missing = [e for e in env_ids if e not in table]
        if missing:
            raise TransferError(
                f"no default training budget for {', '.join(missing)}: give --steps N"
            )
        budgets = {e: table[e] for e in env_ids}
    seeds = tuple(args.seeds) if args.seeds is not None else (0,)
    episodes = args.episodes if args.episodes is not None else (
        QUICK_EPISODES if quick else EPISODES
    )  # fmt: skip
    return TransferSpec(
        env_ids=env_ids,
        train=train,
        evaluate=evaluate,
        reference=reference[0],
        algo=str(args.algo).lower(),
        steps=budgets,
        seeds=seeds,
        episodes=episodes,
    )


def run_transfer_command(args: argparse.Namespace) -> int:
    """Validate, run (resumable), and say where the outputs are; returns the exit code."""
    from agents.learning.transfer.run import run_transfer

    spec = transfer_spec_from_args(args)
    out = Path(args.out) / TRANSFER_DIR
    command = getattr(args, "command_line", None) or "probegym study --transfer"
    outcome = run_transfer(spec, out, ray_address=args.ray, command=command)
    print(
        f"transfer: {outcome.trained_now} runs trained now, {outcome.evaluated_now} cells "
        f"evaluated now, {len(outcome.records) - outcome.evaluated_now} from an earlier run"
    )
    for note in outcome.redone:
        print(f"redone: {note}")
    for name in ("transfer.json", "transfer.csv", "report.md"):
        print(f"written: {out / name}")
    return 0
