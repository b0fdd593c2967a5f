"""The tissue sleeps in free air (``TissueSpec(sleep_speed_m_s=...)``): a step with the tissue
at rest, out of contact and the probe clear of the skin runs no solve, reports what a step
would, and the tissue wakes before the probe touches.

Every registered method and both profiles on the 623-tet phantom, each beside a twin with sleep
off stepping the same poses. What "the same" means was measured first: a full step in free air
leaves a tissue at rest exactly at rest for robust penalty and robust prescribed displacement
(no Newton iteration is needed), and moves it by round-off elsewhere (at most about 1e-17 m at
623 and 1,363 tets; the paper profile's capped CG then carries that into forces in contact at
about 1e-6 relative). So the sleeping tissue is compared bit for bit with the twin where the
twin stayed exactly at rest, and otherwise bit for bit with the tissue it is -- one at rest,
reset where the probe woke it -- and within round-off or 1 um of the twin.
"""

from __future__ import annotations

import math
import pickle
from collections.abc import Callable, Iterator

import numpy as np
import pytest
from numpy.typing import NDArray

import tissue
from tissue.contact.sleep import SLEEP_SAFETY_MARGIN_M
from tissue.probe import LinearProbeFace, Probe, matrix_to_quat, quat_to_matrix

METHODS = ("penalty", "lm", "prescribed", "pbd")
PROFILES = ("paper", "robust")
LEVEL = 623
ABOVE_M = 0.02  # the probe's start, above the skin along its pressing axis
SPEED = tissue.SLEEP_SPEED_M_S
# The largest displacement a full free-air step leaves on a tissue at rest [m] (measured:
# 1e-17 m; see the module docstring).
ROUND_OFF_M = 1e-15

Pose = tuple[NDArray[np.float64], NDArray[np.float64]]


@pytest.fixture(scope="module")
def built() -> dict[tuple[str, str, bool], tissue.Tissue]:
    return {}


def _tissue(built, method: str, profile: str, sleep: bool) -> tissue.Tissue:
    """A tissue per (method, profile, sleep) for the module (built once: PBD's calibration)."""
    key = (method, profile, sleep)
    if key not in built:
        built[key] = tissue.make_tissue(
            mesh=LEVEL, contact=method, profile=profile, sleep_speed_m_s=SPEED if sleep else None
        )
    return built[key]


def _pair(built, method: str, profile: str) -> tuple[tissue.Tissue, tissue.Tissue]:
    return _tissue(built, method, profile, True), _tissue(built, method, profile, False)


def _frame(t: tissue.Tissue) -> tuple[Pose, NDArray[np.float64]]:
    """The pose touching the skin above lesion 1 and the pressing direction there."""
    position, quat = t.touching_pose(t.lesions[0].rest_centre_m)
    return (position, quat), tissue.pressing_direction(quat)


class _Solves:
    """Counts the calls of a model's ``_advance`` (its solve), which it then runs."""

    def __init__(self, model: tissue.ContactModel) -> None:
        self.count = 0
        self._advance: Callable = model._advance

    def __call__(self, h: float):
        self.count += 1
        return self._advance(h)


@pytest.fixture
def spy(monkeypatch: pytest.MonkeyPatch) -> Iterator[Callable[[tissue.Tissue], _Solves]]:
    def install(t: tissue.Tissue) -> _Solves:
        solves = _Solves(t.contact_model)
        monkeypatch.setattr(t.contact_model, "_advance", solves)
        return solves

    yield install


def _asleep(step: tissue.TissueStep) -> bool:
    return step.diagnostics.details.get("asleep", 0.0) == 1.0


def _observed(step: tissue.TissueStep, pose: Pose) -> NDArray[np.float32]:
    """What an environment observes of the tissue: lesion centroids and landmarks in the probe
    frame, and the wrench, in float32 (``envs.observations`` casts them so)."""
    rotation = quat_to_matrix(pose[1])
    points = np.concatenate([step.lesion_centroids_world_m, step.landmarks_world_m])
    local = (points - pose[0]) @ rotation
    wrench = np.concatenate([step.force_world_n, step.torque_world_nm])
    return np.concatenate([local.ravel(), wrench]).astype(np.float32)


def _speed(t: tissue.Tissue) -> float:
    return float(np.linalg.norm(t.velocities_m_s, axis=1).max())


def _touched(step: tissue.TissueStep) -> bool:
    return bool(
        np.any(step.force_world_n != 0.0)
        or step.contact_points_world_m.shape[0]
        or step.skin_penetration_m > 0.0
    )


@pytest.mark.parametrize("profile", PROFILES)
@pytest.mark.parametrize("method", METHODS)
def test_far_above_the_skin_steps_sleep_and_report_what_a_step_would(
    built, spy, method: str, profile: str
) -> None:
    sleeper, twin = _pair(built, method, profile)
    (touching, quat), pressing = _frame(sleeper)
    above = touching - ABOVE_M * pressing
    lateral = quat_to_matrix(quat)[:, 0]
    # Held, slid sideways and turned, all far from the skin.
    turned = quat_to_matrix(quat) @ np.array(
        [[math.cos(0.1), 0.0, math.sin(0.1)], [0.0, 1.0, 0.0], [-math.sin(0.1), 0.0, math.cos(0.1)]]
    )
    poses = [(above, quat)] * 3 + [(above + 0.001 * k * lateral, quat) for k in range(1, 5)]
    poses += [(above, matrix_to_quat(turned))] * 2
    for t in (sleeper, twin):
        t.reset(above, quat)
    solves = spy(sleeper)
    rest = sleeper.rest_nodes_m
    for pose in poses:
        asleep, full = sleeper.step(*pose), twin.step(*pose)
        assert _asleep(asleep) and asleep.diagnostics.iterations == 0
        assert "asleep" not in full.diagnostics.details
        assert asleep.status is full.status is tissue.StepStatus.OK
        assert asleep.time_s == full.time_s
        assert np.array_equal(asleep.force_world_n, full.force_world_n)
        assert np.array_equal(asleep.torque_world_nm, full.torque_world_nm)
        assert not np.any(full.force_world_n) and not np.any(full.torque_world_nm)
        assert asleep.contact_points_world_m.shape == full.contact_points_world_m.shape == (0, 3)
        assert asleep.skin_penetration_m == full.skin_penetration_m == 0.0
        # What an environment observes is the full step's, bit for bit, but for values that
        # are zero but for the full step's round-off (the lesion on the probe's axis: its
        # lateral offset is 1e-17 m, which float32 holds), which agree to that round-off.
        observed, expected = _observed(asleep, pose), _observed(full, pose)
        large = np.abs(expected) > 1e-12
        assert np.array_equal(observed[large], expected[large])
        assert np.abs(observed - expected).max() <= ROUND_OFF_M
        # The sleeping tissue has not moved; a full step moves it by round-off at most, and
        # where it does not move it at all the two agree exactly in double precision too.
        assert np.array_equal(sleeper.positions_m, rest)
        assert not np.any(sleeper.velocities_m_s)
        assert np.abs(twin.positions_m - rest).max() <= ROUND_OFF_M
        assert np.array_equal(asleep.lesion_centroids_world_m, sleeper.lesion_centroids_m())
        if np.array_equal(twin.positions_m, rest):
            assert np.array_equal(asleep.lesion_centroids_world_m, full.lesion_centroids_world_m)
            assert np.array_equal(asleep.landmarks_world_m, full.landmarks_world_m)
        else:
            assert np.allclose(
                asleep.lesion_centroids_world_m, full.lesion_centroids_world_m, rtol=0, atol=1e-15
            )
    assert solves.count == 0


@pytest.mark.parametrize("profile", PROFILES)
@pytest.mark.parametrize("method", METHODS)
def test_the_tissue_wakes_before_the_probe_touches(built, method: str, profile: str) -> None:
    sleeper, twin = _pair(built, method, profile)
    (touching, quat), pressing = _frame(sleeper)
    above = touching - ABOVE_M * pressing
    # Down at 0.5 mm a step to the skin, then 4 mm into it at 0.2 mm a step.
    poses = [(above, quat)] * 3 + [(above + 0.0005 * k * pressing, quat) for k in range(1, 41)]
    poses += [(touching + 0.0002 * k * pressing, quat) for k in range(1, 21)]
    for t in (sleeper, twin):
        t.reset(above, quat)
    asleep_steps = [sleeper.step(*pose) for pose in poses]
    full_steps = [twin.step(*pose) for pose in poses]
    slept = [_asleep(step) for step in asleep_steps]
    touched = [_touched(step) for step in full_steps]
    assert all(slept[:5]) and any(touched)
    wake = slept.index(False)
    # Awake before the first step that touches, and never asleep again on the way in.
    assert wake < touched.index(True)
    assert not any(slept[wake:])
    # The clearance that woke it: within the probe's travel and the method's reach.
    model = sleeper.contact_model
    reach = model.sleep_reach_m()
    assert reach is not None
    assert touched.index(True) - wake <= math.ceil((reach + SLEEP_SAFETY_MARGIN_M) / 0.0005) + 2
    # The sleeping tissue is one at rest: from the pose where it woke, a tissue reset there
    # steps as it does, bit for bit.
    fresh = twin
    fresh.reset(*poses[wake - 1])
    for pose, step in zip(poses[wake:], asleep_steps[wake:], strict=True):
        again = fresh.step(*pose)
        assert np.array_equal(again.force_world_n, step.force_world_n)
        assert np.array_equal(again.torque_world_nm, step.torque_world_nm)
        assert np.array_equal(again.lesion_centroids_world_m, step.lesion_centroids_world_m)
    # And the twin that stepped in free air all along: bit for bit where its free-air steps
    # left it exactly at rest, else apart by what its round-off grows to in a press.
    forces = np.array([step.force_world_n for step in asleep_steps])
    twin_forces = np.array([step.force_world_n for step in full_steps])
    assert np.array_equal(forces != 0.0, twin_forces != 0.0)
    if np.array_equal(forces, twin_forces):
        return
    assert method not in ("penalty", "prescribed") or profile != "robust"
    # The paper profile's CG stops at 25 iterations, far from converged: there the twin's
    # 1e-17 m grows to a few 1e-6 of the force (measured: 3e-6 for prescribed displacement);
    # the robust profile's converged solves keep it at round-off.
    share = 1e-5 if profile == "paper" else 1e-9
    assert np.abs(forces - twin_forces).max() <= share * np.abs(twin_forces).max()
    centroids = np.array([step.lesion_centroids_world_m for step in asleep_steps])
    twin_centroids = np.array([step.lesion_centroids_world_m for step in full_steps])
    assert np.abs(centroids - twin_centroids).max() <= 1e-9


@pytest.mark.parametrize("profile", PROFILES)
@pytest.mark.parametrize("method", METHODS)
def test_after_a_press_it_sleeps_only_once_at_rest_and_stays_within_1_um(
    built, method: str, profile: str
) -> None:
    sleeper, twin = _pair(built, method, profile)
    (touching, quat), pressing = _frame(sleeper)
    above = touching - ABOVE_M * pressing
    presses = [(touching + 0.0002 * k * pressing, quat) for k in range(1, 26)]  # 5 mm
    for t in (sleeper, twin):
        t.reset(touching, quat)
    for pose in presses:
        pressed, reference = sleeper.step(*pose), twin.step(*pose)
        assert not _asleep(pressed)  # in contact all along: the same steps, bit for bit
        assert np.array_equal(pressed.force_world_n, reference.force_world_n)
    assert np.linalg.norm(pressed.force_world_n) > 0.1
    # Lifted 20 mm clear at once, then held there.
    speeds, slept, pairs = [], [], []
    for _ in range(400):
        asleep, full = sleeper.step(above, quat), twin.step(above, quat)
        speeds.append(_speed(sleeper))
        slept.append(_asleep(asleep))
        pairs.append((asleep, full))
        if sum(slept) >= 10:
            break
    if method == "prescribed" and profile == "paper":
        # The paper's prescribed displacement holds the node set it took at first contact
        # for good: in contact still, it never sleeps.
        assert not any(slept)
        assert all(np.linalg.norm(full.force_world_n) > 0 for _, full in pairs)
        for asleep, full in pairs:
            assert np.array_equal(asleep.force_world_n, full.force_world_n)
        return
    first = slept.index(True)
    # Asleep only once the nodes are slower than the threshold, and as soon as they are.
    assert first >= 2 and speeds[first - 1] < SPEED <= speeds[first - 2]
    assert all(speeds[k - 1] < SPEED for k, asleep in enumerate(slept) if asleep)
    for k, (asleep, full) in enumerate(pairs):
        assert asleep.time_s == full.time_s
        if k < first:
            assert np.array_equal(asleep.lesion_centroids_world_m, full.lesion_centroids_world_m)
        assert not np.any(full.force_world_n) and not np.any(asleep.force_world_n)
        offset = np.abs(asleep.lesion_centroids_world_m - full.lesion_centroids_world_m).max()
        assert offset <= 1e-6
        landmarks = np.abs(asleep.landmarks_world_m - full.landmarks_world_m)
        assert landmarks.max(initial=0.0) <= 1e-6


@pytest.mark.parametrize("method", METHODS)
def test_sleeping_advances_the_time_as_a_step_would(built, spy, method: str) -> None:
    sleeper, twin = _pair(built, method, "robust")
    (touching, quat), pressing = _frame(sleeper)
    above = touching - ABOVE_M * pressing
    far = above - 0.1 * pressing  # 100 mm farther in one step: a split motion
    for t in (sleeper, twin):
        t.reset(above, quat)
    solves = spy(sleeper)
    # (Back towards the skin in one 100 mm step it would wake: the travel alone could bring
    # the probe anywhere within 100 mm of where it ends, so the sweep is not known clear.)
    splits = []
    for k, pose in enumerate([(above, quat), (far, quat), (far, quat)], start=1):
        asleep, full = sleeper.step(*pose), twin.step(*pose)
        assert _asleep(asleep)
        # The same bits: a split motion's sub-motions each add their share of dt.
        assert asleep.time_s == full.time_s == sleeper.time_s
        assert asleep.time_s == pytest.approx(k * sleeper.dt, abs=1e-15)
        splits.append(full.diagnostics.sub_motions)
    assert splits[1] > 1
    assert solves.count == 0


@pytest.mark.parametrize("method", METHODS)
def test_a_sleeping_tissue_snapshots_copies_and_pickles_bit_for_bit(built, method: str) -> None:
    sleeper = _tissue(built, method, "robust", True)
    (touching, quat), pressing = _frame(sleeper)
    above = touching - ABOVE_M * pressing
    sleeper.reset(above, quat)
    assert _asleep(sleeper.step(above, quat))
    state = sleeper.state()
    restored = pickle.loads(pickle.dumps(sleeper))
    assert restored.spec.sleep_speed_m_s == SPEED
    poses = [(above + 0.001 * k * pressing, quat) for k in range(1, 25)]
    first = [sleeper.step(*pose) for pose in poses]
    assert _asleep(first[0]) and not _asleep(first[-1]) and np.any(first[-1].force_world_n)
    sleeper.set_state(state)
    for steps in (
        [sleeper.step(*pose) for pose in poses],
        [restored.step(*pose) for pose in poses],
    ):
        for a, b in zip(first, steps, strict=True):
            assert _asleep(a) == _asleep(b)
            assert np.array_equal(a.force_world_n, b.force_world_n)
            assert np.array_equal(a.lesion_centroids_world_m, b.lesion_centroids_world_m)


def test_sleep_is_off_by_default_and_does_not_change_the_body() -> None:
    assert tissue.SLEEP_SPEED_M_S == 1e-6
    assert tissue.TissueSpec().sleep_speed_m_s is None
    spec = tissue.TissueSpec(mesh=LEVEL, sleep_speed_m_s=1e-5)
    assert spec.sleep_speed_m_s == 1e-5
    plain = tissue.make_tissue(mesh=LEVEL)
    sleepy = tissue.make_tissue(spec)
    assert plain.contact_model.sleep_speed_m_s is None
    assert sleepy.contact_model.sleep_speed_m_s == 1e-5
    # One body: a state moves between them, and a variant keeps the setting.
    sleepy.set_state(plain.state())
    variant = sleepy.varied(lesion_offsets_m=np.zeros((len(sleepy.lesions), 3)))
    assert variant.contact_model.sleep_speed_m_s == 1e-5


@pytest.mark.parametrize("value", [0, 0.0, -1, -1e-6, math.nan, math.inf, "x", "1e-6", True])
def test_a_bad_sleep_speed_is_refused_by_name(value: object) -> None:
    with pytest.raises(tissue.TissueInputError, match=r"sleep_speed_m_s .*got") as error:
        tissue.TissueSpec(mesh=LEVEL, sleep_speed_m_s=value)  # type: ignore[arg-type]
    assert repr(value) in str(error.value)
    model = tissue.make_tissue(mesh=LEVEL, contact="penalty").contact_model
    with pytest.raises(tissue.TissueInputError, match="sleep_speed_m_s"):
        model.sleep_speed_m_s = value  # type: ignore[assignment]
    assert model.sleep_speed_m_s is None


@pytest.mark.parametrize("method", METHODS)
def test_the_compiled_sleep_check_leaves_what_the_full_check_would(
    built, monkeypatch: pytest.MonkeyPatch, method: str
) -> None:
    """A sleeping step the compiled checks settle (``ContactModel.sleep_if_clear``) against
    one of a copy whose every step takes the full checks: the same decisions, poses, clock
    and results, bit for bit, from free air (held, swept in split motions, turned) down
    into contact and back."""
    fast = _tissue(built, method, "robust", True)
    (touching, quat), pressing = _frame(fast)
    above = touching - ABOVE_M * pressing
    fast.reset(above, quat)
    full = pickle.loads(pickle.dumps(fast))
    monkeypatch.setattr(full.contact_model, "sleep_if_clear", lambda *pose: False)
    taken = []
    sleep_if_clear = fast.contact_model.sleep_if_clear

    def counted(*pose):
        taken.append(sleep_if_clear(*pose))
        return taken[-1]

    monkeypatch.setattr(fast.contact_model, "sleep_if_clear", counted)
    rotation = quat_to_matrix(quat)
    lateral = rotation[:, 0]
    turn = 0.05
    turned = rotation @ np.array(
        [[math.cos(turn), -math.sin(turn), 0.0], [math.sin(turn), math.cos(turn), 0.0], [0, 0, 1]]
    )
    poses = [(above, quat)] * 2
    # 2 mm steps, then 12 mm ones (split: longer than max_sub_motion_m), a turn in place
    # and back.
    poses += [(above + 0.002 * k * lateral, quat) for k in range(1, 4)]
    poses += [(above + 0.012 * k * lateral, quat) for k in range(1, 4)]
    poses += [(above + 0.036 * lateral, matrix_to_quat(turned)), (above, quat)]
    poses += [(above + 0.001 * k * pressing, quat) for k in range(1, 25)]  # into contact
    poses += [(above + 0.001 * k * pressing, quat) for k in range(24, -1, -4)]
    for pose in poses:
        a, b = fast.step(*pose), full.step(*pose)
        assert _asleep(a) == _asleep(b)
        assert a.status is b.status and a.time_s == b.time_s
        for name in (
            "force_world_n",
            "torque_world_nm",
            "contact_points_world_m",
            "contact_forces_world_n",
            "landmarks_world_m",
            "lesion_centroids_world_m",
        ):
            assert np.array_equal(getattr(a, name), getattr(b, name)), name
        assert a.skin_penetration_m == b.skin_penetration_m
        assert a.diagnostics.sub_motions == b.diagnostics.sub_motions
        ours, theirs = fast.contact_model, full.contact_model
        assert np.array_equal(ours.probe.position_world, theirs.probe.position_world)
        assert np.array_equal(ours.probe.quat_wxyz, theirs.probe.quat_wxyz)
        assert np.array_equal(ours.probe.rotation_world(), theirs.probe.rotation_world())
        assert ours._last_pose is not None and theirs._last_pose is not None
        assert all(map(np.array_equal, ours._last_pose, theirs._last_pose))
        assert np.array_equal(fast.positions_m, full.positions_m)
    assert fast.contact_model.max_sub_motion_m < 0.012
    assert sum(taken) >= 10  # the free-air steps, split ones among them
    assert not all(taken)  # near and in contact: the full path


def test_the_compiled_box_test_answers_as_the_probes_own() -> None:
    """Blocked points in a widened probe box (``sleep_kernel._any_in_box``): the answer of
    the probe's own point-by-point test (``tissue.probe.pose._any_in_box``), near the box's
    faces included."""
    from tissue.contact.sleep_kernel import _any_in_box, blocked_points
    from tissue.probe.pose import _any_in_box as probe_any_in_box

    probe = Probe(LinearProbeFace())
    bounds = probe.shape.local_bounds_m()
    rng = np.random.default_rng(7)
    answers = set()
    for _ in range(400):
        position = rng.uniform(-0.05, 0.05, 3)
        probe.set_pose(position, rng.normal(size=4))
        rotation = probe.rotation_world()
        margin = float(rng.uniform(0.0, 0.005))
        count = int(rng.integers(1, 200))
        local = rng.uniform(-0.12, 0.12, (count, 3))
        # A few points on the widened box's faces, within round-off.
        face = rng.integers(0, count, 3)
        axis = rng.integers(0, 3, 3)
        side = rng.integers(0, 2, 3)
        local[face, axis] = np.where(side, bounds[1, axis] + margin, bounds[0, axis] - margin)
        points = np.ascontiguousarray(local @ rotation.T + position)
        blocks = blocked_points(points)
        expected = probe_any_in_box(points, position, rotation, bounds, margin)
        answers.add(bool(expected))
        assert _any_in_box(*blocks, position, rotation, bounds, margin) == expected
    assert answers == {True, False}


@pytest.mark.parametrize(
    "position, quat",
    [
        ([math.nan, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]),
        ([0.0, 0.0, math.inf], [1.0, 0.0, 0.0, 0.0]),
        ([0.0, 0.0], [1.0, 0.0, 0.0, 0.0]),
        ([0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]),
        ([0.0, 0.0, 0.0], [math.nan, 0.0, 0.0, 1.0]),
        ([0.0, 0.0, 0.0], [1.0, 0.0, 0.0]),
    ],
)
def test_a_sleeping_tissue_refuses_a_bad_pose(built, position, quat) -> None:
    sleeper = _tissue(built, "penalty", "robust", True)
    (touching, good), pressing = _frame(sleeper)
    sleeper.reset(touching - ABOVE_M * pressing, good)
    assert _asleep(sleeper.step(touching - ABOVE_M * pressing, good))
    time_s = sleeper.time_s
    with pytest.raises(tissue.TissueInputError):
        sleeper.step(position, quat)
    assert sleeper.time_s == time_s


def test_the_sleeping_steps_results_are_built_as_their_classes_build_them() -> None:
    """A sleeping step builds its :class:`tissue.TissueStep` and its diagnostics without
    their dataclass ``__init__`` (``tissue.step_result.frozen``): only right for classes that do
    nothing else when built."""
    import dataclasses

    from tissue.step_result import asleep_diagnostics

    for cls in (tissue.TissueStep, tissue.StepDiagnostics):
        assert dataclasses.is_dataclass(cls) and cls.__dict__["__dataclass_params__"].frozen
        assert not hasattr(cls, "__post_init__") and not hasattr(cls, "__slots__")
    built = asleep_diagnostics(1.5)
    assert built == tissue.StepDiagnostics(
        iterations=0,
        linear_iterations=0,
        contact_count=0,
        sub_motions=1,
        subdivisions=0,
        min_volume_ratio=None,
        compute_ms=1.5,
        details={"asleep": 1.0},
    )
    with pytest.raises(dataclasses.FrozenInstanceError):
        built.compute_ms = 2.0  # type: ignore[misc]
