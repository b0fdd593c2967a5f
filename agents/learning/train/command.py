"""``probegym train ENV_ID ...``: its options, and many runs (seeds, algorithms, contact
methods) one after another here or as Ray tasks on a cluster (``--ray ADDRESS``).

Many runs go to ``OUT/<algo>-<contact>-seed<S>/`` each; a single run to ``OUT`` itself.
A summary table (each run's last evaluation: mean return and success rate) is printed and
written to ``OUT/summary.json`` when there are several.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np

from agents.learning.train.run import ALGORITHMS, TrainError, TrainSettings, train
from agents.learning.train.workers import WorkerDiedError


def add_train_parser(commands: Any) -> None:
    """The ``train`` subcommand on an argparse subparsers object."""
    parser = commands.add_parser(
        "train", help="train an SB3 agent on an environment (resumable; many seeds on Ray)"
    )
    parser.add_argument("env_id", metavar="ENV_ID", help="e.g. probegym/BreastCompress-v0")
    parser.add_argument("--algo", default="ppo", help="ppo or sac; comma-separated for a sweep")
    parser.add_argument(
        "--contact", default="lm", help="contact method; comma-separated for a sweep (default lm)"
    )
    parser.add_argument("--mesh", default="1363", help="phantom level or mesh file (default 1363)")
    parser.add_argument("--profile", default="robust", help="paper or robust (default robust)")
    parser.add_argument(
        "--steps", type=step_count, default=300_000, help="env steps (default 300k)"
    )
    parser.add_argument("--n-envs", type=step_count, default=2, help="parallel envs (default 2)")
    parser.add_argument("--seed", type=seed_list, default=None, help="seed (default 0)")
    parser.add_argument("--seeds", type=seed_list, default=None, help="several seeds: 0,1,2")
    parser.add_argument("--out", type=Path, default=None, help="default probegym-out/train/...")
    parser.add_argument("--eval-every", type=step_count, default=10_000, help="env steps")
    parser.add_argument("--eval-episodes", type=step_count, default=20, help="per evaluation")
    parser.add_argument("--checkpoint-every", type=step_count, default=20_000, help="env steps")
    parser.add_argument("--no-normalize", action="store_true", help="do not normalise observations")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument(
        "--domain-randomization", action="store_true", help="randomise each episode (defaults)"
    )
    parser.add_argument(
        "--env-kwargs",
        type=env_kwargs_json,
        default={},
        metavar="JSON",
        help="more gymnasium.make keyword arguments, a JSON object, e.g. "
        + "'{\"start_offset_range_m\": [0.0, 0.01]}'",
    )
    parser.add_argument(
        "--hyperparameters",
        type=hyperparameters_json,
        default={},
        metavar="JSON",
        help="SB3 keyword arguments over the task's defaults "
        + "(agents/learning/train/hyperparameters.py), a JSON object, e.g. '{\"n_steps\": 2048}'",
    )
    parser.add_argument(
        "--init-from",
        type=Path,
        default=None,
        metavar="RUN",
        help="start from a trained model (a train folder or a .zip in one): a curriculum's "
        "next stage",
    )
    parser.add_argument(
        "--pretrain-scripted",
        type=int,
        default=0,
        metavar="EPISODES",
        help="first clone the task's scripted policy from this many of its episodes (PPO)",
    )
    parser.add_argument(
        "--ray",
        default=None,
        metavar="ADDRESS",
        help="run the runs as Ray tasks: ray://host:10001, host:6379, auto or local",
    )


def run_train(args: argparse.Namespace) -> int:
    """Run ``probegym train`` from its parsed options; the exit status."""
    algos = [a.strip().lower() for a in args.algo.split(",") if a.strip()]
    contacts = [c.strip() for c in args.contact.split(",") if c.strip()]
    unknown = sorted(set(algos) - set(ALGORITHMS))
    if unknown or not algos:
        raise TrainError(f"--algo {args.algo!r}: choose from {', '.join(ALGORITHMS)}")
    if args.seed is not None and args.seeds is not None:
        raise TrainError("give --seed or --seeds, not both")
    seeds = args.seeds or args.seed or [0]
    runs = list(itertools.product(algos, contacts, seeds))
    name = args.env_id.split("/")[-1]
    out = args.out
    if out is None:
        from agents.outputs import default_output

        out = default_output("train", name if len(runs) > 1 else _run_name(*runs[0], name))
    folders = [out] if len(runs) == 1 else [out / _run_name(*run) for run in runs]
    settings = [
        _settings(args, algo, contact, seed, folder)
        for (algo, contact, seed), folder in zip(runs, folders, strict=True)
    ]
    if args.ray is not None:
        finals = train_on_ray(settings, args.ray, args.command_line)
    else:
        warning = cores_warning(args.n_envs, os.cpu_count())
        if warning is not None:
            print(warning, file=sys.stderr)
        try:
            finals = [train(s, command=args.command_line) for s in settings]
        except WorkerDiedError as error:
            print(f"probegym: error: {error}", file=sys.stderr)
            return 1
    if len(runs) > 1:
        _summarise(settings, finals, out)
    return 0


def cores_warning(n_envs: int, cores: int | None) -> str | None:
    """The warning for more environments than the machine has cores (None: no warning):
    every environment's worker, and the training's process, then share the cores, and each
    steps slower than the same run with ``--n-envs`` at most the cores."""
    if cores is None or n_envs <= cores:
        return None
    return (
        f"warning: --n-envs {n_envs} is more than this machine's {cores} cores: the "
        f"environments share them, each stepping slower; --n-envs {cores} is as fast or faster"
    )


def _run_name(algo: str, contact: str, seed: int, env_name: str | None = None) -> str:
    base = f"{algo}-{contact}-seed{seed}"
    return base if env_name is None else f"{env_name}-{base}"


def _settings(
    args: argparse.Namespace, algo: str, contact: str, seed: int, out: Path
) -> TrainSettings:
    env_kwargs: dict[str, Any] = {
        "contact": contact,
        "mesh": int(args.mesh) if str(args.mesh).isdigit() else args.mesh,
        "profile": args.profile,
    }
    if args.domain_randomization:
        env_kwargs["domain_randomization"] = True
    clashes = sorted(set(args.env_kwargs) & set(env_kwargs))
    if clashes:
        raise TrainError(
            f"--env-kwargs sets {', '.join(clashes)}, which have options of their own: "
            f"use --{clashes[0].replace('_', '-')} instead"
        )
    env_kwargs.update(args.env_kwargs)
    return TrainSettings(
        env_id=args.env_id,
        out=out,
        algo=algo,
        env_kwargs=env_kwargs,
        steps=args.steps,
        n_envs=args.n_envs,
        seed=seed,
        eval_every=args.eval_every,
        eval_episodes=args.eval_episodes,
        checkpoint_every=args.checkpoint_every,
        normalize=not args.no_normalize,
        hyperparameters=dict(args.hyperparameters),
        init_from=args.init_from,
        pretrain_episodes=args.pretrain_scripted,
        progress=not args.no_progress and args.ray is None,
    )


def _train_quietly(settings: TrainSettings, command: str) -> str:
    """One run in a Ray worker (no progress bar), its final model's path."""
    from tissue import configure_threads

    configure_threads()
    return str(train(settings, command=command))


def train_on_ray(settings: list[TrainSettings], address: str, command: str) -> list[Path]:
    """Every run as a Ray task (each asks for ``n_envs`` CPUs); their final models."""
    from agents.lab.study.ray_backend import ray_submitter

    workers = max(s.n_envs for s in settings)
    submit = ray_submitter(address, workers, cpus_per_task=workers)
    futures = [submit(_train_quietly, s, command) for s in settings]
    return [Path(future.result()) for future in futures]


def _summarise(settings: list[TrainSettings], finals: list[Path], out: Path) -> None:
    """Each run's last evaluation, printed and in ``summary.json``."""
    from agents.outputs import write_json

    rows = []
    for s, final in zip(settings, finals, strict=True):
        log = Path(s.out) / "eval" / "evaluations.npz"
        row: dict[str, Any] = {
            "algo": s.algo,
            "contact": s.env_kwargs["contact"],
            "seed": s.seed,
            "model": str(final),
        }
        if log.is_file():
            data = np.load(log)
            row["timesteps"] = int(data["timesteps"][-1])
            row["mean_return"] = float(np.mean(data["results"][-1]))
            if "successes" in data and len(data["successes"]):
                row["success_rate"] = float(np.mean(data["successes"][-1]))
        rows.append(row)
        print(
            f"{row['algo']:4s} {row['contact']:10s} seed {row['seed']}: "
            f"return {row.get('mean_return', float('nan')):.2f}, success "
            f"{row.get('success_rate', float('nan')):.2f} at {row.get('timesteps', 0):,} steps"
        )
    write_json({"runs": rows}, out / "summary.json", indent=1)


def step_count(value: str) -> int:
    """An option's step count: a whole number >= 1, ``300000`` or ``300k``."""
    text = value.replace("_", "").replace(",", "")
    if text.lower().endswith("k") and text[:-1].isdigit():
        return int(text[:-1]) * 1000
    if not text.isdigit() or int(text) < 1:
        raise argparse.ArgumentTypeError(
            f"expected a whole number >= 1 (e.g. 300000 or 300k); got {value!r}"
        )
    return int(text)


#: What ``--env-kwargs`` takes, for its error messages.
EXAMPLE_KWARGS = "'{\"hold_steps\": 10}'"


def env_kwargs_json(value: str) -> dict[str, Any]:
    """``--env-kwargs``: a JSON object of ``gymnasium.make`` keyword arguments (JSON lists
    become tuples, as the task configs' pairs are written)."""
    try:
        parsed = json.loads(value)
    except json.JSONDecodeError as error:
        raise argparse.ArgumentTypeError(
            f"{value!r} is not JSON ({error.msg}); give an object such as " + EXAMPLE_KWARGS
        ) from None
    if not isinstance(parsed, dict):
        raise argparse.ArgumentTypeError(
            f"{value!r} is not a JSON object; give one such as " + EXAMPLE_KWARGS
        )
    return {key: _tuples(item) for key, item in parsed.items()}


def hyperparameters_json(value: str) -> dict[str, Any]:
    """``--hyperparameters``: a JSON object of SB3 keyword arguments (lists stay lists: SB3
    takes ``net_arch`` as one)."""
    try:
        parsed = json.loads(value)
    except json.JSONDecodeError as error:
        raise argparse.ArgumentTypeError(
            f"{value!r} is not JSON ({error.msg}); give an object such as "
            '\'{"n_steps": 2048, "learning_rate": 0.0001}\''
        ) from None
    if not isinstance(parsed, dict):
        raise argparse.ArgumentTypeError(
            f"{value!r} is not a JSON object; give one such as '{{\"n_steps\": 2048}}'"
        )
    return parsed


def _tuples(value: Any) -> Any:
    if isinstance(value, list):
        return tuple(_tuples(item) for item in value)
    if isinstance(value, dict):
        return {key: _tuples(item) for key, item in value.items()}
    return value


def seed_list(value: str) -> list[int]:
    """An option's comma-separated seeds (whole numbers >= 0)."""
    parts = [part.strip() for part in value.split(",") if part.strip()]
    if not parts or not all(part.isdigit() for part in parts):
        raise argparse.ArgumentTypeError(
            f"expected comma-separated whole numbers >= 0 (seeds); got {value!r}"
        )
    return [int(part) for part in parts]
