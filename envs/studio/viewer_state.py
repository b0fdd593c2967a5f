"""What the probegym viewer plugins share on the viewer thread, and the plugin that fills it
from the simulation's messages.

:class:`SimulationLink` receives :class:`~envs.studio.protocol.SceneInfoEvent`,
:class:`~envs.studio.protocol.ProbeStatusSnapshot` and
:class:`~envs.studio.protocol.UltrasoundSnapshot` into one :class:`ViewerState` that the
panels and overlays read when they build their frame; it also counts the viewer's frames
(its rate is shown, and printed with ``stats_every_s``). Everything here runs on the viewer
thread and does O(1) work per message: the viewer keeps its 60 Hz whatever the tissue costs.
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np
from mujoco.studio import messages, plugin

from envs.studio.protocol import ProbeStatusSnapshot, SceneInfoEvent, UltrasoundSnapshot

#: How much simulated time the live plot keeps [s].
HISTORY_S = 10.0
#: How often the panels' figures change [s of wall time]: the web viewer sends a window's
#: drawing again only when it changed, so ten updates a second instead of sixty keep the
#: UI stream small (on a slow client a busy stream lags behind the scene).
PANEL_REFRESH_S = 0.1
#: Views the camera can take: the image plane from the side (the dent in profile), the
#: scene's overview camera, or wherever the user moves it.
VIEWS = ("side", "overview", "free")


@dataclass
class ViewerState:
    """The viewer plugins' shared picture of the simulation (viewer thread only).

    Attributes:
        info: the scene built (None until the simulation says).
        status: the latest status (the overlays draw it every frame).
        history: (time [s], force magnitude [N], lesion depth [mm]) of the current episode's
            recent steps, at most :data:`HISTORY_S` of simulated time.
        shown: the status the panels show, ``status`` at most every
            :data:`PANEL_REFRESH_S`.
        shown_history: likewise, ``history`` as three lists (times, forces, depths).
        shown_frame_rate_hz: likewise, ``frame_rate_hz``.
        image: the latest ultrasound image (None before the first).
        image_serial: how many images arrived (a panel uploads when it changes).
        view: the camera's view, one of :data:`VIEWS`.
        frames: viewer frames built so far.
        frame_rate_hz: the viewer's frame rate, recent average [Hz].
        placed_for: the page size [pixels] each panel was last placed for.
    """

    info: SceneInfoEvent | None = None
    status: ProbeStatusSnapshot = field(default_factory=ProbeStatusSnapshot)
    history: deque[tuple[float, float, float]] = field(default_factory=deque)
    shown: ProbeStatusSnapshot = field(default_factory=ProbeStatusSnapshot)
    shown_history: tuple[list[float], list[float], list[float]] = ([], [], [])
    shown_frame_rate_hz: float = 0.0
    image: UltrasoundSnapshot | None = None
    image_serial: int = 0
    view: str = "side"
    frames: int = 0
    frame_rate_hz: float = 0.0
    placed_for: dict[str, tuple[float, float]] = field(default_factory=dict)

    def force_n(self, shown: bool = False) -> float:
        """The contact force's magnitude [N], now or as shown."""
        status = self.shown if shown else self.status
        return float(np.linalg.norm(status.force_world_n))

    def refresh_shown(self) -> None:
        """What the panels show, from the latest."""
        self.shown = self.status
        self.shown_frame_rate_hz = self.frame_rate_hz
        self.shown_history = (
            [row[0] for row in self.history],
            [row[1] for row in self.history],
            [row[2] for row in self.history],
        )


class SimulationLink(plugin.ViewerPlugin):
    """Fills a :class:`ViewerState` from the simulation's messages (module docstring).

    Args:
        state: the state the panels share.
        stats_every_s: print a one-line status to stdout this often [s of wall time]
            (0: never); for headless runs and logs.
    """

    def __init__(self, state: ViewerState, stats_every_s: float = 0.0) -> None:
        self.state = state
        self.stats_every_s = float(stats_every_s)
        self._frame_times: deque[float] = deque(maxlen=120)
        self._next_print = 0.0
        self._next_refresh = 0.0

    @messages.handler
    def on_scene_info(self, event: SceneInfoEvent) -> None:
        self.state.info = event
        if not event.error:
            self.state.history.clear()

    @messages.handler
    def on_status(self, snapshot: ProbeStatusSnapshot) -> None:
        state = self.state
        history = state.history
        if snapshot.episode != state.status.episode or (
            history and snapshot.time_s < history[-1][0]
        ):
            history.clear()
        state.status = snapshot
        depth_mm = snapshot.lesion_depth_m * 1e3
        history.append((snapshot.time_s, state.force_n(), depth_mm))
        while history and history[0][0] < snapshot.time_s - HISTORY_S:
            history.popleft()

    @messages.handler
    def on_image(self, snapshot: UltrasoundSnapshot) -> None:
        self.state.image = snapshot
        self.state.image_serial += 1

    @messages.handler(priority=messages.Priority.LIBRARY)
    def on_update(self, _: messages.UpdateEvent) -> None:
        now = time.perf_counter()
        state = self.state
        state.frames += 1
        self._frame_times.append(now)
        if len(self._frame_times) >= 2:
            span = self._frame_times[-1] - self._frame_times[0]
            state.frame_rate_hz = (len(self._frame_times) - 1) / max(span, 1e-9)
        if now >= self._next_refresh and state.status is not state.shown:
            # Only when the simulation moved on: a paused scene's panels stand still, and
            # so does the UI stream.
            self._next_refresh = now + PANEL_REFRESH_S
            state.refresh_shown()
        if self.stats_every_s > 0.0 and now >= self._next_print:
            self._next_print = now + self.stats_every_s
            print(stats_line(state), flush=True)


def stats_line(state: ViewerState) -> str:
    """One line of status: the viewer's frames and rate, the simulated time and its
    real-time factor, the tissue step, the force and the lesion depth."""
    status = state.status
    depth = status.lesion_depth_m
    depth_text = "-" if math.isnan(depth) else f"{depth * 1e3:.1f} mm"
    return (
        f"probegym view: frames {state.frames}, viewer {state.frame_rate_hz:.0f} Hz, "
        f"episode {status.episode} t {status.time_s:.2f} s ({status.realtime:.2f}x real time"
        f"{', paused' if status.paused else ''}), "
        f"tissue step {status.tissue_step_s * 1e3:.1f} ms {status.tissue_status}, "
        f"force {state.force_n():.2f} N, lesion depth {depth_text}, "
        f"press {status.offset_m[1] * 1e3:.1f} mm"
        + (f", error: {status.error}" if status.error else "")
    )
