"""The README's Python quick starts run as written (a user copies them first)."""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np
import pytest

README = Path(__file__).resolve().parents[2] / "README.md"


def _python_blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.DOTALL)


def _offscreen_gl_error() -> str | None:
    """Why offscreen OpenGL does not work here, or None where it does."""
    import mujoco

    try:
        renderer = mujoco.Renderer(mujoco.MjModel.from_xml_string("<mujoco/>"), 16, 16)
    except Exception as error:  # noqa: BLE001 - any failure means no GL; said in the skip
        return f"{type(error).__name__}: {error}"
    renderer.close()
    return None


def test_the_readme_has_both_quick_starts() -> None:
    blocks = _python_blocks()
    assert any("tissue.make_tissue" in block for block in blocks)
    assert any("gym.make" in block for block in blocks)


def test_the_tissue_quick_start_runs_and_presses() -> None:
    block = next(b for b in _python_blocks() if "tissue.make_tissue" in b)
    scope: dict[str, object] = {}
    exec(compile(block, str(README), "exec"), scope)  # noqa: S102 - the README's own code
    step = scope["s"]
    assert step.ok and np.linalg.norm(step.force_world_n) > 0.1  # type: ignore[attr-defined]


def test_the_environment_quick_start_runs_and_renders() -> None:
    reason = _offscreen_gl_error()
    if reason is not None:
        pytest.skip(
            f"no offscreen OpenGL (MUJOCO_GL={os.environ.get('MUJOCO_GL')}): {reason}; install "
            "Mesa's EGL (Debian: libegl1 libgl1-mesa-dri) or osmesa (libosmesa6)"
        )
    block = next(b for b in _python_blocks() if "gym.make" in b)
    scope: dict[str, object] = {}
    exec(compile(block, str(README), "exec"), scope)  # noqa: S102 - the README's own code
    frame = scope["frame"]
    assert isinstance(frame, np.ndarray) and frame.ndim == 3 and frame.std() > 0
    scope["env"].close()  # type: ignore[attr-defined]
