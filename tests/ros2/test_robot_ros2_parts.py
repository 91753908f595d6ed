"""The robot's ``ros2:`` block without ROS 2: the profile's errors, the one line naming the extra
when rclpy is missing, and the safety checks a ``cmd_vel`` goes through (speed limits, the
robot's health, a goal that has the base, the stale-command stop) on the simulated rover.
These run everywhere, with or without the extra."""

from __future__ import annotations

import importlib.util
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml

from temoto.config import Ros2Settings, parse_profile
from temoto.core.registrar import Registrar
from temoto.errors import ProfileError, ResourceError
from temoto.managers.process import ProcessManager
from temoto.managers.robot import RobotManager, RobotManagerClient
from temoto.ros2.manager import PYTHON_VARIABLE, Ros2Manager
from temoto.ros2.robot import RobotRos2Link

ROOT = Path(__file__).resolve().parents[2]
PROFILES = ROOT / "hw_profiles"


def doc_of(name: str, ros2: Any) -> dict[str, Any]:
    doc = yaml.safe_load((PROFILES / f"{name}.yaml").read_text())
    doc["ros2"] = ros2
    return doc


def test_the_ros2_block_is_read_with_defaults_for_what_the_robot_has() -> None:
    rover = parse_profile(doc_of("sim_rover", {}), file="rover.yaml").ros2
    assert rover == Ros2Settings({"odom": 20.0, "joint_states": 20.0, "diagnostics": 1.0})
    quad = parse_profile(doc_of("sim_quad", {"cmd_vel": False}), file="quad.yaml").ros2
    assert quad is not None
    assert set(quad.rates) == {"fix", "diagnostics"}
    given = {"publish": {"odom": 50, "diagnostics": 0}, "cmd_vel": True, "cmd_vel_timeout": 0.3}
    rover = parse_profile(doc_of("sim_rover", given), file="rover.yaml").ros2
    assert rover == Ros2Settings({"odom": 50.0}, cmd_vel=True, cmd_vel_timeout=0.3)
    assert parse_profile(doc_of("sim_rover", None), file="rover.yaml").ros2 is None


@pytest.mark.parametrize(
    ("name", "block", "message"),
    [
        ("sim_arm", {"cmd_vel": True}, "arm.yaml: ros2.cmd_vel: the robot has no navigation"),
        ("sim_arm", {"publish": {"odom": 10}}, "arm.yaml: ros2.publish.odom: the robot has no"),
        ("sim_arm", {"publish": {"fix": 1}}, "arm.yaml: ros2.publish.fix: the robot has no flight"),
        ("sim_arm", {"publish": {"tf": 1}}, "arm.yaml: ros2.publish.tf: unknown key"),
        ("sim_arm", {"publish": {"joint_states": -1}}, "arm.yaml: ros2.publish.joint_states:"),
        ("sim_arm", {"rate": 1}, "arm.yaml: ros2.rate: unknown key"),
        ("sim_arm", {"cmd_vel_timeout": 0}, "arm.yaml: ros2.cmd_vel_timeout: must be"),
        ("sim_arm", {"domain_id": 300}, "arm.yaml: ros2.domain_id: must be an integer 0..232"),
        ("sim_arm", [1], "arm.yaml: ros2: must be a mapping"),
    ],
)
def test_a_bad_ros2_block_is_one_line_naming_file_and_key(
    name: str, block: Any, message: str
) -> None:
    with pytest.raises(ProfileError) as err:
        parse_profile(doc_of(name, block), file="arm.yaml")
    text = str(err.value)
    assert "\n" not in text
    assert text.startswith(message), text


@pytest.mark.skipif(importlib.util.find_spec("rclpy") is not None, reason="rclpy is installed here")
def test_without_the_extra_a_ros2_block_fails_in_one_line_naming_it(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.delenv(PYTHON_VARIABLE, raising=False)
    registrar = Registrar("no-ros")
    processes = ProcessManager(registrar)
    ros2 = Ros2Manager(registrar)
    manager = RobotManager(registrar, parse_profile(doc_of("sim_rover", {}), file="rover.yaml"))
    try:
        with pytest.raises(ResourceError) as err:
            RobotManagerClient(registrar).request(client="test")
        inner: BaseException = err.value
        while inner.__cause__ is not None:
            inner = inner.__cause__
        assert isinstance(inner, ProfileError)
        assert str(inner) == (
            "rover.yaml: ros2: the ros2 block needs rclpy: pip install 'temoto[ros2]'"
            " (or source a ROS 2 installation)"
        )
        assert registrar.resources() == []  # the drivers were let go
    finally:
        manager.shutdown()
        processes.shutdown()
        ros2.shutdown()
        registrar.close()


@pytest.fixture
def rover() -> Iterator[tuple[Registrar, RobotManager]]:
    registrar = Registrar("test-cmd-vel")
    manager = RobotManager(registrar, parse_profile(doc_of("sim_rover", None), file="rover.yaml"))
    try:
        yield registrar, manager
    finally:
        for ref in registrar.references():
            registrar.release(ref.id)
        manager.shutdown()
        registrar.close()


def settle(check: Any, timeout: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout
    while not check():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.02)
    return True


def test_cmd_vel_goes_through_the_limits_and_stops_when_commands_stop(
    rover: tuple[Registrar, RobotManager],
) -> None:
    registrar, manager = rover
    handle = RobotManagerClient(registrar).request(client="test")
    robot = manager.robot()
    link = RobotRos2Link(registrar, robot, Ros2Settings({}, cmd_vel=True, cmd_vel_timeout=0.3))
    drive = robot.drive
    assert drive is not None
    assert drive.command_velocity(9.0, -9.0, 0.3) == (1.0, -2.0)  # max_speed, max_turn_rate
    with pytest.raises(ValueError, match="finite"):
        drive.command_velocity(float("nan"), 0.0, 0.3)
    for _ in range(10):  # a stream of commands at 10 Hz
        assert link.drive(0.5, 0.0)
        time.sleep(0.1)
    assert settle(lambda: drive.velocity()[0] > 0.3), drive.velocity()
    # no new command: zero velocity after the timeout
    assert settle(lambda: abs(drive.velocity()[0]) < 0.02, 3.0), drive.velocity()
    x = handle.pose()[0]
    assert x > 0.2, x
    time.sleep(0.5)
    assert abs(handle.pose()[0] - x) < 0.02  # it stays stopped
    # a goal has the base: cmd_vel is ignored while it runs
    motion = handle.navigate_to(x + 2.0, 0.0)
    assert not link.drive(-1.0, 0.0)
    assert link.commands["refused"] == 1
    motion.cancel()
    # a faulted base: refused, and nothing is stored to drive on after a recovery
    manager.simulator("base").inject("silence")
    assert settle(lambda: not handle.healthy())
    assert not link.drive(0.5, 0.0)
    assert link.commands["refused"] == 2
    registrar.release(handle.resource.id)
