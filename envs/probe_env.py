"""The machinery every probegym task shares: :class:`ProbeEnv`.

An arm (:mod:`envs.scene`) holds the linear probe, driven by a controller
(:mod:`envs.controller`) and coupled two ways to the FE breast (:mod:`envs.coupling`). A task
(:mod:`envs.tasks`) subclasses :class:`ProbeEnv` and declares; :meth:`ProbeEnv.step` owns
the step loop (dm_control's task / environment split). A task's declarations: its config
(``task_config_type``), ``reset`` (where an episode starts), ``_observation_spaces`` and
``_observation`` (what is observed beyond the common terms), ``_track`` (its state after a
step), ``_succeeded``, ``_reward_terms`` (named terms, the reward their sum) and ``_info``;
the loop adds the common failures (the tissue step not ``ok``, the force over
``hard_force_n``, a non-finite arm) and termination. Each observation and
reward term declares the simulated effects it needs (:data:`envs.effects.EFFECTS`).

Keyword arguments common to every task (unknown ones are errors that list the valid ones):
``contact`` (penalty | lm | prescribed | pbd), ``profile`` (paper | robust), ``mesh`` (a
phantom level or a mesh file, see ``tissue.TissueSpec``), ``collision_edge_m`` (the skin's
resolution: its collision surface's edge [m], :data:`COLLISION_EDGE_M` by default, finer
than the probe's 13.2 mm face; None for the mesh's own surface, the paper's 1,004 triangles
on the phantom), ``young_pa``, ``poisson``, ``lesion_stiffness_ratio``, ``control_mode``
(cartesian_impedance | joint_delta), ``stiffness_n_per_m`` (the probe impedance's
translational stiffness), ``render_mode`` (rgb_array | human), ``camera_name`` (overview |
probe_side), ``width``, ``height``, ``robot`` (an MJCF arm of any joint count, its keyframe
``home`` seeding its home pose where it has one; :data:`envs.scene.ARM7_PATH` is a 7-joint
one) and ``flange_site``, ``robot_base_m`` (where its base stands), ``robot_dt``, ``scene``
(a preset of :data:`envs.effects.SCENES`: ``full``, the default, ``imaging``, ``one_way``,
``rigid``) or ``effects`` (a list of effect names, see :mod:`envs.effects`: a scene
simulates only the effects it calls for, and a task whose terms need an effect the scene
lacks is refused), ``max_translation_m`` and ``max_rotation_rad`` (the action's scale), the
imaging geometry ``aperture_m``, ``imaging_depth_m``, ``slice_thickness_m``, and ``image``
(True, or an :class:`envs.ultrasound.BModeConfig`: observe a B-mode image of the slice under
the probe; off by default, and then never computed; with it, ``rgb_array`` frames show the
image to the right of the 3D view, at the frame's height), ``domain_randomization`` (True, a
dict or an :class:`envs.randomization.DomainRandomization`: each reset draws the tissue's
and lesions' stiffness and the lesions' places, and the F/T sensor and probe pose the policy
observes are noisy; off by default).

Threads: an environment applies the process's thread policy (``tissue.configure_threads()``)
before it builds its tissue: numba's kernels on Intel TBB, which lets vector environments
fork their workers, and MKL Pardiso sequential; a policy already in force (the command
line's, or one its user set) is kept. Its observations are the same bits on any number of
numba threads for every phantom level up to 26,220 tets and any mesh under 40,000 unknowns
(13,333 nodes); from the level of 105,004 tets up, the FE contact methods' solver sums follow
the thread count (``tissue.configure_threads(threads=1)`` makes them repeatable; ``pbd``
keeps its bits). Measured figures: docs/tissue-model.md, "Threads".

Vector environments: ``gymnasium.make_vec`` (``sync``; ``async`` with workers started by
fork, forkserver or spawn) and SB3's ``SubprocVecEnv``; ``metadata["autoreset_mode"]`` is
``AutoresetMode.NEXT_STEP``, the default of Gymnasium's ``SyncVectorEnv`` and
``AsyncVectorEnv``: the step after an episode ends returns the next one's first observation,
reward 0, the action ignored (SB3's reset within the ending step instead, the last
observation in ``info["terminal_observation"]``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, fields
from typing import Any, ClassVar

import gymnasium as gym
import mujoco
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode
from numpy.typing import NDArray

import tissue
from envs.arguments import check_display, route_kwargs
from envs.controller import (
    CartesianImpedance,
    ControllerConfig,
    JointImpedance,
    solve_ik,
)
from envs.coupling import TissueCoupling
from envs.effects import Scene, check_terms, resolve_scene
from envs.errors import EnvConfigError, check_positive
from envs.observations import TOUCH_FORCE_N, ImagingConfig, sensed_wrench
from envs.randomization import DomainRandomization, Randomizer
from envs.rendering import CAMERAS, SceneRenderer, beside
from envs.rigid import RigidCoupling
from envs.rotations import axis_angle, pointing_down, quat_matrix, rotation_angle, turn_matrix
from envs.scene import HOME_KEY, ROBOT_PREFIX, SceneConfig, build_scene, scene_names
from envs.ultrasound import BModeConfig, BModeImager

#: A seed configuration of the default arm for the probe over the phantom, pointing down;
#: each reset solves IK from it.
HOME_SEED_RAD = (-0.32, -1.5, 2.32, -2.39, 1.57, 1.25)
#: Where the probe hovers at home [m] (above the phantom's apex, pointing down).
HOME_PROBE_M = (0.0, 0.0, 0.14)
#: The built-in phantom's lesions whose compression by 5-7 mm is within reach of a gentle
#: press (measured with robust LM at 1,303 tets, probe normal to the skin above each:
#: lesion 1 at 15 mm depth moves 5 mm up the image under a 12 mm press at 1.5-2 N, lesions
#: 6, 7 and 10 (21-40 mm deep) under 8-10 mm at 1.2-1.5 N, lesion 4 (18 mm) under 15 mm at
#: 2.7 N; lesions 2, 3, 5, 8 and 9 lie 7-15 mm under 45-degree skin, where frictionless
#: tissue slides out sideways: 25 mm of press and 7-8 N moved them 5 mm at most).
PHANTOM_TARGET_LESIONS = (1, 4, 6, 7, 10)
#: The tissue sleeps in free air below this node speed [m/s] (see
#: :mod:`tissue.contact.sleep`): a step with the probe clear of a resting breast costs no
#: tissue work; the observation is the same as a full step's.
TISSUE_SLEEP_SPEED_M_S: float | None = tissue.SLEEP_SPEED_M_S
#: The skin's resolution in the environments [m]: the collision surface's edge length
#: (:attr:`tissue.TissueSpec.collision_edge_m`). The probe's 13.2 mm face spans six or seven
#: vertices, and a facet kept out of the probe at its vertices can cut its 1.35 mm rounded
#: edge by 0.65 mm at most (:func:`tissue.probe.surface_depth.facet_allowance_m`). Chosen by
#: measurement: docs/contact.md, "The skin's resolution".
COLLISION_EDGE_M = 0.002
#: Limits of a wrench observation [N, N m] and a joint velocity [rad/s] (the spaces' bounds).
WRENCH_LIMIT = 200.0
JOINT_VELOCITY_LIMIT = 20.0


@dataclass(frozen=True)
class StepState:
    """What one step measured, as the task's declarations (:meth:`ProbeEnv._track`,
    :meth:`ProbeEnv._succeeded`, :meth:`ProbeEnv._reward_terms`) receive it.

    Attributes:
        action: the action taken, clipped to the box, (action_size,).
        tissue_step: the tissue's step (None for a state a test builds).
        force_n: the contact force's magnitude [N].
        normal_n: the contact force along the probe's pressing axis [N] (positive pressing).
        finite: whether the arm's state is finite after the step.
    """

    action: NDArray[np.float64]
    tissue_step: tissue.TissueStep | None
    force_n: float
    normal_n: float
    finite: bool = True


@dataclass(frozen=True)
class ActionConfig:
    """How an action in [-1, 1]^6 moves the probe's target each step (``joint_delta``: one
    number per joint moves its target).

    Attributes:
        max_translation_m: translation at |a| = 1 [m per step], along the probe's axes.
        max_rotation_rad: rotation at |a| = 1 [rad per step], about the probe's axes.
        max_joint_step_rad: ``joint_delta`` mode: joint target change at |a| = 1 [rad].
    """

    max_translation_m: float = 0.005
    max_rotation_rad: float = 0.05
    max_joint_step_rad: float = 0.05

    def __post_init__(self) -> None:
        check_positive(self, (f.name for f in fields(self)))


#: ``ProbeEnv``'s own keyword arguments (the configs' fields are the others).
_COMMON_ARGUMENTS = (
    "contact", "profile", "mesh", "collision_edge_m", "young_pa", "poisson",
    "lesion_stiffness_ratio", "control_mode", "render_mode", "camera_name", "width", "height",
    "robot", "flange_site", "robot_base_m", "robot_dt", "scene", "effects", "image",
    "domain_randomization",
)  # fmt: skip


class ProbeEnv(gym.Env[dict[str, NDArray[Any]], NDArray[np.float32]]):
    """The coupled arm, probe and breast; tasks subclass it (see the module docstring)."""

    #: ``autoreset_mode``: the mode a task's vector environments are tested under, Gymnasium's
    #: default (the module docstring, "Vector environments").
    metadata = {  # noqa: RUF012
        "render_modes": ["rgb_array", "human"],
        "render_fps": 50,
        "autoreset_mode": AutoresetMode.NEXT_STEP,
    }

    #: The simulated effects of the observation terms every task shares (a task's
    #: ``TERM_EFFECTS`` adds its own terms; see :data:`envs.effects.EFFECTS`).
    COMMON_TERM_EFFECTS: ClassVar[dict[str, tuple[str, ...]]] = {
        "probe_pose": (),
        "wrench": ("force_feedback",),
        "joint_pos": (),
        "joint_vel": (),
        "image": ("deformation", "image"),
    }
    #: The effects each of the task's terms needs; tasks replace it with theirs.
    TERM_EFFECTS: ClassVar[dict[str, tuple[str, ...]]] = COMMON_TERM_EFFECTS

    #: The task's registered episode length [steps] (tasks set theirs).
    episode_steps: ClassVar[int] = 0

    #: The task's own settings (a frozen dataclass); keyword arguments of its fields go there.
    task_config_type: ClassVar[type] = type(None)

    def __init__(
        self,
        contact: str = "lm",
        profile: str = "robust",
        mesh: int | str = 1363,
        collision_edge_m: float | None = COLLISION_EDGE_M,
        young_pa: float | None = None,
        poisson: float | None = None,
        lesion_stiffness_ratio: float | None = None,
        control_mode: str = "cartesian_impedance",
        render_mode: str | None = None,
        camera_name: str = "overview",
        width: int = 480,
        height: int = 480,
        robot: str | None = None,
        flange_site: str | None = None,
        robot_base_m: tuple[float, float, float] | None = None,
        robot_dt: float = 0.002,
        scene: str | Scene | None = None,
        effects: list[str] | tuple[str, ...] | None = None,
        image: bool | BModeConfig = False,
        domain_randomization: bool | dict[str, Any] | DomainRandomization | None = False,
        **kwargs: Any,
    ) -> None:
        configs = {
            "controller": ControllerConfig,
            "action": ActionConfig,
            "imaging": ImagingConfig,
            "task": self.task_config_type,
        }
        routed = route_kwargs(type(self).__name__, kwargs, configs, _COMMON_ARGUMENTS)
        check_display(
            render_mode, self.metadata["render_modes"], camera_name, CAMERAS, width, height
        )
        self.controller_config = ControllerConfig(mode=control_mode, **routed["controller"])
        self.action_config = ActionConfig(**routed["action"])
        self.imaging = ImagingConfig(**routed["imaging"])
        self.task_config = self.task_config_type(**routed["task"])
        scene_kwargs: dict[str, Any] = {"robot_dt": float(robot_dt)}
        if robot is not None:
            scene_kwargs["robot_path"] = robot
        if flange_site is not None:
            scene_kwargs["flange_site"] = flange_site
        if robot_base_m is not None:
            scene_kwargs["robot_base_m"] = tuple(robot_base_m)
        self.scene_config = SceneConfig(**scene_kwargs)
        # The process's thread policy before the tissue is built: the default (numba on TBB,
        # MKL sequential), or the one its user set, kept (see the module docstring, Threads).
        tissue.configure_threads()
        self.tissue = tissue.make_tissue(
            mesh=mesh,
            contact=contact,
            profile=profile,
            collision_edge_m=collision_edge_m,
            sleep_speed_m_s=TISSUE_SLEEP_SPEED_M_S,
            young_pa=young_pa,
            poisson=poisson,
            lesion_stiffness_ratio=lesion_stiffness_ratio,
        )
        # The tasks locate their target lesion themselves, when a term needs it: no tissue
        # step evaluates any lesion.
        self.tissue.track_lesions(())
        #: What this environment simulates (:mod:`envs.effects`).
        self.scene = resolve_scene(scene, effects, image is not False)
        deforms = self.scene.has("deformation")
        self.model = build_scene(
            self.scene_config,
            self.tissue.probe_shape,
            rigid_breast=None if deforms else self.tissue.surface(),
        )
        self.data = mujoco.MjData(self.model)
        self.names = scene_names(self.model)
        if deforms:
            self.coupling: TissueCoupling | RigidCoupling = TissueCoupling(
                self.model,
                self.data,
                self.names,
                self.tissue,
                reaction=self.scene.has("force_feedback"),
            )
        else:
            self.coupling = RigidCoupling(self.model, self.data, self.names, self.tissue)
        self.joint_count = len(self.names.joint_qpos)
        if self.controller_config.mode == "cartesian_impedance":
            self.controller: CartesianImpedance | JointImpedance = CartesianImpedance(
                self.model, self.names, self.controller_config
            )
        else:
            self.controller = JointImpedance(self.model, self.names, self.controller_config)
        self.imager = self._make_imager(
            True if image is False and self.scene.has("image") else image
        )
        check_terms(type(self).__name__, self.scene, self.term_effects())
        settings = DomainRandomization.parse(domain_randomization)
        #: Draws each episode's variation (None: no domain randomisation).
        self.randomizer = None if settings is None else Randomizer(settings, self.tissue)
        self._home = self._solve_home()
        self.render_mode = render_mode
        self.camera_name = camera_name
        self._renderer: SceneRenderer | None = None
        self._frame_size = (width, height)
        #: The action's length: 6 (the probe's motion) in ``cartesian_impedance`` mode, one
        #: per joint in ``joint_delta`` mode.
        self.action_size = (
            6 if self.controller_config.mode == "cartesian_impedance" else self.joint_count
        )
        self.action_space = spaces.Box(-1.0, 1.0, shape=(self.action_size,), dtype=np.float32)
        self.observation_space = spaces.Dict(self._observation_spaces())  # type: ignore[assignment]
        self._start_pos = np.zeros(3)
        self._start_rot = np.eye(3)
        self._last_action = np.zeros(self.action_size)
        self._held = 0
        #: Wall time of the last step's parts [s] (not in ``info``: not deterministic).
        self.last_timing: dict[str, float] = {}

    # ------------------------------------------------------------------ spaces

    def term_effects(self) -> dict[str, tuple[str, ...]]:
        """The effects each of this environment's terms needs (``image`` only where the
        image is observed)."""
        terms = dict(self.TERM_EFFECTS)
        if self.imager is None:
            terms.pop("image", None)
        return terms

    def _make_imager(self, image: bool | BModeConfig) -> BModeImager | None:
        """The B-mode imager ``image`` asks for (None: no image, never computed)."""
        if image is False:
            return None
        if image is True:
            image = BModeConfig(
                aperture_m=self.imaging.aperture_m, imaging_depth_m=self.imaging.imaging_depth_m
            )
        if not isinstance(image, BModeConfig):
            raise EnvConfigError(
                f"image must be True, False or an envs.ultrasound.BModeConfig; got {image!r}"
            )
        return BModeImager(self.tissue, image)

    def _observation_spaces(self) -> dict[str, spaces.Space]:
        """The common observation terms; tasks add theirs."""
        n = self.joint_count
        image: dict[str, spaces.Space] = {}
        if self.imager is not None:
            shape = (self.imager.config.rows, self.imager.config.cols, 1)
            image["image"] = spaces.Box(0, 255, shape=shape, dtype=np.uint8)
        return image | {
            "probe_pose": spaces.Box(
                np.array([-2.0] * 3 + [-1.0] * 4, dtype=np.float32),
                np.array([2.0] * 3 + [1.0] * 4, dtype=np.float32),
                dtype=np.float32,
            ),
            "wrench": spaces.Box(-WRENCH_LIMIT, WRENCH_LIMIT, shape=(6,), dtype=np.float32),
            "joint_pos": spaces.Box(
                self.names.joint_ranges[:, 0].astype(np.float32),
                self.names.joint_ranges[:, 1].astype(np.float32),
                dtype=np.float32,
            ),
            "joint_vel": spaces.Box(
                -JOINT_VELOCITY_LIMIT, JOINT_VELOCITY_LIMIT, shape=(n,), dtype=np.float32
            ),
        }

    # ------------------------------------------------------------------ episodes

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, NDArray[Any]], dict[str, Any]]:
        """Seed the generators; with domain randomisation, draw this episode's variation and
        its tissue. Tasks extend this (they place the probe and observe)."""
        super().reset(seed=seed)
        if self.randomizer is not None:
            self.randomizer.seed(seed)
            _, variant = self.randomizer.draw()
            self._use_tissue(variant)
        return {}, {}

    def _use_tissue(self, model: tissue.Tissue) -> None:
        """Simulate, image and draw ``model`` from now on (a variant of the nominal tissue:
        same topology, so the scene's drawn surface fits it)."""
        if model is self.tissue:
            return
        model.track_lesions(())
        self.tissue = model
        self.coupling.tissue = model
        if self.imager is not None:
            self.imager = BModeImager(model, self.imager.config)
        if self._renderer is not None:
            self._renderer.tissue = model

    def target_lesions(self, min_depth_m: float | None = None) -> tuple[int, ...]:
        """The lesions an episode may aim at: the task config's ``target_lesions``, else
        :data:`PHANTOM_TARGET_LESIONS` on the built-in phantom, else on other meshes every
        lesion (``min_depth_m`` None) or those from ``min_depth_m`` to 5 mm short of the
        imaging depth under the skin at rest (:meth:`rest_depth`).

        Raises:
            EnvConfigError: ``target_lesions`` names none, or a lesion the mesh lacks.
        """
        lesions = self.tissue.lesions
        wanted = self.task_config.target_lesions
        if wanted is None:
            if self.tissue.spec.mesh_kind() == "level":
                wanted = PHANTOM_TARGET_LESIONS
            elif min_depth_m is None:
                wanted = tuple(lesion.label for lesion in lesions)
            else:
                deepest = self.imaging.imaging_depth_m - 0.005
                wanted = tuple(
                    lesion.label
                    for lesion in lesions
                    if min_depth_m <= self.rest_depth(lesion) <= deepest
                )
        labels = {lesion.label for lesion in lesions}
        if not wanted or not set(wanted) <= labels:
            raise EnvConfigError(
                f"target_lesions must name lesions of this mesh, {sorted(labels)}; got {wanted!r}"
            )
        return tuple(wanted)

    def rest_depth(self, lesion: tissue.Lesion) -> float:
        """The lesion's centre's depth [m] below the probe touching the skin above it at rest,
        along the probe's axis; -1 where no skin lies above it."""
        try:
            position, quat = self.tissue.touching_pose(lesion.rest_centre_m)
        except tissue.TissueInputError:
            return -1.0
        rotation = quat_matrix(quat)
        return float((rotation.T @ (lesion.rest_centre_m - position))[1])

    def _variation_info(self) -> dict[str, Any]:
        """``{"variation": ...}`` for a reset's info under domain randomisation, else {}."""
        if self.randomizer is None or self.randomizer.variation is None:
            return {}
        return {"variation": self.randomizer.variation.as_info()}

    # ------------------------------------------------------------------ the arm

    def _solve_home(self) -> NDArray[np.float64]:
        """Joint angles with the probe hovering over the phantom, pointing down: IK from the
        arm's own keyframe ``home`` where its MJCF has one (its joints' angles), else from
        :data:`HOME_SEED_RAD` (the UR5e's; joints past the sixth at zero)."""
        key = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_KEY, ROBOT_PREFIX + HOME_KEY)
        if key >= 0:
            seed = self.model.key_qpos[key][self.names.joint_qpos].astype(np.float64)
        else:
            seed = np.zeros(self.joint_count)
            seed[: min(6, self.joint_count)] = HOME_SEED_RAD[: self.joint_count]
        rotation = pointing_down()
        q, error = solve_ik(
            self.model, self.data, self.names, np.array(HOME_PROBE_M), rotation, seed
        )
        if error > 1e-5:
            raise EnvConfigError(
                f"the arm cannot hold the probe over the phantom (IK error {error:.3g}); move "
                f"it with robot_base_m or give another robot"
            )
        return q

    def place_probe(self, position: NDArray[np.float64], rotation: NDArray[np.float64]) -> None:
        """Put the arm, at rest, where its probe site has the pose (IK from home); the
        controller then holds that pose and the tissue starts at rest with the probe there."""
        mujoco.mj_resetData(self.model, self.data)
        q, error = solve_ik(self.model, self.data, self.names, position, rotation, self._home)
        if error > 1e-6:
            raise EnvConfigError(f"the start pose is out of the arm's reach (IK error {error:.3g})")
        self.data.qpos[self.names.joint_qpos] = q
        self.data.qvel[:] = 0.0
        mujoco.mj_forward(self.model, self.data)
        if isinstance(self.controller, CartesianImpedance):
            site_rot = self.data.site_xmat[self.names.probe_site].reshape(3, 3)
            self.controller.set_target(self.data.site_xpos[self.names.probe_site], site_rot)
            self.controller.posture = q.copy()
        else:
            self.controller.target_q = q.copy()
        self.controller.update_inertia(self.data)
        # Held still: the controller's torques (gravity compensation) in place, so that the
        # first observation's sensor reads the arm at rest.
        self.data.ctrl[self.names.actuators] = self.controller.torques(self.data)
        mujoco.mj_forward(self.model, self.data)
        self.coupling.reset()
        self._start_pos = self.data.site_xpos[self.names.probe_site].copy()
        self._start_rot = self.data.site_xmat[self.names.probe_site].reshape(3, 3).copy()
        self._last_action = np.zeros(self.action_size)

    def _apply_action(self, action: NDArray[np.float64]) -> None:
        """Move the controller's target by the action (see :class:`ActionConfig`)."""
        if isinstance(self.controller, CartesianImpedance):
            scale = self.action_config
            rotation = self.controller.target_rot
            position = self.controller.target_pos + rotation @ (
                action[:3] * scale.max_translation_m
            )
            turn = np.empty(4)
            mujoco.mju_axisAngle2Quat(turn, *axis_angle(action[3:] * scale.max_rotation_rad))
            local = np.empty(9)
            mujoco.mju_quat2Mat(local, turn)
            rotation = rotation @ local.reshape(3, 3)
            position, rotation = self._clip_target(position, rotation)
            self.controller.set_target(position, rotation)
        else:
            step = action * self.action_config.max_joint_step_rad
            ranges = self.names.joint_ranges
            self.controller.target_q = np.clip(
                self.controller.target_q + step, ranges[:, 0], ranges[:, 1]
            )

    def _clip_target(
        self, position: NDArray[np.float64], rotation: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The probe's target kept in the task's workspace around the start pose: its task
        config's ``workspace_m`` sideways (x, z), ``max_press_m`` in and ``max_lift_m`` out
        (y), and within ``max_turn_rad`` of the start's orientation (else the last target's);
        a task whose config has no workspace is not clipped."""
        cfg = self.task_config
        if not hasattr(cfg, "workspace_m"):
            return position, rotation
        local = self._start_rot.T @ (position - self._start_pos)
        local[0] = np.clip(local[0], -cfg.workspace_m, cfg.workspace_m)
        local[2] = np.clip(local[2], -cfg.workspace_m, cfg.workspace_m)
        local[1] = np.clip(local[1], -cfg.max_lift_m, cfg.max_press_m)
        position = self._start_pos + self._start_rot @ local
        if rotation_angle(rotation, self._start_rot) > cfg.max_turn_rad:
            rotation = self.controller.target_rot  # type: ignore[union-attr]
        return position, rotation

    def horizon(self) -> int:
        """The episode's length [steps]: ``max_episode_steps`` as made, else the task's."""
        spec = self.spec
        if spec is not None and spec.max_episode_steps is not None:
            return int(spec.max_episode_steps)
        return self.episode_steps

    def failure_reward(self) -> float:
        """The ``failure`` reward term on a failing last step: the task config's
        ``failure_reward`` where given, else -(horizon + 1), so that with every other
        step's reward in [-1, 0] a failing episode returns less than any other."""
        given = getattr(self.task_config, "failure_reward", None)
        return -float(self.horizon() + 1) if given is None else float(given)

    def _make_finite(self) -> None:
        """After a non-finite arm state (the episode ends), leave the arm at the start pose."""
        self.place_probe(self._start_pos, self._start_rot)

    # ------------------------------------------------------------------ stepping

    def step(
        self, action: Any
    ) -> tuple[dict[str, NDArray[Any]], float, bool, bool, dict[str, Any]]:
        """One step of every task: the action moves the arm and the tissue; the common
        failures (the tissue step not ``ok``, the contact force over the task's
        ``hard_force_n``, a non-finite arm) are found; then the task's declarations track
        its state (:meth:`_track`), judge success (:meth:`_succeeded`) and give the reward's
        terms (:meth:`_reward_terms`), whose sum is the reward. Terminated on success or
        failure; truncation is the TimeLimit wrapper's (``max_episode_steps``)."""
        values = self._check_action(action)
        step = self._advance(values)
        observed_from = time.perf_counter()
        state = StepState(
            action=values,
            tissue_step=step,
            force_n=self.contact_force_n(step),
            normal_n=self.normal_force_n(step),
            finite=bool(np.isfinite(self.data.qpos).all() and np.isfinite(self.data.qvel).all()),
        )
        failure: dict[str, Any] = {}
        if step.status is not tissue.StepStatus.OK:
            failure["tissue_unstable"] = step.status.value
        if state.force_n > self.task_config.hard_force_n:
            failure["force_exceeded"] = True
        if not state.finite:
            failure["robot_unstable"] = True
        self._track(state)
        success = self._succeeded(state, bool(failure))
        terms = self._reward_terms(state, success, bool(failure))
        reward = float(sum(terms.values()))
        self._last_action = values
        terminated = success or bool(failure)
        if not state.finite:
            self._make_finite()
        observation = self._observation()
        info = self._info(step, terms, success, failure)
        self.last_timing["observation_s"] = time.perf_counter() - observed_from
        return observation, reward, terminated, False, info

    # A task declares these (and its reset and observation spaces).

    def _track(self, state: StepState) -> None:
        """Update the task's own state from the step (a lesion's place, a path's progress)."""

    def _succeeded(self, state: StepState, failed: bool) -> bool:
        """Whether the episode succeeds on this step (never on a failing one)."""
        raise NotImplementedError

    def _reward_terms(self, state: StepState, success: bool, failed: bool) -> dict[str, float]:
        """The reward's named terms (weighted; the reward is their sum)."""
        raise NotImplementedError

    def _observation(self) -> dict[str, NDArray[Any]]:
        """The observation (the common terms, :meth:`_common_observation`, and the task's)."""
        raise NotImplementedError

    def _info(
        self,
        step: tissue.TissueStep | None,
        terms: dict[str, float],
        success: bool,
        failure: dict[str, Any] | None = None,
    ) -> dict[str, Any]:
        """The step's ``info``: success, the reward's terms, the task's figures, the failure."""
        raise NotImplementedError

    def _held_for(self, in_band: bool, failed: bool, steps: int) -> bool:
        """Count the steps in a row spent in the goal's band without failing
        (``self._held``, zeroed by the task's reset); True once they reach ``steps``."""
        self._held = self._held + 1 if in_band and not failed else 0
        return self._held >= steps

    def _check_action(self, action: Any) -> NDArray[np.float64]:
        values = np.asarray(action, dtype=np.float64).reshape(-1)
        if values.shape != (self.action_size,):
            raise EnvConfigError(
                f"an action is {self.action_size} numbers in [-1, 1] "
                f"({self.controller_config.mode} mode); got shape {np.shape(action)}"
            )
        if not np.all(np.isfinite(values)):
            raise EnvConfigError(
                f"an action must be finite; got {values.tolist()} (NaN or inf: check the policy)"
            )
        return np.clip(values, -1.0, 1.0)  # documented: actions beyond the box are clipped

    def _advance(self, action: NDArray[np.float64]) -> tissue.TissueStep:
        """Move the target, step the arm and the tissue (timings into :attr:`last_timing`)."""
        started = time.perf_counter()
        self._apply_action(action)
        self.controller.update_inertia(self.data)
        controller_s = time.perf_counter() - started

        def control(data: mujoco.MjData) -> NDArray[np.float64]:
            nonlocal controller_s
            tic = time.perf_counter()
            torques = self.controller.torques(data)
            controller_s += time.perf_counter() - tic
            return torques

        step = self.coupling.step(control)
        timing = self.coupling.timing
        self.last_timing = {
            "controller_s": controller_s,
            "robot_s": max(0.0, timing["substeps_s"] - controller_s),
            "tissue_s": timing["tissue_s"] + timing["stiffness_s"],
            "stiffness_s": timing["stiffness_s"],
            "observation_s": 0.0,
        }
        return step

    # ------------------------------------------------------------------ observations

    def _common_observation(self) -> dict[str, NDArray[Any]]:
        site = self.names.probe_site
        quat = np.empty(4)
        mujoco.mju_mat2Quat(quat, self.data.site_xmat[site])
        if quat[0] < 0.0:
            quat = -quat  # one of the two: w >= 0
        pose = np.concatenate([self.data.site_xpos[site], quat])
        wrench = self.sensed_wrench()
        if self.randomizer is not None:
            wrench = self.randomizer.noisy_wrench(wrench)
            shift, turn = self.randomizer.pose_noise()
            seen = turn_matrix(turn) @ self.data.site_xmat[site].reshape(3, 3)
            reported = np.empty(4)
            mujoco.mju_mat2Quat(reported, seen.reshape(-1))
            if reported[0] < 0.0:
                reported = -reported
            pose = np.concatenate([self.data.site_xpos[site] + shift, reported])
        return {
            "probe_pose": pose.astype(np.float32),
            "wrench": np.clip(wrench, -WRENCH_LIMIT, WRENCH_LIMIT).astype(np.float32),
            "joint_pos": self.data.qpos[self.names.joint_qpos].astype(np.float32),
            "joint_vel": np.clip(
                self.data.qvel[self.names.joint_dof], -JOINT_VELOCITY_LIMIT, JOINT_VELOCITY_LIMIT
            ).astype(np.float32),
        } | self._image_observation(quat)

    def _image_observation(self, quat: NDArray[np.float64]) -> dict[str, NDArray[np.uint8]]:
        """The B-mode image of the slice under the probe, (rows, cols, 1), where asked for:
        the tissue as it is now, seen from the probe's pose, black without contact."""
        if self.imager is None:
            return {}
        return {"image": self._ultrasound(quat)[:, :, None]}

    def _ultrasound(self, quat: NDArray[np.float64]) -> NDArray[np.uint8]:
        """The B-mode frame at the probe's pose ``quat`` (w, x, y, z) now, (rows, cols)."""
        assert self.imager is not None
        step = self.coupling.last_step
        force = 0.0 if step is None else float(np.linalg.norm(step.force_world_n))
        position = self.data.site_xpos[self.names.probe_site]
        return self.imager.image(self.tissue, position, quat, force > TOUCH_FORCE_N)

    def _beside(self, frame: NDArray[np.uint8]) -> NDArray[np.uint8]:
        """``frame`` with the B-mode image to its right, scaled to its height at the
        image's aspect (aperture by imaging depth), grey as RGB."""
        assert self.imager is not None
        quat = np.empty(4)
        mujoco.mju_mat2Quat(quat, self.data.site_xmat[self.names.probe_site])
        config = self.imager.config
        return beside(frame, self._ultrasound(quat), config.aperture_m / config.imaging_depth_m)

    def sensed_wrench(self) -> NDArray[np.float64]:
        """The F/T sensor's wrench in the probe frame (see
        :func:`envs.observations.sensed_wrench`), (6,)."""
        return sensed_wrench(self.model, self.data, self.names)

    def tissue_step_wrench(self) -> NDArray[np.float64]:
        """The last tissue step's wrench on the probe, (6,): force [N], torque [N m] about
        the probe origin, world frame (zeros before the first step)."""
        step = self.coupling.last_step
        if step is None:
            return np.zeros(6)
        return np.concatenate([step.force_world_n, step.torque_world_nm])

    def contact_force_n(self, step: tissue.TissueStep | None) -> float:
        """The contact force's magnitude [N] (the tissue's, on the probe)."""
        if step is None:
            return 0.0
        return float(np.linalg.norm(step.force_world_n))

    def normal_force_n(self, step: tissue.TissueStep | None) -> float:
        """The contact force along the probe's pressing axis [N] (positive pressing)."""
        if step is None:
            return 0.0
        _, rotation = self.probe_pose()
        return float(-step.force_world_n @ rotation[:, 1])

    def probe_pose(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The probe site's position [m] and rotation matrix, world frame."""
        return self.coupling.probe_pose()

    # ------------------------------------------------------------------ rendering

    def render(self) -> NDArray[np.uint8] | None:
        if self.render_mode is None:
            gym.logger.warn("render() called without a render_mode; pass render_mode=...")
            return None
        if self._renderer is None:
            width, height = self._frame_size
            self._renderer = SceneRenderer(
                self.scene_config, self.tissue, width, height, self.camera_name
            )
        if self.render_mode == "rgb_array":
            frame = self._renderer.frame(self.data)
            return frame if self.imager is None else self._beside(frame)
        self._renderer.show(self.data)
        return None

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
