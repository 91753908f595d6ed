"""Component Manager benchmark: failover time (thesis demo 1, sensor redundancy).

A consumer listens on a channel; the Component Manager runs the best of two simulated range
sensors (``examples/components/sim_sensor.py`` started with ``python -S -I``, 200 readings/s)
publishing there. Once the first reading of the primary arrived, it is killed with SIGKILL (the
time taken just before ``os.kill``); ``failover_ms`` is the time until the consumer receives the
first reading of the substitute: crash detection (pidfd) + FATAL + rating + starting the
substitute process (spawn and interpreter start dominate) + its first datagram. Each kill uses a
fresh request (released afterwards), so every measurement is primary -> substitute. The
registrar journals to a catalog in a temporary directory, as a robot's would.
"""

from __future__ import annotations

import logging
import os
import shutil
import signal
import sys
import tempfile
from pathlib import Path

from bench.common import Results, median, now, percentile
from temoto.core.registrar import Registrar
from temoto.managers.component import (
    ChannelReader,
    ComponentDescription,
    ComponentManager,
    ComponentManagerClient,
)
from temoto.managers.process import ProcessManager
from temoto.testing import ProcessLeakCheck

REPO = Path(__file__).resolve().parent.parent
SENSOR = str(REPO / "examples" / "components" / "sim_sensor.py")
WAIT = 10.0
GOAL_FAILOVER_MS = ("<=", 150.0)


def _sensor(name: str, priority: int) -> ComponentDescription:
    return ComponentDescription(
        name,
        "bench_range",
        sys.executable,
        ("-S", "-I", SENSOR, "--output", "{output:scan}", "--name", "{name}", "--rate", "200"),
        outputs=("scan",),
        priority=priority,
    )


def failover_series(kills: int) -> list[float]:
    """Milliseconds from SIGKILL of the primary to the substitute's first reading, per kill."""
    tmp = tempfile.mkdtemp(prefix="temoto-bench-component-")
    registrar = Registrar("bench", catalog=Path(tmp) / "catalog.journal")
    processes = ProcessManager(registrar, grace=1.0)
    manager = ComponentManager(registrar, channel_prefix=f"bench-{os.getpid()}")
    manager.add([_sensor("primary", 2), _sensor("substitute", 1)])
    client = ComponentManagerClient(registrar)
    times: list[float] = []
    try:
        with ChannelReader(f"unix:@bench-{os.getpid()}-consumer") as reader:
            for _ in range(kills):
                handle = client.request("bench_range", outputs={"scan": reader.channel})
                try:
                    if reader.recv_until(lambda d: d.startswith(b"primary "), WAIT) is None:
                        raise RuntimeError("the primary sensor sent nothing")
                    start = now()
                    os.kill(handle.response.pid, signal.SIGKILL)
                    got = reader.recv_until(lambda d: d.startswith(b"substitute "), WAIT)
                    end = now()
                    if got is None:
                        raise RuntimeError("the substitute sent nothing")
                    times.append((end - start) * 1000.0)
                finally:
                    client.release(handle)
                reader.drain()
    finally:
        manager.shutdown()
        processes.shutdown()
        registrar.close()
        shutil.rmtree(tmp, ignore_errors=True)
    return times


def bench_component(quick: bool) -> Results:
    out = Results()
    leak = ProcessLeakCheck()
    os.environ[leak.variable] = leak.mark
    kills = 15 if quick else 50
    quiet = logging.getLogger("temoto.managers")  # one WARNING per kill is expected here
    level = quiet.level
    quiet.setLevel(logging.ERROR)
    try:
        times = failover_series(kills)
    finally:
        quiet.setLevel(level)
        os.environ.pop(leak.variable, None)
        leaked = leak.kill_leftovers()
    out.add(
        "failover_ms",
        median(times),
        "ms",
        f"median of {kills} kills: SIGKILL of the active sensor -> first reading of the"
        " substitute at the consumer (python -S -I sensor processes)",
        GOAL_FAILOVER_MS,
    )
    out.add("failover_p99_ms", percentile(times, 99), "ms", f"p99 of {kills} kills")
    out.add("failover_max_ms", max(times), "ms", f"max of {kills} kills")
    if leaked:
        out.notes.append(f"processes left running were killed: {leaked}")
    return out


if __name__ == "__main__":
    for metric in bench_component("--quick" in sys.argv).metrics:
        print(f"{metric.name}: {metric.value:.2f} {metric.unit}")
