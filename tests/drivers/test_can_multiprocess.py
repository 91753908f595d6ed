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
        control("inject silence")
        out["faulted"] = until(lambda: d.state is DriverState.FAULT, 30)
        out["error"] = type(d.health().error).__name__
        out["message"] = str(d.health().error)
        control("clear silence")
        out["recovered"] = until(lambda: d.state is DriverState.ACTIVE, 30)
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
        timeout=180,  # a hang guard: three Python processes start on a loaded machine
        env=env,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result["moved"]
    assert result["faulted"]
    assert result["error"] == "DriverTimeoutError"
    assert "stale" in result["message"] or "heartbeat" in result["message"], result["message"]
    # how soon: bench `stale_detect_ms` (wall-clock figures are no test on a loaded machine)
    assert result["recovered"]


KILL_HARNESS = r"""
import json, os, signal, subprocess, sys, time
import can
from temoto.drivers.can_motor import cansimple as cs

link, watchdog = json.loads(sys.argv[1]), float(sys.argv[2])
SIM = '''
import json, sys
from temoto.clock import MonotonicClock
from temoto.drivers.can_motor.sim import SimODrive
sim = SimODrive(json.loads(sys.argv[1]), [4, 5], MonotonicClock(), heartbeat_period=0.05,
                watchdog_timeout=float(sys.argv[2]))
sim.start()
print("ready", flush=True)
sys.stdin.readline()
sim.close()
'''
DRIVER = '''
import json, sys, time
from temoto.clock import MonotonicClock
from temoto.drivers.can_motor.odrive import ODriveDriver
from temoto.drivers.capabilities import ControlMode, JointCommand
cfg = {"link": json.loads(sys.argv[1]), "heartbeat_period": 0.05, "init_timeout": 2.0,
       "watchdog_timeout": float(sys.argv[2]),
       "nodes": [{"node_id": 4, "joint": "left"}, {"node_id": 5, "joint": "right"}]}
d = ODriveDriver.from_profile("base", cfg, clock=MonotonicClock(), where="base")
d.configure()
d.activate()
d.command([JointCommand("left", ControlMode.VELOCITY, 3.0)])
print("active", flush=True)
time.sleep(60)
'''
args = [json.dumps(link), str(watchdog)]
sim = subprocess.Popen([sys.executable, "-c", SIM, *args], stdin=subprocess.PIPE,
                       stdout=subprocess.PIPE, text=True)
out = {}
try:
    assert sim.stdout.readline().strip() == "ready"
    driver = subprocess.Popen([sys.executable, "-c", DRIVER, *args], stdout=subprocess.PIPE,
                              text=True)
    assert driver.stdout.readline().strip() == "active"
    with can.Bus(**link) as bus:
        def states(seconds):
            seen, end = {}, time.monotonic() + seconds
            while time.monotonic() < end:
                msg = bus.recv(0.05)
                if msg is not None and not msg.is_remote_frame:
                    node, cmd = cs.split_id(msg.arbitration_id)
                    if cmd == cs.Cmd.HEARTBEAT and len(msg.data) == 8:
                        seen[node] = cs.decode_heartbeat(msg.data)
            return seen
        fed = states(3 * watchdog)  # the driver feeds: the axes stay armed
        out["armed"] = all(b.axis_state == cs.AxisState.CLOSED_LOOP_CONTROL for b in fed.values())
        os.kill(driver.pid, signal.SIGKILL)
        killed = time.monotonic()
        driver.wait()
        idle = {}
        while len(idle) < 2 and time.monotonic() - killed < 30:
            msg = bus.recv(0.05)
            if msg is None or msg.is_remote_frame:
                continue
            node, cmd = cs.split_id(msg.arbitration_id)
            if cmd == cs.Cmd.HEARTBEAT and len(msg.data) == 8:
                beat = cs.decode_heartbeat(msg.data)
                if beat.axis_state == cs.AxisState.IDLE and node not in idle:
                    idle[node] = (time.monotonic() - killed, beat.axis_error)
        out["idle"] = {str(n): v for n, v in idle.items()}
finally:
    sim.stdin.write("quit\n"); sim.stdin.flush()
    sim.wait(10)
print(json.dumps(out))
"""


@pytest.mark.slow
@pytest.mark.skipif(bool(_why_not()), reason=_why_not() or "ok")
def test_sigkill_of_the_driver_process_leaves_the_watchdog_to_disarm_the_axes() -> None:
    watchdog = 0.3
    script = (
        "ip link set lo up && ip route replace 224.0.0.0/4 dev lo && "
        f'exec "{sys.executable}" -c "$0" "$1" "$2"'
    )
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    link = {**LINK, "channel": "239.74.163.3"}
    proc = subprocess.run(
        ["unshare", "-n", "sh", "-c", script, KILL_HARNESS, json.dumps(link), str(watchdog)],
        capture_output=True,
        text=True,
        timeout=180,  # a hang guard: four Python processes start on a loaded machine
        env=env,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result["armed"]
    assert set(result["idle"]) == {"4", "5"}
    for took, error in result["idle"].values():
        # WATCHDOG_TIMER_EXPIRED, seen on the wire: the watchdog, nothing else, disarmed them;
        # how soon after the kill is the simulator's timing on a loaded machine (bench/safety.py)
        assert error & 0x01000000, (took, error)
