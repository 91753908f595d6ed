"""Safety: how fast a signal puts every device in its safe state, seen on the wire.

``safe_stop_ms``: for each device family (ODrive axes and MIT motors on CAN over
``udp_multicast``, a Dynamixel chain on a pseudo-terminal, a MAVLink vehicle in the air over
UDP), :mod:`temoto.testing.exitpaths` runs the device's simulator in one process and the robot
command with a mission in another, sends SIGINT (and SIGTERM) while the device acts, and takes
the time from the signal to the first state line in which the simulator sees the device safe
(every axis IDLE, motor mode off, torque off, a hold mode). The metric is the median over the
runs of the slowest family of each round (signal -> last device safe). The CAN families need
root and ``unshare``; without them they are left out with a note.

``safe_stop_silent_links_ms`` (root only): the ODrive rover with two more devices, a six-servo
Dynamixel arm and a MAVLink quad, whose links are cut (``link_loss``) just before SIGTERM: the
time to the live ODrive safe (every device is made safe at once, so the silent ones, waiting
for replies that never come, must not delay it; bound 200 ms).

``recover_after_pause_ms``: the mobile manipulator serving (``sim: true``), its process stopped
for 1.5 s (SIGSTOP, then SIGCONT; its simulators pause with it, so the ODrive axes' and the
Dynamixel servos' 1 s watchdogs expire): the time from SIGCONT to the last device's
``recovered on try`` line (the Robot Manager's recovery policy, its default).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from typing import Any

from bench.common import Results, median

#: The goal: every device safe within 100 ms of the signal.
GOAL_MS = 100.0


def _silent_links() -> dict[str, object]:
    """A six-servo Dynamixel arm and a MAVLink quad, whose links are cut before the signal."""
    from temoto.testing.exitpaths import FAMILIES

    arm = json.loads(json.dumps(FAMILIES["dynamixel"]["device"]))
    servo = arm["servos"][0]
    arm["servos"] = [{**servo, "id": i, "joint": f"joint{i}"} for i in range(1, 7)]
    return {"arm": arm, "quad": dict(FAMILIES["mavlink"]["device"])}


def _one(family: str, path: str, netns: bool, silent: dict[str, object] | None = None) -> float:
    argv = [sys.executable, "-m", "temoto.testing.exitpaths", family, path]
    if netns:
        argv.append("--netns")
    if silent is not None:
        argv += ["--silent", json.dumps(silent)]
    proc = subprocess.run(argv, capture_output=True, text=True, timeout=120, check=False)
    if proc.returncode != 0:
        raise RuntimeError(f"exitpaths {family} {path}: {proc.stderr.strip()[-500:]}")
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    if result["safe_ms"] is None:
        raise RuntimeError(f"{family} {path}: the device was never safe: {result['stderr'][-500:]}")
    return float(result["safe_ms"])


def bench_safety(quick: bool) -> Results:
    """``safe_stop_ms`` (and per family ``safe_stop_<family>_ms``)."""
    out = Results()
    netns = os.geteuid() == 0 and shutil.which("unshare") is not None
    families = ["odrive", "mit", "dynamixel", "mavlink"]
    if not netns:
        families = ["dynamixel", "mavlink"]
        out.notes.append("not root (or no unshare): the CAN families are left out of safe_stop_ms")
    paths = ["sigint"] if quick else ["sigint", "sigterm"]
    rounds = 1 if quick else 3
    per_family: dict[str, list[float]] = {f: [] for f in families}
    slowest: list[float] = []
    for _ in range(rounds):
        for path in paths:
            times = {f: _one(f, path, netns and f in ("odrive", "mit")) for f in families}
            for family, ms in times.items():
                per_family[family].append(ms)
            slowest.append(max(times.values()))
    out.add(
        "safe_stop_ms",
        median(slowest),
        "ms",
        f"signal -> last device safe on the wire, {len(slowest)} runs of {len(families)} families",
        goal=("<=", GOAL_MS),
    )
    for family, values in per_family.items():
        out.add(f"safe_stop_{family}_ms", median(values), "ms", f"{len(values)} runs")
    if netns:  # the rover's ODrive with two more devices whose links are silent
        silent = _silent_links()
        runs = [_one("odrive", "sigterm", True, silent) for _ in range(rounds)]
        out.add(
            "safe_stop_silent_links_ms",
            median(runs),
            "ms",
            f"SIGTERM -> the live ODrive safe, arm and quad links cut; {len(runs)} runs",
            goal=("<=", 200.0),
        )
    pauses = [_recovery_after_pause() for _ in range(rounds)]
    out.add(
        "recover_after_pause_ms",
        median(pauses),
        "ms",
        f"SIGCONT after a 1.5 s SIGSTOP of a serving robot -> every device recovered; {len(pauses)}"
        " runs",
    )
    return out


#: The serving robot of ``recover_after_pause_ms`` (its simulators pause with it).
_PAUSED_PROFILE = "hw_profiles/sim_mobile_manipulator.yaml"


def _recovery_after_pause() -> float:
    """Milliseconds from SIGCONT to the last device's ``recovered on try`` line on stderr."""
    import signal
    import threading
    import time
    from pathlib import Path

    profile = Path(__file__).resolve().parents[1] / _PAUSED_PROFILE
    env = {k: v for k, v in os.environ.items() if k != "TEMOTO_FLEET_KEY"}
    argv = [sys.executable, "-m", "temoto.managers.robot", "--profile", str(profile), "--local"]
    proc = subprocess.Popen(
        argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env
    )
    lines: list[tuple[float, str]] = []

    def read() -> None:
        assert proc.stderr is not None
        for line in proc.stderr:
            lines.append((time.monotonic(), line))

    reader = threading.Thread(target=read, name="bench-robot-stderr")
    reader.start()
    try:
        deadline = time.monotonic() + 60.0
        while not any("serving" in line for _, line in lines):
            if time.monotonic() > deadline or proc.poll() is not None:
                raise RuntimeError(f"the robot did not serve: {''.join(text for _, text in lines)}")
            time.sleep(0.05)
        time.sleep(0.5)
        proc.send_signal(signal.SIGSTOP)
        time.sleep(1.5)  # longer than the profile's 1 s watchdogs
        proc.send_signal(signal.SIGCONT)
        t0 = time.monotonic()
        while sum("recovered on try" in line for _, line in list(lines)) < 2:
            if time.monotonic() > t0 + 30.0:
                raise RuntimeError(f"not recovered: {''.join(text for _, text in lines)[-1500:]}")
            time.sleep(0.01)
        return (max(t for t, line in lines if "recovered on try" in line) - t0) * 1000.0
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        reader.join(5)
        if proc.stderr is not None:
            proc.stderr.close()


def bench_stale(quick: bool) -> Results:
    """``stale_detect_ms``: an ODrive's encoder stream stops (heartbeats go on) -> driver FAULT.

    An :class:`~temoto.drivers.can_motor.odrive.ODriveDriver` and a
    :class:`~temoto.drivers.can_motor.sim.SimODrive`, encoder estimates every 10 ms; the
    simulator's ``no_encoder`` fault stops them and the time to the driver's FAULT report is
    taken (goal: within 3 stream periods, 30 ms). Each injection waits a random fraction of a
    stream period first (seeded): a stream stops at any moment of its period, while the bench's
    loop would otherwise inject at one phase (just after a frame: right after ``activate``
    returns on a reply).

    The link is python-can's ``udp_multicast`` inside a private network namespace (root and
    ``unshare``), as a device on a real bus is: on the ``virtual`` bus the driver knows its
    device is a simulator in its own process and gives its streams 0.2 s at least
    (``STALE_REAL_FLOOR_IN_PROCESS``). Without root the ``virtual`` bus is measured, with a note.
    """
    out = Results()
    rounds = 5 if quick else 20
    period = 0.01
    if os.geteuid() == 0 and shutil.which("unshare") is not None:
        script = (
            "ip link set lo up && ip route add 224.0.0.0/4 dev lo && exec "
            f"'{sys.executable}' -m bench.safety stale {rounds} udp_multicast"
        )
        proc = subprocess.run(
            ["unshare", "-n", "sh", "-c", script],
            capture_output=True,
            text=True,
            timeout=300,
            check=False,
        )
        if proc.returncode != 0:
            raise RuntimeError(f"stale bench in a network namespace: {proc.stderr.strip()[-500:]}")
        times = json.loads(proc.stdout.strip().splitlines()[-1])
        where = "udp_multicast in a network namespace"
    else:
        times = _stale_times(rounds, "virtual")
        where = "virtual bus"
        out.notes.append(
            "not root (or no unshare): stale_detect_ms measured on the virtual bus, where the"
            " driver gives an in-process simulator's streams 0.2 s at least"
        )
    out.add(
        "stale_detect_ms",
        median(times),
        "ms",
        f"encoder stream stops -> FAULT, stream every {period * 1000:g} ms, {len(times)} runs,"
        f" {where}",
        goal=("<=", 3 * period * 1000.0),
    )
    return out


def _stale_times(rounds: int, interface: str) -> list[float]:
    """Milliseconds from each ``no_encoder`` injection to the driver's FAULT."""
    import random
    import threading
    import time

    from temoto.clock import MonotonicClock
    from temoto.drivers import DriverState
    from temoto.drivers.can_motor.odrive import ODriveDriver
    from temoto.drivers.can_motor.sim import SimODrive

    period = 0.01
    if interface == "virtual":
        link: dict[str, Any] = {"interface": "virtual", "channel": f"bench-stale-{os.getpid()}"}
    else:
        link = {"interface": "udp_multicast", "channel": "239.74.163.25", "fd": False}
    clock = MonotonicClock()
    entry = {
        "link": link,
        "heartbeat_period": 0.05,
        "encoder_period": period,
        "nodes": [{"node_id": 1, "joint": "left"}, {"node_id": 2, "joint": "right"}],
    }
    times: list[float] = []
    with SimODrive(link, [1, 2], clock, heartbeat_period=0.05, encoder_period=period) as sim:
        driver = ODriveDriver.from_profile("base", entry, clock=clock, where="bench")
        faulted = threading.Event()
        driver.add_health_listener(
            lambda h: faulted.set() if h.state is DriverState.FAULT else None
        )
        with driver:
            driver.configure()
            driver.activate()
            phase = random.Random(25)
            for _ in range(rounds):
                faulted.clear()
                time.sleep(phase.uniform(0.0, period))
                t0 = time.monotonic()
                sim.inject("no_encoder")
                if not faulted.wait(2.0):
                    raise RuntimeError("the stale encoder stream was not reported within 2 s")
                times.append((time.monotonic() - t0) * 1000.0)
                sim.clear("no_encoder")
                driver.make_safe("bench")  # the fault may have left it in FAULT
                deadline = time.monotonic() + 2.0
                while driver.state is DriverState.FAULT and time.monotonic() < deadline:
                    try:
                        driver.recover()
                    except Exception:
                        time.sleep(0.02)
                if driver.state is DriverState.INACTIVE:
                    driver.activate()
                if driver.state is not DriverState.ACTIVE:
                    raise RuntimeError(f"the driver did not come back: {driver.health().message}")
    return times


if __name__ == "__main__":  # python -m bench.safety stale ROUNDS INTERFACE: the times as JSON
    if len(sys.argv) != 4 or sys.argv[1] != "stale":
        sys.exit("usage: python -m bench.safety stale ROUNDS INTERFACE")
    print(json.dumps(_stale_times(int(sys.argv[2]), sys.argv[3])))
