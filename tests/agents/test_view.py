"""``probegym view``: the coupled scene in MuJoCo Studio's web viewer.

Fast: bad arguments fail before anything listens; the web viewer binds loopback only; the
command prints the address it bound and stops on Ctrl-C; the simulation plugin steps the
environment's own coupling, draws its tissue, teleoperates and plays a policy. Slow: a
headless Chromium opens the page, drives the probe into the breast with the plugin's keys
and checks from screenshots that the breast is drawn and dented under the probe and that
the force panel shows a force.
"""

from __future__ import annotations

import base64
import contextlib
import io
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
import urllib.request
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from agents.cli import main
from envs.studio import LOOPBACK, ProbeSimulation, check_host, launch_web, listening_sockets
from envs.studio.panels import FORCE_BAR_RGBA
from envs.studio.protocol import (
    POLICY,
    ChooseSceneEvent,
    ControlSnapshot,
    ProbeStatusSnapshot,
    SceneInfoEvent,
    UltrasoundSnapshot,
)

ROOT = Path(__file__).resolve().parents[2]
ENV_ID = "probegym/BreastCompress-v2"
LOOPBACK_ADDRESSES = ("127.0.0.1", "::1")
#: How far the browser test presses the probe in [mm] (about 3 N on the 623-tet phantom).
PRESS_MM = 15.0


# --------------------------------------------------------------------------- arguments


def _refuse_to_serve(monkeypatch: pytest.MonkeyPatch) -> None:
    import envs.studio

    def refuse(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("the viewer was started although the arguments were bad")

    monkeypatch.setattr(envs.studio, "launch_web", refuse)
    monkeypatch.setattr(envs.studio, "launch_native", refuse)


@pytest.mark.parametrize(
    "argv, message",
    [
        (["probegym/Nope-v0"], "unknown environment 'probegym/Nope-v0'; choose one of"),
        (["--port", "70000"], "--port must be a whole number in 0..65535"),
        (["--port", "-1"], "--port must be a whole number in 0..65535"),
        (["--host", "example.org"], "--host must be an IP address"),
        (["--contact", "springs"], "unknown contact method 'springs'"),
        (["--mesh", "12"], "unknown mesh level 12"),
        (["--policy", "/nonexistent/model.zip"], "--policy /nonexistent/model.zip"),
        (["--stats", "-1"], "--stats must be a number of seconds >= 0"),
    ],
)
def test_bad_arguments_fail_in_one_line_before_anything_listens(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], argv, message
) -> None:
    _refuse_to_serve(monkeypatch)
    assert main(["view", "--mesh", "623", *argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err


def test_native_says_why_it_cannot_run_here(monkeypatch, capsys) -> None:
    from envs.studio import native_viewer_problem

    problem = native_viewer_problem()
    if not problem:
        pytest.skip("Studio's native viewer can run here (a display and Python 3.12+)")
    import envs.studio

    monkeypatch.setattr(envs.studio, "launch_web", lambda *a, **k: pytest.fail("web started"))
    assert main(["view", "--mesh", "623", "--native"]) == 2
    err = capsys.readouterr().err
    assert "--native:" in err and problem in err and "drop --native" in err


def test_hosts_beyond_loopback_warn_and_names_are_refused() -> None:
    assert check_host("127.0.0.1") == ("127.0.0.1", "")
    assert check_host("localhost") == ("127.0.0.1", "")
    assert check_host("::1") == ("::1", "")
    for host in ("0.0.0.0", "::", "192.168.1.20"):
        address, warning = check_host(host)
        assert address == host and "no authentication" in warning and "ssh -L" in warning


def test_a_public_host_is_warned_about_on_the_command_line(monkeypatch, capsys) -> None:
    import envs.studio
    from tissue.errors import ConfigError

    def stop(*args: Any, **kwargs: Any) -> None:
        assert kwargs["host"] == "0.0.0.0"
        raise ConfigError("stopped before binding (test)")

    monkeypatch.setattr(envs.studio, "launch_web", stop)
    assert main(["view", "--mesh", "623", "--host", "0.0.0.0"]) == 2
    err = capsys.readouterr().err
    assert "serving on 0.0.0.0, beyond this machine" in err and "no authentication" in err


# --------------------------------------------------------------------------- binding


def _loopback_only(pid: int | str) -> list[tuple[str, int]]:
    sockets = listening_sockets(pid)
    if not sockets and not os.path.isdir("/proc/self/fd"):
        pytest.skip("listening sockets are read from /proc (Linux only)")
    return sockets


def test_the_web_viewer_listens_on_loopback_only() -> None:
    before = set(_loopback_only("self"))
    served = launch_web([], port=0)
    try:
        # launch_web returns once the viewer's thread listens on the socket it bound.
        now = set(listening_sockets())
        # In this process: the viewer's port (a socket an earlier test's viewer left to the
        # garbage collector may hold the same loopback port already) and nothing new
        # beyond loopback.
        assert (LOOPBACK, served.port) in now, now
        new = now - before
        assert all(address in LOOPBACK_ADDRESSES for address, _ in new), new
        assert served.url == f"http://127.0.0.1:{served.port}/"
        with urllib.request.urlopen(served.url, timeout=20) as response:
            assert response.status == 200
            # The page's WebAssembly client needs cross-origin isolation.
            assert response.headers["Cross-Origin-Opener-Policy"] == "same-origin"
    finally:
        served.handle.close()


class _Server:
    """``probegym view`` in a subprocess; its stdout lines collected on a thread."""

    def __init__(self, *argv: str) -> None:
        self.process = subprocess.Popen(
            [sys.executable, "-m", "agents.cli", "view", *argv],
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            text=True,
            bufsize=1,
        )
        self.lines: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.process.stdout is not None
        for line in self.process.stdout:
            self.lines.append(line.rstrip("\n"))

    def wait_for(self, pattern: str, timeout_s: float) -> re.Match[str]:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for line in list(self.lines):
                found = re.search(pattern, line)
                if found:
                    return found
            if self.process.poll() is not None and not self._reader.is_alive():
                break
            time.sleep(0.2)
        raise AssertionError(f"no line matching {pattern!r}; output:\n" + "\n".join(self.lines))

    def stop(self) -> int:
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGINT)
            try:
                # Ctrl-C is handled once the scene being built is (on a fresh install the
                # first build compiles the tissue's kernels: minutes on a loaded machine).
                self.process.wait(timeout=240)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self._reader.join(timeout=10)
        return int(self.process.returncode)


def _compile_the_default_scene() -> None:
    """Build and step, in this process, what ``probegym view`` builds first (BreastCompress
    with the image, 623 tets), so that the subprocess loads the compiled kernels from the
    on-disk cache: a first compilation holds the process for minutes on a loaded machine,
    and Ctrl-C is handled only after it."""
    import gymnasium as gym

    import envs  # noqa: F401 - registers the ids
    from agents.view import DEFAULT_ENV

    env = gym.make(DEFAULT_ENV, mesh=623, image=True)
    env.reset(seed=0)
    env.step(np.zeros(6, dtype=np.float32))
    env.close()


def test_view_prints_the_loopback_address_it_bound_and_stops_on_ctrl_c() -> None:
    _compile_the_default_scene()
    server = _Server("--mesh", "623", "--port", "0")
    try:
        found = server.wait_for(r"serving (http://127\.0\.0\.1:(\d+)/)", timeout_s=180)
        url, port = found.group(1), int(found.group(2))
        sockets = _loopback_only(server.process.pid)
        assert (LOOPBACK, port) in sockets, sockets
        assert all(address in LOOPBACK_ADDRESSES for address, _ in sockets), sockets
        with urllib.request.urlopen(url, timeout=20) as response:
            assert response.status == 200
    finally:
        code = server.stop()
    assert code == 0, "\n".join(server.lines)
    assert "probegym view: stopped" in server.lines
    assert not any("Traceback" in line for line in server.lines), "\n".join(server.lines)


# --------------------------------------------------------------------------- the plugin


class _Handle:
    """What the plugin sends to the viewer and publishes, recorded (no viewer)."""

    def __init__(self) -> None:
        self.sent: list[Any] = []
        self.models: list[Any] = []

    def send_to_viewer(self, message: Any) -> None:
        self.sent.append(message)

    def set_model(self, model: Any, path: str = "", data: Any = None) -> None:
        self.models.append((model, data))

    def last(self, kind: type) -> Any:
        return next(m for m in reversed(self.sent) if isinstance(m, kind))


def _simulation(**kwargs: Any) -> tuple[ProbeSimulation, _Handle]:
    simulation = ProbeSimulation(ENV_ID, mesh=623, **kwargs)
    handle = _Handle()
    simulation.handle = handle
    simulation.build()
    return simulation, handle


def test_the_plugin_steps_the_environments_coupling_and_draws_its_tissue() -> None:
    simulation, handle = _simulation(image_hz=50.0)
    core = simulation.core
    assert core is not None and simulation.renderer is not None
    start_pos, start_rot = core.probe_pose()
    time0 = float(core.data.time)
    simulation.on_control(ControlSnapshot(offset_m=(0.0, 0.01, 0.0)))
    steps = 40
    for _ in range(steps):
        simulation.step()
    # The environment's own data advanced, a tissue step at a time: no second physics.
    assert float(core.data.time) == pytest.approx(time0 + steps * core.tissue.dt)
    assert core.coupling.last_step is not None
    # Teleoperation went through the action: the controller's target is the slider pose.
    assert core.controller.target_pos == pytest.approx(start_pos + start_rot[:, 1] * 0.01)
    # The drawing is the environment's arm and the tissue's deformed skin.
    drawing = simulation.renderer.data
    assert np.array_equal(drawing.qpos, core.data.qpos)
    vertices = core.tissue.surface().vertices_m
    first = int(
        simulation.renderer.model.body_mocapid[simulation.renderer.model.body("breast/v0").id]
    )
    assert np.array_equal(drawing.mocap_pos[first : first + len(vertices)], vertices)
    rest = core.tissue.rest_nodes_m
    assert np.abs(core.tissue.positions_m - rest).max() > 0.003  # pressed in: deformed
    status = handle.last(ProbeStatusSnapshot)
    assert np.linalg.norm(status.force_world_n) > 0.3 and status.stable
    assert status.offset_m == (0.0, 0.01, 0.0) and status.lesion == 10
    assert status.lesion_depth_m < 0.0398 - 0.002  # the lesion came up the image
    image = handle.last(UltrasoundSnapshot)
    pixels = np.frombuffer(image.rgba, np.uint8).reshape(image.rows, image.cols, 4)
    assert pixels[..., :3].max() > 0  # in contact: not black


def test_a_policy_given_as_a_callable_drives_and_its_episodes_restart() -> None:
    seen: list[dict[str, Any]] = []

    def press(observation: dict[str, Any]) -> np.ndarray:
        seen.append(observation)
        return np.array([0.0, 0.3, 0.0, 0.0, 0.0, 0.0])

    simulation, handle = _simulation(
        policies={ENV_ID: lambda: press},
        policy_label="press",
        env_kwargs={"max_episode_steps": 3},
    )
    info = (
        handle.last(SceneInfoEvent)
        if any(isinstance(m, SceneInfoEvent) for m in handle.sent)
        else None
    )
    assert info is None or info.policy_envs == (ENV_ID,)
    simulation.on_control(ControlSnapshot(mode=POLICY))
    step = _step_event()
    for _ in range(5):
        simulation._next_due = 0.0  # due now: no waiting on the wall clock
        simulation.on_step(step)
    assert len(seen) == 5 and "lesion" in seen[0]
    status = handle.last(ProbeStatusSnapshot)
    assert status.mode == POLICY and simulation.episode == 2  # 3 steps, then a new episode
    assert status.offset_m[1] > 0.0  # the policy's target, shown on the sliders


def test_without_a_policy_the_probe_stays_teleoperated() -> None:
    simulation, handle = _simulation()
    simulation.on_control(ControlSnapshot(mode=POLICY))
    assert simulation.control.mode == "teleop"


def test_a_scene_that_cannot_be_built_keeps_the_previous_one() -> None:
    simulation, handle = _simulation()
    core = simulation.core
    simulation.on_choose_scene(ChooseSceneEvent(ENV_ID, "springs", 623))
    info = handle.last(SceneInfoEvent)
    assert "unknown contact method 'springs'" in info.error
    assert simulation.core is core
    simulation.on_choose_scene(ChooseSceneEvent("probegym/ForceScan-v0", "penalty", 623))
    info = handle.last(SceneInfoEvent)
    assert not info.error and info.env_id == "probegym/ForceScan-v0" and info.contact == "penalty"
    assert handle.models[-1][0] is simulation.renderer.model  # the new drawing published


def _step_event() -> Any:
    from mujoco.studio import messages

    return messages.StepEvent(model=None, data=None)


# --------------------------------------------------------------------------- the browser


def _chromium() -> str:
    for name in ("chromium", "chromium-browser"):
        path = shutil.which(name)
        if path:
            return path
    pytest.skip(
        "no Chromium here and none could be installed: install Debian's (apt-get install "
        "chromium); Playwright drives it by its path (never `playwright install`)"
    )
    raise AssertionError  # unreachable


def _rgb(png: bytes) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(np.int32)


def _skin(rgb: np.ndarray) -> np.ndarray:
    """The breast's pixels: the see-through skin (over the sky or the table) and the red
    lesions are warm; the probe, the arm, the sky, the table and the floor are not, nor is
    the orange sensor site (saturated)."""
    red, green, blue = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    return (red > 40) & (red >= green) & (red - blue >= 15) & (green - blue < 60)


def _panels_drawn(rgb: np.ndarray) -> bool:
    """Whether the control panel covers the page's top-left corner (the side view has
    only sky there)."""
    return bool((rgb[40:290, 20:290].max(axis=-1) > 8).mean() > 0.9)


def _probe(rgb: np.ndarray) -> np.ndarray:
    """The probe's and arm's cool greys and blues (not the black sky)."""
    red, blue = rgb[..., 0], rgb[..., 2]
    return (blue > 12) & (blue >= red + 4)


def _overlay(rgb: np.ndarray) -> np.ndarray:
    """The image plane's green outline."""
    return rgb[..., 1] > rgb[..., 0] + 20


def _force_bar(rgb: np.ndarray) -> np.ndarray:
    target = np.array([round(255 * c) for c in FORCE_BAR_RGBA[:3]])
    return np.abs(rgb - target).max(axis=-1) <= 24


def _centre(mask: np.ndarray, half: int = 130) -> np.ndarray:
    """The window around the page's centre, where the side view puts the contact (the
    panels are at the page's sides)."""
    rows, cols = mask.shape
    return mask[rows // 2 - half : rows // 2 + half, cols // 2 - half : cols // 2 + half]


def _skin_lost(before: np.ndarray, after: np.ndarray) -> int:
    """Pixels near the contact that were breast and now show what lay behind it (the skin
    moved away; the probe moving over them does not count)."""
    lost = _skin(before) & ~_skin(after) & ~_probe(after) & ~_overlay(after)
    return int(_centre(lost).sum())


_STATS = re.compile(
    r"frames (?P<frames>\d+), .*? t (?P<t>[0-9.]+) s \((?P<realtime>[0-9.]+)x real time"
    r"(?P<paused>, paused)?\).*?force (?P<force>[0-9.]+) N.*?press (?P<press>-?[0-9.]+) mm"
)


@pytest.mark.slow
@pytest.mark.browser
def test_the_browser_shows_the_breast_dented_under_the_probe_and_the_force(tmp_path) -> None:
    sync_api = pytest.importorskip(
        "playwright.sync_api", reason="Playwright is not installed (pip install playwright)"
    )
    chromium = _chromium()
    server = _Server("--mesh", "623", "--port", "0", "--stats", "1")
    shots: dict[str, bytes] = {}

    def stats() -> dict[str, Any]:
        for line in reversed(list(server.lines)):
            found = _STATS.search(line)
            if found:
                values = found.groupdict()
                return {
                    k: (v is not None if k == "paused" else float(v)) for k, v in values.items()
                }
        return {}

    def wait(condition: Callable[[], bool], timeout_s: float, what: str) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if condition():
                return
            time.sleep(0.3)
        raise AssertionError(f"timed out waiting for {what}; last: {stats()}")

    try:
        url = server.wait_for(r"serving (http://127\.0\.0\.1:\d+/)", timeout_s=180).group(1)
        sockets = _loopback_only(server.process.pid)
        assert sockets and all(address in LOOPBACK_ADDRESSES for address, _ in sockets), sockets
        with sync_api.sync_playwright() as playwright:
            browser = playwright.chromium.launch(
                executable_path=chromium,
                headless=True,
                # WebGL 2 on the CPU (SwiftShader); root in a container needs no sandbox.
                args=["--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                      "--no-sandbox"],
            )  # fmt: skip
            page = browser.new_page(viewport={"width": 1280, "height": 800})
            page.goto(url)
            cdp = page.context.new_cdp_session(page)

            def hold(key: str, shift: bool = False) -> None:
                """Press a key, held a while: the page sends the keyboard's state once a
                frame, and a slow page (software WebGL on a busy machine draws a frame in
                seconds) misses a press that is down and up between two frames. A held key
                moves the probe once (no repeat)."""
                if shift:
                    page.keyboard.down("Shift")
                page.keyboard.down(key.upper() if shift else key)
                page.wait_for_timeout(2000)
                page.keyboard.up(key.upper() if shift else key)
                if shift:
                    page.keyboard.up("Shift")

            def shot(name: str) -> np.ndarray:
                png = base64.b64decode(
                    cdp.send("Page.captureScreenshot", {"format": "png"})["data"]
                )
                shots[name] = png
                return _rgb(png)

            wait(lambda: stats().get("frames", 0) > 10, 180, "the browser to connect")
            # The scene is drawn once the breast stands at the page's centre, the same in two
            # screenshots (the camera placed, the model loaded), and the panels are up.
            deadline = time.monotonic() + 300
            rest = shot("rest")
            while True:
                again = shot("rest")
                drawn = _centre(_skin(again)).sum() > 3000
                if drawn and _panels_drawn(again) and _skin_lost(rest, again) < 200:
                    break
                rest = again
                assert time.monotonic() < deadline, "the breast or the panels were never drawn"
            noise = _skin_lost(rest, again)
            rest = again
            assert _force_bar(rest).sum() < 50  # touching, not pressing: an empty bar

            # Press 15 mm through the plugin's keys (W: 1 mm, Shift+W: 5 mm), closing the
            # loop on what the simulation reports: over a slow link keys arrive late.
            frames_before = stats()["frames"]
            deadline = time.monotonic() + 420
            while stats()["press"] < PRESS_MM:
                assert time.monotonic() < deadline, f"the keys did not arrive: {stats()}"
                press = stats()["press"]
                hold("w", shift=PRESS_MM - press >= 5.0)  # with Shift: 5 mm
                with contextlib.suppress(AssertionError):  # lost: press again
                    wait(lambda press=press: stats()["press"] != press, 90, "the key to arrive")
            settled: list[float] = []

            def force_settled() -> bool:
                settled.append(stats()["force"])
                return len(settled) > 8 and abs(settled[-1] - settled[-8]) < 0.05

            wait(force_settled, 120, "the force to settle")
            pressed_stats = stats()
            assert pressed_stats["force"] > 0.5, pressed_stats
            # The viewer drew frames all the while the tissue stepped (its own thread).
            assert pressed_stats["frames"] > frames_before

            # Pause, so that the page's panels catch up with the simulation and hold still.
            deadline = time.monotonic() + 240
            while not stats().get("paused", False):
                assert time.monotonic() < deadline, f"the simulation did not pause: {stats()}"
                hold(" ")
                with contextlib.suppress(AssertionError):
                    wait(lambda: stats().get("paused", False), 60, "the simulation to pause")
            print(f"pressed and paused: {stats()}", flush=True)
            deadline = time.monotonic() + 420
            while True:
                pressed = shot("pressed")
                bar = int(_force_bar(pressed).sum())
                print(f"force bar {bar} px", flush=True)
                if bar >= 300:
                    break
                assert time.monotonic() < deadline, "the force panel never showed the force"
            browser.close()
        lost = _skin_lost(rest, pressed)
        assert _centre(_skin(pressed)).sum() > 3000, "the breast is not drawn when pressed"
        assert lost >= max(300, 5 * noise), (lost, noise)
    finally:
        for name, png in shots.items():
            (tmp_path / f"view-{name}.png").write_bytes(png)
        keep = os.environ.get("PROBEGYM_VIEW_SCREENSHOTS")
        if keep:
            Path(keep).mkdir(parents=True, exist_ok=True)
            for name, png in shots.items():
                (Path(keep) / f"view-{name}.png").write_bytes(png)
        code = server.stop()
    assert code == 0, "\n".join(server.lines[-20:])
