"""The coupled scene in MuJoCo Studio: a simulation plugin that steps a probegym
environment and viewer plugins that show and drive it (``probegym view`` serves them).

- :class:`ProbeSimulation` (simulation thread): makes the environment with
  ``gymnasium.make`` and steps it with ``env.step``: the robot and the tissue advance
  through the environment's own coupling, no second copy of the physics; handles the
  choice of task, contact method and mesh, resets, teleoperation and a policy given as a
  callable (``envs`` never imports torch or SB3: ``agents`` loads policies).
- Viewer plugins (viewer thread, :func:`viewer_plugins`): the deformed breast is the
  drawing scene itself (skin see-through, lesions red, moved every step); overlays of the
  image plane and the contact force (:class:`SceneOverlay`); panels for the controls, the
  ultrasound image, a live plot of force and lesion depth, and the status
  (:mod:`envs.studio.panels`).
- :func:`launch_web` serves the web viewer on 127.0.0.1 by default
  (:mod:`envs.studio.server`); :func:`launch_native` opens the desktop viewer where one
  can run.

Example::

    from mujoco.studio import messages
    from envs.studio import ProbeSimulation, launch_web, run_until_closed, viewer_plugins

    simulation = ProbeSimulation("probegym/BreastCompress-v0", mesh=623)
    simulation.build()
    served = launch_web([simulation, *viewer_plugins()], port=0)
    print(served.url)
    served.handle.dispatch(messages.LoadModelEvent(path=""))
    with served.handle:
        run_until_closed(served.handle)

The messages between the two threads are in :mod:`envs.studio.protocol`.
"""

from __future__ import annotations

from mujoco.studio import plugin

from envs.studio.overlays import SceneOverlay
from envs.studio.panels import ControlPanel, ForcePanel, StatusPanel, UltrasoundPanel
from envs.studio.server import (
    LOOPBACK,
    InterfaceWebViewer,
    Served,
    check_host,
    check_port,
    launch_native,
    launch_web,
    listening_sockets,
    native_viewer_problem,
    run_until_closed,
)
from envs.studio.simulation import ProbeSimulation
from envs.studio.viewer_state import SimulationLink, ViewerState


def viewer_plugins(stats_every_s: float = 0.0) -> list[plugin.ViewerPlugin]:
    """probegym's viewer plugins, sharing one :class:`ViewerState`.

    Args:
        stats_every_s: print a status line this often [s] (0: never); see
            :class:`SimulationLink`.
    """
    state = ViewerState()
    return [
        SimulationLink(state, stats_every_s),
        SceneOverlay(state),
        ControlPanel(state),
        UltrasoundPanel(state),
        ForcePanel(state),
        StatusPanel(state),
    ]


__all__ = [
    "LOOPBACK",
    "ControlPanel",
    "ForcePanel",
    "InterfaceWebViewer",
    "ProbeSimulation",
    "SceneOverlay",
    "Served",
    "SimulationLink",
    "StatusPanel",
    "UltrasoundPanel",
    "ViewerState",
    "check_host",
    "check_port",
    "launch_native",
    "launch_web",
    "listening_sockets",
    "native_viewer_problem",
    "run_until_closed",
    "viewer_plugins",
]
