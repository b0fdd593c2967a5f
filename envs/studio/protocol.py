"""The messages the probegym plugins exchange between the viewer thread and the simulation
thread (MuJoCo Studio's typed channels: a ``Snapshot`` is latest-wins, an ``Event`` is
delivered in order, never dropped).

Viewer -> simulation: :class:`ControlSnapshot` (the drive controls: mode, pause, the probe
target's pose from sliders and keys), :class:`ResetEpisodeEvent`, :class:`ChooseSceneEvent`.

Simulation -> viewer: :class:`SceneInfoEvent` (what was built, what can be chosen),
:class:`ProbeStatusSnapshot` (every simulation step: time, force, probe pose, lesion depth,
tissue step time and stability), :class:`UltrasoundSnapshot` (the B-mode image, at a lower
rate).

Frames: ``*_world`` is MuJoCo's world frame; the probe frame is the tissue's (x lateral along
the face, y the pressing axis into the tissue, z elevation, out of the image plane). Poses
given "from the start" are relative to the episode's start pose, in the start's probe frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from mujoco.studio import messages

#: Drive modes: the probe follows the viewer's controls, or the policy.
TELEOP = "teleop"
POLICY = "policy"
MODES = (TELEOP, POLICY)


@dataclass(frozen=True)
class ControlSnapshot(messages.Snapshot):
    """The viewer's drive controls (latest wins: a dragged slider sends many, the simulation
    acts on the last).

    Attributes:
        mode: :data:`TELEOP` or :data:`POLICY`.
        paused: whether the simulation clock stands still.
        offset_m: where the probe's target is from the episode's start pose [m], (3,), in
            the start's probe frame (lateral, press, elevation).
        turn_rad: the target's rotation from the start's orientation, a rotation vector in
            the start's probe frame [rad], (3,): tilt (about x), rotate (about the probe's
            axis, y), rock (about z).
    """

    mode: str = TELEOP
    paused: bool = False
    offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    turn_rad: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class ResetEpisodeEvent(messages.Event):
    """Start a new episode (the environment's ``reset``); ``seed`` None: the next seed."""

    seed: int | None = None


@dataclass(frozen=True)
class ChooseSceneEvent(messages.Event):
    """Build the environment again with this task, contact method and mesh (phantom level
    or mesh file); the simulation answers with a :class:`SceneInfoEvent` (and an error in
    it where the choice cannot be built: the previous scene then stays)."""

    env_id: str
    contact: str
    mesh: int | str


@dataclass(frozen=True)
class SceneInfoEvent(messages.Event):
    """What the simulation runs now and what the viewer may offer.

    Attributes:
        env_id, contact, mesh: the scene built.
        env_ids, contacts, meshes: the choices offered.
        policy_envs: the environments a policy was given for (may be empty).
        policy_label: what the policy is (``scripted``, a model's path), '' without one.
        teleop: whether the probe can be teleoperated (a Cartesian controller).
        tissue_dt_s: the tissue's (and the control) step [s].
        aperture_m, imaging_depth_m: the image plane's width and depth [m].
        error: why the last :class:`ChooseSceneEvent` was refused ('' when it was built).
    """

    env_id: str
    contact: str
    mesh: int | str
    env_ids: tuple[str, ...]
    contacts: tuple[str, ...]
    meshes: tuple[int | str, ...]
    policy_envs: tuple[str, ...] = ()
    policy_label: str = ""
    teleop: bool = True
    tissue_dt_s: float = 0.02
    aperture_m: float = 0.04
    imaging_depth_m: float = 0.06
    error: str = ""


@dataclass(frozen=True)
class ProbeStatusSnapshot(messages.Snapshot):
    """The coupled scene after a simulation step.

    Attributes:
        time_s: simulated time since the episode began [s].
        episode: episodes started so far (1 after the first reset).
        mode, paused: as the simulation applies them.
        probe_pos_world: the probe origin (its face's centre) [m], (3,).
        probe_rot_world: the probe frame's axes as columns, row-major (9,).
        start_pos_world, start_rot_world: the episode's start pose, likewise.
        offset_m, turn_rad: the controller's target from the start pose (as
            :class:`ControlSnapshot`'s); the policy's when it drives.
        force_world_n: the tissue's force on the probe [N], (3,).
        lesion: the target lesion's label (1-based; 0: none).
        lesion_depth_m: its centre's depth below the face along the probe axis [m].
        target_depth_m: the depth the task asks for [m] (NaN where it asks none).
        tissue_step_s: the last tissue step's wall time (its stiffness included) [s].
        step_s: the last environment step's wall time [s].
        realtime: simulated seconds per wall-clock second, recent average.
        tissue_status: the tissue step's status (``ok``, ``not_converged``, ...).
        stable: whether the status is one the coupling keeps using (not diverged or failed).
        reward: the last step's reward.
        ended: '' while the episode runs, else ``success``, ``terminated`` or ``truncated``.
        error: a step that raised (the simulation pauses), '' otherwise.
    """

    time_s: float = 0.0
    episode: int = 0
    mode: str = TELEOP
    paused: bool = False
    probe_pos_world: tuple[float, ...] = (0.0, 0.0, 0.0)
    probe_rot_world: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
    start_pos_world: tuple[float, ...] = (0.0, 0.0, 0.0)
    start_rot_world: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
    offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    turn_rad: tuple[float, float, float] = (0.0, 0.0, 0.0)
    force_world_n: tuple[float, float, float] = (0.0, 0.0, 0.0)
    lesion: int = 0
    lesion_depth_m: float = float("nan")
    target_depth_m: float = float("nan")
    tissue_step_s: float = 0.0
    step_s: float = 0.0
    realtime: float = 0.0
    tissue_status: str = "ok"
    stable: bool = True
    reward: float = 0.0
    ended: str = ""
    error: str = ""


@dataclass(frozen=True, eq=False)
class UltrasoundSnapshot(messages.Snapshot):
    """A B-mode image of the slice under the probe.

    Attributes:
        rgba: the image as RGBA bytes, row-major, row 0 at the face, ``rows * cols * 4``.
        rows, cols: its size [pixels] (depth by lateral).
        time_s: the simulated time it shows [s].
    """

    rgba: bytes = field(repr=False, default=b"")
    rows: int = 0
    cols: int = 0
    time_s: float = 0.0
