"""Sleep in free air: a tissue at rest, with the probe clear of the skin by more than it can
reach in the next step, skips the step's work (:meth:`tissue.contact.base.ContactModel.step`
says when and what a sleeping step returns). :class:`FreeAirSleep` is the part of
:class:`~tissue.contact.base.ContactModel` that decides it; the hooks a contact method
overrides to sleep are :meth:`FreeAirSleep.sleep_reach_m` (None: it never sleeps),
:meth:`FreeAirSleep._in_contact`, :meth:`FreeAirSleep._loaded` and
:meth:`FreeAirSleep._advance_asleep`.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tissue.contact.sleep_kernel import blocked_points, clear_of_probe, rotation_matrix
from tissue.errors import ConfigError

if TYPE_CHECKING:
    from tissue.contact.surface_points import SurfacePoints
    from tissue.probe import Probe

#: How much farther than a method's own reach (:meth:`ContactModel.sleep_reach_m`) the skin
#: must lie from the probe for a step to sleep [m] (see :meth:`ContactModel.step`). The
#: reach and the probe's travel already bound where a step can act; this covers what they
#: do not state (a solver's iterates straying past the positions it converges to, round-off
#: in the signed distance). Waking 1 mm early costs at most a few tissue steps of an
#: approach (5 at the paper's 10 mm/s); waking late would skip contact.
SLEEP_SAFETY_MARGIN_M = 0.001

#: The node speed [m/s] below which a tissue at rest in free air may sleep, the setting the
#: environments use (``TissueSpec(sleep_speed_m_s=SLEEP_SPEED_M_S)``; see
#: :meth:`ContactModel.step`). A node this slow moves 20 nm in a 0.02 s step, far below
#: anything a lesion's position or a force could show; a tissue released from a press
#: falls below it within about 40-150 steps (0.8-3 s) on the coarse phantom levels.
SLEEP_SPEED_M_S = 1e-6


def check_sleep_speed(value: object) -> float | None:
    """``value`` as a sleep threshold [m/s]: None (never sleep) or a finite number > 0.

    Raises:
        ConfigError: anything else, naming the value and what to give instead.
    """
    if value is None:
        return None
    number = math.nan
    if isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool):
        number = float(value)
    if not (math.isfinite(number) and number > 0.0):
        raise ConfigError(
            f"sleep_speed_m_s must be None (the tissue never sleeps) or a node speed > 0 "
            f"[m/s], e.g. tissue.SLEEP_SPEED_M_S = {SLEEP_SPEED_M_S}; got {value!r}"
        )
    return number


class RestPoints(NamedTuple):
    """What a resting tissue's sleep is decided on (worked out once a rest begins; see
    :meth:`FreeAirSleep._rest_check`).

    Attributes:
        points: the points that must stay clear of the probe (the method's contact points,
            then the skin's) [m], (k, 3).
        boundary: the volume's boundary points [m], (b, 3).
        reach_m: the distance [m] the points must be clear by, beyond the probe's travel.
        kernel_args: the compiled checks' arguments that hold while the tissue rests
            (:func:`~tissue.contact.sleep_kernel.clear_of_probe`'s from
            ``bounding_radius`` on: the probe's geometry, the reach, ``points`` and
            ``boundary`` as :class:`~tissue.contact.sleep_kernel.BlockedPoints`), in its
            order.
    """

    points: NDArray[np.float64]
    boundary: NDArray[np.float64]
    reach_m: float
    kernel_args: tuple[Any, ...]


class FreeAirSleep:
    """Whether a step may sleep, and the state that decides it (a mixin of
    :class:`~tissue.contact.base.ContactModel`, whose ``__init__`` sets the attributes)."""

    if TYPE_CHECKING:
        probe: Probe
        skin: SurfacePoints
        _volume_boundary: SurfacePoints
        _sleep_speed_m_s: float | None
        _quiet: bool
        _rest: RestPoints | None
        _rest_known: bool
        _state_version: int
        _probe_geometry: tuple[float, float, int, NDArray[np.float64]]
        _time: float
        _last_pose: tuple[NDArray[np.float64], NDArray[np.float64]] | None

        @property
        def node_positions(self) -> NDArray[np.float64]: ...
        @property
        def node_velocities(self) -> NDArray[np.float64]: ...
        @property
        def dt(self) -> float: ...
        def contact_points_world(self) -> NDArray[np.float64]: ...
        def _behind_skin(self, boundary_points: NDArray[np.float64]) -> bool: ...

    @property
    def sleep_speed_m_s(self) -> float | None:
        """The node speed [m/s] below which a tissue at rest, with the probe clear of the
        skin, sleeps instead of stepping (see :meth:`step`); None (the default): it never
        sleeps.

        Raises:
            ConfigError: (setting it) anything but None or a finite number > 0.
        """
        return self._sleep_speed_m_s

    @sleep_speed_m_s.setter
    def sleep_speed_m_s(self, value: float | None) -> None:
        self._sleep_speed_m_s = check_sleep_speed(value)
        self._forget_rest()

    def sleep_reach_m(self) -> float | None:
        """How far from the probe [m] a point (of :meth:`contact_points_world` or the skin)
        at rest can lie and still be acted on in this method's next step with the probe
        held where it is: its alarm, capture or contact-margin distance. A step sleeps only
        while every point lies farther than this plus the probe's travel and
        :data:`SLEEP_SAFETY_MARGIN_M` (see :meth:`step`).

        None (the default): this method never sleeps, so that a strategy registered
        without stating its reach is never put to sleep wrongly."""
        return None

    def _in_contact(self) -> bool:
        """Whether the method holds contact that its next step must act on though the last
        step returned no contact point (held nodes, active constraints): such a tissue
        never sleeps. False by default; the last step's contact points count already."""
        return False

    def _loaded(self) -> bool:
        """Whether a load other than contact acts on the tissue (gravity), so that nodes
        standing still need not be at rest: such a tissue never sleeps. False by default."""
        return False

    def _advance_asleep(self, h: float, pieces: int) -> None:  # noqa: B027 - most keep nothing
        """A sleeping step's bookkeeping: what the method's :meth:`_advance` would record of
        ``pieces`` sub-motions of ``h`` [s] each beyond the tissue's state (the probe's last
        pose, a clock of its own), the probe now at its new pose. Nothing by default."""

    def _state_replaced(self) -> None:
        """The state was loaded from elsewhere (:meth:`load_state`): nothing is known of
        its contact, so the next step runs in full before any sleeps."""
        self._quiet = False
        self._forget_rest()

    @property
    def state_version(self) -> int:
        """A number that changes whenever the tissue's state may have changed (a step that
        ran, a reset, a restore, a loaded state) and stays while it sleeps: what was read
        off the nodes under one version (lesion centroids, say) holds while it stays."""
        return self._state_version

    def _forget_rest(self) -> None:
        self._rest = None
        self._rest_known = False
        self._state_version += 1

    def _rest_check(self) -> RestPoints | None:
        """While the tissue may sleep: the points it is decided on (:class:`RestPoints`);
        None while it may not (in contact, moving, or a method that never sleeps). Worked
        out once after each step that runs: a sleeping step changes none of it."""
        if not self._rest_known:
            self._rest = self._rest_points()
            self._rest_known = True
        return self._rest

    def _rest_points(self) -> RestPoints | None:
        speed = self._sleep_speed_m_s
        if speed is None or not self._quiet:
            return None
        reach = self.sleep_reach_m()
        if reach is None or self._in_contact() or self._loaded():
            return None
        velocities = self.node_velocities
        if velocities.size and float(np.einsum("ij,ij->i", velocities, velocities).max()) >= (
            speed * speed
        ):
            return None
        positions = self.node_positions
        points = self.contact_points_world()
        skin = self.skin.positions(positions)
        if not np.array_equal(points, skin):  # the same points where a method acts on the skin
            points = np.concatenate([points, skin])
        boundary = self._volume_boundary.positions(positions)
        # A node at the threshold speed moves speed x dt within the step.
        reach = reach + SLEEP_SAFETY_MARGIN_M + speed * self.dt
        kernel_args = (*self._probe_geometry, reach, *blocked_points(points))
        return RestPoints(points, boundary, reach, (*kernel_args, *blocked_points(boundary)))

    def sleep_if_clear(self, position_world: ArrayLike, quat_wxyz: ArrayLike) -> bool:
        """A step that sleeps (see :meth:`step`), taken when one compiled call settles that
        it does (the probe well clear of the skin, no exact signed distance needed): True,
        the probe at the pose and the clock advanced as :meth:`step` would leave them.
        False: nothing has changed, and the step is :meth:`step_after_sleep_check`'s (which
        may still sleep). Every free-air step of a resting tissue takes this path."""
        if self._sleep_speed_m_s is None:
            return False
        pose = self._clear_pose(position_world, quat_wxyz)
        if pose is None:
            return False
        position, quat, rotation, pieces = pose
        self.probe.set_normalised_pose(position, quat, rotation)
        # The pose seen is the probe's new arrays themselves: it replaces them when it
        # moves, never changes them in place.
        self._fall_asleep(self.dt if pieces == 1 else self.dt / pieces, pieces, (position, quat))
        return True

    def _clear_pose(
        self, position_world: ArrayLike, quat_wxyz: ArrayLike
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], int] | None:
        """The pose a sleeping step leaves the probe at, where the step sleeps and one
        compiled call settles it (:func:`~tissue.contact.sleep_kernel.clear_of_probe`): the
        position [m] (3,), the quaternion (4,) and rotation matrix (3, 3) the probe then
        holds, and the sub-motions its travel counts. None: the tissue may not sleep, the
        input is not a finite pose, or the call does not decide (a point near enough to the
        probe to need its exact signed distance); nothing has changed.

        Where this says the step sleeps, so does :meth:`_may_sleep`, and the pose is what
        :meth:`~tissue.probe.Probe.set_pose` makes of the input, to the bit: the
        quaternion's norms are the same numpy dot products, the rest the kernel's IEEE
        arithmetic."""
        rest = self._rest_check()
        if rest is None:
            return None
        position = np.array(position_world, dtype=np.float64)
        quat = np.asarray(quat_wxyz, dtype=np.float64)
        if position.shape != (3,) or quat.shape != (4,):
            return None
        # A finite sum of squares: every component finite (the full path raises otherwise).
        squared = float(quat.dot(quat))
        if not (math.isfinite(squared) and math.sqrt(squared) >= 1e-12):
            return None
        # Probe.set_pose normalises the quaternion (the one it keeps) and again for its
        # matrix (quat_to_matrix normalises what it is given).
        unit = quat / math.sqrt(squared)
        check = unit / math.sqrt(float(unit.dot(unit)))
        begin = self._last_pose
        rotation = np.empty((3, 3))
        pieces = clear_of_probe(
            position,
            unit,
            check,
            position if begin is None else begin[0],
            unit if begin is None else begin[1],
            begin is not None,
            rotation,
            *rest.kernel_args,
        )
        if not pieces:
            return None
        if pieces == 1:
            return position, unit, rotation, pieces
        # Several sub-motions end by setting the end pose again: the probe keeps the
        # quaternion normalised twice, and its matrix is of that normalised once more.
        rotation_matrix(check / math.sqrt(float(check.dot(check))), rotation)
        return position, check, rotation, pieces

    def _fall_asleep(
        self, h: float, pieces: int, seen: tuple[NDArray[np.float64], NDArray[np.float64]]
    ) -> None:
        """A sleeping step's bookkeeping, the probe at its new pose ``seen`` (position [m],
        quaternion, arrays the probe holds or copies of them): the clock advanced as
        ``pieces`` sub-motions of ``h`` [s] would advance it, the pose seen."""
        for _ in range(pieces):
            self._time += h
        self._last_pose = seen
        self._advance_asleep(h, pieces)

    def _may_sleep(self, travel_m: float) -> bool:
        """Whether a step whose probe moved ``travel_m`` [m] (:meth:`probe_travel_m`; 0
        without a sweep) to its present pose sleeps (see :meth:`step`)."""
        rest = self._rest_check()
        if rest is None:
            return False
        points, boundary, reach = rest.points, rest.boundary, rest.reach_m
        # Every probe point stays within its travel of where it ends: a point clear of the
        # probe at its end by travel + reach is clear by reach all along the way.
        reach += travel_m
        if not self.probe.clearance_m(points, reach) > reach:
            return False
        # The tunnelling check a step makes with no force (a probe inside the body, away
        # from every skin point, reports it; a sleeping step would not).
        return not self._behind_skin(boundary)
