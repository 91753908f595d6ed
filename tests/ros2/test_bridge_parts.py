"""The bridge's parts that need no ROS 2: frames, the Fast DDS segment cleaner, and the
one-line errors when rclpy is missing (these run everywhere, with or without the extra)."""

from __future__ import annotations

import fcntl
import importlib.util
import json
import os
import socket
import struct
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from temoto import ActionEngine, Result
from temoto.actions.builtin import ROS2_ACTIONS
from temoto.core.registrar import Registrar
from temoto.errors import ConfigError
from temoto.managers.process import ProcessManager
from temoto.ros2 import require_rclpy
from temoto.ros2.client import BridgeClient, BridgeError
from temoto.ros2.manager import Ros2Manager, program_request
from temoto.ros2.protocol import MAX_FRAME, FrameError, recv_frame, send_frame
from temoto.ros2.shm import PORT_MIN_AGE_S, clean_stale_segments

HAS_RCLPY = importlib.util.find_spec("rclpy") is not None


def test_frames_round_trip_and_bad_frames_are_errors() -> None:
    a, b = socket.socketpair()
    with a, b:
        send_frame(a, {"id": 1, "op": "ping", "text": "é" * 10})
        assert recv_frame(b) == {"id": 1, "op": "ping", "text": "é" * 10}
        a.sendall(struct.pack(">I", 2) + b"[]")
        with pytest.raises(FrameError, match="a JSON list, not an object"):
            recv_frame(b)
        a.sendall(struct.pack(">I", MAX_FRAME + 1))
        with pytest.raises(FrameError, match="over the"):
            recv_frame(b)
        a.close()
        with pytest.raises(FrameError, match="closed"):
            recv_frame(b)


def _segment(shm: Path, name: str, *, lock: bool, port: bool = False) -> int | None:
    (shm / name).write_bytes(b"x")
    if port:
        (shm / f"sem.{name}_mutex").write_bytes(b"x")
    (shm / f"{name}_el").write_bytes(b"")
    if not lock:
        return None
    fd = os.open(shm / f"{name}_el", os.O_RDONLY)
    fcntl.flock(fd, fcntl.LOCK_SH)  # what a live Fast DDS user holds
    return fd


def test_only_segments_nobody_holds_are_removed(tmp_path: Path) -> None:
    held = _segment(tmp_path, "fastrtps_1111", lock=True)
    _segment(tmp_path, "fastrtps_2222", lock=False)
    _segment(tmp_path, "fastdds_port7011", lock=False, port=True)
    held_port = _segment(tmp_path, "fastrtps_port7000", lock=True, port=True)
    # a port segment a peer re-created for a dead participant: no lock file, old enough
    (tmp_path / "fastrtps_port7400").write_bytes(b"x")
    (tmp_path / "sem.fastrtps_port7400_mutex").write_bytes(b"x")
    old = time.time() - PORT_MIN_AGE_S - 5
    os.utime(tmp_path / "fastrtps_port7400", (old, old))
    # one just made (its creator may be about to add the lock file): kept
    (tmp_path / "fastrtps_port7401").write_bytes(b"x")
    (tmp_path / "unrelated").write_bytes(b"x")
    try:
        removed = clean_stale_segments(tmp_path)
    finally:
        for fd in (held, held_port):
            assert fd is not None
            os.close(fd)
    assert sorted(removed) == ["fastdds_port7011", "fastrtps_2222", "fastrtps_port7400"]
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "fastrtps_1111",
        "fastrtps_1111_el",
        "fastrtps_port7000",
        "fastrtps_port7000_el",
        "fastrtps_port7401",
        "sem.fastrtps_port7000_mutex",
        "unrelated",
    ]


@pytest.mark.skipif(HAS_RCLPY, reason="rclpy is installed here")
def test_without_the_extra_the_actions_fail_with_one_line_naming_it() -> None:
    with pytest.raises(ConfigError, match=r"pip install 'temoto\[ros2\]'"):
        require_rclpy()
    registrar = Registrar("r1")
    processes = ProcessManager(registrar, grace=1.0)
    Ros2Manager(registrar, python=sys.executable)
    graph = {
        "graph_name": "no_ros",
        "graph_entry": [{"name": "Ros2Publish", "instance_id": 0}],
        "graph_exit": [{"name": "Ros2Publish", "instance_id": 0}],
        "actions": [
            {
                "name": "Ros2Publish",
                "instance_id": 0,
                "type": "sync",
                "input_parameters": {
                    "topic": {"pvf_type": "string", "pvf_value": "/x"},
                    "type": {"pvf_type": "string", "pvf_value": "std_msgs/msg/String"},
                },
            }
        ],
    }
    try:
        with ActionEngine("r1", actions=[ROS2_ACTIONS], registrar=registrar) as engine:
            outcome = engine.run(graph, timeout=30)
    finally:
        processes.shutdown()
        registrar.close()
    assert outcome.result is Result.ERROR
    (error,) = outcome.errors
    assert str(error) == (
        "Ros2Publish_0 failed: the ROS 2 actions need rclpy: "
        "pip install 'temoto[ros2]' (or source a ROS 2 installation)"
    )
    assert processes.running() == []


def _publish_graph() -> dict[str, object]:
    return {
        "graph_name": "ros2_publish",
        "graph_entry": [{"name": "Ros2Publish", "instance_id": 0}],
        "graph_exit": [{"name": "Ros2Publish", "instance_id": 0}],
        "actions": [
            {
                "name": "Ros2Publish",
                "instance_id": 0,
                "type": "sync",
                "input_parameters": {
                    "topic": {"pvf_type": "string", "pvf_value": "/x"},
                    "type": {"pvf_type": "string", "pvf_value": "std_msgs/msg/String"},
                },
            }
        ],
    }


def test_a_missing_ros2_python_is_one_line(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    missing = tmp_path / "nowhere" / "python"
    monkeypatch.setenv("TEMOTO_ROS2_PYTHON", str(missing))
    registrar = Registrar("r1")
    processes = ProcessManager(registrar, grace=1.0)
    Ros2Manager(registrar)
    try:
        with ActionEngine("r1", actions=[ROS2_ACTIONS], registrar=registrar) as engine:
            outcome = engine.run(_publish_graph(), timeout=30)
    finally:
        processes.shutdown()
        registrar.close()
    assert outcome.result is Result.ERROR
    (error,) = outcome.errors
    assert str(error) == f"Ros2Publish_0 failed: TEMOTO_ROS2_PYTHON={missing}: no such executable"


@pytest.fixture
def no_rclpy_python(tmp_path: Path) -> Iterator[str]:
    """An interpreter without rclpy: this one if it has none, else a bare venv's."""
    if not HAS_RCLPY:
        yield sys.executable
        return
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(tmp_path / "v")], check=True)
    yield str(tmp_path / "v" / "bin" / "python")


def test_a_bridge_without_rclpy_answers_with_one_line(tmp_path: Path, no_rclpy_python: str) -> None:
    path = tmp_path / "b.sock"
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    proc = subprocess.Popen(
        [no_rclpy_python, "-m", "temoto.ros2.bridge", "--socket", str(path)],
        env=env,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + 30
        while not path.exists() and time.monotonic() < deadline:
            time.sleep(0.02)
        with pytest.raises(BridgeError) as caught:
            BridgeClient(str(path))
        assert proc.wait(30) == 2
        assert proc.stderr is not None
        stderr = proc.stderr.read()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        if proc.stderr is not None:
            proc.stderr.close()
    assert str(caught.value) == (
        f"the ROS 2 actions need rclpy in {no_rclpy_python}: "
        "pip install 'temoto[ros2]' (or source a ROS 2 installation)"
    )
    assert "Traceback" not in stderr
    assert not path.exists()


def test_temoto_run_knows_the_ros2_actions(tmp_path: Path) -> None:
    """``temoto run`` has the ROS 2 servers and actions: without rclpy, the extra's one line."""
    graph = tmp_path / "publish.graph.json"
    graph.write_text(json.dumps(_publish_graph()), encoding="utf-8")
    env = {k: v for k, v in os.environ.items() if k != "TEMOTO_ROS2_PYTHON"}
    done = subprocess.run(
        [sys.executable, "-m", "temoto", "run", str(graph), "--timeout", "60"],
        capture_output=True,
        text=True,
        timeout=120,
        env=env,
        check=False,
    )
    assert done.returncode != 0, done.stdout
    assert "pip install 'temoto[ros2]'" in done.stderr, done.stderr
    assert "Traceback" not in done.stderr


def test_a_ros2_program_request_runs_node_files_with_the_ros_interpreter_and_domain() -> None:
    node_file = program_request(("node.py", "--x"), python="/ros/python", domain_id=7)
    assert node_file.executable == "/ros/python"
    assert node_file.args == (str(Path("node.py").resolve()), "--x")
    assert node_file.env == (("ROS_DOMAIN_ID", "7"),)
    assert program_request(("talker",)).env == ()  # the environment's domain
    with pytest.raises(ValueError, match="domain_id"):
        program_request(("talker",), domain_id=300)
