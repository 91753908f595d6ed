"""examples/missions/sim_quad_mission.graph.json end to end on hw_profiles/sim_quad.yaml.

FlyMission uploads the mission to temoto's simulated ArduCopter (MISSION_INT), starts it (GUIDED,
arm, MAV_CMD_MISSION_START) and follows MISSION_CURRENT to the landing, on a clock ten times
faster. It needs the simulator's mission protocol and AUTO mode.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from temoto import ActionEngine, Result, ScaledClock
from temoto.actions.builtin import ROBOT_ACTIONS
from temoto.config import load_profile
from temoto.core.registrar import Registrar
from temoto.managers.robot import RobotManager, RobotManagerClient

ROOT = Path(__file__).resolve().parents[3]
PROFILE = ROOT / "hw_profiles" / "sim_quad.yaml"
MISSION = json.loads((ROOT / "examples" / "missions" / "sim_quad_mission.graph.json").read_text())


@pytest.fixture
def quad() -> Iterator[tuple[Registrar, ScaledClock]]:
    clock = ScaledClock(10)
    registrar = Registrar("test-sim-quad-mission")
    manager = RobotManager(registrar, load_profile(PROFILE, clock=clock), clock=clock)
    try:
        yield registrar, clock
    finally:
        for ref in registrar.references():
            registrar.release(ref.id)
        manager.shutdown()
        registrar.close()


def test_the_sim_quad_mission_flies_four_waypoints_and_lands(
    quad: tuple[Registrar, ScaledClock],
) -> None:
    registrar, clock = quad
    watcher = RobotManagerClient(registrar).request(client="watcher")
    peak = [0.0]
    with ActionEngine(
        "sim_quad", actions=[ROBOT_ACTIONS], registrar=registrar, clock=clock
    ) as engine:
        engine.start(MISSION)
        deadline = time.monotonic() + 120.0
        while True:
            try:
                engine.wait("sim_quad_mission", 0.2)
                break
            except TimeoutError:
                peak[0] = max(peak[0], watcher.telemetry().position.alt)
                assert time.monotonic() < deadline, "the mission did not end in 120 s"
        outcome = engine.outcome("sim_quad_mission")
    assert outcome.result is Result.TRUE, outcome.errors
    assert peak[0] > 12.0  # it climbed to the last waypoints' 15 m
    # the action ends when the last item is done and the vehicle is down; ArduCopter disarms on
    # landing, which the driver hears with the next HEARTBEAT (1 Hz of the vehicle's clock)
    deadline = time.monotonic() + 10.0
    while (telemetry := watcher.telemetry()).armed and time.monotonic() < deadline:
        time.sleep(0.02)
    assert telemetry.position.alt < 0.5  # landed
    assert not telemetry.armed, telemetry.status_texts[-3:]
    home_lat = 47.397742
    assert abs(telemetry.position.lat - home_lat) > 0.0003  # it landed at the last waypoint
    registrar.release(watcher.resource.id)
