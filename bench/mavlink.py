"""MAVLink telemetry cost: the driver's CPU while a simulated vehicle streams at 50 Hz.

The simulated ArduCopter runs in this process and streams seven telemetry messages
(GLOBAL_POSITION_INT, ATTITUDE, SYS_STATUS, BATTERY_STATUS, GPS_RAW_INT, EXTENDED_SYS_STATE,
VFR_HUD) at 50 Hz each plus the 1 Hz heartbeat over UDP loopback. The driver runs alone in a
child process (``udpin:``), configured and active, and a consumer reads ``telemetry()`` at
50 Hz. The child's CPU time (``time.process_time``: user + system of every thread) per wall
second over the window is the metric, so the simulator's own CPU is not counted.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

from bench.common import Results

RATE_HZ = 50.0
STREAMS = (
    "GLOBAL_POSITION_INT",
    "ATTITUDE",
    "SYS_STATUS",
    "BATTERY_STATUS",
    "GPS_RAW_INT",
    "EXTENDED_SYS_STATE",
    "VFR_HUD",
)

CHILD = r"""
import json, sys, time
from temoto.clock import MonotonicClock
from temoto.drivers.mavlink import MavlinkDriver

port, seconds = int(sys.argv[1]), float(sys.argv[2])
driver = MavlinkDriver("bench", link=f"udpin:127.0.0.1:{port}", clock=MonotonicClock(),
                       stream_rate=0, init_timeout=10.0)
with driver:
    driver.configure()
    driver.activate()
    time.sleep(0.5)  # settle: threads started, first bursts absorbed
    n0, cpu0, wall0 = driver.messages_received, time.process_time(), time.perf_counter()
    reads, next_read = 0, wall0
    while (now := time.perf_counter()) - wall0 < seconds:
        driver.telemetry()
        reads += 1
        next_read += 1.0 / 50.0
        time.sleep(max(0.0, next_read - time.perf_counter()))
    cpu, wall = time.process_time() - cpu0, time.perf_counter() - wall0
    n = driver.messages_received - n0
    print(json.dumps({"cpu": cpu, "wall": wall, "messages": n, "reads": reads,
                      "bad": driver.bad_frames}))
"""


def bench_mavlink(quick: bool) -> Results:
    out = Results()
    try:
        from temoto.clock import MonotonicClock
        from temoto.drivers.mavlink.driver import _free_udp_port
        from temoto.drivers.mavlink.sim import SimVehicle
    except ImportError as err:  # pymavlink missing
        out.notes.append(f"mavlink_* skipped: {err}")
        return out
    seconds = 1.0 if quick else 10.0  # quick: the run's 60 s
    port = _free_udp_port()
    sim = SimVehicle(
        "bench",
        clock=MonotonicClock(),
        gcs=[("127.0.0.1", port)],
        rates=dict.fromkeys(STREAMS, RATE_HZ),
        step_rate=RATE_HZ * 2,  # tick twice per period so every stream keeps its 50 Hz
    )
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parent.parent)}
    with sim:
        proc = subprocess.run(
            [sys.executable, "-c", CHILD, str(port), str(seconds)],
            capture_output=True,
            text=True,
            timeout=seconds + 60,
            env=env,
            check=False,
        )
    if proc.returncode != 0:
        raise RuntimeError(f"mavlink benchmark failed: {proc.stderr[-3000:]}")
    data = json.loads(proc.stdout.strip().splitlines()[-1])
    rate = data["messages"] / data["wall"]
    out.add(
        "mavlink_telemetry_50hz_cpu_pct",
        100.0 * data["cpu"] / data["wall"],
        "%",
        f"driver process CPU (all threads) per wall second while SimVehicle streams"
        f" {len(STREAMS)} telemetry messages at {RATE_HZ:g} Hz each over UDP loopback and"
        f" telemetry() is read at 50 Hz; {seconds:g} s window",
        ("<=", 5.0),
    )
    out.add(
        "mavlink_messages_per_s",
        rate,
        "msg/s",
        f"valid MAVLink messages the driver decoded per second in the same window"
        f" ({data['bad']} bad frames)",
    )
    return out


if __name__ == "__main__":
    start = time.perf_counter()
    for metric in bench_mavlink(quick="--quick" in sys.argv).metrics:
        print(f"{metric.name}: {metric.value:.2f} {metric.unit}  ({metric.note})")
    print(f"took {time.perf_counter() - start:.1f} s")
