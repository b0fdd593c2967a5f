"""Serving the probegym plugins in MuJoCo Studio's web viewer, on loopback by default.

MuJoCo 4.0.0's ``WebViewer`` binds its one public port on every interface (``::``, written
into its constructor; upstream plans a host option) and has no authentication: anyone who
reaches the port can drive the robot, upload files and read logs and file paths.
:class:`InterfaceWebViewer` binds the interface it is given instead (127.0.0.1 by
default) by overriding the private attribute the constructor reads (``_host``), which is why
the project pins ``mujoco`` exactly; after binding it checks the socket's address and
refuses to serve on any other (a MuJoCo that changed this fails loudly, never silently
listens everywhere). Its second socket, NetImgui's, is loopback already.

The port: 0 takes the first free port from 8080 (MuJoCo's rule); :func:`launch_web` returns
the address actually bound. Browsers run the viewer's WebAssembly client only in a secure
context (``http://localhost`` / ``127.0.0.1`` or HTTPS): from another machine, forward the
port (``ssh -L 8080:localhost:8080 HOST``) rather than binding a public interface.

The native desktop viewer (:func:`launch_native`) runs where Studio's Filament renderer
imports (Python 3.12 and newer, a display).
"""

from __future__ import annotations

import contextlib
import ipaddress
import os
import queue
import signal
import socket
import sys
import threading
import time
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from mujoco.studio import (
    endpoints,
    launch_thread,
    plugin,
    viewer_handle,
    viewer_protocol,
    web_viewer,
)

from envs.errors import EnvConfigError

#: The default interface: IPv4 loopback.
LOOPBACK = "127.0.0.1"
#: How long to wait for the viewer thread to bind its sockets [s].
BIND_TIMEOUT_S = 60.0


def check_port(port: Any) -> int:
    """A port number in [0, 65535] (0: the first free one from 8080).

    Raises:
        EnvConfigError: anything else (the message says what was given).
    """
    if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
        raise EnvConfigError(
            f"--port must be a whole number in 0..65535 (0: the first free port from 8080); "
            f"got {port!r}"
        )
    return port


def check_host(host: Any) -> tuple[str, str]:
    """The interface to bind and a warning to print ('' for loopback).

    Accepts an IPv4 or IPv6 address literal, or ``localhost``.

    Raises:
        EnvConfigError: a name that is not an address (the message says what to give).
    """
    if not isinstance(host, str) or not host.strip():
        raise EnvConfigError(f"--host must be an IP address such as {LOOPBACK}; got {host!r}")
    text = host.strip()
    if text.lower() == "localhost":
        return LOOPBACK, ""
    try:
        address = ipaddress.ip_address(text.strip("[]"))
    except ValueError:
        raise EnvConfigError(
            f"--host must be an IP address of this machine such as {LOOPBACK} (the "
            f"default), ::1, or 0.0.0.0 for every interface; got {host!r}"
        ) from None
    if address.is_loopback:
        return str(address), ""
    warning = (
        f"warning: serving on {address}, beyond this machine: the viewer has no "
        "authentication or encryption; anyone who can reach the port can drive the robot, "
        "upload files and read logs and file paths. Browsers also refuse its WebAssembly "
        "client over plain http from another machine: prefer the default loopback and "
        "ssh -L PORT:localhost:PORT from the machine with the browser."
    )
    return str(address), warning


class InterfaceWebViewer(web_viewer.WebViewer):
    """MuJoCo Studio's ``WebViewer`` bound to one interface (module docstring).

    Args:
        config: the viewer's configuration (``http_port``: 0 for the first free port from
            8080).
        endpoint: its end of the channels to the simulation.
        host: the interface to bind (an address literal).
        plugins: the viewer plugins.

    Raises:
        RuntimeError: the socket was bound elsewhere than ``host`` (an incompatible MuJoCo).
    """

    def __init__(
        self,
        config: viewer_protocol.ViewerConfig,
        endpoint: endpoints.ViewerEndpoint,
        *,
        host: str = LOOPBACK,
        plugins: list[Any] | None = None,
    ) -> None:
        self._bind_host = host
        super().__init__(config, endpoint, plugins=plugins)
        bound = self._http_sock.getsockname()[0]
        if _normal(bound) != _normal(host):
            self.close()
            import mujoco

            raise RuntimeError(
                f"the web viewer bound {bound!r}, not {host!r}: MuJoCo {mujoco.__version__} "
                "no longer takes the interface this way; install the version probegym pins "
                "(pip install -e .)"
            )

    # WebViewer.__init__ assigns ``self._host = '::'`` and binds ``self._host`` right away:
    # the property keeps the interface given here.
    @property
    def _host(self) -> str:
        return self._bind_host

    @_host.setter
    def _host(self, value: str) -> None:
        del value

    @property
    def address(self) -> tuple[str, int]:
        """The interface and port bound."""
        host, port = self._http_sock.getsockname()[:2]
        return str(host), int(port)


def _normal(host: str) -> str:
    try:
        return str(ipaddress.ip_address(host))
    except ValueError:
        return host


@dataclass(frozen=True)
class Served:
    """A running web viewer.

    Attributes:
        handle: the simulation side's handle (call :func:`run_until_closed`, then close).
        host, port: the interface and port bound.
    """

    handle: viewer_handle.ViewerHandle
    host: str
    port: int

    @property
    def url(self) -> str:
        """The address to open in a browser."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        if self.host in ("0.0.0.0", "::"):
            host = LOOPBACK
        return f"http://{host}:{self.port}/"


def launch_web(
    plugins: Iterable[plugin.Plugin],
    *,
    host: str = LOOPBACK,
    port: int = 0,
    title: str = "probegym",
) -> Served:
    """Start the web viewer with ``plugins`` on a daemon thread, bound to ``host``.

    The simulation runs on the calling thread: publish the model (dispatch a
    ``LoadModelEvent``), then :func:`run_until_closed`.

    Raises:
        EnvConfigError: a bad ``host`` or ``port``.
        RuntimeError, OSError: the viewer could not bind (the port is taken, ...).
    """
    host, _ = check_host(host)
    port = check_port(port)
    config = viewer_protocol.ViewerConfig(title=title, gfx="web", http_port=port)
    viewer_plugins, sim_plugins = plugin.split_plugins(plugins)
    bound: queue.Queue[tuple[str, int] | BaseException] = queue.Queue()

    def target(endpoint: endpoints.ViewerEndpoint) -> None:
        try:
            viewer = InterfaceWebViewer(config, endpoint, host=host, plugins=viewer_plugins)
        except BaseException as error:
            bound.put(error)
            raise
        bound.put(viewer.address)
        viewer_protocol.run_viewer_loop(viewer)

    handle = launch_thread.launch_thread(target, sim_plugins=sim_plugins)
    try:
        result = bound.get(timeout=BIND_TIMEOUT_S)
    except queue.Empty:
        result = RuntimeError(f"the web viewer did not start within {BIND_TIMEOUT_S:.0f} s")
    if isinstance(result, BaseException):
        with contextlib.suppress(BaseException):  # the viewer's own error is raised below
            handle.close()
        raise result
    _wait_until_listening(result[1], BIND_TIMEOUT_S)
    return Served(handle, result[0], result[1])


def _wait_until_listening(port: int, timeout_s: float) -> None:
    """Return once this process listens on ``port``: the viewer binds in its constructor
    and listens moments later on its own thread, so an address printed (or a check of what
    listens) right after binding could come before the socket accepts. Where ``/proc`` cannot
    be read it returns at once; past ``timeout_s`` it returns too (the viewer's own errors
    surface through its handle)."""
    if not os.path.isdir("/proc/self/fd"):
        return
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if any(listening == port for _, listening in listening_sockets()):
            return
        time.sleep(0.05)


def native_viewer_problem() -> str:
    """Why Studio's native desktop viewer cannot run here ('' where it can)."""
    if sys.platform.startswith("linux") and not (
        os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
    ):
        return "no display (DISPLAY and WAYLAND_DISPLAY are unset)"
    try:
        from mujoco.studio import native_viewer  # noqa: F401
    except ImportError as error:
        return (
            f"MuJoCo Studio's native viewer does not import on Python "
            f"{sys.version_info.major}.{sys.version_info.minor} ({error}); it needs 3.12 or newer"
        )
    return ""


def launch_native(plugins: Iterable[plugin.Plugin], *, title: str = "probegym") -> Any:
    """Start Studio's native desktop viewer with ``plugins`` on a daemon thread; returns the
    simulation's handle.

    Raises:
        EnvConfigError: it cannot run here (:func:`native_viewer_problem` says why).
    """
    problem = native_viewer_problem()
    if problem:
        raise EnvConfigError(f"--native: {problem}; use the web viewer (drop --native)")
    from mujoco.studio import launch_native as native

    return native.launch(viewer_protocol.ViewerConfig(title=title), plugins=list(plugins))


def run_until_closed(handle: viewer_handle.ViewerHandle) -> None:
    """Run the simulation's loop (its plugins step and pace) until the viewer closes.

    Raises:
        KeyboardInterrupt: on Ctrl-C (SIGINT), after the step in progress. Studio calls the
            plugins' handlers from C++ and does not pass their exceptions on, so an
            interrupt raised inside one (where a tissue step spends most of the loop's
            time) would be lost: in the main thread the signal only sets a flag, which
            the loop reads between syncs.
    """
    interrupted = threading.Event()
    previous = None
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGINT, lambda *_: interrupted.set())
    try:
        while handle.is_running() and not interrupted.is_set():
            handle.sync()
    finally:
        if previous is not None:
            signal.signal(signal.SIGINT, previous)
    if interrupted.is_set():
        raise KeyboardInterrupt


def listening_sockets(pid: int | str = "self") -> list[tuple[str, int]]:
    """The listening TCP sockets of process ``pid`` (default this one), (address, port);
    read from ``/proc`` (Linux; [] elsewhere or where the process cannot be read)."""
    folder = f"/proc/{pid}/fd"
    try:
        fds = os.listdir(folder)
    except OSError:
        return []
    inodes = set()
    for fd in fds:
        try:
            link = os.readlink(f"{folder}/{fd}")
        except OSError:
            continue
        if link.startswith("socket:["):
            inodes.add(link[8:-1])
    found = []
    for table, family in (("/proc/net/tcp", socket.AF_INET), ("/proc/net/tcp6", socket.AF_INET6)):
        try:
            lines = open(table).read().splitlines()[1:]  # noqa: SIM115
        except OSError:
            continue
        for line in lines:
            fields = line.split()
            if fields[3] != "0A" or fields[9] not in inodes:  # 0A: LISTEN
                continue
            address, port = fields[1].split(":")
            found.append((_proc_address(address, family), int(port, 16)))
    return found


def _proc_address(hex_address: str, family: int) -> str:
    raw = bytes.fromhex(hex_address)
    # /proc/net/tcp* print each 32-bit word in host (little-endian) order.
    words = b"".join(raw[i : i + 4][::-1] for i in range(0, len(raw), 4))
    return socket.inet_ntop(family, words)
