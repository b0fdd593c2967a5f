"""The baseline records' pieces: which runs used the defaults, steps to 80 %, wall time, and
how new records replace old ones."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from agents.learning.evaluation.baselines import (
    _defaults,
    _steps_to,
    _tensorboard_wall_s,
    _wall_s,
    merge,
    policy_record,
)


def _config(**changes) -> dict:
    config = {
        "env_kwargs": {"contact": "lm", "mesh": 1363, "profile": "robust"},
        "settings": {"hyperparameters": {}},
        "normalize": True,
    }
    config.update(changes)
    return config


@pytest.mark.parametrize(
    ("changes", "expected"),
    [
        ({}, True),
        ({"env_kwargs": {"contact": "lm"}}, True),
        ({"env_kwargs": {"contact": "penalty", "mesh": 1363, "profile": "robust"}}, False),
        ({"env_kwargs": {"contact": "lm", "mesh": 1363, "max_translation_m": 0.002}}, False),
        ({"settings": {"hyperparameters": {"n_steps": 512}}}, False),
        ({"init_from": "runs/x"}, False),
        ({"pretrain_episodes": 20}, False),
        ({"normalize": False}, False),
    ],
)
def test_only_runs_with_the_defaults_are_marked_so(changes: dict, expected: bool) -> None:
    assert _defaults(_config(**changes)) is expected


def test_steps_to_80_is_the_first_evaluation_at_80_percent(tmp_path: Path) -> None:
    (tmp_path / "eval").mkdir()
    successes = np.array([[0] * 10, [1] * 7 + [0] * 3, [1] * 8 + [0] * 2, [1] * 10])
    np.savez(tmp_path / "eval" / "evaluations.npz", timesteps=[10, 20, 30, 40], successes=successes)
    assert _steps_to(tmp_path, 0.8) == 30
    assert _steps_to(tmp_path, 1.0) == 40
    assert _steps_to(tmp_path, 0.8, up_to=29) is None  # a checkpoint's: none by then
    assert _steps_to(tmp_path, 0.8, up_to=30) == 30
    np.savez(tmp_path / "eval" / "evaluations.npz", timesteps=[10], successes=successes[:1])
    assert _steps_to(tmp_path, 0.8) is None


def test_wall_time_is_the_latest_episode_end_over_the_monitors(tmp_path: Path) -> None:
    (tmp_path / "monitor").mkdir()
    header = '#{"t_start": 0.0}\nr,l,t,is_success\n'
    (tmp_path / "monitor" / "0.monitor.csv").write_text(header + "1,10,5.5,0\n2,10,40.25,1\n")
    (tmp_path / "monitor" / "1.monitor.csv").write_text(header + "1,10,39.0,1\n")
    assert _wall_s(tmp_path) == 40.25


def test_wall_time_sums_each_training_process_s_events_up_to_the_model(tmp_path: Path) -> None:
    """A run resumed once: two event files (one per process), each timed from its own first
    event to its last; the time between the processes is not counted, and a checkpoint's
    time stops at its steps."""
    pytest.importorskip("tensorboard", reason="TensorBoard is in the rl extra")
    import time

    from torch.utils.tensorboard import SummaryWriter

    for name, points in (("first", [(0, 0.0), (50, 30.0), (100, 60.0)]),
                         ("resumed", [(100, 0.0), (150, 25.0), (200, 40.0)])):  # fmt: skip
        start = time.time()  # the writer stamps its own first event with the clock
        writer = SummaryWriter(str(tmp_path / "tb" / "ppo_1"), filename_suffix=name)
        for step, offset in points:
            writer.add_scalar("rollout/ep_rew_mean", 1.0, step, walltime=start + offset)
        writer.close()
    assert _tensorboard_wall_s(tmp_path, 200) == pytest.approx(100.0, abs=1.0)
    assert _tensorboard_wall_s(tmp_path, 150) == pytest.approx(85.0, abs=1.0)
    assert _tensorboard_wall_s(tmp_path, 100) == pytest.approx(60.0, abs=1.0)
    assert _tensorboard_wall_s(tmp_path / "none", 200) is None


def test_new_records_replace_the_same_runs_only(tmp_path: Path) -> None:
    path = tmp_path / "baselines.json"
    old = [
        {"env_id": "a", "policy": "ppo", "seed": 0, "heldout_success": 0.5},
        {"env_id": "a", "policy": "ppo", "seed": 1, "heldout_success": 0.6},
    ]
    path.write_text(json.dumps({"records": old}))
    new = [{"env_id": "a", "policy": "ppo", "seed": 1, "heldout_success": 0.9}]
    merged = merge(path, new)
    assert [r["heldout_success"] for r in merged] == [0.5, 0.9]


def test_a_hand_written_policy_is_a_record_with_its_command() -> None:
    record = policy_record("probegym/LesionSearch-v1", "scripted", 2, 1000)
    assert record["heldout_successes"] == 2 and record["heldout_episodes"] == 2
    assert record["heldout_seeds"] == [1000, 1001] and record["algo"] is None
    low, high = record["heldout_interval"]
    assert low < 1.0 == high
    assert record["command"].startswith("probegym evaluate probegym/LesionSearch-v1")


def test_the_table_has_a_row_per_record_in_order() -> None:
    from agents.learning.evaluation.baselines import table

    base = {"defaults": True, "steps": 0, "heldout_episodes": 50, "wall_s": None}
    records = [
        base | {"env_id": "b", "policy": "random", "seed": None, "heldout_successes": 0,
                "heldout_interval": [0.0, 0.07]},
        base | {"env_id": "b", "policy": "ppo", "seed": 1, "heldout_successes": 45,
                "heldout_interval": [0.79, 0.96], "steps": 100_352, "steps_to_80": 20_000,
                "wall_s": 900.0, "steps_per_s": 111.5},
    ]  # fmt: skip
    rows = table(records).splitlines()[2:]
    assert rows[0].startswith("| b | ppo | 1 | yes | 100,352 | 20,000 | 45/50 (79%-96%) | 15 min")
    assert rows[1].startswith("| b | random | - | yes | 0 | - | 0/50 (0%-7%) | - | - |")


def test_a_checkpoints_steps_come_from_its_name() -> None:
    from agents.learning.evaluation.baselines import _checkpoint_steps

    assert _checkpoint_steps(Path("runs/x/checkpoints/model_160000_steps.zip")) == 160_000
    assert _checkpoint_steps(Path("runs/x/model.zip")) is None
    assert _checkpoint_steps(Path("runs/x/checkpoints/model_vecnormalize_20000_steps.pkl")) is None
