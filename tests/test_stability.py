"""The stability monitor: each check fires on what it guards against, and only then."""

from __future__ import annotations

import numpy as np
import pytest

from tissue.contact.base import ContactResult
from tissue.contact.stability import StabilityLimits, StabilityMonitor
from tissue.errors import ConfigError
from tissue.status import StepStatus

REST = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.0, 0.01, 0.0], [0.0, 0.0, 0.01]])


def _result(
    status: StepStatus = StepStatus.OK,
    penetration: float = 0.0,
    landmark: tuple[float, float, float] = (0.0, 0.0, 0.005),
    force: tuple[float, float, float] = (0.0, 0.0, 1.0),
    compute_ms: float = 1.0,
) -> ContactResult:
    return ContactResult(
        status=status,
        time_s=0.02,
        force_world=np.array(force),
        torque_world=np.zeros(3),
        contact_points=np.zeros((0, 3)),
        contact_forces=np.zeros((0, 3)),
        penetration_max_m=penetration,
        landmarks=np.array([landmark]),
        compute_ms=compute_ms,
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
def test_each_check_fires(kind: str, result: ContactResult, positions: np.ndarray) -> None:
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
