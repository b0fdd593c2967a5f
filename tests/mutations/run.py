"""Mutation check: does the test suite catch the bugs that matter?

Each mutation below is one small deliberate bug (a text replaced in one source file) and the
tests that should catch it. ``python tests/mutations/run.py`` applies them one at a time to
this checkout, runs those tests, restores the file, and prints which mutations the tests
killed and which survived (``--json PATH`` writes the table too). A surviving mutation is a
blind spot: write the test that kills it. Run it on a clean checkout (it refuses files with
uncommitted changes); a file is always restored, even on Ctrl-C.

The mutations are in the contact strategies, the time integrator, the tunnelling check, the
study's metrics, the command line's checks and the environment's rewards and observations.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


@dataclass(frozen=True)
class Mutation:
    """One deliberate bug: replace ``find`` (which must occur exactly once) by ``replace``
    in ``path``; ``tests`` are pytest arguments that must then fail."""

    name: str
    path: str
    find: str
    replace: str
    tests: tuple[str, ...]


MUTATIONS = (
    Mutation(
        "penalty springs twice as stiff (force, energy and tangent alike)",
        "tissue/contact/penalty.py",
        "magnitude = np.maximum(self.offsets[contacts.points] + self.stiffness * depth, 0.0)",
        "magnitude = np.maximum(self.offsets[contacts.points] + 2 * self.stiffness * depth, 0.0)",
        ("tests/tissue/test_contact.py", "-k", "eq_6_and_the_default_stiffness"),
    ),
    Mutation(
        "online prescribed nodes never let go when they pull",
        "tissue/contact/prescribed.py",
        'keep = (np.einsum("ij,ij->i", reaction, normal) > 0.0) | (distance < 0.0)',
        "keep = np.ones(self._nodes.size, dtype=bool)",
        ("tests/tissue/test_contact.py", "-k", "let_go_when_they_would_pull"),
    ),
    Mutation(
        "the stability metric counts the failed step as completed",
        "agents/lab/compress.py",
        "            if instability is not None:\n                break\n"
        "            motion_done += 1",
        "            motion_done += 1\n"
        "            if instability is not None:\n                break",
        ("tests/tissue/test_stability.py",),
    ),
    Mutation(
        "the stability metric's motion counter not decremented for a failed hold",
        "agents/lab/compress.py",
        "            motion_done -= 1  # the depth was reached but never held",
        "            pass",
        ("tests/tissue/test_stability.py",),
    ),
    Mutation(
        "the hard cases' energy check never fires",
        "agents/lab/hard_cases.py",
        "            self.ok = False",
        "            pass",
        (
            "tests/agents/test_hard_cases.py::test_the_energy_check_fires_when_the_tissue_holds_more_than_the_probe_gave",
        ),
    ),
    Mutation(
        "compress --depths may decrease",
        "agents/lab/compress.py",
        '        raise ConfigError(f"--depths must increase; got {depths_m}")',
        "        pass",
        ("tests/agents/test_cli.py", "-k", "refuses"),
    ),
    Mutation(
        "LM's projected Gauss-Seidel lets a contact pull",
        "tissue/contact/lagrange/pgs.py",
        "            if new < 0.0:\n                new = 0.0",
        "            if new < -1e300:\n                new = 0.0",
        ("tests/tissue/test_contact.py", "-k", "signorini"),
    ),
    Mutation(
        "backward Euler without the mass-proportional damping",
        "tissue/sim/integrator/potential.py",
        "                m / (h * h) + cfg.rayleigh_mass * m / h,",
        "                m / (h * h),",
        ("tests/tissue/test_integrator.py", "-k", "mass_damping"),
    ),
    Mutation(
        "no sub-motions: a long probe motion in one tissue step",
        "tissue/contact/base.py",
        "        return min(MAX_SUB_MOTIONS, max(1, math.ceil(travel / self.max_sub_motion_m - 1e-12)))",  # noqa: E501
        "        return 1",
        ("tests/tissue/test_front_door.py", "-k", "teleport"),
    ),
    Mutation(
        "the skin penetration never reported",
        "tissue/contact/base.py",
        "            skin_penetration_m=skin.depth_m,",
        "            skin_penetration_m=0.0,",
        ("tests/tissue/test_front_door.py", "-k", "623"),
    ),
    Mutation(
        "a snapshot keeps the solver caches",
        "tissue/contact/base.py",
        "        self.drop_caches()\n        last = self._last_pose\n        return {",
        "        last = self._last_pose\n        return {",
        ("tests/tissue/test_front_door.py", "-k", "snapshots"),
    ),
    Mutation(
        "the study scores each profile on its own depths",
        "agents/lab/study/tables.py",
        '            lesion_case: tuple[int, ...] = (record["level"], record["lesion"])',
        '            lesion_case = (record["level"], record["lesion"], record["config"])',
        ("tests/agents/test_study.py", "-k", "same_depths"),
    ),
    Mutation(
        "the coupling's linearised wrench pulls where it should push back",
        "envs/coupling.py",
        "            w = w - self._stiffness @ displacement",
        "            w = w + self._stiffness @ displacement",
        ("tests/envs/test_breast_compress.py", "-k", "predicts"),
    ),
    Mutation(
        "the F/T wrench not tared for the probe's load",
        "envs/observations.py",
        "    force = -site_rot @ force_site + load",
        "    force = -site_rot @ force_site",
        ("tests/envs/test_breast_compress.py", "-k", "sensed_wrench and lm"),
    ),
    Mutation(
        "the reward is not the sum of its logged terms",
        "envs/probe_env.py",
        "        reward = float(sum(terms.values()))",
        "        reward = float(sum(terms.values())) - 0.01",
        ("tests/envs/test_breast_compress.py", "-k", "same_seed and lm"),
    ),
    Mutation(
        "the lesion's depth in the image measured from the wrong side",
        "envs/observations.py",
        "    lateral, depth, out_of_plane = (float(v) for v in local)",
        "    lateral, depth, out_of_plane = local[0], -local[1], local[2]",
        ("tests/envs/test_breast_compress.py", "-k", "scripted and lm"),
    ),
)


def _dirty(path: str) -> bool:
    out = subprocess.run(
        ["git", "-C", str(ROOT), "status", "--porcelain", "--", path],
        capture_output=True, text=True, check=False,
    )  # fmt: skip
    return bool(out.stdout.strip())


def run(mutation: Mutation, timeout_s: float) -> dict[str, object]:
    """Apply, test, restore; the mutation's outcome."""
    source = ROOT / mutation.path
    original = source.read_text()
    if original.count(mutation.find) != 1:
        return {"name": mutation.name, "outcome": "stale (the text to mutate is gone)"}
    started = time.perf_counter()
    try:
        source.write_text(original.replace(mutation.find, mutation.replace))
        result = subprocess.run(
            [sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider", "-n", "0",
             "-m", "slow or not slow", *mutation.tests],
            cwd=ROOT, capture_output=True, text=True, timeout=timeout_s, check=False,
        )  # fmt: skip
        if result.returncode == 1:
            outcome = "killed"
        elif result.returncode == 0:
            outcome = "survived"
        else:
            outcome = f"error (pytest exit {result.returncode})"
        failed = [line for line in result.stdout.splitlines() if line.startswith("FAILED ")]
        caught_by = failed[0].removeprefix("FAILED ").split(" - ")[0] if failed else ""
    except subprocess.TimeoutExpired:
        outcome, caught_by = "killed (timed out)", ""
    finally:
        source.write_text(original)
    return {
        "name": mutation.name,
        "file": mutation.path,
        "tests": " ".join(mutation.tests),
        "outcome": outcome,
        "caught_by": caught_by,
        "seconds": round(time.perf_counter() - started, 1),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", type=Path, default=None, help="write the table as JSON")
    parser.add_argument("--timeout", type=float, default=900.0, help="per mutation [s]")
    parser.add_argument("--only", default=None, help="run the mutations whose name has this")
    args = parser.parse_args()
    chosen = [m for m in MUTATIONS if args.only is None or args.only in m.name]
    dirty = sorted({m.path for m in chosen if _dirty(m.path)})
    if dirty:
        print(f"uncommitted changes in {', '.join(dirty)}: commit or stash them first")
        return 2
    rows = []
    print("| mutation | file | outcome | caught by | s |\n|---|---|---|---|---|")
    for mutation in chosen:
        row = run(mutation, args.timeout)
        rows.append(row)
        cells = (
            row["name"], row.get("file", ""), row["outcome"], row.get("caught_by", ""),
            row.get("seconds", ""),
        )  # fmt: skip
        print("| " + " | ".join(str(cell) for cell in cells) + " |", flush=True)
    survived = [row for row in rows if row["outcome"] != "killed"]
    print(f"\n{len(rows) - len(survived)} of {len(rows)} killed")
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0 if not survived else 1


if __name__ == "__main__":
    raise SystemExit(main())
