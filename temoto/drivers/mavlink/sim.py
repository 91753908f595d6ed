"""A simulated ArduCopter on UDP loopback: the vehicle's side of MAVLink 2 (STYLE §3.7).

:class:`SimVehicle` binds a UDP socket on ``127.0.0.1`` and *sends* to the ground stations it
is given (``gcs=[(host, port)]``, like a real autopilot streaming to ``udpin:`` listeners on
14550 or MAVSDK on 14540); it also answers anyone who sends to its own port (so a
``udpout:`` client works too). It behaves like a small ArduCopter:

* HEARTBEAT at 1 Hz (``MAV_TYPE_QUADROTOR``, ``MAV_AUTOPILOT_ARDUPILOTMEGA``, ArduCopter custom
  modes, the armed flag); GLOBAL_POSITION_INT, ATTITUDE, SYS_STATUS, BATTERY_STATUS,
  GPS_RAW_INT, EXTENDED_SYS_STATE, HOME_POSITION and VFR_HUD at configurable rates (also set by
  ``MAV_CMD_SET_MESSAGE_INTERVAL``); AUTOPILOT_VERSION and any streamed message on
  ``MAV_CMD_REQUEST_MESSAGE``.
* A COMMAND_ACK for every COMMAND_LONG and COMMAND_INT: arm/disarm (400) with pre-arm checks
  (battery below ``min_arm_battery`` %, a hardware error, or a mode that cannot arm →
  ``MAV_RESULT_FAILED``, and a ``PreArm:`` STATUSTEXT *after* the ack, as ArduPilot sends it),
  set mode (176, and the SET_MODE message), takeoff (22, GUIDED and armed), land (21), return
  to launch (20), reposition (192), and SET_POSITION_TARGET_GLOBAL_INT in GUIDED.
* A small parameter table (:data:`PARAMETERS`: the GCS failsafe's), answered with PARAM_VALUE
  on PARAM_REQUEST_READ (by name or index) and after PARAM_SET (the value as stored; an
  unknown name or a NaN gets no answer, as in ArduPilot).
* ArduCopter's GCS failsafe, on the injected clock: once a HEARTBEAT from the GCS system id
  ``SYSID_MYGCS`` (255) was seen, ``FS_GCS_TIMEOUT`` seconds (5) without one trigger it if
  ``FS_GCS_ENABLE`` is not 0: disarmed → nothing but a "GCS Failsafe" text; armed and landed →
  disarm; in the air → RTL (1, 2, 6), SmartRTL-or-RTL (3; SmartRTL is not simulated: RTL),
  SmartRTL-or-LAND (4: LAND), LAND (5), BRAKE (7), RTL for any other value. A heartbeat ends
  the failsafe ("GCS Failsafe Cleared"); the mode stays. ``FS_OPTIONS`` is not simulated.
  Each datagram received is parsed on its own.
* A first-order kinematic model stepped on the injected clock at ``step_rate`` Hz: the
  position approaches its target with time constant ``tau``, limited to ``speed`` m/s
  horizontally, ``climb_rate`` up and ``descent_rate`` down; LAND descends and disarms on
  touchdown; RTL climbs to ``rtl_altitude``, flies home and lands. The battery drains while
  armed (``drain_idle`` %/s) and more in the air (``drain_flight`` %/s).

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
import threading
from collections.abc import Iterable, Mapping
from typing import Any, ClassVar, Final

from temoto.clock import Clock, MonotonicClock
from temoto.drivers.mavlink import protocol as p
from temoto.drivers.mavlink.link import LinkSpec, UdpLink
from temoto.drivers.mavlink.protocol import Codec, Message
from temoto.drivers.sim import Simulator

__all__ = ["DEFAULT_RATES", "PARAMETERS", "SimVehicle"]

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
}

#: The simulated parameters: name → (ArduCopter's default, MAV_PARAM_TYPE).
PARAMETERS: Final[Mapping[str, tuple[float, int]]] = {
    "FS_GCS_ENABLE": (0.0, p.MAV_PARAM_TYPE_INT8),
    "FS_GCS_TIMEOUT": (5.0, p.MAV_PARAM_TYPE_REAL32),
    "SYSID_MYGCS": (255.0, p.MAV_PARAM_TYPE_INT16),
}
_INT_RANGE: Final = {
    p.MAV_PARAM_TYPE_INT8: (-128, 127),
    p.MAV_PARAM_TYPE_INT16: (-32768, 32767),
    p.MAV_PARAM_TYPE_INT32: (-(2**31), 2**31 - 1),
}
#: FS_GCS_ENABLE → the mode taken in the air (ArduCopter's failsafe actions; SmartRTL is not
#: simulated, so its fallbacks are taken).
_GCS_FAILSAFE_MODE: Final = {
    1: "RTL",
    2: "RTL",
    3: "RTL",
    4: "LAND",
    5: "LAND",
    6: "RTL",
    7: "BRAKE",
}

_ARMABLE: Final = frozenset({"STABILIZE", "ACRO", "ALT_HOLD", "GUIDED", "LOITER", "POSHOLD"})
_SUPPORTED_MODES: Final = frozenset(_ARMABLE | {"RTL", "LAND", "BRAKE"})
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


def _clamp(value: float, low: float, high: float) -> float:
    return min(max(value, low), high)


class SimVehicle(Simulator):
    """A simulated ArduCopter quad on UDP loopback (see the module docstring).

    Args:
        name: For thread names and logs.
        clock: Steps the model and paces the streams.
        gcs: Where to send (host, port) pairs; more are learned from whoever sends to us.
        port: This vehicle's own UDP port on 127.0.0.1 (0: any free port).
        system_id: The vehicle's MAVLink system id.
        home: Home latitude, longitude (degrees) and altitude above mean sea level (m).
        rates: Stream rates in Hz by message name (merged over :data:`DEFAULT_RATES`; 0 stops
            a stream).
        battery: Initial charge, percent.
        cells: Battery cells in series (4.2 V full, 3.3 V empty each).
        min_arm_battery: Below this charge (%) arming is refused.
        speed: Horizontal speed limit, m/s.
        climb_rate: Vertical speed limit up, m/s.
        descent_rate: Vertical speed limit down, m/s (also the landing speed).
        tau: Time constant of the position model, s.
        rtl_altitude: Minimum altitude above home for the flight home in RTL, m.
        drain_idle: Battery drain while armed on the ground, %/s.
        drain_flight: Battery drain in the air, %/s.
        step_rate: Model steps per clock second.
        params: Parameter values over :data:`PARAMETERS`' defaults (e.g.
            ``{"FS_GCS_ENABLE": 5}`` for a vehicle whose GCS failsafe lands it).

    Raises:
        ValueError: A parameter out of range, or an unknown parameter name.
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
    ) -> None:
        super().__init__()
        self._params = {name: value for name, (value, _) in PARAMETERS.items()}
        for name, value in (params or {}).items():
            if name not in PARAMETERS or not math.isfinite(value):
                raise ValueError(f"bad parameter {name}={value!r} (known: {list(PARAMETERS)})")
            self._params[name] = self._stored(name, float(value))
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
        self.name = name
        self.clock: Clock = clock or MonotonicClock()
        self.codec = Codec(system_id, 1)
        self.port = port
        self.home = home
        self._periods = {m: (1.0 / hz if hz > 0 else math.inf) for m, hz in merged.items()}
        self._due = dict.fromkeys(merged, 0.0)
        self._cells, self._min_arm = int(cells), float(min_arm_battery)
        self._speed, self._climb, self._descent, self._tau = speed, climb_rate, descent_rate, tau
        self._rtl_alt, self._drain_idle, self._drain_flight = rtl_altitude, drain_idle, drain_flight
        self._dt = 1.0 / step_rate
        self._gcs = list(gcs)
        # model (guarded by _lock)
        self._lock = threading.Lock()
        self._wake = threading.Condition(self._lock)
        self.battery = float(battery)
        self.armed = False
        self.mode = "STABILIZE"
        self.pos = [0.0, 0.0, 0.0]  # north, east, up (m from home)
        self.vel = [0.0, 0.0, 0.0]
        self.yaw = 0.0
        self.airborne = False
        self._target: list[float] | None = None
        self._landed_state = p.MAV_LANDED_STATE_ON_GROUND
        self._texts: list[tuple[int, str]] = []
        self._peers: list[Any] = []
        self._t0 = 0.0
        self._last = 0.0
        self._gcs_seen: float | None = None  # clock time of the GCS's newest heartbeat
        self._gcs_failsafe = False
        # I/O
        self._link: UdpLink | None = None
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        #: Frames received and commands acknowledged, for tests and benchmarks.
        self.received: dict[str, int] = {}
        self.acks: list[tuple[int, int]] = []

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
        self._link = UdpLink(LinkSpec("udpin", "127.0.0.1", self.port))
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
            name: One of :data:`PARAMETERS`.

        Returns:
            The value.

        Raises:
            KeyError: Not a simulated parameter.
        """
        with self._lock:
            return self._params[name]

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

    def _stored(self, name: str, value: float) -> float:
        """``value`` as a parameter of ``name``'s type holds it."""
        limits = _INT_RANGE.get(PARAMETERS[name][1])
        if limits is None:
            return value
        return float(min(max(round(value), limits[0]), limits[1]))

    # ---- geometry ----------------------------------------------------------------------------

    def position(self) -> tuple[float, float, float]:
        """Where the vehicle is: latitude, longitude (degrees), altitude above home (m).

        Returns:
            The position.
        """
        with self._lock:
            return self._geo(self.pos)

    def _geo(self, pos: list[float]) -> tuple[float, float, float]:
        lat0, lon0, _ = self.home
        lat = lat0 + math.degrees(pos[0] / EARTH_RADIUS)
        lon = lon0 + math.degrees(pos[1] / (EARTH_RADIUS * math.cos(math.radians(lat0))))
        return lat, lon, pos[2]

    def _local(self, lat: float, lon: float) -> tuple[float, float]:
        lat0, lon0, _ = self.home
        north = math.radians(lat - lat0) * EARTH_RADIUS
        east = math.radians(lon - lon0) * EARTH_RADIUS * math.cos(math.radians(lat0))
        return north, east

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

    def _step(self, dt: float) -> None:
        target = self._goal()
        if target is not None:
            desired = [(target[i] - self.pos[i]) / self._tau for i in range(3)]
            horizontal = math.hypot(desired[0], desired[1])
            if horizontal > self._speed:
                desired[0] *= self._speed / horizontal
                desired[1] *= self._speed / horizontal
            desired[2] = _clamp(desired[2], -self._descent, self._climb)
            if self.mode in ("LAND",) or (self.mode == "RTL" and target[2] == 0.0):
                desired[2] = -self._descent if self.pos[2] > 0.0 else 0.0
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

    def _goal(self) -> list[float] | None:
        if not self.armed or not self.airborne:
            return None
        if self.mode == "LAND":
            self._landed_state = p.MAV_LANDED_STATE_LANDING
            return [self.pos[0], self.pos[1], 0.0]
        if self.mode == "RTL":
            home_distance = math.hypot(self.pos[0], self.pos[1])
            cruise = max(self._rtl_alt, self.pos[2]) if home_distance > 1.0 else 0.0
            if cruise > 0.0 and self.pos[2] < cruise - 0.5:
                return [self.pos[0], self.pos[1], cruise]  # climb first
            if cruise == 0.0:
                self._landed_state = p.MAV_LANDED_STATE_LANDING
                return [0.0, 0.0, 0.0]
            return [0.0, 0.0, cruise]
        if self._target is None:
            self._target = list(self.pos)
        return self._target

    def _touchdown(self) -> None:
        self.airborne = False
        self._target = None
        self._landed_state = p.MAV_LANDED_STATE_ON_GROUND
        self.vel = [0.0, 0.0, 0.0]
        if self.armed and self.mode in ("LAND", "RTL"):
            self.armed = False
            self._texts.append((p.MAV_SEVERITY_INFO, "Disarming motors: landed"))

    def _voltage(self) -> float:
        if self._hw_kind() == "voltage":
            return self._cells * 2.9
        return self._cells * (3.3 + 0.9 * self.battery / 100.0)

    def _hw_kind(self) -> str | None:
        params = self.fault("hardware_error")
        return None if params is None else str(params.get("kind", "overheat"))

    # ---- GCS failsafe (lock held) -------------------------------------------------------------

    def _check_gcs(self, now: float) -> None:
        """ArduCopter's GCS failsafe check, once per model step."""
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
        self._texts.append((warn, "GCS Failsafe"))
        enable = int(self._params["FS_GCS_ENABLE"])
        if enable in (3, 4):
            fallback = "RTL" if enable == 3 else "Land"
            self._texts.append((warn, f"SmartRTL Unavailable, Using {fallback} Mode"))
        self._set_mode(_GCS_FAILSAFE_MODE.get(enable, "RTL"))

    # ---- commands ----------------------------------------------------------------------------

    def _handle(self, msg: Message) -> list[bytes]:
        target = msg.fields.get("target_system")
        if target not in (None, 0, self.codec.system_id):
            return []
        if msg.name == "HEARTBEAT":
            with self._lock:
                if msg.src_system == round(self._params["SYSID_MYGCS"]):
                    self._gcs_seen = self.clock.monotonic()
            return []
        if msg.name in ("PARAM_REQUEST_READ", "PARAM_SET"):
            return self._param_message(msg)
        if msg.name in ("COMMAND_LONG", "COMMAND_INT"):
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
        if msg.name == "SET_MODE":
            custom = msg.get_int("custom_mode")
            with self._lock:
                result = self._set_mode(p.mode_name(custom))
            ack = self.codec.encode(
                "COMMAND_ACK",
                command=p.MSG_ID["SET_MODE"],
                result=result,
                target_system=msg.src_system,
                target_component=msg.src_component,
            )
            return [ack]
        if msg.name == "SET_POSITION_TARGET_GLOBAL_INT":
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
        return []

    def _param_message(self, msg: Message) -> list[bytes]:
        """PARAM_REQUEST_READ and PARAM_SET: the PARAM_VALUE answer (none if unknown)."""
        names = list(PARAMETERS)
        name = msg.get_text("param_id")
        with self._lock:
            if msg.name == "PARAM_REQUEST_READ" and msg.get_int("param_index") >= 0:
                index = msg.get_int("param_index")
                name = names[index] if index < len(names) else ""
            if name not in PARAMETERS:
                return []
            if msg.name == "PARAM_SET":
                value = msg.get_float("param_value")
                if not math.isfinite(value):
                    return []
                self._params[name] = self._stored(name, value)
            value = self._params[name]
        frame = self.codec.encode(
            "PARAM_VALUE",
            param_id=name.encode(),
            param_value=value,
            param_type=PARAMETERS[name][1],
            param_count=len(names),
            param_index=names.index(name),
        )
        return [frame]

    def _command(self, msg: Message, cmd: int) -> tuple[int, list[bytes]]:
        """Carry out one command (lock held): its MAV_RESULT and any frames to send after."""
        prm = [msg.get_float(f"param{i}") for i in range(1, 5)]
        if msg.name == "COMMAND_LONG":
            prm += [msg.get_float("param5"), msg.get_float("param6"), msg.get_float("param7")]
        else:
            prm += [msg.get_int("x") / 1e7, msg.get_int("y") / 1e7, msg.get_float("z")]
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
        return p.MAV_RESULT_UNSUPPORTED, []

    def _arm(self) -> int:
        if self.armed:
            return p.MAV_RESULT_ACCEPTED
        kind = self._hw_kind()
        if kind is not None:
            self._texts.append((p.MAV_SEVERITY_CRITICAL, f"PreArm: {_HW_TEXT[kind]}"))
            return p.MAV_RESULT_FAILED
        if self.battery < self._min_arm:
            self._texts.append(
                (p.MAV_SEVERITY_CRITICAL, "PreArm: Battery below minimum arming capacity")
            )
            return p.MAV_RESULT_FAILED
        if self.mode not in _ARMABLE:
            self._texts.append((p.MAV_SEVERITY_CRITICAL, "Arm: Mode not armable"))
            return p.MAV_RESULT_FAILED
        self.armed = True
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
        if mode != self.mode:
            self._target = list(self.pos) if self.airborne else None
            self.mode = mode
        return p.MAV_RESULT_ACCEPTED

    def _takeoff(self, altitude: float) -> int:
        if not (math.isfinite(altitude) and altitude > 0):
            return p.MAV_RESULT_DENIED
        if self.mode != "GUIDED" or not self.armed or self.airborne:
            self._texts.append((p.MAV_SEVERITY_WARNING, "Takeoff: needs GUIDED, armed, landed"))
            return p.MAV_RESULT_FAILED
        self.airborne = True
        self._landed_state = p.MAV_LANDED_STATE_TAKEOFF
        self._target = [self.pos[0], self.pos[1], float(altitude)]
        return p.MAV_RESULT_ACCEPTED

    def _reposition(
        self, lat: float, lon: float, alt: float, *, amsl: bool, change_mode: bool
    ) -> int:
        if not (self.armed and self.airborne):
            return p.MAV_RESULT_DENIED
        if self.mode != "GUIDED":
            if not change_mode:
                return p.MAV_RESULT_DENIED
            self.mode = "GUIDED"
        north, east = self.pos[0], self.pos[1]
        if math.isfinite(lat) and math.isfinite(lon) and (lat, lon) != (0.0, 0.0):
            north, east = self._local(lat, lon)
        up = self.pos[2]
        if math.isfinite(alt):
            up = alt - self.home[2] if amsl else alt
        self._target = [north, east, max(up, 0.5)]
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
            base = p.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | p.MAV_MODE_FLAG_STABILIZE_ENABLED
            if self.mode == "GUIDED":
                base |= p.MAV_MODE_FLAG_GUIDED_ENABLED
            if self.armed:
                base |= p.MAV_MODE_FLAG_SAFETY_ARMED
            status = p.MAV_STATE_ACTIVE if self.armed else p.MAV_STATE_STANDBY
            if kind is not None:
                status = p.MAV_STATE_CRITICAL
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
                relative_alt=round(up * 1000),
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
            return enc(
                "SYS_STATUS",
                onboard_control_sensors_present=bits,
                onboard_control_sensors_enabled=bits,
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
            if kind == "voltage" or self.battery < 10:
                charge = p.MAV_BATTERY_CHARGE_STATE_CRITICAL
            elif self.battery < self._min_arm:
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
                current_consumed=-1,
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
                x=0.0,
                y=0.0,
                z=0.0,
                q=[1.0, 0.0, 0.0, 0.0],
                approach_x=0.0,
                approach_y=0.0,
                approach_z=0.0,
                time_usec=boot_ms * 1000,
            )
        if name == "AUTOPILOT_VERSION":
            caps = (
                p.MAV_PROTOCOL_CAPABILITY_MAVLINK2
                | p.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
                | p.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_GLOBAL_INT
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
        raise ValueError(f"the simulator does not send {name}")
