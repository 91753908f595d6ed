"""The simulated ArduCopter in AUTO: flying the stored mission.

:class:`AutoMission` follows ArduCopter's mission logic over the plan that
:class:`~temoto.drivers.mavlink.sim_mission.MissionService` stores: the current command,
starting and resuming (``MIS_RESTART``), MISSION_SET_CURRENT, the NAV commands (TAKEOFF,
WAYPOINT with its acceptance radius and hold, LOITER_TIME, LOITER_UNLIM, LAND,
RETURN_TO_LAUNCH: each a goal for the kinematic model and a test of when it is done), the DO
commands run on the way to the next NAV one (DO_JUMP, DO_CHANGE_SPEED), MISSION_ITEM_REACHED
and the end of the mission. A layer of :class:`~temoto.drivers.mavlink.sim.SimVehicle` (see
:mod:`~temoto.drivers.mavlink.sim_state`); the lock is held in every method.
"""

from __future__ import annotations

import math
from typing import Any, Final

from temoto.drivers.mavlink import protocol as p
from temoto.drivers.mavlink.sim_mission import MissionItem
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

_NAV_LAST: Final = 95  # ArduPilot: command ids below MAV_CMD_NAV_LAST are navigation commands


class AutoMission(VehicleTelemetry):
    """The mission flown in AUTO (see the module docstring)."""

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
