"""The simulated ArduCopter's flight: the kinematic model and the flight modes.

:class:`FlightModel` steps a first-order kinematic model on the injected clock (the position
approaches its goal with time constant ``tau``, within ArduCopter's navigation speed limits;
LAND and RTL as ArduCopter flies them; the battery drains while armed) and changes the
vehicle's flight state as ArduCopter does: arming (with the pre-arm checks) and disarming,
mode changes (AUTO's refusals, a paused mission), GUIDED takeoff and reposition, and the home
position. A layer of :class:`~temoto.drivers.mavlink.sim.SimVehicle` (see
:mod:`~temoto.drivers.mavlink.sim_state`); the lock is held in every method.
"""

from __future__ import annotations

import math
from typing import Final

from temoto.drivers.mavlink import protocol as p
from temoto.drivers.mavlink.sim_auto import AutoMission

__all__ = ["FlightModel"]

_ARMABLE: Final = frozenset({"STABILIZE", "ACRO", "ALT_HOLD", "GUIDED", "LOITER", "POSHOLD"})

_SUPPORTED_MODES: Final = frozenset(_ARMABLE | {"RTL", "LAND", "BRAKE", "AUTO"})

_AUTO_OPTION_ALLOW_ARMING: Final = 1


def _clamp(value: float, low: float, high: float) -> float:
    return min(max(value, low), high)


class FlightModel(AutoMission):
    """The kinematic model and the flight modes (see the module docstring)."""

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

    # ---- flight state ---------------------------------------------------------------------------

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
