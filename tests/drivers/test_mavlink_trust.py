"""Trust only the autopilot: other components and a second vehicle are not believed.

Process tests: ``mavlink/_flying_autopilot.py`` (an independent ArduCopter end written from
common.xml, encoding with pymavlink, not our simulator) runs in a process of its own; the robot
command (``python -m temoto.managers.robot --local``) or a driver talks to it over UDP, and what
the emulator received is read from its own output (the wire, seen from the vehicle's side).
Each case takes a few seconds of real time (two Python processes start).
"""

from __future__ import annotations

import contextlib
import json
import os
import queue
import re
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import IO, Any

import pytest

from temoto.clock import MonotonicClock
from temoto.drivers.mavlink import MavlinkDriver
from temoto.drivers.mavlink import protocol as p
from temoto.errors import DriverInitError
from temoto.testing.exitpaths import _ACTIONS

pytestmark = pytest.mark.slow

EMULATOR = Path(__file__).parent / "mavlink" / "_flying_autopilot.py"
START = (47.397742, 8.545594, 10.0)
LOITER = 5
STEP = 30.0  # real seconds any one step may take on a loaded machine


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
        return port


class Emulator:
    """The emulator's process and its event lines."""

    def __init__(self, port: int, *args: str) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, str(EMULATOR), str(port), *args],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        self.events: list[dict[str, Any]] = []
        self._new: queue.Queue[None] = queue.Queue()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()
        self.wait("ready")

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.events.append(json.loads(line))
            self._new.put(None)

    def wait(self, event: str, timeout: float = STEP) -> dict[str, Any]:
        deadline = time.monotonic() + timeout
        while True:
            for seen in list(self.events):
                if seen["event"] == event:
                    return seen
            left = deadline - time.monotonic()
            assert left > 0, f"the emulator never reported {event!r}: {self.events[-5:]}"
            with contextlib.suppress(queue.Empty):
                self._new.get(timeout=min(left, 0.1))

    def commands(self, command: int) -> list[dict[str, Any]]:
        return [e for e in self.events if e["event"] == "command" and e["command"] == command]

    def close(self) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.close()
        try:
            self.proc.wait(5)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self._reader.join(5)
        for stream in (self.proc.stdout, self.proc.stderr):
            if stream is not None:
                stream.close()


@pytest.fixture
def port() -> int:
    return _free_port()


def _number(value: float) -> dict[str, Any]:
    return {"pvf_type": "number", "pvf_value": value}


def _run_robot(
    port: int, action: dict[str, Any], *, sigint_when: str | None = None
) -> tuple[int, str, str, float, float]:
    """The robot command with one action against the emulator: (rc, stdout, stderr, t, exit).

    ``sigint_when``: a text of the command's standard output after which SIGINT is sent; ``t``
    is the moment of the signal (or of the start).
    """
    with tempfile.TemporaryDirectory(prefix="temoto-trust-") as tmp:
        work = Path(tmp)
        actions = work / "actions"
        actions.mkdir()
        for name, text in _ACTIONS.items():
            (actions / name).write_text(text)
        profile = {
            "robot": "emu_quad",
            "sim": False,
            "devices": {
                "quad": {
                    "driver": "mavlink",
                    "link": f"udpin:127.0.0.1:{port}",
                    "stream_rate": 2,  # supervised at 3 periods (1.5 s): robust on a busy host
                    "command_timeout": 1.0,
                }
            },
            "features": {"flight": {"type": "vehicle", "device": "quad", "tolerance": 1.0}},
        }
        first = {"name": action["name"], "instance_id": 0}
        graph = {
            "graph_name": "trust",
            "graph_entry": [first],
            "graph_exit": [first],
            "actions": [{**action, "instance_id": 0, "type": "sync"}],
        }
        (work / "profile.json").write_text(json.dumps(profile))
        (work / "mission.json").write_text(json.dumps(graph))
        robot = subprocess.Popen(
            [sys.executable, "-m", "temoto.managers.robot", "--profile",
             str(work / "profile.json"), "--mission", str(work / "mission.json"),
             "--actions", str(actions), "--local"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )  # fmt: skip
        out: dict[str, str] = {}
        seen = threading.Event()

        def slurp(stream: IO[str] | None, key: str) -> None:
            assert stream is not None
            lines = []
            for line in stream:
                lines.append(line)
                if sigint_when is not None and sigint_when in line:
                    seen.set()
            out[key] = "".join(lines)

        readers = [
            threading.Thread(target=slurp, args=(robot.stdout, "stdout")),
            threading.Thread(target=slurp, args=(robot.stderr, "stderr")),
        ]
        for reader in readers:
            reader.start()
        t = time.monotonic()
        try:
            if sigint_when is not None:
                assert seen.wait(STEP), f"no {sigint_when!r} from the robot command"
                time.sleep(0.5)  # the action runs; the driver has heard the vehicle a while
                t = time.monotonic()
                robot.send_signal(signal.SIGINT)
            rc = robot.wait(STEP * 2)
        finally:
            if robot.poll() is None:
                robot.kill()
                robot.wait()
            for reader in readers:
                reader.join(5)
            for stream in (robot.stdout, robot.stderr):
                if stream is not None:
                    stream.close()
        return rc, out.get("stdout", ""), out.get("stderr", ""), t, time.monotonic()


def test_sigint_sends_the_safe_state_though_a_companion_says_on_ground(port: int) -> None:
    """A component 100 sending EXTENDED_SYS_STATE "on ground" does not hide a flying vehicle."""
    emu = Emulator(port, "--companion", "on_ground")
    try:
        rc, stdout, stderr, t, _ = _run_robot(port, {"name": "Hold"}, sigint_when="Hold_0 RUNNING")
        story = f"rc={rc}\nstdout:\n{stdout[-2000:]}\nstderr:\n{stderr[-3000:]}"
        assert rc == 130, story
        modes = [c for c in emu.commands(p.MAV_CMD_DO_SET_MODE) if c["t"] >= t]
        assert modes, f"no DO_SET_MODE on the wire after SIGINT\n{story}"
        assert int(modes[0]["param2"]) == LOITER, story
        assert "armed and landed" not in stderr, story
        assert (
            "from system 1 component 100: only the autopilot (system 1, component 1)" in stderr
        ), story
    finally:
        emu.close()


def test_a_spoofed_position_from_another_component_does_not_end_fly_to(port: int) -> None:
    """FlyTo ends when the autopilot is there, not when component 100 says it is."""
    goal = (START[0] + 0.0004, START[1], START[2])  # 44 m north: 5.6 s at 8 m/s
    spoof = ",".join(str(v) for v in goal)
    emu = Emulator(port, "--companion", "spoof", "--spoof-at", spoof, "--speed", "8")
    try:
        action = {
            "name": "FlyTo",
            "input_parameters": {
                "lat": _number(goal[0]),
                "lon": _number(goal[1]),
                "alt": _number(goal[2]),
            },
        }
        rc, stdout, stderr, _, exit_t = _run_robot(port, action)
        story = f"rc={rc}\nstdout:\n{stdout[-2000:]}\nstderr:\n{stderr[-3000:]}"
        assert rc == 0, story
        (reposition,) = emu.commands(p.MAV_CMD_DO_REPOSITION)
        arrived = emu.wait("arrived")  # written before the position that ended FlyTo
        assert arrived["t"] - reposition["t"] > 3.0  # the emulator flew the distance
        assert exit_t >= arrived["t"], f"FlyTo ended before the autopilot arrived\n{story}"
    finally:
        emu.close()


@pytest.mark.parametrize("how", ["address", "sequence"])
def test_a_second_vehicle_with_the_same_system_id_fails_configure(port: int, how: str) -> None:
    emu = Emulator(port, "--duplicate", how)
    driver = MavlinkDriver(
        "quad", link=f"udpin:127.0.0.1:{port}", clock=MonotonicClock(), stream_rate=10
    )
    try:
        with pytest.raises(DriverInitError, match=r"quad: duplicate system id 1: "):
            driver.configure()
        assert emu.commands(p.MAV_CMD_COMPONENT_ARM_DISARM) == []
    finally:
        driver.shutdown()
        emu.close()


def test_the_robot_command_names_a_duplicate_system_id(port: int) -> None:
    emu = Emulator(port, "--duplicate", "address")
    try:
        rc, stdout, stderr, _, _ = _run_robot(port, {"name": "Hold"})
        story = f"rc={rc}\nstdout:\n{stdout[-2000:]}\nstderr:\n{stderr[-3000:]}"
        assert rc != 0, story
        assert "duplicate system id 1" in stderr + stdout, story
        assert "Traceback" not in stderr, story
        assert emu.commands(p.MAV_CMD_COMPONENT_ARM_DISARM) == []
    finally:
        emu.close()


#: The driver in a process of its own: configure, activate, print every health report.
_DRIVER_CHILD = """
import json, sys, time
from temoto.clock import MonotonicClock
from temoto.drivers.mavlink import MavlinkDriver
d = MavlinkDriver.from_profile("quad", json.loads(sys.argv[1]), clock=MonotonicClock(),
                               where="devices.quad")
def said(h):
    print(json.dumps({"t": time.monotonic(), "state": h.state.value, "message": h.message}),
          flush=True)
d.add_health_listener(said)
d.configure()
d.activate()
print(json.dumps({"ready": True}), flush=True)
sys.stdin.read()
d.shutdown()
"""


def test_a_paused_driver_process_reads_its_backlog_without_a_false_fault() -> None:
    """SIGSTOP of the driver's process for longer than heartbeat_timeout; the wire had no gap."""
    from temoto.testing.exitpaths import SimHost

    entry = {"driver": "mavlink", "link": "udpin:0.0.0.0:14550", "heartbeat_timeout": 2.0}
    host = SimHost(entry, dict(os.environ))
    try:
        config = {k: v for k, v in host.config.items() if k != "driver"}
        child = subprocess.Popen(
            [sys.executable, "-c", _DRIVER_CHILD, json.dumps(config)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        errors: list[str] = []
        resumed = threading.Event()

        def read_errors() -> None:
            assert child.stderr is not None
            for text in child.stderr:
                errors.append(text)
                if "this process did not run for" in text:
                    resumed.set()

        reader = threading.Thread(target=read_errors, name="temoto-test-stderr")
        reader.start()
        try:
            assert child.stdout is not None
            assert child.stdin is not None
            lines = []
            while True:
                line = child.stdout.readline()
                assert line, f"the driver did not start: {lines}"
                lines.append(line)
                if '"ready"' in line:
                    break
            time.sleep(0.5)
            child.send_signal(signal.SIGSTOP)
            time.sleep(3.0)  # > heartbeat_timeout (2 s); the vehicle goes on sending
            child.send_signal(signal.SIGCONT)
            # the driver reads its backlog (however late a loaded machine runs it), then has
            # 1.5 s to report a false fault before it is asked to stop
            resumed.wait(STEP)
            time.sleep(1.5)
            child.stdin.close()  # the child shuts the driver down and exits
            out = "".join(child.stdout)
            child.wait(STEP)
        finally:
            if child.poll() is None:
                child.kill()
                child.wait()
            reader.join(STEP)
            for stream in (child.stdin, child.stdout, child.stderr):
                if stream is not None:
                    stream.close()
        err = "".join(errors)
        story = "".join(lines) + out + "\nstderr:\n" + err[-3000:]
        assert child.returncode == 0, story
        assert '"FAULT"' not in out, story
        paused = re.search(r"this process did not run for (\d+\.\d) s", err)
        assert paused is not None, story
        assert float(paused.group(1)) >= 3.0, story  # the whole stop (more on a loaded host)
        assert "no message from the autopilot" not in err, story  # the gap was ours
    finally:
        host.close()
        host._reader.join(5)
        for stream in (host.proc.stdin, host.proc.stdout, host.proc.stderr):
            if stream is not None:
                stream.close()
