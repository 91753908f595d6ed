"""The simulated ArduCopter's shared state: configuration tables, parameters, geometry, battery.

:class:`VehicleState` is the one state object the parts of
:class:`~temoto.drivers.mavlink.sim.SimVehicle` share by reference. The vehicle is one state
machine under one lock, made of parts it holds, each a class that can be built and driven on
its own over a :class:`VehicleState` (and the parts it names in its constructor):

* :mod:`~temoto.drivers.mavlink.sim_state` (this module): the state (validation of the
  arguments, parameters from :data:`~temoto.drivers.mavlink.sim_params.PARAMETERS`, the
  ``.param`` file), the local frame (north, east, up from the origin), the battery model and
  the pre-arm checks;
* :mod:`~temoto.drivers.mavlink.sim_telemetry`: :class:`VehicleTelemetry`, the messages the
  vehicle sends and their rates (over the state);
* :mod:`~temoto.drivers.mavlink.sim_auto`: :class:`AutoMission`, flying the stored mission in
  AUTO (state, telemetry);
* :mod:`~temoto.drivers.mavlink.sim_flight`: :class:`FlightModel`, the kinematic model and the
  flight modes: arming, mode changes, takeoff, reposition, home (state, telemetry, mission);
* :mod:`~temoto.drivers.mavlink.sim_failsafe`: :class:`Failsafes`, the GCS and battery
  failsafes (state, flight model);
* :mod:`~temoto.drivers.mavlink.sim_commands`: :class:`CommandHandler`, what the vehicle does
  with each received message (all of the above);
* :mod:`~temoto.drivers.mavlink.sim`: :class:`SimVehicle`, which holds the parts, the UDP
  endpoint and the threads.

Every method of a part expects :attr:`VehicleState.lock` held unless its docstring says it
takes it.
"""

from __future__ import annotations

import logging
import math
import os
import threading
from collections.abc import Callable, Mapping
from typing import Any, Final, TypedDict

from temoto.clock import Clock, MonotonicClock
from temoto.drivers.mavlink import protocol as p
from temoto.drivers.mavlink.protocol import Codec
from temoto.drivers.mavlink.sim_mission import MissionItem, MissionService
from temoto.drivers.mavlink.sim_params import (
    PARAMETERS,
    READ_ONLY,
    load_param_file,
    stored_value,
)

__all__ = [
    "DEFAULT_RATES",
    "EARTH_RADIUS",
    "GRAVITY",
    "HW_TEXT",
    "STREAM_GROUPS",
    "VehicleModel",
    "VehicleState",
]

logger = logging.getLogger(__name__)

EARTH_RADIUS: Final = 6_378_137.0  # m, WGS-84 equatorial
GRAVITY: Final = 9.80665  # m/s², ArduPilot's GRAVITY_MSS

#: The wind's drag on the vehicle per unit mass, 1/m: acceleration = WIND_DRAG·airspeed².
#: With ArduCopter's ANGLE_MAX of 30° (g·tan 30° = 5.66 m/s²) the vehicle holds its position
#: in winds up to sqrt(5.66/0.025) ≈ 15 m/s, a typical small quad's limit; above, it drifts.
WIND_DRAG: Final = 0.025

#: The battery's internal resistance (with the wiring) per cell, Ω: the load's voltage sag.
CELL_RESISTANCE: Final = 0.01

#: The rotors' induced velocity at hover, m/s: a climb at v_c needs the hover power times
#: v_c/(2·v_h) + sqrt((v_c/(2·v_h))² + 1) (momentum theory).
HOVER_INDUCED_SPEED: Final = 5.0

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

#: The STATUSTEXT of each ``hardware_error`` fault kind (also the "PreArm: ..." reason).
HW_TEXT: Final[Mapping[str, str]] = {
    "overheat": "Motor overheat",
    "overload": "Propulsion overload",
    "voltage": "Battery voltage critical",
}

_AUTOPILOT: Final = 1  # the autopilot's component id (MAV_COMP_ID_AUTOPILOT1)

_ARMING_CHECK_ALL: Final = 1

_ARMING_CHECK_BATTERY: Final = 256


def _no_fault(_: str) -> dict[str, Any] | None:
    return None


class VehicleModel(TypedDict, total=False):
    """The vehicle's model: :class:`VehicleState`'s keyword arguments but ``fault``, each optional.

    :class:`~temoto.drivers.mavlink.sim.SimVehicle` takes them as they are and hands them to
    its state (what each means is said there, the defaults are :class:`VehicleState`'s): the
    list is written once, here, and mypy checks both calls against it.
    """

    clock: Clock | None
    system_id: int
    home: tuple[float, float, float]
    battery: float
    cells: int
    min_arm_battery: float
    speed: float
    climb_rate: float
    descent_rate: float
    tau: float
    rtl_altitude: float
    drain_idle: float
    drain_flight: float
    step_rate: float
    params: Mapping[str, float] | None
    params_file: str | os.PathLike[str] | None


class VehicleState:
    """The state every part of the simulated vehicle shares, and the reads of it.

    The parts (telemetry, mission, flight model, failsafes, commands) each hold this object
    and read and write its public fields; the vehicle holds the parts. The constructor's
    arguments are :class:`~temoto.drivers.mavlink.sim.SimVehicle`'s of the same names (see
    there). The fields are guarded by :attr:`lock`: every method here but :meth:`param` and
    :meth:`position` expects it held.

    Args:
        name: For logs.
        clock: The model's clock.
        system_id: ``SYSID_THISMAV`` unless the parameter file sets it.
        home: Home (and the local frame's origin): latitude, longitude (deg), AMSL (m).
        battery: Initial charge, %.
        cells: Cells in series.
        min_arm_battery: Below this charge (%) arming is refused.
        speed: ``WPNAV_SPEED`` in m/s.
        climb_rate: ``WPNAV_SPEED_UP`` in m/s.
        descent_rate: ``WPNAV_SPEED_DN`` in m/s (``LAND_SPEED`` is a parameter, 0.5 m/s).
        tau: Time constant of the position model, s.
        rtl_altitude: ``RTL_ALT`` in m.
        drain_idle: Battery drain armed on the ground, %/s.
        drain_flight: Extra drain in the air, %/s.
        step_rate: Model steps per clock second.
        params: Parameter values over the defaults.
        params_file: A ``.param`` file loaded over them, if it exists.
        fault: The active fault of a name and its parameters (None: not active); the
            vehicle's :meth:`~temoto.drivers.sim.Simulator.fault`.

    Raises:
        ValueError: An argument out of range, an unknown parameter, a bad parameter file line.
        OSError: ``params_file`` exists but cannot be read.
    """

    def __init__(
        self,
        name: str = "vehicle",
        *,
        clock: Clock | None = None,
        system_id: int = 1,
        home: tuple[float, float, float] = (47.397742, 8.545594, 488.0),
        battery: float = 100.0,
        cells: int = 4,
        min_arm_battery: float = 20.0,
        speed: float = 10.0,
        climb_rate: float = 2.5,
        descent_rate: float = 1.5,
        tau: float = 1.0,
        rtl_altitude: float = 15.0,
        drain_idle: float = 0.01,
        drain_flight: float = 0.1,
        step_rate: float = 50.0,
        params: Mapping[str, float] | None = None,
        params_file: str | os.PathLike[str] | None = None,
        fault: Callable[[str], dict[str, Any] | None] = _no_fault,
    ) -> None:
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
        self.ptypes: dict[str, int] = {n: t for n, (_, t) in PARAMETERS.items()}
        self.params: dict[str, float] = {n: v for n, (v, _) in PARAMETERS.items()}
        initial = {
            "WPNAV_SPEED": speed * 100.0,
            "WPNAV_SPEED_UP": climb_rate * 100.0,
            "WPNAV_SPEED_DN": descent_rate * 100.0,
            "RTL_ALT": rtl_altitude * 100.0,
            "SYSID_THISMAV": float(system_id),
        }
        for key, value in initial.items():
            self.params[key] = self.stored(key, value)
        for key, value in (params or {}).items():
            if key not in PARAMETERS or not math.isfinite(value):
                raise ValueError(f"bad parameter {key}={value!r} (known: {list(PARAMETERS)})")
            self.params[key] = self.stored(key, float(value))
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
                self.ptypes.setdefault(key, p.MAV_PARAM_TYPE_REAL32)
                if key not in READ_ONLY:
                    self.params[key] = self.stored(key, value)
        sysid = round(self.params["SYSID_THISMAV"])
        if not 1 <= sysid <= 255:
            where = f" ({self.params_file})" if self.params_file is not None else ""
            raise ValueError(f"SYSID_THISMAV must be 1..255, got {sysid}{where}")
        self.names = sorted(self.params)  # PARAM_VALUE index order
        self.name = name
        self.clock: Clock = clock or MonotonicClock()
        self.codec = Codec(sysid, _AUTOPILOT)
        self.fault = fault
        self.origin = home
        #: Home: latitude, longitude (degrees), altitude above mean sea level (m).
        self.home = home
        self.home_locked = False
        self.cells, self.min_arm = int(cells), float(min_arm_battery)
        self.tau = tau
        self.drain_idle, self.drain_flight = drain_idle, drain_flight
        self.dt = 1.0 / step_rate
        # model (guarded by lock)
        self.lock = threading.Lock()
        self.battery = float(battery)
        self.current = 0.0  # the battery current of the last model step, A
        self.armed = False
        self.mode = "STABILIZE"
        self.pos = [0.0, 0.0, 0.0]  # north, east, up (m from the origin: home at start)
        self.vel = [0.0, 0.0, 0.0]
        self.accel = [0.0, 0.0]  # horizontal acceleration of the last model step, m/s²
        self.yaw = 0.0
        self.airborne = False
        # ArduCopter's ap.auto_armed: the pilot raised the throttle, or something stood in for
        # it (a GUIDED takeoff, MAV_CMD_MISSION_START, AUTO_OPTIONS bit 1); AUTO leaves the
        # ground only then. No RC here: the throttle is never raised
        self.auto_armed = False
        self.target: list[float] | None = None
        self.landing = False  # descending to land (LAND, RTL's or AUTO's landing)
        self.landed_state = p.MAV_LANDED_STATE_ON_GROUND
        self.texts: list[tuple[int, str]] = []
        self.outbox: list[bytes] = []  # frames the model wants sent with the next streams
        self.t0 = 0.0
        self.last = 0.0
        self.gcs_failsafe = False
        self.batt_failsafe = 0  # 0 none, 1 low, 2 critical
        self.rtl_arrived: float | None = None
        self.speed_override: dict[str, float] = {}
        # missions
        self.plans = MissionService(self.codec.encode, self.home_item, self.flying_mission)
        self.mis_index = 0  # the current mission command (0: none yet)
        self.mis_state = p.MISSION_STATE_NO_MISSION
        self.nav: dict[str, Any] | None = None  # the running navigation command
        self.sync_mission_param()

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
        with self.lock:
            return self.params[name]

    def stored(self, name: str, value: float) -> float:
        """``value`` as a parameter of ``name``'s type holds it."""
        return stored_value(self.ptypes[name], value)

    def value(self, name: str) -> float:
        """A parameter's value (lock held)."""
        return self.params[name]

    def sync_mission_param(self) -> None:
        """``MIS_TOTAL`` follows the stored mission."""
        self.params["MIS_TOTAL"] = float(self.plans.count())

    # ---- geometry ------------------------------------------------------------------------------

    def position(self) -> tuple[float, float, float]:
        """Where the vehicle is: latitude, longitude (degrees), altitude above home (m).

        Returns:
            The position.
        """
        with self.lock:
            lat, lon, up = self.geo(self.pos)
            return lat, lon, up - self.home_up()

    def geo(self, pos: list[float]) -> tuple[float, float, float]:
        """A local position (north, east, up) as latitude, longitude (deg) and up."""
        lat0, lon0, _ = self.origin
        lat = lat0 + math.degrees(pos[0] / EARTH_RADIUS)
        lon = lon0 + math.degrees(pos[1] / (EARTH_RADIUS * math.cos(math.radians(lat0))))
        return lat, lon, pos[2]

    def local(self, lat: float, lon: float) -> tuple[float, float]:
        """Latitude and longitude (deg) as north and east of the origin, m."""
        lat0, lon0, _ = self.origin
        north = math.radians(lat - lat0) * EARTH_RADIUS
        east = math.radians(lon - lon0) * EARTH_RADIUS * math.cos(math.radians(lat0))
        return north, east

    def home_up(self) -> float:
        """Home's height over the origin (the ground), m."""
        return self.home[2] - self.origin[2]

    def home_local(self) -> tuple[float, float, float]:
        """Home in the local frame: north, east, up, m."""
        north, east = self.local(self.home[0], self.home[1])
        return north, east, self.home_up()

    def max_lean(self) -> float:
        """ArduCopter's lean angle limit, rad: ``ANGLE_MAX`` (cdeg, its range 10..80 deg)."""
        return math.radians(min(max(self.value("ANGLE_MAX"), 1000.0), 8000.0) / 100.0)

    def max_accel(self) -> float:
        """The horizontal acceleration the lean limit allows, m/s²: g·tan(``ANGLE_MAX``)."""
        return GRAVITY * math.tan(self.max_lean())

    def wind_drag(self) -> tuple[float, float]:
        """The wind's push on the vehicle now: north, east acceleration, m/s².

        ``SIM_WIND_SPD`` m/s from ``SIM_WIND_DIR`` (true degrees the wind comes *from*, as in
        ArduPilot SITL's ``SIM_WIND_DIR``); the drag is :data:`WIND_DRAG` times the airspeed
        squared, along the air's velocity relative to the vehicle. Zero in still air (the model
        then flies its exact figures: the drag of its own motion is not modelled).
        """
        speed = self.value("SIM_WIND_SPD")
        if speed <= 0.0:
            return 0.0, 0.0
        towards = math.radians(self.value("SIM_WIND_DIR") + 180.0)
        rel_n = speed * math.cos(towards) - self.vel[0]
        rel_e = speed * math.sin(towards) - self.vel[1]
        airspeed = math.hypot(rel_n, rel_e)
        return WIND_DRAG * airspeed * rel_n, WIND_DRAG * airspeed * rel_e

    def flying_mission(self) -> bool:
        """Whether the mission runs (AUTO, started): ``AP_Mission``'s MISSION_RUNNING."""
        return self.mode == "AUTO" and self.mis_state == p.MISSION_STATE_ACTIVE

    def home_item(self) -> MissionItem:
        """Home as mission item 0."""
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

    def drain_rate(self) -> float:
        """The charge the motors draw now, % of the capacity per second.

        Disarmed nothing; armed ``drain_idle`` (the motors at their idle spin); in the air
        ``drain_flight`` more at hover, times the power the thrust needs over the hover's:
        the thrust's ratio to the weight (the lean: sqrt(1 + (a/g)²), the wind's drag
        included) to the power 3/2, and a climb's share (momentum theory,
        :data:`HOVER_INDUCED_SPEED`).
        """
        if not self.armed:
            return 0.0
        if not self.airborne:
            return self.drain_idle
        thrust = math.sqrt(1.0 + (math.hypot(*self.accel) / GRAVITY) ** 2)
        climb = max(self.vel[2], 0.0) / (2.0 * HOVER_INDUCED_SPEED)
        power = thrust * math.sqrt(thrust) * (climb + math.sqrt(climb * climb + 1.0))
        return self.drain_idle + self.drain_flight * power

    def drain(self, dt: float) -> None:
        """Draw the battery for ``dt`` s at :meth:`drain_rate`; sets :attr:`current`."""
        rate = self.drain_rate()
        self.current = rate / 100.0 * self.value("BATT_CAPACITY") * 3.6  # %/s → mAh/s → A
        self.battery = max(self.battery - rate * dt, 0.0)

    def resting_voltage(self) -> float:
        """The battery's voltage without load (its charge's), V."""
        if self.hw_kind() == "voltage":
            return self.cells * 2.9
        return self.cells * (3.3 + 0.9 * self.battery / 100.0)

    def voltage(self) -> float:
        """The battery voltage now, under the load's sag (:data:`CELL_RESISTANCE`), V."""
        return max(self.resting_voltage() - self.current * self.cells * CELL_RESISTANCE, 0.0)

    def failsafe_voltage(self) -> float:
        """The voltage the battery failsafe compares, V.

        ``BATT_FS_VOLTSRC`` 0: the measured one, 1: the sag-compensated (resting) one, as
        ``AP_BattMonitor_Backend::check_failsafe_types`` chooses.
        """
        if round(self.value("BATT_FS_VOLTSRC")) == 1:
            return self.resting_voltage()
        return self.voltage()

    def consumed_mah(self) -> float:
        """The charge used, mAh (of ``BATT_CAPACITY``)."""
        return self.value("BATT_CAPACITY") * (100.0 - self.battery) / 100.0

    def hw_kind(self) -> str | None:
        """The active ``hardware_error`` fault's kind (None: none)."""
        params = self.fault("hardware_error")
        return None if params is None else str(params.get("kind", "overheat"))

    def prearm_failure(self) -> str | None:
        """The first failing pre-arm check's STATUSTEXT (None: they pass)."""
        checks = round(self.value("ARMING_CHECK"))
        if checks == 0:
            return None
        kind = self.hw_kind()
        if kind is not None:
            return f"PreArm: {HW_TEXT[kind]}"
        if checks & (_ARMING_CHECK_ALL | _ARMING_CHECK_BATTERY):
            if self.batt_failsafe:
                return "PreArm: Battery failsafe"
            if self.battery < self.min_arm:
                return "PreArm: Battery below minimum arming capacity"
            arm_volt, arm_mah = self.value("BATT_ARM_VOLT"), self.value("BATT_ARM_MAH")
            if arm_volt > 0 and self.voltage() < arm_volt:
                return "PreArm: Battery 1 below minimum arming voltage"
            if arm_mah > 0 and self.value("BATT_CAPACITY") - self.consumed_mah() < arm_mah:
                return "PreArm: Battery 1 below minimum arming capacity"
        return None
