"""Shared test fixtures: a private mesh cache and the location of the published scene."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

SHARED_SCENE = Path(__file__).resolve().parents[2] / "shared" / "paper-scene"

# Offscreen rendering without a display: Mesa's EGL (set before MuJoCo's renderer loads).
if not os.environ.get("DISPLAY"):
    os.environ.setdefault("MUJOCO_GL", "egl")


@pytest.fixture(autouse=True, scope="session")
def _private_mesh_cache(tmp_path_factory: pytest.TempPathFactory) -> None:
    """Generated meshes go to a per-run cache, so tests never depend on a user's cache."""
    if "PROBEGYM_CACHE_DIR" not in os.environ:
        os.environ["PROBEGYM_CACHE_DIR"] = str(tmp_path_factory.mktemp("probegym-cache"))


@pytest.fixture
def paper_scene_dir() -> Path:
    """The published scene of Tagliabue et al. (read-only test data beside the project)."""
    if not SHARED_SCENE.is_dir():
        pytest.skip(
            f"the published scene is not present at {SHARED_SCENE} (test data, not shipped)"
        )
    return SHARED_SCENE
