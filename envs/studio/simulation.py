"""The simulation plugin: a probegym environment stepped on MuJoCo Studio's simulation thread.

:class:`ProbeSimulation` owns one environment made with ``gymnasium.make`` and steps it with
``env.step(action)``, so the arm, the probe and the breast advance through the environment's
own coupling (:class:`envs.coupling.TissueCoupling`: MuJoCo's substeps, then one tissue
step): there is no second copy of the physics. What Studio shows is the drawing scene of
:class:`envs.rendering.SceneRenderer` (the physics scene plus the breast as display-only
flexes on mocap bodies); after each step the renderer copies the arm's state over and moves
the breast's vertices to the tissue's deformed surface, in the very ``MjData`` Studio
streams to the viewer (the mocap positions are part of MuJoCo's integration state).

Pacing: one environment step (``tissue_dt``, 20 ms by default) is taken when the wall clock
reaches it; a step that takes longer than ``tissue_dt`` slows the simulated clock (shown as
the real-time factor), never the viewer, whose thread only reads snapshots. Between steps
the handler sleeps a millisecond, which also hands the GIL to the viewer thread.

Drive: in :data:`~envs.studio.protocol.TELEOP` mode the action moves the controller's target
towards the pose the viewer's sliders and keys ask for (relative to the episode's start
pose), at most :data:`TELEOP_MAX_ACTION` of the action's range a step; in
:data:`~envs.studio.protocol.POLICY` mode a callable ``policy(observation) -> action`` given
by the caller drives (``envs`` never imports torch: ``probegym view`` loads the policy), and
an episode that ends is followed by a new one.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import gymnasium as gym
import mujoco
import numpy as np
from mujoco.studio import messages, plugin
from numpy.typing import NDArray

import tissue
from envs.controller import CartesianImpedance, rotation_vector
from envs.errors import EnvConfigError
from envs.observations import TOUCH_FORCE_N
from envs.probe_env import ProbeEnv
from envs.rendering import SceneRenderer
from envs.rotations import turn_matrix
from envs.studio.protocol import (
    MODES,
    POLICY,
    TELEOP,
    ChooseSceneEvent,
    ControlSnapshot,
    ProbeStatusSnapshot,
    ResetEpisodeEvent,
    SceneInfoEvent,
    UltrasoundSnapshot,
)
from envs.ultrasound import BModeConfig, BModeImager

#: A policy: the observation in, an action in [-1, 1]^6 out (``reset()`` called, where it
#: has one, before each episode).
Policy = Callable[[dict[str, NDArray[Any]]], Any]
#: Makes an environment: ``make_env(env_id, **kwargs)`` (default ``gymnasium.make``).
EnvFactory = Callable[..., gym.Env[Any, Any]]

#: The largest action a teleoperation step takes (of the action's [-1, 1] range: 0.2 is
#: 1 mm and 0.01 rad a step at the default scale, 50 mm/s at 50 Hz).
TELEOP_MAX_ACTION = 0.2
#: Tissue statuses the coupling stops trusting (its wrench is dropped).
UNSTABLE = (tissue.StepStatus.DIVERGED.value, tissue.StepStatus.SOLVER_FAILED.value)
#: The longest the simulation thread sleeps between looks at the viewer's messages [s].
IDLE_S = 0.01
#: How many steps the real-time factor averages.
_REALTIME_WINDOW = 25


class ProbeSimulation(plugin.SimPlugin):
    """Steps a probegym environment for Studio (see the module docstring).

    Args:
        env_id: the environment (``probegym/BreastCompress-v0``, ...).
        contact: its contact method (None: the environment's default or ``env_kwargs``').
        mesh: its mesh, a phantom level or a mesh file (None: likewise).
        env_kwargs: other keyword arguments of the environment.
        policies: a policy factory per environment id it can drive (may be empty: then only
            teleoperation).
        policy_label: what the policy is, for the status panel.
        seed: the first episode's seed (each new episode takes the next).
        env_ids, contacts, meshes: the choices the viewer offers (default: just the one
            built).
        image_hz: how often the ultrasound image is made [Hz of simulated time] (0: never).
        make_env: the factory (default ``gymnasium.make``).

    Raises:
        EnvConfigError: a bad argument here; the environment's own errors come from
            :meth:`build` (call it before launching to fail early).
    """

    def __init__(
        self,
        env_id: str,
        *,
        contact: str | None = None,
        mesh: int | str | None = None,
        env_kwargs: Mapping[str, Any] | None = None,
        policies: Mapping[str, Callable[[], Policy]] | None = None,
        policy_label: str = "",
        seed: int = 0,
        env_ids: Sequence[str] = (),
        contacts: Sequence[str] = (),
        meshes: Sequence[int | str] = (),
        image_hz: float = 10.0,
        make_env: EnvFactory | None = None,
    ) -> None:
        if not (isinstance(image_hz, (int, float)) and 0.0 <= image_hz <= 1000.0):
            raise EnvConfigError(f"image_hz must be a rate in [0, 1000] Hz; got {image_hz!r}")
        if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
            raise EnvConfigError(f"seed must be a whole number >= 0; got {seed!r}")
        self.env_id = env_id
        self.env_kwargs = dict(env_kwargs or {})
        self.contact = contact if contact is not None else self.env_kwargs.pop("contact", None)
        self.mesh = mesh if mesh is not None else self.env_kwargs.pop("mesh", None)
        self.env_kwargs.pop("contact", None)
        self.env_kwargs.pop("mesh", None)
        self.env_kwargs.pop("render_mode", None)  # Studio draws; the env renders nothing
        self.policies = dict(policies or {})
        self.policy_label = policy_label
        self.seed = seed
        self.choices = (tuple(env_ids), tuple(contacts), tuple(meshes))
        self.image_hz = float(image_hz)
        self.make_env = make_env if make_env is not None else gym.make
        self.env: gym.Env[Any, Any] | None = None
        self.core: ProbeEnv | None = None
        self.renderer: SceneRenderer | None = None
        self.imager: BModeImager | None = None
        self._imaged: tissue.Tissue | None = None  # the tissue the imager was made for
        self.policy: Policy | None = None
        self.control = ControlSnapshot()
        self.episode = 0
        self.observation: dict[str, NDArray[Any]] = {}
        self.info: dict[str, Any] = {}
        self._start = (np.zeros(3), np.eye(3))
        self._episode_start_s = 0.0
        self._last: dict[str, Any] = {}
        self._ended = ""
        self._error = ""
        self._next_due = 0.0
        self._next_image_s = 0.0
        self._recent: list[tuple[float, float]] = []  # (wall, sim) of recent steps

    # ------------------------------------------------------------------ building

    def build(self, env_id: str | None = None, contact: str | None = None,
              mesh: int | str | None = None) -> None:  # fmt: skip
        """Make the environment (again, with any of ``env_id``, ``contact``, ``mesh``
        changed), its drawing scene and imager, and start an episode. On error the previous
        environment (if any) stays.

        Raises:
            EnvConfigError, tissue.TissueInputError: the environment refuses the arguments
                (the message names the value and the valid ones).
            gymnasium.error.Error: an unknown environment id.
        """
        env_id = self.env_id if env_id is None else env_id
        contact = self.contact if contact is None else contact
        mesh = self.mesh if mesh is None else mesh
        kwargs = dict(self.env_kwargs)
        if contact is not None:
            kwargs["contact"] = contact
        if mesh is not None:
            kwargs["mesh"] = mesh
        env = self.make_env(env_id, **kwargs)
        core = env.unwrapped
        if not isinstance(core, ProbeEnv):
            env.close()
            raise EnvConfigError(
                f"{env_id!r} is not a probegym environment; choose one of "
                f"{', '.join(self.choices[0]) or 'probegym/BreastCompress-v0'}"
            )
        renderer = SceneRenderer(core.scene_config, core.tissue, 64, 64, "overview")
        if self.env is not None:
            self.env.close()
        self.env, self.core, self.renderer, self.imager = env, core, renderer, None
        self.env_id, self.contact, self.mesh = env_id, core.tissue.spec.contact, mesh
        factory = self.policies.get(env_id)
        self.policy = factory() if factory is not None else None
        if self.policy is None and self.control.mode == POLICY:
            self.control = ControlSnapshot(paused=self.control.paused)
        self.reset(self.seed)

    def reset(self, seed: int | None = None) -> None:
        """A new episode (seed None: the one after the last), the drawing scene synced."""
        assert self.env is not None and self.core is not None
        if seed is None:
            seed = self.seed + self.episode
        self.observation, self.info = self.env.reset(seed=seed)
        self.episode += 1
        self._start = self.core.probe_pose()
        self._episode_start_s = float(self.core.data.time)
        self._last = {"reward": 0.0, "tissue_s": 0.0, "step_s": 0.0}
        self._ended = ""
        self._error = ""
        self._next_image_s = 0.0
        self._recent.clear()
        if self.policy is not None and hasattr(self.policy, "reset"):
            self.policy.reset()
        # The sliders of the viewer start from the new start pose.
        self.control = ControlSnapshot(mode=self.control.mode, paused=self.control.paused)
        self._sync_drawing()

    def scene_info(self, error: str = "") -> SceneInfoEvent:
        """What is built now and what may be chosen."""
        assert self.core is not None
        env_ids, contacts, meshes = self.choices
        imaging = self.core.imaging
        given = self.mesh if self.mesh is not None else self.core.tissue.spec.mesh
        mesh: int | str = given if isinstance(given, int) else str(given)
        return SceneInfoEvent(
            env_id=self.env_id,
            contact=str(self.contact),
            mesh=mesh,
            env_ids=tuple(dict.fromkeys((*env_ids, self.env_id))),
            contacts=tuple(dict.fromkeys((*contacts, str(self.contact)))),
            meshes=tuple(dict.fromkeys((*meshes, mesh))),
            policy_envs=tuple(self.policies),
            policy_label=self.policy_label,
            teleop=isinstance(self.core.controller, CartesianImpedance),
            tissue_dt_s=float(self.core.tissue.dt),
            aperture_m=float(imaging.aperture_m),
            imaging_depth_m=float(imaging.imaging_depth_m),
            error=error,
        )

    # ------------------------------------------------------------------ handlers

    @messages.handler
    def on_load_model(self, event: messages.LoadModelEvent) -> bool:
        """Publish the drawing scene (building the environment first if need be)."""
        if event.path:
            return False
        if self.env is None:
            self.build()
        self._publish()
        return True

    @messages.handler
    def on_control(self, snapshot: ControlSnapshot) -> bool:
        mode = snapshot.mode if snapshot.mode in MODES else TELEOP
        if mode == POLICY and self.policy is None:
            mode = TELEOP
        pausing = snapshot.paused != self.control.paused
        self.control = ControlSnapshot(mode, snapshot.paused, snapshot.offset_m, snapshot.turn_rad)
        if pausing:
            self._recent.clear()
            if self.core is not None:
                self._send_status()  # the viewer learns at once, stepping or not
        return True

    @messages.handler
    def on_reset_episode(self, event: ResetEpisodeEvent) -> bool:
        self.reset(event.seed)
        self._send_status()
        return True

    @messages.handler
    def on_choose_scene(self, event: ChooseSceneEvent) -> bool:
        try:
            self.build(event.env_id, event.contact, event.mesh)
        except (tissue.TissueInputError, gym.error.Error, ValueError) as error:
            self.handle.send_to_viewer(self.scene_info(error=str(error)))
            return True
        self._publish()
        return True

    @messages.handler
    def on_step(self, event: messages.StepEvent) -> bool:
        """One environment step when it is due (pacing: the module docstring)."""
        now = time.perf_counter()
        if self.core is None or self.control.paused or self._error:
            self._next_due = now
            time.sleep(IDLE_S)
            return True
        if now < self._next_due:
            # Sleeping until the step is due (the viewer's messages wait as long at most)
            # leaves the GIL to the viewer and the web server.
            time.sleep(min(IDLE_S, self._next_due - now))
            return True
        if self._ended and self.control.mode == POLICY:
            self.reset()
        dt = float(self.core.tissue.dt)
        self.step()
        # Late steps are not made up: the simulated clock falls behind instead.
        self._next_due = max(self._next_due + dt, time.perf_counter() - dt)
        time.sleep(0.001)  # even when late, the other threads get a turn
        return True

    @messages.handler
    def on_exit(self, event: messages.ExitEvent) -> None:
        if self.env is not None:
            self.env.close()

    # ------------------------------------------------------------------ stepping

    def step(self) -> None:
        """One environment step with the mode's action; the drawing, status and image
        updated. A step that raises pauses the simulation and reports the error."""
        assert self.env is not None and self.core is not None
        started = time.perf_counter()
        try:
            action = self.action()
            observation, reward, terminated, truncated, info = self.env.step(action)
        except (tissue.TissueInputError, ValueError, FloatingPointError) as error:
            self._error = f"{type(error).__name__}: {error}"
            self._send_status()
            return
        step_s = time.perf_counter() - started
        self.observation, self.info = observation, info
        timing = self.core.last_timing
        self._last = {
            "reward": float(reward),
            "tissue_s": float(timing.get("tissue_s", 0.0)),
            "step_s": step_s,
        }
        if terminated or truncated:
            if info.get("is_success"):
                self._ended = "success"
            else:
                self._ended = "terminated" if terminated else "truncated"
        self._recent.append((time.perf_counter(), float(self.core.data.time)))
        del self._recent[:-_REALTIME_WINDOW]
        self._sync_drawing()
        self._send_status()
        self._send_image()

    def action(self) -> NDArray[np.float64]:
        """The action of this step: the policy's, or the teleoperation's (module docstring)."""
        assert self.core is not None
        if self.control.mode == POLICY and self.policy is not None:
            return np.asarray(self.policy(self.observation), dtype=np.float64).reshape(-1)
        controller = self.core.controller
        action = np.zeros(6)
        if not isinstance(controller, CartesianImpedance):
            return action  # joint control: teleoperation holds still
        start_pos, start_rot = self._start
        want_pos = start_pos + start_rot @ np.asarray(self.control.offset_m)
        want_rot = start_rot @ turn_matrix(np.asarray(self.control.turn_rad, dtype=np.float64))
        scale = self.core.action_config
        rotation = controller.target_rot
        action[:3] = rotation.T @ (want_pos - controller.target_pos) / scale.max_translation_m
        action[3:] = rotation_vector(rotation.T @ want_rot) / scale.max_rotation_rad
        return np.clip(action, -TELEOP_MAX_ACTION, TELEOP_MAX_ACTION)

    # ------------------------------------------------------------------ to the viewer

    def _publish(self) -> None:
        """Hand Studio the drawing scene (its data is the renderer's) and tell the viewer."""
        assert self.renderer is not None
        self.handle.set_model(self.renderer.model, data=self.renderer.data)
        self.handle.send_to_viewer(self.scene_info())
        self._send_status()
        self._send_image(force=True)

    def _sync_drawing(self) -> None:
        """The drawing scene's arm and breast where the environment has them now."""
        assert self.core is not None and self.renderer is not None
        self.renderer.tissue = self.core.tissue  # a randomised episode draws its own tissue
        self.renderer.sync(self.core.data)
        self.renderer.data.time = float(self.core.data.time) - self._episode_start_s

    def status(self) -> ProbeStatusSnapshot:
        """The status snapshot of the scene now."""
        assert self.core is not None
        core = self.core
        position, rotation = core.probe_pose()
        start_pos, start_rot = self._start
        step = core.coupling.last_step
        force = np.zeros(3) if step is None else np.asarray(step.force_world_n, dtype=float)
        label = int(self.info.get("target_lesion", 0) or 0)
        depth = float("nan")
        if 1 <= label <= len(core.tissue.lesions):
            centre = core.tissue.lesion_centroids_m()[label - 1]
            depth = float((rotation.T @ (centre - position))[1])
        target_depth = float(self.info.get("target_depth_m", float("nan")))
        offset, turn = self.control.offset_m, self.control.turn_rad
        controller = core.controller
        if self.control.mode == POLICY and isinstance(controller, CartesianImpedance):
            offset = _triple(start_rot.T @ (controller.target_pos - start_pos))
            turn = _triple(rotation_vector(start_rot.T @ controller.target_rot))
        realtime = 0.0
        if len(self._recent) >= 2:
            (wall0, sim0), (wall1, sim1) = self._recent[0], self._recent[-1]
            realtime = (sim1 - sim0) / max(wall1 - wall0, 1e-9)
        status = "ok" if step is None else step.status.value
        return ProbeStatusSnapshot(
            time_s=float(core.data.time) - self._episode_start_s,
            episode=self.episode,
            mode=self.control.mode,
            paused=self.control.paused,
            probe_pos_world=_triple(position),
            probe_rot_world=tuple(float(v) for v in rotation.reshape(-1)),
            start_pos_world=_triple(start_pos),
            start_rot_world=tuple(float(v) for v in start_rot.reshape(-1)),
            offset_m=offset,
            turn_rad=turn,
            force_world_n=_triple(force),
            lesion=label,
            lesion_depth_m=depth,
            target_depth_m=target_depth,
            tissue_step_s=self._last["tissue_s"],
            step_s=self._last["step_s"],
            realtime=realtime,
            tissue_status=status,
            stable=status not in UNSTABLE,
            reward=self._last["reward"],
            ended=self._ended,
            error=self._error,
        )

    def _send_status(self) -> None:
        self.handle.send_to_viewer(self.status())

    def _send_image(self, force: bool = False) -> None:
        """The B-mode image of the slice under the probe, every 1 / ``image_hz`` s of
        simulated time (``force``: now)."""
        core = self.core
        if self.image_hz <= 0.0 or core is None or not core.scene.has("deformation"):
            return
        if self.imager is None or self._imaged is not core.tissue:
            # A randomised episode has its own tissue (lesions moved): image that one.
            imaging = core.imaging
            self.imager = BModeImager(
                core.tissue,
                BModeConfig(aperture_m=imaging.aperture_m, imaging_depth_m=imaging.imaging_depth_m),
            )
            self._imaged = core.tissue
        now = float(core.data.time) - self._episode_start_s
        if not force and now < self._next_image_s:
            return
        self._next_image_s = now + 1.0 / self.image_hz
        position, rotation = core.probe_pose()
        quat = np.empty(4)
        mujoco.mju_mat2Quat(quat, rotation.reshape(-1))
        step = core.coupling.last_step
        touching = step is not None and float(np.linalg.norm(step.force_world_n)) > TOUCH_FORCE_N
        grey = self.imager.image(core.tissue, position, quat, bool(touching))
        rgba = np.empty((*grey.shape, 4), dtype=np.uint8)
        rgba[..., :3] = grey[..., None]
        rgba[..., 3] = 255
        self.handle.send_to_viewer(
            UltrasoundSnapshot(rgba.tobytes(), grey.shape[0], grey.shape[1], now)
        )


def _triple(vector: Any) -> tuple[float, float, float]:
    values = np.asarray(vector, dtype=np.float64).reshape(3)
    return float(values[0]), float(values[1]), float(values[2])
