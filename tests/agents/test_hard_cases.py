"""The hard-case catalogue: every method stays stable in the robust configuration.

The fast tier runs the small cases on the 1,363-tet level; the slow tier the 4,126-tet level,
the two finest levels (``fine_105k`` and ``fine_176k``: the four methods took 4.5 and 8
minutes here) and the published scene's real level-4 poses. Known failures are strict
xfails: each says what fails, and the test turns red the day it passes, so the catalogue
stays honest.
"""

from __future__ import annotations

import numpy as np
import pytest

from agents.lab.compress import run_compression
from agents.lab.hard_cases import HARD_CASES, SMALL_CASES, case_path, hard_case, run_hard_case
from tissue.contact import make_contact_model
from tissue.errors import ConfigError
from tissue.mesh.phantom import breast_phantom
from tissue.probe import parse_probe_spec
from tissue.sim.simulator import SimulationConfig

METHODS = ("lm", "penalty", "prescribed", "pbd")
# (case, method) -> why it still fails, measured on the 1,363-tet level.
KNOWN_FAILURES_1363: dict[tuple[str, str], str] = {}


def _check(record: dict) -> None:
    assert record["stable"], (
        f"{record['case']} / {record['method']}: {record['instability']}, "
        f"energy ok {record['energy_ok']}"
    )
    assert record["stability_percent"] == 100.0
    assert record["energy_ok"]


def _params(known: dict[tuple[str, str], str]) -> list:
    return [
        pytest.param(
            case,
            method,
            marks=pytest.mark.xfail(strict=True, reason=known[(case, method)])
            if (case, method) in known
            else (),
            id=f"{case}-{method}",
        )
        for case in SMALL_CASES
        for method in METHODS
    ]


@pytest.mark.parametrize(("case", "method"), _params(KNOWN_FAILURES_1363))
def test_small_cases_are_stable_in_robust_mode(case: str, method: str) -> None:
    _check(run_hard_case(case, method, "robust", level=1363))


def test_sliding_slip_is_resolved_in_time() -> None:
    """Sliding's fastest landmark motion is a physical slip, not a numerical one: with half
    the time step the lesion slips at the same speed and ends where it did. Frictionless
    contact on the dome lets the tissue slide back once the face has passed the apex. (With
    the lesion layout before the flank lesions moved inwards, the slip outran the per-step
    bound at h = 20 ms, 1.7 mm per step at 86 mm/s, and not at 10 ms.)"""
    mesh = breast_phantom(1363)
    shape = parse_probe_spec("face")
    case = hard_case("sliding_40mm")
    start, stops = case_path(case, mesh, shape)
    paths = {}
    for dt in (0.02, 0.01):
        model = make_contact_model(
            "lm", mesh, shape, config=SimulationConfig(mode="robust", tissue_dt=dt)
        )
        rows: list = []
        run_compression(model, start, stops, case.speed_m_s,
                        observer=lambda r, p: rows.append((r.landmarks_world_m.copy(), p.copy())))  # noqa: B023  # fmt: skip
        landmarks = np.array([r[0] for r in rows])
        probe = np.array([r[1] for r in rows])
        moved = np.linalg.norm(np.diff(landmarks, axis=0), axis=2).max(axis=1)
        probe_moved = np.linalg.norm(np.diff(probe, axis=0), axis=1)
        paths[dt] = (landmarks, moved / dt, moved - probe_moved)
    coarse, fine = paths[0.02], paths[0.01]
    assert max(coarse[2].max(), fine[2].max()) <= 1e-3  # the per-step bound holds at both
    assert fine[1].max() == pytest.approx(coarse[1].max(), rel=0.2)  # same slip speed
    # The same slip: the lesion that moved most per unit time slides the same distance.
    for landmarks in (coarse[0], fine[0]):
        assert np.linalg.norm(landmarks[-1] - landmarks[0], axis=1).max() > 5e-3
    assert np.linalg.norm(coarse[0][-1] - fine[0][-1], axis=1).max() < 0.5e-3


def test_catalogue_names_every_scenario_of_the_issue() -> None:
    expected = {
        "fine_105k", "fine_176k", "deep_30mm", "paper_level4", "nu_0499", "stiff_lesions",
        "penalty_soft", "penalty_stiff", "fast_probe", "tilted_30", "edge_contact",
        "sliding_40mm", "sudden_release",
    }  # fmt: skip
    assert set(HARD_CASES) == expected
    assert HARD_CASES["penalty_stiff"].penalty_stiffness_scale / (
        HARD_CASES["penalty_soft"].penalty_stiffness_scale
    ) == pytest.approx(1000.0)


def test_paths_do_what_their_names_say() -> None:
    mesh = breast_phantom(623)
    shape = parse_probe_spec("face")
    start, stops = case_path(hard_case("sudden_release"), mesh, shape)
    assert stops[-1].speed_m_s == float("inf")
    assert stops[-1].position == pytest.approx(start.position)
    start, stops = case_path(hard_case("sliding_40mm"), mesh, shape)
    assert abs(stops[-1].position[0] - stops[0].position[0]) == pytest.approx(0.04, abs=1e-3)
    start, stops = case_path(hard_case("tilted_30"), mesh, shape)
    direction = stops[0].position - start.position
    cosine = -direction[2] / (direction @ direction) ** 0.5
    assert cosine == pytest.approx(3**0.5 / 2, abs=1e-6)


def test_unknown_case_is_a_clear_error() -> None:
    with pytest.raises(ConfigError, match="unknown hard case 'deep'"):
        run_hard_case("deep", "lm")


# Measured on the 4,126-tet level.
KNOWN_FAILURES_4126: dict[tuple[str, str], str] = {
    # The robust PBD (60 substeps; the paper's 10 fail every case here but the tilt and edge).
    ("sliding_40mm", "pbd"): "lesion 1, dragged 9 mm sideways under the sliding probe, snaps "
    "back 2.12 then 3.12 mm a step as the probe's edge passes it (XPBD; the FE's snap is slowed "
    "by its Rayleigh stiffness damping and backward Euler to at most 0.78 mm a step; the FE's "
    "r_K as an exact velocity pass per substep still leaves 1.23 mm, see tissue.pbd)",
}


@pytest.mark.slow
@pytest.mark.parametrize(("case", "method"), _params(KNOWN_FAILURES_4126))
def test_small_cases_on_4126_tets(case: str, method: str) -> None:
    _check(run_hard_case(case, method, "robust", level=4126))


@pytest.mark.slow
@pytest.mark.parametrize("method", METHODS)
def test_published_level4_poses(method: str, paper_scene_dir) -> None:
    _check(run_hard_case("paper_level4", method, "robust", scene_dir=paper_scene_dir))


#: The finest level in the slow tier: LM at 105,004 tets (1.5 min on two cores). The whole
#: grid, every method at 105,004 and 176,506 tets, takes about 40 min on two cores (penalty at
#: 176,506 alone 14 min: a Newton solve per augmentation round at that size), too much for CI:
#: `probegym hard-cases --cases fine_105k,fine_176k` runs it (docs/hard-cases.md).
FINEST = [("fine_105k", "lm")]


@pytest.mark.slow
@pytest.mark.parametrize(("case", "method"), FINEST)
def test_finest_levels(case: str, method: str) -> None:
    """10 and 20 mm at the dome's top on the finest levels (:data:`FINEST`), robust
    configuration (LM and penalty act on the volume's boundary there; fine_105k inverted a
    tet at 19 mm with the ~500-point collision surface)."""
    _check(run_hard_case(case, method, "robust"))


def test_the_energy_check_fires_when_the_tissue_holds_more_than_the_probe_gave() -> None:
    """The catalogue's energy check (elastic + kinetic <= the probe's work) passes a real
    press and fires on the same press with the probe's force hidden from it (no work done,
    energy stored)."""
    from dataclasses import replace

    from agents.lab.hard_cases import _EnergyCheck
    from tissue.contact.placement import first_contact_pose

    mesh = breast_phantom(623)
    model = make_contact_model(
        "lm", mesh, parse_probe_spec("face"), config=SimulationConfig(mode="robust")
    )
    position, quat = first_contact_pose(
        model.surface,
        mesh.nodes,
        model.probe.shape,
        np.array([0.0, 0.0, 0.04]),
        np.array([0.0, 0.0, -1.0]),
    )
    honest = _EnergyCheck(model, position, quat)
    blind = _EnergyCheck(model, position, quat)
    model.place_probe(position, quat)
    for k in range(1, 21):
        pose = position - [0.0, 0.0, 2e-4 * k]
        result = model.step(pose, quat)
        honest(result, pose)
        blind(replace(result, force_world_n=np.zeros(3), torque_world_nm=np.zeros(3)), pose)
    assert honest.ok and honest.work_j > 0
    assert not blind.ok and blind.worst_excess_j > 0.5 * honest.work_j
