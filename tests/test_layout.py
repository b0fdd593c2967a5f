"""The project's packages are the ones imported, and imports go one way."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("package", ["tissue", "envs", "agents", "assets"])
def test_generic_package_names_resolve_to_this_repository(package: str) -> None:
    # "envs" and friends are generic names (a PyPI package called envs exists).
    module = __import__(package)
    assert Path(module.__file__).resolve().parent == ROOT / package


def test_tissue_imports_no_robot_or_learning_stack() -> None:
    code = (
        "import sys, tissue, tissue.simulator, tissue.phantom, tissue.mesh_io, tissue.solvers;"
        "heavy = ('mujoco', 'gymnasium', 'torch', 'stable_baselines3');"
        "bad = [m for m in heavy if m in sys.modules];"
        "print(','.join(bad))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""
