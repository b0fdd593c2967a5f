"""Frames of each task for the docs: ``python -m agents.learning.task_frames [--out docs/images]``.

Runs each task's scripted policy (robust LM, the 1,303-tet phantom, seed 0) with the B-mode
image on, and saves the ``rgb_array`` frame (the 3D view with the image to its right) at
the start, when the lesion first shows (a task without one: after :data:`MIDDLE_STEP`
steps) and at the episode's end, as ``task-<task>-<when>.png``.

``--policy RUN [--seed S]``: a trained policy's episode instead (a ``probegym train``
folder; its env id and arguments from the run), saved as ``learned-<task>-<when>.png``
with ``learned-<task>-force.png`` beside them: the normal contact force over the episode,
the frames' steps marked.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path
from typing import Any

import numpy as np

#: (id, file stem, the policy's class name in agents.learning.policies).
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

    import agents.learning.policies
    import envs  # noqa: F401 - registers the environments

    out.mkdir(parents=True, exist_ok=True)
    written = []
    for env_id, stem, policy_name in TASKS:
        env = gym.make(env_id, mesh=mesh, image=True, render_mode="rgb_array", width=400,
                       height=400)  # fmt: skip
        policy: Any = getattr(agents.learning.policies, policy_name)()
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


def save_learned_frames(run: Path, out: Path, seed: int) -> list[Path]:
    """One episode of the trained policy in ``run`` (reset with ``seed``): its frames and
    its force trace into ``out`` (see the module docstring); the files written."""
    os.environ.setdefault("MUJOCO_GL", "egl")
    import gymnasium as gym
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    import envs  # noqa: F401 - registers the environments
    from agents.learning.train import load_policy

    policy = load_policy(run)
    env_id = str(policy.config["env_id"])
    kwargs = dict(policy.config.get("env_kwargs") or {})
    stem = "learned-" + _stem(env_id)
    env = gym.make(env_id, image=True, render_mode="rgb_array", width=400, height=400, **kwargs)
    obs, _ = env.reset(seed=seed)
    frames: dict[str, Any] = {"start": env.render()}
    marks = {"start": 0}
    forces: list[float] = []
    info: dict[str, Any] = {}
    keys = list(policy.model.observation_space.spaces)  # the image is drawn, not observed
    while True:
        action = policy({key: obs[key] for key in keys})
        obs, _, terminated, truncated, info = env.step(action)
        forces.append(float(info["normal_force_n"]))
        steps = len(forces)
        if "lesion" in obs and "seen" not in frames and obs["lesion"][3] > 0.5:
            frames["seen"], marks["seen"] = env.render(), steps
        if "lesion" not in obs and steps == MIDDLE_STEP:
            frames["middle"], marks["middle"] = env.render(), steps
        if terminated or truncated:
            break
    frames["end"], marks["end"] = env.render(), len(forces)
    env.close()
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for when, frame in frames.items():
        path = out / f"{stem}-{when}.png"
        plt.imsave(path, np.asarray(frame))
        written.append(path)
    figure, axes = plt.subplots(figsize=(6, 2.4))
    axes.plot(np.arange(1, len(forces) + 1), forces, color="tab:blue")
    for when, step in marks.items():
        axes.axvline(step, color="0.6", linestyle=":")
        axes.annotate(when, (step, 0), xytext=(2, 2), textcoords="offset points", fontsize=8)
    axes.set_xlabel("step (20 ms)")
    axes.set_ylabel("normal force [N]")
    outcome = "success" if info.get("is_success") else "no success"
    axes.set_title(f"{env_id}, {policy.config['algo']} seed {policy.config['seed']}, "
                   f"episode seed {seed}: {outcome}", fontsize=9)  # fmt: skip
    figure.tight_layout()
    path = out / f"{stem}-force.png"
    figure.savefig(path, dpi=120)
    plt.close(figure)
    written.append(path)
    print(f"{env_id} ({run}): {outcome} in {len(forces)} steps, frames {sorted(frames)}")
    return written


def _stem(env_id: str) -> str:
    """``probegym/LesionSearch-v1`` -> ``lesion-search-v1``."""
    name = env_id.split("/")[-1]
    words = "".join("-" + c.lower() if c.isupper() else c for c in name).lstrip("-")
    return words


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("docs/images"))
    parser.add_argument("--policy", type=Path, default=None, help="a probegym train folder")
    parser.add_argument("--seed", type=int, default=0, help="the episode's seed (--policy)")
    args = parser.parse_args()
    if args.policy is not None:
        written = save_learned_frames(args.policy, args.out, args.seed)
    else:
        written = save_frames(args.out)
    for path in written:
        print(f"written: {path}")


if __name__ == "__main__":
    main()
