"""The robot on ROS 2 (a profile's ``ros2:`` block) against a plain rclpy node in its own process.

The simulated rover and arm run in this process under a Robot Manager; ``robot_peer.py`` (rclpy
only, no TeMoto) subscribes to their odometry, joint states and diagnostics and publishes
``cmd_vel``. Skipped where rclpy is not installed (see docs/ros2.md). Each test uses its own
``ROS_DOMAIN_ID`` and ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``, and checks that no Fast DDS
segment is left in /dev/shm. Process tests: 5-15 s each (discovery, the bridge's start).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml

from temoto.config import parse_profile
from temoto.core.registrar import Registrar
from temoto.managers.process import ProcessManager
from temoto.managers.robot import RobotManager, RobotManagerClient
from temoto.ros2.manager import PYTHON_VARIABLE, Ros2Manager
from temoto.ros2.shm import fastdds_segments

ROS_PYTHON = os.environ.get(PYTHON_VARIABLE) or sys.executable
ROOT = Path(__file__).resolve().parents[2]
PEER = Path(__file__).with_name("robot_peer.py")
_DOMAINS = iter(range(160 + os.getpid() % 30 * 2, 232))


def _has_robot_msgs(python: str) -> bool:
    check = (
        "import importlib.util as u, sys; sys.exit(not all(u.find_spec(m) for m in"
        " ('rclpy', 'nav_msgs', 'sensor_msgs', 'geometry_msgs', 'diagnostic_msgs')))"
    )
    try:
        return subprocess.run([python, "-c", check], timeout=60, check=False).returncode == 0
    except OSError:
        return False


pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(
        not _has_robot_msgs(ROS_PYTHON),
        reason="rclpy and the robot's interfaces are not installed (pip install 'temoto[ros2]',"
        " or set TEMOTO_ROS2_PYTHON)",
    ),
]


class RobotPeer:
    """The rclpy peer process; its JSON lines are collected."""

    def __init__(self, robot: str) -> None:
        self.proc = subprocess.Popen(
            [ROS_PYTHON, str(PEER), robot],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        self.lines: list[dict[str, Any]] = []
        self._ready = threading.Event()
        self._changed = threading.Condition()
        self._reader = threading.Thread(target=self._read, name="test-robot-peer-reader")
        self._reader.start()
        assert self._ready.wait(30), "the rclpy peer did not start"

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            if line.strip() == "ready":
                self._ready.set()
                continue
            with self._changed:
                self.lines.append(json.loads(line))
                self._changed.notify_all()

    def of(self, topic: str) -> list[dict[str, Any]]:
        with self._changed:
            return [m for m in self.lines if m["topic"] == topic]

    def wait_for(self, check: Callable[[], bool], timeout: float) -> bool:
        with self._changed:
            return self._changed.wait_for(check, timeout)

    def matched(self) -> int:
        """Wait until the peer's cmd_vel publisher is matched (or 20 s); the subscriptions."""
        self.send("wait_subscriber 20")
        assert self.wait_for(lambda: bool(self.of("subscribers")), 30)
        return int(self.of("subscribers")[-1]["subscribers"])

    def send(self, line: str) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()

    def stop(self) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
        code = self.proc.wait(15)
        self._reader.join(5)
        for stream in (self.proc.stdin, self.proc.stdout):
            if stream is not None:
                stream.close()
        return code


@pytest.fixture
def ros_env(monkeypatch: pytest.MonkeyPatch) -> Iterator[int]:
    """An own domain, discovery on this machine only, and no Fast DDS segment left after."""
    domain = next(_DOMAINS)
    monkeypatch.setenv("ROS_DOMAIN_ID", str(domain))
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    monkeypatch.delenv("RMW_IMPLEMENTATION", raising=False)
    before = set(fastdds_segments())
    yield domain
    left = sorted(set(fastdds_segments()) - before)
    assert not left, f"Fast DDS segments left in /dev/shm: {left}"


class Loaded:
    """A Robot Manager with a ROS 2 bridge server, and the robot held."""

    def __init__(self, name: str, ros2: dict[str, Any]) -> None:
        doc = yaml.safe_load((ROOT / "hw_profiles" / f"{name}.yaml").read_text())
        doc["ros2"] = ros2
        profile = parse_profile(doc, file=f"{name}.yaml")
        self.registrar = Registrar("r1")
        self.processes = ProcessManager(self.registrar, grace=5.0)
        self.ros2 = Ros2Manager(self.registrar)
        self.manager = RobotManager(self.registrar, profile)
        self.handle: Any = None
        try:
            self.handle = RobotManagerClient(self.registrar).request(client="test")
        except BaseException:
            self.close()
            raise
        self.robot = self.manager.robot()

    def close(self) -> None:
        try:
            if self.handle is not None:
                self.registrar.release(self.handle.resource.id)
            assert self.registrar.resources() == []  # the bridge went with the robot
        finally:
            self.manager.shutdown()
            self.processes.shutdown()
            self.ros2.shutdown()
            self.registrar.close()


@pytest.fixture
def loaded(ros_env: int) -> Iterator[Callable[[str, dict[str, Any]], Loaded]]:
    made: list[Loaded] = []

    def load(name: str, ros2: dict[str, Any]) -> Loaded:
        made.append(Loaded(name, ros2))
        return made[-1]

    yield load
    for item in made:
        item.close()


@pytest.fixture
def peer_of(ros_env: int) -> Iterator[Callable[[str], RobotPeer]]:
    made: list[RobotPeer] = []

    def start(robot: str) -> RobotPeer:
        made.append(RobotPeer(robot))
        return made[-1]

    yield start
    for p in made:
        assert p.stop() == 0


def test_rover_odometry_arrives_and_moves(loaded: Any, peer_of: Any) -> None:
    peer = peer_of("sim_rover")
    rover = loaded("sim_rover", {"publish": {"odom": 20, "diagnostics": 2}})
    assert peer.wait_for(lambda: len(peer.of("odom")) >= 3, 30), "no odometry on /sim_rover/odom"
    first = peer.of("odom")[-1]
    assert (first["frame"], first["child"]) == ("odom", "base_link")
    assert abs(first["stamp"] - time.time()) < 10
    assert peer.wait_for(lambda: bool(peer.of("diagnostics")), 10)
    assert peer.of("diagnostics")[-1]["levels"] == {"sim_rover/base": 0}  # OK
    motion = rover.handle.navigate_to(0.6, 0.0)
    assert peer.wait_for(lambda: peer.of("odom")[-1]["x"] > 0.3, 30), peer.of("odom")[-1]
    assert max(m["v"] for m in peer.of("odom")) > 0.1
    motion.cancel()
    assert not peer.of("joint_states"), "joint_states was not asked for"


def test_a_killed_bridge_is_replaced_and_the_robot_goes_on(loaded: Any, peer_of: Any) -> None:
    """The bridge is no dependency of the robot: its crash does not fail the robot's holders."""
    peer = peer_of("sim_rover")
    statuses: list[Any] = []
    rover = loaded("sim_rover", {"publish": {"odom": 20}})
    client = RobotManagerClient(rover.registrar)
    watcher = client.request(client="watcher", on_status=statuses.append)
    assert peer.wait_for(lambda: bool(peer.of("odom")), 30)
    (bridge,) = [r.response for r in rover.registrar.resources() if r.server == "ros2"]
    os.kill(bridge.pid, signal.SIGKILL)
    time.sleep(0.5)
    before = len(peer.of("odom"))
    assert peer.wait_for(lambda: len(peer.of("odom")) > before + 5, 60), "odometry did not resume"
    (again,) = [r.response for r in rover.registrar.resources() if r.server == "ros2"]
    assert again.pid != bridge.pid
    assert statuses == []  # the robot's holders were told nothing
    assert watcher.healthy()
    rover.registrar.release(watcher.resource.id)


def test_arm_joint_states_arrive_and_follow_the_arm(loaded: Any, peer_of: Any) -> None:
    peer = peer_of("sim_arm")
    arm = loaded("sim_arm", {})  # the defaults: joint_states at 20 Hz, diagnostics at 1 Hz
    assert arm.robot.ros2 is not None
    assert arm.robot.ros2.settings.rates == {"joint_states": 20.0, "diagnostics": 1.0}
    assert peer.wait_for(lambda: bool(peer.of("joint_states")), 30), "no /sim_arm/joint_states"
    names = set(peer.of("joint_states")[-1]["position"])
    assert names == {"shoulder_pan", "shoulder_lift", "elbow", "wrist_pitch", "wrist_roll"} | {
        "gripper"
    }
    arm.handle.move_joints({"shoulder_pan": 0.5})

    def panned() -> bool:
        return peer.of("joint_states")[-1]["position"]["shoulder_pan"] > 0.4

    assert peer.wait_for(panned, 30), peer.of("joint_states")[-1]


def test_the_quads_fix_and_diagnostics_arrive(loaded: Any, peer_of: Any) -> None:
    peer = peer_of("sim_quad")
    quad = loaded("sim_quad", {"publish": {"fix": 5, "diagnostics": 2}})
    assert peer.wait_for(lambda: bool(peer.of("fix")), 30), "no /sim_quad/fix"
    home = quad.handle.telemetry().position
    fix = peer.of("fix")[-1]
    assert fix["lat"] == pytest.approx(home.lat, abs=1e-5)
    assert fix["lon"] == pytest.approx(home.lon, abs=1e-5)
    assert fix["lat"] != 0.0
    assert peer.wait_for(lambda: bool(peer.of("diagnostics")), 10)
    assert set(peer.of("diagnostics")[-1]["levels"]) == {
        f"sim_quad/{d}" for d in quad.robot.health()
    }


def test_cmd_vel_drives_the_rover_and_it_stops_when_cmd_vel_stops(
    loaded: Any, peer_of: Any
) -> None:
    peer = peer_of("sim_rover")
    rover = loaded("sim_rover", {"publish": {"odom": 10}, "cmd_vel": True, "cmd_vel_timeout": 0.5})
    link = rover.robot.ros2
    assert link is not None
    assert peer.matched() == 1
    peer.send("cmd_vel 5.0 0.0 2.5")  # 5 m/s asked: clamped to max_speed 1.0
    assert peer.wait_for(lambda: bool(peer.of("cmd_vel_done")), 30)
    assert peer.of("cmd_vel_done")[0]["subscribers"] == 1
    assert link.commands["applied"] > 5, link.commands
    moved = rover.handle.pose()[0]
    assert moved > 0.2, moved
    top = max(m["v"] for m in peer.of("odom"))
    assert 0.1 < top <= 1.0 + 0.1, top  # the speed limit holds
    # no new cmd_vel: the base stops within the timeout (plus a control period or two)
    time.sleep(1.5)
    v, w = rover.robot.drive.velocity()  # type: ignore[union-attr]
    assert abs(v) < 0.02, (v, w)
    assert abs(w) < 0.05, (v, w)
    here = rover.handle.pose()[0]
    time.sleep(0.5)
    assert abs(rover.handle.pose()[0] - here) < 0.02


def test_cmd_vel_is_ignored_while_a_goal_drives_the_rover(loaded: Any, peer_of: Any) -> None:
    peer = peer_of("sim_rover")
    rover = loaded("sim_rover", {"publish": {"odom": 10}, "cmd_vel": True})
    link = rover.robot.ros2
    assert link is not None
    assert peer.matched() == 1
    motion = rover.handle.navigate_to(0.0, 3.0)  # turns left first, then drives along y
    peer.send("cmd_vel -1.0 0.0 1.0")
    assert peer.wait_for(lambda: bool(peer.of("cmd_vel_done")), 30)
    assert link.commands["refused"] > 0, link.commands
    assert link.commands["applied"] == 0, link.commands
    assert rover.handle.pose()[0] > -0.05  # never backed up
    motion.cancel()


def test_cmd_vel_without_the_opt_in_is_not_subscribed(loaded: Any, peer_of: Any) -> None:
    peer = peer_of("sim_rover")
    rover = loaded("sim_rover", {"publish": {"odom": 10}})
    assert peer.wait_for(lambda: bool(peer.of("odom")), 30)
    peer.send("cmd_vel 0.5 0.0 1.5")
    assert peer.wait_for(lambda: bool(peer.of("cmd_vel_done")), 30)
    assert peer.of("cmd_vel_done")[0]["subscribers"] == 0
    assert abs(rover.handle.pose()[0]) < 0.01
    assert abs(peer.of("odom")[-1]["x"]) < 0.01


def _robot_profile(tmp_path: Path, name: str, ros2: dict[str, Any]) -> Path:
    doc = yaml.safe_load((ROOT / "hw_profiles" / f"{name}.yaml").read_text())
    doc["ros2"] = ros2
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def test_the_robot_command_publishes_odometry_that_moves_during_make_runs_mission(
    ros_env: int, peer_of: Any, tmp_path: Path
) -> None:
    """``make run``'s mission, with a ``ros2:`` block in its profile (a process test, ~20 s)."""
    peer = peer_of("sim_mobile_manipulator")
    profile = _robot_profile(tmp_path, "sim_mobile_manipulator", {"publish": {"odom": 20}})
    mission = ROOT / "examples" / "missions" / "mobile_manipulation.graph.json"
    argv = ["--profile", str(profile), "--mission", str(mission), "--local"]
    done = subprocess.run(
        [sys.executable, "-m", "temoto.managers.robot", *argv],
        capture_output=True,
        text=True,
        timeout=180,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    xs = [m["x"] for m in peer.of("odom")]
    assert xs, "no odometry reached the rclpy subscriber"
    assert max(xs) - min(xs) > 0.5, (min(xs), max(xs))
    assert "Traceback" not in done.stderr


def test_ctrl_c_of_the_robot_command_with_a_ros2_block(
    ros_env: int, peer_of: Any, tmp_path: Path
) -> None:
    """Serving, then SIGINT: exit 0, no traceback, the bridge gone, no segment left."""
    peer = peer_of("sim_rover")
    profile = _robot_profile(tmp_path, "sim_rover", {"cmd_vel": True})
    proc = subprocess.Popen(
        [sys.executable, "-m", "temoto.managers.robot", "--profile", str(profile), "--local"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert peer.wait_for(lambda: bool(peer.of("odom")), 60), "no odometry"
        assert peer.matched() == 1
        proc.send_signal(signal.SIGINT)
        _out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err
    assert "Traceback" not in err, err
