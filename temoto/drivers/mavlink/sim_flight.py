"""The simulated ArduCopter's flight: the kinematic model and the flight modes.

:class:`FlightModel` steps a first-order kinematic model on the injected clock (the position
approaches its goal with time constant ``tau``, within ArduCopter's navigation speed limits;
LAND and RTL as ArduCopter flies them; the battery drains while armed) and changes the
vehicle's flight state as ArduCopter does: arming (with the pre-arm checks) and disarming,
mode changes (AUTO's refusals, a paused mission), GUIDED takeoff and reposition, and the home
position. A part of :class:`~temoto.drivers.mavlink.sim.SimVehicle` (see
:mod:`~temoto.drivers.mavlink.sim_state`); the lock is held in every method.
"""

from __future__ import annotations

import math
from typing import Final

from temoto.drivers.mavlink import protocol as p
from temoto.drivers.mavlink.sim_auto import AutoMission
from temoto.drivers.mavlink.sim_state import VehicleState
from temoto.drivers.mavlink.sim_telemetry import VehicleTelemetry

__all__ = ["FlightModel"]

_ARMABLE: Final = frozenset({"STABILIZE", "ACRO", "ALT_HOLD", "GUIDED", "LOITER", "POSHOLD"})

_SUPPORTED_MODES: Final = frozenset(_ARMABLE | {"RTL", "LAND", "BRAKE", "AUTO"})

_AUTO_OPTION_ALLOW_ARMING: Final = 1


def _clamp(value: float, low: float, high: float) -> float:
    return min(max(value, low), high)


class FlightModel:
    """The kinematic model and the flight modes (see the module docstring).

    Args:
        state: The vehicle's state.
        telemetry: Builds the HOME_POSITION and MISSION_CURRENT sent on a change.
        auto: The mission, run in AUTO.
    """

    def __init__(self, state: VehicleState, telemetry: VehicleTelemetry, auto: AutoMission) -> None:
        self.state = state
        self.telemetry = telemetry
        self.auto = auto

    # ---- model -------------------------------------------------------------------------------

    def advance(self, now: float) -> None:
        """Integrate from the last step to ``now`` in steps of at most ``1/step_rate``."""
        while now - self.state.last > 1e-9:
            dt = min(self.state.dt, now - self.state.last)
            self.state.last += dt
            self._step(dt)

    def _h_speed(self) -> float:
        """The horizontal speed limit now, m/s."""
        rtl = self.state.mode == "RTL" or (
            self.state.nav is not None and self.state.nav["kind"] == "rtl"
        )
        if rtl and self.state.value("RTL_SPEED") > 0:
            return self.state.value("RTL_SPEED") / 100.0
        if "xy" in self.state.speed_override:
            return self.state.speed_override["xy"]
        return max(self.state.value("WPNAV_SPEED"), 20.0) / 100.0

    def _up_speed(self) -> float:
        return self.state.speed_override.get(
            "up", max(self.state.value("WPNAV_SPEED_UP"), 10.0) / 100.0
        )

    def _down_speed(self) -> float:
        return self.state.speed_override.get(
            "down", max(self.state.value("WPNAV_SPEED_DN"), 10.0) / 100.0
        )

    def _land_speed(self) -> float:
        """ArduCopter's landing descent rate at the current height, m/s."""
        if self.state.pos[2] > self.state.value("LAND_ALT_LOW") / 100.0:
            high = self.state.value("LAND_SPEED_HIGH")
            return high / 100.0 if high > 0 else self._down_speed()
        return max(self.state.value("LAND_SPEED"), 30.0) / 100.0

    def _step(self, dt: float) -> None:
        if not self.state.armed:
            self.state.auto_armed = False  # Copter::update_auto_armed: disarmed, never auto-armed
        target = self._goal()
        if target is not None:
            pos, vel = self.state.pos, self.state.vel
            desired = [(target[i] - pos[i]) / self.state.tau for i in range(3)]
            horizontal = math.hypot(desired[0], desired[1])
            # the lean angle bounds the horizontal acceleration, so the speed is also bounded
            # by what can still stop at the target (no overshoot): sqrt(2 a d)
            accel = self.state.max_accel()
            distance = math.hypot(target[0] - pos[0], target[1] - pos[1])
            speed = min(self._h_speed(), math.sqrt(2.0 * accel * distance))
            if horizontal > speed:
                desired[0] *= speed / horizontal
                desired[1] *= speed / horizontal
            # the lean (thrust) gives the change of velocity and counters the wind's drag, all
            # within g·tan(ANGLE_MAX): a wind stronger than that pushes the vehicle off its goal
            drag_n, drag_e = self.state.wind_drag()
            thrust = [(desired[0] - vel[0]) / dt - drag_n, (desired[1] - vel[1]) / dt - drag_e]
            demand = math.hypot(thrust[0], thrust[1])
            if demand > accel or drag_n or drag_e:  # else: what was asked, to the last bit
                if demand > accel:
                    thrust = [thrust[0] * accel / demand, thrust[1] * accel / demand]
                desired[0] = vel[0] + (thrust[0] + drag_n) * dt
                desired[1] = vel[1] + (thrust[1] + drag_e) * dt
            self.state.accel = thrust
            desired[2] = _clamp(desired[2], -self._down_speed(), self._up_speed())
            if self.state.landing:
                desired[2] = -self._land_speed() if pos[2] > 0.0 else 0.0
            self.state.vel = desired
            for i in range(3):
                pos[i] += desired[i] * dt
            if math.hypot(desired[0], desired[1]) > 0.5:
                self.state.yaw = math.atan2(desired[1], desired[0])
        else:
            self.state.vel = [0.0, 0.0, 0.0]
            self.state.accel = [0.0, 0.0]
        if self.state.pos[2] <= 0.0:
            self.state.pos[2] = 0.0
            if (
                self.state.airborne
                and self.state.vel[2] <= 0.0
                and self.state.landed_state != (p.MAV_LANDED_STATE_TAKEOFF)
            ):
                self._touchdown()
        takeoff = self.state.landed_state == p.MAV_LANDED_STATE_TAKEOFF
        if takeoff and target is not None and abs(target[2] - self.state.pos[2]) < 0.3:
            self.state.landed_state = p.MAV_LANDED_STATE_IN_AIR
        self.state.drain(dt)
        if self.state.mode == "AUTO":
            self.auto.update()

    def _goal(self) -> list[float] | None:
        self.state.landing = False
        if not self.state.armed or not self.state.airborne:
            return None
        if self.state.mode == "LAND":
            self.state.landing = True
            self.state.landed_state = p.MAV_LANDED_STATE_LANDING
            return [self.state.pos[0], self.state.pos[1], 0.0]
        if self.state.mode == "RTL":
            return self._rtl_goal()
        nav = self.state.nav
        if self.state.mode == "AUTO" and nav is not None:
            if nav["kind"] == "rtl":
                return self._rtl_goal()
            target: list[float] = nav["target"]
            if nav["kind"] == "land":
                if math.hypot(target[0] - self.state.pos[0], target[1] - self.state.pos[1]) > 1.0:
                    return [target[0], target[1], self.state.pos[2]]  # fly there first, then land
                self.state.landing = True
                self.state.landed_state = p.MAV_LANDED_STATE_LANDING
            return target
        if self.state.target is None:
            self.state.target = list(self.state.pos)
        return self.state.target

    def _rtl_goal(self) -> list[float]:
        """RTL: climb to RTL_ALT, fly home, hover RTL_LOIT_TIME, then land (or RTL_ALT_FINAL)."""
        home_n, home_e, home_u = self.state.home_local()
        if self.state.rtl_arrived is None:
            if math.hypot(self.state.pos[0] - home_n, self.state.pos[1] - home_e) > 1.0:
                cruise = max(home_u + self.state.value("RTL_ALT") / 100.0, self.state.pos[2])
                if self.state.pos[2] < cruise - 0.5:
                    return [self.state.pos[0], self.state.pos[1], cruise]  # climb first
                return [home_n, home_e, cruise]
            self.state.rtl_arrived = self.state.last
        if self.state.last - self.state.rtl_arrived < self.state.value("RTL_LOIT_TIME") / 1000.0:
            return [home_n, home_e, self.state.pos[2]]
        final = self.state.value("RTL_ALT_FINAL") / 100.0
        if final > 0:
            return [home_n, home_e, home_u + final]
        self.state.landing = True
        self.state.landed_state = p.MAV_LANDED_STATE_LANDING
        return [home_n, home_e, 0.0]

    def _touchdown(self) -> None:
        self.state.airborne = False
        self.state.target = None
        self.state.landed_state = p.MAV_LANDED_STATE_ON_GROUND
        self.state.vel = [0.0, 0.0, 0.0]
        if self.state.armed and (self.state.mode in ("LAND", "RTL") or self.state.landing):
            self.state.armed = False
            self.state.texts.append((p.MAV_SEVERITY_INFO, "Disarming motors: landed"))

    # ---- flight state ---------------------------------------------------------------------------

    def arm(self) -> int:
        """Arm (pre-arm checks, an armable mode; home set here): the MAV_RESULT."""
        if self.state.armed:
            return p.MAV_RESULT_ACCEPTED
        failure = self.state.prearm_failure()
        if failure is not None:
            self.state.texts.append((p.MAV_SEVERITY_CRITICAL, failure))
            return p.MAV_RESULT_FAILED
        armable = self.state.mode in _ARMABLE or (
            self.state.mode == "AUTO"
            and round(self.state.value("AUTO_OPTIONS")) & _AUTO_OPTION_ALLOW_ARMING
        )
        if not armable:
            self.state.texts.append((p.MAV_SEVERITY_CRITICAL, "Arm: Mode not armable"))
            return p.MAV_RESULT_FAILED
        self.state.armed = True
        if not self.state.home_locked:  # ArduCopter sets home where it arms
            lat, lon, up = self.state.geo(self.state.pos)
            self.state.home = (lat, lon, self.state.origin[2] + up)
            self.state.outbox.append(self.telemetry.frame("HOME_POSITION", self.state.last))
        self.state.texts.append((p.MAV_SEVERITY_INFO, "Arming motors"))
        return p.MAV_RESULT_ACCEPTED

    def disarm(self, force: bool) -> int:
        """Disarm (in the air only when ``force``d): the MAV_RESULT."""
        if self.state.airborne and not force:
            self.state.texts.append((p.MAV_SEVERITY_CRITICAL, "Disarm: vehicle is flying"))
            return p.MAV_RESULT_FAILED
        self.state.armed = False
        self.state.airborne = False
        self.state.target = None
        if self.state.pos[2] > 0.0:
            self.state.pos[2] = 0.0  # a forced disarm in the air: it falls (instantly, here)
        self.state.landed_state = p.MAV_LANDED_STATE_ON_GROUND
        self.state.texts.append((p.MAV_SEVERITY_INFO, "Disarming motors"))
        return p.MAV_RESULT_ACCEPTED

    def set_mode(self, mode: str) -> int:
        """Change the flight mode as ArduCopter does (AUTO's refusals): the MAV_RESULT."""
        if mode not in _SUPPORTED_MODES:
            self.state.texts.append((p.MAV_SEVERITY_WARNING, f"Mode change to {mode} failed"))
            return p.MAV_RESULT_FAILED  # ArduPilot's answer to a mode it cannot enter
        if mode == "AUTO" and self.state.mode != "AUTO":
            refusal = self.auto.refusal()
            if refusal is not None:
                if refusal:
                    self.state.texts.append((p.MAV_SEVERITY_CRITICAL, refusal))
                self.state.texts.append(
                    (p.MAV_SEVERITY_WARNING, "Mode change to AUTO failed: init failed")
                )
                return p.MAV_RESULT_FAILED
        if mode != self.state.mode:
            if self.state.mode == "AUTO" and self.state.mis_state == p.MISSION_STATE_ACTIVE:
                self.state.mis_state = p.MISSION_STATE_PAUSED
                self.state.outbox.append(self.telemetry.frame("MISSION_CURRENT", self.state.last))
            self.state.nav = None
            self.state.target = list(self.state.pos) if self.state.airborne else None
            self.state.rtl_arrived = None
            self.state.speed_override = {}
            self.state.mode = mode
            if mode == "AUTO":
                self.auto.start_or_resume()
        return p.MAV_RESULT_ACCEPTED

    def takeoff(self, altitude: float) -> int:
        """GUIDED takeoff to ``altitude`` m above home: the MAV_RESULT."""
        if not (math.isfinite(altitude) and altitude > 0):
            return p.MAV_RESULT_DENIED
        if self.state.mode != "GUIDED" or not self.state.armed or self.state.airborne:
            self.state.texts.append(
                (p.MAV_SEVERITY_WARNING, "Takeoff: needs GUIDED, armed, landed")
            )
            return p.MAV_RESULT_FAILED
        self.state.airborne = True
        self.state.auto_armed = True  # Mode::do_user_takeoff
        self.state.landed_state = p.MAV_LANDED_STATE_TAKEOFF
        self.state.target = [
            self.state.pos[0],
            self.state.pos[1],
            self.state.home_up() + float(altitude),
        ]
        return p.MAV_RESULT_ACCEPTED

    def reposition(
        self, lat: float, lon: float, alt: float, *, amsl: bool, change_mode: bool
    ) -> int:
        """Fly to a position in GUIDED (``change_mode``: switch to GUIDED first): the MAV_RESULT."""
        if not (self.state.armed and self.state.airborne):
            return p.MAV_RESULT_DENIED
        if self.state.mode != "GUIDED":
            if not change_mode:
                return p.MAV_RESULT_DENIED
            self.set_mode("GUIDED")
        north, east = self.state.pos[0], self.state.pos[1]
        if math.isfinite(lat) and math.isfinite(lon) and (lat, lon) != (0.0, 0.0):
            north, east = self.state.local(lat, lon)
        up = self.state.pos[2]
        if math.isfinite(alt):
            up = alt - self.state.origin[2] if amsl else self.state.home_up() + alt
        self.state.target = [north, east, max(up, 0.5)]
        return p.MAV_RESULT_ACCEPTED

    def set_home(self, here: bool, lat: float, lon: float, alt: float, *, relative: bool) -> int:
        """DO_SET_HOME: here (param1 1), or at a position (AMSL, or relative in COMMAND_INT)."""
        if here:
            lat, lon, up = self.state.geo(self.state.pos)
            alt = self.state.origin[2] + up
        else:
            valid = math.isfinite(lat) and math.isfinite(lon) and math.isfinite(alt)
            if not valid or abs(lat) > 90 or abs(lon) > 180:
                return p.MAV_RESULT_FAILED
            if math.hypot(*self.state.local(lat, lon)) > 50_000:  # ArduPilot: too far from origin
                return p.MAV_RESULT_FAILED
            if relative:
                alt += self.state.home[2]
        self.state.home = (lat, lon, alt)
        self.state.home_locked = True
        return p.MAV_RESULT_ACCEPTED
