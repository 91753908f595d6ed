"""An ODriveDriver and a SimODrive in two processes, over python-can's ``udp_multicast`` bus.

The processes run in a private network namespace (``unshare -n``) with loopback up and
multicast routed through it, so the host's interfaces are never touched. Runs only as root
with ``unshare``, ``ip`` and msgpack (which python-can's udp_multicast interface needs).
"""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import temoto

REPO = Path(temoto.__file__).resolve().parent.parent
LINK = {"interface": "udp_multicast", "channel": "239.74.163.2", "fd": False}

SIM = r"""
import json, sys
from temoto.clock import MonotonicClock
from temoto.drivers.can_motor.sim import SimODrive
sim = SimODrive(json.loads(sys.argv[1]), [4, 5], MonotonicClock(), heartbeat_period=0.05)
with sim:
    print("ready", flush=True)
    for line in sys.stdin:
        words = line.split()
        if words[0] == "quit":
            break
        if words[0] == "inject":
            sim.inject(words[1])
        elif words[0] == "clear":
            sim.clear(words[1])
        print("ok", flush=True)
"""

DRIVER = r"""
import json, subprocess, sys, threading, time
from temoto.clock import MonotonicClock
from temoto.drivers import DriverState
from temoto.drivers.can_motor.odrive import ODriveDriver
from temoto.drivers.capabilities import ControlMode, JointCommand

link, sim_code = json.loads(sys.argv[1]), sys.argv[2]
sim = subprocess.Popen([sys.executable, "-c", sim_code, json.dumps(link)],
                       stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
out = {}
try:
    assert sim.stdout.readline().strip() == "ready"
    cfg = {"link": link, "heartbeat_period": 0.05, "init_timeout": 2.0,
           "nodes": [{"node_id": 4, "joint": "left"}, {"node_id": 5, "joint": "right"}]}
    def until(pred, timeout):
        end = time.monotonic() + timeout
        while not pred():
            if time.monotonic() > end:
                return False
            time.sleep(0.005)
        return True
    with ODriveDriver.from_profile("base", cfg, clock=MonotonicClock(), where="base") as d:
        d.configure()
        d.activate()
        d.command([JointCommand("right", ControlMode.POSITION, 2.0)])
        out["moved"] = until(lambda: abs(d.read_state().joints["right"].position - 2.0) < 0.01, 5)
        def control(word):
            sim.stdin.write(word + "\n"); sim.stdin.flush()
            assert sim.stdout.readline().strip() == "ok"
        t = time.monotonic()
        control("inject silence")
        out["faulted"] = until(lambda: d.state is DriverState.FAULT, 2)
        out["fault_after"] = time.monotonic() - t
        out["error"] = type(d.health().error).__name__
        control("clear silence")
        out["recovered"] = until(lambda: d.state is DriverState.ACTIVE, 2)
finally:
    sim.stdin.write("quit\n"); sim.stdin.flush()
    sim.wait(10)
print(json.dumps(out))
"""


def _why_not() -> str:
    if os.geteuid() != 0:
        return "needs root for unshare -n"
    if not (shutil.which("unshare") and shutil.which("ip")):
        return "needs unshare and ip"
    if importlib.util.find_spec("msgpack") is None:
        return "python-can's udp_multicast interface needs msgpack"
    return ""


@pytest.mark.slow
@pytest.mark.skipif(bool(_why_not()), reason=_why_not() or "ok")
def test_driver_and_simulator_in_two_processes_over_udp_multicast() -> None:
    script = (
        "ip link set lo up && ip route replace 224.0.0.0/4 dev lo && "
        f'exec "{sys.executable}" -c "$0" "$1" "$2"'
    )
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.run(
        ["unshare", "-n", "sh", "-c", script, DRIVER, json.dumps(LINK), SIM],
        capture_output=True,
        text=True,
        timeout=30,
        env=env,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result["moved"]
    assert result["faulted"]
    assert result["error"] == "DriverTimeoutError"
    assert result["fault_after"] <= 3 * 0.05 + 0.1
    assert result["recovered"]
