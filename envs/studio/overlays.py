"""The probegym scene overlays in MuJoCo Studio's viewer, and its camera.

:class:`SceneOverlay` draws, as per-frame decorative geoms (``viewer.extra_geoms``, not part
of the model), the outline of the ultrasound image plane under the probe (the probe frame's
z = 0 plane: lateral +- aperture / 2, depth 0 to the imaging depth) and an arrow of the
tissue's force on the probe, from the probe's face, 1 cm per newton (capped at 10 cm).

It also places the camera when the view asks for it: ``side`` looks at the start of the
episode's contact along the probe's elevation axis (so the image plane is seen face-on and
the dent the probe makes is seen in profile), from a little below the skin under the probe
and from the side of the arm's base (the arm out of the picture);
``overview`` is the scene's ``overview`` camera; ``free`` leaves the camera to the mouse.
The camera is placed when the view changes, when a model arrives and when an episode
starts; in between the user may move it.

The breast itself needs no overlay: the drawing scene's flexes (the skin see-through, the
lesions red) move with the tissue in the streamed state.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np
from mujoco.studio import messages, plugin
from numpy.typing import NDArray

from envs.scene import ROBOT_PREFIX
from envs.studio.viewer_state import ViewerState

#: The image plane's outline: colour (RGBA) and half-thickness [m].
PLANE_RGBA = (0.1, 0.85, 0.35, 0.9)
PLANE_RADIUS_M = 0.0006
#: The force arrow: colour, length per newton [m/N], the longest [m] and its width [m].
ARROW_RGBA = (1.0, 0.85, 0.1, 1.0)
ARROW_M_PER_N = 0.01
ARROW_MAX_M = 0.1
ARROW_WIDTH_M = 0.004
#: Forces under this are not drawn [N].
ARROW_MIN_N = 0.05
#: The side view: distance [m] and elevation [deg] (positive: from a little below the
#: contact, so the skin's outline stands against the sky), and how far into the tissue it
#: looks along the probe's axis [m].
SIDE_DISTANCE_M = 0.3
SIDE_ELEVATION_DEG = 8.0
SIDE_LOOK_DEPTH_M = 0.005
OVERVIEW_DISTANCE_M = 0.85


class SceneOverlay(plugin.ViewerPlugin):
    """The image plane's outline, the force arrow and the camera (module docstring).

    Args:
        state: the shared viewer state.
    """

    def __init__(self, state: ViewerState) -> None:
        self.state = state
        self._placed: tuple[str, int] | None = None

    @messages.handler
    def on_post_model(self, _: messages.PostModelEvent) -> None:
        self._placed = None

    @messages.handler
    def on_update(self, _: messages.UpdateEvent) -> None:
        self.place_camera()
        geoms = self.viewer.extra_geoms
        geoms.clear()
        status, info = self.state.status, self.state.info
        if info is None or status.episode == 0:
            return
        position = np.asarray(status.probe_pos_world)
        rotation = np.asarray(status.probe_rot_world).reshape(3, 3)
        half = 0.5 * info.aperture_m
        corners = [
            position + rotation @ np.array([x, y, 0.0])
            for x, y in ((-half, 0.0), (half, 0.0), (half, info.imaging_depth_m),
                         (-half, info.imaging_depth_m))
        ]  # fmt: skip
        for a, b in zip(corners, corners[1:] + corners[:1], strict=True):
            geoms.append(
                _connector(mujoco.mjtGeom.mjGEOM_CAPSULE, PLANE_RADIUS_M, a, b, PLANE_RGBA)
            )
        force = np.asarray(status.force_world_n)
        magnitude = float(np.linalg.norm(force))
        if magnitude > ARROW_MIN_N:
            length = min(ARROW_M_PER_N * magnitude, ARROW_MAX_M)
            tip = position + force / magnitude * length
            geoms.append(_connector(mujoco.mjtGeom.mjGEOM_ARROW, ARROW_WIDTH_M, position, tip,
                                    ARROW_RGBA))  # fmt: skip

    def place_camera(self) -> None:
        """Put the camera where the view asks, once per view, model and episode."""
        state = self.state
        key = (state.view, state.status.episode)
        if state.view == "free" or key == self._placed or state.status.episode == 0:
            return
        self._placed = key
        camera = self.viewer.camera
        camera.type = mujoco.mjtCamera.mjCAMERA_FREE
        if state.view == "side":
            status = state.status
            start = np.asarray(status.start_pos_world)
            rotation = np.asarray(status.start_rot_world).reshape(3, 3)
            lookat = start + rotation[:, 1] * SIDE_LOOK_DEPTH_M
            base = _robot_base(self.viewer.model, self.viewer.data)
            azimuth = _side_azimuth(lookat, rotation[:, 2], base)
            _set_camera(camera, lookat, SIDE_DISTANCE_M, azimuth, SIDE_ELEVATION_DEG)
        else:
            model = self.viewer.model
            try:
                index = model.camera("overview").id
            except KeyError:
                return
            forward = -model.cam_mat0[index].reshape(3, 3)[:, 2]
            lookat = model.cam_pos0[index] + forward * OVERVIEW_DISTANCE_M
            azimuth = math.degrees(math.atan2(forward[1], forward[0]))
            elevation = math.degrees(math.asin(float(np.clip(forward[2], -1.0, 1.0))))
            _set_camera(camera, lookat, OVERVIEW_DISTANCE_M, azimuth, elevation)


def _side_azimuth(
    lookat: NDArray[np.float64], elevation_axis: NDArray[np.float64], base: NDArray[np.float64]
) -> float:
    """The azimuth [deg] of a camera looking along the probe's elevation axis (its
    horizontal part), from the side nearer the arm's base: the arm then stands behind the
    camera, not in the picture."""
    direction = np.array([elevation_axis[0], elevation_axis[1], 0.0])
    if float(np.linalg.norm(direction)) < 1e-6:
        direction = np.array([0.0, 1.0, 0.0])
    direction /= np.linalg.norm(direction)
    # The camera stands at lookat - distance * forward.
    if np.linalg.norm((lookat - direction - base)[:2]) > np.linalg.norm(
        (lookat + direction - base)[:2]
    ):
        direction = -direction
    return math.degrees(math.atan2(direction[1], direction[0]))


def _robot_base(model: mujoco.MjModel, data: mujoco.MjData) -> NDArray[np.float64]:
    """Where the arm's root body is [m] (the world origin if there is no arm)."""
    for body in range(1, model.nbody):
        if model.body_parentid[body] == 0 and model.body(body).name.startswith(ROBOT_PREFIX):
            return np.array(data.xpos[body])
    return np.zeros(3)


def _set_camera(
    camera: mujoco.MjvCamera,
    lookat: NDArray[np.float64],
    distance: float,
    azimuth_deg: float,
    elevation_deg: float,
) -> None:
    camera.lookat[:] = lookat
    camera.distance = distance
    camera.azimuth = azimuth_deg
    camera.elevation = elevation_deg


def _connector(
    kind: mujoco.mjtGeom,
    width: float,
    start: NDArray[np.float64],
    end: NDArray[np.float64],
    rgba: tuple[float, float, float, float],
) -> mujoco.MjvGeom:
    geom = mujoco.MjvGeom()
    mujoco.mjv_initGeom(
        geom,
        int(kind),
        np.zeros(3),
        np.zeros(3),
        np.eye(3).reshape(-1),
        np.asarray(rgba, dtype=np.float32),
    )
    mujoco.mjv_connector(geom, int(kind), width, np.asarray(start), np.asarray(end))
    return geom
