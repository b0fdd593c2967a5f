"""The mutation check stays armed: every deliberate bug in tests/mutations/run.py still
finds its text (exactly once) in its file, and names test files that exist. A refactor that
moves the code or the tests makes the mutation "stale" in a full run; this catches it in the
fast tier."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def _mutations():
    spec = importlib.util.spec_from_file_location("mutation_run", ROOT / "tests/mutations/run.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while defining
    spec.loader.exec_module(module)
    return module.MUTATIONS


@pytest.mark.parametrize("mutation", _mutations(), ids=lambda m: m.name)
def test_mutation_still_applies(mutation) -> None:
    source = ROOT / mutation.path
    assert source.is_file(), f"{mutation.path} is gone: point the mutation at the code's new home"
    assert source.read_text().count(mutation.find) == 1, (
        f"the text mutation {mutation.name!r} replaces no longer occurs exactly once in "
        f"{mutation.path}"
    )
    named = [arg.split("::")[0] for arg in mutation.tests if arg.endswith(".py") or "::" in arg]
    assert named, "the mutation names no test file"
    for path in named:
        assert (ROOT / path).is_file(), f"{path} (named by {mutation.name!r}) does not exist"
