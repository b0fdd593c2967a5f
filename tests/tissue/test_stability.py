"""The stability monitor: each check fires on what it guards against, and only then."""

from __future__ import annotations

import numpy as np
import pytest

from tissue.contact.stability import StabilityLimits, StabilityMonitor
from tissue.errors import ConfigError
from tissue.status import StepStatus
from tissue.step_result import StepDiagnostics, TissueStep

REST = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.0, 0.01, 0.0], [0.0, 0.0, 0.01]])


def _result(
    status: StepStatus = StepStatus.OK,
    penetration: float = 0.0,
    landmark: tuple[float, float, float] = (0.0, 0.0, 0.005),
    force: tuple[float, float, float] = (0.0, 0.0, 1.0),
    compute_ms: float = 1.0,
) -> TissueStep:
    diagnostics = StepDiagnostics(
        iterations=1,
        linear_iterations=0,
        contact_count=0,
        sub_motions=1,
        subdivisions=0,
        min_volume_ratio=None,
        compute_ms=compute_ms,
    )
    return TissueStep(
        status=status,
        time_s=0.02,
        force_world_n=np.array(force),
        torque_world_nm=np.zeros(3),
        contact_points_world_m=np.zeros((0, 3)),
        contact_forces_world_n=np.zeros((0, 3)),
        skin_penetration_m=0.0,
        landmarks_world_m=np.array([landmark]),
        lesion_centroids_world_m=np.zeros((0, 3)),
        diagnostics=diagnostics,
        method_penetration_m=penetration,
    )


def _monitor(method: str = "lm", **limits: float | None) -> StabilityMonitor:
    return StabilityMonitor(method, REST, np.array([0.0, 0.0, 0.02]), StabilityLimits(**limits))


def test_a_quiet_step_is_stable() -> None:
    monitor = _monitor()
    assert monitor.check(_result(), REST, np.array([0.0, 0.0, 0.0198])) is None
    assert monitor.check(_result(), REST, np.array([0.0, 0.0, 0.0196])) is None


@pytest.mark.parametrize(
    ("kind", "result", "positions"),
    [
        ("status", _result(status=StepStatus.INVERTED), REST),
        ("non_finite", _result(force=(np.nan, 0.0, 0.0)), REST),
        ("non_finite", _result(), REST + np.array([np.inf, 0, 0])),
        ("penetration", _result(penetration=0.0006), REST),
        ("timeout", _result(compute_ms=121e3), REST),
        ("blow_up", _result(), REST + np.array([0.0, 0.0, 0.006])),
    ],
)
def test_each_check_fires(kind: str, result: TissueStep, positions: np.ndarray) -> None:
    found = _monitor().check(result, positions, np.array([0.0, 0.0, 0.0199]))
    assert found is not None and found.kind == kind


def test_penetration_bound_depends_on_the_method() -> None:
    result = _result(penetration=0.0015)
    probe = np.array([0.0, 0.0, 0.0199])
    assert _monitor("lm").check(result, REST, probe) is not None
    assert _monitor("penalty").check(result, REST, probe) is None
    assert _monitor("lm", penetration_m=0.002).check(result, REST, probe) is None


def test_landmark_jump_beyond_probe_motion_and_its_opt_out() -> None:
    for margin, expected in ((0.001, "landmark_jump"), (None, None)):
        monitor = _monitor(landmark_jump_margin_m=margin)
        probe = np.array([0.0, 0.0, 0.0198])
        assert monitor.check(_result(), REST, probe) is None
        jumped = _result(landmark=(0.0, 0.0035, 0.005))  # 3.5 mm while the probe holds still
        found = monitor.check(jumped, REST, probe)
        assert (found.kind if found else None) == expected


def test_limits_reject_nonsense() -> None:
    with pytest.raises(ConfigError, match="step_timeout_s"):
        StabilityLimits(step_timeout_s=0.0)
    with pytest.raises(ConfigError, match="penetration_m"):
        StabilityLimits(penetration_m=-1.0)


def _compression_failing_at(call: int, depths: list[float], settle: int) -> dict:
    """A penalty press of the 623-tet phantom whose ``call``-th step reports a divergence:
    run_compression's record, with the stability monitor on."""
    from dataclasses import replace

    from agents.lab.compress import build_model, plan_straight, run_compression
    from tissue.mesh.phantom import breast_phantom
    from tissue.probe import linear_probe

    mesh = breast_phantom(623)
    model = build_model(mesh, linear_probe(), "penalty", "robust", None, None, None)
    start, stops = plan_straight(model, None, np.array([0.0, 0.0, -1.0]), depths)
    real = model.step
    calls = {"n": 0}

    def step(position, quat):
        calls["n"] += 1
        result = real(position, quat)
        return replace(result, status=StepStatus.DIVERGED) if calls["n"] == call else result

    model.step = step  # type: ignore[method-assign]
    monitor = StabilityMonitor("penalty", mesh.nodes, start.position)
    return run_compression(model, start, stops, 0.01, monitor=monitor, max_settle_steps=settle)


def test_the_stability_metric_counts_the_motion_steps_before_the_failure() -> None:
    """The paper's metric by hand: 0.2 mm steps from 1 mm clear of the skin to 2 mm deep
    (15 steps), then to 4 mm (10 more); failing on the 7th step leaves 6 of the 25
    completed: the failed step is not one of them."""
    record = _compression_failing_at(7, [0.002, 0.004], settle=3)
    assert record["instability"]["step"] == 6
    total = 15 + 10  # 3 mm from 1 mm clear to 2 mm deep, then 2 mm more
    assert record["stability_percent"] == pytest.approx(100.0 * 6 / total)


def test_a_failure_while_settling_counts_as_failing_on_that_depths_last_motion_step() -> None:
    """Reaching 2 mm takes 15 motion steps (from 1 mm clear); failing on the 2nd settling
    step there counts as failing on the 15th motion step: 14 completed of 25."""
    record = _compression_failing_at(17, [0.002, 0.004], settle=5)
    assert record["instability"]["step"] == 16
    assert record["stability_percent"] == pytest.approx(100.0 * 14 / 25)
