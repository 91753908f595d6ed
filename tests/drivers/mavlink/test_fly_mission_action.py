"""The FlyMission action through the Robot Manager, on a MAVLink vehicle end that flies AUTO.

The vehicle is :mod:`_mavemu` (independent of temoto's simulator): in AUTO it goes to the next
mission item every 0.05 real seconds, holds in any other mode, and disarms after a last LAND.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mav

from temoto import ActionEngine, Result
from temoto.actions.builtin import ROBOT_ACTIONS
from temoto.actions.builtin.robot.fly_mission import mission_from_inputs
from temoto.clock import MonotonicClock
from temoto.config import parse_profile
from temoto.core.registrar import Registrar
from temoto.drivers import MissionItem
from temoto.managers.robot import RobotManager, RobotManagerClient

from ._mavemu import AUTO, MavEmu

LAT = [47.3981, 47.3981, 47.39785, 47.39785]
LON = [8.54560, 8.54610, 8.54610, 8.54560]
ALT = [10.0, 10.0, 12.0, 12.0]
LOITER = 5


def graph(**inputs: Any) -> dict[str, Any]:
    """A graph of one FlyMission node with ``inputs`` (pvf types inferred)."""
    params: dict[str, Any] = {}
    for name, value in inputs.items():
        kind = "numbers" if isinstance(value, list) else "number"
        kind = "bool" if isinstance(value, bool) else kind
        if name in ("lat", "lon", "alt"):
            params.setdefault("waypoints", {})[name] = {"pvf_type": kind, "pvf_value": value}
        else:
            params[name] = {"pvf_type": kind, "pvf_value": value}
    return {
        "graph_name": "emu_mission",
        "graph_entry": [{"name": "FlyMission", "instance_id": 0}],
        "graph_exit": [{"name": "FlyMission", "instance_id": 0}],
        "actions": [
            {
                "name": "FlyMission",
                "instance_id": 0,
                "type": "sync",
                "input_parameters": params,
            }
        ],
    }


@pytest.fixture
def emu() -> Iterator[MavEmu]:
    with MavEmu() as vehicle:
        vehicle.item_seconds = 0.05
        yield vehicle


@pytest.fixture
def rig(emu: MavEmu) -> Iterator[tuple[ActionEngine, Registrar]]:
    clock = MonotonicClock()
    doc = {
        "robot": "emu_quad",
        "devices": {
            "quad": {
                "driver": "mavlink",
                "link": emu.link,
                "system_id": 1,
                "init_timeout": 3.0,
                "command_timeout": 0.2,
                "mission_timeout": 0.2,
                "stream_rate": 0,
            }
        },
        "features": {"flight": {"type": "vehicle", "device": "quad", "tolerance": 1.0}},
    }
    registrar = Registrar("test-fly-mission")
    manager = RobotManager(registrar, parse_profile(doc, file="emu.yaml", clock=clock), clock=clock)
    engine = ActionEngine("emu_quad", actions=[ROBOT_ACTIONS], registrar=registrar, clock=clock)
    try:
        yield engine, registrar
    finally:
        engine.shutdown()
        for ref in registrar.references():
            registrar.release(ref.id)
        manager.shutdown()
        registrar.close()


def test_the_waypoints_are_flown_as_one_mission_that_lands(
    emu: MavEmu, rig: tuple[ActionEngine, Registrar]
) -> None:
    engine = rig[0]
    outcome = engine.run(graph(lat=LAT, lon=LON, alt=ALT, speed=6.0), timeout=20)
    assert outcome.result is Result.TRUE, outcome.errors
    commands = [item.command for item in emu.mission[1:]]
    assert commands == [
        mav.MAV_CMD_NAV_TAKEOFF,
        mav.MAV_CMD_DO_CHANGE_SPEED,
        *[mav.MAV_CMD_NAV_WAYPOINT] * 4,
        mav.MAV_CMD_NAV_LAND,
    ]
    assert [round(item.x / 1e7, 7) for item in emu.mission[3:7]] == LAT
    assert emu.mission[1].z == 10.0  # the take-off altitude: the first waypoint's
    assert not emu.armed  # landed and disarmed: the mission is done


def test_a_stopped_mission_leaves_the_vehicle_loitering(
    emu: MavEmu, rig: tuple[ActionEngine, Registrar]
) -> None:
    emu.item_seconds = 30.0  # slow: it is stopped at the take-off
    # another consumer holds the robot: its release at the graph's end makes nothing safe,
    # the action's stop itself must hold the vehicle
    engine, registrar = rig
    RobotManagerClient(registrar).request(client="watcher")
    engine.start(graph(lat=LAT, lon=LON, alt=ALT))
    _wait_for(lambda: emu.mode == AUTO)
    assert engine.stop("emu_mission", timeout=10) is not Result.TRUE
    _wait_for(lambda: emu.mode == LOITER)
    assert emu.flying_seq == 1  # it holds where it was


def test_a_paused_mission_loiters_and_goes_on_from_the_same_item(
    emu: MavEmu, rig: tuple[ActionEngine, Registrar]
) -> None:
    engine = rig[0]
    emu.item_seconds = 0.4
    engine.start(graph(lat=LAT, lon=LON, alt=ALT, land=False))
    _wait_for(lambda: emu.flying_seq >= 2)
    engine.pause("emu_mission")
    _wait_for(lambda: emu.mode == LOITER)
    held = emu.flying_seq
    time.sleep(0.5)  # longer than an item takes in AUTO: LOITER holds
    assert emu.flying_seq == held
    emu.item_seconds = 0.05
    engine.resume("emu_mission")
    assert engine.wait("emu_mission", 20) is Result.TRUE
    # it flew the rest to the end, which it does only in AUTO (not its mode now: the ended
    # graph releases the robot, whose shutdown may already have put it in its safe LOITER)
    assert emu.flying_seq == 0
    assert emu.mission[-1].command == mav.MAV_CMD_NAV_WAYPOINT  # land: false
    assert emu.armed  # no landing: it hovers at the last waypoint


@pytest.mark.parametrize(
    ("inputs", "message"),
    [
        ({"lat": LAT, "lon": LON[:3], "alt": ALT}, "differ in length"),
        ({"lat": LAT, "lon": LON, "alt": [10.0, 0.0, 5.0, 5.0]}, r"waypoints::alt\[1\]"),
        ({"lat": [47.3, 95.0], "lon": [8.5, 8.5], "alt": [5.0, 5.0]}, "waypoint 1: .*out of range"),
        ({"lat": LAT, "lon": LON, "alt": ALT, "speed": -2.0}, "speed must be positive"),
        ({"lat": LAT, "lon": LON, "alt": ALT, "hold": -1.0}, "hold must be >= 0"),
    ],
)
def test_bad_inputs_fail_the_action_naming_them(
    emu: MavEmu, rig: tuple[ActionEngine, Registrar], inputs: dict[str, Any], message: str
) -> None:
    engine = rig[0]
    outcome = engine.run(graph(**inputs), timeout=10)
    assert outcome.result is Result.ERROR
    assert any(_matches(message, str(e)) for e in _chain(outcome.errors)), outcome.errors
    assert "MISSION_COUNT" not in emu.names_received()  # nothing was sent


def test_mission_from_inputs_builds_takeoff_speed_waypoints_and_landing() -> None:
    inputs = {
        "waypoints::lat": LAT[:2],
        "waypoints::lon": LON[:2],
        "waypoints::alt": [8.0, 9],
        "takeoff_alt": 5.0,
        "hold": 1.5,
        "speed": 4,
    }
    assert mission_from_inputs(inputs) == [
        MissionItem.takeoff(5.0),
        MissionItem.change_speed(4.0),
        MissionItem.waypoint(LAT[0], LON[0], 8.0, hold=1.5),
        MissionItem.waypoint(LAT[1], LON[1], 9.0, hold=1.5),
        MissionItem.land(),
    ]
    inputs = {"waypoints::lat": LAT[:1], "waypoints::lon": LON[:1], "waypoints::alt": [7.0]}
    assert mission_from_inputs({**inputs, "land": False}) == [
        MissionItem.takeoff(7.0),
        MissionItem.waypoint(LAT[0], LON[0], 7.0),
    ]
    with pytest.raises(ValueError, match="waypoints::lon must be a non-empty list"):
        mission_from_inputs({"waypoints::lat": LAT, "waypoints::alt": ALT})
    with pytest.raises(ValueError, match=r"waypoints::lat\[0\] must be a number"):
        mission_from_inputs({**inputs, "waypoints::lat": ["north"]})
    with pytest.raises(ValueError, match="land must be true or false"):
        mission_from_inputs({**inputs, "land": "yes"})


def _chain(errors: tuple[BaseException, ...]) -> Iterator[BaseException]:
    for error in errors:
        seen: BaseException | None = error
        while seen is not None:
            yield seen
            seen = seen.__cause__ or seen.__context__


def _matches(pattern: str, text: str) -> bool:
    import re

    return re.search(pattern, text) is not None


def _wait_for(pred: Callable[[], bool], seconds: float = 5.0) -> None:
    idle = threading.Event()
    deadline = time.monotonic() + seconds
    while not pred():
        assert time.monotonic() < deadline, "not within the time"
        idle.wait(0.01)
