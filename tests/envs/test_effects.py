"""Declared effects (issue: a scene simulates only the effects it calls for): the scene's
validation against the tasks' terms, and stages that never run when nothing needs them."""

from __future__ import annotations

import re

import gymnasium as gym
import numpy as np
import pytest

import envs  # noqa: F401 - registers the environments
from envs import probe_env
from envs.coupling import TissueCoupling
from envs.effects import EFFECTS, SCENES, needed_effects
from envs.errors import EnvConfigError
from envs.tasks.breast_compress import BreastCompressEnv
from envs.tasks.force_scan import ForceScanEnv
from envs.tasks.lesion_search import LesionSearchEnv
from envs.ultrasound import BModeImager

TASKS = {
    "probegym/BreastCompress-v0": BreastCompressEnv,
    "probegym/LesionSearch-v0": LesionSearchEnv,
    "probegym/ForceScan-v0": ForceScanEnv,
}
PRESS = np.array([0.0, 0.4, 0.0, 0.0, 0.0, 0.0], dtype=np.float32)
LIFT = np.array([0.0, -1.0, 0.0, 0.0, 0.0, 0.0], dtype=np.float32)


def test_an_unknown_effect_lists_the_valid_ones() -> None:
    with pytest.raises(EnvConfigError) as error:
        gym.make("probegym/ForceScan-v0", mesh=623, effects=["deformation", "wobble"])
    message = str(error.value)
    assert "wobble" in message and all(name in message for name in EFFECTS)
    with pytest.raises(EnvConfigError, match="list of effect names"):
        gym.make("probegym/ForceScan-v0", mesh=623, effects="deformation")
    with pytest.raises(EnvConfigError, match="unknown scene 'soft'"):
        gym.make("probegym/ForceScan-v0", mesh=623, scene="soft")
    with pytest.raises(EnvConfigError, match="not both"):
        gym.make("probegym/ForceScan-v0", mesh=623, scene="full", effects=["deformation"])


def test_a_term_whose_effect_the_scene_lacks_is_refused_by_name() -> None:
    with pytest.raises(EnvConfigError) as error:
        gym.make("probegym/BreastCompress-v0", mesh=623, scene="rigid")
    message = str(error.value)
    assert "BreastCompressEnv" in message and "'deformation'" in message
    assert "scene 'rigid'" in message and re.search(r"term '\w+'", message)
    # Without force feedback the F/T observation means nothing: the first term needing it.
    with pytest.raises(EnvConfigError, match="term 'wrench' needs the effect 'force_feedback'"):
        gym.make("probegym/LesionSearch-v0", mesh=623, scene="one_way")


@pytest.mark.parametrize(
    ("kwargs", "pattern"),
    [
        ({"effects": ["deformation", "force_feedback", "gravity"]}, "does not simulate"),
        ({"effects": ["deformation", "force_feedback", "stress"]}, "does not simulate"),
        ({"effects": ["force_feedback", "image"]}, "without 'deformation'"),
        ({"effects": ["force_feedback", "damping"], "profile": "paper"}, "without 'deformation'"),
    ],
)
def test_effects_the_tissue_cannot_simulate_are_refused(kwargs: dict, pattern: str) -> None:
    with pytest.raises(EnvConfigError, match=pattern):
        gym.make("probegym/ForceScan-v0", mesh=623, **kwargs)


def test_the_scene_fills_in_the_tissues_own_effects() -> None:
    robust = gym.make("probegym/ForceScan-v0", mesh=623).unwrapped.scene
    assert robust.name == "full" and {"damping", "sliding"} <= robust.effects
    # The paper profile integrates inertia and damping too (tests/tissue/test_profile_dynamics.py).
    paper = gym.make("probegym/ForceScan-v0", mesh=623, profile="paper").unwrapped.scene
    assert {"damping", "sliding"} <= paper.effects
    asked = gym.make(
        "probegym/ForceScan-v0", mesh=623, profile="paper",
        effects=["deformation", "force_feedback", "damping"],
    )  # fmt: skip
    assert asked.unwrapped.scene.has("damping")
    imaging = gym.make("probegym/ForceScan-v0", mesh=623, image=True).unwrapped.scene
    assert imaging.has("image")


@pytest.mark.parametrize("env_id", sorted(TASKS))
def test_each_task_documents_the_effects_its_terms_need(env_id: str) -> None:
    """The docstring (the env's spec) names exactly the effects its terms need, and the
    scenes it runs on are those that have them."""
    task = TASKS[env_id]
    doc = task.__doc__ or ""
    section = doc.split("## Effects", 1)[1].split("##", 1)[0]
    needs = needed_effects({k: v for k, v in task.TERM_EFFECTS.items() if k != "image"})
    listed = set(re.findall(r"``(\w+)``", section.split("Scenes", 1)[0]))
    assert listed == set(needs), (listed, needs)
    runs_on = {name for name, scene in SCENES.items() if needs <= scene.effects}
    named = set(re.findall(r"``(\w+)``", section.split("Scenes", 1)[1]))
    assert named == runs_on


class _Counter:
    """Counts calls of a method replaced on an instance or class."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch, owner: object, name: str) -> None:
        self.calls = 0
        original = getattr(owner, name)

        def counted(*args, **kwargs):  # type: ignore[no-untyped-def]
            self.calls += 1
            return original(*args, **kwargs)

        monkeypatch.setattr(owner, name, counted)


def test_the_rigid_breast_never_steps_the_tissue(monkeypatch: pytest.MonkeyPatch) -> None:
    """The rigid scene: no tissue step at all; MuJoCo's contact is the reaction, read by
    the F/T sensor as the step's force; the lesion stays at rest."""
    env = gym.make("probegym/LesionSearch-v0", mesh=623, scene="rigid", hard_force_n=50.0)
    unwrapped = env.unwrapped
    steps = _Counter(monkeypatch, unwrapped.tissue, "step")
    env.reset(seed=3)
    rest = unwrapped.tissue.lesion_centroids_m().copy()
    for _ in range(8):  # the target 4 mm into the rigid skin: about 3000 N/m x 4 mm
        env.step(PRESS * 0.25)
    for _ in range(20):  # held still: the sensor settles on the contact force
        observation, _, terminated, truncated, info = env.step(np.zeros(6, dtype=np.float32))
        assert not (terminated or truncated)
    assert steps.calls == 0
    assert 8.0 < info["normal_force_n"] < 16.0
    assert -observation["wrench"][1] == pytest.approx(info["normal_force_n"], rel=0.05)
    assert np.array_equal(unwrapped.tissue.lesion_centroids_m(), rest)


def test_without_force_feedback_no_reaction_is_computed(monkeypatch: pytest.MonkeyPatch) -> None:
    """One-way coupling: the tissue steps, but its wrench stiffness is never computed and
    nothing is applied to the probe."""
    env = gym.make("probegym/BreastCompress-v0", mesh=623)
    unwrapped = env.unwrapped
    coupling = TissueCoupling(
        unwrapped.model, unwrapped.data, unwrapped.names, unwrapped.tissue, reaction=False
    )
    unwrapped.coupling = coupling
    stiffness = _Counter(monkeypatch, unwrapped.tissue, "wrench_stiffness")
    env.reset(seed=0)
    forces = []
    for _ in range(30):
        _, _, terminated, _, info = env.step(PRESS)
        forces.append(info["contact_force_n"])
        assert not np.any(unwrapped.data.xfrc_applied[unwrapped.names.probe_body])
        if terminated:
            break
    assert max(forces) > 0.5  # the tissue was pressed
    assert stiffness.calls == 0


def test_no_wrench_stiffness_without_contact(monkeypatch: pytest.MonkeyPatch) -> None:
    """Two-way coupling in free air: K is zero without a factorisation; it is computed
    once the probe touches."""
    env = gym.make("probegym/BreastCompress-v0", mesh=623)
    unwrapped = env.unwrapped
    stiffness = _Counter(monkeypatch, unwrapped.tissue, "wrench_stiffness")
    env.reset(seed=0)
    for _ in range(10):
        env.step(LIFT)
    assert stiffness.calls == 0
    assert not np.any(unwrapped.coupling._stiffness)
    for _ in range(20):
        env.step(PRESS)
    assert stiffness.calls > 0


def test_nothing_is_sliced_or_drawn_unless_asked(monkeypatch: pytest.MonkeyPatch) -> None:
    """Without the image no B-mode frame is made; with a render mode but no render()
    call, the drawn surface is never updated."""
    sliced = _Counter(monkeypatch, BModeImager, "image")
    env = gym.make("probegym/ForceScan-v0", mesh=623, render_mode="rgb_array")
    drawn = _Counter(monkeypatch, env.unwrapped.tissue, "surface")
    env.reset(seed=0)
    for _ in range(5):
        env.step(PRESS)
    assert sliced.calls == 0 and drawn.calls == 0
    imaging = gym.make("probegym/ForceScan-v0", mesh=623, image=True)
    imaging.reset(seed=0)
    imaging.step(PRESS)
    assert sliced.calls >= 2  # the reset's observation and the step's


def _sleep_run(
    monkeypatch: pytest.MonkeyPatch, contact: str, sleep: bool
) -> tuple[list[dict], int]:
    """ForceScan from seed 0: lift 20 mm, sweep sideways in free air, come back down and
    press, lift again; each observation, and the steps the tissue slept."""
    monkeypatch.setattr(probe_env, "TISSUE_SLEEP_SPEED_M_S", 1e-6 if sleep else None)
    env = gym.make("probegym/ForceScan-v0", mesh=623, contact=contact)
    unwrapped = env.unwrapped
    observations = [env.reset(seed=0)[0]]
    moves = [(1, -0.8)] * 5 + [(0, 0.4)] * 10 + [(1, 0.8)] * 5 + [(1, 0.3)] * 15
    moves += [(1, -0.8)] * 6 + [(1, 0.0)] * 10
    asleep = 0
    for axis, amount in moves:
        action = np.zeros(6, dtype=np.float32)
        action[axis] = amount
        observations.append(env.step(action)[0])
        asleep += bool(unwrapped.coupling.last_step.diagnostics.details.get("asleep"))
    return observations, asleep


@pytest.mark.parametrize("contact", ["lm", "penalty", "prescribed", "pbd"])
def test_a_sleeping_tissue_observes_as_a_stepping_one(
    monkeypatch: pytest.MonkeyPatch, contact: str
) -> None:
    """The tissue sleeps while the probe is in free air and wakes as it comes back: the
    observations are those of a tissue that never sleeps, to round-off (a full free-air
    step moves the tissue by about 1e-17 m where it moves it at all, which the sensed
    wrench, a balance of the sensor's reading against the probe's load, carries as 1e-16 N).
    PBD, and LM, within 1e-6 of each observation's largest value and a float32 ulp of the
    value (at least 1e-9): LM's kept factorisation preconditions CG from the history it saw,
    which sleeping shortens, so its solves agree to CG's tolerance, not bit for bit. How far
    depends on the factor's last bits, which MKL's code path sets (MKL_CBWR): 4e-15 N to
    4e-7 N on a 4 N wrench with MKL 2026.2 here, while two runs of one history agree bit for
    bit, in one process or two. A float32 observation rounds such a difference either way
    (one ulp of a 0.3 N force is 3e-8 N)."""
    sleeping, asleep = _sleep_run(monkeypatch, contact, sleep=True)
    stepping, never = _sleep_run(monkeypatch, contact, sleep=False)
    assert never == 0 and asleep >= 15
    for ours, theirs in zip(sleeping, stepping, strict=True):
        for key in ours:
            difference = np.abs(ours[key].astype(np.float64) - theirs[key])
            allowed = np.full(difference.shape, 1e-12)
            if contact in ("pbd", "lm"):
                magnitude = np.abs(theirs[key]).astype(np.float64)
                ulp = np.spacing(magnitude.astype(np.float32)).astype(np.float64)
                allowed = np.maximum(1e-9, ulp + 1e-6 * float(magnitude.max(initial=0.0)))
            assert np.all(difference <= allowed), (key, float(difference.max()))
    assert float(-stepping[35]["wrench"][1]) > 0.5  # the probe did press the breast


@pytest.mark.parametrize(("env_id", "located"), [("ForceScan-v0", 0), ("LesionSearch-v0", 1)])
def test_only_the_lesion_a_term_tracks_is_located(
    monkeypatch: pytest.MonkeyPatch, env_id: str, located: int
) -> None:
    """ForceScan tracks no lesion: none is ever located; LesionSearch locates its target
    only, once a step."""
    from tissue import lesions as lesions_module

    sizes: list[int] = []
    original = lesions_module._volume_centroids

    def counted(*args):  # type: ignore[no-untyped-def]
        sizes.append(int(args[-1].size))
        return original(*args)

    monkeypatch.setattr(lesions_module, "_volume_centroids", counted)
    env = gym.make(f"probegym/{env_id}", mesh=623)
    env.reset(seed=0)
    sizes.clear()
    for _ in range(5):
        env.step(PRESS)
    assert sizes == [located] * (5 if located else 0)


def test_the_table_stops_the_probe_as_a_chest_wall() -> None:
    """Pressed down beside the breast, the probe's face stops on the table (z = 0, the
    phantom's fixed base) and the F/T sensor reads the table's push; the tissue feels
    nothing there."""
    from envs.rotations import pointing_down

    env = gym.make("probegym/ForceScan-v0", mesh=623, hard_force_n=100.0)
    unwrapped = env.unwrapped
    env.reset(seed=0)
    unwrapped.place_probe(np.array([0.0, -0.11, 0.03]), pointing_down())  # beside the breast
    for _ in range(40):  # the target 100 mm down, 3,000 N/m behind it
        observation, _, _, _, info = env.step(np.array([0, 1, 0, 0, 0, 0], dtype=np.float32))
    position, _ = unwrapped.probe_pose()
    assert -0.001 < position[2] < 0.001
    assert -observation["wrench"][1] > 5.0 and info["normal_force_n"] == 0.0
