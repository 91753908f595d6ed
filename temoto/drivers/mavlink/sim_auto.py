"""The simulated ArduCopter in AUTO: flying the stored mission.

:class:`AutoMission` follows ArduCopter's mission logic over the plan that
:class:`~temoto.drivers.mavlink.sim_mission.MissionService` stores: the current command,
starting and resuming (``MIS_RESTART``), MISSION_SET_CURRENT, the NAV commands (TAKEOFF,
WAYPOINT with its acceptance radius and hold, LOITER_TIME, LOITER_UNLIM, LAND,
RETURN_TO_LAUNCH: each a goal for the kinematic model and a test of when it is done), the DO
commands run on the way to the next NAV one (DO_JUMP, DO_CHANGE_SPEED), MISSION_ITEM_REACHED
and the end of the mission. A part of :class:`~temoto.drivers.mavlink.sim.SimVehicle` (see
:mod:`~temoto.drivers.mavlink.sim_state`); the lock is held in every method.
"""

from __future__ import annotations

import math
from typing import Any, Final

from temoto.drivers.mavlink import protocol as p
from temoto.drivers.mavlink.sim_mission import MissionItem
from temoto.drivers.mavlink.sim_state import VehicleState
from temoto.drivers.mavlink.sim_telemetry import VehicleTelemetry

__all__ = ["AutoMission"]

_NAV_CMDS: Final = {
    p.MAV_CMD_NAV_WAYPOINT: "wp",
    p.MAV_CMD_NAV_LOITER_UNLIM: "loiter_unlim",
    p.MAV_CMD_NAV_LOITER_TIME: "loiter_time",
    p.MAV_CMD_NAV_RETURN_TO_LAUNCH: "rtl",
    p.MAV_CMD_NAV_LAND: "land",
    p.MAV_CMD_NAV_TAKEOFF: "takeoff",
}

_AUTO_OPTION_TAKEOFF_NO_THROTTLE: Final = 2  # AUTO_OPTIONS bit 1

_NAV_LAST: Final = 95  # ArduPilot: command ids below MAV_CMD_NAV_LAST are navigation commands


class AutoMission:
    """The mission flown in AUTO (see the module docstring).

    Args:
        state: The vehicle's state (its ``plans`` hold the mission).
        telemetry: Builds the MISSION_CURRENT sent on every change.
    """

    def __init__(self, state: VehicleState, telemetry: VehicleTelemetry) -> None:
        self.state = state
        self.telemetry = telemetry
        self._mission_version = state.plans.version
        self._jumps: dict[int, int] = {}  # DO_JUMP item → jumps done

    def check_plan(self) -> None:
        """Follow a change of the stored mission (after a transfer or a clear)."""
        if self.state.plans.version != self._mission_version:
            self.on_mission_changed()

    def mission(self) -> list[MissionItem]:
        """The stored mission, item 0 (home as uploaded) included; empty if none.

        Returns:
            A copy of the items.
        """
        with self.state.lock:
            return self.state.plans.items

    @property
    def mission_current(self) -> int:
        """The sequence number of the current mission command (0: none)."""
        with self.state.lock:
            return self.state.mis_index

    def on_mission_changed(self) -> None:
        """A new mission was stored (or cleared): ArduCopter's mission change detector."""
        self._mission_version = self.state.plans.version
        self.state.sync_mission_param()
        count = self.state.plans.count()
        running = self.state.mode == "AUTO" and self.state.mis_state == p.MISSION_STATE_ACTIVE
        if count <= 1:
            self.state.mis_index = 0
            self.state.mis_state = p.MISSION_STATE_NO_MISSION
            if running:
                self._mission_complete()
                self.state.mis_state = p.MISSION_STATE_NO_MISSION
        elif not running:  # a new mission, not started yet
            self.state.mis_index = 1
            self.state.mis_state = p.MISSION_STATE_NOT_STARTED
            self._jumps = {}
        else:  # flying it: restart the current command of the new mission
            if self.state.mis_index >= count:
                self.state.mis_index = 1
            self.state.nav = None
            self.state.texts.append(
                (p.MAV_SEVERITY_CRITICAL, "Auto mission changed, restarted command")
            )
        self.state.outbox.append(self.telemetry.frame("MISSION_CURRENT", self.state.last))

    def _first_nav_is_takeoff(self) -> bool:
        seq = 1
        while (item := self.state.plans.item(seq)) is not None:
            if item.command < _NAV_LAST:
                return item.command == p.MAV_CMD_NAV_TAKEOFF
            seq += 1
        return False

    def refusal(self) -> str | None:
        """Why ArduCopter's ModeAuto::init would refuse AUTO now (None: it would not)."""
        if self.state.plans.count() <= 1:
            return ""
        if self.state.armed and not self.state.airborne and not self._first_nav_is_takeoff():
            return "Auto: Missing Takeoff Cmd"
        return None

    def start_or_resume(self) -> None:
        """Start the mission in AUTO, or resume it where it stopped (``MIS_RESTART``)."""
        restart = self.state.value("MIS_RESTART") == 1 or self.state.mis_index < 1
        if restart or self.state.mis_state in (
            p.MISSION_STATE_COMPLETE,
            p.MISSION_STATE_NO_MISSION,
        ):
            self.state.mis_index = 1
            self._jumps = {}
        self.state.mis_state = p.MISSION_STATE_ACTIVE
        self.state.nav = None
        self.state.outbox.append(self.telemetry.frame("MISSION_CURRENT", self.state.last))

    def set_current(self, seq: int, *, reset: bool = False) -> int:
        """MISSION_SET_CURRENT / DO_SET_MISSION_CURRENT: the MAV_RESULT."""
        seq = max(seq, 1)
        if self.state.plans.item(seq) is None:
            return p.MAV_RESULT_FAILED
        if reset:
            self._jumps = {}
        self.state.mis_index = seq
        if self.state.mis_state == p.MISSION_STATE_COMPLETE:
            self.state.mis_state = p.MISSION_STATE_PAUSED
        if self.state.mode == "AUTO" and self.state.mis_state == p.MISSION_STATE_ACTIVE:
            self.state.nav = None
            if self.state.armed:
                self._start_command(seq)
        self.state.outbox.append(self.telemetry.frame("MISSION_CURRENT", self.state.last))
        return p.MAV_RESULT_ACCEPTED

    def update(self) -> None:
        """Run the mission one model step (mode AUTO)."""
        if self.state.mis_state != p.MISSION_STATE_ACTIVE:
            return
        nav = self.state.nav
        if nav is None:
            if self.state.armed:
                self._start_command(self.state.mis_index)
            return
        self._lift_off()
        if not self._nav_done(nav):
            return
        seq = int(nav["seq"])
        self.state.nav = None
        self.state.outbox.append(self.state.codec.encode("MISSION_ITEM_REACHED", seq=seq))
        self.state.texts.append((p.MAV_SEVERITY_INFO, f"Reached command #{seq}"))
        if self.state.plans.item(seq + 1) is None:
            self._mission_complete()
        elif self.state.armed:
            self._start_command(seq + 1)
        else:
            self.state.mis_index = seq + 1
            self.state.outbox.append(self.telemetry.frame("MISSION_CURRENT", self.state.last))

    def _start_command(self, seq: int) -> None:
        """Start mission command ``seq``, running DO commands on the way to the next NAV one."""
        for _ in range(256):  # bounds a DO_JUMP loop without NAV commands
            item = self.state.plans.item(seq) if seq >= 1 else None
            if item is None:
                self._mission_complete()
                return
            self.state.mis_index = seq
            kind = _NAV_CMDS.get(item.command)
            if kind is not None:
                self._begin_nav(kind, item)
                self.state.outbox.append(self.telemetry.frame("MISSION_CURRENT", self.state.last))
                return
            if item.command == p.MAV_CMD_DO_JUMP:
                done = self._jumps.get(seq, 0)
                if item.param2 < 0 or done < item.param2:
                    self._jumps[seq] = done + 1
                    seq = int(item.param1)
                    continue
            elif item.command == p.MAV_CMD_DO_CHANGE_SPEED:
                self.change_speed(item.param1, item.param2)
            elif item.command < _NAV_LAST:
                self.state.texts.append(
                    (p.MAV_SEVERITY_WARNING, f"Skipping cmd #{seq}: not simulated")
                )
            seq += 1
        self._mission_complete()

    def _begin_nav(self, kind: str, item: MissionItem) -> None:
        north, east = self.state.pos[0], self.state.pos[1]
        if item.x != 0 or item.y != 0:
            north, east = self.state.local(item.lat, item.lon)
        up = self.state.home_up() + item.z if item.relative else item.z - self.state.origin[2]
        nav: dict[str, Any] = {"kind": kind, "seq": item.seq, "item": item, "reached": None}
        if kind == "takeoff":
            floor = self.state.pos[2] + (0.0 if self.state.airborne else 1.0)
            nav["target"] = [self.state.pos[0], self.state.pos[1], max(up, floor)]
        elif kind == "land":
            nav["target"] = [north, east, 0.0]
        elif kind == "rtl":
            self.state.rtl_arrived = None
            nav["target"] = None
        else:
            if item.z == 0:
                up = self.state.pos[2]  # ArduCopter: altitude 0 keeps the current one
            nav["target"] = [north, east, max(up, 0.5)]
        self.state.nav = nav
        self._lift_off()

    def _lift_off(self) -> None:
        """Leave the ground for the running NAV command once ArduCopter would spool up.

        ArduCopter's ``ModeAuto::takeoff_run`` sets ``auto_armed`` itself only with
        ``AUTO_OPTIONS`` bit 1 (AllowTakeOffWithoutRaisingThrottle); otherwise the takeoff
        waits on the ground until the throttle is raised or MAV_CMD_MISSION_START is sent.
        """
        nav, state = self.state.nav, self.state
        if nav is None or state.airborne or not state.armed or nav["kind"] in ("rtl", "land"):
            return
        no_throttle = round(state.value("AUTO_OPTIONS")) & _AUTO_OPTION_TAKEOFF_NO_THROTTLE
        if nav["kind"] == "takeoff" and no_throttle:
            state.auto_armed = True
        if state.auto_armed:
            state.airborne = True
            state.landed_state = p.MAV_LANDED_STATE_TAKEOFF

    def _nav_done(self, nav: dict[str, Any]) -> bool:
        kind = nav["kind"]
        item: MissionItem = nav["item"]
        if kind in ("land", "rtl"):
            return not self.state.airborne
        target: list[float] = nav["target"]
        if kind == "takeoff":
            return abs(target[2] - self.state.pos[2]) < 0.3
        if kind == "loiter_unlim":
            return False
        radius = (
            item.param2
            if kind == "wp" and item.param2 > 0
            else self.state.value("WPNAV_RADIUS") / 100
        )
        if nav["reached"] is None:
            if math.dist(target, self.state.pos) > max(radius, 0.05):
                return False
            nav["reached"] = self.state.last
        return bool(self.state.last - nav["reached"] >= max(item.param1, 0.0))

    def _mission_complete(self) -> None:
        self.state.nav = None
        self.state.mis_state = p.MISSION_STATE_COMPLETE
        if self.state.airborne:
            self.state.target = list(self.state.pos)  # hold where it is, still in AUTO
        elif self.state.armed:
            self.state.armed = False
            self.state.texts.append((p.MAV_SEVERITY_INFO, "Disarming motors"))
        self.state.outbox.append(self.telemetry.frame("MISSION_CURRENT", self.state.last))

    def change_speed(self, kind: float, speed: float) -> int:
        """DO_CHANGE_SPEED: 0/1 horizontal, 2 climb, 3 descent (m/s); the MAV_RESULT."""
        if not (math.isfinite(speed) and speed > 0):
            return p.MAV_RESULT_FAILED
        key = {2: "up", 3: "down"}.get(round(kind), "xy")
        self.state.speed_override[key] = float(speed)
        return p.MAV_RESULT_ACCEPTED
