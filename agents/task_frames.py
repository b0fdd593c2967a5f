"""Frames of each task for the docs: ``python -m agents.task_frames [--out docs/images]``.

Runs each task's scripted policy (robust LM, the 1,303-tet phantom, seed 0) with the B-mode
image on, and saves the ``rgb_array`` frame (the 3D view with the image to its right) at
the start, when the lesion first shows (a task without one: after :data:`MIDDLE_STEP`
steps) and at the episode's end, as ``task-<task>-<when>.png``.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path
from typing import Any

import numpy as np

#: (id, file stem, the policy's class name in agents.policies).
TASKS = (
    ("probegym/BreastCompress-v0", "breast-compress", "CompressionPolicy"),
    ("probegym/LesionSearch-v0", "lesion-search", "LesionSearchPolicy"),
    ("probegym/ForceScan-v0", "force-scan", "ForceScanPolicy"),
)
#: Without a lesion in the observation, the middle frame is taken after this many steps.
MIDDLE_STEP = 20


def save_frames(out: Path, mesh: int = 1363, seed: int = 0) -> list[Path]:
    """Run every task once and save its frames into ``out``; the files written."""
    os.environ.setdefault("MUJOCO_GL", "egl")
    import gymnasium as gym
    import matplotlib.pyplot as plt

    import agents.policies
    import envs  # noqa: F401 - registers the environments

    out.mkdir(parents=True, exist_ok=True)
    written = []
    for env_id, stem, policy_name in TASKS:
        env = gym.make(env_id, mesh=mesh, image=True, render_mode="rgb_array", width=400,
                       height=400)  # fmt: skip
        policy: Any = getattr(agents.policies, policy_name)()
        obs, _ = env.reset(seed=seed)
        frames = {"start": env.render()}
        info: dict[str, Any] = {}
        steps = 0
        while True:
            obs, _, terminated, truncated, info = env.step(policy(obs))
            steps += 1
            if "lesion" in obs and "seen" not in frames and obs["lesion"][3] > 0.5:
                frames["seen"] = env.render()
            if "lesion" not in obs and steps == MIDDLE_STEP:
                frames["middle"] = env.render()
            if terminated or truncated:
                break
        frames["end"] = env.render()
        env.close()
        for when, frame in frames.items():
            path = out / f"task-{stem}-{when}.png"
            plt.imsave(path, np.asarray(frame))
            written.append(path)
        print(f"{env_id}: success {info.get('is_success')}, frames {sorted(frames)}")
    return written


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("docs/images"))
    args = parser.parse_args()
    for path in save_frames(args.out):
        print(f"written: {path}")


if __name__ == "__main__":
    main()
