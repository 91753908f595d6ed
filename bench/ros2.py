"""ROS 2: a service call through the bridge and from an action, against rclpy's own round trip.

Needs an interpreter with rclpy: ``$TEMOTO_ROS2_PYTHON`` (``make test-ros2`` makes one in
``.venv-ros2``) or this one; without, the group is skipped with a note. Three processes on
loopback, ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``, a domain of their own
(``$ROS_DOMAIN_ID`` if set, else one from the pid): an rclpy peer serving
``std_srvs/srv/Trigger``; an rclpy client timing its own calls to it (single-threaded executor:
the peer's own figure); and TeMoto, timing the same call through the bridge (``call_service`` on
a :class:`~temoto.ros2.client.BridgeClient`) and as a one-action graph (``Ros2CallService``, the
bridge held across runs as a graph run's actions hold it).

And a published message's latency: an rclpy subscriber records, for each
``geometry_msgs/msg/Point`` it receives, ``time.monotonic()`` (``CLOCK_MONOTONIC``, one clock for
every process of the machine) minus the stamp the sender put in ``y`` just before sending
(``x``: the sequence number, -1 for warm-up). Senders: a plain rclpy publisher (the peer's own
figure), TeMoto's ``publish`` through the bridge, and a one-action ``Ros2Publish`` graph run (the
stamp taken just before ``engine.run``). One message every 2 ms, so no message queues behind
another.
"""

from __future__ import annotations

import importlib.util
import json
import os
import queue
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from bench.common import Results, median, now, percentile

_PEER = """
import signal, sys, threading, rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.signals import SignalHandlerOptions
from std_srvs.srv import Trigger
rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
stop = threading.Event()
signal.signal(signal.SIGTERM, lambda *_: stop.set())
node = rclpy.create_node("bench_peer")
def cb(req, resp):
    resp.success = True
    return resp
node.create_service(Trigger, "/bench/trigger", cb)
ex = SingleThreadedExecutor(); ex.add_node(node)
print("ready", flush=True)
while not stop.is_set():
    ex.spin_once(timeout_sec=0.1)
node.destroy_node(); rclpy.try_shutdown()
"""

_CLIENT = """
import json, sys, time, rclpy
from rclpy.executors import SingleThreadedExecutor
from std_srvs.srv import Trigger
n = int(sys.argv[1])
rclpy.init()
node = rclpy.create_node("bench_client")
cli = node.create_client(Trigger, "/bench/trigger")
assert cli.wait_for_service(timeout_sec=30)
ex = SingleThreadedExecutor(); ex.add_node(node)
out = []
for i in range(n + 20):
    t = time.perf_counter()
    fut = cli.call_async(Trigger.Request())
    while not fut.done():
        ex.spin_once(timeout_sec=10)
    if i >= 20:
        out.append((time.perf_counter() - t) * 1e3)
print(json.dumps(out))
node.destroy_node(); rclpy.try_shutdown()
"""


_SUBSCRIBER = """
import json, signal, sys, threading, time, rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.signals import SignalHandlerOptions
from geometry_msgs.msg import Point
rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
stop = threading.Event()
signal.signal(signal.SIGTERM, lambda *_: stop.set())
node = rclpy.create_node("bench_subscriber")
got = {}
def on(topic):
    def cb(msg):
        t = time.monotonic()
        if msg.x < 0:
            if topic not in got:
                got[topic] = []
                print("warm " + topic, flush=True)
        else:
            got.setdefault(topic, []).append((t - msg.y) * 1e3)
    return cb
for topic in sys.argv[1:]:
    node.create_subscription(Point, "/bench/" + topic, on(topic), 10)
ex = SingleThreadedExecutor(); ex.add_node(node)
print("ready", flush=True)
while not stop.is_set():
    ex.spin_once(timeout_sec=0.1)
print(json.dumps(got), flush=True)
node.destroy_node(); rclpy.try_shutdown()
"""

_PUBLISHER = """
import sys, time, rclpy
from rclpy.executors import SingleThreadedExecutor
from geometry_msgs.msg import Point
n = int(sys.argv[1])
rclpy.init()
node = rclpy.create_node("bench_publisher")
pub = node.create_publisher(Point, "/bench/rclpy", 10)
deadline = time.monotonic() + 30
while pub.get_subscription_count() == 0 and time.monotonic() < deadline:
    time.sleep(0.01)
for i in range(-20, n):
    time.sleep(0.002)
    pub.publish(Point(x=float(max(i, -1)), y=time.monotonic()))
time.sleep(0.5)
node.destroy_node(); rclpy.try_shutdown()
"""

_LATENCY_TOPICS = ("rclpy", "bridge", "action")


def _publish_graph(seq: int) -> dict[str, Any]:
    """A one-action graph publishing one stamped Point on ``/bench/action``."""
    message = json.dumps({"x": float(seq), "y": time.monotonic()})
    params = {
        "topic": "/bench/action",
        "type": "geometry_msgs/msg/Point",
        "message": message,
    }
    return {
        "graph_name": "bench_ros2_publish",
        "graph_entry": [{"name": "Ros2Publish", "instance_id": 0}],
        "graph_exit": [{"name": "Ros2Publish", "instance_id": 0}],
        "actions": [
            {
                "name": "Ros2Publish",
                "instance_id": 0,
                "type": "sync",
                "input_parameters": {
                    k: {"pvf_type": "string", "pvf_value": v} for k, v in params.items()
                },
            }
        ],
    }


def _latencies(
    python: str, env: dict[str, str], tmp: str, socket: str, registrar: Any, n: int, n_runs: int
) -> dict[str, list[float]]:
    """Milliseconds from stamp to receipt, per sender (``_LATENCY_TOPICS``)."""
    from temoto import ActionEngine, Result
    from temoto.actions.builtin import ROS2_ACTIONS
    from temoto.ros2.client import BridgeClient

    sub_py, pub_py = Path(tmp, "subscriber.py"), Path(tmp, "publisher.py")
    sub_py.write_text(_SUBSCRIBER)
    pub_py.write_text(_PUBLISHER)
    sub = subprocess.Popen(
        [python, str(sub_py), *_LATENCY_TOPICS], stdout=subprocess.PIPE, text=True, env=env
    )
    lines: queue.Queue[str] = queue.Queue()

    def read() -> None:
        assert sub.stdout is not None
        for line in sub.stdout:
            lines.put(line.strip())

    reader = threading.Thread(target=read, name="temoto-bench-ros2-subscriber", daemon=True)
    reader.start()

    def warm(topic: str, send: Any) -> None:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            send()
            try:
                if lines.get(timeout=0.05) == f"warm {topic}":
                    return
            except queue.Empty:
                pass
        raise RuntimeError(f"the rclpy subscriber never got /bench/{topic}")

    try:
        if lines.get(timeout=60) != "ready":
            raise RuntimeError("the rclpy subscriber did not start")
        subprocess.run([python, str(pub_py), str(n)], env=env, timeout=300, check=True)
        point: dict[str, Any] = {
            "topic": "/bench/bridge",
            "type": "geometry_msgs/msg/Point",
            "timeout": 5,
        }
        with BridgeClient(socket) as client:
            warm("bridge", lambda: client.request("publish", message={"x": -1.0}, **point))
            for i in range(n):
                time.sleep(0.002)
                client.request("publish", message={"x": float(i), "y": time.monotonic()}, **point)
        with ActionEngine("r1", actions=[ROS2_ACTIONS], registrar=registrar) as engine:

            def run(seq: int) -> None:
                outcome = engine.run(_publish_graph(seq), timeout=60)
                if outcome.result is not Result.TRUE:
                    raise RuntimeError(f"Ros2Publish failed: {outcome.errors}")

            warm("action", lambda: run(-1))
            for i in range(n_runs):
                time.sleep(0.002)
                run(i)
        time.sleep(0.5)
    finally:
        sub.terminate()
        sub.wait(30)
        reader.join(10)
        if sub.stdout is not None:
            sub.stdout.close()
    got: dict[str, list[float]] = {}
    while not lines.empty():
        line = lines.get()
        if line.startswith("{"):
            got = json.loads(line)
    for topic, count in zip(_LATENCY_TOPICS, (n, n, n_runs), strict=True):
        if len(got.get(topic, [])) != count:
            raise RuntimeError(f"/bench/{topic}: {len(got.get(topic, []))} of {count} received")
    return got


def _ros_python() -> str | None:
    python = os.environ.get("TEMOTO_ROS2_PYTHON") or sys.executable
    if python == sys.executable:
        return python if importlib.util.find_spec("rclpy") else None
    return python if Path(python).exists() else None


def bench_ros2(quick: bool) -> Results:
    """Service round trips and publish latencies: rclpy's own, the bridge's, an action's."""
    out = Results()
    python = _ros_python()
    if python is None:
        out.notes.append("ros2: skipped: no rclpy (set TEMOTO_ROS2_PYTHON; docs/ros2.md)")
        return out
    from temoto import ActionEngine, Result
    from temoto.actions.builtin import ROS2_ACTIONS
    from temoto.core.registrar import Registrar
    from temoto.managers.process import ProcessManager
    from temoto.ros2.client import BridgeClient
    from temoto.ros2.manager import Ros2BridgeRequest, Ros2Manager

    n_calls = 200 if quick else 1000
    n_runs = 20 if quick else 100
    env = dict(os.environ)
    # The caller's ROS_DOMAIN_ID if set (parallel runs on one machine each pass their own: two
    # runs in one domain would share /bench/trigger's servers), else one from the pid.
    domain = os.environ.get("ROS_DOMAIN_ID") or str(150 + os.getpid() % 50)
    env.update(ROS_DOMAIN_ID=domain, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    saved = {k: os.environ.get(k) for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE")}
    os.environ.update({k: env[k] for k in saved})
    with tempfile.TemporaryDirectory() as tmp:
        peer_py, client_py = Path(tmp, "peer.py"), Path(tmp, "client.py")
        peer_py.write_text(_PEER)
        client_py.write_text(_CLIENT)
        peer = subprocess.Popen([python, str(peer_py)], stdout=subprocess.PIPE, text=True, env=env)
        registrar = Registrar("bench-ros2")
        processes = ProcessManager(registrar)
        manager = Ros2Manager(registrar, python=python)
        try:
            if peer.stdout is None or peer.stdout.readline().strip() != "ready":
                raise RuntimeError("the rclpy peer did not start")
            mine = subprocess.run(
                [python, str(client_py), str(n_calls)],
                env=env,
                capture_output=True,
                text=True,
                timeout=300,
                check=True,
            )
            rclpy_ms = json.loads(mine.stdout.strip().splitlines()[-1])
            bridge = registrar.call("ros2", Ros2BridgeRequest(), client="bench")
            with BridgeClient(bridge.response.socket) as client:
                fields: dict[str, Any] = {
                    "service": "/bench/trigger",
                    "type": "std_srvs/srv/Trigger",
                    "timeout": 30,
                }
                for _ in range(20):
                    client.request("call_service", **fields)
                bridge_ms = []
                for _ in range(n_calls):
                    t = now()
                    client.request("call_service", **fields)
                    bridge_ms.append((now() - t) * 1e3)
            graph = {
                "graph_name": "bench_ros2_call",
                "graph_entry": [{"name": "Ros2CallService", "instance_id": 0}],
                "graph_exit": [{"name": "Ros2CallService", "instance_id": 0}],
                "actions": [
                    {
                        "name": "Ros2CallService",
                        "instance_id": 0,
                        "type": "sync",
                        "input_parameters": {
                            "service": {"pvf_type": "string", "pvf_value": "/bench/trigger"},
                            "type": {"pvf_type": "string", "pvf_value": "std_srvs/srv/Trigger"},
                        },
                    }
                ],
            }
            action_ms = []
            with ActionEngine("r1", actions=[ROS2_ACTIONS], registrar=registrar) as engine:
                for i in range(n_runs + 3):
                    t = now()
                    outcome = engine.run(graph, timeout=60)
                    if outcome.result is not Result.TRUE:
                        raise RuntimeError(f"Ros2CallService failed: {outcome.errors}")
                    if i >= 3:
                        action_ms.append((now() - t) * 1e3)
            latency = _latencies(
                python, env, tmp, bridge.response.socket, registrar, n_calls, n_runs
            )
            registrar.release(bridge.id)
        finally:
            processes.shutdown()
            manager.shutdown()
            registrar.close()
            peer.terminate()
            peer.wait(30)
            if peer.stdout is not None:
                peer.stdout.close()
            for k, v in saved.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v
    r, b, a = median(rclpy_ms), median(bridge_ms), median(action_ms)
    out.add("ros2_rclpy_service_rtt_median", r, "ms", f"rclpy client, {n_calls} Trigger calls")
    out.add("ros2_rclpy_service_rtt_p99", percentile(rclpy_ms, 99), "ms")
    out.add("ros2_bridge_service_rtt_median", b, "ms", "BridgeClient call_service, same peer")
    out.add("ros2_bridge_service_rtt_p99", percentile(bridge_ms, 99), "ms")
    out.add("ros2_action_service_run_median", a, "ms", f"one-action graph run, {n_runs} runs")
    out.add("ros2_bridge_over_rclpy", b / r, "ratio")
    out.add("ros2_action_over_rclpy", a / r, "ratio")
    notes = {
        "rclpy": f"rclpy publisher -> rclpy subscriber, {n_calls} Points, stamp to receipt",
        "bridge": "BridgeClient publish -> the same subscriber",
        "action": f"one-action Ros2Publish graph run -> the same subscriber, {n_runs} runs",
    }
    for topic in _LATENCY_TOPICS:
        ms = latency[topic]
        out.add(f"ros2_{topic}_publish_latency_median", median(ms), "ms", notes[topic])
        out.add(f"ros2_{topic}_publish_latency_p99", percentile(ms, 99), "ms")
    base = median(latency["rclpy"])
    out.add("ros2_bridge_publish_over_rclpy", median(latency["bridge"]) / base, "ratio")
    out.add("ros2_action_publish_over_rclpy", median(latency["action"]) / base, "ratio")
    return out
