"""``probegym envs``: the listing says on which scenes each environment can be made, and
that is where it can be made."""

from __future__ import annotations

import json
from pathlib import Path

import gymnasium as gym
import pytest

from agents.cli import main
from envs.effects import SCENES
from envs.errors import EnvConfigError


def test_the_listing_matches_what_can_be_made(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    assert main(["envs", "--json", str(tmp_path / "envs.json")]) == 0
    printed = capsys.readouterr().out
    listing = json.loads((tmp_path / "envs.json").read_text())
    assert {row["id"] for row in listing["environments"]} == {
        "probegym/BreastCompress-v0",
        "probegym/LesionSearch-v0",
        "probegym/ForceScan-v0",
        "probegym/LesionSearch-v1",
        "probegym/ForceScan-v1",
        "probegym/BreastCompress-v1",
        "probegym/BreastCompress-v2",
    }
    for row in listing["environments"]:
        assert row["id"] in printed
        for scene in SCENES:
            if scene in row["scenes"]:
                gym.make(row["id"], mesh=623, scene=scene).close()
            else:
                with pytest.raises(EnvConfigError, match=f"scene '{scene}'"):
                    gym.make(row["id"], mesh=623, scene=scene)
