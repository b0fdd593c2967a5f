"""The probegym viewer panels (Dear ImGui windows in MuJoCo Studio's viewer).

- :class:`ControlPanel`: choose the task, contact method and mesh; reset; pause; drive the
  probe by teleoperation (sliders for its pose from the episode's start, or keys) or let the
  policy drive; choose the camera's view.
- :class:`UltrasoundPanel`: the B-mode image of the slice under the probe, uploaded as a
  texture when a new one arrives.
- :class:`ForcePanel`: the contact force now (a bar and its value) and a live plot of the
  contact force and the target lesion's depth against time.
- :class:`StatusPanel`: the contact method, mesh, tissue step time, stability, real-time
  factor and the viewer's frame rate.

Keys (when no text field has the keyboard): W/S press in / lift along the probe's axis, A/D
move along the face (lateral), Q/E move out of the image plane (elevation), 1 mm a press
(Shift: 5 mm; the sliders move it continuously); R resets the episode, Space pauses.

Panels only read :class:`~envs.studio.viewer_state.ViewerState` and send messages to the
simulation: no panel waits on the simulation, which runs on its own thread.
"""

from __future__ import annotations

import math

import numpy as np
from mujoco.studio import messages, plugin
from mujoco.studio.dear_imgui import dear_imgui as imgui
from mujoco.studio.implot import implot

from envs.studio.protocol import (
    POLICY,
    TELEOP,
    ChooseSceneEvent,
    ControlSnapshot,
    ResetEpisodeEvent,
)
from envs.studio.viewer_state import HISTORY_S, VIEWS, ViewerState

#: The force bar's colour (RGBA in [0, 1]); the browser test finds the bar by it.
FORCE_BAR_RGBA = (0.85, 0.15, 0.75, 1.0)
#: The force at which the bar is full [N].
FORCE_BAR_FULL_N = 10.0
#: The plot's smallest force range [N] and depth span [mm] (a steady value is a flat line,
#: not noise magnified).
PLOT_MIN_FORCE_N = 1.0
PLOT_MIN_DEPTH_MM = 10.0
#: Slider ranges: translation [mm] (lateral, press, elevation) and rotation [deg].
OFFSET_RANGE_MM = ((-30.0, 30.0), (-20.0, 35.0), (-30.0, 30.0))
TURN_RANGE_DEG = 30.0
#: How far a key press moves the probe's target [mm] (with Shift: KEY_SHIFT_FACTOR times).
KEY_STEP_MM = 1.0
KEY_SHIFT_FACTOR = 5.0

#: The status bar the web client draws at the bottom of the page [pixels].
_BOTTOM_BAR_PX = 36.0
_MARGIN_PX = 10.0
_CONTROL_WIDTH = 330.0
_STATUS_SIZE = (330.0, 232.0)
_ULTRASOUND_SIZE = (250.0, 330.0)
_FORCE_SIZE = (440.0, 270.0)
_VIEW_LABELS = {"side": "side (image plane)", "overview": "overview", "free": "free (mouse)"}
_AXIS_KEYS = (
    (imgui.Key.D, imgui.Key.A),
    (imgui.Key.W, imgui.Key.S),
    (imgui.Key.E, imgui.Key.Q),
)
_OFFSET_LABELS = ("lateral [mm]", "press [mm]", "elevation [mm]")
_TURN_LABELS = ("tilt [deg]", "rotate [deg]", "rock [deg]")


def _display() -> tuple[float, float]:
    size = imgui.GetIO().DisplaySize
    return float(size.x), float(size.y)


def _place(state: ViewerState, name: str, x: float, y: float, size: tuple[float, float]) -> None:
    """The next window's position and size: set at first and whenever the browser's page
    changes size (the first frames come before the browser reports its size); in between
    the user may move and resize it."""
    display = _display()
    cond = imgui.Cond.FirstUseEver
    if state.placed_for.get(name) != display:
        state.placed_for[name] = display
        cond = imgui.Cond.Always
    imgui.SetNextWindowPos(imgui.Vec2(x, y), cond)
    imgui.SetNextWindowSize(imgui.Vec2(*size), cond)


class ControlPanel(plugin.ViewerPlugin):
    """Scene choice, episode, drive mode, probe pose and view (module docstring).

    Args:
        state: the shared viewer state.
    """

    def __init__(self, state: ViewerState) -> None:
        self.state = state
        self.mode = TELEOP
        self.paused = False
        self.offset_mm = [0.0, 0.0, 0.0]
        self.turn_deg = [0.0, 0.0, 0.0]
        self.choice = [0, 0, 0]  # indices into env_ids, contacts, meshes
        self._episode = -1
        self._info_seen: object = None
        self._sent: ControlSnapshot | None = None

    # ------------------------------------------------------------------ data

    def _zero_pose(self) -> None:
        self.offset_mm = [0.0, 0.0, 0.0]
        self.turn_deg = [0.0, 0.0, 0.0]

    def snapshot(self) -> ControlSnapshot:
        """The controls as the simulation takes them (SI units)."""
        x, y, z = (v * 1e-3 for v in self.offset_mm)
        tilt, rotate, rock = (math.radians(v) for v in self.turn_deg)
        return ControlSnapshot(self.mode, self.paused, (x, y, z), (tilt, rotate, rock))

    def _send_if_changed(self) -> None:
        snapshot = self.snapshot()
        if snapshot != self._sent:
            self.viewer.send_to_sim(snapshot)
            self._sent = snapshot

    def reset_episode(self) -> None:
        """Ask for a new episode; the pose sliders go back to the start."""
        self._zero_pose()
        self.viewer.send_to_sim(ResetEpisodeEvent())
        self._send_if_changed()

    @messages.handler
    def on_update(self, _: messages.UpdateEvent) -> None:
        """Follow the simulation (a new episode, the policy's pose) and apply held keys."""
        state = self.state
        status = state.status
        if state.info is not None and state.info is not self._info_seen:
            self._info_seen = state.info
            info = state.info
            self.choice = [
                _index(info.env_ids, info.env_id),
                _index(info.contacts, info.contact),
                _index(info.meshes, info.mesh),
            ]
            if self.mode == POLICY and info.env_id not in info.policy_envs:
                self.mode = TELEOP
        if status.episode != self._episode:
            self._episode = status.episode
            if self.mode == TELEOP:
                self._zero_pose()
        shown = state.shown
        if shown.mode == POLICY and self.mode == POLICY and shown.episode == status.episode:
            # Mirror the policy's target, so that taking over continues from there.
            self.offset_mm = [v * 1e3 for v in shown.offset_m]
            self.turn_deg = [math.degrees(v) for v in shown.turn_rad]
        io = imgui.GetIO()
        if not io.WantCaptureKeyboard:
            self._keys(bool(io.KeyShift))
        self._send_if_changed()

    def _keys(self, fast: bool) -> None:
        if imgui.IsKeyPressed(imgui.Key.R, False):
            self.reset_episode()
        if imgui.IsKeyPressed(imgui.Key.Space, False):
            self.paused = not self.paused
        if self.mode != TELEOP:
            return
        step = KEY_STEP_MM * (KEY_SHIFT_FACTOR if fast else 1.0)
        for axis, (plus, minus) in enumerate(_AXIS_KEYS):
            # One step a press, no repeat: over a slow link a press can reach the viewer
            # looking held for seconds, and a repeat would run on.
            move = float(imgui.IsKeyPressed(plus, False)) - float(imgui.IsKeyPressed(minus, False))
            if move:
                low, high = OFFSET_RANGE_MM[axis]
                self.offset_mm[axis] = float(np.clip(self.offset_mm[axis] + move * step, low, high))

    # ------------------------------------------------------------------ layout

    @messages.handler
    def on_build_gui(self, _: messages.BuildGuiEvent) -> None:
        _, height = _display()
        # As tall as the page leaves above the status panel (it scrolls on a small page).
        tall = max(200.0, height - _STATUS_SIZE[1] - _BOTTOM_BAR_PX - 2.0 * _MARGIN_PX)
        _place(self.state, "Probe controls", _MARGIN_PX, _MARGIN_PX, (_CONTROL_WIDTH, tall))
        if imgui.Begin("Probe controls")[0]:
            self.build_scene_gui()
            self.build_drive_gui()
            self.build_pose_gui()
            self.build_view_gui()
        imgui.End()
        self._send_if_changed()

    def build_scene_gui(self) -> None:
        info = self.state.info
        imgui.SeparatorText("Scene")
        if info is None:
            imgui.TextUnformatted("waiting for the simulation...")
            return
        lists = (info.env_ids, info.contacts, tuple(str(m) for m in info.meshes))
        for index, (label, items) in enumerate(
            zip(("task", "contact", "mesh"), lists, strict=True)
        ):
            changed, value = imgui.Combo(label, self.choice[index], list(items))
            if changed:
                self.choice[index] = int(value)
        if imgui.Button("Build scene"):
            self._zero_pose()
            self.viewer.send_to_sim(
                ChooseSceneEvent(
                    info.env_ids[self.choice[0]],
                    info.contacts[self.choice[1]],
                    info.meshes[self.choice[2]],
                )
            )
        if info.error:
            imgui.TextWrapped(f"Not built: {info.error}")

    def build_drive_gui(self) -> None:
        info = self.state.info
        imgui.SeparatorText("Drive")
        if imgui.Button("Reset episode (R)"):
            self.reset_episode()
        imgui.SameLine()
        if imgui.Button("Play (Space)" if self.paused else "Pause (Space)"):
            self.paused = not self.paused
        if imgui.RadioButton("Teleoperate", self.mode == TELEOP):
            self.mode = TELEOP
        imgui.SameLine()
        has_policy = info is not None and info.env_id in info.policy_envs
        imgui.BeginDisabled(not has_policy)
        if imgui.RadioButton("Policy", self.mode == POLICY):
            self.mode = POLICY
        imgui.EndDisabled()
        if info is not None:
            label = info.policy_label if has_policy else "none for this task"
            imgui.TextUnformatted(f"policy: {label}")

    def build_pose_gui(self) -> None:
        info = self.state.info
        imgui.SeparatorText("Probe pose from the start")
        teleop = self.mode == TELEOP and (info is None or info.teleop)
        imgui.BeginDisabled(not teleop)
        for axis, label in enumerate(_OFFSET_LABELS):
            low, high = OFFSET_RANGE_MM[axis]
            changed, value = imgui.SliderFloat(label, self.offset_mm[axis], low, high, "%.1f")
            if changed:
                self.offset_mm[axis] = float(value)
        for axis, label in enumerate(_TURN_LABELS):
            changed, value = imgui.SliderFloat(
                label, self.turn_deg[axis], -TURN_RANGE_DEG, TURN_RANGE_DEG, "%.1f"
            )
            if changed:
                self.turn_deg[axis] = float(value)
        if imgui.Button("Back to the start pose"):
            self._zero_pose()
        imgui.EndDisabled()
        if info is not None and not info.teleop:
            imgui.TextWrapped("teleoperation needs control_mode cartesian_impedance")
        imgui.TextDisabled("keys: W/S press/lift, A/D lateral, Q/E elevation")

    def build_view_gui(self) -> None:
        imgui.SeparatorText("View")
        labels = [_VIEW_LABELS[view] for view in VIEWS]
        changed, value = imgui.Combo("camera", VIEWS.index(self.state.view), labels)
        if changed:
            self.state.view = VIEWS[int(value)]


class UltrasoundPanel(plugin.ViewerPlugin):
    """The B-mode image under the probe (module docstring)."""

    def __init__(self, state: ViewerState) -> None:
        self.state = state
        self.texture = 0
        self._serial = 0

    @messages.handler
    def on_post_model(self, _: messages.PostModelEvent) -> None:
        self.texture = 0  # a new page: its textures are new too
        self._serial = -1

    @messages.handler
    def on_update(self, _: messages.UpdateEvent) -> None:
        image = self.state.image
        if image is None or self.state.image_serial == self._serial or not image.rgba:
            return
        self._serial = self.state.image_serial
        self.texture = int(
            self.viewer.upload_image(self.texture, image.rgba, image.cols, image.rows, 4)
        )

    @messages.handler
    def on_build_gui(self, _: messages.BuildGuiEvent) -> None:
        width, _ = _display()
        _place(
            self.state,
            "Ultrasound",
            width - _ULTRASOUND_SIZE[0] - _MARGIN_PX,
            _MARGIN_PX,
            _ULTRASOUND_SIZE,
        )
        if imgui.Begin("Ultrasound")[0]:
            info, image = self.state.info, self.state.image
            if info is None or image is None or not self.texture:
                imgui.TextUnformatted("no image (the scene has no deformation)")
            else:
                avail = imgui.GetContentRegionAvail()
                aspect = info.imaging_depth_m / info.aperture_m
                w = max(16.0, min(float(avail.x), (float(avail.y) - 24.0) / aspect))
                imgui.Image(self.texture, imgui.Vec2(w, w * aspect))
                imgui.TextDisabled(
                    f"{info.aperture_m * 1e3:.0f} mm wide, {info.imaging_depth_m * 1e3:.0f} mm "
                    f"deep, t = {image.time_s:.2f} s"
                )
        imgui.End()


class ForcePanel(plugin.ViewerPlugin):
    """The contact force now and a live plot of force and lesion depth (module docstring)."""

    def __init__(self, state: ViewerState) -> None:
        self.state = state

    @messages.handler
    def on_build_gui(self, _: messages.BuildGuiEvent) -> None:
        width, height = _display()
        _place(
            self.state,
            "Contact force and lesion depth",
            width - _FORCE_SIZE[0] - _MARGIN_PX,
            height - _FORCE_SIZE[1] - _BOTTOM_BAR_PX,
            _FORCE_SIZE,
        )
        if imgui.Begin("Contact force and lesion depth")[0]:
            self.build_bar_gui()
            self.build_plot_gui()
        imgui.End()

    def build_bar_gui(self) -> None:
        force = self.state.force_n(shown=True)
        imgui.PushStyleColor(imgui.Col.PlotHistogram, imgui.Vec4(*FORCE_BAR_RGBA))
        imgui.ProgressBar(
            min(force / FORCE_BAR_FULL_N, 1.0), imgui.Vec2(-1.0, 0.0), f"force {force:.2f} N"
        )
        imgui.PopStyleColor(1)
        status = self.state.shown
        depth = status.lesion_depth_m
        if status.lesion and not math.isnan(depth):
            text = f"lesion {status.lesion}: {depth * 1e3:.1f} mm deep"
            if not math.isnan(status.target_depth_m):
                text += f" (target {status.target_depth_m * 1e3:.1f} mm)"
            imgui.TextUnformatted(text)

    def build_plot_gui(self) -> None:
        times, force, depth = self.state.shown_history
        now = times[-1] if times else 0.0
        force_top = max([PLOT_MIN_FORCE_N, *force]) * 1.15
        shown_depth = [v for v in depth if not math.isnan(v)]
        if shown_depth:
            middle = 0.5 * (min(shown_depth) + max(shown_depth))
            half = max(0.5 * (max(shown_depth) - min(shown_depth)) * 1.15, PLOT_MIN_DEPTH_MM / 2)
        else:
            middle, half = 0.0, PLOT_MIN_DEPTH_MM / 2
        if implot.BeginPlot("##force_depth", imgui.Vec2(-1.0, -1.0)):
            implot.SetupAxis(implot.Axis.X1, "time [s]")
            implot.SetupAxis(implot.Axis.Y1, "force [N]")
            implot.SetupAxis(implot.Axis.Y2, "depth [mm]", int(implot.AxisFlags.Opposite))
            always = implot.Cond.Always
            implot.SetupAxisLimits(
                implot.Axis.X1, max(0.0, now - HISTORY_S), max(HISTORY_S, now), always
            )
            implot.SetupAxisLimits(implot.Axis.Y1, 0.0, force_top, always)
            implot.SetupAxisLimits(implot.Axis.Y2, middle - half, middle + half, always)
            if times:
                implot.SetAxes(implot.Axis.X1, implot.Axis.Y1)
                implot.PlotLine("force [N]", times, force)
                if shown_depth:
                    implot.SetAxes(implot.Axis.X1, implot.Axis.Y2)
                    implot.PlotLine("lesion depth [mm]", times, depth)
            implot.EndPlot()


class StatusPanel(plugin.ViewerPlugin):
    """Method, mesh, tissue step time, stability and rates (module docstring)."""

    def __init__(self, state: ViewerState) -> None:
        self.state = state
        self._tissue_ms: list[float] = []
        self._shown: object = None

    @messages.handler
    def on_update(self, _: messages.UpdateEvent) -> None:
        if self.state.shown is not self._shown:
            self._shown = self.state.shown
            self._tissue_ms.append(self.state.shown.tissue_step_s * 1e3)
            del self._tissue_ms[:-20]

    @messages.handler
    def on_build_gui(self, _: messages.BuildGuiEvent) -> None:
        _, height = _display()
        _place(
            self.state,
            "Status",
            _MARGIN_PX,
            height - _STATUS_SIZE[1] - _BOTTOM_BAR_PX,
            _STATUS_SIZE,
        )
        if imgui.Begin("Status")[0]:
            self.build_table_gui()
        imgui.End()

    def build_table_gui(self) -> None:
        state = self.state
        info, status = state.info, state.shown
        mean_ms = float(np.mean(self._tissue_ms)) if self._tissue_ms else 0.0
        rows = [
            ("task", info.env_id if info else "-"),
            ("contact method", info.contact if info else "-"),
            ("mesh", str(info.mesh) if info else "-"),
            ("tissue step", f"{status.tissue_step_s * 1e3:.1f} ms (mean {mean_ms:.1f})"),
            ("env step", f"{status.step_s * 1e3:.1f} ms"),
            ("stability", f"{status.tissue_status} ({'stable' if status.stable else 'UNSTABLE'})"),
            ("clock", f"t = {status.time_s:.2f} s, {status.realtime:.2f}x real time"),
            ("episode", f"{status.episode} ({status.mode}{', paused' if status.paused else ''})"),
            ("reward", f"{status.reward:+.3f}" + (f", {status.ended}" if status.ended else "")),
            ("viewer", f"{state.shown_frame_rate_hz:.0f} frames/s"),
        ]
        if imgui.BeginTable("status", 2):
            imgui.TableSetupColumn("name", imgui.TableColumnFlags.WidthFixed)
            imgui.TableSetupColumn("value", imgui.TableColumnFlags.WidthStretch)
            for name, value in rows:
                imgui.TableNextRow()
                imgui.TableNextColumn()
                imgui.TextUnformatted(name)
                imgui.TableNextColumn()
                imgui.TextUnformatted(value)
            imgui.EndTable()
        if status.error:
            imgui.TextWrapped(f"Paused on an error: {status.error}")


def _index(items: tuple[object, ...], value: object) -> int:
    return items.index(value) if value in items else 0
