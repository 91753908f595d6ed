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
  a message (a :class:`~temoto.errors.DriverTimeoutError` naming the stream; for a vehicle on
  this machine, a loopback address, at least
  :data:`~temoto.drivers.supervision.STALE_REAL_FLOOR_IN_PROCESS` of real time); frames with a
  bad CRC from the vehicle are counted, and a fault only when 5 fall within 1 s
  (:class:`~temoto.drivers.supervision.FaultWindow`); when the vehicle is healthy again the
  driver reports itself recovered;
* trusts nothing on the wire: each UDP datagram is parsed on its own, and a ``udpin`` link
  replies only to the address the target vehicle's valid frames (its system and component id)
  come from; garbage from other addresses is counted and never a fault;
* trusts only the autopilot (component ``component_id``, MAV_COMP_ID_AUTOPILOT1 = 1, of the
  vehicle's system): other components' and systems' messages are ignored and counted
  (``ignored_messages``); a second sender of the autopilot's ids (another address, or sequence
  numbers going back) is a fault "duplicate system id N", heard in ``configure`` before
  anything can arm;
* notices the vehicle's own mode changes from every HEARTBEAT (``telemetry().mode``; a WARNING
  and ``last_mode_change`` when this driver had not asked for the mode) and gaps in its
  messages shorter than ``heartbeat_timeout`` (a WARNING naming the gap, ``link_gaps``);
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
``brake``, ``land`` or ``rtl``. On the ground (disarmed, or armed and landed) nothing is sent,
unless a take-off or mission start was asked for and the vehicle has not yet been reported off
the ground (it may be leaving it: the mode is sent as in the air); in the air the driver sets
that ArduCopter mode (``MAV_CMD_DO_SET_MODE``) and waits at most
:attr:`MavlinkDriver.SAFE_CONFIRM_WAIT` for the ack or a heartbeat in that mode; a vehicle that
refuses LOITER or BRAKE (no position estimate) is sent LAND.

Flight modes are ArduCopter's (``GUIDED``, ``LOITER``, ``RTL``, ``LAND``, ...);
:meth:`~MavlinkDriver.takeoff` switches to GUIDED first, :meth:`~MavlinkDriver.goto` sends
``MAV_CMD_DO_REPOSITION`` (GUIDED), :meth:`~MavlinkDriver.land` and
:meth:`~MavlinkDriver.return_to_launch` send ``MAV_CMD_NAV_LAND`` and
``MAV_CMD_NAV_RETURN_TO_LAUNCH``.

:meth:`MavlinkDriver.detect` finds vehicles by listening only: it opens each link, parses the
HEARTBEATs that arrive within its timeout and sends nothing at all
(:mod:`~temoto.drivers.mavlink.detect`).

The class is built in layers, one concept per module: the link, its threads, supervision and
commands (:mod:`~temoto.drivers.mavlink._session`), the parameter protocol
(:mod:`~temoto.drivers.mavlink._parameters`), mission transfers
(:mod:`~temoto.drivers.mavlink._mission_transfer`), and here the profile, the vehicle's verbs
and its safe state. The profile's keys are declared in :mod:`~temoto.drivers.mavlink.settings`.
"""

from __future__ import annotations

import ipaddress
import logging
import math
import socket
import threading
from collections.abc import Mapping, Sequence
from typing import Any, ClassVar, Final

from temoto.clock import Clock
from temoto.drivers.base import DriverState
from temoto.drivers.capabilities import GeoPoint, MissionProgress, VehicleTelemetry
from temoto.drivers.mavlink import protocol as p
from temoto.drivers.mavlink._mission_transfer import MissionClient
from temoto.drivers.mavlink.detect import detect
from temoto.drivers.mavlink.link import open_link
from temoto.drivers.mavlink.settings import PROFILE_FIELDS, read_sim
from temoto.drivers.mavlink.sim import SimVehicle
from temoto.drivers.profile import REQUIRED, Field, ProfileReader
from temoto.drivers.sim import Simulator
from temoto.drivers.supervision import StreamAge, stale_periods
from temoto.errors import (
    DriverInitError,
    DriverTimeoutError,
    MavlinkCommandError,
    StateError,
)

__all__ = ["MavlinkDriver"]

logger = logging.getLogger(__name__)

#: Streams asked for in configure: message → share of ``stream_rate`` (capped at 2 Hz if < 1).
_STREAMS: Final[Mapping[str, float]] = {
    "GLOBAL_POSITION_INT": 1.0,
    "ATTITUDE": 1.0,
    "SYS_STATUS": 0.2,
    "BATTERY_STATUS": 0.2,
    "EXTENDED_SYS_STATE": 0.2,
}
#: The streams whose age is supervised (when the vehicle accepted their interval).
_SUPERVISED: Final = ("GLOBAL_POSITION_INT", "ATTITUDE")
#: Safe state → the ArduCopter mode it sets in the air.
_SAFE_MODES: Final[Mapping[str, str]] = {
    "loiter": "LOITER",
    "brake": "BRAKE",
    "land": "LAND",
    "rtl": "RTL",
}


class MavlinkDriver(MissionClient):
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

    #: Seconds (clock) :meth:`make_safe` waits for the vehicle to confirm its mode.
    SAFE_CONFIRM_WAIT: ClassVar[float] = 0.3

    #: Clock seconds ``configure`` listens from the vehicle's first heartbeat before it ends,
    #: so that a second vehicle using the same system id (whose heartbeat also comes once a
    #: second) is heard before anything can arm: ArduPilot's heartbeat period.
    DUPLICATE_LISTEN: ClassVar[float] = 1.0

    # ---- profile -----------------------------------------------------------------------------

    #: The keys of a profile entry (:mod:`~temoto.drivers.mavlink.settings`); an entry from
    #: :meth:`detect` is accepted as it is. The constructor checks the keys that depend on
    #: each other (``heartbeat_period`` against the GCS failsafe's timeout).
    profile_fields: ClassVar[Mapping[str, Field[Any]]] = PROFILE_FIELDS

    @classmethod
    def read_profile(cls, config: Mapping[str, Any], where: str) -> dict[str, Any]:
        """Check a profile entry; also refuse an empty (null) value of a key with a default.

        ``safe_state:`` with nothing after it would otherwise silently be ``loiter``; only
        ``system_id`` and ``gcs_failsafe``, whose absence means something, may be null.

        Args:
            config: The entry.
            where: The entry's place for messages.

        Returns:
            The checked values (see :meth:`~temoto.drivers.base.Driver.read_profile`).

        Raises:
            ProfileError: The first problem; the message names the file and the key path.
        """
        if isinstance(config, Mapping):
            schema = cls.profile_schema()
            for key, value in config.items():
                field = schema.get(key)
                if value is None and field is not None and field.default not in (None, REQUIRED):
                    default = field.default
                    told = f" (its default is {default!r})" if not isinstance(default, dict) else ""
                    raise ProfileReader.at(where).error(
                        key, f"empty (null): give a value or leave the key out{told}"
                    )
        return super().read_profile(config, where)

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
            system = "any system" if self.system_id is None else f"system {self.system_id}"
            raise DriverTimeoutError(
                f"{self.name}: no HEARTBEAT from an autopilot ({system}, component"
                f" {self.component_id}) on {self.link_spec} within {self.init_timeout:g} s"
            )
        with self._cond:
            first_hb = self._last_hb
        if self._autopilot != p.MAV_AUTOPILOT_ARDUPILOTMEGA:
            raise DriverInitError(
                f"{self.name}: system {self._target} is not an ArduPilot autopilot"
                f" (MAV_AUTOPILOT {self._autopilot}); only ArduCopter modes are supported"
            )
        self._check_duplicate()
        self._request_streams()
        self._check_duplicate()
        self._configure_failsafe()
        # a second vehicle with the same ids heartbeats once a second too: listen that long
        # (the requests above usually took it) before anything can arm
        assert first_hb is not None
        left = first_hb + self.DUPLICATE_LISTEN - self.clock.monotonic()
        if left > 0:
            self._await(lambda: self._duplicate is not None, left)
        self._check_duplicate()

    def _check_duplicate(self) -> None:
        """Raise if a second vehicle answers with the autopilot's ids.

        Raises:
            DriverInitError: ``duplicate system id N: ...``.
        """
        with self._cond:
            duplicate = self._duplicate
        if duplicate is not None:
            raise DriverInitError(
                f"{duplicate}; nothing was sent to arm or move. Give each vehicle its own"
                " SYSID_THISMAV, or point this link at one vehicle only"
            )

    def _request_streams(self) -> None:
        """Ask for the telemetry streams; supervise those the vehicle accepted."""
        if self.stream_rate <= 0:
            return
        with self._cond:
            here = _on_this_machine(self._vehicle_addr)
        real_per_clock = self.clock.real_seconds(1.0)
        for msg, share in _STREAMS.items():
            hz = self.stream_rate * share if share >= 1 else min(self.stream_rate, 2.0)
            accepted = self._best_effort(p.MAV_CMD_SET_MESSAGE_INTERVAL, p.MSG_ID[msg], 1e6 / hz)
            if accepted and msg in _SUPERVISED:
                # a vehicle on this machine (our simulator, SITL) competes with this process
                # for the cores: on a clock faster than real time, its few-ms stalls are
                # several periods (docs/safety.md, "Supervision of feedback")
                periods = stale_periods(1.0 / hz, real_per_clock, in_process=here)
                age = StreamAge(msg, 1.0 / hz, periods)
                age.feed(self.clock.monotonic())  # due from now on, even if none ever comes
                with self._cond:
                    self._ages[msg] = age
        self._best_effort(p.MAV_CMD_REQUEST_MESSAGE, p.MSG_ID["HOME_POSITION"])

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
            lift, off_ground = self._lift_at, self._off_ground_at
        heard = last_hb is not None and now - last_hb <= self.heartbeat_timeout
        # an arm or take-off asked for after the newest heartbeat: it may be flying already
        stale_view = moved is not None and (last_hb is None or last_hb <= moved)
        if heard and not stale_view and not armed:
            return "vehicle on the ground: disarmed, nothing to do"
        stale_landed = moved is not None and (landed_at is None or landed_at <= moved)
        # a take-off asked for and never seen off the ground: "on the ground" is a vehicle
        # spooling up to leave it (its landed state comes at 2 Hz), so it is sent the mode too
        lifting = lift is not None and (off_ground is None or off_ground <= lift)
        if heard and not stale_landed and not lifting and landed == p.MAV_LANDED_STATE_ON_GROUND:
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
        self._note_mode(p.mode_number(mode))
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
        self._note_mode(number)
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
        self._moved_at = self._lift_at = self.clock.monotonic()
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
        self._note_mode(p.mode_number("GUIDED"))  # the change-mode flag: GUIDED
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
        self._note_mode(p.mode_number("LAND"))  # ArduCopter lands in its LAND mode
        self._send_command(p.MAV_CMD_NAV_LAND, (0.0, 0.0, 0.0, math.nan))

    def return_to_launch(self) -> None:
        """Fly home and land (``MAV_CMD_NAV_RETURN_TO_LAUNCH``).

        Raises:
            StateError: The driver is not ``ACTIVE``.
            MavlinkCommandError: Refused.
            DriverTimeoutError: No acknowledgement.
        """
        self.require_active("return_to_launch")
        self._note_mode(p.mode_number("RTL"))
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
        self._moved_at = self._lift_at = self.clock.monotonic()
        with self._cond:
            self._progress = MissionProgress(total=self._mission_total)
        self._note_mode(p.mode_number("AUTO"))  # MISSION_START switches to AUTO
        self._send_command(p.MAV_CMD_MISSION_START, (0.0, 0.0))


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
        return port


def _on_this_machine(addr: Any) -> bool:
    """Whether a UDP vehicle address is a loopback one (the vehicle runs on this machine)."""
    if not (isinstance(addr, tuple) and addr and isinstance(addr[0], str)):
        return False  # a serial line, or not heard yet
    try:
        return ipaddress.ip_address(addr[0].split("%", 1)[0]).is_loopback
    except ValueError:
        return False
