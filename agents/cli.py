"""The ``probegym`` command line: ``demo``, ``mesh``, ``compress``, ``study``, ``bench``,
``train``, ``evaluate``, ``envs``.

Every subcommand validates its arguments before doing any work and exits with status 2
and a message naming the bad value when they are wrong.
"""

from __future__ import annotations

import argparse
import math
import shlex
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from agents.env_listing import add_envs_parser, run_envs
from agents.learning.evaluation import add_evaluate_parser, run_evaluate
from agents.learning.train.command import add_train_parser, seed_list
from agents.view import add_view_parser, run_view
from tissue import ConfigError, Profile, TissueInputError


def _level(value: str) -> int:
    from tissue.lab import parse_level

    try:
        return parse_level(value)
    except TissueInputError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def _levels(value: str) -> list[int]:
    return [_level(part) for part in value.split(",") if part.strip()]


def _floats(value: str) -> list[float]:
    try:
        return [float(part) for part in value.split(",") if part.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated numbers; got {value!r}"
        ) from None


def _names(text: str | None, parse: Callable[[str], object] | None = None) -> list[str] | None:
    """The names of a comma-separated option (``None`` where it was not given), each checked
    by ``parse`` (a choice's parser, which raises an error naming the valid ones)."""
    if text is None or text == "":
        return None
    names = [part.strip() for part in text.split(",") if part.strip()]
    for name in names:
        if parse is not None:
            parse(name)
    return names


def _train_algos(parser: argparse.ArgumentParser, text: str) -> list[str]:
    """``bench train --algo``'s algorithms (``none``: no train phase)."""
    from agents.learning.train.run import ALGORITHMS

    if text.strip() == "none":
        return []
    algos = _names(text) or []
    for algo in algos:
        if algo not in ALGORITHMS:
            parser.error(
                f"--algo {algo!r} is not an algorithm; choose from {', '.join(ALGORITHMS)} "
                "(comma-separated) or none"
            )
    return algos


def _at_least_one(parser: argparse.ArgumentParser, option: str, value: int) -> int:
    if value < 1:
        parser.error(f"{option} must be a whole number >= 1; got {value}")
    return value


def _methods_and_profiles(
    parser: argparse.ArgumentParser, methods: str | None, profiles: str | None
) -> tuple[list[str] | None, list[str]]:
    """A benchmark's ``--contact`` (None: all) and ``--profile`` (one or more) options,
    checked."""
    from tissue.lab import contact_method

    chosen = _names(profiles, Profile.parse)
    if not chosen:
        parser.error("--profile needs one or more of paper,robust; got nothing")
    return _names(methods, contact_method), chosen


_SKIN_HELP = (
    "comma-separated skin resolutions: collision edges in mm, or 'paper' for the phantom's "
    "own 1,004 triangles; default {default}"
)


def _skins(value: str) -> list[float | None]:
    """``--skin``: collision edges in mm (to metres), ``paper`` for the mesh's own surface."""
    chosen: list[float | None] = []
    for item in (part.strip() for part in value.split(",")):
        if item.lower() == "paper":
            chosen.append(None)
            continue
        try:
            edge_mm = float(item)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"a skin is an edge in mm or 'paper'; got {item!r}"
            ) from None
        if not (math.isfinite(edge_mm) and edge_mm > 0.0):
            raise argparse.ArgumentTypeError(f"a skin's edge must be > 0 mm; got {item!r}")
        chosen.append(edge_mm * 1e-3)
    if not chosen:
        raise argparse.ArgumentTypeError("--skin needs one or more resolutions; got nothing")
    return chosen


def _check_skins(
    parser: argparse.ArgumentParser, skins: list[float | None] | None, levels: list[int]
) -> None:
    """Refuse, before any work, a skin resolution outside a level's range."""
    from tissue import ConfigError
    from tissue.lab import breast_phantom, check_collision_edge

    for level in levels:
        mesh = breast_phantom(level)
        for edge in skins or ():
            if edge is None:
                continue
            try:
                check_collision_edge(mesh, edge)
            except ConfigError as refused:
                parser.error(f"--skin {edge * 1e3:g} at level {level}: {refused}")


def _pair(value: str) -> tuple[float, float]:
    numbers = _floats(value)
    if len(numbers) != 2:
        raise argparse.ArgumentTypeError(f"expected X,Y; got {value!r}")
    return numbers[0], numbers[1]


def _triple(value: str) -> tuple[float, float, float]:
    numbers = _floats(value)
    if len(numbers) != 3:
        raise argparse.ArgumentTypeError(f"expected DX,DY,DZ; got {value!r}")
    return numbers[0], numbers[1], numbers[2]


def _build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="probegym",
        description="Robotic breast ultrasound: FE tissue, probe contact, Gymnasium environments.",
    )
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    demo = commands.add_parser(
        "demo", help="compress the built-in phantom with the probe and print what happened"
    )
    demo.add_argument("--level", type=_level, default=4126, help="phantom mesh level (tet count)")
    demo.add_argument("--depth-mm", type=float, default=10.0, help="compression depth [mm]")
    demo.add_argument(
        "--profile", "--mode", dest="mode", choices=[p.value for p in Profile], default="robust"
    )

    mesh = commands.add_parser("mesh", help="write a phantom mesh level to a file")
    mesh.add_argument("--level", type=_level, required=True, help="tet-count level, e.g. 4126")
    mesh.add_argument("--out", type=Path, required=True, help="output file; format by suffix")

    compress = commands.add_parser(
        "compress", help="one scripted probe compression, recorded as JSON"
    )
    tissue_source = compress.add_mutually_exclusive_group()
    tissue_source.add_argument(
        "--mesh",
        default=None,
        help="phantom level (tet count, default 4126) or a tet-mesh file meshio reads",
    )
    tissue_source.add_argument("--scene", type=Path, help="a directory in the published layout")
    compress.add_argument("--fixed-plane", help="with --mesh FILE: fix nodes on e.g. z=min")
    compress.add_argument("--fixed-nodes", type=Path, help="with --mesh FILE: file of node indices")
    compress.add_argument("--lesion", type=int, default=None, help="with --scene: tumour number")
    compress.add_argument(
        "--scale", type=float, default=None, help="with --mesh FILE: factor to metres (0.001: mm)"
    )
    compress.add_argument("--young", type=float, help="tissue Young's modulus [Pa] (default 2850)")
    compress.add_argument("--poisson", type=float, help="tissue Poisson ratio (default 0.49)")
    compress.add_argument(
        "--probe",
        default=None,
        help="face | sphere:R | box:LX,LY,LZ | cylinder:R,H | FILE (metres; default face)",
    )
    compress.add_argument("--at", type=_pair, help="X,Y [m]: the surface point to press")
    compress.add_argument("--direction", type=_triple, default=(0.0, 0.0, -1.0), help="DX,DY,DZ")
    compress.add_argument(
        "--depths", type=_floats, default=None, help="D1,D2,... [m] past first contact"
    )
    compress.add_argument("--speed", type=float, default=0.01, help="probe speed [m/s]")
    compress.add_argument(
        "--settle-steps",
        type=int,
        default=None,
        help="most steps held still at each depth to settle (default 250, 5 s)",
    )
    compress.add_argument(
        "--contact", "--method", dest="method", default="lm", help="penalty | lm | prescribed | pbd"
    )
    compress.add_argument(
        "--profile", "--mode", dest="mode", default="robust", help="paper | robust"
    )
    compress.add_argument(
        "--online",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="prescribed: update the contact node set every step, the nodes sticking to "
        "the probe (--online, as the study's robust cells) or fix it at first contact or "
        "the scene's own (--no-online); default: the profile's (robust: online, sliding, "
        "the skin guarded; paper: fixed)",
    )
    compress.add_argument(
        "--sliding",
        action="store_true",
        help="prescribed, online: frictionless contact (nodes held along the probe's normal "
        "only, free to slide on it) instead of nodes moving rigidly with the probe",
    )
    compress.add_argument(
        "--json", type=Path, default=None, help="output (default probegym-out/compress/)"
    )
    compress.add_argument(
        "--case",
        default=None,
        help="run a named hard case (see probegym hard-cases) with --method and --mode",
    )

    study = commands.add_parser(
        "study", help="the compression study of Tagliabue et al. 2020: tables, figures, report"
    )
    from agents.lab.study.command import add_study_arguments
    from agents.learning.transfer.command import add_transfer_arguments

    add_study_arguments(study)
    add_transfer_arguments(study)

    hard = commands.add_parser(
        "hard-cases", help="the hard-case catalogue: which methods stay stable where"
    )
    hard.add_argument("--cases", default=None, help="comma-separated names; default all small")
    hard.add_argument(
        "--contact", "--methods", dest="methods", default="lm,penalty,prescribed,pbd",
        help="comma-separated contact methods",
    )  # fmt: skip
    hard.add_argument(
        "--profile", "--config", dest="config", default="robust", help="paper | robust | both"
    )
    hard.add_argument("--level", type=_level, default=None, help="override every case's level")
    hard.add_argument("--scene", type=Path, default=None, help="published scene (paper_level4)")
    hard.add_argument(
        "--json", type=Path, default=None, help="output (default probegym-out/hard-cases/)"
    )

    bench = commands.add_parser("bench", help="benchmarks that print a table and write JSON")
    bench_kinds = bench.add_subparsers(dest="bench", required=True, metavar="BENCHMARK")
    tissue = bench_kinds.add_parser("tissue", help="assembly, paper step, factorisation, Newton")
    tissue.add_argument(
        "--levels",
        type=_levels,
        default=None,
        help="comma-separated levels (default: 623 to 26220; add 105004,176506 for the finest)",
    )
    tissue.add_argument("--repeats", type=int, default=15, help="timed repeats per figure")
    tissue.add_argument("--json", type=Path, default=None, help="default probegym-out/bench/")
    contact = bench_kinds.add_parser("contact", help="step time, force, penetration per method")
    contact.add_argument("--levels", type=_levels, default=None, help="default 623 to 26220")
    contact.add_argument(
        "--contact", "--methods", dest="methods", default=None, help="comma-separated; default all"
    )
    contact.add_argument(
        "--profile", "--modes", dest="modes", default="paper,robust", help="comma-separated"
    )
    contact.add_argument(
        "--skin", type=_skins, default=None, help=_SKIN_HELP.format(default="paper,2")
    )
    contact.add_argument("--json", type=Path, default=None, help="default probegym-out/bench/")
    env = bench_kinds.add_parser("env", help="environment steps per second, per method")
    env.add_argument("--ids", default=None, help="comma-separated env ids; default all")
    env.add_argument(
        "--contact", "--methods", dest="methods", default=None, help="comma-separated; default all"
    )
    env.add_argument(
        "--profile", "--profiles", dest="profiles", default="robust", help="comma-separated"
    )
    env.add_argument("--levels", type=_levels, default=None, help="default 1363,2539")
    env.add_argument("--skin", type=_skins, default=None, help=_SKIN_HELP.format(default="2,paper"))
    env.add_argument("--json", type=Path, default=None, help="default probegym-out/bench/")
    train_bench = bench_kinds.add_parser(
        "train",
        help="a training step's cost by phase: the scripted press, exploring, probegym train",
    )
    train_bench.add_argument(
        "--ids", default=None, help="comma-separated env ids; default probegym/BreastCompress-v2"
    )
    train_bench.add_argument(
        "--contact", "--methods", dest="methods", default=None, help="comma-separated; default lm"
    )
    train_bench.add_argument("--level", type=int, default=1363, help="phantom level (default 1363)")
    train_bench.add_argument(
        "--algo", default="ppo,sac", help="comma-separated algorithms of the train phase "
        "(default ppo,sac; none: skip it)",
    )  # fmt: skip
    train_bench.add_argument(
        "--n-envs", type=int, default=2, help="the train phase's worker processes (default 2)"
    )
    train_bench.add_argument(
        "--train-steps", type=int, default=None,
        help="the train phase's environment steps (default: PPO three updates, SAC 3,000)",
    )  # fmt: skip
    train_bench.add_argument(
        "--model", type=Path, default=None,
        help="a probegym train run (folder or .zip) trained on one of --ids: replay its policy",
    )  # fmt: skip
    train_bench.add_argument("--json", type=Path, default=None, help="default probegym-out/bench/")
    sweep = bench_kinds.add_parser("sweep", help="each method's force along a sweep, against LM")
    sweep.add_argument(
        "--seeds", type=seed_list, default=[0, 1, 2, 3, 4], help="comma-separated ForceScan seeds"
    )
    sweep.add_argument(
        "--contact", "--methods", dest="methods", default=None,
        help="comma-separated methods to replay; default penalty,prescribed,pbd",
    )  # fmt: skip
    sweep.add_argument("--mesh", type=_level, default=1363, help="phantom level (default 1363)")
    sweep.add_argument("--profile", default="robust", help="paper or robust (default robust)")
    sweep.add_argument("--json", type=Path, default=None, help="default probegym-out/bench/")
    effects = bench_kinds.add_parser(
        "effects", help="what each simulated effect costs; free air against robot only"
    )
    effects.add_argument(
        "--contact", "--methods", dest="methods", default=None, help="comma-separated; default all"
    )
    effects.add_argument(
        "--profile", "--profiles", dest="profiles", default="robust,paper", help="comma-separated"
    )
    effects.add_argument("--mesh", type=_level, default=1363, help="phantom level (default 1363)")
    effects.add_argument("--json", type=Path, default=None, help="default probegym-out/bench/")
    peer = bench_kinds.add_parser("peer", help="ours against MuJoCo's flex, same phantom")
    peer.add_argument("--levels", type=_levels, default=None, help="default 623,4126,26220")
    peer.add_argument("--sim-seconds", type=float, default=1.0, help="simulated seconds per run")
    peer.add_argument("--json", type=Path, default=None, help="default probegym-out/bench/")
    add_train_parser(commands)
    add_evaluate_parser(commands)
    add_envs_parser(commands)
    add_view_parser(commands)
    return parser


# compress options a named hard case sets itself (its path, probe, material, node set).
_CASE_SETS = (
    "fixed_plane", "fixed_nodes", "lesion", "young", "poisson", "probe", "at", "direction",
    "depths", "speed", "settle_steps", "online", "sliding",
)  # fmt: skip


def _reject_options_a_case_sets(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """A clear error for ``compress --case`` with options the case would silently override."""
    defaults = parser.parse_args(["compress"])
    given = [
        "--" + name.replace("_", "-")
        for name in _CASE_SETS
        if getattr(args, name) != getattr(defaults, name)
    ]
    if given:
        raise ConfigError(
            f"--case {args.case} sets its own path, probe, material and node set; drop "
            f"{', '.join(given)} (only --mesh LEVEL, --scene, --method, --mode and --json apply)"
        )


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``probegym`` console script."""
    parser = _build_parser()
    args = parser.parse_args(argv)
    # How the run was asked for, as benchmarks record it beside their tables.
    args.command_line = "probegym " + shlex.join(list(argv) if argv is not None else sys.argv[1:])
    try:
        _check_outputs(args)  # before any work: a bad path is a one-line error, exit 2
        # The process's thread policy, explicitly (TBB, MKL sequential; see tissue.threads).
        from tissue import configure_threads

        configure_threads()
        if args.command in ("demo", "compress", "hard-cases", "bench"):
            from agents.lab.first_use import announce_compilation

            announce_compilation()
        return _run(parser, args)
    except TissueInputError as error:
        print(f"probegym: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"probegym: interrupted; {_kept(args)}", file=sys.stderr)
        return 130


def _check_outputs(args: argparse.Namespace) -> None:
    """Give every output option its default under probegym-out/ and check it is writable."""
    from agents.outputs import check_output_file, check_output_folder, default_output

    if args.command == "study":
        if args.out is None:
            args.out = default_output("study", "")
        check_output_folder(args.out, "--out")
        return
    if args.command == "mesh":
        check_output_file(args.out, "--out")
        return
    defaults = {
        "compress": ("compress", "compress.json"),
        "hard-cases": ("hard-cases", "hard_cases.json"),
    }
    if args.command == "bench":
        defaults["bench"] = ("bench", f"bench_{args.bench}.json")
    if args.command in defaults and hasattr(args, "json"):
        if args.json is None:
            args.json = default_output(*defaults[args.command])
        check_output_file(args.json, "--json")


def _kept(args: argparse.Namespace) -> str:
    """What an interrupted command kept, and how to go on."""
    if args.command == "study":
        results = f"{args.out}/robot/results.jsonl" if args.robot else f"{args.out}/results.jsonl"
        return (
            f"every cell finished so far is kept in {results}; run the same command again to resume"
        )
    if args.command == "train":
        return (
            "the checkpoints written so far are kept in the --out folder; run the same command "
            "again to resume from the latest"
        )
    return "nothing was written"


def _run(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    """Run the parsed command; returns its exit status."""
    if args.command == "demo":
        from agents.lab.tissue_demo import run_demo

        return run_demo(level=args.level, depth_m=args.depth_mm * 1e-3, mode=args.mode)
    if args.command == "compress" and args.case is not None:
        from agents.lab.hard_cases import run_catalogue
        from tissue.lab import parse_level

        _reject_options_a_case_sets(parser, args)

        level = None if args.mesh is None else parse_level(args.mesh)
        records = run_catalogue(
            [args.case], [args.method], [args.mode], level, args.scene, args.json
        )
        return 0 if all(record["stable"] for record in records) else 1
    if args.command == "compress":
        from agents.lab.compress_command import run_compress_command

        return run_compress_command(args)
    if args.command == "study" and args.transfer:
        from agents.learning.transfer.command import run_transfer_command

        return run_transfer_command(args)
    if args.command == "study":
        from agents.lab.study.command import run_study_command

        return run_study_command(args)
    if args.command == "hard-cases":
        from agents.lab.hard_cases import SMALL_CASES, run_catalogue

        configs = [Profile.parse(c).value for c in args.config.split(",")]
        cases = args.cases.split(",") if args.cases else list(SMALL_CASES)
        run_catalogue(cases, args.methods.split(","), configs, args.level, args.scene, args.json)
        return 0
    if args.command == "mesh":
        return _mesh(args.level, args.out)
    if args.command == "bench" and args.bench == "tissue":
        from agents.lab.bench.tissue import run_tissue_benchmark

        if args.repeats < 1:
            parser.error(f"--repeats must be >= 1; got {args.repeats}")
        run_tissue_benchmark(args.levels, args.repeats, args.json, command=args.command_line)
        return 0
    if args.command == "bench" and args.bench == "contact":
        from agents.lab.bench.contact import DEFAULT_LEVELS as CONTACT_LEVELS
        from agents.lab.bench.contact import run_contact_benchmark

        methods, modes = _methods_and_profiles(parser, args.methods, args.modes)
        _check_skins(parser, args.skin, list(args.levels or CONTACT_LEVELS))
        run_contact_benchmark(
            args.levels, methods, modes, args.json, command=args.command_line, skins=args.skin
        )
        return 0
    if args.command == "bench" and args.bench == "env":
        from agents.lab.bench.env import DEFAULT_LEVELS as ENV_LEVELS
        from agents.lab.bench.env import run_env_benchmark

        methods, profiles = _methods_and_profiles(parser, args.methods, args.profiles)
        _check_skins(parser, args.skin, list(args.levels or ENV_LEVELS))
        run_env_benchmark(
            _names(args.ids),
            methods,
            profiles,
            args.levels,
            args.json,
            command=args.command_line,
            skins=args.skin,
        )
        return 0
    if args.command == "bench" and args.bench == "train":
        from agents.lab.bench.train import run_train_benchmark

        methods, _ = _methods_and_profiles(parser, args.methods, "robust")
        run_train_benchmark(
            _names(args.ids),
            methods,
            args.level,
            args.json,
            command=args.command_line,
            algos=_train_algos(parser, args.algo),
            n_envs=_at_least_one(parser, "--n-envs", args.n_envs),
            steps=None
            if args.train_steps is None
            else _at_least_one(parser, "--train-steps", args.train_steps),
            model=args.model,
        )
        return 0
    if args.command == "bench" and args.bench == "effects":
        from agents.lab.bench.effects import run_effects_benchmark

        methods, profiles = _methods_and_profiles(parser, args.methods, args.profiles)
        run_effects_benchmark(methods, profiles, args.mesh, args.json, command=args.command_line)
        return 0
    if args.command == "evaluate":
        return run_evaluate(args)
    if args.command == "envs":
        return run_envs(args)
    if args.command == "view":
        return run_view(args)
    if args.command == "train":
        from agents.learning.train.command import run_train

        return run_train(args)
    if args.command == "bench" and args.bench == "sweep":
        from agents.lab.bench.sweep import run_sweep_benchmark

        methods, profiles = _methods_and_profiles(parser, args.methods, args.profile)
        if len(profiles) != 1:
            parser.error(f"bench sweep takes one --profile; got {args.profile!r}")
        run_sweep_benchmark(
            args.seeds, methods, args.mesh, profiles[0], args.json, command=args.command_line
        )
        return 0
    if args.command == "bench" and args.bench == "peer":
        from agents.lab.bench.peer import run_peer_benchmark

        if not args.sim_seconds > 0:
            parser.error(f"--sim-seconds must be > 0; got {args.sim_seconds}")
        run_peer_benchmark(args.levels, args.json, args.sim_seconds, command=args.command_line)
        return 0
    parser.error("unknown command")
    return 2


def _mesh(level: int, out: Path) -> int:
    from tissue.lab import breast_phantom, describe_mesh, write_mesh

    mesh = breast_phantom(level)
    path = write_mesh(mesh, out)
    print(describe_mesh(mesh))
    print(f"written: {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
