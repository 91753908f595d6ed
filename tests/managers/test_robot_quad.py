"""The Robot Manager on the simulated MAVLink quadcopter, on a clock ten times faster."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml
from _robots import robot_manager

from temoto import ActionEngine, Result, ScaledClock
from temoto.actions.builtin import ROBOT_ACTIONS
from temoto.config import load_profile, parse_profile
from temoto.core.registrar import Registrar
from temoto.errors import MavlinkCommandError
from temoto.managers.robot import RobotManager, RobotManagerClient

ROOT = Path(__file__).resolve().parents[2]
PROFILE = ROOT / "hw_profiles" / "sim_quad.yaml"
MISSION = json.loads((ROOT / "examples" / "missions" / "quad_survey.graph.json").read_text())
WAIT = 20.0


@pytest.fixture
def quad() -> Iterator[tuple[Registrar, RobotManager, ScaledClock]]:
    clock = ScaledClock(10)
    with robot_manager("test-quad", load_profile(PROFILE, clock=clock), clock) as (reg, manager):
        yield reg, manager, clock


def test_the_survey_mission_flies_and_lands(
    quad: tuple[Registrar, RobotManager, ScaledClock],
) -> None:
    registrar, _, clock = quad
    with ActionEngine(
        "sim_quad", actions=[ROBOT_ACTIONS], registrar=registrar, clock=clock
    ) as engine:
        outcome = engine.run(MISSION, timeout=WAIT * 10)
    assert outcome.result is Result.TRUE, outcome.errors
    assert registrar.resources() == []  # the graph's references released the robot


def test_lost_heartbeats_fail_the_flying_action_with_the_robots_fault(
    quad: tuple[Registrar, RobotManager, ScaledClock],
) -> None:
    registrar, manager, clock = quad
    watcher = RobotManagerClient(registrar).request(client="watcher")
    with ActionEngine(
        "sim_quad", actions=[ROBOT_ACTIONS], registrar=registrar, clock=clock
    ) as engine:
        engine.start(MISSION)
        deadline = time.monotonic() + WAIT
        while watcher.telemetry().position.alt < 3.0:  # airborne: the take-off is under way
            assert time.monotonic() < deadline, "the quad did not climb"
            time.sleep(0.02)
        manager.simulator("quad").inject("no_heartbeat")
        assert engine.wait("quad_survey", WAIT) is Result.ERROR
        errors = engine.outcome("quad_survey").errors
    assert any("quad" in str(e) and "heartbeat" in str(e).lower() for e in errors), errors
    registrar.release(watcher.resource.id)


def test_a_refused_arm_is_a_typed_error_with_the_vehicles_words() -> None:
    doc = yaml.safe_load(PROFILE.read_text())
    doc["devices"]["quad"]["sim"]["battery"] = 10  # below min_arm_battery: pre-arm fails
    clock = ScaledClock(10)
    registrar = Registrar("test-quad-battery")
    manager = RobotManager(registrar, parse_profile(doc, file="low.yaml", clock=clock), clock=clock)
    try:
        robot = RobotManagerClient(registrar).request(client="test")
        with pytest.raises(MavlinkCommandError, match=r"(?i)battery") as err:
            robot.takeoff(5.0)
        assert err.value.command == 400  # MAV_CMD_COMPONENT_ARM_DISARM
        registrar.release(robot.resource.id)
    finally:
        manager.shutdown()
        registrar.close()
