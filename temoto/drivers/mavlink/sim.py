"""A simulated ArduCopter on UDP: the vehicle's side of MAVLink 2 (STYLE §3.7).

:class:`SimVehicle` binds a UDP socket (on ``127.0.0.1`` unless told ``host=``) and *sends*
to the ground stations it is given (``gcs=[(host, port)]``, like a real autopilot streaming
to ``udpin:`` listeners on 14550 or MAVSDK on 14540); it also answers anyone who sends to its
own port (so a ``udpout:`` client works too). It behaves like a small ArduCopter 4.5, so
that MAVProxy, QGroundControl, MAVSDK and a pymavlink ground station work with it as with SITL:

* HEARTBEAT at 1 Hz (``MAV_TYPE_QUADROTOR``, ``MAV_AUTOPILOT_ARDUPILOTMEGA``, ArduCopter custom
  modes, the armed flag) and the streams of :data:`DEFAULT_RATES`, grouped as ArduCopter's
  ``SRx_*`` stream groups (:data:`STREAM_GROUPS`) so that REQUEST_DATA_STREAM sets a group's
  rate; ``MAV_CMD_SET_MESSAGE_INTERVAL`` sets one message's. AUTOPILOT_VERSION (with the
  capabilities it really has: MAVLINK2, PARAM_FLOAT, MISSION_INT, COMMAND_INT,
  SET_POSITION_TARGET_GLOBAL_INT, MISSION_FENCE, MISSION_RALLY; not FTP) and any streamed
  message on ``MAV_CMD_REQUEST_MESSAGE``; TIMESYNC answered.
* The parameter protocol over :data:`PARAMETERS` (ArduCopter's names, defaults and types):
  PARAM_REQUEST_LIST streams every PARAM_VALUE with its index and the count (paced, a few per
  model step, after the version banner), PARAM_REQUEST_READ by name (answered with index -1,
  as ArduPilot does) or index, PARAM_SET answered with the stored value (an unknown name or
  NaN gets no answer; a read-only one "Param write denied" and the kept value). The
  parameters drive the model (below). ``params_file=`` loads them from a ``.param`` file and
  writes every accepted PARAM_SET back to it. FILE_TRANSFER_PROTOCOL requests are NAKed
  (the vehicle has no files), so MAVProxy's ``param fetch`` falls back to PARAM_REQUEST_LIST
  at once.
* The mission protocol (:class:`~temoto.drivers.mavlink.sim_mission.MissionService`: upload
  and download with MISSION_INT or the legacy messages, CLEAR_ALL, fence and rally plans
  stored), MISSION_SET_CURRENT and ``MAV_CMD_DO_SET_MISSION_CURRENT``, MISSION_CURRENT
  (streamed and on every change), MISSION_ITEM_REACHED. The guided forms of MISSION_ITEM(_INT)
  (``current`` 2: fly there, 3: change altitude) act in GUIDED.
* AUTO flies the mission: NAV_TAKEOFF, NAV_WAYPOINT (acceptance radius: param2, else
  ``WPNAV_RADIUS``; hold: param1 s), NAV_LOITER_TIME, NAV_LOITER_UNLIM, NAV_LAND,
  NAV_RETURN_TO_LAUNCH, DO_CHANGE_SPEED and DO_JUMP; other commands are skipped. Entering AUTO
  needs a mission and, armed on the ground, a NAV_TAKEOFF first ("Auto: Missing Takeoff
  Cmd"); arming in AUTO needs ``AUTO_OPTIONS`` bit 0, as in ArduCopter;
  ``MAV_CMD_MISSION_START`` switches to AUTO and starts a stopped mission. At the end of the
  mission the vehicle holds in the air, or disarms on the ground.
* A COMMAND_ACK for every COMMAND_LONG and COMMAND_INT addressed to the autopilot (component 1
  or broadcast 0; messages for another component, e.g. a camera's 100, are not acted on):
  arm/disarm (400) with pre-arm checks (``ARMING_CHECK``; a battery below
  ``min_arm_battery`` %, ``BATT_ARM_VOLT`` or ``BATT_ARM_MAH``, a hardware error → ``FAILED``
  and a ``PreArm:`` STATUSTEXT *after* the ack, as ArduPilot sends it; a mode that cannot arm
  → ``FAILED``, "Arm: Mode not armable"), set mode (176, and SET_MODE), takeoff (22, GUIDED and
  armed), land (21), return to launch (20), reposition (192), GET_HOME_POSITION (410),
  DO_SET_HOME (179; home is also set where the vehicle arms, unless DO_SET_HOME fixed it),
  DO_CHANGE_SPEED (178), MISSION_START (300), SET_POSITION_TARGET_GLOBAL_INT in GUIDED;
  ``UNSUPPORTED`` for the rest. SYS_STATUS carries ``MAV_SYS_STATUS_PREARM_CHECK`` (present;
  enabled when ``ARMING_CHECK`` is not 0; healthy when the pre-arm checks pass, always when
  armed).
* ArduCopter's GCS failsafe, on the injected clock: once a HEARTBEAT from the GCS system id
  ``SYSID_MYGCS`` (255) was seen, ``FS_GCS_TIMEOUT`` seconds (5) without one trigger it if
  ``FS_GCS_ENABLE`` is not 0: disarmed → nothing but a "GCS Failsafe" text; armed and landed →
  disarm; in the air → RTL (1, 2, 6), SmartRTL-or-RTL (3; SmartRTL is not simulated: RTL),
  SmartRTL-or-LAND (4: LAND), LAND (5), BRAKE (7), RTL for any other value. A heartbeat ends
  the failsafe ("GCS Failsafe Cleared"); the mode stays. In AUTO, ``FS_GCS_ENABLE`` 2 or
  ``FS_OPTIONS`` bit 1 (2) continue the mission; the other ``FS_OPTIONS`` bits are not
  simulated.
  The battery failsafe likewise: ``BATT_LOW_VOLT`` (for ``BATT_LOW_TIMER`` s) or
  ``BATT_LOW_MAH`` (of ``BATT_CAPACITY``) → ``BATT_FS_LOW_ACT``, the ``CRT`` ones →
  ``BATT_FS_CRT_ACT`` (0 none, 1 LAND, 2 RTL, 3 RTL, 4 LAND, 5 disarm, 6 RTL, 7 BRAKE);
  both latch. Each datagram received is parsed on its own.
* A first-order kinematic model stepped on the injected clock at ``step_rate`` Hz: the
  position approaches its target with time constant ``tau``, limited to ``WPNAV_SPEED``
  horizontally (``RTL_SPEED`` in RTL, a DO_CHANGE_SPEED in AUTO/GUIDED), ``WPNAV_SPEED_UP`` up
  and ``WPNAV_SPEED_DN`` down; LAND descends at ``LAND_SPEED_HIGH`` (0: ``WPNAV_SPEED_DN``)
  above ``LAND_ALT_LOW`` and ``LAND_SPEED`` below, and disarms on touchdown; RTL climbs to
  ``RTL_ALT``, flies home, hovers ``RTL_LOIT_TIME`` ms and lands (or stays at
  ``RTL_ALT_FINAL``). The battery drains while armed (``drain_idle`` %/s) and more in the air
  (``drain_flight`` %/s).

Faults (:class:`~temoto.drivers.sim.Simulator`): ``silence`` and ``link_loss`` (nothing in or
out), ``corrupt`` (every frame leaves with its CRC inverted), ``no_heartbeat`` (no HEARTBEAT,
everything else flows), ``hardware_error`` (``overheat`` → the motor-outputs health bit cleared
and the battery's over-temperature fault, ``overload`` → the propulsion health bit cleared,
``voltage`` → battery voltage far below minimum and the battery health bit cleared; each with
``MAV_STATE_CRITICAL`` and a STATUSTEXT).
"""

from __future__ import annotations

import logging
import math
import os
import threading
from collections.abc import Iterable, Mapping
from typing import Any, ClassVar, Final

from temoto.clock import Clock, MonotonicClock
from temoto.drivers.mavlink import protocol as p
from temoto.drivers.mavlink.link import LinkSpec, UdpLink
from temoto.drivers.mavlink.protocol import Codec, Message
from temoto.drivers.mavlink.sim_mission import MissionItem, MissionService
from temoto.drivers.mavlink.sim_params import (
    PARAMETERS,
    READ_ONLY,
    load_param_file,
    save_param_file,
    stored_value,
)
from temoto.drivers.sim import Simulator

__all__ = ["DEFAULT_RATES", "PARAMETERS", "STREAM_GROUPS", "SimVehicle"]

logger = logging.getLogger(__name__)

EARTH_RADIUS: Final = 6_378_137.0  # m, WGS-84 equatorial

#: Messages the simulator streams, and their default rates (Hz).
DEFAULT_RATES: Final[Mapping[str, float]] = {
    "HEARTBEAT": 1.0,
    "GLOBAL_POSITION_INT": 10.0,
    "ATTITUDE": 10.0,
    "SYS_STATUS": 2.0,
    "BATTERY_STATUS": 1.0,
    "GPS_RAW_INT": 2.0,
    "EXTENDED_SYS_STATE": 2.0,
    "VFR_HUD": 4.0,
    "HOME_POSITION": 0.5,
    "LOCAL_POSITION_NED": 2.0,
    "MISSION_CURRENT": 1.0,
    "NAV_CONTROLLER_OUTPUT": 2.0,
    "POWER_STATUS": 1.0,
    "MEMINFO": 1.0,
    "RC_CHANNELS": 2.0,
    "SERVO_OUTPUT_RAW": 2.0,
    "SYSTEM_TIME": 1.0,
    "EKF_STATUS_REPORT": 1.0,
    "VIBRATION": 1.0,
}

#: ArduCopter's stream groups (``SRx_EXT_STAT``, ``SRx_RC_CHAN``, ``SRx_POSITION``,
#: ``SRx_EXTRA1..3``) by ``MAV_DATA_STREAM`` id, as far as this simulator sends their
#: messages: REQUEST_DATA_STREAM sets the rate of every message of a group (0: all groups).
STREAM_GROUPS: Final[Mapping[int, tuple[str, ...]]] = {
    p.MAV_DATA_STREAM_EXTENDED_STATUS: (
        "SYS_STATUS",
        "POWER_STATUS",
        "MEMINFO",
        "MISSION_CURRENT",
        "GPS_RAW_INT",
        "NAV_CONTROLLER_OUTPUT",
    ),
    p.MAV_DATA_STREAM_RC_CHANNELS: ("SERVO_OUTPUT_RAW", "RC_CHANNELS"),
    p.MAV_DATA_STREAM_POSITION: ("GLOBAL_POSITION_INT", "LOCAL_POSITION_NED"),
    p.MAV_DATA_STREAM_EXTRA1: ("ATTITUDE",),
    p.MAV_DATA_STREAM_EXTRA2: ("VFR_HUD",),
    p.MAV_DATA_STREAM_EXTRA3: ("SYSTEM_TIME", "BATTERY_STATUS", "EKF_STATUS_REPORT", "VIBRATION"),
}

#: FS_GCS_ENABLE / BATT_FS_*_ACT → the mode taken in the air (ArduCopter's failsafe actions;
#: SmartRTL is not simulated, so its fallbacks are taken; DO_LAND_START neither: RTL).
_GCS_FAILSAFE_MODE: Final = {
    1: "RTL",
    2: "RTL",
    3: "RTL",
    4: "LAND",
    5: "LAND",
    6: "RTL",
    7: "BRAKE",
}
_BATT_FAILSAFE_MODE: Final = {1: "LAND", 2: "RTL", 3: "RTL", 4: "LAND", 6: "RTL", 7: "BRAKE"}

_ARMABLE: Final = frozenset({"STABILIZE", "ACRO", "ALT_HOLD", "GUIDED", "LOITER", "POSHOLD"})
_SUPPORTED_MODES: Final = frozenset(_ARMABLE | {"RTL", "LAND", "BRAKE", "AUTO"})
_FORCE_DISARM: Final = 21196.0  # ArduPilot's magic param2 of a forced disarm
_SENSORS: Final = (
    "3D_GYRO",
    "3D_ACCEL",
    "3D_MAG",
    "ABSOLUTE_PRESSURE",
    "GPS",
    "ANGULAR_RATE_CONTROL",
    "ATTITUDE_STABILIZATION",
    "YAW_POSITION",
    "Z_ALTITUDE_CONTROL",
    "XY_POSITION_CONTROL",
    "MOTOR_OUTPUTS",
    "BATTERY",
    "PROPULSION",
)
_HW_SENSOR: Final = {"overheat": "MOTOR_OUTPUTS", "overload": "PROPULSION", "voltage": "BATTERY"}
_HW_TEXT: Final = {
    "overheat": "Motor overheat",
    "overload": "Propulsion overload",
    "voltage": "Battery voltage critical",
}
_UINT16_MAX: Final = 65535
_AUTOPILOT: Final = 1  # the autopilot's component id (MAV_COMP_ID_AUTOPILOT1)
_PARAMS_PER_STEP: Final = 5  # PARAM_VALUEs of a list download per model step (ArduPilot: 5)
_ARMING_CHECK_ALL: Final = 1
_ARMING_CHECK_BATTERY: Final = 256
_AUTO_OPTION_ALLOW_ARMING: Final = 1
_NAV_CMDS: Final = {
    p.MAV_CMD_NAV_WAYPOINT: "wp",
    p.MAV_CMD_NAV_LOITER_UNLIM: "loiter_unlim",
    p.MAV_CMD_NAV_LOITER_TIME: "loiter_time",
    p.MAV_CMD_NAV_RETURN_TO_LAUNCH: "rtl",
    p.MAV_CMD_NAV_LAND: "land",
    p.MAV_CMD_NAV_TAKEOFF: "takeoff",
}
_NAV_LAST: Final = 95  # ArduPilot: command ids below MAV_CMD_NAV_LAST are navigation commands
_BANNER: Final = ("ArduCopter V4.5.7 (temoto simulator)", "Frame: QUAD/X")
_EKF_FLAGS: Final = 0x33F  # attitude, velocities, positions rel/abs, vertical, predicted
_FTP_SESSION_OPS: Final = frozenset(
    {p.FTP_OP_READ_FILE, p.FTP_OP_WRITE_FILE, p.FTP_OP_BURST_READ_FILE, 12}  # 12: truncate
)


def _clamp(value: float, low: float, high: float) -> float:
    return min(max(value, low), high)


class SimVehicle(Simulator):
    """A simulated ArduCopter quad on UDP loopback (see the module docstring).

    The keyword arguments ``speed``, ``climb_rate``, ``descent_rate`` and ``rtl_altitude``
    (and ``system_id``) are the initial values of the ArduCopter parameters that hold them
    (``WPNAV_SPEED``, ``WPNAV_SPEED_UP``, ``WPNAV_SPEED_DN`` and ``LAND_SPEED``, ``RTL_ALT``,
    ``SYSID_THISMAV``); ``params`` is applied over them, and the ``params_file`` over that
    (it is the vehicle's stored configuration, as ArduPilot's EEPROM).

    Args:
        name: For thread names and logs.
        clock: Steps the model and paces the streams.
        gcs: Where to send (host, port) pairs; more are learned from whoever sends to us.
        port: This vehicle's own UDP port (0: any free port).
        host: The address it binds: loopback by default; ``0.0.0.0`` or a network address
            for ground stations on other machines.
        system_id: The vehicle's MAVLink system id (``SYSID_THISMAV``; a value in the
            parameter file wins).
        home: Home latitude, longitude (degrees) and altitude above mean sea level (m); also
            the origin of the model's local frame and its ground level.
        rates: Stream rates in Hz by message name (merged over :data:`DEFAULT_RATES`; 0 stops
            a stream).
        battery: Initial charge, percent.
        cells: Battery cells in series (4.2 V full, 3.3 V empty each).
        min_arm_battery: Below this charge (%) arming is refused.
        speed: Horizontal speed, m/s (``WPNAV_SPEED``).
        climb_rate: Vertical speed up, m/s (``WPNAV_SPEED_UP``).
        descent_rate: Vertical speed down, m/s (``WPNAV_SPEED_DN`` and ``LAND_SPEED``).
        tau: Time constant of the position model, s.
        rtl_altitude: Minimum altitude above home for the flight home in RTL, m (``RTL_ALT``).
        drain_idle: Battery drain while armed on the ground, %/s.
        drain_flight: Battery drain in the air, %/s.
        step_rate: Model steps per clock second.
        params: Parameter values (e.g. ``{"FS_GCS_ENABLE": 5}`` for a vehicle whose GCS
            failsafe lands it); names from :data:`PARAMETERS`.
        params_file: A ``.param`` file (``NAME VALUE`` or ``NAME,VALUE`` lines, ``#``
            comments) loaded at construction if it exists and rewritten, atomically, after
            every accepted PARAM_SET. Names the table does not have are kept and served as
            ``REAL32`` parameters.

    Raises:
        ValueError: A parameter out of range, an unknown parameter name in ``params``, a bad
            line in ``params_file`` (naming the file and line).
        OSError: ``params_file`` exists but cannot be read.
    """

    FAULTS: ClassVar[frozenset[str]] = frozenset(
        {"silence", "corrupt", "hardware_error", "no_heartbeat", "link_loss"}
    )

    def __init__(
        self,
        name: str = "vehicle",
        *,
        clock: Clock | None = None,
        gcs: Iterable[tuple[str, int]] = (),
        port: int = 0,
        host: str = "127.0.0.1",
        system_id: int = 1,
        home: tuple[float, float, float] = (47.397742, 8.545594, 488.0),
        rates: Mapping[str, float] | None = None,
        battery: float = 100.0,
        cells: int = 4,
        min_arm_battery: float = 20.0,
        speed: float = 5.0,
        climb_rate: float = 2.5,
        descent_rate: float = 1.5,
        tau: float = 1.0,
        rtl_altitude: float = 15.0,
        drain_idle: float = 0.01,
        drain_flight: float = 0.1,
        step_rate: float = 50.0,
        params: Mapping[str, float] | None = None,
        params_file: str | os.PathLike[str] | None = None,
    ) -> None:
        super().__init__()
        merged = dict(DEFAULT_RATES)
        for msg, hz in (rates or {}).items():
            if msg.upper() not in DEFAULT_RATES or not (math.isfinite(hz) and hz >= 0):
                raise ValueError(f"bad stream rate {msg}={hz!r} (streams: {list(DEFAULT_RATES)})")
            merged[msg.upper()] = float(hz)
        positive = {
            "speed": speed,
            "climb_rate": climb_rate,
            "descent_rate": descent_rate,
            "tau": tau,
            "step_rate": step_rate,
            "cells": cells,
        }
        for key, value in positive.items():
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{key} must be positive, got {value!r}")
        if not 0.0 <= battery <= 100.0:
            raise ValueError(f"battery must be 0..100 %, got {battery!r}")
        if not 1 <= system_id <= 255:
            raise ValueError(f"system_id must be 1..255, got {system_id!r}")
        self._ptypes: dict[str, int] = {n: t for n, (_, t) in PARAMETERS.items()}
        self._params: dict[str, float] = {n: v for n, (v, _) in PARAMETERS.items()}
        initial = {
            "WPNAV_SPEED": speed * 100.0,
            "WPNAV_SPEED_UP": climb_rate * 100.0,
            "WPNAV_SPEED_DN": descent_rate * 100.0,
            "LAND_SPEED": descent_rate * 100.0,
            "RTL_ALT": rtl_altitude * 100.0,
            "SYSID_THISMAV": float(system_id),
        }
        for key, value in initial.items():
            self._params[key] = self._stored(key, value)
        for key, value in (params or {}).items():
            if key not in PARAMETERS or not math.isfinite(value):
                raise ValueError(f"bad parameter {key}={value!r} (known: {list(PARAMETERS)})")
            self._params[key] = self._stored(key, float(value))
        self.params_file = None if params_file is None else os.fspath(params_file)
        if self.params_file is not None and os.path.exists(self.params_file):
            loaded = load_param_file(self.params_file)
            extra = sorted(set(loaded) - set(PARAMETERS))
            if extra:
                logger.info(
                    "%s: %d parameters of %s are not simulated; kept and served as REAL32: %s",
                    name,
                    len(extra),
                    self.params_file,
                    ", ".join(extra[:10]) + (" ..." if len(extra) > 10 else ""),
                )
            for key, value in loaded.items():
                self._ptypes.setdefault(key, p.MAV_PARAM_TYPE_REAL32)
                if key not in READ_ONLY:
                    self._params[key] = self._stored(key, value)
        sysid = round(self._params["SYSID_THISMAV"])
        if not 1 <= sysid <= 255:
            where = f" ({self.params_file})" if self.params_file is not None else ""
            raise ValueError(f"SYSID_THISMAV must be 1..255, got {sysid}{where}")
        self._names = sorted(self._params)  # PARAM_VALUE index order
        self.name = name
        self.clock: Clock = clock or MonotonicClock()
        self.codec = Codec(sysid, _AUTOPILOT)
        self.port = port
        self.host = host
        self._origin = home
        #: Home: latitude, longitude (degrees), altitude above mean sea level (m).
        self.home = home
        self._home_locked = False
        self._periods = {m: (1.0 / hz if hz > 0 else math.inf) for m, hz in merged.items()}
        self._due = dict.fromkeys(merged, 0.0)
        self._cells, self._min_arm = int(cells), float(min_arm_battery)
        self._tau = tau
        self._drain_idle, self._drain_flight = drain_idle, drain_flight
        self._dt = 1.0 / step_rate
        self._gcs = list(gcs)
        # model (guarded by _lock)
        self._lock = threading.Lock()
        self._wake = threading.Condition(self._lock)
        self.battery = float(battery)
        self.armed = False
        self.mode = "STABILIZE"
        self.pos = [0.0, 0.0, 0.0]  # north, east, up (m from the origin: home at start)
        self.vel = [0.0, 0.0, 0.0]
        self.yaw = 0.0
        self.airborne = False
        self._target: list[float] | None = None
        self._landing = False  # descending to land (LAND, RTL's or AUTO's landing)
        self._landed_state = p.MAV_LANDED_STATE_ON_GROUND
        self._texts: list[tuple[int, str]] = []
        self._outbox: list[bytes] = []  # frames the model wants sent with the next streams
        self._peers: list[Any] = []
        self._t0 = 0.0
        self._last = 0.0
        self._gcs_seen: float | None = None  # clock time of the GCS's newest heartbeat
        self._gcs_failsafe = False
        self._batt_failsafe = 0  # 0 none, 1 low, 2 critical
        self._low_volt_since: float | None = None
        self._crt_volt_since: float | None = None
        self._rtl_arrived: float | None = None
        self._speed_override: dict[str, float] = {}
        # parameters being listed (PARAM_REQUEST_LIST): the next index
        self._param_cursor: int | None = None
        # missions
        self._mission = MissionService(self.codec.encode, self._home_item)
        self._mission_version = 0
        self._mis_index = 0  # the current mission command (0: none yet)
        self._mis_state = p.MISSION_STATE_NO_MISSION
        self._nav: dict[str, Any] | None = None  # the running navigation command
        self._jumps: dict[int, int] = {}
        # I/O
        self._link: UdpLink | None = None
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        #: Frames received and commands acknowledged, for tests and benchmarks.
        self.received: dict[str, int] = {}
        self.acks: list[tuple[int, int]] = []
        self._sync_mission_param()

    # ---- lifecycle ---------------------------------------------------------------------------

    @property
    def address(self) -> tuple[str, int]:
        """The vehicle's own UDP address (after :meth:`start`).

        Raises:
            RuntimeError: Not started.
        """
        if self._link is None:
            raise RuntimeError("the simulator is not started")
        return self._link.address

    def add_gcs(self, host: str, port: int) -> None:
        """Also stream to ``(host, port)``.

        Args:
            host: The ground station's host.
            port: Its UDP port.
        """
        with self._lock:
            if (host, port) not in self._gcs:
                self._gcs.append((host, port))

    def start(self) -> None:
        """Bind the socket and start the model and receive threads.

        Raises:
            RuntimeError: Already started.
            OSError: The port cannot be bound.
        """
        if self._link is not None:
            raise RuntimeError("the simulator is already started")
        self._link = UdpLink(LinkSpec("udpin", self.host, self.port))
        self.port = self._link.address[1]
        self._stop.clear()
        now = self.clock.monotonic()
        self._t0 = self._last = now
        self._threads = [
            threading.Thread(target=self._step_loop, name=f"temoto-sim-{self.name}-step"),
            threading.Thread(target=self._rx_loop, name=f"temoto-sim-{self.name}-rx"),
        ]
        for thread in self._threads:
            thread.start()

    def close(self) -> None:
        """Stop the threads and close the socket (idempotent)."""
        self._stop.set()
        with self._lock:
            self._wake.notify_all()
        for thread in self._threads:
            thread.join()
        self._threads = []
        if self._link is not None:
            self._link.close()
            self._link = None

    def on_fault_changed(self, fault: str, active: bool) -> None:
        """Announce a hardware error at once (STATUSTEXT); see :meth:`Simulator.inject`."""
        if fault == "hardware_error" and active:
            kind = (self.fault("hardware_error") or {}).get("kind", "overheat")
            with self._lock:
                self._texts.append((p.MAV_SEVERITY_CRITICAL, _HW_TEXT[kind]))

    def param(self, name: str) -> float:
        """A parameter's value, as the vehicle stores it.

        Args:
            name: One of :data:`PARAMETERS` (or a name loaded from the parameter file).

        Returns:
            The value.

        Raises:
            KeyError: Not a parameter of this vehicle.
        """
        with self._lock:
            return self._params[name]

    def mission(self) -> list[MissionItem]:
        """The stored mission, item 0 (home as uploaded) included; empty if none.

        Returns:
            A copy of the items.
        """
        with self._lock:
            return self._mission.items

    @property
    def mission_current(self) -> int:
        """The sequence number of the current mission command (0: none)."""
        with self._lock:
            return self._mis_index

    def set_rate(self, message: str, hz: float) -> None:
        """Stream ``message`` at ``hz`` from now on (0 stops it), as the vehicle's own setting.

        For fault injection: a stream that stops while the heartbeats go on.

        Args:
            message: One of :data:`DEFAULT_RATES`.
            hz: The rate (≥ 0).

        Raises:
            ValueError: Not a simulated stream, or a negative rate.
        """
        name = message.upper()
        if name not in DEFAULT_RATES or not (math.isfinite(hz) and hz >= 0):
            raise ValueError(f"bad stream rate {message}={hz!r} (streams: {list(DEFAULT_RATES)})")
        with self._lock:
            self._periods[name] = 1.0 / hz if hz > 0 else math.inf
            self._due[name] = 0.0

    def rate(self, message: str) -> float:
        """The rate a message is streamed at now, Hz (0: not streamed).

        Args:
            message: One of :data:`DEFAULT_RATES`.

        Returns:
            The rate.

        Raises:
            KeyError: Not a simulated stream.
        """
        with self._lock:
            period = self._periods[message.upper()]
        return 0.0 if period == math.inf else 1.0 / period

    def send_raw(self, datagram: bytes) -> None:
        """Send bytes as one datagram to every ground station, from the vehicle's own port.

        For fault injection (a malformed frame from the vehicle's address).

        Args:
            datagram: The bytes, sent as they are.

        Raises:
            RuntimeError: Not started.
        """
        link = self._link
        if link is None:
            raise RuntimeError("the simulator is not started")
        with self._lock:
            peers = list(dict.fromkeys([*self._gcs, *self._peers]))
        for peer in peers:
            link.send_to(datagram, peer)

    @property
    def gcs_failsafe(self) -> bool:
        """Whether the GCS failsafe is active (no GCS heartbeat for ``FS_GCS_TIMEOUT``)."""
        with self._lock:
            return self._gcs_failsafe

    @property
    def battery_failsafe(self) -> int:
        """The battery failsafe level: 0 none, 1 low, 2 critical (they latch)."""
        with self._lock:
            return self._batt_failsafe

    def _stored(self, name: str, value: float) -> float:
        """``value`` as a parameter of ``name``'s type holds it."""
        return stored_value(self._ptypes[name], value)

    def _p(self, name: str) -> float:
        return self._params[name]

    # ---- geometry ----------------------------------------------------------------------------

    def position(self) -> tuple[float, float, float]:
        """Where the vehicle is: latitude, longitude (degrees), altitude above home (m).

        Returns:
            The position.
        """
        with self._lock:
            lat, lon, up = self._geo(self.pos)
            return lat, lon, up - self._home_up()

    def _geo(self, pos: list[float]) -> tuple[float, float, float]:
        lat0, lon0, _ = self._origin
        lat = lat0 + math.degrees(pos[0] / EARTH_RADIUS)
        lon = lon0 + math.degrees(pos[1] / (EARTH_RADIUS * math.cos(math.radians(lat0))))
        return lat, lon, pos[2]

    def _local(self, lat: float, lon: float) -> tuple[float, float]:
        lat0, lon0, _ = self._origin
        north = math.radians(lat - lat0) * EARTH_RADIUS
        east = math.radians(lon - lon0) * EARTH_RADIUS * math.cos(math.radians(lat0))
        return north, east

    def _home_up(self) -> float:
        """Home's height over the origin (the ground), m."""
        return self.home[2] - self._origin[2]

    def _home_local(self) -> tuple[float, float, float]:
        north, east = self._local(self.home[0], self.home[1])
        return north, east, self._home_up()

    def _home_item(self) -> MissionItem:
        return MissionItem(
            seq=0,
            frame=p.MAV_FRAME_GLOBAL,
            command=p.MAV_CMD_NAV_WAYPOINT,
            current=0,
            autocontinue=1,
            param1=0.0,
            param2=0.0,
            param3=0.0,
            param4=0.0,
            x=p.deg_e7(self.home[0]),
            y=p.deg_e7(self.home[1]),
            z=self.home[2],
        )

    # ---- threads -----------------------------------------------------------------------------

    def _step_loop(self) -> None:
        with self._lock:
            next_tick = self.clock.monotonic()
            while not self._stop.is_set():
                now = self.clock.monotonic()
                if now >= next_tick:
                    self._advance(now)
                    self._check_gcs(now)
                    frames = self._streams(now)
                    self._lock.release()
                    try:
                        self._send(frames)
                    finally:
                        self._lock.acquire()
                    next_tick = now + self._dt
                    if self._stop.is_set():  # close() notified while the lock was released
                        break
                self.clock.wait(self._wake, max(next_tick - now, 0.0))

    def _rx_loop(self) -> None:
        link = self._link
        assert link is not None
        while not self._stop.is_set():
            try:
                data, peer = link.receive(0.05)
            except OSError:
                if self._stop.is_set():
                    return
                raise
            if not data or self.fault("silence") is not None or self.fault("link_loss"):
                continue
            with self._lock:
                if peer not in self._peers:
                    self._peers.append(peer)
            for msg in self.codec.decode_datagram(data):
                self.received[msg.name] = self.received.get(msg.name, 0) + 1
                replies = self._handle(msg)
                self._send(replies)

    def _send(self, frames: list[bytes]) -> None:
        link = self._link
        if not frames or link is None:
            return
        if self.fault("silence") is not None or self.fault("link_loss") is not None:
            return
        if self.fault("corrupt") is not None:
            frames = [p.corrupt(f) for f in frames]
        with self._lock:
            peers = list(dict.fromkeys([*self._gcs, *self._peers]))
        for frame in frames:
            for peer in peers:
                link.send_to(frame, peer)

    # ---- model -------------------------------------------------------------------------------

    def _advance(self, now: float) -> None:
        """Integrate from the last step to ``now`` in steps of at most ``1/step_rate``."""
        while now - self._last > 1e-9:
            dt = min(self._dt, now - self._last)
            self._last += dt
            self._step(dt)

    def _h_speed(self) -> float:
        """The horizontal speed limit now, m/s."""
        rtl = self.mode == "RTL" or (self._nav is not None and self._nav["kind"] == "rtl")
        if rtl and self._p("RTL_SPEED") > 0:
            return self._p("RTL_SPEED") / 100.0
        if "xy" in self._speed_override:
            return self._speed_override["xy"]
        return max(self._p("WPNAV_SPEED"), 20.0) / 100.0

    def _up_speed(self) -> float:
        return self._speed_override.get("up", max(self._p("WPNAV_SPEED_UP"), 10.0) / 100.0)

    def _down_speed(self) -> float:
        return self._speed_override.get("down", max(self._p("WPNAV_SPEED_DN"), 10.0) / 100.0)

    def _land_speed(self) -> float:
        """ArduCopter's landing descent rate at the current height, m/s."""
        if self.pos[2] > self._p("LAND_ALT_LOW") / 100.0:
            high = self._p("LAND_SPEED_HIGH")
            return high / 100.0 if high > 0 else self._down_speed()
        return max(self._p("LAND_SPEED"), 30.0) / 100.0

    def _step(self, dt: float) -> None:
        target = self._goal()
        if target is not None:
            desired = [(target[i] - self.pos[i]) / self._tau for i in range(3)]
            horizontal = math.hypot(desired[0], desired[1])
            speed = self._h_speed()
            if horizontal > speed:
                desired[0] *= speed / horizontal
                desired[1] *= speed / horizontal
            desired[2] = _clamp(desired[2], -self._down_speed(), self._up_speed())
            if self._landing:
                desired[2] = -self._land_speed() if self.pos[2] > 0.0 else 0.0
            self.vel = desired
            for i in range(3):
                self.pos[i] += desired[i] * dt
            if math.hypot(desired[0], desired[1]) > 0.5:
                self.yaw = math.atan2(desired[1], desired[0])
        else:
            self.vel = [0.0, 0.0, 0.0]
        if self.pos[2] <= 0.0:
            self.pos[2] = 0.0
            if (
                self.airborne
                and self.vel[2] <= 0.0
                and self._landed_state != (p.MAV_LANDED_STATE_TAKEOFF)
            ):
                self._touchdown()
        takeoff = self._landed_state == p.MAV_LANDED_STATE_TAKEOFF
        if takeoff and target is not None and abs(target[2] - self.pos[2]) < 0.3:
            self._landed_state = p.MAV_LANDED_STATE_IN_AIR
        if self.armed:
            self.battery -= (self._drain_idle + (self._drain_flight if self.airborne else 0)) * dt
            self.battery = max(self.battery, 0.0)
        if self.mode == "AUTO":
            self._auto_update()

    def _goal(self) -> list[float] | None:
        self._landing = False
        if not self.armed or not self.airborne:
            return None
        if self.mode == "LAND":
            self._landing = True
            self._landed_state = p.MAV_LANDED_STATE_LANDING
            return [self.pos[0], self.pos[1], 0.0]
        if self.mode == "RTL":
            return self._rtl_goal()
        nav = self._nav
        if self.mode == "AUTO" and nav is not None:
            if nav["kind"] == "rtl":
                return self._rtl_goal()
            target: list[float] = nav["target"]
            if nav["kind"] == "land":
                if math.hypot(target[0] - self.pos[0], target[1] - self.pos[1]) > 1.0:
                    return [target[0], target[1], self.pos[2]]  # fly there first, then land
                self._landing = True
                self._landed_state = p.MAV_LANDED_STATE_LANDING
            return target
        if self._target is None:
            self._target = list(self.pos)
        return self._target

    def _rtl_goal(self) -> list[float]:
        """RTL: climb to RTL_ALT, fly home, hover RTL_LOIT_TIME, then land (or RTL_ALT_FINAL)."""
        home_n, home_e, home_u = self._home_local()
        if self._rtl_arrived is None:
            if math.hypot(self.pos[0] - home_n, self.pos[1] - home_e) > 1.0:
                cruise = max(home_u + self._p("RTL_ALT") / 100.0, self.pos[2])
                if self.pos[2] < cruise - 0.5:
                    return [self.pos[0], self.pos[1], cruise]  # climb first
                return [home_n, home_e, cruise]
            self._rtl_arrived = self._last
        if self._last - self._rtl_arrived < self._p("RTL_LOIT_TIME") / 1000.0:
            return [home_n, home_e, self.pos[2]]
        final = self._p("RTL_ALT_FINAL") / 100.0
        if final > 0:
            return [home_n, home_e, home_u + final]
        self._landing = True
        self._landed_state = p.MAV_LANDED_STATE_LANDING
        return [home_n, home_e, 0.0]

    def _touchdown(self) -> None:
        self.airborne = False
        self._target = None
        self._landed_state = p.MAV_LANDED_STATE_ON_GROUND
        self.vel = [0.0, 0.0, 0.0]
        if self.armed and (self.mode in ("LAND", "RTL") or self._landing):
            self.armed = False
            self._texts.append((p.MAV_SEVERITY_INFO, "Disarming motors: landed"))

    def _voltage(self) -> float:
        if self._hw_kind() == "voltage":
            return self._cells * 2.9
        return self._cells * (3.3 + 0.9 * self.battery / 100.0)

    def _consumed_mah(self) -> float:
        return self._p("BATT_CAPACITY") * (100.0 - self.battery) / 100.0

    def _hw_kind(self) -> str | None:
        params = self.fault("hardware_error")
        return None if params is None else str(params.get("kind", "overheat"))

    # ---- AUTO (lock held) ---------------------------------------------------------------------

    def _sync_mission_param(self) -> None:
        self._params["MIS_TOTAL"] = float(self._mission.count())

    def _on_mission_changed(self) -> None:
        """A new mission was stored (or cleared): ArduCopter's mission change detector."""
        self._mission_version = self._mission.version
        self._sync_mission_param()
        count = self._mission.count()
        running = self.mode == "AUTO" and self._mis_state == p.MISSION_STATE_ACTIVE
        if count <= 1:
            self._mis_index = 0
            self._mis_state = p.MISSION_STATE_NO_MISSION
            if running:
                self._mission_complete()
                self._mis_state = p.MISSION_STATE_NO_MISSION
        elif not running:  # a new mission, not started yet
            self._mis_index = 1
            self._mis_state = p.MISSION_STATE_NOT_STARTED
            self._jumps = {}
        else:  # flying it: restart the current command of the new mission
            if self._mis_index >= count:
                self._mis_index = 1
            self._nav = None
            self._texts.append((p.MAV_SEVERITY_CRITICAL, "Auto mission changed, restarted command"))
        self._outbox.append(self._frame("MISSION_CURRENT", self._last))

    def _first_nav_is_takeoff(self) -> bool:
        seq = 1
        while (item := self._mission.item(seq)) is not None:
            if item.command < _NAV_LAST:
                return item.command == p.MAV_CMD_NAV_TAKEOFF
            seq += 1
        return False

    def _auto_refusal(self) -> str | None:
        """Why ArduCopter's ModeAuto::init would refuse AUTO now (None: it would not)."""
        if self._mission.count() <= 1:
            return ""
        if self.armed and not self.airborne and not self._first_nav_is_takeoff():
            return "Auto: Missing Takeoff Cmd"
        return None

    def _start_or_resume(self) -> None:
        restart = self._p("MIS_RESTART") == 1 or self._mis_index < 1
        if restart or self._mis_state in (p.MISSION_STATE_COMPLETE, p.MISSION_STATE_NO_MISSION):
            self._mis_index = 1
            self._jumps = {}
        self._mis_state = p.MISSION_STATE_ACTIVE
        self._nav = None
        self._outbox.append(self._frame("MISSION_CURRENT", self._last))

    def _set_current(self, seq: int, *, reset: bool = False) -> int:
        """MISSION_SET_CURRENT / DO_SET_MISSION_CURRENT: the MAV_RESULT."""
        seq = max(seq, 1)
        if self._mission.item(seq) is None:
            return p.MAV_RESULT_FAILED
        if reset:
            self._jumps = {}
        self._mis_index = seq
        if self._mis_state == p.MISSION_STATE_COMPLETE:
            self._mis_state = p.MISSION_STATE_PAUSED
        if self.mode == "AUTO" and self._mis_state == p.MISSION_STATE_ACTIVE:
            self._nav = None
            if self.armed:
                self._start_command(seq)
        self._outbox.append(self._frame("MISSION_CURRENT", self._last))
        return p.MAV_RESULT_ACCEPTED

    def _auto_update(self) -> None:
        """Run the mission one model step (mode AUTO)."""
        if self._mis_state != p.MISSION_STATE_ACTIVE:
            return
        nav = self._nav
        if nav is None:
            if self.armed:
                self._start_command(self._mis_index)
            return
        if not self._nav_done(nav):
            return
        seq = int(nav["seq"])
        self._nav = None
        self._outbox.append(self.codec.encode("MISSION_ITEM_REACHED", seq=seq))
        self._texts.append((p.MAV_SEVERITY_INFO, f"Reached command #{seq}"))
        if self._mission.item(seq + 1) is None:
            self._mission_complete()
        elif self.armed:
            self._start_command(seq + 1)
        else:
            self._mis_index = seq + 1
            self._outbox.append(self._frame("MISSION_CURRENT", self._last))

    def _start_command(self, seq: int) -> None:
        """Start mission command ``seq``, running DO commands on the way to the next NAV one."""
        for _ in range(256):  # bounds a DO_JUMP loop without NAV commands
            item = self._mission.item(seq) if seq >= 1 else None
            if item is None:
                self._mission_complete()
                return
            self._mis_index = seq
            kind = _NAV_CMDS.get(item.command)
            if kind is not None:
                self._begin_nav(kind, item)
                self._outbox.append(self._frame("MISSION_CURRENT", self._last))
                return
            if item.command == p.MAV_CMD_DO_JUMP:
                done = self._jumps.get(seq, 0)
                if item.param2 < 0 or done < item.param2:
                    self._jumps[seq] = done + 1
                    seq = int(item.param1)
                    continue
            elif item.command == p.MAV_CMD_DO_CHANGE_SPEED:
                self._change_speed(item.param1, item.param2)
            elif item.command < _NAV_LAST:
                self._texts.append((p.MAV_SEVERITY_WARNING, f"Skipping cmd #{seq}: not simulated"))
            seq += 1
        self._mission_complete()

    def _begin_nav(self, kind: str, item: MissionItem) -> None:
        north, east = self.pos[0], self.pos[1]
        if item.x != 0 or item.y != 0:
            north, east = self._local(item.lat, item.lon)
        up = self._home_up() + item.z if item.relative else item.z - self._origin[2]
        nav: dict[str, Any] = {"kind": kind, "seq": item.seq, "item": item, "reached": None}
        if kind == "takeoff":
            floor = self.pos[2] + (0.0 if self.airborne else 1.0)
            nav["target"] = [self.pos[0], self.pos[1], max(up, floor)]
        elif kind == "land":
            nav["target"] = [north, east, 0.0]
        elif kind == "rtl":
            self._rtl_arrived = None
            nav["target"] = None
        else:
            if item.z == 0:
                up = self.pos[2]  # ArduCopter: altitude 0 keeps the current one
            nav["target"] = [north, east, max(up, 0.5)]
        if not self.airborne and kind != "rtl" and kind != "land":
            self.airborne = True
            self._landed_state = p.MAV_LANDED_STATE_TAKEOFF
        self._nav = nav

    def _nav_done(self, nav: dict[str, Any]) -> bool:
        kind = nav["kind"]
        item: MissionItem = nav["item"]
        if kind in ("land", "rtl"):
            return not self.airborne
        target: list[float] = nav["target"]
        if kind == "takeoff":
            return abs(target[2] - self.pos[2]) < 0.3
        if kind == "loiter_unlim":
            return False
        radius = item.param2 if kind == "wp" and item.param2 > 0 else self._p("WPNAV_RADIUS") / 100
        if nav["reached"] is None:
            if math.dist(target, self.pos) > max(radius, 0.05):
                return False
            nav["reached"] = self._last
        return bool(self._last - nav["reached"] >= max(item.param1, 0.0))

    def _mission_complete(self) -> None:
        self._nav = None
        self._mis_state = p.MISSION_STATE_COMPLETE
        if self.airborne:
            self._target = list(self.pos)  # hold where it is, still in AUTO
        elif self.armed:
            self.armed = False
            self._texts.append((p.MAV_SEVERITY_INFO, "Disarming motors"))
        self._outbox.append(self._frame("MISSION_CURRENT", self._last))

    def _change_speed(self, kind: float, speed: float) -> int:
        """DO_CHANGE_SPEED: 0/1 horizontal, 2 climb, 3 descent (m/s); the MAV_RESULT."""
        if not (math.isfinite(speed) and speed > 0):
            return p.MAV_RESULT_FAILED
        key = {2: "up", 3: "down"}.get(round(kind), "xy")
        self._speed_override[key] = float(speed)
        return p.MAV_RESULT_ACCEPTED

    # ---- failsafes (lock held) ------------------------------------------------------------------

    def _check_gcs(self, now: float) -> None:
        """ArduCopter's GCS failsafe check, once per model step."""
        self._check_battery(now)
        if self._params["FS_GCS_ENABLE"] == 0 or self._gcs_seen is None:
            return
        late = now - self._gcs_seen > self._params["FS_GCS_TIMEOUT"]
        if late and not self._gcs_failsafe:
            self._gcs_failsafe = True
            self._gcs_failsafe_on()
        elif not late and self._gcs_failsafe:
            self._gcs_failsafe = False
            self._texts.append((p.MAV_SEVERITY_WARNING, "GCS Failsafe Cleared"))

    def _gcs_failsafe_on(self) -> None:
        warn = p.MAV_SEVERITY_WARNING
        if not self.armed:
            self._texts.append((warn, "GCS Failsafe"))
            return
        if not self.airborne:
            self._disarm(force=True)
            self._texts.append((warn, "GCS Failsafe - Disarming"))
            return
        enable = int(self._params["FS_GCS_ENABLE"])
        continue_auto = enable == 2 or round(self._p("FS_OPTIONS")) & 2  # FS_OPTIONS bit 1
        if self.mode == "AUTO" and continue_auto:
            self._texts.append((warn, "GCS Failsafe - Continuing Auto Mode"))
            return
        self._texts.append((warn, "GCS Failsafe"))
        if enable in (3, 4):
            fallback = "RTL" if enable == 3 else "Land"
            self._texts.append((warn, f"SmartRTL Unavailable, Using {fallback} Mode"))
        self._set_mode(_GCS_FAILSAFE_MODE.get(enable, "RTL"))

    def _volts_below(self, threshold: float, since: float | None, now: float) -> float | None:
        """When the voltage went below ``threshold`` (None: it is not below it)."""
        if threshold <= 0 or self._voltage() >= threshold:
            return None
        return now if since is None else since

    def _check_battery(self, now: float) -> None:
        """ArduPilot's battery failsafe (AP_BattMonitor): low and critical, latched."""
        if self._p("BATT_MONITOR") == 0:
            return
        timer = self._p("BATT_LOW_TIMER")
        self._low_volt_since = self._volts_below(
            self._p("BATT_LOW_VOLT"), self._low_volt_since, now
        )
        self._crt_volt_since = self._volts_below(
            self._p("BATT_CRT_VOLT"), self._crt_volt_since, now
        )
        remaining = self._p("BATT_CAPACITY") - self._consumed_mah()
        crt_mah, low_mah = self._p("BATT_CRT_MAH"), self._p("BATT_LOW_MAH")
        critical = (self._crt_volt_since is not None and now - self._crt_volt_since >= timer) or (
            crt_mah > 0 and remaining < crt_mah
        )
        low = (self._low_volt_since is not None and now - self._low_volt_since >= timer) or (
            low_mah > 0 and remaining < low_mah
        )
        level = 2 if critical else 1 if low else 0
        if level <= self._batt_failsafe:
            return
        self._batt_failsafe = level
        word = "critical" if level == 2 else "low"
        self._texts.append(
            (
                p.MAV_SEVERITY_WARNING,
                f"Battery 1 is {word} {self._voltage():.2f}V used {self._consumed_mah():.0f} mAh",
            )
        )
        action = int(self._p("BATT_FS_CRT_ACT" if level == 2 else "BATT_FS_LOW_ACT"))
        if action == 0 or not self.armed:
            return
        if not self.airborne or action == 5:  # landed: disarm; 5: terminate (motors off)
            self._disarm(force=True)
            return
        mode = _BATT_FAILSAFE_MODE.get(action, "RTL")
        if self.mode != "LAND":  # never from landing back to something else
            self._set_mode(mode)

    def _prearm_failure(self) -> str | None:
        """The first failing pre-arm check's STATUSTEXT (None: they pass)."""
        checks = round(self._p("ARMING_CHECK"))
        if checks == 0:
            return None
        kind = self._hw_kind()
        if kind is not None:
            return f"PreArm: {_HW_TEXT[kind]}"
        if checks & (_ARMING_CHECK_ALL | _ARMING_CHECK_BATTERY):
            if self._batt_failsafe:
                return "PreArm: Battery failsafe"
            if self.battery < self._min_arm:
                return "PreArm: Battery below minimum arming capacity"
            arm_volt, arm_mah = self._p("BATT_ARM_VOLT"), self._p("BATT_ARM_MAH")
            if arm_volt > 0 and self._voltage() < arm_volt:
                return "PreArm: Battery 1 below minimum arming voltage"
            if arm_mah > 0 and self._p("BATT_CAPACITY") - self._consumed_mah() < arm_mah:
                return "PreArm: Battery 1 below minimum arming capacity"
        return None

    # ---- received messages ---------------------------------------------------------------------

    _MISSION_MESSAGES: ClassVar[frozenset[str]] = frozenset(
        {
            "MISSION_COUNT",
            "MISSION_ITEM_INT",
            "MISSION_ITEM",
            "MISSION_REQUEST_LIST",
            "MISSION_REQUEST_INT",
            "MISSION_REQUEST",
            "MISSION_CLEAR_ALL",
            "MISSION_ACK",
        }
    )

    def _handle(self, msg: Message) -> list[bytes]:
        target = msg.fields.get("target_system")
        if target not in (None, 0, self.codec.system_id):
            return []
        if msg.fields.get("target_component") not in (None, 0, self.codec.component_id):
            return []  # for another component of this system (a camera, a gimbal)
        name = msg.name
        if name == "HEARTBEAT":
            with self._lock:
                if msg.src_system == round(self._params["SYSID_MYGCS"]):
                    self._gcs_seen = self.clock.monotonic()
            return []
        if name == "PARAM_REQUEST_LIST":
            with self._lock:
                self._texts.extend((p.MAV_SEVERITY_INFO, text) for text in _BANNER)
                self._param_cursor = 0
            return []
        if name in ("PARAM_REQUEST_READ", "PARAM_SET"):
            return self._param_message(msg)
        if name in ("MISSION_ITEM_INT", "MISSION_ITEM") and msg.get_int("current") in (2, 3):
            return self._guided_item(msg)
        if name in self._MISSION_MESSAGES:
            with self._lock:
                frames = self._mission.handle(msg, self.clock.monotonic())
                if self._mission.version != self._mission_version:
                    self._on_mission_changed()
            return frames
        if name == "MISSION_SET_CURRENT":
            with self._lock:
                self._set_current(msg.get_int("seq"))
                frames, self._outbox = self._outbox, []
            return frames
        if name in ("COMMAND_LONG", "COMMAND_INT"):
            cmd = msg.get_int("command")
            with self._lock:
                result, extra = self._command(msg, cmd)
                self.acks.append((cmd, result))
                texts, self._texts = self._texts, []
            ack = self.codec.encode(
                "COMMAND_ACK",
                command=cmd,
                result=result,
                progress=0,
                result_param2=0,
                target_system=msg.src_system,
                target_component=msg.src_component,
            )
            return [ack, *extra, *self._text_frames(texts)]  # ArduPilot: the reason after
        if name == "SET_MODE":
            custom = msg.get_int("custom_mode")
            with self._lock:
                result = self._set_mode(p.mode_name(custom))
                texts, self._texts = self._texts, []
            ack = self.codec.encode(
                "COMMAND_ACK",
                command=p.MSG_ID["SET_MODE"],
                result=result,
                target_system=msg.src_system,
                target_component=msg.src_component,
            )
            return [ack, *self._text_frames(texts)]
        if name == "SET_POSITION_TARGET_GLOBAL_INT":
            if msg.get_int("type_mask") & 0b111 == 0:
                with self._lock:
                    frame = msg.get_int("coordinate_frame")
                    self._reposition(
                        msg.get_int("lat_int") / 1e7,
                        msg.get_int("lon_int") / 1e7,
                        msg.get_float("alt"),
                        amsl=frame in (p.MAV_FRAME_GLOBAL, p.MAV_FRAME_GLOBAL_INT),
                        change_mode=False,
                    )
            return []
        if name == "REQUEST_DATA_STREAM":
            self._request_data_stream(msg)
            return []
        if name == "TIMESYNC":
            if msg.get_int("tc1") != 0:
                return []  # an answer to someone's request, not a request
            now_ns = round((self.clock.monotonic() - self._t0) * 1e9)
            return [self.codec.encode("TIMESYNC", tc1=max(now_ns, 1), ts1=msg.get_int("ts1"))]
        if name == "FILE_TRANSFER_PROTOCOL":
            return self._ftp(msg)
        return []

    def _param_value(self, name: str, index: int) -> bytes:
        return self.codec.encode(
            "PARAM_VALUE",
            param_id=name.encode(),
            param_value=self._params[name],
            param_type=self._ptypes[name],
            param_count=len(self._names),
            param_index=index if index >= 0 else _UINT16_MAX,
        )

    def _param_message(self, msg: Message) -> list[bytes]:
        """PARAM_REQUEST_READ and PARAM_SET: the PARAM_VALUE answer (none if unknown).

        As ArduPilot: a read by index answers with that index, a read by name and the echo of
        a set with index -1 (65535 on the wire); a read-only parameter is not changed ("Param
        write denied" and its value).
        """
        name = msg.get_text("param_id")
        index = -1
        frames: list[bytes] = []
        with self._lock:
            if msg.name == "PARAM_REQUEST_READ" and msg.get_int("param_index") >= 0:
                index = msg.get_int("param_index")
                if index >= len(self._names):
                    return []
                name = self._names[index]
            if name not in self._params:
                return []
            if msg.name == "PARAM_SET":
                value = msg.get_float("param_value")
                if not math.isfinite(value):
                    return []
                if name in READ_ONLY:
                    text = f"Param write denied ({name})"
                    frames += self._text_frames([(p.MAV_SEVERITY_WARNING, text)])
                else:
                    self._params[name] = self._stored(name, value)
                    self._persist()
            frames.insert(0, self._param_value(name, index))
        return frames

    def _persist(self) -> None:
        if self.params_file is None:
            return
        try:
            save_param_file(self.params_file, self._params, self._ptypes)
        except OSError as err:
            logger.error("%s: cannot write parameters to %s: %s", self.name, self.params_file, err)

    def _guided_item(self, msg: Message) -> list[bytes]:
        """MISSION_ITEM(_INT) with current=2 (guided: fly there) or 3 (change altitude)."""
        item = MissionItem.from_message(msg)
        with self._lock:
            if item.current == 2:
                result = self._reposition(
                    item.lat, item.lon, item.z, amsl=not item.relative, change_mode=False
                )
            elif self.mode == "GUIDED" and self.airborne and self._target is not None:
                up = self._home_up() + item.z if item.relative else item.z - self._origin[2]
                self._target = [self._target[0], self._target[1], max(up, 0.5)]
                result = p.MAV_RESULT_ACCEPTED
            else:
                result = p.MAV_RESULT_FAILED
        verdict = p.MAV_MISSION_ACCEPTED if result == p.MAV_RESULT_ACCEPTED else p.MAV_MISSION_ERROR
        return [
            self.codec.encode(
                "MISSION_ACK",
                target_system=msg.src_system,
                target_component=msg.src_component,
                type=verdict,
                mission_type=p.MAV_MISSION_TYPE_MISSION,
            )
        ]

    def _request_data_stream(self, msg: Message) -> None:
        """REQUEST_DATA_STREAM: set the rate of a stream group (ArduPilot's SRx_* groups)."""
        start_stop = msg.get_int("start_stop")
        if start_stop not in (0, 1):
            return
        hz = float(msg.get_int("req_message_rate")) if start_stop == 1 else 0.0
        stream = msg.get_int("req_stream_id")
        if stream == p.MAV_DATA_STREAM_ALL:
            names = [n for group in STREAM_GROUPS.values() for n in group]
        else:
            names = list(STREAM_GROUPS.get(stream, ()))
        with self._lock:
            for name in names:
                self._periods[name] = 1.0 / hz if hz > 0 else math.inf
                self._due[name] = 0.0

    def _ftp(self, msg: Message) -> list[bytes]:
        """MAVLink FTP: this vehicle has no files; every request is NAKed (sessions ACKed)."""
        payload = bytes(int(b) & 0xFF for b in msg.fields.get("payload", []))
        if len(payload) < 12:
            return []
        seq = payload[0] | payload[1] << 8
        session, opcode = payload[2], payload[3]
        if opcode in (p.FTP_OP_TERMINATE_SESSION, p.FTP_OP_RESET_SESSIONS):
            reply, data = p.FTP_OP_ACK, b""
        elif opcode in _FTP_SESSION_OPS:
            reply, data = p.FTP_OP_NAK, bytes([p.FTP_ERR_INVALID_SESSION])
        else:
            reply, data = p.FTP_OP_NAK, bytes([p.FTP_ERR_FILE_NOT_FOUND])
        header = bytes(
            [(seq + 1) & 0xFF, ((seq + 1) >> 8) & 0xFF, session, reply, len(data), opcode, 0, 0]
        )
        body = header + bytes(4) + data  # the 4-byte offset is 0
        return [
            self.codec.encode(
                "FILE_TRANSFER_PROTOCOL",
                target_network=0,
                target_system=msg.src_system,
                target_component=msg.src_component,
                payload=list(body + bytes(251 - len(body))),
            )
        ]

    def _command(self, msg: Message, cmd: int) -> tuple[int, list[bytes]]:
        """Carry out one command (lock held): its MAV_RESULT and any frames to send after."""
        prm = [msg.get_float(f"param{i}") for i in range(1, 5)]
        if msg.name == "COMMAND_LONG":
            prm += [msg.get_float("param5"), msg.get_float("param6"), msg.get_float("param7")]
        else:
            prm += [msg.get_int("x") / 1e7, msg.get_int("y") / 1e7, msg.get_float("z")]
        now = self.clock.monotonic()
        if cmd == p.MAV_CMD_COMPONENT_ARM_DISARM:
            return (self._arm() if prm[0] == 1.0 else self._disarm(prm[1] == _FORCE_DISARM)), []
        if cmd == p.MAV_CMD_DO_SET_MODE:
            if not int(prm[0]) & p.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
                return p.MAV_RESULT_UNSUPPORTED, []
            return self._set_mode(p.mode_name(int(prm[1]))), []
        if cmd == p.MAV_CMD_NAV_TAKEOFF:
            return self._takeoff(prm[6]), []
        if cmd == p.MAV_CMD_NAV_LAND:
            return self._set_mode("LAND"), []
        if cmd == p.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            return self._set_mode("RTL"), []
        if cmd == p.MAV_CMD_DO_REPOSITION:
            amsl = msg.name == "COMMAND_LONG" or msg.get_int("frame") in (
                p.MAV_FRAME_GLOBAL,
                p.MAV_FRAME_GLOBAL_INT,
            )
            return self._reposition(prm[4], prm[5], prm[6], amsl=amsl, change_mode=True), []
        if cmd == p.MAV_CMD_SET_MESSAGE_INTERVAL:
            return self._set_interval(int(prm[0]), prm[1]), []
        if cmd == p.MAV_CMD_REQUEST_MESSAGE:
            frame = self._one_message(int(prm[0]))
            return (p.MAV_RESULT_ACCEPTED, [frame]) if frame else (p.MAV_RESULT_DENIED, [])
        if cmd == p.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            frame = self._one_message(p.MSG_ID["AUTOPILOT_VERSION"])
            return p.MAV_RESULT_ACCEPTED, [frame] if frame else []
        if cmd == p.MAV_CMD_GET_HOME_POSITION:
            return p.MAV_RESULT_ACCEPTED, [self._frame("HOME_POSITION", now)]
        if cmd == p.MAV_CMD_DO_SET_HOME:
            relative = msg.name == "COMMAND_INT" and msg.get_int("frame") not in (
                p.MAV_FRAME_GLOBAL,
                p.MAV_FRAME_GLOBAL_INT,
            )
            if prm[0] not in (0.0, 1.0):
                return p.MAV_RESULT_FAILED, []  # ArduCopter: param1 is 1 (here) or 0
            result = self._set_home(prm[0] == 1.0, prm[4], prm[5], prm[6], relative=relative)
            extra = [self._frame("HOME_POSITION", now)] if result == p.MAV_RESULT_ACCEPTED else []
            return result, extra
        if cmd == p.MAV_CMD_DO_CHANGE_SPEED:
            if not (math.isfinite(prm[1]) and prm[1] > 0) or not 0 <= prm[0] < 4:
                return p.MAV_RESULT_DENIED, []
            if self.mode not in ("AUTO", "GUIDED"):
                return p.MAV_RESULT_FAILED, []  # modes without a speed to change
            return self._change_speed(prm[0], prm[1]), []
        if cmd == p.MAV_CMD_MISSION_START:  # ArduCopter: AUTO, then start a stopped mission
            if prm[0] != 0 or prm[1] != 0:
                return p.MAV_RESULT_DENIED, []  # first/last item: not supported
            result = self._set_mode("AUTO")
            if result == p.MAV_RESULT_ACCEPTED and self._mis_state != p.MISSION_STATE_ACTIVE:
                self._start_or_resume()
            return result, []
        if cmd == p.MAV_CMD_DO_SET_MISSION_CURRENT:
            result = self._set_current(int(prm[0]), reset=prm[1] == 1.0)
            frames, self._outbox = self._outbox, []
            return result, frames
        return p.MAV_RESULT_UNSUPPORTED, []

    def _arm(self) -> int:
        if self.armed:
            return p.MAV_RESULT_ACCEPTED
        failure = self._prearm_failure()
        if failure is not None:
            self._texts.append((p.MAV_SEVERITY_CRITICAL, failure))
            return p.MAV_RESULT_FAILED
        armable = self.mode in _ARMABLE or (
            self.mode == "AUTO" and round(self._p("AUTO_OPTIONS")) & _AUTO_OPTION_ALLOW_ARMING
        )
        if not armable:
            self._texts.append((p.MAV_SEVERITY_CRITICAL, "Arm: Mode not armable"))
            return p.MAV_RESULT_FAILED
        self.armed = True
        if not self._home_locked:  # ArduCopter sets home where it arms
            lat, lon, up = self._geo(self.pos)
            self.home = (lat, lon, self._origin[2] + up)
            self._outbox.append(self._frame("HOME_POSITION", self._last))
        self._texts.append((p.MAV_SEVERITY_INFO, "Arming motors"))
        return p.MAV_RESULT_ACCEPTED

    def _disarm(self, force: bool) -> int:
        if self.airborne and not force:
            self._texts.append((p.MAV_SEVERITY_CRITICAL, "Disarm: vehicle is flying"))
            return p.MAV_RESULT_FAILED
        self.armed = False
        self.airborne = False
        self._target = None
        if self.pos[2] > 0.0:
            self.pos[2] = 0.0  # a forced disarm in the air: it falls (instantly, here)
        self._landed_state = p.MAV_LANDED_STATE_ON_GROUND
        self._texts.append((p.MAV_SEVERITY_INFO, "Disarming motors"))
        return p.MAV_RESULT_ACCEPTED

    def _set_mode(self, mode: str) -> int:
        if mode not in _SUPPORTED_MODES:
            self._texts.append((p.MAV_SEVERITY_WARNING, f"Mode change to {mode} failed"))
            return p.MAV_RESULT_FAILED  # ArduPilot's answer to a mode it cannot enter
        if mode == "AUTO" and self.mode != "AUTO":
            refusal = self._auto_refusal()
            if refusal is not None:
                if refusal:
                    self._texts.append((p.MAV_SEVERITY_CRITICAL, refusal))
                self._texts.append(
                    (p.MAV_SEVERITY_WARNING, "Mode change to AUTO failed: init failed")
                )
                return p.MAV_RESULT_FAILED
        if mode != self.mode:
            if self.mode == "AUTO" and self._mis_state == p.MISSION_STATE_ACTIVE:
                self._mis_state = p.MISSION_STATE_PAUSED
                self._outbox.append(self._frame("MISSION_CURRENT", self._last))
            self._nav = None
            self._target = list(self.pos) if self.airborne else None
            self._rtl_arrived = None
            self._speed_override = {}
            self.mode = mode
            if mode == "AUTO":
                self._start_or_resume()
        return p.MAV_RESULT_ACCEPTED

    def _takeoff(self, altitude: float) -> int:
        if not (math.isfinite(altitude) and altitude > 0):
            return p.MAV_RESULT_DENIED
        if self.mode != "GUIDED" or not self.armed or self.airborne:
            self._texts.append((p.MAV_SEVERITY_WARNING, "Takeoff: needs GUIDED, armed, landed"))
            return p.MAV_RESULT_FAILED
        self.airborne = True
        self._landed_state = p.MAV_LANDED_STATE_TAKEOFF
        self._target = [self.pos[0], self.pos[1], self._home_up() + float(altitude)]
        return p.MAV_RESULT_ACCEPTED

    def _reposition(
        self, lat: float, lon: float, alt: float, *, amsl: bool, change_mode: bool
    ) -> int:
        if not (self.armed and self.airborne):
            return p.MAV_RESULT_DENIED
        if self.mode != "GUIDED":
            if not change_mode:
                return p.MAV_RESULT_DENIED
            self._set_mode("GUIDED")
        north, east = self.pos[0], self.pos[1]
        if math.isfinite(lat) and math.isfinite(lon) and (lat, lon) != (0.0, 0.0):
            north, east = self._local(lat, lon)
        up = self.pos[2]
        if math.isfinite(alt):
            up = alt - self._origin[2] if amsl else self._home_up() + alt
        self._target = [north, east, max(up, 0.5)]
        return p.MAV_RESULT_ACCEPTED

    def _set_home(self, here: bool, lat: float, lon: float, alt: float, *, relative: bool) -> int:
        """DO_SET_HOME: here (param1 1), or at a position (AMSL, or relative in COMMAND_INT)."""
        if here:
            lat, lon, up = self._geo(self.pos)
            alt = self._origin[2] + up
        else:
            valid = math.isfinite(lat) and math.isfinite(lon) and math.isfinite(alt)
            if not valid or abs(lat) > 90 or abs(lon) > 180:
                return p.MAV_RESULT_FAILED
            if math.hypot(*self._local(lat, lon)) > 50_000:  # ArduPilot: too far from origin
                return p.MAV_RESULT_FAILED
            if relative:
                alt += self.home[2]
        self.home = (lat, lon, alt)
        self._home_locked = True
        return p.MAV_RESULT_ACCEPTED

    def _set_interval(self, msg_id: int, interval_us: float) -> int:
        names = {v: k for k, v in p.MSG_ID.items()}
        name = names.get(msg_id)
        if name not in self._periods or name == "HEARTBEAT":
            return p.MAV_RESULT_ACCEPTED if name is not None else p.MAV_RESULT_DENIED
        if interval_us < 0:
            self._periods[name] = math.inf
        elif interval_us == 0:
            hz = DEFAULT_RATES[name]
            self._periods[name] = 1.0 / hz
        else:
            self._periods[name] = interval_us / 1e6
        self._due[name] = 0.0
        return p.MAV_RESULT_ACCEPTED

    # ---- outgoing messages -------------------------------------------------------------------

    def _streams(self, now: float) -> list[bytes]:
        frames: list[bytes] = []
        for name, period in self._periods.items():
            if period == math.inf or now < self._due[name]:
                continue
            if name == "HEARTBEAT" and self.fault("no_heartbeat") is not None:
                continue
            self._due[name] = max(self._due[name] + period, now)
            frames.append(self._frame(name, now))
        texts, self._texts = self._texts, []
        frames.extend(self._text_frames(texts))
        frames.extend(self._outbox)
        self._outbox = []
        frames.extend(self._mission.tick(now))
        if self._param_cursor is not None:  # a PARAM_REQUEST_LIST being answered, paced
            stop = min(self._param_cursor + _PARAMS_PER_STEP, len(self._names))
            frames += [
                self._param_value(self._names[i], i) for i in range(self._param_cursor, stop)
            ]
            self._param_cursor = stop if stop < len(self._names) else None
        return frames

    def _text_frames(self, texts: list[tuple[int, str]]) -> list[bytes]:
        return [
            self.codec.encode("STATUSTEXT", severity=sev, text=text.encode()[:50], id=0)
            for sev, text in texts
        ]

    def _one_message(self, msg_id: int) -> bytes | None:
        names = {v: k for k, v in p.MSG_ID.items()}
        name = names.get(msg_id, "")
        if name not in DEFAULT_RATES and name != "AUTOPILOT_VERSION":
            return None
        return self._frame(name, self.clock.monotonic())

    def _frame(self, name: str, now: float) -> bytes:
        boot_ms = int((now - self._t0) * 1000) & 0xFFFFFFFF
        lat, lon, up = self._geo(self.pos)
        amsl = self.home[2] + up
        kind = self._hw_kind()
        enc = self.codec.encode
        if name == "HEARTBEAT":
            base = (
                p.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
                | p.MAV_MODE_FLAG_STABILIZE_ENABLED
                | p.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED  # ArduCopter sets it in every mode
            )
            if self.mode in ("GUIDED", "AUTO", "RTL", "LOITER", "POSHOLD", "BRAKE"):
                base |= p.MAV_MODE_FLAG_GUIDED_ENABLED  # ArduCopter's modes with a position goal
            if self.armed:
                base |= p.MAV_MODE_FLAG_SAFETY_ARMED
            # ArduCopter: STANDBY while landed (armed or not), ACTIVE in the air
            status = p.MAV_STATE_ACTIVE if self.airborne else p.MAV_STATE_STANDBY
            if kind is not None or self._gcs_failsafe or self._batt_failsafe:
                status = p.MAV_STATE_CRITICAL  # ArduCopter: any failsafe triggered
            return enc(
                "HEARTBEAT",
                type=p.MAV_TYPE_QUADROTOR,
                autopilot=p.MAV_AUTOPILOT_ARDUPILOTMEGA,
                base_mode=base,
                custom_mode=p.COPTER_MODES[self.mode],
                system_status=status,
                mavlink_version=3,
            )
        if name == "GLOBAL_POSITION_INT":
            hdg = round(math.degrees(self.yaw) % 360 * 100) % 36000
            return enc(
                "GLOBAL_POSITION_INT",
                time_boot_ms=boot_ms,
                lat=p.deg_e7(lat),
                lon=p.deg_e7(lon),
                alt=round(amsl * 1000),
                relative_alt=round((up - self._home_up()) * 1000),
                vx=round(self.vel[0] * 100),
                vy=round(self.vel[1] * 100),
                vz=round(-self.vel[2] * 100),
                hdg=hdg,
            )
        if name == "ATTITUDE":
            cos_y, sin_y = math.cos(self.yaw), math.sin(self.yaw)
            forward = self.vel[0] * cos_y + self.vel[1] * sin_y
            right = -self.vel[0] * sin_y + self.vel[1] * cos_y
            yaw = math.atan2(sin_y, cos_y)
            return enc(
                "ATTITUDE",
                time_boot_ms=boot_ms,
                roll=0.03 * right,
                pitch=-0.03 * forward,
                yaw=yaw,
                rollspeed=0.0,
                pitchspeed=0.0,
                yawspeed=0.0,
            )
        if name == "SYS_STATUS":
            bits = 0
            for sensor in _SENSORS:
                bits |= p.SENSOR_BITS[sensor]
            health = bits & ~p.SENSOR_BITS[_HW_SENSOR[kind]] if kind else bits
            prearm = p.MAV_SYS_STATUS_PREARM_CHECK
            enabled = bits | (prearm if self._p("ARMING_CHECK") != 0 else 0)
            if self.armed or self._prearm_failure() is None:
                health |= prearm  # MAVLink: always healthy when armed
            return enc(
                "SYS_STATUS",
                onboard_control_sensors_present=bits | prearm,
                onboard_control_sensors_enabled=enabled,
                onboard_control_sensors_health=health,
                load=250,
                voltage_battery=round(self._voltage() * 1000),
                current_battery=-1,
                battery_remaining=round(self.battery),
                drop_rate_comm=0,
                errors_comm=0,
                errors_count1=0,
                errors_count2=0,
                errors_count3=0,
                errors_count4=0,
            )
        if name == "BATTERY_STATUS":
            cell = round(self._voltage() / self._cells * 1000)
            cells = [cell] * min(self._cells, 10) + [_UINT16_MAX] * (10 - min(self._cells, 10))
            if kind == "voltage" or self.battery < 10 or self._batt_failsafe == 2:
                charge = p.MAV_BATTERY_CHARGE_STATE_CRITICAL
            elif self.battery < self._min_arm or self._batt_failsafe == 1:
                charge = p.MAV_BATTERY_CHARGE_STATE_LOW
            else:
                charge = p.MAV_BATTERY_CHARGE_STATE_OK
            faults = 0
            if kind == "overheat":
                faults = p.MAV_BATTERY_FAULT_OVER_TEMPERATURE
            return enc(
                "BATTERY_STATUS",
                id=0,
                battery_function=0,
                type=p.MAV_BATTERY_TYPE_LIPO,
                temperature=7000 if kind == "overheat" else 2500,
                voltages=cells,
                current_battery=-1,
                current_consumed=round(self._consumed_mah()),
                energy_consumed=-1,
                battery_remaining=round(self.battery),
                time_remaining=0,
                charge_state=charge,
                voltages_ext=[0, 0, 0, 0],
                mode=0,
                fault_bitmask=faults,
            )
        if name == "GPS_RAW_INT":
            return enc(
                "GPS_RAW_INT",
                time_usec=boot_ms * 1000,
                fix_type=3,
                lat=p.deg_e7(lat),
                lon=p.deg_e7(lon),
                alt=round(amsl * 1000),
                eph=80,
                epv=120,
                vel=round(math.hypot(self.vel[0], self.vel[1]) * 100),
                cog=_UINT16_MAX,
                satellites_visible=14,
            )
        if name == "EXTENDED_SYS_STATE":
            landed = self._landed_state if self.airborne else p.MAV_LANDED_STATE_ON_GROUND
            return enc("EXTENDED_SYS_STATE", vtol_state=0, landed_state=landed)
        if name == "VFR_HUD":
            return enc(
                "VFR_HUD",
                airspeed=math.hypot(self.vel[0], self.vel[1]),
                groundspeed=math.hypot(self.vel[0], self.vel[1]),
                heading=round(math.degrees(self.yaw)) % 360,
                throttle=50 if self.airborne else 0,
                alt=amsl,
                climb=self.vel[2],
            )
        if name == "HOME_POSITION":
            return enc(
                "HOME_POSITION",
                latitude=p.deg_e7(self.home[0]),
                longitude=p.deg_e7(self.home[1]),
                altitude=round(self.home[2] * 1000),
                x=self._home_local()[0],  # home in the local frame (NED from the origin)
                y=self._home_local()[1],
                z=-self._home_up(),
                q=[1.0, 0.0, 0.0, 0.0],
                approach_x=0.0,
                approach_y=0.0,
                approach_z=0.0,
                time_usec=boot_ms * 1000,
            )
        if name == "AUTOPILOT_VERSION":
            caps = (
                p.MAV_PROTOCOL_CAPABILITY_MAVLINK2
                | p.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
                | p.MAV_PROTOCOL_CAPABILITY_MISSION_INT
                | p.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
                | p.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_GLOBAL_INT
                | p.MAV_PROTOCOL_CAPABILITY_MISSION_FENCE
                | p.MAV_PROTOCOL_CAPABILITY_MISSION_RALLY
            )
            return enc(
                "AUTOPILOT_VERSION",
                capabilities=caps,
                flight_sw_version=(4 << 24) | (5 << 16) | (0 << 8) | 255,
                middleware_sw_version=0,
                os_sw_version=0,
                board_version=0,
                flight_custom_version=b"temoto\x00\x00",
                middleware_custom_version=b"\x00" * 8,
                os_custom_version=b"\x00" * 8,
                vendor_id=0,
                product_id=0,
                uid=self.codec.system_id,
            )
        return self._frame_more(name, now, boot_ms)

    def _nav_target(self) -> list[float] | None:
        if self._nav is not None and self._nav.get("target") is not None:
            target: list[float] = self._nav["target"]
            return target
        return self._target if self.airborne else None

    def _frame_more(self, name: str, now: float, boot_ms: int) -> bytes:
        """The messages added for ground stations (issue 16)."""
        enc = self.codec.encode
        if name == "LOCAL_POSITION_NED":
            return enc(
                "LOCAL_POSITION_NED",
                time_boot_ms=boot_ms,
                x=self.pos[0],
                y=self.pos[1],
                z=-self.pos[2],
                vx=self.vel[0],
                vy=self.vel[1],
                vz=-self.vel[2],
            )
        if name == "MISSION_CURRENT":
            count = self._mission.count()
            return enc(
                "MISSION_CURRENT",
                seq=self._mis_index,
                total=count - 1 if count > 1 else _UINT16_MAX,
                mission_state=self._mis_state,
                mission_mode=1 if self.mode == "AUTO" else 2,
            )
        if name == "NAV_CONTROLLER_OUTPUT":
            target = self._nav_target()
            dist, bearing, alt_error = 0.0, 0, 0.0
            if target is not None:
                dist = math.hypot(target[0] - self.pos[0], target[1] - self.pos[1])
                bearing = round(
                    math.degrees(math.atan2(target[1] - self.pos[1], target[0] - self.pos[0]))
                )
                alt_error = target[2] - self.pos[2]
            return enc(
                "NAV_CONTROLLER_OUTPUT",
                nav_roll=0.0,
                nav_pitch=0.0,
                nav_bearing=bearing,
                target_bearing=bearing,
                wp_dist=min(round(dist), _UINT16_MAX),
                alt_error=alt_error,
                aspd_error=0.0,
                xtrack_error=0.0,
            )
        if name == "POWER_STATUS":
            return enc("POWER_STATUS", Vcc=5000, Vservo=0, flags=p.MAV_POWER_STATUS_BRICK_VALID)
        if name == "MEMINFO":
            return enc("MEMINFO", brkval=0, freemem=_UINT16_MAX, freemem32=200_000)
        if name == "RC_CHANNELS":
            sticks = [1500, 1500, 1000, 1500] + [1000] * 12  # no pilot: throttle low
            return enc(
                "RC_CHANNELS",
                time_boot_ms=boot_ms,
                chancount=16,
                **{f"chan{i + 1}_raw": value for i, value in enumerate(sticks)},
                chan17_raw=_UINT16_MAX,
                chan18_raw=_UINT16_MAX,
                rssi=255,
            )
        if name == "SERVO_OUTPUT_RAW":
            pwm = (1600 if self.airborne else 1100) if self.armed else 1000
            return enc(
                "SERVO_OUTPUT_RAW",
                time_usec=(boot_ms * 1000) & 0xFFFFFFFF,
                port=0,
                **{f"servo{i}_raw": pwm if i <= 4 else 0 for i in range(1, 9)},
            )
        if name == "SYSTEM_TIME":
            return enc(
                "SYSTEM_TIME",
                time_unix_usec=round(self.clock.time() * 1e6),
                time_boot_ms=boot_ms,
            )
        if name == "EKF_STATUS_REPORT":
            return enc(
                "EKF_STATUS_REPORT",
                flags=_EKF_FLAGS,
                velocity_variance=0.02,
                pos_horiz_variance=0.01,
                pos_vert_variance=0.02,
                compass_variance=0.01,
                terrain_alt_variance=0.0,
                airspeed_variance=0.0,
            )
        if name == "VIBRATION":
            level = 3.0 if self.airborne else 0.05
            return enc(
                "VIBRATION",
                time_usec=boot_ms * 1000,
                vibration_x=level,
                vibration_y=level,
                vibration_z=level * 1.2,
                clipping_0=0,
                clipping_1=0,
                clipping_2=0,
            )
        raise ValueError(f"the simulator does not send {name}")
