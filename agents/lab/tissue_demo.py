"""A short tissue demo: press the probe's footprint into the built-in phantom and report."""

from __future__ import annotations

import math

import numpy as np

from tissue import ConfigError, TissueMaterials
from tissue.lab import (
    PAPER_PROBE_SPEED_M_S,
    SimulationConfig,
    TissueSimulator,
    breast_phantom,
    describe_mesh,
    top_surface_nodes,
)

# The linear probe's face, about 53 x 13 mm (us_probe_collision.stl of the published scene).
PROBE_FACE_HALF_SIZE_M = (0.0265, 0.0065)


#: The deepest demo press [m]: the study's deepest, past which the probe nears the base.
DEMO_MAX_DEPTH_M = 0.03


def run_demo(level: int = 4126, depth_m: float = 0.01, mode: str = "robust") -> int:
    """Compress the phantom's apex by ``depth_m`` [m] at 0.01 m/s and print what happened."""
    if not (math.isfinite(depth_m) and 0.0 < depth_m <= DEMO_MAX_DEPTH_M):
        raise ConfigError(
            f"--depth-mm must be a depth in (0, {DEMO_MAX_DEPTH_M * 1e3:g}] mm; got "
            f"{depth_m * 1e3:g} (the phantom is 80 mm tall)"
        )
    mesh = breast_phantom(level)
    print(describe_mesh(mesh))
    sim = TissueSimulator(mesh, TissueMaterials(), SimulationConfig(mode=mode))
    center = mesh.nodes[:, :2].min(axis=0) / 2 + mesh.nodes[:, :2].max(axis=0) / 2
    # Every surface node under the face's footprint can be reached; each one is held at the
    # face's height (along z only: the face is frictionless) from the step the face reaches it.
    candidates = top_surface_nodes(
        mesh, (center[0], center[1]), PROBE_FACE_HALF_SIZE_M, depth_m=depth_m + 0.01
    )
    top = mesh.nodes[candidates, 2].max()
    dt = sim.config.tissue_dt
    step_count = int(np.ceil(depth_m / (PAPER_PROBE_SPEED_M_S * dt)))
    print(
        f"pressing a flat 53 x 13 mm probe face {depth_m * 1e3:.1f} mm into the apex at "
        f"{PAPER_PROBE_SPEED_M_S * 1e3:.0f} mm/s ({step_count} steps of {dt * 1e3:.0f} ms, "
        f"{mode} mode; "
        "surface nodes under the face follow it once reached)"
    )
    header = ("depth mm", "nodes", "force N", "lesion 1 moved mm", "step ms")
    print("{:>9} {:>6} {:>9} {:>18} {:>8}  status".format(*header))
    rest_landmarks = sim.landmark_positions()
    times = []
    for step in range(1, step_count + 1):
        depth = min(depth_m, step * PAPER_PROBE_SPEED_M_S * dt)
        face_z = top - depth
        in_contact = candidates[sim.positions[candidates, 2] >= face_z]
        sim.prescribe(in_contact, np.array([0.0, 0.0, face_z]), axes=(2,))
        result = sim.step()
        times.append(result.compute_ms)
        if step % max(1, step_count // 10) == 0 or step == step_count:
            force = -result.reaction_force_n(in_contact)  # the tissue pushing on the probe
            moved = (
                np.linalg.norm(result.landmarks[0] - rest_landmarks[0]) * 1e3
                if result.landmarks.size
                else float("nan")
            )
            print(
                f"{depth * 1e3:9.2f} {in_contact.size:6d} {force[2]:9.3f} {moved:18.2f} "
                f"{result.compute_ms:8.1f}  {result.status.value}"
            )
    print(f"median step time: {np.median(times):.1f} ms (real time is {dt * 1e3:.0f} ms)")
    return 0
