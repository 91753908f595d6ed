"""MAVLink 2 vehicles (ArduPilot Copter) over UDP or serial: :class:`MavlinkDriver`.

The driver is a ground station for one vehicle. ``configure`` opens the link, starts a receive
thread and a heartbeat thread, waits for the vehicle's HEARTBEAT (``init_timeout``), then asks
for telemetry streams (``MAV_CMD_SET_MESSAGE_INTERVAL``) and the home position. While
configured it

* keeps a telemetry cache (position, attitude, battery, mode, armed flag, status texts) stamped
  with the driver's clock (:meth:`MavlinkDriver.telemetry`);
* sends its own GCS HEARTBEAT every ``heartbeat_period`` seconds, steadily, so that the
  vehicle's GCS failsafe (ArduPilot ``FS_GCS_ENABLE``) can be used: the profile's
  ``gcs_failsafe`` sets ``FS_GCS_ENABLE``/``FS_GCS_TIMEOUT`` at configure (PARAM_SET, checked
  against the PARAM_VALUE echo) and checks that the vehicle watches this driver's system id;
* watches the vehicle: no valid HEARTBEAT within ``heartbeat_timeout`` is a fault
  (:class:`~temoto.errors.DriverTimeoutError`, or :class:`~temoto.errors.DriverOperationError`
  when only frames with a bad CRC arrived), and so is an enabled SYS_STATUS sensor reported
  unhealthy (a hardware error: overheating motors, low battery voltage, ...); each telemetry
  stream it asked for (GLOBAL_POSITION_INT, ATTITUDE) is stale after 3 of its periods without
  a message (a :class:`~temoto.errors.DriverTimeoutError` naming the stream); frames with a
  bad CRC from the vehicle are counted, and a fault only when 5 fall within 1 s
  (:class:`~temoto.drivers.supervision.FaultWindow`); when the vehicle is healthy again the
  driver reports itself recovered;
* trusts nothing on the wire: each UDP datagram is parsed on its own, and a ``udpin`` link
  replies only to the address the target vehicle's valid frames (its system and component id)
  come from; garbage from other addresses is counted and never a fault;
* sends commands as COMMAND_LONG (COMMAND_INT for positions), resending up to
  ``command_retries`` times when no COMMAND_ACK arrives within ``command_timeout``; a result
  other than ``MAV_RESULT_ACCEPTED`` raises :class:`~temoto.errors.MavlinkCommandError` with the
  command id and the result, and the STATUSTEXTs the vehicle sent with it: those that arrive
  within :attr:`MavlinkDriver.STATUS_TEXT_WINDOW` (0.5 s) after a FAILED or DENIED ack are
  waited for (ArduPilot acknowledges at once and sends "PreArm: ..." after the ack).

**Missions and parameters.** :meth:`MavlinkDriver.upload_mission`,
:meth:`~MavlinkDriver.download_mission` and :meth:`~MavlinkDriver.clear_mission` speak the
MAVLink mission protocol with MISSION_INT (each step waits ``mission_timeout``, 1.5 s, and is
resent up to ``mission_retries``, 5, times, the protocol's defaults; a refusing MISSION_ACK is a
:class:`~temoto.errors.MavlinkMissionError` naming the ``MAV_MISSION_RESULT``);
:meth:`~MavlinkDriver.start_mission` arms in GUIDED and sends ``MAV_CMD_MISSION_START`` as
ArduCopter expects; MISSION_CURRENT and MISSION_ITEM_REACHED become
:attr:`~MavlinkDriver.mission_progress` (and listeners). :meth:`~MavlinkDriver.get_param` and
:meth:`~MavlinkDriver.set_param` read and write one parameter (PARAM_REQUEST_READ / PARAM_SET →
PARAM_VALUE, typed by its ``MAV_PARAM_TYPE``, integers carried as floats as ArduPilot does).

**Safe state** (``safe_state:``, :attr:`MavlinkDriver.safe_states`): ``loiter`` (default),
``brake``, ``land`` or ``rtl``. On the ground (disarmed, or armed and landed) nothing is sent;
in the air the driver sets that ArduCopter mode (``MAV_CMD_DO_SET_MODE``) and waits at most
:attr:`MavlinkDriver.SAFE_CONFIRM_WAIT` for the ack or a heartbeat in that mode; a vehicle that
refuses LOITER or BRAKE (no position estimate) is sent LAND.

Flight modes are ArduCopter's (``GUIDED``, ``LOITER``, ``RTL``, ``LAND``, ...);
:meth:`~MavlinkDriver.takeoff` switches to GUIDED first, :meth:`~MavlinkDriver.goto` sends
``MAV_CMD_DO_REPOSITION`` (GUIDED), :meth:`~MavlinkDriver.land` and
:meth:`~MavlinkDriver.return_to_launch` send ``MAV_CMD_NAV_LAND`` and
``MAV_CMD_NAV_RETURN_TO_LAUNCH``.

:meth:`MavlinkDriver.detect` finds vehicles by listening only: it opens each link, parses the
HEARTBEATs that arrive within its timeout and sends nothing at all.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import math
import socket
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any, ClassVar, Final

from temoto.clock import Clock
from temoto.drivers.base import Driver, DriverState
from temoto.drivers.capabilities import GeoPoint, MissionItem, MissionProgress, VehicleTelemetry
from temoto.drivers.mavlink import missions
from temoto.drivers.mavlink import protocol as p
from temoto.drivers.mavlink.detect import detect
from temoto.drivers.mavlink.link import Link, LinkSpec, open_link, parse_link
from temoto.drivers.mavlink.protocol import Codec, Message
from temoto.drivers.mavlink.settings import PROFILE_FIELDS, failsafe_params, read_sim
from temoto.drivers.mavlink.sim import SimVehicle
from temoto.drivers.profile import Field, ProfileReader
from temoto.drivers.sim import Simulator
from temoto.drivers.supervision import FaultWindow, StreamAge
from temoto.errors import (
    DriverError,
    DriverInitError,
    DriverOperationError,
    DriverTimeoutError,
    MavlinkCommandError,
    MavlinkMissionError,
    StateError,
)

__all__ = ["MavlinkDriver"]

logger = logging.getLogger(__name__)

_POLL: Final = 0.05  # real seconds per socket read (also how often waiters re-check)
_UNKNOWN_VOLTAGE: Final = 65535
#: Streams asked for in configure: message → share of ``stream_rate`` (capped at 2 Hz if < 1).
_STREAMS: Final[Mapping[str, float]] = {
    "GLOBAL_POSITION_INT": 1.0,
    "ATTITUDE": 1.0,
    "SYS_STATUS": 0.2,
    "BATTERY_STATUS": 0.2,
    "EXTENDED_SYS_STATE": 0.2,
}
_SEVERITY_LEVEL: Final = {0: 50, 1: 50, 2: 50, 3: 40, 4: 30, 5: 20, 6: 20, 7: 10}
#: The streams whose age is supervised (when the vehicle accepted their interval).
_SUPERVISED: Final = ("GLOBAL_POSITION_INT", "ATTITUDE")
#: Safe state → the ArduCopter mode it sets in the air.
_SAFE_MODES: Final[Mapping[str, str]] = {
    "loiter": "LOITER",
    "brake": "BRAKE",
    "land": "LAND",
    "rtl": "RTL",
}
#: The parameter naming the GCS system id whose heartbeats the failsafe watches (the older
#: name, and the one newer ArduPilot firmware uses).
_GCS_SYSID_PARAMS: Final = ("SYSID_MYGCS", "MAV_GCS_SYSID")
_TEXT_QUIET: Final = 0.1  # once a refusal's text came: seconds without another end the wait


class MavlinkDriver(Driver):
    """An ArduPilot Copter over MAVLink 2 (implements :class:`~temoto.drivers.Vehicle`).

    Args:
        name: The device's name in its profile.
        link: Where the vehicle is: ``udpin:HOST:PORT`` (listen, the usual ground-station
            setup), ``udpout:HOST:PORT`` or ``serial:DEVICE?baud=N``.
        clock: Stamps, heartbeat periods and timeouts.
        system_id: The vehicle's system id, or None for the first autopilot heard.
        component_id: The autopilot's component id.
        gcs_system_id: This ground station's system id.
        gcs_component_id: This ground station's component id.
        heartbeat_period: Seconds between the driver's own heartbeats.
        heartbeat_timeout: Seconds without a vehicle heartbeat that make a fault.
        init_timeout: Seconds ``configure`` waits for the first heartbeat.
        command_timeout: Seconds to wait for one COMMAND_ACK.
        command_retries: Resends after a missing COMMAND_ACK (and a missing PARAM_VALUE).
        mission_timeout: Seconds one step of a mission transfer waits (the MAVLink mission
            protocol's default, 1.5 s).
        mission_retries: Resends of a mission transfer's step that went unanswered (the
            protocol's default, 5).
        stream_rate: Position and attitude rate (Hz) asked of the vehicle; 0 asks for nothing.
        status_texts: How many STATUSTEXT messages the telemetry keeps.
        gcs_failsafe: The vehicle's GCS failsafe, set at configure: ``{"enable": N}``
            (``FS_GCS_ENABLE``, 0..7) and/or ``{"timeout": S}`` (``FS_GCS_TIMEOUT``, 2..120 s);
            None or empty leaves the vehicle's settings alone.

    Raises:
        ValueError: A bad argument (``from_profile`` reports it as a ``ProfileError``).
    """

    kind: ClassVar[str] = "mavlink"

    #: ``loiter`` (default), ``brake``, ``land``, ``rtl``: the ArduCopter mode set in the air.
    safe_states: ClassVar[tuple[str, ...]] = tuple(_SAFE_MODES)

    #: Seconds (clock) after a FAILED or DENIED ack during which the vehicle's STATUSTEXTs are
    #: attached to the error (ArduPilot sends the reason after the ack).
    STATUS_TEXT_WINDOW: ClassVar[float] = 0.5

    #: Seconds (clock) :meth:`make_safe` waits for the vehicle to confirm its mode.
    SAFE_CONFIRM_WAIT: ClassVar[float] = 0.3

    def __init__(
        self,
        name: str,
        *,
        link: str,
        clock: Clock | None = None,
        system_id: int | None = None,
        component_id: int = 1,
        gcs_system_id: int = 255,
        gcs_component_id: int = 190,
        heartbeat_period: float = 1.0,
        heartbeat_timeout: float = 3.0,
        init_timeout: float = 5.0,
        command_timeout: float = 1.0,
        command_retries: int = 2,
        mission_timeout: float = 1.5,
        mission_retries: int = 5,
        stream_rate: float = 10.0,
        status_texts: int = 20,
        gcs_failsafe: Mapping[str, float] | None = None,
    ) -> None:
        super().__init__(name, clock=clock)
        self.link_spec: LinkSpec = parse_link(link)
        for key, ident, low in (
            ("system_id", system_id, 1),
            ("component_id", component_id, 0),
            ("gcs_system_id", gcs_system_id, 1),
            ("gcs_component_id", gcs_component_id, 0),
        ):
            if ident is not None and (
                isinstance(ident, bool) or not isinstance(ident, int) or not low <= ident <= 255
            ):
                raise ValueError(f"{key} must be an integer {low}..255, got {ident!r}")
        for key, value in (
            ("heartbeat_period", heartbeat_period),
            ("heartbeat_timeout", heartbeat_timeout),
            ("init_timeout", init_timeout),
            ("command_timeout", command_timeout),
            ("mission_timeout", mission_timeout),
        ):
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{key} must be a positive number of seconds, got {value!r}")
        if not (isinstance(command_retries, int) and 0 <= command_retries <= 10):
            raise ValueError(f"command_retries must be an integer 0..10, got {command_retries!r}")
        if not (isinstance(mission_retries, int) and 0 <= mission_retries <= 20):
            raise ValueError(f"mission_retries must be an integer 0..20, got {mission_retries!r}")
        if not (math.isfinite(stream_rate) and 0 <= stream_rate <= 1000):
            raise ValueError(f"stream_rate must be 0..1000 Hz, got {stream_rate!r}")
        if not (isinstance(status_texts, int) and status_texts >= 1):
            raise ValueError(f"status_texts must be a positive integer, got {status_texts!r}")
        self.system_id = system_id
        self.component_id = component_id
        self.heartbeat_period = float(heartbeat_period)
        self.heartbeat_timeout = float(heartbeat_timeout)
        self.init_timeout = float(init_timeout)
        self.command_timeout = float(command_timeout)
        self.command_retries = command_retries
        self.mission_timeout = float(mission_timeout)
        self.mission_retries = mission_retries
        self.stream_rate = float(stream_rate)
        #: ArduPilot parameter → value, set at configure (from ``gcs_failsafe``).
        self.failsafe_params: dict[str, float] = failsafe_params(gcs_failsafe)
        timeout = self.failsafe_params.get("FS_GCS_TIMEOUT")
        if timeout is not None and self.heartbeat_period > timeout / 2:
            raise ValueError(
                f"heartbeat_period must be at most half the GCS failsafe timeout ({timeout:g} s),"
                f" got {self.heartbeat_period:g}: one lost heartbeat must not trigger it"
            )
        self._gcs_ids = (gcs_system_id, gcs_component_id)
        self._codec = Codec(gcs_system_id, gcs_component_id)
        self._link: Link | None = None
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._cond = threading.Condition()  # the cache and the acks; notified on every read
        self._watch = threading.Condition()  # wakes the heartbeat thread
        self._command_lock = threading.Lock()
        self._param_lock = threading.Lock()  # one public parameter exchange at a time
        self._mission_lock = threading.Lock()  # one mission transfer at a time
        self._mission_listeners: list[Callable[[MissionProgress], None]] = []
        self._eval_lock = threading.Lock()
        self._texts: collections.deque[str] = collections.deque(maxlen=status_texts)
        self._ages: dict[str, StreamAge] = {}
        self._bad_window = FaultWindow()
        self._reset()

    def _reset(self) -> None:
        self._target: int | None = self.system_id
        self._last_hb: float | None = None
        self._last_msg = self.clock.monotonic()
        self._autopilot = p.MAV_AUTOPILOT_INVALID
        self._armed = False
        self._custom_mode = 0
        self._position = (0.0, 0.0, 0.0)
        self._attitude = (0.0, 0.0, 0.0)
        self._voltage = math.nan
        self._remaining = -1
        self._home: tuple[float, float, float] | None = None
        self._landed_state = 0
        #: When this driver last asked the vehicle to arm or take off (clock seconds): until a
        #: newer heartbeat arrives, "disarmed" and "landed" are not to be trusted.
        self._moved_at: float | None = None
        self._landed_at: float | None = None  # when EXTENDED_SYS_STATE last said
        self._unhealthy: tuple[str, ...] = ()
        self._bad_at_hb = 0  # the vehicle's bad frames when its newest heartbeat came
        self._vehicle_bad = 0  # bad frames from the vehicle's address (or a serial line)
        self._acks: dict[int, tuple[int, int]] = {}  # command → (result, arrival number)
        self._ack_count = 0
        self._text_count = 0
        self._mine = False  # the current FAULT was reported by this driver's watch
        self._texts.clear()
        self._received = 0
        self._params: dict[str, tuple[float, int]] = {}  # name → (value, MAV_PARAM_TYPE)
        self._param_count = 0  # PARAM_VALUE arrivals
        self._param_seen: dict[str, int] = {}  # name → arrival number of its newest value
        #: name → MAV_PARAM_ERROR of a PARAM_ERROR about it (newer ArduPilot answers an unknown
        #: name or a bad value so; older ones stay silent), since its exchange began.
        self._param_errors: dict[str, int] = {}
        #: Mission-transfer messages for this GCS: (arrival number, message), newest last.
        self._mission_rx: collections.deque[tuple[int, Message]] = collections.deque(maxlen=64)
        self._mission_seq = 0
        self._mission_total = 0  # items of the mission this driver uploaded or downloaded
        self._progress = MissionProgress()
        self._notify: list[tuple[Callable[[MissionProgress], None], MissionProgress]] = []
        self._ages.clear()
        self._stale: StreamAge | None = None  # the stream whose staleness is the fault
        self._bad_window.clear()
        self._drained_at: float | None = None  # clock time the link was last read empty
        self._beat_now = False  # send a heartbeat at once (the vehicle's address is new)
        self._foreign = 0  # bad frames from addresses other than the vehicle's
        self._foreign_seen: set[Any] = set()

    # ---- profile -----------------------------------------------------------------------------

    #: The keys of a profile entry (:mod:`~temoto.drivers.mavlink.settings`); an entry from
    #: :meth:`detect` is accepted as it is. The constructor checks the keys that depend on
    #: each other (``heartbeat_period`` against the GCS failsafe's timeout).
    profile_fields: ClassVar[Mapping[str, Field[Any]]] = PROFILE_FIELDS

    @classmethod
    def simulate(
        cls, name: str, config: Mapping[str, Any], *, clock: Clock
    ) -> tuple[Simulator, dict[str, Any]]:
        """A simulated vehicle for this profile entry, and the settings to reach it.

        The simulator (not started: call ``start()`` or use it as a context manager) streams
        to a free UDP port on 127.0.0.1, and the returned settings are ``config`` with
        ``link: udpin:127.0.0.1:<that port>`` (and without ``sim``). The entry's optional
        ``sim`` mapping sets the model (see :class:`~temoto.drivers.mavlink.sim.SimVehicle`).

        Args:
            name: The device's name.
            config: Its profile settings.
            clock: The clock the simulator steps on.

        Returns:
            The simulator and the driver's settings.

        Raises:
            ProfileError: A bad ``sim`` mapping.
        """
        sim_kwargs = read_sim(ProfileReader(name), config.get("sim", {}), "sim")
        port = _free_udp_port()
        system_id = config.get("system_id")
        sim = SimVehicle(
            name,
            clock=clock,
            gcs=[("127.0.0.1", port)],
            system_id=system_id if isinstance(system_id, int) else 1,
            **sim_kwargs,
        )
        settings = {k: v for k, v in config.items() if k != "sim"}
        settings["link"] = f"udpin:127.0.0.1:{port}"
        return sim, settings

    # ---- discovery ---------------------------------------------------------------------------

    @classmethod
    def detect(
        cls, links: Sequence[Any] | None = None, *, timeout: float = 2.5
    ) -> list[dict[str, Any]]:
        """The vehicles heard on MAVLink links, as profile device entries (listening only).

        Each link is opened with :mod:`~temoto.drivers.mavlink.link` and its bytes are parsed
        with :class:`~temoto.drivers.mavlink.protocol.Codec` for ``timeout`` real seconds.
        Nothing at all is sent: no heartbeat of our own, no request, so no vehicle even learns
        that a ground station looked. Every valid HEARTBEAT is a sign of life; those of ground
        stations (``MAV_TYPE_GCS``) and of components without an autopilot
        (``MAV_AUTOPILOT_INVALID``: companion computers, cameras, gimbals) are skipped, and
        the rest are vehicles, logged at INFO with their ``MAV_TYPE`` and ``MAV_AUTOPILOT``
        names (and a warning for an autopilot other than ArduPilot, which ``configure``
        refuses). A serial link without ``?baud=`` is tried at 57600, 115200 and 921600 baud in
        that order, stopping at the first rate at which a valid HEARTBEAT arrives. A link that
        cannot be opened (a port in use, a missing device) is skipped with a warning. A
        ``udpout:`` link only hears a vehicle that streams to it unasked.

        Args:
            links: Link URLs as in a profile's ``link`` (``udpin:``/``udp:``, ``udpout:``,
                ``serial:``); a single string is one link. None: every serial port pyserial
                lists (if pyserial is installed), then ``udpin:0.0.0.0:14550``, where
                autopilots and telemetry radios usually send to a ground station.
            timeout: Real seconds to listen on each link (and on each baud rate tried). The
                default, 2.5, hears at least two heartbeats of a vehicle sending one a second.

        Returns:
            One entry per vehicle (system id) heard, link by link in the order looked at:
            ``{"driver": "mavlink", "link": ..., "system_id": ..., "component_id": ...}``, the
            ``link`` as given (with the baud rate that worked for a serial link given without
            one), the component its autopilot's (1 when heard). :meth:`from_profile` accepts
            each as it is. Empty when no vehicle was heard.

        Raises:
            ValueError: ``timeout`` is not a positive number of seconds, or a link is not a URL
                in a scheme the link module knows (raised before any link is opened).
            DriverUnavailableError: A serial link, but pyserial is not installed.
        """
        return detect(cls.kind, links, timeout)

    # ---- lifecycle hooks ---------------------------------------------------------------------

    def on_configure(self) -> None:
        """Open the link, start the threads, wait for a heartbeat, ask for streams.

        Raises:
            DriverInitError: The link cannot be opened, or the vehicle is not an ArduPilot.
            DriverTimeoutError: No heartbeat within ``init_timeout``.
        """
        try:
            self._link = open_link(self.link_spec)
        except OSError as err:
            raise DriverInitError(f"{self.name}: cannot open {self.link_spec}: {err}") from err
        self._stop.clear()
        with self._cond:
            self._reset()
        self._threads = [
            threading.Thread(target=self._rx_loop, name=f"temoto-mavlink-{self.name}-rx"),
            threading.Thread(target=self._watch_loop, name=f"temoto-mavlink-{self.name}-hb"),
        ]
        for thread in self._threads:
            thread.start()
        if not self._await(lambda: self._last_hb is not None, self.init_timeout):
            raise DriverTimeoutError(
                f"{self.name}: no heartbeat from a vehicle on {self.link_spec}"
                f" within {self.init_timeout:g} s"
            )
        if self._autopilot != p.MAV_AUTOPILOT_ARDUPILOTMEGA:
            raise DriverInitError(
                f"{self.name}: system {self._target} is not an ArduPilot autopilot"
                f" (MAV_AUTOPILOT {self._autopilot}); only ArduCopter modes are supported"
            )
        self._request_streams()
        self._configure_failsafe()

    def on_shutdown(self) -> None:
        """Stop and join the threads, close the link."""
        self._stop.set()
        with self._watch:
            self._watch.notify_all()
        with self._cond:
            self._cond.notify_all()
        for thread in self._threads:
            if thread is not threading.current_thread():
                thread.join()
        self._threads = []
        if self._link is not None:
            self._link.close()
            self._link = None

    def _request_streams(self) -> None:
        """Ask for the telemetry streams; supervise those the vehicle accepted."""
        if self.stream_rate <= 0:
            return
        for msg, share in _STREAMS.items():
            hz = self.stream_rate * share if share >= 1 else min(self.stream_rate, 2.0)
            accepted = self._best_effort(p.MAV_CMD_SET_MESSAGE_INTERVAL, p.MSG_ID[msg], 1e6 / hz)
            if accepted and msg in _SUPERVISED:
                age = StreamAge(msg, 1.0 / hz)
                age.feed(self.clock.monotonic())  # due from now on, even if none ever comes
                with self._cond:
                    self._ages[msg] = age
        self._best_effort(p.MAV_CMD_REQUEST_MESSAGE, p.MSG_ID["HOME_POSITION"])

    def _best_effort(self, command: int, *params: float) -> bool:
        try:
            self._send_command(command, params, retries=0, texts=False)
        except DriverError as err:
            logger.info("driver %s: %s", self.name, err)
            return False
        return True

    # ---- parameters (only what configure needs; the full protocol is not here) ---------------

    def _configure_failsafe(self) -> None:
        """Set the GCS failsafe parameters and check that the failsafe watches this driver.

        Raises:
            DriverInitError: The vehicle kept another value, or watches another GCS system id.
            DriverTimeoutError: No PARAM_VALUE came back.
        """
        if not self.failsafe_params:
            return
        for name, value in self.failsafe_params.items():
            self._set_param(name, value)
        watched: float | None = None
        for name in _GCS_SYSID_PARAMS:
            got = self._read_param(name, retries=0)
            if got is not None:
                watched = got[0]
                break
        own = self._gcs_ids[0]
        if watched is None:
            logger.warning(
                "driver %s: the vehicle did not say which GCS system id its failsafe watches"
                " (%s); it must be %d, this driver's gcs_system_id",
                self.name,
                " or ".join(_GCS_SYSID_PARAMS),
                own,
            )
        elif round(watched) != own:
            raise DriverInitError(
                f"{self.name}: the vehicle's GCS failsafe watches system {round(watched)}"
                f" ({'/'.join(_GCS_SYSID_PARAMS)}), not this driver's gcs_system_id {own}:"
                " it would not notice this driver stopping; set one to the other"
            )

    def _read_param(self, name: str, *, retries: int | None = None) -> tuple[float, int] | None:
        """Ask for one parameter (PARAM_REQUEST_READ): its value and type, or None."""
        tries = 1 + (self.command_retries if retries is None else retries)
        return self._param_exchange("PARAM_REQUEST_READ", name, tries, param_index=-1)

    def _set_param(self, name: str, value: float) -> None:
        """Set one parameter (PARAM_SET) and check the PARAM_VALUE echo.

        Raises:
            DriverInitError: The vehicle has no such parameter or kept another value.
            DriverTimeoutError: No PARAM_VALUE.
        """
        current = self._read_param(name)
        if current is None:
            raise DriverTimeoutError(
                f"{self.name}: no PARAM_VALUE for {name} (does this firmware have it?)"
            )
        if _same(current[0], value):
            logger.info("driver %s: %s is %g already", self.name, name, value)
            return
        tries = 1 + self.command_retries
        got = self._param_exchange(
            "PARAM_SET", name, tries, param_value=value, param_type=current[1]
        )
        if got is None:
            raise DriverTimeoutError(
                f"{self.name}: no PARAM_VALUE after setting {name} in {tries} tries"
                f" of {self.command_timeout:g} s"
            )
        if not _same(got[0], value):
            raise DriverInitError(
                f"{self.name}: the vehicle kept {name} = {got[0]:g} (asked for {value:g})"
            )
        logger.info("driver %s: %s %g -> %g", self.name, name, current[0], value)

    def _param_exchange(
        self, message: str, name: str, tries: int, **fields: Any
    ) -> tuple[float, int] | None:
        """Send ``message`` about parameter ``name`` until a PARAM_VALUE of it answers.

        Up to ``tries`` sends, each waiting ``command_timeout``; the answer's value and type,
        or None (also at once when a PARAM_ERROR about it came: :attr:`_param_errors`).
        """
        with self._cond:
            target = self._target or 1
            self._param_errors.pop(name, None)
        for _ in range(tries):
            with self._cond:
                start = self._param_count
            self._write(
                self._codec.encode(
                    message,
                    target_system=target,
                    target_component=self.component_id,
                    param_id=name.encode(),
                    **fields,
                )
            )
            got = self._await_param(name, start)
            if got is not None:
                return got
            with self._cond:
                if name in self._param_errors:
                    break  # the vehicle answered: asking again changes nothing
        return None

    def _await_param(self, name: str, after: int) -> tuple[float, int] | None:
        def arrived() -> bool:
            return self._param_seen.get(name, 0) > after or name in self._param_errors

        if not self._await(arrived, self.command_timeout):
            return None
        with self._cond:
            if self._param_seen.get(name, 0) > after:
                return self._params[name]
        return None

    def _param_failure(self, name: str, what: str) -> DriverError:
        """The error of a parameter exchange that got no PARAM_VALUE (after its retries)."""
        with self._cond:
            error = self._param_errors.get(name)
        if error is not None:
            return DriverOperationError(
                f"{self.name}: {what} {name}: the vehicle answered PARAM_ERROR"
                f" {p._enum_name('MAV_PARAM_ERROR', error)}"
            )
        tries = 1 + self.command_retries
        hint = " (does this firmware have it?)" if what == "reading" else ""
        return DriverTimeoutError(
            f"{self.name}: no PARAM_VALUE for {name} in {tries} tries of"
            f" {self.command_timeout:g} s ({what}){hint}"
        )

    # ---- parameters (public) ------------------------------------------------------------------

    def get_param(self, name: str) -> float | int:
        """Read one parameter of the vehicle (``PARAM_REQUEST_READ`` → ``PARAM_VALUE``).

        Sent up to ``1 + command_retries`` times, each waiting ``command_timeout``. The value
        is typed by the answer's ``MAV_PARAM_TYPE``: an ``int`` for the integer types (which
        ArduPilot sends as a float holding the integer, its "C cast" encoding), a ``float``
        for ``REAL32``.

        Args:
            name: The parameter's name (``WPNAV_SPEED``; at most 16 characters).

        Returns:
            The value.

        Raises:
            ValueError: Not a parameter name.
            StateError: The driver is not configured.
            DriverTimeoutError: No PARAM_VALUE of it (a name the firmware does not have goes
                unanswered too; the message says so).
        """
        self._check_param_name(name)
        self._require_link("get_param")
        with self._param_lock:
            got = self._read_param(name)
        if got is None:
            raise self._param_failure(name, "reading")
        return missions.typed_param_value(*got)

    def set_param(self, name: str, value: float) -> float | int:
        """Set one parameter of the vehicle (``PARAM_SET`` → the ``PARAM_VALUE`` echo).

        The parameter is read first for its type (unless this driver has seen it); an integer
        type takes only integers in its range, and no more than 2**24 in size (ArduPilot carries
        every value as a float32). ``PARAM_SET`` is sent up to ``1 + command_retries`` times,
        each waiting ``command_timeout`` for the echo; a value equal to the current one is
        not sent again.

        Args:
            name: The parameter's name (at most 16 characters).
            value: The new value.

        Returns:
            The value the vehicle reports it now holds.

        Raises:
            ValueError: Not a parameter name, or a value its type cannot hold.
            StateError: The driver is not configured.
            DriverTimeoutError: No PARAM_VALUE came back (for the read or the set).
            DriverOperationError: The vehicle kept another value.
        """
        self._check_param_name(name)
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ValueError(f"{name}: a parameter value must be a number, got {value!r}")
        if not math.isfinite(value):
            raise ValueError(f"{name}: a parameter value must be finite, got {value!r}")
        self._require_link("set_param")
        tries = 1 + self.command_retries
        with self._param_lock:
            with self._cond:
                known = self._params.get(name)
            current = known if known is not None else self._read_param(name)
            if current is None:
                raise self._param_failure(name, "reading")
            param_type = current[1]
            missions.check_param_value(name, value, param_type)
            if known is not None or not _same(current[0], value):
                got = self._param_exchange(
                    "PARAM_SET", name, tries, param_value=float(value), param_type=param_type
                )
                if got is None:
                    raise self._param_failure(name, "setting")
                current = got
        if not _same(current[0], value):
            raise DriverOperationError(
                f"{self.name}: the vehicle kept {name} = {current[0]:g} (asked for {value:g})"
            )
        logger.info("driver %s: %s = %g", self.name, name, current[0])
        return missions.typed_param_value(*current)

    def _check_param_name(self, name: str) -> None:
        if not (
            isinstance(name, str) and 0 < len(name) <= p.PARAM_ID_LEN and name.isascii()
        ) or any(c.isspace() or c == "\x00" for c in name):
            raise ValueError(
                f"{self.name}: a parameter name is 1..{p.PARAM_ID_LEN} ASCII characters without"
                f" spaces, got {name!r}"
            )

    def _require_link(self, what: str) -> None:
        if self._link is None or self.state in (DriverState.UNCONFIGURED, DriverState.FINALIZED):
            raise StateError(f"{self.name}: {what} needs a configured driver ({self.state.value})")

    # ---- missions -----------------------------------------------------------------------------

    def upload_mission(self, items: Sequence[MissionItem]) -> None:
        """Replace the vehicle's mission (the MAVLink mission protocol, MISSION_INT).

        Sends ``MISSION_COUNT`` and answers each ``MISSION_REQUEST_INT`` (and the older
        ``MISSION_REQUEST``) with the ``MISSION_ITEM_INT`` asked for, until the vehicle's
        ``MISSION_ACK``. ArduPilot keeps its home position as item 0, so the items go as
        1..n after a placeholder item 0 (the home position when known). Each step waits
        ``mission_timeout``; with nothing heard, the last message is sent again, up to
        ``mission_retries`` times; a request for an earlier item is answered again, and a
        ``MAV_MISSION_INVALID_SEQUENCE`` ack (ArduPilot's answer to a stray copy of an item)
        does not end the upload. Positions go in ``MAV_FRAME_GLOBAL_RELATIVE_ALT``
        (altitudes above home).

        Args:
            items: The mission (see :class:`~temoto.drivers.capabilities.MissionItem`).

        Raises:
            ValueError: No items, too many, or not MissionItems.
            StateError: The driver is not configured.
            MavlinkMissionError: The vehicle's MISSION_ACK refused it (the message names the
                ``MAV_MISSION_RESULT``, and the item the vehicle asked for last).
            DriverTimeoutError: A step went unanswered (the message names it).
        """
        mission = list(items)
        if not mission:
            raise ValueError(f"{self.name}: a mission needs at least one item")
        for index, item in enumerate(mission, 1):
            if not isinstance(item, MissionItem):
                raise ValueError(
                    f"{self.name}: mission item {index} is not a MissionItem: {type(item).__name__}"
                )
        if len(mission) >= 0xFFFF:
            raise ValueError(f"{self.name}: {len(mission)} items: too many for MAVLink")
        self._require_link("upload_mission")
        with self._mission_lock:
            target = self._target_ids()
            with self._cond:
                home = self._home
            frames = [self._item_frame(0, missions.home_fields(home), target)]
            frames += [
                self._item_frame(seq, missions.item_fields(item), target)
                for seq, item in enumerate(mission, 1)
            ]
            count = len(frames)
            last = self._codec.encode(
                "MISSION_COUNT",
                target_system=target[0],
                target_component=target[1],
                count=count,
                mission_type=p.MAV_MISSION_TYPE_MISSION,
            )
            with self._cond:
                seen = self._mission_seq
                self._mission_total = 0
            self._write(last)
            step = "MISSION_REQUEST for item 0 after MISSION_COUNT"
            asked = -1  # the highest item the vehicle asked for
            tries = 0
            while True:
                got = self._await_mission(seen, missions.upload_answer)
                if got is None:
                    tries += 1
                    if tries > self.mission_retries:
                        raise DriverTimeoutError(
                            f"{self.name}: mission upload: no {step} in"
                            f" {1 + self.mission_retries} tries of {self.mission_timeout:g} s"
                        )
                    self._write(last)
                    continue
                seen, msg = got
                if msg.name == "MISSION_ACK":
                    result = msg.get_int("type")
                    if result == p.MAV_MISSION_INVALID_SEQUENCE:
                        # ArduPilot's answer to a copy of an item it did not ask for (ours
                        # after a lost or doubled request): the upload goes on.
                        logger.debug("driver %s: mission upload: %s", self.name, msg.fields)
                        continue
                    if result != p.MAV_MISSION_ACCEPTED:
                        where = f" at item {asked}" if asked >= 0 else ""
                        raise MavlinkMissionError(
                            f"{self.name}: mission upload refused{where}:"
                            f" {p.mission_result_name(result)}",
                            result=result,
                        )
                    if asked < count - 1:
                        raise DriverOperationError(
                            f"{self.name}: mission upload: the vehicle accepted after item"
                            f" {asked} of {count - 1}: it does not hold the whole mission"
                        )
                    break
                seq = msg.get_int("seq")
                if not 0 <= seq < count:
                    raise DriverOperationError(
                        f"{self.name}: mission upload: the vehicle asked for item {seq},"
                        f" the mission has 0..{count - 1}"
                    )
                tries = 0  # progress: each step has its own retries
                asked = max(asked, seq)
                last = frames[seq]
                self._write(last)
                step = (
                    "MISSION_ACK after the last item"
                    if seq == count - 1
                    else f"MISSION_REQUEST for item {seq + 1}"
                )
            with self._cond:
                self._mission_total = len(mission)
                self._progress = MissionProgress(total=len(mission))
        logger.info("driver %s: mission of %d items uploaded", self.name, len(mission))

    def download_mission(self) -> list[MissionItem]:
        """The vehicle's mission (``MISSION_REQUEST_LIST``, then each ``MISSION_REQUEST_INT``).

        Item 0, ArduPilot's home position, is left out. Each step waits ``mission_timeout``
        and is sent again up to ``mission_retries`` times; the transfer ends with a
        ``MISSION_ACK`` (accepted) to the vehicle.

        Returns:
            The items, first first.

        Raises:
            StateError: The driver is not configured.
            DriverOperationError: An item this driver cannot represent (its command or frame is
                named), or the vehicle refused the transfer.
            DriverTimeoutError: A step went unanswered (the message names it).
        """
        self._require_link("download_mission")
        with self._mission_lock:
            target = self._target_ids()
            ids = {"target_system": target[0], "target_component": target[1]}
            request = self._codec.encode(
                "MISSION_REQUEST_LIST", **ids, mission_type=p.MAV_MISSION_TYPE_MISSION
            )
            with self._cond:
                seen = self._mission_seq
            got = self._mission_step(request, seen, missions.count_answer, "MISSION_COUNT")
            seen, msg = got
            count = msg.get_int("count")
            raw: list[Message] = []
            for seq in range(count):
                request = self._codec.encode(
                    "MISSION_REQUEST_INT", **ids, seq=seq, mission_type=p.MAV_MISSION_TYPE_MISSION
                )
                seen, msg = self._mission_step(
                    request, seen, missions.item_answer(seq), f"MISSION_ITEM_INT {seq} of {count}"
                )
                raw.append(msg)
            self._write(
                self._codec.encode(
                    "MISSION_ACK",
                    **ids,
                    type=p.MAV_MISSION_ACCEPTED,
                    mission_type=p.MAV_MISSION_TYPE_MISSION,
                )
            )
            with self._cond:
                home = self._home
        items = [missions.decoded_item(self.name, msg, home) for msg in raw[1:]]
        with self._cond:
            self._mission_total = len(items)
        return items

    def clear_mission(self) -> None:
        """Delete the vehicle's mission (``MISSION_CLEAR_ALL`` → ``MISSION_ACK``).

        Raises:
            StateError: The driver is not configured.
            MavlinkMissionError: The vehicle refused (its ``MAV_MISSION_RESULT`` named).
            DriverTimeoutError: No MISSION_ACK.
        """
        self._require_link("clear_mission")
        with self._mission_lock:
            target = self._target_ids()
            request = self._codec.encode(
                "MISSION_CLEAR_ALL",
                target_system=target[0],
                target_component=target[1],
                mission_type=p.MAV_MISSION_TYPE_MISSION,
            )
            with self._cond:
                seen = self._mission_seq
            _, msg = self._mission_step(
                request, seen, missions.ack_answer, "MISSION_ACK to MISSION_CLEAR_ALL"
            )
            result = msg.get_int("type")
            if result != p.MAV_MISSION_ACCEPTED:
                raise MavlinkMissionError(
                    f"{self.name}: mission clear refused: {p.mission_result_name(result)}",
                    result=result,
                )
            with self._cond:
                self._mission_total = 0
                self._progress = MissionProgress()

    def start_mission(self) -> None:
        """Fly the vehicle's mission, as ArduCopter expects it.

        ArduCopter starts a freshly uploaded mission at item 1, and otherwise resumes it at its
        current item (``MIS_RESTART`` 0, the default; ``MAV_CMD_MISSION_START``'s first and
        last item must be 0).

        On the ground and disarmed: GUIDED (ArduCopter does not arm in AUTO unless
        ``AUTO_OPTIONS`` allows it), arm, then
        ``MAV_CMD_MISSION_START``, which switches to AUTO and starts the mission with the
        motors running (ArduCopter's AUTO refuses a landed, armed start whose first item is not
        a take-off: "Auto: Missing Takeoff Cmd"). Armed (flying, or on the ground):
        ``MAV_CMD_MISSION_START`` alone. Returns when the vehicle accepted, not when it flew.

        Raises:
            StateError: The driver is not ``ACTIVE``.
            MavlinkCommandError: A step was refused (the message carries the vehicle's words).
            DriverTimeoutError: No acknowledgement.
        """
        self.require_active("start_mission")
        with self._cond:
            armed = self._armed
        if not armed:
            if p.mode_name(self._custom_mode) != "GUIDED":
                self.set_mode("GUIDED")
            self.arm()
        self._moved_at = self.clock.monotonic()
        with self._cond:
            self._progress = MissionProgress(total=self._mission_total)
        self._send_command(p.MAV_CMD_MISSION_START, (0.0, 0.0))

    @property
    def mission_progress(self) -> MissionProgress:
        """The newest mission progress (``MISSION_CURRENT``, ``MISSION_ITEM_REACHED``).

        Items are counted as :meth:`upload_mission` took them (1..n; ArduPilot's home item 0
        is not one).
        """
        with self._cond:
            return self._progress

    def add_mission_listener(self, listener: Callable[[MissionProgress], None]) -> None:
        """Call ``listener`` with each new mission progress (on the receive thread: be quick).

        Args:
            listener: Takes the :class:`~temoto.drivers.capabilities.MissionProgress`.
        """
        with self._cond:
            self._mission_listeners.append(listener)

    def _target_ids(self) -> tuple[int, int]:
        with self._cond:
            return (self._target or 1, self.component_id)

    def _item_frame(self, seq: int, fields: dict[str, Any], target: tuple[int, int]) -> bytes:
        return self._codec.encode(
            "MISSION_ITEM_INT",
            target_system=target[0],
            target_component=target[1],
            seq=seq,
            current=0,
            autocontinue=1,
            mission_type=p.MAV_MISSION_TYPE_MISSION,
            **fields,
        )

    def _mission_step(
        self, request: bytes, seen: int, accept: Callable[[Message], bool], step: str
    ) -> tuple[int, Message]:
        """Send ``request`` until an accepted answer (retries); a refusing MISSION_ACK raises."""
        for _ in range(1 + self.mission_retries):
            self._write(request)
            got = self._await_mission(seen, lambda msg: accept(msg) or msg.name == "MISSION_ACK")
            if got is None:
                continue
            if got[1].name == "MISSION_ACK" and not accept(got[1]):
                result = got[1].get_int("type")
                raise MavlinkMissionError(
                    f"{self.name}: the vehicle ended the transfer waiting for {step}:"
                    f" {p.mission_result_name(result)}",
                    result=result,
                )
            return got
        raise DriverTimeoutError(
            f"{self.name}: no {step} in {1 + self.mission_retries} tries of"
            f" {self.mission_timeout:g} s"
        )

    def _await_mission(
        self, after: int, accept: Callable[[Message], bool]
    ) -> tuple[int, Message] | None:
        """The first mission-transfer message newer than ``after`` that ``accept`` takes."""
        found: list[tuple[int, Message]] = []

        def arrived() -> bool:
            for number, msg in self._mission_rx:
                if number > after and accept(msg):
                    found.append((number, msg))
                    return True
            return False

        return found[0] if self._await(arrived, self.mission_timeout) else None

    def _absorb_mission(self, msg: Message) -> list[Callable[[MissionProgress], None]]:
        """A mission message (lock held); the listeners to call when progress changed."""
        name = msg.name
        if name in missions.TRANSFER_MESSAGES:
            if msg.fields.get("target_system", 0) not in (0, self._codec.system_id):
                return []
            if msg.fields.get("mission_type", 0) != p.MAV_MISSION_TYPE_MISSION:
                return []
            self._mission_seq += 1
            self._mission_rx.append((self._mission_seq, msg))
            return []
        old = self._progress
        if name == "MISSION_CURRENT":
            total = msg.fields.get("total", 0)
            # MISSION_CURRENT.total leaves out a home item 0 (on the last item, seq == total)
            known = self._mission_total or (total if 0 < total < 0xFFFF else 0)
            finished = old.finished or (
                msg.fields.get("mission_state", 0) == p.MISSION_STATE_COMPLETE
            )
            new = MissionProgress(msg.get_int("seq"), known, old.reached, finished)
        else:  # MISSION_ITEM_REACHED
            seq = msg.get_int("seq")
            total = old.total
            new = MissionProgress(
                max(old.current, seq), total, seq, old.finished or (total > 0 and seq >= total)
            )
        if new == old:
            return []
        self._progress = new
        return list(self._mission_listeners)

    # ---- safe state --------------------------------------------------------------------------

    def on_make_safe(self) -> str:
        """Nothing on the ground; in the air, the safe state's flight mode (see the module).

        Returns:
            What was done: ``"vehicle LOITER"``, ``"vehicle on the ground: disarmed, nothing
            to do"``, or what was sent without confirmation.

        Raises:
            MavlinkCommandError: The vehicle refused the mode, and LAND too.
            StateError: The link is closed.
        """
        mode = _SAFE_MODES[self.safe_state]
        now = self.clock.monotonic()
        with self._cond:
            last_hb, armed, landed = self._last_hb, self._armed, self._landed_state
            moved, landed_at = self._moved_at, self._landed_at
        heard = last_hb is not None and now - last_hb <= self.heartbeat_timeout
        # an arm or take-off asked for after the newest heartbeat: it may be flying already
        stale_view = moved is not None and (last_hb is None or last_hb <= moved)
        if heard and not stale_view and not armed:
            return "vehicle on the ground: disarmed, nothing to do"
        stale_landed = moved is not None and (landed_at is None or landed_at <= moved)
        if heard and not stale_landed and landed == p.MAV_LANDED_STATE_ON_GROUND:
            return "vehicle on the ground: armed and landed, nothing sent"
        if not heard:  # it may be flying: send anyway, but do not wait for a silent vehicle
            if not self._send_mode(mode):
                return f"vehicle {mode} NOT sent: the vehicle's address is unknown"
            age = "never heard" if last_hb is None else f"not heard for {now - last_hb:.1f} s"
            return f"vehicle {mode} sent, not confirmed ({age})"
        result = self._set_mode_now(mode)
        if result == p.MAV_RESULT_ACCEPTED:
            return f"vehicle {mode}"
        if result is None:
            return f"vehicle {mode} sent, not confirmed within {self.SAFE_CONFIRM_WAIT:g} s"
        if mode != "LAND":
            fallback = self._set_mode_now("LAND")
            refused = f"{mode} refused: {p.result_name(result)}"
            if fallback == p.MAV_RESULT_ACCEPTED:
                return f"vehicle LAND ({refused})"
            if fallback is None:
                return f"vehicle LAND sent, not confirmed ({refused})"
            result = fallback
        raise MavlinkCommandError(
            f"{self.name}: the vehicle refused its safe mode {mode}: {p.result_name(result)}",
            command=p.MAV_CMD_DO_SET_MODE,
            result=result,
        )

    def _send_mode(self, mode: str) -> bool:
        """Send MAV_CMD_DO_SET_MODE once, without the command lock (never waits on a caller).

        Returns:
            False when there was nowhere to send (a ``udpin`` link that never heard it).
        """
        with self._cond:
            target = self._target or 1
        return self._write(
            self._codec.encode(
                "COMMAND_LONG",
                target_system=target,
                target_component=self.component_id,
                command=p.MAV_CMD_DO_SET_MODE,
                confirmation=0,
                param1=float(p.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED),
                param2=float(p.mode_number(mode)),
                param3=0.0,
                param4=0.0,
                param5=0.0,
                param6=0.0,
                param7=0.0,
            )
        )

    def _set_mode_now(self, mode: str) -> int | None:
        """Send a mode and wait briefly: ACCEPTED (ack or heartbeat), a refusal, or None."""
        number = p.mode_number(mode)
        with self._cond:
            start = self._ack_count
            sent_at = self.clock.monotonic()
        self._send_mode(mode)
        got: list[int] = []

        def confirmed() -> bool:
            ack = self._acks.get(p.MAV_CMD_DO_SET_MODE)
            if ack is not None and ack[1] > start and ack[0] != p.MAV_RESULT_IN_PROGRESS:
                got.append(ack[0])
                return True
            hb = self._last_hb
            if hb is not None and hb > sent_at and self._custom_mode == number:
                got.append(p.MAV_RESULT_ACCEPTED)
                return True
            return False

        return got[0] if self._await(confirmed, self.SAFE_CONFIRM_WAIT) else None

    # ---- Vehicle -----------------------------------------------------------------------------

    def arm(self) -> None:
        """Arm the motors (waits for the acknowledgement).

        Raises:
            StateError: The driver is not ``ACTIVE``.
            MavlinkCommandError: Refused (the message carries the pre-arm failure text).
            DriverTimeoutError: No acknowledgement.
        """
        self.require_active("arm")
        self._moved_at = self.clock.monotonic()
        self._send_command(p.MAV_CMD_COMPONENT_ARM_DISARM, (1.0,))

    def disarm(self) -> None:
        """Disarm (ArduPilot refuses while flying).

        Raises:
            StateError: The driver is not ``ACTIVE``.
            MavlinkCommandError: Refused.
            DriverTimeoutError: No acknowledgement.
        """
        self.require_active("disarm")
        self._send_command(p.MAV_CMD_COMPONENT_ARM_DISARM, (0.0,))

    def set_mode(self, mode: str) -> None:
        """Switch the ArduCopter flight mode (``MAV_CMD_DO_SET_MODE``).

        Args:
            mode: ``GUIDED``, ``LOITER``, ``RTL``, ``LAND``, ``STABILIZE``, ...

        Raises:
            ValueError: Not an ArduCopter mode.
            StateError: The driver is not ``ACTIVE``.
            MavlinkCommandError: Refused.
            DriverTimeoutError: No acknowledgement.
        """
        number = p.mode_number(mode)
        self.require_active("set_mode")
        self._send_command(
            p.MAV_CMD_DO_SET_MODE, (float(p.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED), float(number))
        )

    def takeoff(self, altitude: float) -> None:
        """Switch to GUIDED (if needed) and take off to ``altitude`` m above home.

        Returns when the vehicle accepted the command, not when it got there.

        Args:
            altitude: Metres above home (> 0).

        Raises:
            ValueError: ``altitude`` not positive and finite.
            StateError: The driver is not ``ACTIVE``.
            MavlinkCommandError: Refused (e.g. not armed).
            DriverTimeoutError: No acknowledgement.
        """
        if not (isinstance(altitude, int | float) and math.isfinite(altitude) and altitude > 0):
            raise ValueError(f"takeoff altitude must be positive metres, got {altitude!r}")
        self.require_active("takeoff")
        if p.mode_name(self._custom_mode) != "GUIDED":
            self.set_mode("GUIDED")
        nan = math.nan
        self._moved_at = self.clock.monotonic()
        self._send_command(p.MAV_CMD_NAV_TAKEOFF, (0.0, 0.0, 0.0, nan, nan, nan, float(altitude)))

    def goto(self, target: GeoPoint) -> None:
        """Fly to a position in GUIDED (``MAV_CMD_DO_REPOSITION``, relative altitude).

        Args:
            target: Latitude, longitude and metres above home.

        Raises:
            TypeError: ``target`` is not a GeoPoint.
            StateError: The driver is not ``ACTIVE``.
            MavlinkCommandError: Refused (e.g. not flying).
            DriverTimeoutError: No acknowledgement.
        """
        if not isinstance(target, GeoPoint):
            raise TypeError(f"goto needs a GeoPoint, got {type(target).__name__}")
        self.require_active("goto")
        flags = float(p.MAV_DO_REPOSITION_FLAGS_CHANGE_MODE)
        self._send_command(
            p.MAV_CMD_DO_REPOSITION,
            (-1.0, flags, 0.0, math.nan),
            frame=p.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
            position=(p.deg_e7(target.lat), p.deg_e7(target.lon), float(target.alt)),
        )

    def land(self) -> None:
        """Land where the vehicle is (``MAV_CMD_NAV_LAND``).

        Raises:
            StateError: The driver is not ``ACTIVE``.
            MavlinkCommandError: Refused.
            DriverTimeoutError: No acknowledgement.
        """
        self.require_active("land")
        self._send_command(p.MAV_CMD_NAV_LAND, (0.0, 0.0, 0.0, math.nan))

    def return_to_launch(self) -> None:
        """Fly home and land (``MAV_CMD_NAV_RETURN_TO_LAUNCH``).

        Raises:
            StateError: The driver is not ``ACTIVE``.
            MavlinkCommandError: Refused.
            DriverTimeoutError: No acknowledgement.
        """
        self.require_active("return_to_launch")
        self._send_command(p.MAV_CMD_NAV_RETURN_TO_LAUNCH, ())

    def telemetry(self) -> VehicleTelemetry:
        """The newest telemetry (the driver's cache; no traffic).

        Returns:
            The snapshot, stamped with the clock time of the newest message.

        Raises:
            StateError: Never configured, or shut down.
        """
        if self.state in (DriverState.UNCONFIGURED, DriverState.FINALIZED):
            raise StateError(f"{self.name}: no telemetry while {self.state.value}")
        now = self.clock.monotonic()
        with self._cond:
            lat, lon, alt = self._position
            return VehicleTelemetry(
                stamp=self._last_msg,
                armed=self._armed,
                mode=p.mode_name(self._custom_mode),
                position=GeoPoint(lat, lon, alt),
                attitude=self._attitude,
                battery_voltage=self._voltage,
                battery_remaining=self._remaining,
                status_texts=tuple(self._texts),
                heartbeat_age=math.inf if self._last_hb is None else now - self._last_hb,
            )

    @property
    def home(self) -> GeoPoint | None:
        """The vehicle's home (altitude 0 m above itself), once HOME_POSITION arrived."""
        with self._cond:
            home = self._home
        return None if home is None else GeoPoint(home[0], home[1], 0.0)

    @property
    def messages_received(self) -> int:
        """Valid messages received since configure (from any system)."""
        return self._received

    @property
    def foreign_frames(self) -> int:
        """Bad frames since configure from addresses other than the vehicle's (never a fault)."""
        return self._foreign

    @property
    def bad_frames(self) -> int:
        """Frames dropped since configure (bad CRC, unknown message id)."""
        return self._codec.bad_frames

    # ---- commands ----------------------------------------------------------------------------

    def _send_command(
        self,
        command: int,
        params: tuple[float, ...],
        *,
        retries: int | None = None,
        frame: int | None = None,
        position: tuple[int, int, float] | None = None,
        texts: bool = True,
    ) -> None:
        """Send a command until acknowledged (COMMAND_INT when ``position`` is given).

        A refusal's error carries the STATUSTEXTs that arrived since the command was sent;
        after a FAILED or DENIED ack (and ``texts``), those arriving within
        :attr:`STATUS_TEXT_WINDOW` are waited for.
        """
        tries = 1 + (self.command_retries if retries is None else retries)
        values = [*params, *([0.0] * (7 - len(params)))]
        with self._command_lock:
            with self._cond:
                target = self._target or 1
                start_acks, start_texts = self._ack_count, self._text_count
            for attempt in range(tries):
                if position is None:
                    frame_bytes = self._codec.encode(
                        "COMMAND_LONG",
                        target_system=target,
                        target_component=self.component_id,
                        command=command,
                        confirmation=attempt,
                        param1=values[0],
                        param2=values[1],
                        param3=values[2],
                        param4=values[3],
                        param5=values[4],
                        param6=values[5],
                        param7=values[6],
                    )
                else:
                    frame_bytes = self._codec.encode(
                        "COMMAND_INT",
                        target_system=target,
                        target_component=self.component_id,
                        frame=frame or 0,
                        command=command,
                        current=0,
                        autocontinue=0,
                        param1=values[0],
                        param2=values[1],
                        param3=values[2],
                        param4=values[3],
                        x=position[0],
                        y=position[1],
                        z=position[2],
                    )
                self._write(frame_bytes)
                result = self._await_ack(command, start_acks, self.command_timeout)
                if result is None:
                    continue
                if result == p.MAV_RESULT_ACCEPTED:
                    return
                if texts and result in (p.MAV_RESULT_FAILED, p.MAV_RESULT_DENIED):
                    self._await_texts(start_texts)
                with self._cond:
                    count = self._text_count - start_texts
                    news = list(self._texts)[-count:] if count > 0 else []
                said = f" (vehicle: {'; '.join(news)})" if news else ""
                raise MavlinkCommandError(
                    f"{self.name}: {p.command_name(command)} refused:"
                    f" {p.result_name(result)}{said}",
                    command=command,
                    result=result,
                )
        raise DriverTimeoutError(
            f"{self.name}: no COMMAND_ACK for {p.command_name(command)} in {tries} tries"
            f" of {self.command_timeout:g} s"
        )

    def _await_texts(self, after: int) -> None:
        """Wait for the STATUSTEXTs that follow a refusal (bounded by STATUS_TEXT_WINDOW).

        Ends when no text came within the window, or :data:`_TEXT_QUIET` seconds after the
        newest one (ArduPilot may send several "PreArm:" lines).
        """
        deadline = self.clock.monotonic() + self.STATUS_TEXT_WINDOW
        seen = after
        while (left := deadline - self.clock.monotonic()) > 0:
            wait = left if seen == after else min(left, _TEXT_QUIET)
            if not self._await(lambda n=seen: self._text_count > n, wait):  # type: ignore[misc]
                return
            with self._cond:
                seen = self._text_count

    def _await_ack(self, command: int, after: int, timeout: float) -> int | None:
        """The result of the first final ack of ``command`` newer than arrival ``after``."""
        got: list[int] = []

        def acked() -> bool:
            ack = self._acks.get(command)
            if ack is None or ack[1] <= after:
                return False
            if ack[0] == p.MAV_RESULT_IN_PROGRESS:
                return False  # the vehicle is still at it; the final ack comes later
            got.append(ack[0])
            return True

        return got[0] if self._await(acked, timeout) else None

    def _await(self, pred: Callable[[], bool], timeout: float) -> bool:
        """Wait (cache lock taken) until ``pred()``, for ``timeout`` clock seconds.

        The wait also ends after ``clock.real_seconds(timeout)`` real seconds, so a virtual
        clock nobody advances cannot hang a command forever.
        """
        deadline = self.clock.monotonic() + timeout
        real_deadline = time.monotonic() + self.clock.real_seconds(timeout) + _POLL
        with self._cond:
            while not pred():
                now = self.clock.monotonic()
                if now >= deadline or time.monotonic() >= real_deadline or self._stop.is_set():
                    return False
                self.clock.wait(self._cond, deadline - now)
        return True

    def _write(self, frame: bytes) -> bool:
        link = self._link
        if link is None:
            raise StateError(f"{self.name}: the link is closed")
        try:
            return link.write(frame)
        except OSError as err:
            raise DriverOperationError(f"{self.name}: sending failed: {err}") from err

    # ---- threads -----------------------------------------------------------------------------

    def _rx_loop(self) -> None:
        link = self._link
        assert link is not None
        while not self._stop.is_set():
            try:
                data, sender = link.receive(_POLL)
            except OSError as err:
                if self._stop.is_set():
                    break
                self._evaluate(DriverOperationError(f"{self.name}: the link failed: {err}"))
                self._stop.wait(_POLL)
                continue
            now = self.clock.monotonic()
            if not data:
                self._drained_at = now
                with self._cond:
                    self._cond.notify_all()  # waiters re-check their real-time guards
                continue
            bad_before = self._codec.bad_frames
            if link.datagrams:
                messages = self._codec.decode_datagram(data)
            else:
                messages = self._codec.decode(data)
            bad = self._codec.bad_frames - bad_before
            self._received += len(messages)
            check = False
            with self._cond:
                for msg in messages:
                    check |= self._absorb(msg, now)
                target = self._target
                ours = any(
                    m.src_system == target and m.src_component == self.component_id
                    for m in messages
                )
                if ours and link.accept_peer(sender):
                    logger.info("driver %s: the vehicle is at %s", self.name, sender)
                    self._beat_now = True  # greet it at once: its GCS failsafe starts then
                if bad:
                    check |= self._count_bad(bad, sender, link.peer, ours, now)
                if not link.pending():
                    self._drained_at = now
                self._cond.notify_all()
                notify, self._notify = self._notify, []
            for listener, progress in notify:
                try:
                    listener(progress)
                except Exception:
                    logger.exception("driver %s: a mission listener raised", self.name)
            if self._beat_now:
                with self._watch:
                    self._watch.notify_all()
            if check:
                self._evaluate()

    def _count_bad(self, bad: int, sender: Any, peer: Any, ours: bool, now: float) -> bool:
        """Count bad frames (lock held): the vehicle's go to the fault window, others' not.

        Returns:
            True when the vehicle's bad frames may have made a fault.
        """
        if sender is None or ours or sender == peer:
            self._vehicle_bad += bad
            fault = False
            for _ in range(bad):
                fault = self._bad_window.add(now)
            return fault
        self._foreign += bad
        if sender not in self._foreign_seen:
            self._foreign_seen.add(sender)
            logger.warning(
                "driver %s: malformed datagrams from %s (not the vehicle): counted and dropped",
                self.name,
                sender,
            )
        return False

    def _absorb(self, msg: Message, now: float) -> bool:
        """Update the cache (lock held); True if health may have changed."""
        if self._target is None:
            if msg.name != "HEARTBEAT" or msg.get_int("autopilot") == p.MAV_AUTOPILOT_INVALID:
                return False
            if msg.get_int("type") == p.MAV_TYPE_GCS:
                return False
            self._target = msg.src_system
        if msg.src_system != self._target:
            return False
        self._last_msg = max(self._last_msg, now)
        name = msg.name
        age = self._ages.get(name)
        changed = False
        if age is not None:
            age.feed(now)
            if self._stale is age:
                self._stale = None
                changed = True
        if name == "HEARTBEAT":
            if msg.src_component != self.component_id:
                return False
            self._last_hb = now
            self._bad_at_hb = self._vehicle_bad
            self._autopilot = msg.get_int("autopilot")
            self._armed = bool(msg.get_int("base_mode") & p.MAV_MODE_FLAG_SAFETY_ARMED)
            self._custom_mode = msg.get_int("custom_mode")
            return True
        if name == "GLOBAL_POSITION_INT":
            self._position = (
                msg.get_int("lat") / 1e7,
                msg.get_int("lon") / 1e7,
                msg.get_int("relative_alt") / 1000.0,
            )
        elif name == "ATTITUDE":
            self._attitude = (msg.get_float("roll"), msg.get_float("pitch"), msg.get_float("yaw"))
        elif name == "SYS_STATUS":
            millivolts = msg.get_int("voltage_battery")
            self._voltage = math.nan if millivolts == _UNKNOWN_VOLTAGE else millivolts / 1000.0
            self._remaining = msg.get_int("battery_remaining")
            enabled = msg.get_int("onboard_control_sensors_present") & msg.get_int(
                "onboard_control_sensors_enabled"
            )
            bad = enabled & ~msg.get_int("onboard_control_sensors_health")
            unhealthy = tuple(sorted(n for n, bit in p.SENSOR_BITS.items() if bad & bit))
            changed |= unhealthy != self._unhealthy
            self._unhealthy = unhealthy
            return changed
        elif name == "STATUSTEXT":
            text = msg.get_text("text")
            self._texts.append(text)
            self._text_count += 1
            level = _SEVERITY_LEVEL.get(msg.get_int("severity"), logging.INFO)
            logger.log(level, "vehicle %s: %s", self.name, text)
        elif name == "COMMAND_ACK":
            if msg.fields.get("target_system", 0) in (0, self._codec.system_id):
                self._ack_count += 1
                self._acks[msg.get_int("command")] = (msg.get_int("result"), self._ack_count)
        elif name == "HOME_POSITION":
            self._home = (
                msg.get_int("latitude") / 1e7,
                msg.get_int("longitude") / 1e7,
                msg.get_int("altitude") / 1000.0,
            )
        elif name == "EXTENDED_SYS_STATE":
            self._landed_state = msg.get_int("landed_state")
            self._landed_at = now
        elif name in missions.MISSION_MESSAGES:
            for listener in self._absorb_mission(msg):
                self._notify.append((listener, self._progress))
        elif name == "PARAM_ERROR":
            if msg.fields.get("target_system", 0) in (0, self._codec.system_id):
                self._param_errors[msg.get_text("param_id")] = msg.get_int("error")
        elif name == "PARAM_VALUE":
            param = msg.get_text("param_id")
            self._params[param] = (msg.get_float("param_value"), msg.get_int("param_type"))
            self._param_count += 1
            self._param_seen[param] = self._param_count
        return changed

    def _watch_loop(self) -> None:
        next_hb = self.clock.monotonic()
        check = min(0.1, self.heartbeat_timeout / 10)
        wake: float | None = None
        while not self._stop.is_set():
            now = self.clock.monotonic()
            with self._cond:
                periods = [age.period for age in self._ages.values()]
            shortest = min(periods, default=check)
            # A late wake-up means this process was not running: the streams' gaps may be
            # ours, not the vehicle's; judge them at the next, punctual, round.
            punctual = wake is None or now - wake <= shortest
            if now >= next_hb or self._beat_now:
                self._beat_now = False
                next_hb = now + self.heartbeat_period
                with contextlib.suppress(DriverError, StateError):  # rx loop reports the link
                    self._write(
                        self._codec.encode(
                            "HEARTBEAT",
                            type=p.MAV_TYPE_GCS,
                            autopilot=p.MAV_AUTOPILOT_INVALID,
                            base_mode=0,
                            custom_mode=0,
                            system_status=p.MAV_STATE_ACTIVE,
                            mavlink_version=3,
                        )
                    )
            self._evaluate(streams=punctual)
            with self._watch:
                if self._stop.is_set():
                    break
                timeout = max(min(next_hb - now, check, shortest), 0.0)
                wake = now + timeout
                self.clock.wait(self._watch, timeout)

    def _evaluate(self, link_error: DriverError | None = None, *, streams: bool = False) -> None:
        """Report a fault, or the recovery from one this driver reported.

        Args:
            link_error: The link failed.
            streams: Judge the streams' ages now (the watch thread, when it woke on time).
                A stream is stale when it was overdue both at a moment the link had been
                read empty (data waiting in the socket never counts as missing) and when
                another message of the vehicle arrived (the vehicle talks, but not this
                stream; a vehicle that says nothing at all is the heartbeat timeout's case).
        """
        now = self.clock.monotonic()
        with self._cond:
            last_hb, unhealthy = self._last_hb, self._unhealthy
            corrupt = self._vehicle_bad > self._bad_at_hb
            drained, talked = self._drained_at, self._last_msg
            if streams and drained is not None and self._stale is None:
                for age in self._ages.values():
                    seen = min(drained, talked)
                    if age.last is not None and seen - age.last > age.max_age:
                        self._stale = age
                        break
            stale = self._stale
            window = self._bad_window
            bursts = window.recent(now) >= window.limit
        error: DriverError | None = link_error
        if error is None and bursts:
            error = DriverOperationError(
                f"{self.name}: corrupt frames (bad CRC): {window.limit} or more within"
                f" {window.window:g} s"
            )
        elif error is None and (last_hb is None or now - last_hb > self.heartbeat_timeout):
            if corrupt:
                error = DriverOperationError(
                    f"{self.name}: only corrupt frames (bad CRC), no valid heartbeat within"
                    f" {self.heartbeat_timeout:g} s"
                )
            else:
                error = DriverTimeoutError(
                    f"{self.name}: no heartbeat within {self.heartbeat_timeout:g} s"
                )
        elif error is None and stale is not None:
            error = DriverTimeoutError(
                f"{self.name}: {stale.name} stale: none for over {stale.max_age:g} s"
                f" (expected every {stale.period:g} s)"
            )
        elif error is None and unhealthy:
            error = DriverOperationError(
                f"{self.name}: hardware error: unhealthy {', '.join(unhealthy)}"
            )
        with self._eval_lock:
            state = self.state
            if error is not None:
                if state in (DriverState.INACTIVE, DriverState.ACTIVE) or (
                    state is DriverState.FAULT and self._mine
                ):
                    self._mine = True
                    self.report_fault(error)
            elif self._mine and state is DriverState.FAULT:
                self._mine = False
                self.report_recovered(f"{self.name}: the vehicle answers and is healthy")


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
        return port


def _same(a: float, b: float) -> bool:
    """Parameter values equal as a float32 carries them."""
    return abs(a - b) <= 1e-5 * max(1.0, abs(b))
