"""Shared test fixtures: a private mesh cache and the location of the published scene."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

SHARED_SCENE = Path(__file__).resolve().parents[2] / "shared" / "paper-scene"

# Offscreen rendering without a display: Mesa's EGL (set before MuJoCo's renderer loads).
if not os.environ.get("DISPLAY"):
    os.environ.setdefault("MUJOCO_GL", "egl")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Tests marked ``browser`` run only without other test workers beside them: software
    WebGL needs the cores to itself (a screenshot took 40 s beside another worker, and the
    page's panels never caught up)."""
    del config
    if int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")) <= 1:
        return
    skip = pytest.mark.skip(
        reason="drives a browser with software WebGL, which needs the cores to itself: "
        "python -m pytest -m browser -n 0"
    )
    for item in items:
        if "browser" in item.keywords:
            item.add_marker(skip)


@pytest.fixture(autouse=True, scope="session")
def _private_mesh_cache(tmp_path_factory: pytest.TempPathFactory) -> None:
    """Generated meshes go to a cache of this run's own (shared by its test workers, whose
    writes are atomic), so tests never depend on a user's cache."""
    if "PROBEGYM_CACHE_DIR" not in os.environ:
        base = tmp_path_factory.getbasetemp()
        if os.environ.get("PYTEST_XDIST_WORKER"):
            base = base.parent  # the run's folder, above each worker's own
        cache = base / "probegym-cache"
        cache.mkdir(exist_ok=True)
        os.environ["PROBEGYM_CACHE_DIR"] = str(cache)


@pytest.fixture
def paper_scene_dir() -> Path:
    """The published scene of Tagliabue et al. (read-only test data beside the project)."""
    if not SHARED_SCENE.is_dir():
        pytest.skip(
            f"the published scene is not present at {SHARED_SCENE} (test data, not shipped)"
        )
    return SHARED_SCENE
