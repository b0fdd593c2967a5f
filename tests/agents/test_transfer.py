"""``probegym study --transfer``: bad configurations refused before any training; the success
matrix, the Pareto front and the conclusions computed from the records; a corrupt cell redone;
a tiny study end to end, resumed without training or evaluating again."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from agents.cli import main
from agents.learning.transfer.report import conclusions, reference_points, success_matrix
from agents.learning.transfer.run import TransferOutcome, _finished_cell, cell_folder
from agents.learning.transfer.spec import Configuration, TransferSpec

RL_EXTRA = "training needs the rl extra: pip install -e '.[rl]' (a CPU torch first)"
ENV_ID = "probegym/BreastCompress-v2"


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (["--train", "lm@623,foo@623"], ["--train", "'foo@623'", "'foo'", "lm", "pbd"]),
        (["--train", "lm@999"], ["--train", "'lm@999'", "999", "623", "176506"]),
        (["--train", "lm1363"], ["--train", "METHOD@LEVEL", "'lm1363'"]),
        (["--reference", "penalty@12"], ["--reference", "12"]),
        (["--evaluate", "pbd@623,xpbd@1363"], ["--evaluate", "'xpbd'"]),
        (["--env", "probegym/Nope-v0"], ["--env", "probegym/Nope-v0", "BreastCompress-v2"]),
        (["--algo", "dqn"], ["--algo", "'dqn'", "ppo", "sac"]),
        (["--env", "probegym/ForceScan-v0"], ["probegym/ForceScan-v0", "--steps"]),
    ],
)
def test_bad_configurations_are_refused_before_any_work(
    args: list[str], words: list[str], tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    out = tmp_path / "study"
    assert main(["study", "--transfer", "--out", str(out), *args]) == 2
    error = capsys.readouterr().err
    for word in words:
        assert word in error
    assert not (out / "transfer").exists()  # nothing trained, nothing written


def _spec() -> TransferSpec:
    configs = tuple(Configuration.parse(c, "--train") for c in ("penalty@623", "lm@623"))
    return TransferSpec(
        env_ids=(ENV_ID,),
        train=configs,
        evaluate=configs,
        reference=Configuration("lm", 4126),
        steps={ENV_ID: 1000},
        episodes=10,
    )


def _record(train: str, on: str, successes: int, wall_s: float) -> dict:
    return {
        "env_id": ENV_ID, "train": train, "evaluate": on, "seed": 0, "episodes": 10,
        "successes": successes, "success_rate": successes / 10, "train_wall_s": wall_s,
    }  # fmt: skip


def test_the_matrix_the_front_and_the_conclusions_follow_the_records() -> None:
    spec = _spec()
    assert [c.label for c in spec.evaluate] == ["penalty@623", "lm@623", "lm@4126"]
    records = [
        _record("penalty@623", "penalty@623", 10, 60.0),
        _record("penalty@623", "lm@623", 9, 60.0),
        _record("penalty@623", "lm@4126", 5, 60.0),  # breaks: 50 % against its own 100 %
        _record("lm@623", "penalty@623", 8, 120.0),
        _record("lm@623", "lm@623", 9, 120.0),
        _record("lm@623", "lm@4126", 9, 120.0),
    ]
    matrix = success_matrix(spec, records)
    assert matrix["rows"] == ["penalty@623", "lm@623"]
    assert matrix["values"].tolist() == [[1.0, 0.9, 0.5], [0.8, 0.9, 0.9]]
    points = {p["train"]: p for p in reference_points(spec, records)}
    assert points["penalty@623"]["pareto"] and points["lm@623"]["pareto"]  # cheaper / better
    assert points["lm@623"]["own_success"] == 0.9
    found = " ".join(conclusions(spec, matrix, list(points.values())))
    assert "Best buy: training on lm@623 (2.0 min)" in found  # penalty's 50 % is not within 10
    assert "95 % interval 60-98 %" in found  # 9 of 10 episodes, Wilson
    # 5 of 10 against 10 of 10: Fisher's exact test, one-sided, p = 0.016.
    assert "Transfer breaks" in found
    assert "penalty@623 on lm@4126 (50 % against 100 %, p = 0.02)" in found
    assert "cannot tell" not in found
    assert "lm@623 on" not in found  # LM's policy keeps its success everywhere
    # 6 of 10 against 9 of 10: 30 points down, but p = 0.15: reported as not told from chance.
    records[4] = _record("lm@623", "lm@623", 9, 120.0)
    records[3] = _record("lm@623", "penalty@623", 6, 120.0)
    found = " ".join(conclusions(spec, success_matrix(spec, records), list(points.values())))
    assert "cannot tell from chance" in found
    assert "lm@623 on penalty@623 (60 % against 90 %" in found
    assert "lm@623 on penalty@623" not in found.split("cannot tell")[0]
    # A cheaper configuration as good as the best is the best buy, and dominates.
    records[2] = _record("penalty@623", "lm@4126", 9, 60.0)
    points = {p["train"]: p for p in reference_points(spec, records)}
    assert not points["lm@623"]["pareto"]
    found = " ".join(conclusions(spec, success_matrix(spec, records), list(points.values())))
    assert "Best buy: training on penalty@623 (1.0 min)" in found
    assert "Transfer holds" in found


def test_a_corrupt_or_foreign_cell_is_reported_and_redone(tmp_path: Path) -> None:
    from agents.learning.transfer.run import train_settings

    spec = _spec()
    settings = train_settings(spec, tmp_path)[0]
    trained_on, on = spec.train[0], spec.evaluate[2]
    folder = cell_folder(tmp_path, ENV_ID, trained_on, 0, on)
    folder.mkdir(parents=True)
    outcome = TransferOutcome()
    assert _finished_cell(folder, spec, settings, on, outcome) is None  # not run yet
    assert outcome.redone == []
    (folder / "cell.json").write_text('{"env_id": "probegym/Brea')  # cut off mid-write
    assert _finished_cell(folder, spec, settings, on, outcome) is None
    assert "unreadable or incomplete, evaluated again" in outcome.redone[-1]
    record = _record("penalty@623", "lm@4126", 3, 1.0) | {"steps": 1000}
    (folder / "cell.json").write_text(json.dumps(record | {"episodes": 50}))
    assert _finished_cell(folder, spec, settings, on, outcome) is None
    assert "another study's cell" in outcome.redone[-1]
    (folder / "cell.json").write_text(json.dumps(record))
    assert _finished_cell(folder, spec, settings, on, outcome) == record
    assert len(outcome.redone) == 2


@pytest.mark.train
def test_a_tiny_study_runs_and_resumes_without_redoing_anything(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    pytest.importorskip("stable_baselines3", reason=RL_EXTRA)
    args = [
        "study", "--transfer", "--env", ENV_ID, "--train", "penalty@623,lm@623",
        "--evaluate", "penalty@623", "--reference", "lm@623", "--steps", "1000",
        "--episodes", "2", "--out", str(tmp_path),
    ]  # fmt: skip
    assert main(args) == 0
    printed = capsys.readouterr().out
    assert "2 runs trained now, 4 cells evaluated now" in printed
    out = tmp_path / "transfer"
    payload = json.loads((out / "transfer.json").read_text())
    cells = {(r["train"], r["evaluate"]): r for r in payload["records"]}
    assert set(cells) == {
        (t, e) for t in ("penalty@623", "lm@623") for e in ("penalty@623", "lm@623")
    }
    for record in cells.values():
        assert record["episodes"] == 2 and 0 <= record["successes"] <= 2
        assert record["trained_steps"] >= 1000 and record["train_wall_s"] > 0
        assert record["reference"] == (record["evaluate"] == "lm@623")
    for name in ("transfer.csv", "report.md", "BreastCompress-v2-matrix.png",
                 "BreastCompress-v2-pareto.png"):  # fmt: skip
        assert (out / name).is_file(), name
    assert "Best buy" in (out / "report.md").read_text()
    # Resumed: nothing trained or evaluated again; a corrupt cell alone is redone.
    corrupt = out / "BreastCompress-v2" / "cells" / "lm@623-seed0" / "on-penalty@623" / "cell.json"
    corrupt.write_text("{")
    assert main(args) == 0
    printed = capsys.readouterr().out
    assert "0 runs trained now, 1 cells evaluated now, 3 from an earlier run" in printed
    assert "redone:" in printed and str(corrupt) in printed
    again = json.loads(corrupt.read_text())
    assert again["successes"] == cells[("lm@623", "penalty@623")]["successes"]  # same seeds
