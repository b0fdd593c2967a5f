"""The benchmark commands keep their contracts: the fields the issues name, in the JSON they
write, with values that make physical sense. Timings are not judged here (a shared machine);
the benchmarks' own tables hold the targets."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from agents.cli import main
from agents.lab.bench.tissue import print_robust_targets, robust_step_target
from tissue.contact.penalty import PenaltyParams


def _run(args: list[str], json_path: Path) -> list[dict]:
    assert main([*args, "--json", str(json_path)]) == 0
    _check_markdown(json_path.with_suffix(".md"), args)
    return json.loads(json_path.read_text())


def _check_markdown(path: Path, args: list[str]) -> None:
    """The benchmark wrote its tables beside the JSON, saying what made them and where."""
    text = path.read_text()
    assert f"`probegym {' '.join(args)} --json {path.with_suffix('.json')}`" in text
    assert "on revision `" in text and "load average" in text and "cores" in text
    assert "| --- |" in text


def test_bench_contact_writes_every_method_mode_and_skin(tmp_path: Path) -> None:
    records = _run(["bench", "contact", "--levels", "623"], tmp_path / "contact.json")
    assert {(r["method"], r["mode"], r["skin"]) for r in records} == {
        (method, mode, skin)
        for method in ("penalty", "lm", "prescribed", "pbd")
        for mode in ("paper", "robust")
        for skin in ("paper", "2 mm")
    }
    for record in records:
        name = f"{record['method']}/{record['mode']}"
        assert record["tets"] == 571, name
        for key in ("step_ms", "step_ms_mean", "step_ms_max"):
            assert math.isfinite(record[key]) and record[key] > 0.0, (name, key)
        assert record["step_ms"] <= record["step_ms_max"], name
        assert record["steps_in_contact"] == 51, name  # the first step in contact and 50 more
        if record["mode"] == "paper" and record["method"] in ("prescribed", "pbd"):
            # The paper's prescribed node set and its 10-substep PBD hold the volume's
            # boundary nodes (25 mm apart here) and points between them, not the skin: a
            # skin fine enough to show it sags into the probe, and the steps say so.
            assert set(record["status_counts"]) <= {"ok", "penetrated"}, name
            if record["skin"] == "2 mm":
                assert record["skin_penetration_max_m"] > 1e-3, name
        else:
            assert record["status_counts"] == {"ok": record["steps_in_contact"]}, name
        assert record["force_n"] > 0.0, name  # the tissue pushes the probe back up
        assert record["lesion1_displacement_m"] > 1e-3, name  # a 10 mm press moves lesion 1
        assert not record["stopped_by_wall_budget"], name
        assert 0.0 <= record["force_largest_dip"] < 1.0, name
        assert record["skin_vertex_penetration_max_m"] <= record["skin_penetration_max_m"], name
    # The skin at the probe's scale has a vertex every 2 mm, and its facets stay out of the
    # probe where the paper's, held out at their vertices, cut its rim.
    skins = {(r["method"], r["mode"], r["skin"]): r for r in records}
    assert (
        skins["lm", "robust", "2 mm"]["skin_vertices"]
        > 10 * skins["lm", "robust", "paper"]["skin_vertices"]
    )
    fine = skins["lm", "robust", "2 mm"]["skin_penetration_max_m"]
    assert fine < 0.5e-3 < skins["lm", "robust", "paper"]["skin_penetration_max_m"]
    by = {(r["method"], r["mode"]): r for r in records if r["skin"] == "paper"}
    # Exact contact: LM leaves no penetration; augmented penalty stays within its tolerance.
    assert by["lm", "robust"]["penetration_max_m"] < 1e-6
    penalty = by["penalty", "robust"]["penetration_max_m"]
    assert 0.0 < penalty <= PenaltyParams().penetration_tolerance_m
    # Converged FE methods with exact contact agree on the force (measured 2.4 % apart).
    assert by["penalty", "robust"]["force_n"] == pytest.approx(
        by["lm", "robust"]["force_n"], rel=0.05
    )


def test_robust_step_targets_are_issue_5s(capsys: pytest.CaptureFixture[str]) -> None:
    """<= 20 / 100 / 500 ms on the 4,126 / 26,220 / 176,506-tet levels, only converged."""
    assert robust_step_target(4126, 19.9, True) == {
        "robust_target_step_ms": 20.0,
        "meets_robust_target": True,
    }
    assert robust_step_target(26220, 100.1, True)["meets_robust_target"] is False
    assert robust_step_target(176506, 499.0, True)["meets_robust_target"] is True
    assert robust_step_target(176506, 10.0, False)["meets_robust_target"] is False
    assert robust_step_target(623, 1.0, True) == {}
    records = [
        {"method": "lm", "tets": 4141, "step_ms": 12.5, **robust_step_target(4126, 12.5, True)},
        {"method": "pbd", "tets": 26854, "step_ms": 130.0, **robust_step_target(26220, 130, True)},
        {"method": "lm", "tets": 571, "step_ms": 2.0},
    ]
    print_robust_targets(records, "step_ms", "median step")
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[0] == "targets: a converged robust step"
    assert lines[1].split()[-1] == "meets" and "4141 tets" in lines[1]
    assert lines[2].split()[-1] == "MISSES" and "pbd" in lines[2]
    assert len(lines) == 3  # no target at 571 tets


def test_bench_tissue_reports_a_converged_newton_step(tmp_path: Path) -> None:
    (record,) = _run(
        ["bench", "tissue", "--levels", "623", "--repeats", "1"], tmp_path / "tissue.json"
    )
    assert record["tets"] == 571
    for key in ("assembly_ms", "paper_step_ms", "direct_factor_ms", "newton_step_ms"):
        assert math.isfinite(record[key]) and record[key] > 0.0, key
    assert record["newton_status"] == "ok"
    assert record["newton_residual_max"] <= 1e-4  # the robust mode's Newton tolerance
    assert 0.0 <= record["cg25_energy_error"] < 1.0


def test_bench_peer_compares_ours_with_mujoco_flex(tmp_path: Path) -> None:
    (record,) = _run(
        ["bench", "peer", "--levels", "623", "--sim-seconds", "0.2"], tmp_path / "peer.json"
    )
    assert record["tets"] == 571
    assert record["mujoco_status"] == "ok"
    for mode in ("paper", "robust"):
        ours = record["ours_ms_per_sim_s"][mode]
        assert ours > 0.0
        assert record["ratio"][mode] == pytest.approx(record["mujoco_ms_per_sim_s"] / ours)
    # Both sides are scored against our converged reference: robust LM follows it closely,
    # MuJoCo's flex (Saint Venant-Kirchhoff, soft contact) less so, but finitely.
    assert record["ours_lesion_error_m"]["robust"] < 1e-4
    assert math.isfinite(record["mujoco_lesion_error_m"])
    assert record["reference_lesion1_displacement_m"] > 1e-3 * 0.2  # 2 mm of travel moves it


def test_bench_env_reports_steps_per_second_and_where_the_time_goes(tmp_path: Path) -> None:
    json_path = tmp_path / "env.json"
    args = ["bench", "env", "--levels", "623", "--methods", "lm", "--skin", "2"]
    assert main([*args, "--json", str(json_path)]) == 0
    _check_markdown(json_path.with_suffix(".md"), args)
    payload = json.loads(json_path.read_text())
    assert payload["revision"] and payload["machine"]
    import envs
    from agents.lab.bench.env import SLIDE_STEPS

    assert [record["env_id"] for record in payload["records"]] == list(envs.ENV_IDS)
    for record in payload["records"]:
        assert record["tets"] == 571 and record["statuses"] == {"ok": record["steps"]}
        parts = ("robot_ms", "controller_ms", "tissue_ms", "observation_ms")
        # The robot's share is the substeps' time less the controller's, tens of
        # microseconds: on a loaded machine its median may round to zero.
        assert all(record[part] >= 0.0 for part in parts)
        assert record["tissue_ms"] > 0.0 and record["controller_ms"] > 0.0
        assert sum(record[part] for part in parts) <= record["step_wall_ms"] * 1.05
        assert record["steps_per_s"] > 0.0 and record["reset_ms"] > 0.0
        assert 0.0 < record["image_ms"] < 1e3  # a B-mode frame, timed apart from the steps
        assert record["reset_randomized_ms"] > record["reset_ms"]  # it builds a variant
        assert record["skin"] == "2 mm" and record["collision_edge_m"] == 0.002
        assert 0.0 <= record["skin_penetration_max_m"] < 0.5e-3  # LM, the skin at 2 mm
        assert 0.0 <= record["force_largest_dip"] < 1.0
        if record["env_id"].startswith("probegym/BreastCompress-"):  # a press normal to the skin
            assert record["force_largest_dip"] < 0.05
        assert 0.0 <= record["slide_force_largest_fall"] <= 1.0
        assert 0 <= record["slide_force_jumps"] <= SLIDE_STEPS
        assert record["iterations_per_step"] >= 1.0  # LM: at least one Newton iteration a step
    assert "image (ms a frame)" in json_path.with_suffix(".md").read_text()


def test_a_force_s_step_to_step_falls_and_jumps_are_counted_above_the_floor() -> None:
    from agents.lab.bench.contact import largest_step_fall

    # Below the 0.02 N floor nothing counts: 0.01 -> 1.0 is first contact, not a jump.
    assert largest_step_fall([0.0, 0.01, 1.0, 1.0, 0.3, 0.9, 0.85]) == (
        pytest.approx(0.7),
        2,  # 1.0 -> 0.3 and 0.3 -> 0.9; 0.9 -> 0.85 moves 5.6 %
    )
    assert largest_step_fall([0.5, 0.6, 0.7]) == (0.0, 0)  # rising only: no fall
    assert largest_step_fall([0.01, 0.0]) == (0.0, 0)
    assert largest_step_fall([]) == (0.0, 0)


def test_contact_targets_reach_its_markdown() -> None:
    """Every target a contact record carries becomes a row of the published table, with its
    verdict; records without one add none."""
    from agents.lab.bench.contact import _annotate_targets, markdown_tables, target_rows

    def record(method: str, mode: str, step_ms: float) -> dict:
        return {"method": method, "mode": mode, "level": 4126, "tets": 4141,
                "step_ms": step_ms, "step_ms_max": step_ms, "force_n": 1.0,
                "penetration_max_m": 0.0, "lesion1_displacement_m": 0.007,
                "skin_penetration_max_m": 0.0, "force_largest_dip": 0.0,
                "status_counts": {"ok": 50}, "stopped_by_wall_budget": False}  # fmt: skip

    records = [record("penalty", "paper", 4.0), record("lm", "paper", 9.0)]
    _annotate_targets(records)
    rows = target_rows(records)
    assert [
        "paper step", "penalty/paper (paper skin)", "4,141", "4.00 ms", "<= 5 ms", "met"
    ] in rows  # fmt: skip
    assert ["LM / penalty", "lm/paper (paper skin)", "4,141", "2.25 x", "<= 2 x", "MISSED"] in rows
    tables = markdown_tables(records, [4126])
    assert tables[-1].caption == "speed targets" and len(tables[-1].rows) == len(rows)
    untargeted = [record("pbd", "paper", 1.0)]
    _annotate_targets(untargeted)
    assert target_rows(untargeted) == []


def test_bench_sweep_compares_each_method_with_lm_on_the_same_commands(tmp_path: Path) -> None:
    json_path = tmp_path / "sweep.json"
    args = ["bench", "sweep", "--seeds", "0", "--mesh", "623", "--contact", "penalty"]
    assert main([*args, "--json", str(json_path)]) == 0
    _check_markdown(json_path.with_suffix(".md"), args)
    payload = json.loads(json_path.read_text())
    records = {record["contact"]: record for record in payload["records"]}
    assert set(records) == {"lm", "penalty"}
    lm, penalty = records["lm"], records["penalty"]
    # LM holds the skin's vertices exactly; its 2 mm facets stay within a fraction of a mm.
    assert lm["rms_error_n"] == 0.0 and lm["max_skin_penetration_mm"] < 0.5
    # The replay took LM's commands: the same number of steps unless its episode ended first.
    assert 0 < penalty["steps_compared"] == min(penalty["steps"], lm["steps"])
    # Penalty follows LM's force while sliding, not exactly: its springs let the skin in.
    assert 0.0 < penalty["rms_error_n"] < 0.5 and penalty["max_skin_penetration_mm"] > 0.0
    assert lm["mean_force_n"] > 0.5  # the sweep pressed
    with pytest.raises(SystemExit):
        main(["bench", "sweep", "--seeds", "zero"])


def test_bench_train_times_the_press_and_the_exploring_step(tmp_path: Path) -> None:
    json_path = tmp_path / "train.json"
    args = ["bench", "train", "--level", "623", "--algo", "none"]
    payload = _run(args, json_path)
    press, exploring = payload["records"]
    assert (press["phase"], exploring["phase"]) == ("press", "exploring")
    for record in (press, exploring):
        assert record["env_id"] == "probegym/BreastCompress-v2" and record["contact"] == "lm"
        assert record["tets"] == 571 and record["profile"] == "robust"
        assert record["collision_edge_m"] == 0.002  # the environments' default skin
        assert record["steps_per_s"] > 0.0 and record["newton_iterations_mean"] >= 1.0
        assert 0.0 < record["contact_share"] <= 1.0
    # PPO's initial spread under probegym train: e^-1.
    assert exploring["action_std"] == pytest.approx(math.exp(-1.0))
    ratio = exploring["steps_per_s"] / press["steps_per_s"]
    assert exploring["exploring_over_press"] == pytest.approx(ratio)
    assert exploring["meets_target"] == (ratio >= 0.85)


def test_bench_train_replay_times_a_policys_own_steps_in_contact() -> None:
    """The replay phase steps the policy on what it observes (here the task's scripted
    policy standing in for a trained one), across episodes, and times the steps in contact."""
    from agents.lab.bench.train import replay_record
    from agents.learning.policies.compression import CompressionPolicy

    seen: list[float] = []
    scripted = CompressionPolicy()

    def policy(observation: dict) -> np.ndarray:
        seen.append(float(observation["lesion"][3]))
        return scripted(observation)

    record = replay_record("probegym/BreastCompress-v0", "lm", 623, policy, steps=80)
    assert record["phase"] == "replay" and record["tets"] == 571
    assert len(seen) == 80  # one decision per step, from the step's own observation
    assert 1.0 in seen  # the lesion came into view: the policy pressed on what it saw
    assert 0 < record["steps_timed"] <= 80 and record["steps_per_s"] > 0.0
    assert record["episodes"] >= 2  # the scripted press succeeds in under 80 steps


def test_bench_train_steps_its_phases_in_turn_and_each_as_alone() -> None:
    """Stepped in turn (so that a machine's drifting speed reaches every phase alike), the
    press, the exploring actions and a policy's replay take the same steps, Newton
    iterations and episodes as each run on its own."""
    from agents.lab.bench.train import (
        exploring_record,
        phase_records,
        press_record,
        replay_record,
    )
    from agents.learning.policies.compression import CompressionPolicy

    env_id, level, steps = "probegym/BreastCompress-v2", 623, 60
    together = phase_records(env_id, "lm", level, CompressionPolicy(), steps=steps)
    alone = [
        press_record(env_id, "lm", level),
        exploring_record(env_id, "lm", level, steps=steps),
        replay_record(env_id, "lm", level, CompressionPolicy(), steps=steps),
    ]
    assert [r["phase"] for r in together] == ["press", "exploring", "replay"]
    for mixed, single in zip(together, alone, strict=True):
        for key in ("steps_timed", "newton_iterations_mean", "contact_share", "episodes"):
            assert mixed[key] == single[key], (mixed["phase"], key)


def test_interleaved_runs_advance_by_their_share_of_work() -> None:
    from agents.lab.bench.timed_runs import TimedRun, interleave

    order: list[str] = []

    def run(name: str, steps: int) -> TimedRun:
        for step in range(1, steps + 1):
            order.append(name)
            yield step / steps
        return {"phase": name}

    records = interleave([run("a", 2), run("b", 6)])
    assert records == [{"phase": "a"}, {"phase": "b"}]
    # b takes three steps for each of a's: neither runs far ahead of the other.
    assert order == ["a", "b", "b", "b", "a", "b", "b", "b"]


def test_bench_train_refuses_a_model_of_another_task_before_any_work(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text(json.dumps({"env_id": "probegym/ForceScan-v1"}))
    (run / "model.zip").write_bytes(b"not read")
    json_path = tmp_path / "train.json"
    args = ["bench", "train", "--algo", "none", "--model", str(run), "--json", str(json_path)]
    assert main(args) == 2
    error = capsys.readouterr().err
    assert "probegym/ForceScan-v1" in error and "--ids" in error
    assert not json_path.exists()
    assert main([*args[:-4], "--model", str(tmp_path / "missing"), "--json", str(json_path)]) == 2
    assert "missing" in capsys.readouterr().err


@pytest.mark.slow
def test_bench_train_times_probegym_train_end_to_end(tmp_path: Path) -> None:
    """The train phase runs probegym train's own path (two worker processes, PPO's one
    update) and accounts for its loop's wall time by parts; the threads phase times two
    environments in threads against one after another."""
    json_path = tmp_path / "train.json"
    args = ["bench", "train", "--level", "623", "--algo", "ppo", "--train-steps", "64"]
    payload = _run(args, json_path)
    press, _, threads, trained = payload["records"]
    assert threads["phase"] == "threads" and threads["n_envs"] == 2
    assert threads["steps_per_env"] == 100 and threads["threaded_s"] > 0.0
    assert threads["thread_speedup"] == pytest.approx(
        threads["sequential_s"] / threads["threaded_s"]
    )
    assert trained["phase"] == "train" and trained["algo"] == "ppo"
    assert trained["n_envs"] == 2 and trained["cores"] >= 1
    # PPO collects a whole rollout (1,024 steps per env) before it checks the budget.
    assert trained["steps"] == 2048
    parts = trained["parts_s"]
    assert set(parts) >= {"env_s", "transfer_s", "normalisation_s", "inference_s", "updates_s"}
    assert all(value >= 0.0 for value in parts.values())
    assert 0.0 < parts["env_tissue_s"] < parts["env_s"] <= parts["env_steps_summed_s"]
    named = sum(parts[k] for k in ("env_s", "transfer_s", "normalisation_s", "inference_s"))
    # The parts add up to the loop (the clamps at zero aside): nothing large is unaccounted.
    assert named + parts["updates_s"] == pytest.approx(trained["loop_s"], rel=0.05)
    assert trained["steps_per_s"] == pytest.approx(2048 / trained["loop_s"])
    ratio = trained["steps_per_s"] / (min(2, trained["cores"]) * press["steps_per_s"])
    assert trained["train_over_press"] == pytest.approx(ratio)
    assert trained["meets_target"] == (ratio >= 0.75)
    assert "probegym train end to end" in json_path.with_suffix(".md").read_text()
