"""The tissue's front door (``import tissue``): every method and profile driven the way an
environment drives it -- presses, slides, rocks, snapshots, pickles, teleports, threads and
processes."""

from __future__ import annotations

import copy
import multiprocessing
import pickle
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

import tissue
from tissue.probe import Probe, matrix_to_quat, quat_to_matrix
from tissue.probe.surface_depth import facet_allowance_m

ROOT = Path(__file__).resolve().parents[2]
METHODS = ("lm", "penalty", "prescribed", "pbd")
PROFILES = ("paper", "robust")
STEP_M = 0.0002  # 0.01 m/s at 0.02 s
DEPTH_M = 0.008


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def _sampled_skin_depth(probe: Probe, skin: tissue.SurfaceMesh) -> tuple[float, float]:
    """The deepest of a fine grid of points on the skin's triangles inside the probe [m],
    and how much deeper a point between them can lie (a grid cell's circumradius) [m]."""
    order = 24
    grid = np.array(
        [(i / order, j / order, 1 - (i + j) / order) for i in range(order + 1)
         for j in range(order + 1 - i)]
    )  # fmt: skip
    corners = skin.vertices_m[skin.triangles[skin.triangle_region == 0]]
    near = probe.near(corners.reshape(-1, 3), 0.02).reshape(-1, 3).any(axis=1)
    samples = np.einsum("sk,tkd->tsd", grid, corners[near]).reshape(-1, 3)
    distance, _ = probe.signed_distance_world(samples)
    longest = float(np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2).max())
    return max(0.0, -float(distance.min())), longest / order / np.sqrt(3.0)


def _scenario(t: tissue.Tissue) -> dict[str, object]:
    """Press 8 mm above lesion 1, hold 1 s; slide 10 mm along the image's lateral axis,
    hold 1 s; rock 20 degrees about the elevation axis, hold 1 s. Records every step."""
    position, quat = t.touching_pose(t.lesions[0].rest_centre_m)
    rotation = quat_to_matrix(quat)
    lateral, pressing, elevation = rotation[:, 0], rotation[:, 1], rotation[:, 2]
    t.reset(position, quat)
    steps: list[tissue.TissueStep] = []
    ends: dict[str, float] = {}
    poses = [(position + STEP_M * k * pressing, quat) for k in range(1, 41)]
    poses += [poses[-1]] * 50
    ends["press"] = len(poses)
    pressed = poses[-1][0]
    poses += [(pressed + STEP_M * k * lateral, quat) for k in range(1, 51)]
    poses += [poses[-1]] * 50
    ends["slide"] = len(poses)
    slid = poses[-1][0]
    for k in range(1, 51):
        turned = _rotation(elevation, np.radians(20.0) * k / 50) @ rotation
        poses.append((slid, matrix_to_quat(turned)))
    poses += [poses[-1]] * 50
    ends["rock"] = len(poses)
    for pose in poses:
        steps.append(t.step(*pose))
    forces = {
        name: float(np.linalg.norm(steps[end - 1].force_world_n)) for name, end in ends.items()
    }
    return {"steps": steps, "forces": forces, "poses": poses}


@pytest.fixture(scope="module")
def runs() -> dict[tuple[int, str, str], dict[str, object]]:
    return {}


def _run(runs, level: int, method: str, profile: str) -> dict[str, object]:
    key = (level, method, profile)
    if key not in runs:
        t = tissue.make_tissue(mesh=level, contact=method, profile=profile)
        runs[key] = {"tissue": t, **_scenario(t)}
    return runs[key]


def _check_scenario(runs, level: int, method: str, profile: str) -> None:
    run = _run(runs, level, method, profile)
    t = run["tissue"]
    steps = run["steps"]
    statuses = {step.status for step in steps}
    if profile == "robust" or method == "lm":
        assert statuses == {tissue.StepStatus.OK}, statuses
    # The paper's configurations may fail (the paper's PBD inverts surface tets under the
    # rocked edge at 623 tets): reported as a status, with finite numbers all the same.
    assert all(np.all(np.isfinite(step.force_world_n)) for step in steps)
    assert np.all(np.isfinite(t.positions_m))
    penetration = np.array([step.skin_penetration_m for step in steps])
    assert np.all(np.isfinite(penetration)) and penetration.min() >= 0.0
    # The reported penetration is the skin's surface, measured independently here at the
    # end: its triangles sampled on a fine grid. The grid finds no more than the report, and
    # the report no more than the grid plus its cell's reach (the distance is 1-Lipschitz).
    skin = t.surface()
    held = Probe(t.probe_shape)
    held.set_pose(*run["poses"][-1])
    sampled, cell = _sampled_skin_depth(held, skin)
    reported = steps[-1].skin_penetration_m
    assert sampled - 1e-9 <= reported <= sampled + cell
    # What the method holds: the skin's vertices (its bound) ...
    vertices = np.array([step.diagnostics.details["skin_vertex_penetration_m"] for step in steps])
    if method == "lm" or (method == "prescribed" and profile == "robust"):
        assert vertices.max() <= 0.5e-3
    elif method == "penalty":
        # Penalty's documented bound: robust augments to its tolerance (0.1 mm); paper
        # springs sink by their force over k_s.
        model = t.contact_model
        if profile == "robust":
            bound = model.params.penetration_tolerance_m + 1e-6
        else:
            largest = max(
                float(np.linalg.norm(step.contact_forces_world_n, axis=1).max(initial=0.0))
                for step in steps
            )
            bound = largest / model.stiffness_n_per_m + 1e-6
        assert vertices.max() <= bound
    elif method == "pbd" and profile == "robust":
        assert vertices.max() <= 1e-3
    # ... and between them the facets, no deeper than a facet of the skin's size can reach
    # with its vertices where they are.
    on_skin = skin.triangles[skin.triangle_region == 0]
    corners = skin.vertices_m[on_skin]
    longest = float(np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2).max())
    allowance = facet_allowance_m(longest, t.probe_shape.edge_radius_m)
    assert np.all(penetration <= vertices + allowance + 1e-9)
    if profile == "robust" and method != "lm":
        # Within 20 % of LM's force (PBD, calibrated for the mesh on another press: 15 %).
        share = 0.15 if method == "pbd" else 0.2
        reference = _run(runs, level, "lm", "robust")["forces"]
        for name, force in run["forces"].items():
            assert abs(force - reference[name]) <= share * reference[name] + 1e-3, (name, force)


@pytest.mark.parametrize("profile", PROFILES)
@pytest.mark.parametrize("method", METHODS)
def test_press_slide_rock_at_623_tets(runs, method: str, profile: str) -> None:
    _check_scenario(runs, 623, method, profile)


@pytest.mark.slow
@pytest.mark.parametrize("profile", PROFILES)
@pytest.mark.parametrize("method", METHODS)
def test_press_slide_rock_at_1363_tets(runs, method: str, profile: str) -> None:
    _check_scenario(runs, 1363, method, profile)


def _pressed(method: str, profile: str, level: int = 623) -> tuple[tissue.Tissue, list]:
    """A tissue pressed 4 mm above lesion 1, and the poses of a slide that follows."""
    t = tissue.make_tissue(mesh=level, contact=method, profile=profile)
    position, quat = t.touching_pose(t.lesions[0].rest_centre_m)
    rotation = quat_to_matrix(quat)
    t.reset(position, quat)
    for k in range(1, 21):
        t.step(position + STEP_M * k * rotation[:, 1], quat)
    pressed = position + 20 * STEP_M * rotation[:, 1]
    return t, [(pressed + STEP_M * k * rotation[:, 0], quat) for k in range(1, 11)]


def _same_steps(a: list[tissue.TissueStep], b: list[tissue.TissueStep]) -> None:
    for first, second in zip(a, b, strict=True):
        assert first.status is second.status
        assert np.array_equal(first.force_world_n, second.force_world_n)
        assert np.array_equal(first.torque_world_nm, second.torque_world_nm)
        assert np.array_equal(first.lesion_centroids_world_m, second.lesion_centroids_world_m)


@pytest.mark.parametrize("profile", PROFILES)
@pytest.mark.parametrize("method", METHODS)
def test_snapshots_copies_and_pickles_continue_bit_for_bit(method: str, profile: str) -> None:
    t, poses = _pressed(method, profile)
    state = t.state()
    restored = pickle.loads(pickle.dumps(t))
    copied = copy.deepcopy(t)
    first = [t.step(*pose) for pose in poses]
    assert any(np.linalg.norm(step.force_world_n) > 0 for step in first)
    t.set_state(state)
    again = [t.step(*pose) for pose in poses]
    _same_steps(first, again)
    _same_steps(first, [restored.step(*pose) for pose in poses])
    _same_steps(first, [copied.step(*pose) for pose in poses])
    # A state belongs to its tissue: another spec's is refused.
    other = tissue.make_tissue(mesh=623, contact="lm" if method != "lm" else "penalty")
    with pytest.raises(tissue.TissueInputError, match="another tissue"):
        other.set_state(state)


def test_a_state_restores_only_into_the_same_materials() -> None:
    state = tissue.make_tissue(mesh=623).state()
    tissue.make_tissue(mesh=623).set_state(state)
    stiffer = tissue.make_tissue(mesh=623, young_pa=5000.0)
    with pytest.raises(tissue.TissueInputError, match="another tissue"):
        stiffer.set_state(state)


@pytest.mark.parametrize("profile", PROFILES)
@pytest.mark.parametrize("method", METHODS)
def test_a_30_mm_teleport_never_ends_ok_with_the_skin_behind_the_probe(
    method: str, profile: str
) -> None:
    t = tissue.make_tissue(mesh=623, contact=method, profile=profile)
    position, quat = t.touching_pose(t.lesions[0].rest_centre_m)
    pressing = tissue.pressing_direction(quat)
    depth = 0.03
    t.reset(position, quat)
    jumped = t.step(position + depth * pressing, quat)
    assert jumped.diagnostics.sub_motions >= 5  # 30 mm in pieces under half of 13.2 mm
    for _ in range(50):  # settle at that depth
        jumped = t.step(position + depth * pressing, quat)
    slow = tissue.make_tissue(mesh=623, contact=method, profile=profile)
    slow.reset(position, quat)
    for k in range(1, 151):
        pressed = slow.step(position + STEP_M * k * pressing, quat)
    for _ in range(50):
        pressed = slow.step(position + depth * pressing, quat)
    if jumped.status is tissue.StepStatus.OK:
        # Not behind the probe: pressing back, the skin held out as in a slow press.
        assert float(-jumped.force_world_n @ pressing) >= 0.8 * float(
            -pressed.force_world_n @ pressing
        )
        if method == "prescribed" and profile == "paper":
            # The paper's node set, fixed at first contact, does not hold the skin between
            # its nodes: the penetration is reported, and stays short of the mid-plane.
            assert jumped.skin_penetration_m < t.contact_model.max_sub_motion_m
        else:
            # The skin's vertices held out as in the slow press (its facets, at the paper's
            # 10-18 mm, cut the probe's rim between them in both).
            held = jumped.diagnostics.details["skin_vertex_penetration_m"]
            slowly = pressed.diagnostics.details["skin_vertex_penetration_m"]
            assert held <= max(slowly, 0.5e-3) + 1e-4


def test_the_probe_frame_is_documented_and_used():
    """+y presses: a probe moved along +y from the touching pose pushes the skin, and the
    tissue pushes back along -y."""
    t = tissue.make_tissue(mesh=623, contact="lm")
    position, quat = t.touching_pose(t.lesions[0].rest_centre_m)
    pressing = tissue.pressing_direction(quat)
    assert np.allclose(pressing, quat_to_matrix(quat)[:, 1])
    t.reset(position, quat)
    for k in range(1, 11):
        step = t.step(position + STEP_M * k * pressing, quat)
    assert float(step.force_world_n @ pressing) < 0.0


def test_lesions_surfaces_and_centroids() -> None:
    t = tissue.make_tissue(mesh=623, contact="penalty")
    assert len(t.lesions) == 10 and all(lesion.tets.size for lesion in t.lesions)
    np.testing.assert_allclose(
        t.lesion_centroids_m(), [lesion.rest_centre_m for lesion in t.lesions], atol=1e-12
    )
    surface = t.surface()
    assert set(np.unique(surface.triangle_region)) == set(range(11))
    assert surface.triangles.max() < surface.vertices_m.shape[0]
    # Pressing lesion 1 moves its centroid along the press, more than a far lesion's.
    position, quat = t.touching_pose(t.lesions[0].rest_centre_m)
    pressing = tissue.pressing_direction(quat)
    t.reset(position, quat)
    for k in range(1, 41):
        step = t.step(position + STEP_M * k * pressing, quat)
    shift = step.lesion_centroids_world_m - np.array([lesion.rest_centre_m for lesion in t.lesions])
    assert float(shift[0] @ pressing) > 1e-3
    assert np.linalg.norm(shift[0]) > np.linalg.norm(shift[1:], axis=1).max()


def test_published_scene_lesions_are_points(paper_scene_dir) -> None:
    t = tissue.make_tissue(mesh=str(paper_scene_dir), contact="lm", profile="paper")
    assert [lesion.name for lesion in t.lesions] == ["tumor1", "tumor2"]
    assert all(lesion.radius_m == 0.0 and lesion.tets.size == 0 for lesion in t.lesions)
    np.testing.assert_allclose(t.lesion_centroids_m()[0], t.lesions[0].rest_centre_m, atol=1e-12)


@pytest.mark.parametrize("method", ["lm", "penalty", "prescribed"])
def test_wrench_stiffness_matches_finite_differences(method: str) -> None:
    """K predicts how the settled force changes when the probe is pressed a little further
    from a settled press (the static stiffness: a small difference of two settled states)."""
    t, _ = _pressed(method, "robust")
    position, quat = t.contact_model.probe.position_world.copy(), t.contact_model.probe.quat_wxyz
    for _ in range(100):
        settled = t.step(position, quat)
    stiffness = t.wrench_stiffness()
    assert stiffness is not None and stiffness.shape == (6, 6)
    np.testing.assert_allclose(stiffness, stiffness.T, atol=1e-9 * np.abs(stiffness).max())
    assert np.linalg.eigvalsh(stiffness[:3, :3]).min() > -1e-6 * np.abs(stiffness).max()
    pressing = tissue.pressing_direction(quat)
    delta = 2e-4
    for _ in range(150):
        moved = t.step(position + delta * pressing, quat)
    measured = -(moved.force_world_n - settled.force_world_n) / delta
    predicted = stiffness[:3, :3] @ pressing
    assert float(measured @ pressing) > 0.0
    np.testing.assert_allclose(measured @ pressing, predicted @ pressing, rtol=0.15)


def test_pbd_has_no_wrench_stiffness() -> None:
    assert tissue.make_tissue(mesh=623, contact="pbd", profile="paper").wrench_stiffness() is None


@pytest.mark.parametrize(
    "settings, message",
    [
        ({"contact": "springs"}, "unknown contact method 'springs'"),
        ({"profile": "fast"}, "unknown profile 'fast'"),
        ({"tissue_dt": 0.0}, "tissue_dt must be a time step"),
        ({"mesh": 999}, "level"),
        ({"young_pa": -5.0}, "Young"),
        ({"materials": tissue.TissueMaterials(), "poisson": 0.3}, "not both"),
        ({"fixed_plane": "z=min"}, "apply to a mesh file only"),
        ({"scene_lesion": 1}, "published scene only"),
        ({"contact": "lm", "contact_params": 3}, "LagrangeParams"),
        ({"probe": "needle"}, "needle"),
        ({"velocity": 3}, "unknown tissue setting"),
    ],
)
def test_bad_specs_are_named(settings: dict, message: str) -> None:
    with pytest.raises(tissue.TissueInputError, match=message):
        tissue.make_tissue(**settings)


def test_bad_poses_are_named() -> None:
    t = tissue.make_tissue(mesh=623, contact="lm")
    with pytest.raises(tissue.TissueInputError, match="position"):
        t.step([0.0, np.nan, 0.1], [1.0, 0.0, 0.0, 0.0])
    with pytest.raises(tissue.TissueInputError, match="quaternion"):
        t.step([0.0, 0.0, 0.1], [0.0, 0.0, 0.0, 0.0])


def test_importing_tissue_sets_no_environment_variables() -> None:
    code = (
        "import os; before = dict(os.environ); import tissue, tissue.model, tissue.spec;"
        "t = tissue.make_tissue(mesh=623, contact='lm');"
        "print(sorted(set(os.environ.items()) ^ set(before.items())))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


_PRESS_SCRIPT = """
import sys, numpy as np, tissue
t = tissue.make_tissue(mesh=623, contact=sys.argv[1], profile="robust")
position, quat = t.touching_pose(t.lesions[0].rest_centre_m)
t.reset(position, quat)
d = tissue.pressing_direction(quat)
out = [t.step(position + 0.0002 * k * d, quat).force_world_n for k in range(1, 31)]
print(np.array(out).tobytes().hex())
"""


@pytest.mark.parametrize("method", ["lm", "penalty", "prescribed"])
def test_one_thread_and_two_give_the_same_bits(method: str) -> None:
    outputs = []
    for threads in ("1", "2"):
        env = {**__import__("os").environ, "NUMBA_NUM_THREADS": threads}
        out = subprocess.run(
            [sys.executable, "-c", _PRESS_SCRIPT, method],
            capture_output=True,
            text=True,
            check=True,
            env=env,
            cwd=ROOT,
        )
        outputs.append(out.stdout.strip())
    assert outputs[0] == outputs[1]


def _child_step(connection, t: tissue.Tissue, pose) -> None:
    step = t.step(*pose)
    connection.send_bytes(step.force_world_n.tobytes())
    connection.close()


@pytest.mark.parametrize("context", ["fork", "forkserver", "spawn"])
def test_a_tissue_steps_in_a_child_process(context: str) -> None:
    """Built (and stepped) here, then stepped in a child: fork included (GNU OpenMP made a
    forked child abort; the TBB layer does not)."""
    t, poses = _pressed("lm", "robust", level=1363)
    state = t.state()
    expected = t.step(*poses[0]).force_world_n
    t.set_state(state)
    ctx = multiprocessing.get_context(context)
    receiver, sender = ctx.Pipe(duplex=False)
    process = ctx.Process(target=_child_step, args=(sender, t, poses[0]))
    process.start()
    process.join(timeout=120)
    assert process.exitcode == 0
    assert np.frombuffer(receiver.recv_bytes(), dtype=np.float64).tolist() == expected.tolist()


def test_two_threads_step_two_tissues_at_once() -> None:
    tissues = [_pressed(method, "robust", level=1363) for method in ("lm", "penalty")]
    states = [t.state() for t, _ in tissues]
    alone = [[t.step(*pose).force_world_n for pose in poses] for t, poses in tissues]
    for (t, _), state in zip(tissues, states, strict=True):
        t.set_state(state)
    together: list[list[np.ndarray]] = [[], []]

    def drive(index: int) -> None:
        t, poses = tissues[index]
        together[index] = [t.step(*pose).force_world_n for pose in poses]

    threads = [threading.Thread(target=drive, args=(i,)) for i in range(2)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    for first, second in zip(alone, together, strict=True):
        np.testing.assert_array_equal(np.array(first), np.array(second))
