"""Stop and pause act on the devices: a stopped or paused robot action leaves every device it
commanded still, seen from the simulators' state, before the engine reports it.

The robots here step their controllers at 2 Hz (``rate_hz``) instead of 50 Hz: a stop or hold
that waited for the control thread's next step would then be late by up to half a
second, so the checks at the moment the engine reports STOPPED or PAUSED tell the two apart
without tight timing. The arm's servos are slowed down (their Velocity Limit register, in the
simulator) so that a stop comes long before the pose is reached even on a loaded machine.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
from _robots import robot_manager

from temoto import ActionEngine, Result, ScaledClock
from temoto.actions.builtin import ROBOT_ACTIONS
from temoto.config import Profile, load_profile, parse_profile
from temoto.core.registrar import Registrar
from temoto.drivers.dynamixel import control_table as ct
from temoto.managers.robot import RobotManager, RobotManagerClient

ROOT = Path(__file__).resolve().parents[2]
PROFILES = ROOT / "hw_profiles"
WAIT = 20.0

#: X-series control table (ROBOTIS e-Manual, XM430-W350 "Control Table"): Velocity Limit (44,
#: 0.229 rpm units) and Moving (122).
VELOCITY_LIMIT = 44
MOVING = 122
#: About 0.5 rad/s: the move to pose 'reach' (0.8 rad on shoulder_lift) takes ~1.7 s.
SLOW = 20
#: Seconds the simulator's thread may take to act on a frame already written to its link.
WIRE = 0.03


def graph(name: str, action: str, inputs: dict[str, Any]) -> dict[str, Any]:
    params = {
        k: {"pvf_type": "string" if isinstance(v, str) else "number", "pvf_value": v}
        for k, v in inputs.items()
    }
    node = {"name": action, "instance_id": 0}
    return {
        "graph_name": name,
        "graph_entry": [node],
        "graph_exit": [node],
        "actions": [{**node, "type": "sync", "input_parameters": params}],
    }


def until(check: Callable[[], bool], what: str | Callable[[], str], timeout: float = WAIT) -> None:
    deadline = time.monotonic() + timeout
    while not check():
        assert time.monotonic() < deadline, what if isinstance(what, str) else what()
        time.sleep(0.002)


def node_state(engine: ActionEngine, name: str) -> str:
    return str(engine.graph_json(name)["actions"][0]["state"])


# ---- the arm ---------------------------------------------------------------------------------


@pytest.fixture
def arm() -> Iterator[tuple[Registrar, RobotManager, Any]]:
    with robot_manager("test-stop-arm", load_profile(PROFILES / "sim_arm.yaml"), rate_hz=2) as (
        registrar,
        manager,
    ):
        watcher = RobotManagerClient(registrar).request(client="watcher")  # loaded up front
        sim = manager.simulator("arm")
        for servo in sim.ids:
            sim.write_register(servo, VELOCITY_LIMIT, SLOW)
        yield registrar, manager, sim
        registrar.release(watcher.resource.id)


def _ticks(sim: Any, servo: int, reg: int) -> int:
    return int(sim.read_register(servo, reg))


def test_a_stopped_move_leaves_the_arm_where_it_was_not_at_the_pose(
    arm: tuple[Registrar, RobotManager, Any],
) -> None:
    registrar, _, sim = arm
    lift = 2  # shoulder_lift: 0 -> 0.8 rad in pose 'reach'
    start = _ticks(sim, lift, ct.GOAL_POSITION.address)
    with ActionEngine("sim_arm", actions=[ROBOT_ACTIONS], registrar=registrar) as engine:
        engine.start(graph("reach", "MoveJoints", {"pose": "reach"}))
        until(lambda: _ticks(sim, lift, ct.GOAL_POSITION.address) != start, "no goal was sent")
        pose = _ticks(sim, lift, ct.GOAL_POSITION.address)
        time.sleep(0.02)  # 5-30 ms after the motion started
        assert engine.stop("reach", WAIT) is Result.STOPPED
        at_stop = _ticks(sim, lift, ct.PRESENT_POSITION.address)
        # told before the engine said STOPPED: the goal is where the servo is, not the pose
        time.sleep(WIRE)
        goal = _ticks(sim, lift, ct.GOAL_POSITION.address)
        assert abs(goal - pose) > 100, (goal, pose)
        until(lambda: all(_ticks(sim, s, MOVING) == 0 for s in sim.ids), "the arm moves on", 5)
        final = _ticks(sim, lift, ct.PRESENT_POSITION.address)
    # 0.1 rad is 65 ticks; the pose is ~520 ticks from the start
    assert abs(final - at_stop) < 65, (final, at_stop, pose)
    assert abs(final - pose) > 200, (final, at_stop, pose)


def test_a_paused_move_holds_the_arm_before_the_node_is_paused_and_resumes_to_the_pose(
    arm: tuple[Registrar, RobotManager, Any],
) -> None:
    registrar, _, sim = arm
    lift = 2
    start = _ticks(sim, lift, ct.GOAL_POSITION.address)
    with ActionEngine("sim_arm", actions=[ROBOT_ACTIONS], registrar=registrar) as engine:
        engine.start(graph("reach", "MoveJoints", {"pose": "reach"}))
        until(lambda: _ticks(sim, lift, ct.GOAL_POSITION.address) != start, "no goal was sent")
        pose = _ticks(sim, lift, ct.GOAL_POSITION.address)
        time.sleep(0.02)
        engine.pause("reach")
        until(lambda: node_state(engine, "reach") == "PAUSED", "the node was not paused", 5)
        time.sleep(WIRE)
        held = _ticks(sim, lift, ct.GOAL_POSITION.address)
        assert abs(held - pose) > 100, (held, pose)  # held where it was, not going on
        until(lambda: all(_ticks(sim, s, MOVING) == 0 for s in sim.ids), "the arm moves on", 5)
        still = _ticks(sim, lift, ct.PRESENT_POSITION.address)
        assert abs(still - pose) > 200, (still, pose)
        engine.resume("reach")
        assert engine.wait("reach", WAIT) is Result.TRUE, engine.outcome("reach").errors
        final = _ticks(sim, lift, ct.PRESENT_POSITION.address)
    assert abs(final - pose) < 50, (final, pose)  # tolerance 0.03 rad is ~20 ticks


# ---- the base --------------------------------------------------------------------------------


def _lenient_rover() -> Profile:
    """The shipped rover with slower ODrive streams (heartbeats 4 Hz, encoder estimates 20 Hz).

    Its simulator shares this process: on a loaded 2-core machine a 10 ms encoder stream can
    miss its bound and fault the base, which is not what these tests are about.
    """
    doc = yaml.safe_load((PROFILES / "sim_rover.yaml").read_text())
    doc["devices"]["base"].update(heartbeat_period=0.25, encoder_period=0.05)
    return parse_profile(doc, file="sim_rover.yaml")


@pytest.fixture
def rover() -> Iterator[tuple[Registrar, RobotManager, Any]]:
    with robot_manager("test-stop-rover", _lenient_rover(), rate_hz=2) as (registrar, manager):
        watcher = RobotManagerClient(registrar).request(client="watcher")
        yield registrar, manager, manager.simulator("base")
        registrar.release(watcher.resource.id)


def _wheels(sim: Any) -> list[float]:
    return [float(axis.input_vel) for axis in sim.axes.values()]


def test_a_stopped_drive_has_its_wheels_at_zero_velocity_before_the_graph_is_stopped(
    rover: tuple[Registrar, RobotManager, Any],
) -> None:
    registrar, manager, sim = rover
    with ActionEngine("sim_rover", actions=[ROBOT_ACTIONS], registrar=registrar) as engine:
        engine.start(graph("drive", "NavigateTo", {"x": 2.0, "y": 0.0}))
        until(
            lambda: any(v != 0 for v in _wheels(sim)),
            lambda: f"the wheels were not driven: {manager.robot().health()}",
        )
        time.sleep(0.02)
        assert engine.stop("drive", WAIT) is Result.STOPPED
        time.sleep(WIRE)
        assert _wheels(sim) == [0.0, 0.0]
        # and they stay so (the control thread does not send the old goal again)
        time.sleep(0.6)
        assert _wheels(sim) == [0.0, 0.0]


def test_a_paused_drive_stops_its_wheels_and_resumes_to_the_goal(
    rover: tuple[Registrar, RobotManager, Any],
) -> None:
    registrar, manager, sim = rover
    with ActionEngine("sim_rover", actions=[ROBOT_ACTIONS], registrar=registrar) as engine:
        engine.start(graph("drive", "NavigateTo", {"x": 0.6, "y": 0.0}))
        until(lambda: any(v != 0 for v in _wheels(sim)), "the wheels were not driven")
        engine.pause("drive")
        until(lambda: node_state(engine, "drive") == "PAUSED", "the node was not paused", 5)
        time.sleep(WIRE)
        assert _wheels(sim) == [0.0, 0.0]
        engine.resume("drive")
        assert engine.wait("drive", WAIT) is Result.TRUE, engine.outcome("drive").errors
        x, y, _ = manager.robot().drive.pose()  # type: ignore[union-attr]
    assert math.hypot(x - 0.6, y) < 0.1, (x, y)


# ---- the vehicle -----------------------------------------------------------------------------


@pytest.fixture
def quad() -> Iterator[tuple[Registrar, RobotManager, Any, Any]]:
    clock = ScaledClock(10)
    profile = load_profile(PROFILES / "sim_quad.yaml", clock=clock)
    # 1 Hz of clock time: 100 ms real between two control steps (see the module)
    with robot_manager("test-stop-quad", profile, clock, rate_hz=1) as (registrar, manager):
        watcher = RobotManagerClient(registrar).request(client="watcher")
        motion = watcher.takeoff(5.0)
        assert motion.wait(WAIT)
        assert motion.error is None, motion.error
        yield registrar, manager, manager.simulator("quad"), clock
        registrar.release(watcher.resource.id)


def _far(sim: Any, north_m: float) -> dict[str, float]:
    lat, lon, _ = sim.home
    return {"lat": lat + north_m / 111_195.0, "lon": lon, "alt": 5.0}


def _speed(sim: Any) -> float:
    return math.hypot(sim.vel[0], sim.vel[1])


def test_a_stopped_flight_loiters_before_the_graph_is_stopped(
    quad: tuple[Registrar, RobotManager, Any, Any],
) -> None:
    registrar, _, sim, clock = quad
    with ActionEngine(
        "sim_quad", actions=[ROBOT_ACTIONS], registrar=registrar, clock=clock
    ) as engine:
        engine.start(graph("fly", "FlyTo", _far(sim, 2000.0)))
        until(lambda: _speed(sim) > 1.0, "the vehicle did not fly")
        assert engine.stop("fly", WAIT) is Result.STOPPED
        assert sim.mode == "LOITER"  # acknowledged before on_stop returned
        until(lambda: _speed(sim) < 0.1, "the vehicle flies on", 5)


def test_a_vehicle_switching_to_rtl_on_its_own_ends_the_flight_with_the_reason(
    quad: tuple[Registrar, RobotManager, Any, Any],
) -> None:
    registrar, _, sim, clock = quad
    with ActionEngine(
        "sim_quad", actions=[ROBOT_ACTIONS], registrar=registrar, clock=clock
    ) as engine:
        engine.start(graph("fly", "FlyTo", _far(sim, 2000.0)))
        until(lambda: _speed(sim) > 1.0, "the vehicle did not fly")
        with sim.state.lock:  # a pilot's switch, or a failsafe's: the vehicle changes mode itself
            sim.flight.set_mode("RTL")
        t0 = clock.monotonic()
        assert engine.wait("fly", WAIT) is Result.ERROR
        took = clock.monotonic() - t0
        errors = [str(e) for e in engine.outcome("fly").errors]
        assert sim.mode == "RTL"  # not talked out of it
    assert any("quad: the vehicle switched to RTL (not commanded)" in e for e in errors), errors
    assert took < 3.0, took  # within a heartbeat period or two (1 s, clock time), not hanging


def test_a_paused_flight_loiters_and_resumes_to_its_goal(
    quad: tuple[Registrar, RobotManager, Any, Any],
) -> None:
    registrar, _, sim, clock = quad
    with ActionEngine(
        "sim_quad", actions=[ROBOT_ACTIONS], registrar=registrar, clock=clock
    ) as engine:
        engine.start(graph("fly", "FlyTo", _far(sim, 60.0)))
        until(lambda: _speed(sim) > 1.0, "the vehicle did not fly")
        engine.pause("fly")
        until(lambda: node_state(engine, "fly") == "PAUSED", "the node was not paused", 5)
        assert sim.mode == "LOITER"
        engine.resume("fly")
        assert engine.wait("fly", WAIT) is Result.TRUE, engine.outcome("fly").errors
