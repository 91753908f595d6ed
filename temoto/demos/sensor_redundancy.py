"""Demonstration 1, fault-tolerant sensor redundancy (thesis §8).

A robot has three range sensors — a 3D lidar, a depth camera and a 2D lidar (simulated sensor
processes, ``data/sensors.yaml``), in the operator's priority order. The operator's display
asks the Component Manager for a ``range_sensor``: only the best one is started, and its
readings reach the display's channel. The active sensor's process is killed; the manager
starts the next one on the same channel, and the display keeps receiving. Killed again, the
third one takes over.

It reports the switch-over times (kill → the substitute's first reading at the display) and,
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
from typing import Final

from temoto.core.registrar import Registrar, StatusUpdate
from temoto.demos._display import Display
from temoto.demos._timeline import DemoReport, Timeline
from temoto.managers import ProcessManager
from temoto.managers.component import ChannelReader, ComponentManager, ComponentManagerClient

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


def run(timeline: Timeline, *, speed: float = 1.0) -> DemoReport:
    """Run the demonstration (real processes: ``speed`` does not apply).

    Args:
        timeline: Where events are printed.
        speed: Ignored (the sensors are real processes on the real clock).

    Returns:
        The report (facts: the sensors in the order they fed the display, switch-over times,
        sensor processes running at most and on average against three).
    """
    report = DemoReport()
    registrar = Registrar(f"demo1-{secrets.token_hex(3)}")
    processes = ProcessManager(registrar)
    components = ComponentManager(registrar, files=[SENSORS])
    client = ComponentManagerClient(registrar)
    reader = ChannelReader(f"unix:@temoto-demo1-display-{secrets.token_hex(4)}")
    display = Display(reader, timeline, "receiving from")
    counter = _ProcessCounter(registrar)
    ranking = [c.description.name for c in components.candidates("range_sensor")]
    timeline.say("component manager", f"range_sensor candidates, best first: {ranking}")

    def on_status(update: StatusUpdate) -> None:
        timeline.say("display", f"told: {update.status.value} {update.message}")

    try:
        sensor = client.request(
            "range_sensor", outputs={"scan": reader.channel}, client="display", on_status=on_status
        )
        timeline.say("display", f"asked for a range_sensor; got {sensor.name}")
        display.wait_for(ORDER[0], WAIT)
        switch_ms: list[float] = []
        for previous, nxt in itertools.pairwise(ORDER):
            time.sleep(0.3)  # let the display show the active sensor for a moment
            pid = sensor.response.pid
            timeline.say("operator", f"{previous} fails (process {pid} killed)")
            t_kill = time.monotonic()
            os.kill(pid, signal.SIGKILL)
            t_first = display.wait_for(nxt, WAIT)
            switch_ms.append(round((t_first - t_kill) * 1000, 1))
            timeline.say("display", f"switched to {nxt} in {switch_ms[-1]:.1f} ms")
        time.sleep(0.3)
        report.facts["fed_the_display"] = display.order()
        report.facts["switch_over_ms"] = switch_ms
        report.facts["readings"] = dict(display.count)
        client.release(sensor)
        timeline.say("display", "released the sensor")
    finally:
        counter.close()
        display.close()
        reader.close()
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
