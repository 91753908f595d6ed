"""The Robot Manager on the simulated ODrive rover and the mobile manipulator (faster clocks)."""

from __future__ import annotations

import json
import math
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml
from _robots import robot_manager

from temoto import ActionEngine, Result, ScaledClock
from temoto.actions.builtin import ROBOT_ACTIONS
from temoto.config import Profile, parse_profile
from temoto.core.registrar import Registrar, Status, StatusUpdate
from temoto.managers.robot import RobotManager, RobotManagerClient

ROOT = Path(__file__).resolve().parents[2]
PROFILES = ROOT / "hw_profiles"
MISSIONS = ROOT / "examples" / "missions"
WAIT = 30.0


def sim_profile(name: str, clock: ScaledClock) -> Profile:
    """A shipped profile with ODrive heartbeats at 4 Hz instead of 10 Hz.

    The tests run the robots on a clock 3-5 times faster than real time; three missed 10 Hz
    heartbeats would then be 60-100 real milliseconds, which a loaded 2-core machine can
    take to schedule the simulator's thread. The driver's own tests check the bound itself.
    """
    doc = yaml.safe_load((PROFILES / name).read_text())
    for device in doc["devices"].values():
        if device["driver"] == "odrive_can":
            device["heartbeat_period"] = 0.25
    return parse_profile(doc, file=name, clock=clock)


def mission(name: str) -> dict[str, object]:
    doc: dict[str, object] = json.loads((MISSIONS / f"{name}.graph.json").read_text())
    return doc


@pytest.fixture
def rover() -> Iterator[tuple[Registrar, RobotManager, ScaledClock]]:
    clock = ScaledClock(5)
    profile = sim_profile("sim_rover.yaml", clock)
    with robot_manager("test-rover", profile, clock) as (registrar, manager):
        yield registrar, manager, clock


def test_the_route_comes_back_to_the_start(
    rover: tuple[Registrar, RobotManager, ScaledClock],
) -> None:
    registrar, _, clock = rover
    with ActionEngine(
        "sim_rover", actions=[ROBOT_ACTIONS], registrar=registrar, clock=clock
    ) as engine:
        outcome = engine.run(mission("rover_route"), timeout=WAIT * 5)
    assert outcome.result is Result.TRUE, outcome.errors
    x, y, yaw = (outcome.outputs[k] for k in ("pose_x", "pose_y", "pose_yaw"))
    assert math.hypot(x, y) < 0.1, (x, y)  # odometry: back where it started
    assert abs(yaw) < 0.1


def test_a_silent_wheel_fails_the_drive_and_its_return_is_reported(
    rover: tuple[Registrar, RobotManager, ScaledClock],
) -> None:
    registrar, manager, clock = rover
    statuses: list[StatusUpdate] = []
    watcher = RobotManagerClient(registrar).request(client="watcher", on_status=statuses.append)
    with ActionEngine(
        "sim_rover", actions=[ROBOT_ACTIONS], registrar=registrar, clock=clock
    ) as engine:
        engine.start(mission("rover_route"))
        deadline = time.monotonic() + WAIT
        while watcher.pose()[0] < 0.3:  # under way
            assert time.monotonic() < deadline, "the rover did not move"
            time.sleep(0.01)
        manager.simulator("base").inject("silence", node=2)
        assert engine.wait("rover_route", WAIT) is Result.ERROR
        errors = engine.outcome("rover_route").errors
    assert any("right_wheel" in str(e) or "node 2" in str(e) for e in errors), errors
    assert [s.status for s in statuses] == [Status.WARNING]  # the recovery runs meanwhile
    manager.simulator("base").clear()
    deadline = time.monotonic() + WAIT
    while Status.OK not in [s.status for s in statuses]:
        assert time.monotonic() < deadline, statuses
        time.sleep(0.01)
    assert watcher.healthy()


def test_the_mobile_manipulation_mission() -> None:
    clock = ScaledClock(3)
    registrar = Registrar("test-mm")
    profile = sim_profile("sim_mobile_manipulator.yaml", clock)
    manager = RobotManager(registrar, profile, clock=clock)
    try:
        with ActionEngine(
            "sim_mobile_manipulator", actions=[ROBOT_ACTIONS], registrar=registrar, clock=clock
        ) as engine:
            outcome = engine.run(mission("mobile_manipulation"), timeout=WAIT * 3)
        assert outcome.result is Result.TRUE, outcome.errors
        assert outcome.outputs["arm_positions"] == pytest.approx([0.0] * 6, abs=0.05)
        assert registrar.resources() == []
    finally:
        manager.shutdown()
        registrar.close()


def goto_graph(name: str, x: float, y: float) -> dict[str, object]:
    return {
        "graph_name": name,
        "graph_entry": [{"name": "NavigateTo", "instance_id": 0}],
        "graph_exit": [{"name": "NavigateTo", "instance_id": 0}],
        "actions": [
            {
                "name": "NavigateTo",
                "instance_id": 0,
                "type": "sync",
                "input_parameters": {
                    "x": {"pvf_type": "number", "pvf_value": x},
                    "y": {"pvf_type": "number", "pvf_value": y},
                },
            }
        ],
    }


def test_a_paused_graph_goes_on_after_another_graph_used_the_robot(
    rover: tuple[Registrar, RobotManager, ScaledClock],
) -> None:
    registrar, _, clock = rover
    watcher = RobotManagerClient(registrar).request(client="watcher")
    with ActionEngine(
        "sim_rover", actions=[ROBOT_ACTIONS], registrar=registrar, clock=clock
    ) as engine:
        engine.start(goto_graph("patrol", 2.0, 0.0))
        deadline = time.monotonic() + WAIT
        while watcher.pose()[0] < 0.3:
            assert time.monotonic() < deadline, "the rover did not move"
            time.sleep(0.01)
        engine.pause("patrol")
        errand = engine.run(goto_graph("errand", 0.0, 1.0), timeout=WAIT * 5)
        assert errand.result is Result.TRUE, errand.errors
        x, y, _ = watcher.pose()
        assert math.hypot(x, y - 1.0) < 0.1, (x, y)
        engine.resume("patrol")
        assert engine.wait("patrol", WAIT) is Result.TRUE
        x, y, _ = watcher.pose()
        assert math.hypot(x - 2.0, y) < 0.1, (x, y)
        logs = engine.graph_json("patrol")["actions"][0]["runtime"]["messages"]
    assert any("used meanwhile" in m["message"] for m in logs), logs
