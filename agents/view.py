"""``probegym view``: the coupled scene in MuJoCo Studio's web viewer.

Serves the robot, the probe and the deforming breast of one environment on 127.0.0.1 (the
viewer has no authentication; ``--host`` binds another interface, with a warning), prints
the address it bound and runs until Ctrl-C. In the browser: choose the task, contact method
and mesh, reset, teleoperate the probe (sliders, or keys W/S A/D Q/E) or play a policy, and
watch the ultrasound image, the contact force and the lesion's depth (``docs/view.md``).

``--policy scripted`` gives each task its scripted policy, ``--policy random`` uniform
actions, ``--policy PATH`` a model trained by ``probegym train`` (its training
environment's arguments are the defaults; it drives only the task it was trained on). The
policy is loaded here and handed to the simulation plugin as a callable: ``envs`` never
imports torch or stable-baselines3.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

from tissue import ConfigError

DEFAULT_ENV = "probegym/BreastCompress-v2"
#: The mesh levels the viewer offers beside the one given (finer ones step too slowly to
#: drive by hand on a laptop; any level or mesh file can be given with --mesh).
VIEW_LEVELS = (623, 1363, 2539, 4126)


def add_view_parser(commands: Any) -> argparse.ArgumentParser:
    """Add the ``view`` subcommand to an ``add_subparsers()`` object; returns it."""
    parser: argparse.ArgumentParser = commands.add_parser(
        "view",
        help="serve the coupled scene in MuJoCo Studio's web viewer (drive the probe, "
        "play a policy)",
        description="Serve the arm, probe and deforming breast of an environment in MuJoCo "
        "Studio's web viewer on 127.0.0.1, print the address and run until Ctrl-C. "
        "See docs/view.md.",
    )
    parser.add_argument(
        "env_id",
        nargs="?",
        default=DEFAULT_ENV,
        metavar="ENV_ID",
        help=f"the environment (default {DEFAULT_ENV}; see probegym envs)",
    )
    parser.add_argument(
        "--contact", default=None, help="penalty | lm | prescribed | pbd (default: the env's)"
    )
    parser.add_argument(
        "--mesh",
        default=None,
        help="phantom level (tet count, e.g. 623) or a tet-mesh file (default: the env's)",
    )
    parser.add_argument(
        "--policy",
        default=None,
        help="'scripted' (each task's scripted policy), 'random', or PATH: a probegym train "
        "folder or a model .zip in one (default: none, teleoperation only)",
    )
    parser.add_argument("--seed", type=int, default=0, help="the first episode's seed")
    parser.add_argument(
        "--port",
        type=int,
        default=0,
        help="the port to serve on (default 0: the first free port from 8080)",
    )
    parser.add_argument(
        "--host",
        default="127.0.0.1",
        help="the interface to bind (default 127.0.0.1; anything else is reachable by "
        "others and the viewer has no authentication)",
    )
    parser.add_argument(
        "--native",
        action="store_true",
        help="open Studio's desktop viewer instead (needs a display and Python 3.12+)",
    )
    parser.add_argument(
        "--stats",
        type=float,
        default=0.0,
        metavar="SECONDS",
        help="print a status line this often while a browser is connected (default: never)",
    )
    return parser


def _mesh_argument(mesh: str | None) -> int | str | None:
    """A phantom level as an int, a mesh file as its path."""
    if mesh is None:
        return None
    text = mesh.strip().replace(",", "").replace("_", "")
    return int(text) if text.isdigit() else mesh


def resolve_view_policy(
    env_id: str, policy: str | None
) -> tuple[dict[str, Any], str, dict[str, Any]]:
    """The policy factories per environment id, the policy's label and the environment's
    keyword arguments a trained policy brings.

    Raises:
        ConfigError: an unknown environment or a policy that cannot be loaded (the message
            says what to give).
    """
    import envs

    if env_id not in envs.ENV_IDS:
        raise ConfigError(
            f"unknown environment {env_id!r}; choose one of {', '.join(envs.ENV_IDS)}"
        )
    if policy is None:
        return {}, "", {}
    from agents.learning.evaluation.run import SCRIPTED, resolve_policy

    if policy == SCRIPTED:
        from agents.learning.policies import SCRIPTED_POLICIES

        return dict(SCRIPTED_POLICIES), SCRIPTED, {}
    label, factory, kwargs = resolve_policy(env_id, policy, {})
    return {env_id: factory}, label, kwargs


def run_view(args: argparse.Namespace) -> int:
    """Build the environment, serve the viewer, print its address, run until Ctrl-C."""
    import envs
    import tissue
    from envs.studio import (
        ProbeSimulation,
        check_host,
        check_port,
        launch_native,
        launch_web,
        listening_sockets,
        native_viewer_problem,
        run_until_closed,
        viewer_plugins,
    )

    if args.native and native_viewer_problem():
        raise ConfigError(
            f"--native: {native_viewer_problem()}; use the web viewer (drop --native)"
        )
    host, warning = check_host(args.host)
    port = check_port(args.port)
    if not (args.stats >= 0.0):
        raise ConfigError(f"--stats must be a number of seconds >= 0; got {args.stats!r}")
    if isinstance(args.seed, bool) or args.seed < 0:
        raise ConfigError(f"--seed must be a whole number >= 0; got {args.seed!r}")
    policies, label, env_kwargs = resolve_view_policy(args.env_id, args.policy)
    mesh = _mesh_argument(args.mesh)
    simulation = ProbeSimulation(
        args.env_id,
        contact=args.contact,
        mesh=mesh,
        env_kwargs=env_kwargs,
        policies=policies,
        policy_label=label,
        seed=args.seed,
        env_ids=envs.ENV_IDS,
        contacts=tissue.contact_methods(),
        meshes=VIEW_LEVELS,
    )
    simulation.build()  # bad --contact / --mesh: a one-line error before anything listens
    plugins = [simulation, *viewer_plugins(stats_every_s=args.stats)]
    from mujoco.studio import messages

    if args.native:
        handle = launch_native(plugins)
        print("probegym view: the native viewer is open (close it or Ctrl-C to stop)")
    else:
        if warning:
            print(f"probegym view: {warning}", file=sys.stderr, flush=True)
        served = launch_web(plugins, host=host, port=port)
        handle = served.handle
        beyond = [
            address
            for address, _ in listening_sockets()
            if address not in ("127.0.0.1", "::1", host)
        ]
        if beyond and not warning:
            handle.close()
            raise ConfigError(
                f"the viewer listens on {beyond}, not only on loopback: refusing to serve "
                "(install the mujoco version probegym pins)"
            )
        print(f"probegym view: serving {served.url} (Ctrl-C to stop)", flush=True)
    try:
        handle.dispatch(messages.LoadModelEvent(path=""))
        run_until_closed(handle)
    except KeyboardInterrupt:
        print("probegym view: stopped", flush=True)
    finally:
        handle.close()
    return 0
