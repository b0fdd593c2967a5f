"""``probegym study --robot``: the study's cells with the arm holding the probe, compared
with the kinematic cells."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from agents.lab.study import robot as robot_module
from agents.lab.study import robot_runner
from agents.lab.study.cell import run_cell
from agents.lab.study.robot import (
    TWIN_ENV_TISSUE,
    TWIN_FROM_RESULTS,
    TWIN_RUN,
    check_robot_spec,
    run_robot_cell,
)
from agents.lab.study.robot_runner import (
    compare_with_kinematic,
    kinematic_records,
    kinematic_twin,
    robot_cell_with_twin,
    run_robot_study,
)
from agents.lab.study.runner import RESULTS_FILE, SPEC_FILE, read_results
from agents.lab.study.spec import Cell, StudySpec
from tissue import TissueSpec
from tissue.contact.stability import StabilityLimits
from tissue.errors import ConfigError
from tissue.profile import Profile

# One cell: the dome's top lesion on the coarsest level, pressed 10 mm (about 5 s).
ONE = StudySpec(methods=("lm",), levels=(623,), lesions=(1,), configs=("robust",), depths_m=(0.01,))
ONE_CELL = Cell(Profile.ROBUST, "lm", 623, 1)
PRESCRIBED = StudySpec(
    methods=("prescribed",), levels=(623,), lesions=(1,), configs=("robust",), depths_m=(0.01,)
)
PRESCRIBED_CELL = Cell(Profile.ROBUST, "prescribed", 623, 1)
#: The arm's translational impedance [N/m] (envs.controller.ControllerConfig's default).
STIFFNESS_N_PER_M = 3000.0


def _quiet(_: str) -> None:
    pass


@pytest.fixture(scope="module")
def one_cell() -> dict:
    return compare_with_kinematic(run_robot_cell(ONE, ONE_CELL), run_cell(ONE, ONE_CELL), "run")


def test_robot_cell_records_the_protocol_and_agrees_with_the_kinematic_cell(one_cell) -> None:
    record = one_cell
    assert record["key"] == ONE_CELL.key and record["robot"] is True
    assert record["status"] == "ok" and record["instability"] is None
    assert record["stability_percent"] == 100.0
    assert record["depths_m"] == [0.01]
    for name in ("tracked_m", "force_normal_n", "skin_penetration_m", "lesion_error_m"):
        assert len(record[name]) == 1, name
    tracking = record["tracking"]
    for name in ("along_m", "across_m", "orientation_deg"):
        assert len(tracking[name]) == 1 and np.isfinite(tracking[name][0]), name
    trace = record["trace"]
    assert len(trace["t_s"]) == record["step_ms"]["count"] > 55  # 55 motion steps + holds
    assert sum(trace["moving"]) == 55  # 11 mm at 0.2 mm a step, as the kinematic cell
    force = record["force_normal_n"][0]
    kinematic_force = record["kinematic"]["force_normal_n"][0]
    along = tracking["along_m"][0]
    # Held still, the impedance balances the tissue's push: the probe stops short of its
    # target by F / K (measured: 0.448 mm at 1.342 N, F / K = 0.447 mm).
    assert -1e-3 < along < 0.0
    assert along == pytest.approx(-force / STIFFNESS_N_PER_M, rel=0.05)
    # Across the axis and in orientation the arm holds the target closely (measured
    # 0.0002 mm, 0.005 degrees).
    assert tracking["across_m"][0] < 5e-5
    assert tracking["orientation_deg"][0] < 0.1
    # Pressed |along| less deep, the tissue pushes back less: by its stiffness times the
    # shortfall. The force-depth curve stiffens (measured: its slope at 10 mm is 1.5 x its
    # secant F / d), so the gap lies within 3 x secant x shortfall (measured 0.098 N).
    gap = kinematic_force - force
    assert 0.0 < gap <= 3.0 * (kinematic_force / 0.01) * abs(along)
    # The lesion under the probe moves by less than the probe: the lesion error is at most
    # the shortfall (measured 0.37 mm for 0.45 mm), with 0.05 mm for settling differences.
    error = record["lesion_error_m"][0]
    assert 0.0 < error <= abs(along) + 5e-5


def test_a_physical_failure_is_recorded_as_data(monkeypatch: pytest.MonkeyPatch) -> None:
    # A penetration bound no contact meets (1 nm): the first step touching the skin is an
    # instability, which must end the cell as a record, not an exception.
    strict = StabilityLimits(penetration_m=1e-9, landmark_jump_margin_m=None)
    monkeypatch.setattr(robot_module, "STUDY_LIMITS", strict)
    spec = StudySpec(
        methods=("penalty",), levels=(623,), lesions=(1,), configs=("robust",), depths_m=(0.01,)
    )
    record = run_robot_cell(spec, Cell(Profile.ROBUST, "penalty", 623, 1))
    assert record["status"] == "unstable"
    assert record["instability"]["kind"] == "penetration"
    assert record["depths_m"] == [] and record["tracked_m"] == []
    assert 0.0 <= record["stability_percent"] < 100.0
    assert json.dumps(record, allow_nan=False)  # no NaN passed off as a number


@pytest.mark.parametrize(
    ("spec", "names"),
    [
        (StudySpec(methods=("lm",), levels=(623,), depths_m=(0.01, 0.035)), ["35 mm", "0.034"]),
        (StudySpec(scene="paper", methods=("lm",), levels=(623,)), ["--scene paper", "phantom"]),
    ],
)
def test_bad_input_is_refused_naming_the_value_and_the_fix(spec: StudySpec, names) -> None:
    with pytest.raises(ConfigError) as caught:
        check_robot_spec(spec)
    for name in names:
        assert name in str(caught.value)


def test_kinematic_twins_are_read_only_from_a_study_with_the_same_physics(
    tmp_path: Path,
) -> None:
    record = {"key": ONE_CELL.key, "status": "ok"}
    (tmp_path / SPEC_FILE).write_text(json.dumps(ONE.as_json()))
    (tmp_path / RESULTS_FILE).write_text(json.dumps(record) + "\n")
    assert kinematic_records(ONE, tmp_path, _quiet) == {ONE_CELL.key: record}
    deeper = StudySpec(
        methods=("lm",), levels=(623,), lesions=(1,), configs=("robust",), depths_m=(0.02,)
    )
    assert kinematic_records(deeper, tmp_path, _quiet) == {}
    assert kinematic_records(ONE, tmp_path / "missing", _quiet) == {}


def test_twins_of_lm_and_penalty_are_the_study_s_and_of_the_others_the_env_s_tissue(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    calls: list[tuple[str, object]] = []

    def spy(spec: StudySpec, cell: Cell, tissue_spec: object = None) -> dict:
        calls.append((cell.key, tissue_spec))
        return {"key": cell.key, "ran": True}

    monkeypatch.setattr(robot_runner, "run_cell", spy)
    env_spec = TissueSpec(mesh=623, contact="prescribed")
    stored: dict[str, dict] = {
        ONE_CELL.key: {"key": ONE_CELL.key},
        PRESCRIBED_CELL.key: {"stale": True},
    }
    # LM with the kinematic study's record: read, nothing run.
    assert kinematic_twin(ONE, ONE_CELL, env_spec, stored) == (
        stored[ONE_CELL.key],
        TWIN_FROM_RESULTS,
    )
    assert calls == []
    # LM without one: the study's own cell, run with the study's configuration.
    assert kinematic_twin(ONE, ONE_CELL, env_spec, {})[1] == TWIN_RUN
    assert calls == [(ONE_CELL.key, None)]
    # Prescribed: the study's record is not its twin (other contact settings); the protocol
    # runs on the environment's tissue.
    twin, source = kinematic_twin(PRESCRIBED, PRESCRIBED_CELL, env_spec, stored)
    assert source == TWIN_ENV_TISSUE and twin["ran"]
    assert calls[-1] == (PRESCRIBED_CELL.key, env_spec)


def test_a_twin_on_another_tissue_than_the_cell_s_is_refused() -> None:
    with pytest.raises(ValueError, match="not the study's level 623"):
        run_cell(PRESCRIBED, PRESCRIBED_CELL, TissueSpec(mesh=1363, contact="prescribed"))
    with pytest.raises(ValueError, match="contact and profile"):
        run_cell(PRESCRIBED, PRESCRIBED_CELL, TissueSpec(mesh=623, contact="pbd"))


def test_prescribed_robot_cell_agrees_with_its_twin_on_the_environment_s_tissue() -> None:
    record = robot_cell_with_twin(PRESCRIBED, PRESCRIBED_CELL, {})
    assert record["kinematic"]["source"] == TWIN_ENV_TISSUE
    assert record["kinematic"]["tissue"] == "environment"
    assert record["status"] == "ok" and record["kinematic"]["status"] == "ok"
    assert record["depths_m"] == [0.01] and len(record["penetration_max_m"]) == 1
    force, along = record["force_normal_n"][0], record["tracking"]["along_m"][0]
    # The same balance as LM's: the probe stops short by F / K (measured 0.44 mm at 1.33 N),
    # pressing less than the kinematic probe (measured 1.43 N) and moving the lesion less
    # than its shortfall (measured 0.37 mm).
    assert along == pytest.approx(-force / STIFFNESS_N_PER_M, rel=0.05)
    gap = record["kinematic"]["force_normal_n"][0] - force
    assert 0.0 < gap <= 3.0 * (record["kinematic"]["force_normal_n"][0] / 0.01) * abs(along)
    assert 0.0 < record["lesion_error_m"][0] <= abs(along) + 5e-5
    # The study's own prescribed cell (sticking, no skin guard) is another tissue: its force
    # differs from the twin's by more than the round-off of one protocol.
    study = run_cell(PRESCRIBED, PRESCRIBED_CELL)
    assert study["tissue"] == "study"
    assert abs(study["force_normal_n"][0] - record["kinematic"]["force_normal_n"][0]) > 1e-3


@pytest.mark.slow
def test_robot_study_writes_its_outputs_and_resumes(tmp_path: Path) -> None:
    methods = ("lm", "penalty", "prescribed", "pbd")
    spec = StudySpec(methods=methods, levels=(623,), lesions=(1, 10), configs=("robust",))
    outcome = run_robot_study(spec, tmp_path, progress=False, log=_quiet)
    out = tmp_path / "robot"
    assert outcome.ran_now == 8 and not outcome.failed
    for name in ("robot_vs_kinematic.png", "tracking.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    table = (out / "robot.md").read_text()
    assert "lesion error robot vs kinematic" in table and "| 10 | 30 |" in table
    assert "run kinematically on the environment's own tissue" in table
    records = read_results(out / RESULTS_FILE)
    assert len(records) == 8
    for record in records:
        assert record["status"] == "ok" and record["kinematic"]["status"] == "ok"
        env_twin = record["method"] in ("prescribed", "pbd")
        assert record["kinematic"]["source"] == (TWIN_ENV_TISSUE if env_twin else TWIN_RUN)
        assert record["depths_m"] == list(spec.depths_m)
        along = np.abs(record["tracking"]["along_m"])
        # The shortfall is the impedance's give under the force at every depth.
        np.testing.assert_allclose(
            along, np.array(record["force_normal_n"]) / STIFFNESS_N_PER_M, rtol=0.05
        )
        # Measured up to 2.5 mm at 30 mm (7.5 N); the lesion follows the probe's shortfall
        # (penalty at 623, lesion 1, 30 mm: 2.52 mm for 2.49 mm). Sliding prescribed
        # displacement and PBD move it up to 0.5 mm further (prescribed, lesion 10, 20 mm:
        # 1.57 mm for 1.08 mm).
        beyond = 1e-3 if env_twin else 2e-4
        assert np.all(np.array(record["lesion_error_m"]) <= along + beyond)
        assert record["tracking"]["orientation_max_deg"] < 0.5
    again = run_robot_study(spec, tmp_path, progress=False, log=_quiet)
    assert again.ran_now == 0 and again.skipped == 8
    with pytest.raises(ConfigError, match="different depths_m"):
        run_robot_study(
            StudySpec(methods=("lm",), levels=(623,), lesions=(1,), depths_m=(0.01,)),
            tmp_path,
            progress=False,
            log=_quiet,
        )
