"""The simulated ArduCopter's telemetry: the messages it sends, and how often.

:class:`VehicleTelemetry` builds every message the vehicle sends from the shared state
(HEARTBEAT, the position, attitude, battery, status and mission messages, AUTOPILOT_VERSION,
PARAM_VALUE, STATUSTEXT) and paces the streams: each message of
:data:`~temoto.drivers.mavlink.sim_state.DEFAULT_RATES` has a period, changed by
``MAV_CMD_SET_MESSAGE_INTERVAL`` or :meth:`VehicleTelemetry.set_rate`; one call of
:meth:`VehicleTelemetry.streams` per model step returns what is due, with the queued texts,
the mission service's frames and the next few PARAM_VALUEs of a list download. No I/O: the
vehicle sends what it returns. A part of :class:`~temoto.drivers.mavlink.sim.SimVehicle` (see
:mod:`~temoto.drivers.mavlink.sim_state`).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import Final

from temoto.drivers.mavlink import protocol as p
from temoto.drivers.mavlink.sim_state import DEFAULT_RATES, GRAVITY, VehicleState
from temoto.drivers.realism import Realism

__all__ = ["VehicleTelemetry"]

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

_UINT16_MAX: Final = 65535
_INT16_MAX: Final = 32767

_FENCE_ALT_CIRCLE: Final = 1 | 2 | 8  # FENCE_TYPE bits: altitude max, circle, altitude min
_FENCE_POLYGON: Final = 4

_PARAMS_PER_STEP: Final = 5  # PARAM_VALUEs of a list download per model step (ArduPilot: 5)

_EKF_FLAGS: Final = 0x33F  # attitude, velocities, positions rel/abs, vertical, predicted

#: The messages that report the position estimate (noisy at a realism level other than off).
_POSITION_MESSAGES: Final = frozenset(
    {"GLOBAL_POSITION_INT", "GPS_RAW_INT", "VFR_HUD", "LOCAL_POSITION_NED"}
)
#: The messages that report the heading.
_HEADING_MESSAGES: Final = frozenset({"GLOBAL_POSITION_INT", "ATTITUDE", "VFR_HUD"})


class VehicleTelemetry:
    """The messages the simulated vehicle sends (see the module docstring).

    At a realism level other than ``off`` (:mod:`temoto.drivers.realism`) the reported
    position, altitude, velocity, attitude, heading and battery voltage carry the level's
    sensor noise (the model's state stays true), and each streamed frame may be lost
    (:meth:`~temoto.drivers.realism.Realism.lost`); the vehicle adds the link's jitter and
    stalls.

    Args:
        state: The vehicle's state.
        rates: Stream rates in Hz by message name, over :data:`DEFAULT_RATES` (0: not sent).
        realism: The vehicle's imperfections (None: none, the exact figures).

    Raises:
        ValueError: An unknown stream or a negative rate.
    """

    def __init__(
        self,
        state: VehicleState,
        rates: Mapping[str, float] | None = None,
        realism: Realism | None = None,
    ) -> None:
        merged = dict(DEFAULT_RATES)
        for msg, hz in (rates or {}).items():
            if msg.upper() not in DEFAULT_RATES or not (math.isfinite(hz) and hz >= 0):
                raise ValueError(f"bad stream rate {msg}={hz!r} (streams: {list(DEFAULT_RATES)})")
            merged[msg.upper()] = float(hz)
        self.state = state
        #: The noise and lost frames of the vehicle's realism level.
        self.realism = realism if realism is not None else Realism("off")
        #: Streamed frames lost on purpose (realism), by message name.
        self.lost: dict[str, int] = {}
        self._periods = {m: (1.0 / hz if hz > 0 else math.inf) for m, hz in merged.items()}
        self._due = dict.fromkeys(merged, 0.0)
        self._param_cursor: int | None = None  # PARAM_REQUEST_LIST being answered: next index

    def list_params(self) -> None:
        """Start sending every PARAM_VALUE, a few per model step (PARAM_REQUEST_LIST)."""
        self._param_cursor = 0

    def set_group_rate(self, names: Iterable[str], hz: float) -> None:
        """Stream each of ``names`` at ``hz`` (0: stop), as REQUEST_DATA_STREAM does.

        Args:
            names: Messages of :data:`DEFAULT_RATES`.
            hz: The rate.
        """
        for name in names:
            self._periods[name] = 1.0 / hz if hz > 0 else math.inf
            self._due[name] = 0.0

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
        with self.state.lock:
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
        with self.state.lock:
            period = self._periods[message.upper()]
        return 0.0 if period == math.inf else 1.0 / period

    def set_interval(self, msg_id: int, interval_us: float) -> int:
        """MAV_CMD_SET_MESSAGE_INTERVAL: the MAV_RESULT."""
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

    def streams(self, now: float) -> list[bytes]:
        """The frames due at ``now``: streams, queued texts and frames, transfers."""
        frames: list[bytes] = []
        for name, period in self._periods.items():
            if period == math.inf or now < self._due[name]:
                continue
            if name == "HEARTBEAT" and self.state.fault("no_heartbeat") is not None:
                continue
            self._due[name] = max(self._due[name] + period, now)
            if self.realism.lost():  # lost on the way: the schedule goes on
                self.lost[name] = self.lost.get(name, 0) + 1
                continue
            frames.append(self.frame(name, now))
        texts, self.state.texts = self.state.texts, []
        frames.extend(self.text_frames(texts))
        frames.extend(self.state.outbox)
        self.state.outbox = []
        frames.extend(self.state.plans.tick(now))
        if self._param_cursor is not None:  # a PARAM_REQUEST_LIST being answered, paced
            stop = min(self._param_cursor + _PARAMS_PER_STEP, len(self.state.names))
            frames += [
                self.param_value(self.state.names[i], i) for i in range(self._param_cursor, stop)
            ]
            self._param_cursor = stop if stop < len(self.state.names) else None
        return frames

    def text_frames(self, texts: list[tuple[int, str]]) -> list[bytes]:
        """STATUSTEXT frames of (severity, text) pairs."""
        return [
            self.state.codec.encode("STATUSTEXT", severity=sev, text=text.encode()[:50], id=0)
            for sev, text in texts
        ]

    def param_value(self, name: str, index: int) -> bytes:
        """The PARAM_VALUE of a parameter (``index`` -1: answered by name)."""
        return self.state.codec.encode(
            "PARAM_VALUE",
            param_id=name.encode(),
            param_value=self.state.params[name],
            param_type=self.state.ptypes[name],
            param_count=len(self.state.names),
            param_index=index if index >= 0 else _UINT16_MAX,
        )

    def one_message(self, msg_id: int) -> bytes | None:
        """MAV_CMD_REQUEST_MESSAGE: the message, or None if the vehicle does not send it."""
        names = {v: k for k, v in p.MSG_ID.items()}
        name = names.get(msg_id, "")
        if name not in DEFAULT_RATES and name != "AUTOPILOT_VERSION":
            return None
        return self.frame(name, self.state.clock.monotonic())

    def frame(self, name: str, now: float) -> bytes:
        """Message ``name`` as the vehicle would send it at ``now``."""
        boot_ms = int((now - self.state.t0) * 1000) & 0xFFFFFFFF
        pos, vel = self.state.pos, self.state.vel
        realism = self.realism
        noisy = realism.enabled
        if noisy and name in _POSITION_MESSAGES:  # what the estimate says, not the truth
            pos = [
                realism.noise("position", pos[0]),
                realism.noise("position", pos[1]),
                realism.noise("altitude", pos[2]),
            ]
            vel = [realism.noise("velocity", v) for v in vel]
        lat, lon, up = self.state.geo(pos)
        amsl = self.state.home[2] + up
        kind = self.state.hw_kind()
        enc = self.state.codec.encode
        if name == "HEARTBEAT":
            base = (
                p.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
                | p.MAV_MODE_FLAG_STABILIZE_ENABLED
                | p.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED  # ArduCopter sets it in every mode
            )
            if self.state.mode in ("GUIDED", "AUTO", "RTL", "LOITER", "POSHOLD", "BRAKE"):
                base |= p.MAV_MODE_FLAG_GUIDED_ENABLED  # ArduCopter's modes with a position goal
            if self.state.armed:
                base |= p.MAV_MODE_FLAG_SAFETY_ARMED
            # ArduCopter: STANDBY while landed (armed or not), ACTIVE in the air
            status = p.MAV_STATE_ACTIVE if self.state.airborne else p.MAV_STATE_STANDBY
            if kind is not None or self.state.gcs_failsafe or self.state.batt_failsafe:
                status = p.MAV_STATE_CRITICAL  # ArduCopter: any failsafe triggered
            return enc(
                "HEARTBEAT",
                type=p.MAV_TYPE_QUADROTOR,
                autopilot=p.MAV_AUTOPILOT_ARDUPILOTMEGA,
                base_mode=base,
                custom_mode=p.COPTER_MODES[self.state.mode],
                system_status=status,
                mavlink_version=3,
            )
        yaw = self.state.yaw
        if noisy and name in _HEADING_MESSAGES:
            yaw = realism.noise("heading", yaw)
        if name == "GLOBAL_POSITION_INT":
            hdg = round(math.degrees(yaw) % 360 * 100) % 36000
            return enc(
                "GLOBAL_POSITION_INT",
                time_boot_ms=boot_ms,
                lat=p.deg_e7(lat),
                lon=p.deg_e7(lon),
                alt=round(amsl * 1000),
                relative_alt=round((up - self.state.home_up()) * 1000),
                vx=round(vel[0] * 100),
                vy=round(vel[1] * 100),
                vz=round(-vel[2] * 100),
                hdg=hdg,
            )
        if name == "ATTITUDE":
            cos_y, sin_y = math.cos(self.state.yaw), math.sin(self.state.yaw)
            vel, acc = self.state.vel, self.state.accel
            # the tilt that accelerates it (atan(a/g)), plus a stand-in for the tilt against
            # drag at speed, within ANGLE_MAX (ArduCopter's lean limit)
            lean = self.state.max_lean()
            # in wind the model's acceleration is the thrust, the air's drag included
            stand_in = 0.0 if any(self.state.wind_drag()) else 0.03
            forward = math.atan((acc[0] * cos_y + acc[1] * sin_y) / GRAVITY)
            forward += stand_in * (vel[0] * cos_y + vel[1] * sin_y)
            right = math.atan((-acc[0] * sin_y + acc[1] * cos_y) / GRAVITY)
            right += stand_in * (-vel[0] * sin_y + vel[1] * cos_y)
            roll, pitch = min(max(right, -lean), lean), -min(max(forward, -lean), lean)
            if noisy:
                roll = realism.noise("attitude", roll)
                pitch = realism.noise("attitude", pitch)
            return enc(
                "ATTITUDE",
                time_boot_ms=boot_ms,
                roll=roll,
                pitch=pitch,
                yaw=math.atan2(math.sin(yaw), math.cos(yaw)),
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
            enabled = bits | (prearm if self.state.value("ARMING_CHECK") != 0 else 0)
            if self.state.armed or self.state.prearm_failure() is None:
                health |= prearm  # MAVLink: always healthy when armed
            present = bits | prearm
            # ArduPilot's AC_Fence::sys_status_present/enabled/failed: present when FENCE_TYPE
            # names a circle or altitude fence (or a polygon with points), enabled when
            # FENCE_ENABLE is set and FENCE_ACTION is not 0 (report only), failed only on a
            # breach (none simulated: always healthy)
            fence = p.MAV_SYS_STATUS_GEOFENCE
            types = round(self.state.value("FENCE_TYPE"))
            if types & _FENCE_ALT_CIRCLE or (
                types & _FENCE_POLYGON and self.state.plans.count(p.MAV_MISSION_TYPE_FENCE)
            ):
                present |= fence
                health |= fence
                if self.state.value("FENCE_ENABLE") and self.state.value("FENCE_ACTION"):
                    enabled |= fence
            return enc(
                "SYS_STATUS",
                onboard_control_sensors_present=present,
                onboard_control_sensors_enabled=enabled,
                onboard_control_sensors_health=health,
                load=250,
                voltage_battery=round(self._voltage() * 1000),
                current_battery=min(round(self.state.current * 100), _INT16_MAX),  # cA
                battery_remaining=round(self.state.battery),
                drop_rate_comm=0,
                errors_comm=0,
                errors_count1=0,
                errors_count2=0,
                errors_count3=0,
                errors_count4=0,
            )
        if name == "BATTERY_STATUS":
            cell = round(self._voltage() / self.state.cells * 1000)
            cells = [cell] * min(self.state.cells, 10) + [_UINT16_MAX] * (
                10 - min(self.state.cells, 10)
            )
            if kind == "voltage" or self.state.battery < 10 or self.state.batt_failsafe == 2:
                charge = p.MAV_BATTERY_CHARGE_STATE_CRITICAL
            elif self.state.battery < self.state.min_arm or self.state.batt_failsafe == 1:
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
                current_battery=min(round(self.state.current * 100), _INT16_MAX),  # cA
                current_consumed=round(self.state.consumed_mah()),
                energy_consumed=-1,
                battery_remaining=round(self.state.battery),
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
                vel=round(math.hypot(vel[0], vel[1]) * 100),
                cog=_UINT16_MAX,
                satellites_visible=14,
            )
        if name == "EXTENDED_SYS_STATE":
            landed = (
                self.state.landed_state if self.state.airborne else p.MAV_LANDED_STATE_ON_GROUND
            )
            return enc("EXTENDED_SYS_STATE", vtol_state=0, landed_state=landed)
        if name == "VFR_HUD":
            return enc(
                "VFR_HUD",
                airspeed=math.hypot(vel[0], vel[1]),
                groundspeed=math.hypot(vel[0], vel[1]),
                heading=round(math.degrees(yaw)) % 360,
                throttle=50 if self.state.airborne else 0,
                alt=amsl,
                climb=vel[2],
            )
        if name == "HOME_POSITION":
            return enc(
                "HOME_POSITION",
                latitude=p.deg_e7(self.state.home[0]),
                longitude=p.deg_e7(self.state.home[1]),
                altitude=round(self.state.home[2] * 1000),
                x=self.state.home_local()[0],  # home in the local frame (NED from the origin)
                y=self.state.home_local()[1],
                z=-self.state.home_up(),
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
                uid=self.state.codec.system_id,
            )
        return self._frame_more(name, now, boot_ms, pos, vel)

    def _voltage(self) -> float:
        """The battery voltage as the power monitor reports it, V."""
        volts = self.state.voltage()
        return self.realism.noise("voltage", volts) if self.realism.enabled else volts

    def _nav_target(self) -> list[float] | None:
        if self.state.nav is not None and self.state.nav.get("target") is not None:
            target: list[float] = self.state.nav["target"]
            return target
        return self.state.target if self.state.airborne else None

    def _frame_more(
        self, name: str, now: float, boot_ms: int, pos: list[float], vel: list[float]
    ) -> bytes:
        """The messages added for ground stations (issue 16); ``pos``, ``vel`` as reported."""
        enc = self.state.codec.encode
        if name == "LOCAL_POSITION_NED":
            return enc(
                "LOCAL_POSITION_NED",
                time_boot_ms=boot_ms,
                x=pos[0],
                y=pos[1],
                z=-pos[2],
                vx=vel[0],
                vy=vel[1],
                vz=-vel[2],
            )
        if name == "MISSION_CURRENT":
            count = self.state.plans.count()
            return enc(
                "MISSION_CURRENT",
                seq=self.state.mis_index,
                total=count - 1 if count > 1 else _UINT16_MAX,
                mission_state=self.state.mis_state,
                mission_mode=1 if self.state.mode == "AUTO" else 2,
            )
        if name == "NAV_CONTROLLER_OUTPUT":
            target = self._nav_target()
            dist, bearing, alt_error = 0.0, 0, 0.0
            if target is not None:
                dist = math.hypot(target[0] - self.state.pos[0], target[1] - self.state.pos[1])
                bearing = round(
                    math.degrees(
                        math.atan2(target[1] - self.state.pos[1], target[0] - self.state.pos[0])
                    )
                )
                alt_error = target[2] - self.state.pos[2]
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
            pwm = (1600 if self.state.airborne else 1100) if self.state.armed else 1000
            return enc(
                "SERVO_OUTPUT_RAW",
                time_usec=(boot_ms * 1000) & 0xFFFFFFFF,
                port=0,
                **{f"servo{i}_raw": pwm if i <= 4 else 0 for i in range(1, 9)},
            )
        if name == "SYSTEM_TIME":
            return enc(
                "SYSTEM_TIME",
                time_unix_usec=round(self.state.clock.time() * 1e6),
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
            level = 3.0 if self.state.airborne else 0.05
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
