"""Visualization benchmarks: the live Foxglove server's cost per message, a display's latency.

``viz_publish_us``: :meth:`FoxgloveServer.publish` of one ``temoto.JointStates`` message (six
joints) on a channel one client is subscribed to, per message, on the publishing thread (JSON
encoding, the last-value copy, the SDK's log); the client (:mod:`temoto.testing.foxglove_client`,
on ``websockets``, not the SDK) runs in another process and reads every frame meanwhile; the
number it got is noted (the SDK drops the oldest of a slow client's backlog, 1024 messages).

``viz_display_first_ms``: a display of the simulated arm's joints (the robot already loaded by
another consumer) from ``registrar.call`` to its first message at a connected client: the
client sees the advertise, subscribes, and gets the last message again or the next sample
(10 Hz). Median and p90 of repeated load/release cycles.

Run ``python -m bench.visualization`` for the group alone. Needs ``foxglove-sdk`` and
``websockets`` (the ``dev`` extra); without them the group is skipped with a note.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from bench.common import Results, median, now, percentile

ROOT = Path(__file__).resolve().parent.parent


def _joints(i: int) -> dict[str, Any]:
    return {
        "name": ["j1", "j2", "j3", "j4", "j5", "j6"],
        "position": [0.001 * i, 0.1, 0.2, 0.3, 0.4, 0.5],
        "velocity": [],
        "effort": [],
        "timestamp": {"sec": i, "nsec": 0},
    }


def _client_main(url: str, topic: str) -> None:
    """The client process: subscribe, say "ready", count messages until 1 s of silence."""
    import sys

    from temoto.testing.foxglove_client import FoxgloveClient

    with FoxgloveClient(url) as client:
        client.wait(lambda c: topic in c.topics())
        sub = client.subscribe(topic)
        client.first_message(sub)
        sys.stdout.write("ready\n")
        sys.stdout.flush()
        while True:
            try:
                client.read_one(1.0)
            except TimeoutError:
                break
        sys.stdout.write(f"{sum(1 for m in client.messages if m.subscription == sub) - 1}\n")


def _publish_cost(results: Results, count: int) -> None:
    import subprocess
    import sys

    from temoto.managers.visualization.foxglove import FoxgloveServer

    topic = "/bench/joints"
    with FoxgloveServer(port=0) as server:
        server.publish(topic, "temoto.JointStates", _joints(0))
        child = subprocess.Popen(
            [sys.executable, "-m", "bench.visualization", "--client", server.url, topic],
            stdout=subprocess.PIPE,
            text=True,
            cwd=ROOT,
        )
        try:
            assert child.stdout is not None
            if child.stdout.readline().strip() != "ready":
                raise RuntimeError("the bench's Foxglove client did not subscribe")
            messages = [_joints(i) for i in range(count)]
            t0 = now()
            for message in messages:
                server.publish(topic, "temoto.JointStates", message)
            per_us = (now() - t0) / count * 1e6
            got = child.stdout.readline().strip()
            child.wait(30)
        finally:
            if child.poll() is None:
                child.kill()
                child.wait()
            if child.stdout is not None:
                child.stdout.close()
    results.add(
        "viz_publish_us",
        per_us,
        "us",
        f"{count} messages, one subscribed client in another process (got {got}); JSON, 6 joints",
    )


def _display_latency(results: Results, cycles: int) -> None:
    from temoto.config import load_profile
    from temoto.core.registrar import Registrar
    from temoto.managers.robot import RobotManager, RobotManagerClient
    from temoto.managers.visualization import DisplayRequest, VisualizationManager
    from temoto.managers.visualization.foxglove import FoxgloveServer
    from temoto.testing.foxglove_client import FoxgloveClient

    registrar = Registrar("bench-viz")
    robots = RobotManager(registrar, load_profile(ROOT / "hw_profiles" / "sim_arm.yaml"))
    server = FoxgloveServer(port=0)
    manager = VisualizationManager(registrar, server)
    samples: list[float] = []
    try:
        robot = RobotManagerClient(registrar).request(client="bench")
        with FoxgloveClient(server.url) as client:
            client.wait(lambda c: bool(c.server_info))
            topic = DisplayRequest("robot", "joints").topic
            for _ in range(cycles):
                client.messages.clear()
                t0 = time.monotonic()
                ref = registrar.call("display", DisplayRequest("robot", "joints"), client="op")
                client.wait(lambda c: topic in c.topics())
                first = client.first_message(client.subscribe(topic))
                samples.append((first.at - t0) * 1e3)
                registrar.release(ref.id)
                client.wait(lambda c: topic not in c.topics())
        registrar.release(robot.resource.id)
    finally:
        for ref in registrar.references():
            registrar.release(ref.id)
        manager.shutdown()
        server.close()
        robots.shutdown()
        registrar.close()
    note = f"{cycles} load/release cycles, sim_arm joints at 10 Hz, robot already loaded"
    results.add("viz_display_first_ms", median(samples), "ms", note)
    results.add("viz_display_first_p90_ms", percentile(samples, 90), "ms", note)


def bench_visualization(quick: bool) -> Results:
    """The group: per-message cost with one client, display load -> first message."""
    results = Results()
    try:
        import foxglove  # noqa: F401
        import websockets  # noqa: F401
    except ImportError as err:
        results.notes.append(f"visualization skipped: {err} (pip install 'temoto[dev]')")
        return results
    _publish_cost(results, 2_000 if quick else 50_000)
    _display_latency(results, 5 if quick else 50)
    return results


if __name__ == "__main__":
    import sys

    if sys.argv[1:2] == ["--client"]:
        _client_main(sys.argv[2], sys.argv[3])
        raise SystemExit(0)
    for m in bench_visualization(quick=True).metrics:
        print(f"{m.name:28s} {m.value:10.3f} {m.unit}  {m.note}")
