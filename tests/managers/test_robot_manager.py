"""The Robot Manager on the simulated Dynamixel arm: load, move, faults, recovery, actions."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from _robots import robot_manager

from temoto import ActionEngine, Result
from temoto.actions.builtin import ROBOT_ACTIONS
from temoto.config import load_profile
from temoto.core.registrar import Registrar, Status, StatusUpdate
from temoto.managers.robot import RobotManager, RobotManagerClient

ROOT = Path(__file__).resolve().parents[2]
PROFILES = ROOT / "hw_profiles"
WAIT = 10.0


class Statuses:
    """Collects a consumer's statuses; waits for one."""

    def __init__(self) -> None:
        self.got: list[tuple[float, StatusUpdate]] = []
        self._cond = threading.Condition()

    def __call__(self, update: StatusUpdate) -> None:
        with self._cond:
            self.got.append((time.monotonic(), update))
            self._cond.notify_all()

    def wait_for(self, status: Status, timeout: float = WAIT) -> tuple[float, StatusUpdate]:
        with self._cond:
            assert self._cond.wait_for(
                lambda: any(u.status is status for _, u in self.got), timeout
            ), f"no {status.value} status; got {[u.status for _, u in self.got]}"
            return next((t, u) for t, u in self.got if u.status is status)


@pytest.fixture
def arm() -> Iterator[tuple[Registrar, RobotManager]]:
    with robot_manager("test-robot", load_profile(PROFILES / "sim_arm.yaml")) as pair:
        yield pair


def test_the_robot_loads_with_its_driver_as_a_dependency_and_moves(
    arm: tuple[Registrar, RobotManager],
) -> None:
    registrar, manager = arm
    robot = RobotManagerClient(registrar).request(client="test")
    assert robot.name == "sim_arm"
    assert robot.features == ("manipulation",)
    info = registrar.info(robot.resource.id)
    assert [d.server for d in registrar.dependencies(info.id)] == ["driver"]
    motion = robot.move_to_pose("reach")
    assert motion.wait(WAIT), motion
    assert motion.error is None
    positions = robot.joint_positions()
    assert positions["shoulder_pan"] == pytest.approx(0.6, abs=0.05)
    assert positions["elbow"] == pytest.approx(-1.0, abs=0.05)
    # released: the robot and its driver are unloaded, the simulator closed
    registrar.release(robot.resource.id)
    assert registrar.resources() == []
    with pytest.raises(Exception, match="not loaded"):
        manager.simulator("arm")


def test_a_silent_device_is_a_warning_for_the_robots_consumers_and_its_return_ok(
    arm: tuple[Registrar, RobotManager],
) -> None:
    registrar, manager = arm
    statuses = Statuses()
    robot = RobotManagerClient(registrar).request(client="test", on_status=statuses)
    sim = manager.simulator("arm")
    t0 = time.monotonic()
    sim.inject("silence")
    t_fatal, fatal = statuses.wait_for(Status.WARNING)  # FATAL only if the recovery gives up
    assert "arm" in fatal.message
    assert fatal.hops == ("driver", "robot")
    # three poll periods (20 ms) of unanswered SyncReads, each waiting its reply timeout
    print(f"fault reported after {(t_fatal - t0) * 1000:.0f} ms")
    assert t_fatal - t0 < 3 * (0.02 + 0.1) + 1.0
    assert not robot.healthy()
    sim.clear("silence")
    _, ok = statuses.wait_for(Status.OK)
    assert "arm" in ok.message
    assert robot.healthy()
    # recovered: the same robot is shared again, not loaded a second time on the same chain
    again = RobotManagerClient(registrar).request(client="other")
    assert again.resource.resource_id == robot.resource.resource_id


def test_an_overheating_servo_is_reported_with_its_typed_error(
    arm: tuple[Registrar, RobotManager],
) -> None:
    registrar, manager = arm
    statuses = Statuses()
    RobotManagerClient(registrar).request(client="test", on_status=statuses)
    manager.simulator("arm").inject("hardware_error", kind="overheat", device=3)
    _, fatal = statuses.wait_for(Status.FATAL)
    assert "overheat" in fatal.message.lower()


GRAPH = {
    "graph_name": "arm_moves",
    "graph_entry": [{"name": "MoveJoints", "instance_id": 0}],
    "graph_exit": [{"name": "MoveJoints", "instance_id": 1}],
    "actions": [
        {
            "name": "MoveJoints",
            "instance_id": 0,
            "type": "sync",
            "input_parameters": {"pose": {"pvf_type": "string", "pvf_value": "reach"}},
            "children": [{"name": "MoveJoints", "instance_id": 1}],
        },
        {
            "name": "MoveJoints",
            "instance_id": 1,
            "type": "sync",
            "parents": [{"name": "MoveJoints", "instance_id": 0}],
            "input_parameters": {
                "joints": {"pvf_type": "strings", "pvf_value": ["shoulder_pan", "elbow"]},
                "positions": {"pvf_type": "numbers", "pvf_value": [-0.4, 0.7]},
                "timeout": {"pvf_type": "number", "pvf_value": 10},
            },
        },
    ],
}


def test_robot_actions_in_a_graph(arm: tuple[Registrar, RobotManager]) -> None:
    registrar, _ = arm
    with ActionEngine("sim_arm", actions=[ROBOT_ACTIONS], registrar=registrar) as engine:
        outcome = engine.run(GRAPH, timeout=30)
        assert outcome.result is Result.TRUE, outcome.errors
        snapshot = engine.graph_json("arm_moves")
    logs = [m for a in snapshot["actions"] for m in a.get("runtime", {}).get("messages", [])]
    assert any("pose 'reach'" in str(m) for m in logs), logs
    # the graph ended: its reference to the robot is gone, and so is the robot
    assert registrar.resources() == []
