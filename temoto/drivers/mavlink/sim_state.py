"""The simulated ArduCopter's shared state: configuration tables, parameters, geometry, battery.

:class:`VehicleState` is the bottom layer of :class:`~temoto.drivers.mavlink.sim.SimVehicle`.
The vehicle is one state machine under one lock, written in layers that each use only the
layers below them (no layer calls up):

* :mod:`~temoto.drivers.mavlink.sim_state` (this module): the constructor (validation of the
  arguments, parameters from :data:`~temoto.drivers.mavlink.sim_params.PARAMETERS`, the
  ``.param`` file), the model's variables, the local frame (north, east, up from the origin),
  the battery model and the pre-arm checks;
* :mod:`~temoto.drivers.mavlink.sim_telemetry`: the messages the vehicle sends and their rates;
* :mod:`~temoto.drivers.mavlink.sim_auto`: flying the stored mission in AUTO;
* :mod:`~temoto.drivers.mavlink.sim_flight`: the kinematic model and the flight modes
  (arming, mode changes, takeoff, reposition, home);
* :mod:`~temoto.drivers.mavlink.sim_failsafe`: the GCS and battery failsafes;
* :mod:`~temoto.drivers.mavlink.sim_commands`: what the vehicle does with each received message;
* :mod:`~temoto.drivers.mavlink.sim`: :class:`SimVehicle` itself, the UDP endpoint and threads.

Methods whose names start with ``_`` expect the lock held unless their docstring says otherwise.
"""

from __future__ import annotations

import logging
import math
import os
import threading
from collections.abc import Iterable, Mapping
from typing import Any, Final

from temoto.clock import Clock, MonotonicClock
from temoto.drivers.mavlink import protocol as p
from temoto.drivers.mavlink.link import UdpLink
from temoto.drivers.mavlink.protocol import Codec
from temoto.drivers.mavlink.sim_mission import MissionItem, MissionService
from temoto.drivers.mavlink.sim_params import (
    PARAMETERS,
    READ_ONLY,
    load_param_file,
    stored_value,
)
from temoto.drivers.sim import Simulator

__all__ = ["DEFAULT_RATES", "EARTH_RADIUS", "STREAM_GROUPS", "VehicleState"]

logger = logging.getLogger("temoto.drivers.mavlink.sim")

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

_HW_TEXT: Final = {
    "overheat": "Motor overheat",
    "overload": "Propulsion overload",
    "voltage": "Battery voltage critical",
}

_AUTOPILOT: Final = 1  # the autopilot's component id (MAV_COMP_ID_AUTOPILOT1)

_ARMING_CHECK_ALL: Final = 1

_ARMING_CHECK_BATTERY: Final = 256


class VehicleState(Simulator):
    """The state every layer of the simulated vehicle shares, and the reads of it.

    The constructor's arguments are :class:`~temoto.drivers.mavlink.sim.SimVehicle`'s (see
    there). The model's variables are guarded by ``_lock``.
    """

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
        self._link: UdpLink | None = None  # SimVehicle's endpoint
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        #: Frames received (counted once handled) by message name, for tests and benchmarks.
        self.received: dict[str, int] = {}
        self.acks: list[tuple[int, int]] = []
        self._sync_mission_param()

    # ---- parameters ----------------------------------------------------------------------------

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

    def _stored(self, name: str, value: float) -> float:
        """``value`` as a parameter of ``name``'s type holds it."""
        return stored_value(self._ptypes[name], value)

    def _p(self, name: str) -> float:
        return self._params[name]

    def _sync_mission_param(self) -> None:
        self._params["MIS_TOTAL"] = float(self._mission.count())

    # ---- geometry ------------------------------------------------------------------------------

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

    # ---- battery and health --------------------------------------------------------------------

    def _voltage(self) -> float:
        if self._hw_kind() == "voltage":
            return self._cells * 2.9
        return self._cells * (3.3 + 0.9 * self.battery / 100.0)

    def _consumed_mah(self) -> float:
        return self._p("BATT_CAPACITY") * (100.0 - self.battery) / 100.0

    def _hw_kind(self) -> str | None:
        params = self.fault("hardware_error")
        return None if params is None else str(params.get("kind", "overheat"))

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
