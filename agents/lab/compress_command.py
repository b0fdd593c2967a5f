"""Argument handling of ``probegym compress`` (the work is in :mod:`agents.lab.compress`)."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from agents.lab.compress import (
    ACCURATE_SETTLE_STEPS,
    build_model,
    plan_scene,
    plan_straight,
    run_compression,
    write_json,
)
from tissue import ConfigError, ProbeShape
from tissue.lab import (
    StabilityMonitor,
    TetMesh,
    parse_probe_spec,
    profile_choices,
    spring_nodes_to_volume,
)

# Synthetic default depths past first contact [m] (the study's: 10, 20, 25, 30 mm).
DEFAULT_DEPTHS_M = [0.01, 0.02, 0.025, 0.03]


def _load_mesh(args: argparse.Namespace) -> TetMesh:
    mesh_arg = str(args.mesh) if args.mesh is not None else "4126"
    if Path(mesh_arg).suffix:
        from tissue.lab import load_tet_mesh

        if args.fixed_plane is None and args.fixed_nodes is None:
            raise ConfigError(
                f"--mesh {mesh_arg} needs its fixed nodes: --fixed-plane AXIS=min|max or "
                "--fixed-nodes FILE"
            )
        return load_tet_mesh(
            mesh_arg,
            fixed_plane=args.fixed_plane,
            fixed_nodes_file=args.fixed_nodes,
            scale=1.0 if args.scale is None else args.scale,
        )
    if args.fixed_plane is not None or args.fixed_nodes is not None or args.scale is not None:
        raise ConfigError("--fixed-plane, --fixed-nodes and --scale apply to --mesh FILE only")
    from tissue.lab import breast_phantom, parse_level

    return breast_phantom(parse_level(mesh_arg))


def run_compress_command(args: argparse.Namespace) -> int:
    """Validate the arguments, run the compression, write the JSON; returns the exit code."""
    settle = ACCURATE_SETTLE_STEPS if args.settle_steps is None else args.settle_steps
    if settle < 1:
        raise ConfigError(
            f"--settle-steps must be a whole number of steps >= 1; got {settle} "
            f"(default {ACCURATE_SETTLE_STEPS}: a hold of up to 5 s at each depth)"
        )
    # None: the profile's node set (tissue.spec: robust online, sliding, skin guarded; paper
    # chosen at first contact, or on the published scene its own set).
    online = args.online
    given_nodes = None
    if args.lesion is not None and args.scene is None:
        raise ConfigError(
            f"--lesion {args.lesion} picks a tumour of the published scene; give --scene DIR "
            "too (on the built-in phantom, choose the point to press with --at X,Y)"
        )
    if args.scene is not None:
        args.lesion = 1 if args.lesion is None else args.lesion
        from tissue.lab import load_paper_scene

        scene = load_paper_scene(args.scene)
        if args.lesion not in scene.probe_poses:
            raise ConfigError(
                f"--lesion {args.lesion} is not in {args.scene}; choose one of "
                f"{sorted(scene.probe_poses)}"
            )
        mesh = scene.mesh
        paper_set = online is False or (
            online is None and not profile_choices(args.mode).online_prescribed
        )
        if args.method == "prescribed" and paper_set:  # the paper's set for this lesion
            given_nodes = spring_nodes_to_volume(mesh, scene.spring_nodes[args.lesion])
    else:
        mesh = _load_mesh(args)
    # The scene's own collision STL is the same face as "face" but only 2.7 mm thick: the
    # default probe keeps that face and adds the probe's body behind it (see linear_probe).
    shape: ProbeShape = parse_probe_spec(args.probe or "face")
    model = build_model(
        mesh,
        shape,
        args.method,
        args.mode,
        args.young,
        args.poisson,
        online,
        given_nodes,
        sliding=args.sliding,
    )
    if args.scene is not None:
        if args.depths is not None or args.at is not None:
            raise ConfigError(
                "with --scene the scene's probe poses are the path; drop --at/--depths"
            )
        start, stops = plan_scene(scene.probe_poses[args.lesion])
    else:
        depths = args.depths if args.depths is not None else DEFAULT_DEPTHS_M
        direction = np.asarray(args.direction, dtype=np.float64)
        start, stops = plan_straight(model, args.at, direction, depths)
    print(
        f"compress: {mesh.name} ({mesh.tet_count} tets), probe {shape.name}, "
        f"method {args.method}, mode {args.mode}, {len(stops)} depths"
    )
    monitor = StabilityMonitor(args.method, mesh.nodes, start.position)
    record = run_compression(
        model,
        start,
        stops,
        args.speed,
        progress=True,
        monitor=monitor,
        max_settle_steps=settle,
    )
    record["config"] = {
        "mesh": mesh.name,
        "tets": mesh.tet_count,
        "method": args.method,
        "mode": args.mode,
        "probe": shape.name,
        "speed_m_s": args.speed,
        "settle_steps": settle,
        "online": getattr(getattr(model, "params", None), "online", None),
        "sliding": getattr(getattr(model, "params", None), "sliding", None),
    }
    write_json(record, args.json)
    print(f"written: {args.json} ({len(record['steps'])} steps)")
    # Exit status: 0 the compression completed stably, 1 it met an instability (recorded in
    # the JSON's "instability"), 2 bad input.
    return 0 if record.get("instability") is None else 1
