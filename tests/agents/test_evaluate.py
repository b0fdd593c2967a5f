"""``probegym evaluate``: the files it writes, its numbers against the environment run
directly, determinism for a seed, the plots, and bad input refused before any work.

Fast tier: the 623-tet phantom, two episodes, the scripted policies."""

from __future__ import annotations

import argparse
import csv
import json
import shlex
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest

import envs
from agents.learning.evaluation import (
    CSV_COLUMNS,
    TIMING_PREFIX,
    add_evaluate_parser,
    evaluate,
    run_evaluate,
    without_timings,
)
from agents.learning.evaluation.report import wilson_interval
from agents.learning.evaluation.run import resolve_policy
from agents.learning.policies import SCRIPTED_POLICIES
from tissue.errors import ConfigError

MESH = 623
EPISODES = 2
SEED = 3
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module", params=envs.ENV_IDS)
def evaluation(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
) -> tuple[str, Path, list[dict[str, Any]]]:
    """Each task evaluated once with its scripted policy (a stale plot left in its folder
    beforehand, which the run must clear where it does not apply)."""
    env_id = request.param
    out = tmp_path_factory.mktemp("evaluate")
    (out / "lesion_path.png").write_bytes(b"stale")
    (out / "scan_progress.png").write_bytes(b"stale")
    records = evaluate(
        env_id, "scripted", EPISODES, SEED, {"mesh": MESH}, out, command="probegym evaluate test"
    )
    return env_id, out, records


def _run_directly(env_id: str, seed: int) -> dict[str, Any]:
    """One episode of a fresh env and a fresh scripted policy, by hand."""
    env = gym.make(env_id, mesh=MESH)
    policy = SCRIPTED_POLICIES[env_id]()
    if hasattr(policy, "reset"):
        policy.reset()
    observation, _ = env.reset(seed=seed)
    total, steps, peak = 0.0, 0, 0.0
    while True:
        observation, reward, terminated, truncated, info = env.step(policy(observation))
        total += float(reward)
        steps += 1
        peak = max(peak, float(info["contact_force_n"]))
        if terminated or truncated:
            env.close()
            return {"return": total, "length": steps, "peak": peak, "info": info}


def test_the_files_hold_the_documented_columns(evaluation) -> None:
    env_id, out, records = evaluation
    for name in ("episodes.json", "episodes.csv", "summary.json", "summary.md"):
        assert (out / name).is_file(), name
    with (out / "episodes.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert tuple(rows[0]) == CSV_COLUMNS
    assert [int(row["episode"]) for row in rows] == list(range(EPISODES))
    assert [int(row["seed"]) for row in rows] == [SEED + k for k in range(EPISODES)]
    for row, record in zip(rows, records, strict=True):
        assert float(row["return"]) == record["return"]
        assert row["success"] == str(record["success"])
        assert int(row["length"]) == record["length"] == len(record["series"]["contact_force_n"])
        assert float(row["contact_force_peak_n"]) == max(record["series"]["contact_force_n"])
        assert row["tissue_status"] == "ok"
    stored = json.loads((out / "episodes.json").read_text())
    assert stored["env_id"] == env_id and stored["env_kwargs"] == {"mesh": MESH}
    assert stored["episodes"] == json.loads(json.dumps(records))
    summary = json.loads((out / "summary.json").read_text())
    successes = sum(record["success"] for record in records)
    assert summary["successes"] == successes
    assert summary["success_rate_ci95"] == list(wilson_interval(successes, EPISODES))
    assert summary["return_mean"] == pytest.approx(np.mean([r["return"] for r in records]))
    text = (out / "summary.md").read_text()
    assert "`probegym evaluate test`" in text and "on revision `" in text
    assert f"{successes}/{EPISODES} = " in text and "**Timings**" in text


def test_the_numbers_are_those_of_the_env_run_directly(evaluation) -> None:
    env_id, _, records = evaluation
    record = records[-1]
    direct = _run_directly(env_id, SEED + EPISODES - 1)
    assert record["seed"] == SEED + EPISODES - 1
    assert record["return"] == direct["return"]
    assert record["length"] == direct["length"]
    assert record["contact_force_peak_n"] == direct["peak"]
    info = direct["info"]
    assert record["success"] == info["is_success"]
    if env_id.startswith("probegym/LesionSearch-"):
        assert record["centring_error_m"] == abs(info["lesion_lateral_m"])
    elif env_id.startswith("probegym/BreastCompress-"):
        expected = abs(info["lesion_depth_m"] - info["target_depth_m"])
        assert record["centring_error_m"] == expected
    else:
        assert record["centring_error_m"] is None
        assert record["remaining_end_m"] == info["remaining_m"]
        assert record["good_share_end"] == info["good_share"]


def test_the_plots_are_png_images(evaluation) -> None:
    from PIL import Image

    env_id, out, _ = evaluation
    expected = ["success_rate.png", "contact_force.png"]
    expected.append(
        "scan_progress.png" if env_id.startswith("probegym/ForceScan-") else "lesion_path.png"
    )
    for name in expected:
        data = (out / name).read_bytes()
        assert data.startswith(PNG_MAGIC), name
        with Image.open(out / name) as image:
            image.verify()
        with Image.open(out / name) as image:
            assert image.size[0] > 100 and image.size[1] > 100
            # Not blank: more than one colour is drawn.
            assert len(image.convert("L").getcolors(maxcolors=1 << 16) or [0, 0]) > 1
    stale = {"lesion_path.png", "scan_progress.png"} - set(expected)
    assert not any((out / name).exists() for name in stale)


def test_the_same_seed_repeats_every_number_but_the_timings(tmp_path: Path) -> None:
    env_id = "probegym/BreastCompress-v0"
    first = evaluate(env_id, "scripted", EPISODES, 5, {"mesh": MESH}, tmp_path / "a")
    again = evaluate(env_id, "scripted", EPISODES, 5, {"mesh": MESH}, tmp_path / "b")
    other = evaluate(env_id, "scripted", EPISODES, 6, {"mesh": MESH}, tmp_path / "c")
    timings = [key for key in first[0] if key.startswith(TIMING_PREFIX)]
    assert timings and all(key.startswith(TIMING_PREFIX) for key in timings)
    assert without_timings(first) == without_timings(again)
    # Episode 1 of seed 5 is episode 0 of seed 6 (seed 6 both times); episode 0 differs.
    assert without_timings(first)[1]["series"] == without_timings(other)[0]["series"]
    assert first[0]["return"] != other[0]["return"]
    assert first[0]["series"] != other[0]["series"]
    summaries = [json.loads((tmp_path / k / "summary.json").read_text()) for k in "ab"]
    for summary in summaries:
        del summary["timing"]
    assert summaries[0] == summaries[1]


def _parse(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="probegym")
    add_evaluate_parser(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    args.command_line = "probegym " + shlex.join(argv)
    return args


def test_the_command_runs_and_records_itself(tmp_path: Path, capsys) -> None:
    out = tmp_path / "run"
    argv = ["evaluate", "probegym/BreastCompress-v0", "--policy", "scripted", "--episodes", "1"]
    argv += ["--seed", "2", "--mesh", str(MESH), "--contact", "lm", "--profile", "robust"]
    argv += ["--out", str(out)]
    assert run_evaluate(_parse(argv)) == 0
    text = (out / "summary.md").read_text()
    assert f"`probegym {shlex.join(argv)}`" in text
    stored = json.loads((out / "episodes.json").read_text())
    assert stored["env_kwargs"] == {"contact": "lm", "profile": "robust", "mesh": MESH}
    assert [record["seed"] for record in stored["episodes"]] == [2]
    printed = capsys.readouterr().out
    assert "probegym/BreastCompress-v0, policy scripted: " in printed and str(out) in printed


def _refuse_work(monkeypatch) -> None:
    def refuse(*args, **kwargs):
        raise AssertionError("an environment was made although the input was bad")

    monkeypatch.setattr(gym, "make", refuse)


@pytest.mark.parametrize(
    ("argv", "words"),
    [
        (["probegym/Nope-v0"], ["'probegym/Nope-v0'", "probegym/LesionSearch-v0"]),
        (["probegym/ForceScan-v0", "--episodes", "0"], ["--episodes", ">= 1", "got 0"]),
        (["probegym/ForceScan-v0", "--seed", "-1"], ["--seed", ">= 0", "got -1"]),
        (["probegym/ForceScan-v0", "--contact", "springs"], ["'springs'", "'lm'"]),
        (["probegym/ForceScan-v0", "--profile", "fast"], ["'fast'", "'robust'"]),
        (["probegym/ForceScan-v0", "--mesh", "5"], ["'5'", "623"]),
        (["probegym/ForceScan-v0", "--mesh", "no/such.vtu"], ["no/such.vtu", "tet count"]),
    ],
)
def test_bad_options_are_refused_before_any_work(monkeypatch, capsys, tmp_path, argv, words):
    _refuse_work(monkeypatch)
    args = _parse(["evaluate", *argv, "--policy", "scripted", "--out", str(tmp_path / "o")])
    assert run_evaluate(args) == 2
    error = capsys.readouterr().err
    assert error.startswith("probegym: error: ") and error.count("\n") == 1
    for word in words:
        assert word in error


def test_a_path_that_is_not_a_model_is_refused(monkeypatch, capsys, tmp_path) -> None:
    _refuse_work(monkeypatch)
    empty = tmp_path / "not-a-model"
    empty.mkdir()
    args = _parse(["evaluate", "probegym/ForceScan-v0", "--policy", str(empty)])
    args.out = tmp_path / "o"
    assert run_evaluate(args) == 2
    error = capsys.readouterr().err
    assert str(empty) in error and "model.zip" in error and "--policy scripted" in error


def test_an_out_folder_that_is_a_file_is_refused(monkeypatch, tmp_path) -> None:
    _refuse_work(monkeypatch)
    file = tmp_path / "a-file"
    file.write_text("")
    with pytest.raises(ConfigError, match=r"--out .*a-file is a file; give a folder"):
        evaluate("probegym/ForceScan-v0", "scripted", 1, 0, {}, file)


class _FakeTrained:
    """What load_policy returns, without a model: a config and a call."""

    def __init__(self, config: dict[str, Any]) -> None:
        self.config = config

    def __call__(self, observation: dict[str, Any]) -> Any:
        return np.zeros(6, dtype=np.float32)


def test_a_trained_policy_brings_its_env_and_refuses_another(monkeypatch, tmp_path) -> None:
    import agents.learning.train

    trained = _FakeTrained(
        {"env_id": "probegym/LesionSearch-v0", "env_kwargs": {"mesh": 1363, "contact": "pbd"}}
    )
    monkeypatch.setattr(agents.learning.train, "load_policy", lambda path: trained)
    label, make, kwargs = resolve_policy(
        "probegym/LesionSearch-v0", tmp_path, {"contact": "lm", "domain_randomization": True}
    )
    assert label == str(tmp_path) and make() is trained
    assert kwargs == {"mesh": 1363, "contact": "lm", "domain_randomization": True}
    _refuse_work(monkeypatch)
    with pytest.raises(ConfigError, match=r"trained on 'probegym/LesionSearch-v0', not"):
        evaluate("probegym/ForceScan-v0", tmp_path, 1, 0, {}, tmp_path / "o")


def test_a_model_of_another_version_is_refused_naming_both_spaces(monkeypatch, tmp_path) -> None:
    import agents.learning.train

    v0 = gym.make("probegym/LesionSearch-v0")
    trained = _FakeTrained({"env_id": "probegym/LesionSearch-v0", "env_kwargs": {}})
    trained.model = type("Model", (), {"observation_space": v0.observation_space})()  # type: ignore[attr-defined]
    v0.close()
    monkeypatch.setattr(agents.learning.train, "load_policy", lambda path: trained)
    with pytest.raises(ConfigError) as refused:
        evaluate("probegym/LesionSearch-v1", tmp_path, 1, 0, {}, tmp_path / "o")
    message = str(refused.value)
    assert "trained on 'probegym/LesionSearch-v0', not 'probegym/LesionSearch-v1'" in message
    observed, given = message.split("the model observes ")[1].split(", probegym/LesionSearch-v1")
    assert "lesion (4,)" in observed and "last_action" not in observed
    assert "last_action (6,)" in given and "scan_extent (2,)" in given


def test_each_task_has_its_centring_figure() -> None:
    from agents.learning.evaluation.run import _task_figures

    search = _task_figures({"lesion_lateral_m": -0.002})
    assert search["centring_error_m"] == pytest.approx(0.002)
    compress = _task_figures({"lesion_depth_m": 0.030, "target_depth_m": 0.033})
    assert compress["centring_error_m"] == pytest.approx(0.003)
    scan = _task_figures({"remaining_m": 0.004, "good_share": 0.95})
    assert scan["centring_error_m"] is None
    assert (scan["remaining_end_m"], scan["good_share_end"]) == (0.004, 0.95)


def test_the_random_baseline_is_seeded_and_acts_at_random(tmp_path: Path) -> None:
    from agents.learning.evaluation import evaluate

    first = evaluate("probegym/BreastCompress-v0", "random", 1, 5, {"mesh": 623}, tmp_path / "a")
    again = evaluate("probegym/BreastCompress-v0", "random", 1, 5, {"mesh": 623}, tmp_path / "b")
    assert first[0]["return"] == again[0]["return"]
    assert not first[0]["success"]


@pytest.mark.parametrize(("successes", "trials"), [(0, 50), (50, 50), (0, 7), (3, 7), (1, 1)])
def test_the_interval_contains_the_rate_and_plots(successes: int, trials: int, tmp_path) -> None:
    from agents.learning.evaluation.plots import success_plot
    from agents.learning.evaluation.report import wilson_interval

    low, high = wilson_interval(successes, trials)
    rate = successes / trials
    assert 0.0 <= low <= rate <= high <= 1.0
    summary = {
        "success_rate": rate,
        "success_rate_ci95": [low, high],
        "successes": successes,
        "episodes": trials,
        "policy": "random",
        "env_id": "probegym/BreastCompress-v0",
    }
    assert success_plot(tmp_path / "s.png", summary).stat().st_size > 0
