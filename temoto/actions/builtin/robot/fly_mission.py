"""FlyMission: upload a waypoint mission to the robot's vehicle and fly it (AUTO)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from temoto.actions.builtin.robot._common import RobotAction
from temoto.drivers import MissionItem
from temoto.managers.robot.client import RobotHandle
from temoto.managers.robot.features import Motion

__all__ = ["FlyMission", "mission_from_inputs"]

_AXES = ("lat", "lon", "alt")


def mission_from_inputs(inputs: Mapping[str, Any]) -> list[MissionItem]:
    """The mission FlyMission flies, from its inputs (checked).

    ``waypoints::lat``, ``waypoints::lon`` (degrees) and ``waypoints::alt`` (m above home)
    are lists of equal length, one waypoint each. The mission is a take-off to
    ``takeoff_alt`` (default: the first waypoint's altitude), then ``speed`` (m/s) if given,
    the waypoints (each held ``hold`` seconds), and a landing where the last one is unless
    ``land`` is false.

    Args:
        inputs: The action's inputs by full name.

    Returns:
        The mission items.

    Raises:
        ValueError: A missing, mismatched or out-of-range input (the message names it).
    """
    columns: dict[str, list[float]] = {}
    for axis in _AXES:
        name = f"waypoints::{axis}"
        raw = inputs.get(name)
        if not isinstance(raw, list) or not raw:
            raise ValueError(f"FlyMission: {name} must be a non-empty list of numbers")
        values: list[float] = []
        for index, value in enumerate(raw):
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise ValueError(f"FlyMission: {name}[{index}] must be a number, got {value!r}")
            if not math.isfinite(value):
                raise ValueError(f"FlyMission: {name}[{index}] must be finite, got {value!r}")
            values.append(float(value))
        columns[axis] = values
    counts = {axis: len(values) for axis, values in columns.items()}
    if len(set(counts.values())) != 1:
        shown = ", ".join(f"{axis} {n}" for axis, n in counts.items())
        raise ValueError(f"FlyMission: waypoints::lat, ::lon and ::alt differ in length ({shown})")
    hold = _number(inputs, "hold", 0.0)
    if hold < 0:
        raise ValueError(f"FlyMission: hold must be >= 0 seconds, got {hold:g}")
    waypoints: list[MissionItem] = []
    for index, (lat, lon, alt) in enumerate(zip(*columns.values(), strict=True)):
        if alt <= 0:
            raise ValueError(
                f"FlyMission: waypoints::alt[{index}] must be above home (> 0 m), got {alt:g}"
            )
        try:
            waypoints.append(MissionItem.waypoint(lat, lon, alt, hold=hold))
        except ValueError as err:
            raise ValueError(f"FlyMission: waypoint {index}: {err}") from None
    takeoff = _number(inputs, "takeoff_alt", columns["alt"][0])
    if takeoff <= 0:
        raise ValueError(f"FlyMission: takeoff_alt must be positive metres, got {takeoff:g}")
    mission = [MissionItem.takeoff(takeoff)]
    if "speed" in inputs:
        speed = _number(inputs, "speed", 0.0)
        if speed <= 0:
            raise ValueError(f"FlyMission: speed must be positive m/s, got {speed:g}")
        mission.append(MissionItem.change_speed(speed))
    mission.extend(waypoints)
    land = inputs.get("land", True)
    if not isinstance(land, bool):
        raise ValueError(f"FlyMission: land must be true or false, got {land!r}")
    if land:
        mission.append(MissionItem.land())
    return mission


def _number(inputs: Mapping[str, Any], name: str, default: float) -> float:
    value = inputs.get(name, default)
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ValueError(f"FlyMission: {name} must be a finite number, got {value!r}")
    return float(value)


class FlyMission(RobotAction):
    """Fly waypoints as one mission the vehicle flies itself (ArduPilot AUTO).

    Inputs ``waypoints::lat``, ``waypoints::lon`` (degrees), ``waypoints::alt`` (m above home):
    lists of equal length; optional ``takeoff_alt`` (m, default the first waypoint's),
    ``speed`` (m/s), ``hold`` (s at each waypoint), ``land`` (default true), ``robot``,
    ``timeout`` (see :func:`mission_from_inputs`). Progress: ``quad: item 3/6 (waypoint), alt
    10.0 m``. Paused, the vehicle loiters and goes on from the same item when resumed; stopped
    or timed out, it is left in LOITER (it does not fly the rest of the mission).
    """

    feature = "flight"
    _robot: RobotHandle | None = None

    def on_run(self) -> bool:
        """Do it; True when the vehicle flew the whole mission."""
        mission = mission_from_inputs(self.inputs)  # bad inputs fail before the robot is taken
        robot = self.robot()
        waypoints = sum(item.kind == "waypoint" for item in mission)
        landing = ", then land" if mission[-1].kind == "land" else ""
        self.log(f"{robot.name}: flying a mission of {waypoints} waypoints{landing}")
        self._robot = robot
        return self.run_motion(
            lambda: robot.fly_mission(mission), lambda: robot.estimate_mission(mission)
        )

    def missed(self, motion: Motion) -> tuple[str, str]:
        """``done with its mission`` and ``item 3/6 (waypoint), alt 10.0 m``."""
        return "done with its mission", motion.progress

    def progress(self, motion: Motion) -> str:
        """The item the vehicle is at, of how many, and its altitude."""
        if self._robot is None or not motion.progress:
            return motion.progress
        return f"{self._robot.name}: {motion.progress}"
