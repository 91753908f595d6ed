"""The ROS 2 actions against a plain rclpy node in its own process, through the bridge process.

Skipped where rclpy is not installed (the ``temoto[ros2]`` extra; see docs/ros2.md). Each test
uses its own ``ROS_DOMAIN_ID`` and ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``, and checks that
no Fast DDS segment is left in /dev/shm. Process tests: a few seconds each (discovery).
"""

from __future__ import annotations

import importlib.util
import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from temoto import ActionEngine, Result
from temoto.actions.builtin import ROS2_ACTIONS
from temoto.core.registrar import Registrar
from temoto.managers.process import ProcessManager
from temoto.ros2.client import BridgeClient, BridgeError
from temoto.ros2.lifecycle import Ros2LifecycleManager
from temoto.ros2.manager import PYTHON_VARIABLE, Ros2BridgeResponse, Ros2Manager
from temoto.ros2.shm import fastdds_segments

#: The interpreter with rclpy: $TEMOTO_ROS2_PYTHON (what the bridge then runs in), else this one.
ROS_PYTHON = os.environ.get(PYTHON_VARIABLE) or sys.executable


def _has_rclpy(python: str) -> bool:
    if python == sys.executable:
        return importlib.util.find_spec("rclpy") is not None
    check = "import importlib.util, sys; sys.exit(importlib.util.find_spec('rclpy') is None)"
    try:
        return subprocess.run([python, "-c", check], timeout=60, check=False).returncode == 0
    except OSError:
        return False


pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(
        not _has_rclpy(ROS_PYTHON),
        reason="rclpy is not installed (pip install 'temoto[ros2]', or set TEMOTO_ROS2_PYTHON)",
    ),
]

PEER = Path(__file__).with_name("peer_node.py")
_DOMAINS = iter(range(100 + os.getpid() % 50 * 2, 232))


class Peer:
    """The rclpy peer process; its stdout lines are collected."""

    def __init__(self, env: dict[str, str] | None = None) -> None:
        self.proc = subprocess.Popen(
            [ROS_PYTHON, str(PEER)],
            stdout=subprocess.PIPE,
            text=True,
            env={**os.environ, **(env or {})},
        )
        self.lines: list[str] = []
        self._changed = threading.Condition()
        self._reader = threading.Thread(target=self._read, name="test-peer-reader")
        self._reader.start()
        assert self.wait_line("ready", 30), "the rclpy peer did not start"

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            with self._changed:
                self.lines.append(line.strip())
                self._changed.notify_all()

    def wait_line(self, text: str, timeout: float) -> bool:
        with self._changed:
            return self._changed.wait_for(lambda: text in self.lines, timeout)

    def stop(self) -> int:
        if self.proc.poll() is None:  # idempotent
            self.proc.send_signal(signal.SIGINT)
        code = self.proc.wait(15)
        self._reader.join(5)
        assert self.proc.stdout is not None
        self.proc.stdout.close()
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


@pytest.fixture
def peer(ros_env: int) -> Iterator[Peer]:
    p = Peer()
    try:
        yield p
    finally:
        assert p.stop() == 0


@pytest.fixture
def registrar(ros_env: int) -> Iterator[Registrar]:
    reg = Registrar("r1")
    processes = ProcessManager(reg, grace=5.0)
    manager = Ros2Manager(reg)
    Ros2LifecycleManager(reg, check_period=0.2)
    try:
        yield reg
    finally:
        for info in reg.resources():
            for ref in info.references:
                if not ref.holder:
                    reg.release(ref.id)
        processes.shutdown()
        manager.shutdown()
        reg.close()


def node(
    name: str, params: dict[str, Any], children: list[str] = (), parents: list[str] = ()
) -> dict[str, Any]:  # type: ignore[assignment]
    def pvf(v: Any) -> dict[str, Any]:
        kind = "number" if isinstance(v, (int, float)) else "string"
        return {"pvf_type": kind, "pvf_value": v}

    return {
        "name": name,
        "instance_id": 0,
        "type": "sync",
        "input_parameters": {k: pvf(v) for k, v in params.items()},
        "children": [{"name": c, "instance_id": 0} for c in children],
        "parents": [{"name": p, "instance_id": 0} for p in parents],
    }


def graph(name: str, *nodes: dict[str, Any]) -> dict[str, Any]:
    entry = [n for n in nodes if not n["parents"]]
    leaves = [n for n in nodes if not n["children"]]
    return {
        "graph_name": name,
        "graph_entry": [{"name": n["name"], "instance_id": 0} for n in entry],
        "graph_exit": [{"name": n["name"], "instance_id": 0} for n in leaves],
        "actions": list(nodes),
    }


def outputs_of(outcome: Any) -> dict[str, Any]:
    return dict(outcome.outputs)


def messages_of(snapshot: dict[str, Any]) -> list[str]:
    return [
        str(m.get("message", m)) if isinstance(m, dict) else str(m)
        for a in snapshot["actions"]
        for m in a.get("runtime", {}).get("messages", [])
    ]


def test_service_publish_and_wait_for_message(peer: Peer, registrar: Registrar) -> None:
    g = graph(
        "ros2_basics",
        node(
            "Ros2CallService",
            {"service": "/peer/trigger", "type": "std_srvs/srv/Trigger", "request": "{}"},
            children=["Ros2Publish", "Ros2WaitForMessage"],
        ),
        node(
            "Ros2Publish",
            {
                "topic": "/peer/echo_in",
                "type": "std_msgs/msg/String",
                "message": '{"data": "hello"}',
                "timeout": 10,
            },
            parents=["Ros2CallService"],
        ),
        node(
            "Ros2WaitForMessage",
            {"topic": "/peer/echo_out", "type": "std_msgs/msg/String", "timeout": 20},
            parents=["Ros2CallService"],
        ),
    )
    with ActionEngine("r1", actions=[ROS2_ACTIONS], registrar=registrar) as engine:
        outcome = engine.run(g, timeout=60)
        assert outcome.result is Result.TRUE, outcome.errors
        snapshot = engine.graph_json("ros2_basics")
    assert '/peer/trigger answered: {"success":true,"message":"triggered 1"}' in messages_of(
        snapshot
    )
    out = outputs_of(outcome)
    assert out["subscribers"] == 1
    assert json.loads(out["message"]) == {"data": "echo: hello"}
    assert peer.lines.count("called") == 1
    assert registrar.resources() == []  # the bridge was released with the run, and stopped


def test_wait_for_message_timeout_is_an_error(registrar: Registrar) -> None:
    g = graph(
        "ros2_silence",
        node(
            "Ros2WaitForMessage",
            {"topic": "/nobody", "type": "std_msgs/msg/String", "timeout": 0.5},
        ),
    )
    with ActionEngine("r1", actions=[ROS2_ACTIONS], registrar=registrar) as engine:
        outcome = engine.run(g, timeout=60)
    assert outcome.result is Result.ERROR
    assert "no std_msgs/msg/String message on /nobody within 0.5 s" in str(outcome.errors)


def test_bad_message_is_one_line_naming_the_field(registrar: Registrar) -> None:
    g = graph(
        "ros2_bad",
        node(
            "Ros2Publish",
            {"topic": "/x", "type": "std_msgs/msg/String", "message": '{"dat": 1}', "timeout": 0},
        ),
    )
    with ActionEngine("r1", actions=[ROS2_ACTIONS], registrar=registrar) as engine:
        outcome = engine.run(g, timeout=60)
    assert outcome.result is Result.ERROR
    assert "String has no field 'dat' (fields: data)" in str(outcome.errors)


def test_send_goal_feedback_and_result(peer: Peer, registrar: Registrar) -> None:
    g = graph(
        "ros2_goal",
        node(
            "Ros2SendGoal",
            {
                "action": "/peer/fibonacci",
                "type": "test_msgs/action/Fibonacci",
                "goal": '{"order": 5}',
                "timeout": 30,
            },
        ),
    )
    with ActionEngine("r1", actions=[ROS2_ACTIONS], registrar=registrar) as engine:
        outcome = engine.run(g, timeout=60)
        assert outcome.result is Result.TRUE, outcome.errors
        snapshot = engine.graph_json("ros2_goal")
    out = outputs_of(outcome)
    assert out["status"] == "SUCCEEDED"
    assert json.loads(out["result"]) == {"sequence": [0, 1, 1, 2, 3, 5]}
    assert any(
        'feedback from /peer/fibonacci: {"sequence":[0,1,1,2,3]}' in m
        for m in messages_of(snapshot)
    )


def test_stopping_the_graph_cancels_the_goal(peer: Peer, registrar: Registrar) -> None:
    g = graph(
        "ros2_long_goal",
        node(
            "Ros2SendGoal",
            {
                "action": "/peer/fibonacci",
                "type": "test_msgs/action/Fibonacci",
                "goal": '{"order": 40}',
            },
        ),
    )
    with ActionEngine("r1", actions=[ROS2_ACTIONS], registrar=registrar) as engine:
        engine.start(g)
        assert peer.wait_line("goal", 30), peer.lines
        result = engine.stop("ros2_long_goal", timeout=30)
        assert result is Result.STOPPED, engine.outcome("ros2_long_goal").errors
    assert "canceled" in peer.lines  # the cancel reached the server before the run ended
    assert "succeeded" not in peer.lines


def test_a_crashed_bridge_fails_its_consumer_and_the_next_request_starts_a_new_one(
    peer: Peer, registrar: Registrar
) -> None:
    g = graph(
        "ros2_wait",
        node(
            "Ros2WaitForMessage", {"topic": "/nobody", "type": "std_msgs/msg/String", "timeout": 60}
        ),
    )
    with ActionEngine("r1", actions=[ROS2_ACTIONS], registrar=registrar) as engine:
        engine.start(g)
        deadline = time.monotonic() + 30
        bridges: list[Ros2BridgeResponse] = []
        while not bridges and time.monotonic() < deadline:
            bridges = [r.response for r in registrar.resources() if r.server == "ros2"]
            time.sleep(0.05)
        assert bridges, "no bridge was started"
        time.sleep(0.5)  # the action is waiting on it
        os.kill(bridges[0].pid, signal.SIGKILL)
        engine.wait("ros2_wait", timeout=30)
        outcome = engine.outcome("ros2_wait")
        assert outcome.result is Result.ERROR
        assert "killed by signal SIGKILL" in str(outcome.errors), outcome.errors
        again = graph(
            "ros2_again",
            node(
                "Ros2CallService",
                {"service": "/peer/trigger", "type": "std_srvs/srv/Trigger", "timeout": 20},
            ),
        )
        outcome = engine.run(again, timeout=60)
        assert outcome.result is Result.TRUE, outcome.errors
    # The peer re-creates the dead bridge's port segment while it still sends to it (until the
    # lease runs out); stopped, it leaves that for the manager's shutdown to remove, and ros_env
    # checks that nothing is left.
    assert peer.stop() == 0


@pytest.mark.parametrize(
    ("rmw", "expected"),
    [
        ("rmw_nope", "RMW_IMPLEMENTATION=rmw_nope: librmw_nope.so cannot be loaded"),
        # a library that loads but is not an RMW this rclpy can use: import rclpy exits 102
        (
            "rmw_fastrtps_shared_cpp",
            "RMW_IMPLEMENTATION=rmw_fastrtps_shared_cpp: this rclpy cannot use it",
        ),
    ],
)
def test_a_wrong_rmw_is_one_line(
    registrar: Registrar, monkeypatch: pytest.MonkeyPatch, rmw: str, expected: str
) -> None:
    monkeypatch.setenv("RMW_IMPLEMENTATION", rmw)
    g = graph("ros2_rmw", node("Ros2Publish", {"topic": "/x", "type": "std_msgs/msg/String"}))
    with ActionEngine("r1", actions=[ROS2_ACTIONS], registrar=registrar) as engine:
        outcome = engine.run(g, timeout=60)
    assert outcome.result is Result.ERROR
    (error,) = outcome.errors
    assert str(error).startswith(f"Ros2Publish_0 failed: {expected}"), error
    assert "{" not in str(error)  # no request JSON from the registrar's wrapping


def _bridge_env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])}


def _wait_path(path: Path) -> None:
    deadline = time.monotonic() + 30
    while not path.exists() and time.monotonic() < deadline:
        time.sleep(0.02)
    assert path.exists(), "the bridge did not listen"


def _request_error(client: BridgeClient) -> str:
    try:
        client.request("wait_message", topic="/nobody", type="std_msgs/msg/String", timeout=60)
    except BridgeError as exc:
        return str(exc)
    return ""


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_the_bridge_ends_cleanly_on_a_signal_during_a_request(
    ros_env: int, tmp_path: Path, sig: signal.Signals
) -> None:
    path = tmp_path / "b.sock"
    proc = subprocess.Popen(
        [ROS_PYTHON, "-m", "temoto.ros2.bridge", "--socket", str(path)],
        env=_bridge_env(),
        stderr=subprocess.PIPE,
        text=True,
    )
    errors: list[str] = []
    try:
        _wait_path(path)
        with BridgeClient(str(path)) as client:
            waiting = threading.Thread(
                target=lambda: errors.append(_request_error(client)), name="test-waiting"
            )
            waiting.start()
            time.sleep(0.5)  # the request is in the bridge
            proc.send_signal(sig)
            assert proc.wait(30) == 0
            waiting.join(10)
        assert proc.stderr is not None
        stderr = proc.stderr.read()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        if proc.stderr is not None:
            proc.stderr.close()
    assert errors, "the waiting request hung"
    assert errors[0], "the waiting request got no error"
    assert "Traceback" not in stderr, stderr
    assert not path.exists()
    # ros_env: no segment left (the executor thread was joined, rclpy shut down)


def test_the_bridge_exits_when_the_process_that_started_it_is_gone(
    ros_env: int, tmp_path: Path
) -> None:
    path = tmp_path / "b.sock"
    starter = (
        "import subprocess, sys; "
        "import os; "
        "p = subprocess.Popen([sys.argv[1], '-m', 'temoto.ros2.bridge', '--socket', sys.argv[2], "
        "'--parent', str(os.getpid())], "
        "stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL); "
        "print(p.pid, flush=True)"
    )
    out = subprocess.run(
        [sys.executable, "-c", starter, ROS_PYTHON, str(path)],
        env=_bridge_env(),
        capture_output=True,
        text=True,
        check=True,
        timeout=30,
    )
    pid = int(out.stdout.split()[0])
    _wait_path(path)  # started, and its parent has exited by now
    deadline = time.monotonic() + 30
    while Path(f"/proc/{pid}").exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not Path(f"/proc/{pid}").exists(), "the orphaned bridge still runs"
    assert not path.exists()


def test_an_instance_serves_the_ros2_actions(peer: Peer, monkeypatch: pytest.MonkeyPatch) -> None:
    from temoto.instance import Instance
    from temoto.transport import InProcessTransport

    monkeypatch.setenv(PYTHON_VARIABLE, ROS_PYTHON)
    instance = Instance("r1", transport=InProcessTransport(f"ros2-{os.getpid()}"), key=bytes(32))
    try:
        g = graph(
            "ros2_instance",
            node(
                "Ros2CallService",
                {"service": "/peer/trigger", "type": "std_srvs/srv/Trigger", "timeout": 20},
            ),
        )
        outcome = instance.engine.run(g, timeout=60)
        assert outcome.result is Result.TRUE, outcome.errors
        assert json.loads(outcome.outputs["response"])["success"] is True
    finally:
        instance.close()
    assert instance.processes.running() == []


def test_stopping_a_call_that_waits_for_discovery(registrar: Registrar) -> None:
    g = graph(
        "ros2_undiscovered",
        node(
            "Ros2CallService", {"service": "/nobody", "type": "std_srvs/srv/Trigger", "timeout": 0}
        ),
    )
    with ActionEngine("r1", actions=[ROS2_ACTIONS], registrar=registrar, stop_timeout=10) as engine:
        engine.start(g)
        deadline = time.monotonic() + 30
        while not registrar.resources() and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.5)  # the bridge is waiting for /nobody
        assert engine.stop("ros2_undiscovered", timeout=30) is Result.STOPPED


def _holder(name: str, duration: float) -> dict[str, Any]:
    return graph(name, node("Ros2LifecycleNode", {"node": "peer_lifecycle", "duration": duration}))


def test_a_lifecycle_node_shared_by_two_graphs_goes_down_when_both_end(
    peer: Peer, registrar: Registrar
) -> None:
    with ActionEngine("r1", actions=[ROS2_ACTIONS], registrar=registrar) as engine:
        engine.start(_holder("short", 1.0))
        engine.start(_holder("long", 6.0))
        assert engine.wait("short", timeout=60) is Result.TRUE, engine.outcome("short").errors
        held = [r for r in registrar.resources() if r.server == "ros2_lifecycle"]
        assert len(held) == 1, held  # one node, shared
        assert "deactivate" not in peer.lines  # "long" still holds it
        assert engine.wait("long", timeout=60) is Result.TRUE, engine.outcome("long").errors
    lifecycle = [
        line for line in peer.lines if line in ("configure", "activate", "deactivate", "cleanup")
    ]
    assert lifecycle == ["configure", "activate", "deactivate", "cleanup"]
    assert registrar.resources() == []


def test_a_lifecycle_node_that_deactivates_itself_fails_its_holder(
    ros_env: int, registrar: Registrar
) -> None:
    peer = Peer({"PEER_SELF_DEACTIVATE_S": "1.0"})
    try:
        with ActionEngine("r1", actions=[ROS2_ACTIONS], registrar=registrar) as engine:
            engine.start(_holder("held", 60.0))
            assert engine.wait("held", timeout=60) is Result.ERROR
            errors = str(engine.outcome("held").errors)
        assert "lifecycle node /peer_lifecycle left ACTIVE on its own (now inactive)" in errors
        assert registrar.resources() == []
        # released after the failure: cleaned up (deactivate was the node's own)
        assert peer.wait_line("cleanup", 10), peer.lines
    finally:
        assert peer.stop() == 0


def test_the_example_graph_runs_against_the_example_peer(ros_env: int) -> None:
    examples = Path(__file__).resolve().parents[2] / "examples" / "ros2"
    env = {**_bridge_env(), PYTHON_VARIABLE: ROS_PYTHON}
    peer = subprocess.Popen(
        [ROS_PYTHON, str(examples / "peer.py")], stdout=subprocess.PIPE, text=True, env=env
    )
    try:
        assert peer.stdout is not None
        assert peer.stdout.readline().strip() == "peer ready"
        run = subprocess.run(
            [sys.executable, str(examples / "run.py")],
            env=env,
            capture_output=True,
            text=True,
            timeout=120,
            check=False,
        )
        assert run.returncode == 0, run.stdout + run.stderr
        assert run.stdout == 'ros2_tour: goal SUCCEEDED: {"sequence":[0,1,1,2,3,5,8]}\n'
    finally:
        peer.send_signal(signal.SIGINT)
        assert peer.wait(15) == 0
        if peer.stdout is not None:
            peer.stdout.close()


def test_a_lifecycle_node_whose_program_is_started_first(registrar: Registrar) -> None:
    g = graph(
        "ros2_program",
        node(
            "Ros2LifecycleNode",
            {"node": "peer_lifecycle", "program": str(PEER), "timeout": 30, "duration": 0.5},
        ),
    )
    with ActionEngine("r1", actions=[ROS2_ACTIONS], registrar=registrar) as engine:
        outcome = engine.run(g, timeout=90)
    assert outcome.result is Result.TRUE, outcome.errors
    assert outcome.outputs["state"] == 1  # found unconfigured: it was just started
    assert registrar.resources() == []  # the program was stopped with the node


def test_a_ros2_node_program_started_by_the_process_manager(registrar: Registrar) -> None:
    # The node file is started by Ros2Node in a domain of its own (not the environment's):
    # only if it got the ROS environment and that ROS_DOMAIN_ID does the call reach it.
    domain = next(_DOMAINS)
    g = graph(
        "ros2_node",
        node("Ros2Node", {"program": str(PEER), "domain_id": domain}, children=["Ros2CallService"]),
        node(
            "Ros2CallService",
            {
                "service": "/peer/trigger",
                "type": "std_srvs/srv/Trigger",
                "timeout": 30,
                "domain_id": domain,
            },
            parents=["Ros2Node"],
        ),
    )
    g["graph_exit"].append({"name": "Ros2Node", "instance_id": 0})  # for its output pid
    with ActionEngine("r1", actions=[ROS2_ACTIONS], registrar=registrar) as engine:
        outcome = engine.run(g, timeout=90)
    assert outcome.result is Result.TRUE, outcome.errors
    assert json.loads(outcome.outputs["response"])["message"] == "triggered 1"
    pid = int(outcome.outputs["pid"])
    assert registrar.resources() == []  # released with the run: the process was stopped
    assert not Path(f"/proc/{pid}").exists()


def test_ctrl_c_of_the_example_and_its_peer(ros_env: int) -> None:
    examples = Path(__file__).resolve().parents[2] / "examples" / "ros2"
    env = {**_bridge_env(), PYTHON_VARIABLE: ROS_PYTHON}
    peer = subprocess.Popen(
        [ROS_PYTHON, str(examples / "peer.py")],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    run = subprocess.Popen(
        [sys.executable, str(examples / "run.py"), "--order", "45"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    try:
        assert peer.stdout is not None
        assert peer.stdout.readline().strip() == "peer ready"
        assert peer.stderr is not None
        deadline = time.monotonic() + 60
        seen = ""
        while "activated" not in seen and time.monotonic() < deadline:
            seen += peer.stderr.readline()  # the gripper's log: held, the goal comes next
        assert "activated" in seen, seen
        time.sleep(1.0)  # the goal runs
        run.send_signal(signal.SIGINT)  # Ctrl-C: to the run, then to the peer
        out, err = run.communicate(timeout=60)
        peer.send_signal(signal.SIGINT)
        peer_err = peer.communicate(timeout=30)[1]
    finally:
        for proc in (run, peer):
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
    assert run.returncode == 130, out + err
    assert out == "ros2_tour: interrupted (on_stopped)\n"
    assert peer.returncode == 0
    assert "Traceback" not in err + peer_err, err + peer_err
    assert "count cancelled" in peer_err  # the goal was cancelled
    assert "deactivated" in peer_err  # the lifecycle node was brought down on the way out
    # ros_env: no /dev/shm segment left; the leak check: no process left (the bridge included)
