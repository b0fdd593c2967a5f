"""``probegym envs``: the registered environments, the effects their terms need and the
scenes they run on, then each scene's effects. Read from the classes: nothing is built."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any


def add_envs_parser(commands: Any) -> None:
    """The ``envs`` subcommand."""
    parser = commands.add_parser(
        "envs", help="list the environments, the effects they need and the scenes they run on"
    )
    parser.add_argument("--json", type=Path, default=None, help="also write the listing here")


def env_listing() -> dict[str, Any]:
    """Every registered environment (id, task, episode steps, effects its terms need, each
    term's needs, scenes that have them) and every scene (its effects, what it is)."""
    import gymnasium as gym

    import envs
    from envs.effects import EFFECTS, SCENES, needed_effects

    rows = []
    for env_id in envs.ENV_IDS:
        spec = gym.spec(env_id)
        task: Any = gym.envs.registration.load_env_creator(str(spec.entry_point))
        terms = {k: list(v) for k, v in task.TERM_EFFECTS.items()}
        needs = needed_effects({k: v for k, v in task.TERM_EFFECTS.items() if k != "image"})
        rows.append(
            {
                "id": env_id,
                "task": " ".join((task.__doc__ or "").strip().split("\n\n")[0].split()),
                "max_episode_steps": spec.max_episode_steps,
                "effects": [name for name in EFFECTS if name in needs],
                "scenes": [name for name, scene in SCENES.items() if needs <= scene.effects],
                "terms": terms,
            }
        )
    scenes = [
        {"name": scene.name, "effects": scene.listing().split(", "), "about": scene.description}
        for scene in SCENES.values()
    ]
    return {"environments": rows, "scenes": scenes, "effects": dict(EFFECTS)}


def run_envs(args: argparse.Namespace) -> int:
    """Print the listing (and write it as JSON with ``--json``)."""
    listing = env_listing()
    print("| id | task | steps | needs | scenes |")
    print("| --- | --- | --- | --- | --- |")
    for row in listing["environments"]:
        print(
            f"| {row['id']} | {row['task']} | {row['max_episode_steps']} | "
            f"{', '.join(row['effects'])} | {', '.join(row['scenes'])} |"
        )
    print()
    print("| scene | effects | about |")
    print("| --- | --- | --- |")
    for scene in listing["scenes"]:
        print(f"| {scene['name']} | {', '.join(scene['effects'])} | {scene['about']} |")
    print()
    print(
        "damping is added under the robust profile, sliding whenever the breast deforms; "
        "choose with gymnasium.make(ID, scene=NAME) or effects=[...] (docs/effects.md)"
    )
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(listing, indent=2) + "\n")
        print(f"wrote {args.json}")
    return 0
