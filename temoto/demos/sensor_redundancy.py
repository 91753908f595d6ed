"""Demonstration 1, fault-tolerant sensor redundancy (thesis §8).

A robot has three range sensors — a 3D lidar, a depth camera and a 2D lidar (simulated sensor
processes, ``data/sensors.yaml``), in the operator's priority order. As in the thesis, the
operator's display is a Visualization Manager display (``docs/visualization.md``) of the active
sensor: only that sensor is started (a dependency of its display), and its readings reach the
display. The active sensor's process is killed; its display fails with it (a FATAL status)
and is released, and the next sensor's display is loaded, which starts that sensor. Killed
again, the third one takes over. With a live Foxglove server (``temoto demo 1 --foxglove``),
each display is a topic ``/display/<sensor>/data``: unadvertised when it fails, the next
one's advertised.

It reports the switch-over times (kill → the next sensor's first reading at its display) and,
for the energy argument, how many sensor processes ran over time against starting all three.
"""

from __future__ import annotations

import itertools
import os
import secrets
import signal
import threading
import time
from pathlib import Path
from typing import Any, Final

from temoto.core.registrar import Registrar, Resource, Status, StatusUpdate
from temoto.demos._timeline import DemoReport, Timeline
from temoto.managers import ProcessManager
from temoto.managers.component import ComponentManager
from temoto.managers.visualization import DisplayRequest, VisualizationManager

__all__ = ["run"]

SENSORS: Final = Path(__file__).resolve().parent / "data" / "sensors.yaml"
ORDER: Final = ("lidar_3d", "depth_camera", "lidar_2d")
WAIT: Final = 10.0  # real seconds any step may take
SAMPLE_S: Final = 0.02  # how often the running sensor processes are counted


class _ProcessCounter:
    """Counts the running sensor processes every ``SAMPLE_S`` (the energy argument).

    Running: a ``process`` resource not reported FATAL.
    """

    def __init__(self, registrar: Registrar) -> None:
        self.registrar = registrar
        self.samples: list[int] = []
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._count, name="demo1-counter", daemon=True)
        self.thread.start()

    def _count(self) -> None:
        while not self._stop.wait(SAMPLE_S):
            # a killed sensor's resource stays until the substitute runs (make before break):
            # it is failed, not running
            resources = self.registrar.resources()
            self.samples.append(sum(1 for r in resources if r.server == "process" and not r.failed))

    def close(self) -> None:
        self._stop.set()
        self.thread.join(5.0)


def run(
    timeline: Timeline, *, speed: float = 1.0, foxglove: tuple[str, int] | None = None
) -> DemoReport:
    """Run the demonstration (real processes: ``speed`` does not apply).

    Args:
        timeline: Where events are printed.
        speed: Ignored (the sensors are real processes on the real clock).
        foxglove: Serve the displays live to Foxglove on this (host, port), or None.

    Returns:
        The report (facts: the sensors in the order they fed the display, switch-over times,
        sensor processes running at most and on average against three).

    Raises:
        ConfigError: ``foxglove`` is given but the SDK is missing or the port is taken.
    """
    server = None
    if foxglove is not None:
        from temoto.managers.visualization.foxglove import FoxgloveServer

        server = FoxgloveServer(*foxglove, name="temoto demo 1")
        timeline.say("foxglove", f"serving the displays on {server.url}")
    try:
        return _run(timeline, server)
    finally:
        if server is not None:
            server.close()


def _run(timeline: Timeline, server: Any) -> DemoReport:
    report = DemoReport()
    registrar = Registrar(f"demo1-{secrets.token_hex(3)}")
    processes = ProcessManager(registrar)
    components = ComponentManager(registrar, files=[SENSORS])
    displays = VisualizationManager(registrar, server)
    counter = _ProcessCounter(registrar)
    ranking = [c.description.name for c in components.candidates("range_sensor")]
    timeline.say("component manager", f"range_sensor candidates, best first: {ranking}")
    failed = threading.Event()

    def on_status(update: StatusUpdate) -> None:
        timeline.say("display", f"told: {update.status.value} {update.message}")
        if update.status is Status.FATAL:
            failed.set()

    def show(sensor: str) -> tuple[Resource[Any], float]:
        # one display per sensor (named after it), holding that sensor without failover
        request = DisplayRequest("component", target="range_sensor", candidate=sensor, name=sensor)
        ref = registrar.call("display", request, client="operator", on_status=on_status)
        timeline.say("display", f"showing {sensor} ({ref.response.topics[0]})")
        t_first = displays.displays()[request.name].wait_for_message(WAIT)
        timeline.say("display", f"receiving from {sensor}")
        return ref, t_first

    fed: list[str] = []
    readings: dict[str, int] = {}
    try:
        ref, _ = show(ranking[0])
        fed.append(ranking[0])
        switch_ms: list[float] = []
        for previous, nxt in itertools.pairwise(ranking):
            time.sleep(0.3)  # let the display show the active sensor for a moment
            (sensor,) = registrar.dependencies(ref.resource_id)
            pid = sensor.response.pid
            timeline.say("operator", f"{previous} fails (process {pid} killed)")
            failed.clear()
            t_kill = time.monotonic()
            os.kill(pid, signal.SIGKILL)
            if not failed.wait(WAIT):
                raise TimeoutError(f"{previous}'s failure did not reach its display")
            readings[previous] = displays.displays()[previous].count
            registrar.release(ref.id)
            timeline.say("display", f"released {previous}")
            ref, t_first = show(nxt)
            fed.append(nxt)
            switch_ms.append(round((t_first - t_kill) * 1000, 1))
            timeline.say("display", f"switched to {nxt} in {switch_ms[-1]:.1f} ms")
        time.sleep(0.3)
        readings[ranking[-1]] = displays.displays()[ranking[-1]].count
        report.facts["fed_the_display"] = fed
        report.facts["switch_over_ms"] = switch_ms
        report.facts["readings"] = readings
        registrar.release(ref.id)
        timeline.say("display", "released the sensor")
    finally:
        counter.close()
        for left in registrar.references():
            registrar.release(left.id)
        displays.shutdown()
        components.shutdown()
        processes.shutdown(stop_processes=True)  # nothing it started outlives it
        registrar.close()
    samples = counter.samples or [0]
    report.facts["sensor_processes_max"] = max(samples)
    report.facts["sensor_processes_mean"] = round(sum(samples) / len(samples), 2)
    report.facts["if_all_started"] = len(ORDER)
    report.ok = (
        report.facts["fed_the_display"] == list(ORDER)
        and report.facts["sensor_processes_max"] == 1
        and all(ms < 1000 for ms in report.facts["switch_over_ms"])
    )
    return report
