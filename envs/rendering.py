"""Drawing the coupled scene: the arm, the probe and the deformed breast.

The physics steps a scene without the breast (:mod:`envs.scene`); drawing uses a second
compiled scene with it: one mocap body per surface vertex and a display-only flex per region
(the skin see-through, the lesions red). Before a frame, the arm's joint angles are copied
over, the vertices moved to the tissue's deformed surface and the kinematics computed; the
surface is updated only when a frame is drawn. Offscreen on a CPU works with
``MUJOCO_GL=egl`` or ``osmesa`` (Debian's Mesa); shadows are off (a 480 x 480 frame took
30-36 ms without them and 170 ms with the default shadow map on these machines).
"""

from __future__ import annotations

from typing import Any

import mujoco
import numpy as np
from numpy.typing import NDArray

import tissue
from envs.errors import EnvConfigError
from envs.scene import SceneConfig, build_scene

CAMERAS = ("overview", "probe_side")


class SceneRenderer:
    """Frames of the coupled scene (see the module docstring).

    Args:
        scene: the layout (as the physics scene's).
        tissue_model: the tissue whose surface is drawn.
        width, height: frame size [pixels].
        camera_name: ``overview`` or ``probe_side``.
    """

    def __init__(
        self,
        scene: SceneConfig,
        tissue_model: tissue.Tissue,
        width: int,
        height: int,
        camera_name: str,
    ) -> None:
        if camera_name not in CAMERAS:
            raise EnvConfigError(
                f"unknown camera_name {camera_name!r}; choose one of {', '.join(CAMERAS)}"
            )
        self.tissue = tissue_model
        self.model = build_scene(scene, tissue_model.probe_shape, tissue_model.surface())
        self.data = mujoco.MjData(self.model)
        self.camera_name = camera_name
        self.width, self.height = width, height
        self._renderer: mujoco.Renderer | None = None
        self._viewer: Any = None
        first = self.model.body("breast/v0").id
        self._mocap = int(self.model.body_mocapid[first])

    def sync(self, physics: mujoco.MjData) -> None:
        """Copy the arm's state and move the breast's vertices to the tissue's surface."""
        self.data.qpos[:] = physics.qpos
        self.data.qvel[:] = physics.qvel
        vertices = self.tissue.surface().vertices_m
        self.data.mocap_pos[self._mocap : self._mocap + vertices.shape[0]] = vertices
        mujoco.mj_forward(self.model, self.data)

    def frame(self, physics: mujoco.MjData) -> NDArray[np.uint8]:
        """An RGB frame, (height, width, 3) uint8."""
        self.sync(physics)
        if self._renderer is None:
            self._renderer = mujoco.Renderer(self.model, self.height, self.width)
        self._renderer.update_scene(self.data, self.camera_name)
        return self._renderer.render()

    def show(self, physics: mujoco.MjData) -> None:
        """Draw in MuJoCo's interactive viewer (opened at the first call)."""
        self.sync(physics)
        if self._viewer is None:
            import mujoco.viewer

            self._viewer = mujoco.viewer.launch_passive(self.model, self.data)
        self._viewer.sync()

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        if self._viewer is not None:
            self._viewer.close()
            self._viewer = None


def beside(frame: NDArray[np.uint8], image: NDArray[np.uint8], aspect: float) -> NDArray[np.uint8]:
    """``frame`` (h, w, 3) with the grey ``image`` (rows, cols) to its right, scaled
    (nearest) to the frame's height at ``aspect`` (width / height: aperture over imaging
    depth), as RGB."""
    height = frame.shape[0]
    width = max(1, round(height * aspect))
    rows = np.minimum((np.arange(height) * image.shape[0]) // height, image.shape[0] - 1)
    cols = np.minimum((np.arange(width) * image.shape[1]) // width, image.shape[1] - 1)
    scaled = image[np.ix_(rows, cols)]
    return np.concatenate([frame, np.repeat(scaled[:, :, None], 3, axis=2)], axis=1)
