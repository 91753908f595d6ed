"""Every way out of the robot command, watched from the device's side of the wire.

``python -m temoto.testing.exitpaths FAMILY PATH [--json]`` starts one device simulator in a
process of its own (:mod:`temoto.testing.simhost`), a robot command
(``python -m temoto.managers.robot --mission ... --local``) in another one whose profile points
at the simulator over the real link (CAN over python-can's ``udp_multicast``, the Dynamixel
chain's pseudo-terminal, MAVLink over UDP), waits until the device acts, takes the exit path,
and prints what the simulator saw as one JSON object.

Families (:data:`FAMILIES`): ``odrive`` (a rover, two ODrive axes), ``mit`` (a two-joint arm of
MIT-mode motors), ``dynamixel`` (a two-servo arm), ``mavlink`` (a quadcopter, in the air when
the path is taken).

Paths (:data:`PATHS`):

==================  ===========================================================================
``end``             the mission ends by itself (on_true); the device must be safe when the
                    command exits
``fault``           the device's driver faults (the simulator stops its heartbeats or corrupts
                    its replies); the mission fails (exit 1)
``exception``       an action of the mission raises (exit 1)
``sigint``          SIGINT while the device acts (exit 130)
``sigterm``         SIGTERM while the device acts (exit 143)
``double_sigint``   SIGINT twice while an action ignores its stop (exit 130 at once)
``sigkill``         SIGKILL of the robot command: only the device's own watchdog can help
==================  ===========================================================================

The CAN families need a network namespace of their own with multicast routed on loopback:
with ``--netns`` (as root) the command re-runs itself under ``unshare -n`` and sets that up; the
host's interfaces are never touched. The result's keys: ``family``, ``path``, ``rc`` (None if the
command did not exit), ``traceback`` (whether its standard error has one), ``event_t`` (the
path's moment, CLOCK_MONOTONIC; the first signal of ``double_sigint``), ``second_t`` (its second
signal), ``exit_t``, ``safe_t`` (the first moment the device was
safe after the event), ``safe_ms`` (``safe_t - event_t``, milliseconds), ``safe_at_exit``,
``leftovers`` (processes of the command still alive after it exited), ``states`` (the
simulator's state lines after the event) and ``stderr``.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import json
import os
import queue
import secrets
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import IO, Any, Final

from temoto.testing import reaper

__all__ = [
    "CAN_LINK",
    "FAMILIES",
    "PATHS",
    "SimHost",
    "in_netns",
    "main",
    "marked_pids",
    "run_path",
    "slurp",
    "why_not_netns",
]

PATHS: Final = ("end", "fault", "exception", "sigint", "sigterm", "double_sigint", "sigkill")

#: The CAN link of the process tests: python-can's ``udp_multicast`` (inside ``unshare -n``).
CAN_LINK: Final = {"interface": "udp_multicast", "channel": "239.74.163.9", "fd": False}

#: What the two arm families share: a two-joint arm and its motion.
_ARM: Final[Mapping[str, Any]] = {
    "features": {
        "manipulation": {
            "type": "arm",
            "device": "device",
            "tolerance": 0.05,
            "poses": {"home": {"shoulder": 0.0, "elbow": 0.0}, "reach": {"shoulder": 0.5}},
        }
    },
    "long": ("MoveJoints", {"pose": "reach"}),
    "short": ("MoveJoints", {"pose": "reach"}),
}

#: Per family: the device entry, the features, the long and short motions, the fault to inject
#: and, where the device has a watchdog, the SIGKILL bound (its timeout plus one period).
FAMILIES: Final[Mapping[str, Mapping[str, Any]]] = {
    "odrive": {
        "device": {
            "driver": "odrive_can",
            "link": CAN_LINK,
            "heartbeat_period": 0.05,
            "encoder_period": 0.01,
            "command_period": 0.05,
            "watchdog_timeout": 0.2,
            "nodes": [
                {"node_id": 1, "joint": "left_wheel", "velocity_limit": 20.0},
                {"node_id": 2, "joint": "right_wheel", "velocity_limit": 20.0},
            ],
        },
        "features": {
            "navigation": {
                "type": "differential_drive",
                "left_wheel": "left_wheel",
                "right_wheel": "right_wheel",
                "wheel_radius": 0.08,
                "wheel_separation": 0.42,
                "max_speed": 1.0,
                "max_turn_rate": 2.0,
                "tolerance": 0.05,
            }
        },
        "long": ("NavigateTo", {"x": 100.0, "y": 0.0}),
        "short": ("NavigateTo", {"x": 0.3, "y": 0.0}),
        "fault": "no_heartbeat",
        # SIGKILL: the axis watchdog (0.2 s) plus one set-point period
        "sigkill_bound_s": 0.2 + 0.05,
    },
    "mit": {
        "device": {
            "driver": "mit_can",
            "link": CAN_LINK,
            "poll_rate": 100,
            "can_timeout": 0.1,
            "motors": [
                {"motor_id": 1, "joint": "shoulder", "model": "AK80-9"},
                {"motor_id": 2, "joint": "elbow", "model": "AK80-9"},
            ],
        },
        **_ARM,
        "fault": "corrupt",
        # SIGKILL: the motor controller's CAN timeout (0.1 s) plus one poll period
        "sigkill_bound_s": 0.1 + 0.01,
    },
    "dynamixel": {
        "device": {
            "driver": "dynamixel",
            "link": "serial:/dev/null?baud=1000000",
            "poll_rate": 50,
            "bus_watchdog": 0.1,
            "servos": [
                {
                    "id": 1,
                    "joint": "shoulder",
                    "model": "XM430-W350",
                    "mode": "position",
                    "min_position": -2.0,
                    "max_position": 2.0,
                },
                {
                    "id": 2,
                    "joint": "elbow",
                    "model": "XM430-W350",
                    "mode": "position",
                    "min_position": -2.0,
                    "max_position": 2.0,
                },
            ],
        },
        **_ARM,
        "fault": "corrupt",
        # SIGKILL: the Bus Watchdog (0.1 s) plus one poll period (50 Hz)
        "sigkill_bound_s": 0.1 + 0.02,
    },
    "mavlink": {
        "device": {
            "driver": "mavlink",
            "link": "udpin:0.0.0.0:14550",
            "heartbeat_timeout": 2.0,  # the least the driver takes (2 of ArduPilot's heartbeats)
            "command_timeout": 1.0,
            "stream_rate": 10,
            "gcs_failsafe": {"enable": 1, "timeout": 2.0},
            "sim": {"climb_rate": 3.0, "speed": 8.0},
        },
        "features": {"flight": {"type": "vehicle", "device": "device", "tolerance": 1.0}},
        "long": ("TakeOff", {"altitude": 60.0}),
        "short": ("TakeOff", {"altitude": 2.0}),
        "fault": "no_heartbeat",
        # SIGKILL: ArduPilot's GCS failsafe (FS_GCS_TIMEOUT 2 s, then RTL) plus one heartbeat
        "sigkill_bound_s": 2.0 + 1.0,
    },
}

#: Test actions the missions use (written to a temporary action folder).
_ACTIONS: Final = {
    "hold.py": '''
"""Hold: keeps the mission open while the robot is healthy; fails when it is not."""
from temoto import Action
from temoto.managers.robot.client import RobotManagerClient


class Hold(Action):
    def on_run(self) -> bool:
        robot = RobotManagerClient.for_action(self).acquire(self, "")
        while not self.wait_until_stopped(0.02):
            if not robot.healthy():
                raise RuntimeError("the robot is not healthy")
        return True
''',
    "hold.umrf.json": '{"name": "Hold", "type": "sync"}',
    "boom.py": '''
"""Boom: raises after a moment, as a buggy plugin would."""
from temoto import Action


class Boom(Action):
    def on_run(self) -> bool:
        self.wait_until_stopped(0.3)
        raise RuntimeError("boom: an action's bug")
''',
    "boom.umrf.json": '{"name": "Boom", "type": "sync"}',
    "stuck.py": '''
"""Stuck: ignores its stop for a minute, as a blocked driver call would."""
import time

from temoto import Action


class Stuck(Action):
    def on_run(self) -> bool:
        time.sleep(60)
        return True
''',
    "stuck.umrf.json": '{"name": "Stuck", "type": "sync"}',
}

#: Seconds the runner waits for each step at most.
STEP_TIMEOUT: Final = 20.0


def _value(value: Any) -> dict[str, Any]:
    kind = "string" if isinstance(value, str) else "number"
    return {"pvf_type": kind, "pvf_value": value}


def _mission(family: Mapping[str, Any], path: str) -> dict[str, Any]:
    """The mission of a path.

    ``end``: the short motion alone. ``double_sigint``: the short motion, then ``Stuck`` (so the
    first signal's stop has to wait for it). Otherwise the long motion with ``Boom``
    (``exception``) or ``Hold`` beside it.
    """
    name, inputs = family["short"] if path in ("end", "double_sigint") else family["long"]
    motion: dict[str, Any] = {
        "name": name,
        "instance_id": 0,
        "type": "sync",
        "input_parameters": {k: _value(v) for k, v in inputs.items()},
    }
    first = {"name": name, "instance_id": 0}
    graph: dict[str, Any] = {"graph_name": f"exit_{path}", "graph_entry": [first]}
    if path == "end":
        graph.update(graph_exit=[first], actions=[motion])
    elif path == "double_sigint":
        stuck = {"name": "Stuck", "instance_id": 0}
        motion["children"] = [stuck]
        graph.update(
            graph_exit=[stuck], actions=[motion, {**stuck, "type": "sync", "parents": [first]}]
        )
    else:
        beside = {"name": "Boom" if path == "exception" else "Hold", "instance_id": 0}
        graph.update(
            graph_entry=[first, beside],
            graph_exit=[first, beside],
            actions=[motion, {**beside, "type": "sync"}],
        )
    return graph


class SimHost:
    """The simulator's process and its state lines."""

    def __init__(self, entry: Mapping[str, Any], env: Mapping[str, str]) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "temoto.testing.simhost", json.dumps(entry)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=dict(env),
        )
        self.lines: queue.Queue[dict[str, Any]] = queue.Queue()
        self.states: list[dict[str, Any]] = []
        self.replies: queue.Queue[dict[str, Any]] = queue.Queue()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()
        try:
            first = self.lines.get(timeout=STEP_TIMEOUT)
        except queue.Empty:
            self.proc.kill()
            _, err = self.proc.communicate()
            raise RuntimeError(f"the simulator did not start: {err.strip()}") from None
        self.config: dict[str, Any] = first["config"]

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for text in self.proc.stdout:
            line = json.loads(text)
            if "t" in line:
                self.states.append(line)
            elif "config" not in line:
                self.replies.put(line)
                continue
            self.lines.put(line)

    def wait(
        self, what: str, *, since: float = 0.0, timeout: float = STEP_TIMEOUT
    ) -> dict[str, Any]:
        """The first state line since ``since`` where ``what`` holds.

        ``what``: ``safe``, ``active``, ``acting`` (active and not safe) or ``airborne``
        (acting and in the air).
        """
        deadline = time.monotonic() + timeout
        while True:
            for line in list(self.states):
                if line["t"] >= since and _holds(line, what):
                    return line
            left = deadline - time.monotonic()
            if left <= 0:
                last = self.states[-1] if self.states else None
                raise TimeoutError(f"the device was not {what} within {timeout} s (last: {last})")
            with contextlib.suppress(queue.Empty):
                self.lines.get(timeout=min(left, 0.05))

    def command(self, words: str) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(words + "\n")
        self.proc.stdin.flush()
        reply = self.replies.get(timeout=STEP_TIMEOUT)
        if "error" in reply:
            raise RuntimeError(f"simulator: {reply['error']}")

    def close(self) -> None:
        with contextlib.suppress(OSError):
            assert self.proc.stdin is not None
            self.proc.stdin.close()
        try:
            self.proc.wait(5)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


def _holds(line: Mapping[str, Any], what: str) -> bool:
    acting = bool(line["active"] and not line["safe"])
    if what == "acting":
        return acting
    if what == "airborne":
        return acting and bool(line["state"].get("airborne", True))
    return bool(line[what])


def marked_pids(mark: str) -> list[int]:
    """Pids of live processes whose environment holds ``TEMOTO_EXITPATH_MARK=mark``."""
    return reaper.marked_pids("TEMOTO_EXITPATH_MARK", mark)


def run_path(
    family_name: str,
    path: str,
    *,
    entry: Mapping[str, Any] | None = None,
    silent: Mapping[str, Mapping[str, Any]] | None = None,
) -> dict[str, Any]:
    """Take one exit path and report what the device saw (see the module docstring).

    Args:
        family_name: A key of :data:`FAMILIES`.
        path: One of :data:`PATHS`.
        entry: The device entry to use instead of the family's (watchdog settings, say).
        silent: More devices of the robot, by name → entry, each with its simulator in a
            process of its own; their links are cut (``link_loss``: nothing in, nothing out)
            just before the path is taken, so the robot makes them safe with silent links.

    Returns:
        The result mapping.

    Raises:
        ValueError: An unknown family or path.
        TimeoutError: The device never became active.
    """
    if family_name not in FAMILIES or path not in PATHS:
        raise ValueError(f"unknown family or path: {family_name!r} {path!r}")
    family = FAMILIES[family_name]
    device = dict(entry if entry is not None else family["device"])
    mark = secrets.token_hex(8)
    env = {**os.environ, "TEMOTO_EXITPATH_MARK": mark}
    env.pop("TEMOTO_FLEET_KEY", None)
    work = Path(tempfile.mkdtemp(prefix="temoto-exitpath-"))
    host_env = {k: v for k, v in env.items() if k != "TEMOTO_EXITPATH_MARK"}
    host = SimHost(device, host_env)
    others: dict[str, SimHost] = {}
    robot: subprocess.Popen[str] | None = None
    try:
        for other, other_entry in (silent or {}).items():
            others[other] = SimHost(other_entry, host_env)
        actions = work / "actions"
        actions.mkdir()
        for name, text in _ACTIONS.items():
            (actions / name).write_text(text)
        profile = {
            "robot": f"exit_{family_name}",
            "sim": False,
            "devices": {"device": host.config, **{n: h.config for n, h in others.items()}},
            "features": family["features"],
        }
        (work / "profile.json").write_text(json.dumps(profile))
        (work / "mission.json").write_text(json.dumps(_mission(family, path)))
        robot = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "temoto.managers.robot",
                "--profile",
                str(work / "profile.json"),
                "--mission",
                str(work / "mission.json"),
                "--actions",
                str(actions),
                "--local",
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
        )
        out: dict[str, str] = {}
        stuck = threading.Event()
        moving = threading.Event()
        marks = {"Stuck_0 RUNNING": stuck, f"{family['long'][0]}_0 RUNNING": moving}
        readers = [
            threading.Thread(target=slurp, args=(robot.stdout, out, "stdout", marks), daemon=True),
            threading.Thread(target=slurp, args=(robot.stderr, out, "stderr", {}), daemon=True),
        ]
        for reader in readers:
            reader.start()
        try:
            active = host.wait("airborne" if family_name == "mavlink" else "acting")
        except TimeoutError as err:  # say what the robot command said
            robot.kill()
            robot.wait()
            for reader in readers:
                reader.join(5)
            said = out.get("stderr", "")[-2000:]
            raise TimeoutError(f"{err}; the robot command's stderr:\n{said}") from None
        if path == "double_sigint" and not stuck.wait(STEP_TIMEOUT):
            raise TimeoutError("the mission's Stuck action did not start")
        if others and not moving.wait(STEP_TIMEOUT):  # every device loaded: the mission runs
            raise TimeoutError("the mission's motion did not start")
        second: dict[str, float] = {}
        for silent_host in others.values():
            silent_host.command("inject link_loss")
        event_t = _take(path, robot, host, family, second)
        try:
            rc: int | None = robot.wait(STEP_TIMEOUT)
        except subprocess.TimeoutExpired:
            rc = None
        exit_t = time.monotonic()
        for reader in readers:
            reader.join(5)
        since = active["t"] if path in ("end", "exception") else event_t
        safe_line: dict[str, Any] | None
        try:
            safe_line = host.wait("safe", since=since, timeout=5.0)
        except TimeoutError:
            safe_line = None
        last = host.states[-1]
        leftovers = marked_pids(mark) if rc is not None else []
        stderr = out.get("stderr", "")
        return {
            "family": family_name,
            "path": path,
            "rc": rc,
            "traceback": "Traceback" in stderr,
            "event_t": event_t,
            "second_t": second.get("t"),
            "exit_t": exit_t,
            "safe_t": None if safe_line is None else safe_line["t"],
            "safe_ms": None if safe_line is None else (safe_line["t"] - event_t) * 1000.0,
            "safe_at_exit": bool(last["safe"]),
            "leftovers": leftovers,
            "states": [s for s in host.states if s["t"] >= since],
            "stdout": out.get("stdout", ""),
            "stderr": stderr,
        }
    finally:
        if robot is not None and robot.poll() is None:
            robot.kill()
            robot.wait()
        host.close()
        for silent_host in others.values():
            silent_host.close()
        shutil.rmtree(work, ignore_errors=True)


def slurp(
    stream: IO[str] | None, out: dict[str, str], key: str, marks: Mapping[str, threading.Event]
) -> None:
    """Read a stream to its end into ``out[key]``; set each event when its text is seen."""
    assert stream is not None
    lines = []
    for line in stream:
        lines.append(line)
        for text, event in marks.items():
            if text in line:
                event.set()
    out[key] = "".join(lines)


def _take(
    path: str,
    robot: subprocess.Popen[str],
    host: SimHost,
    family: Mapping[str, Any],
    second: dict[str, float],
) -> float:
    """Take the path; returns its moment (the (first) signal, the injection, or the exit).

    For ``double_sigint`` the second signal's moment goes into ``second["t"]``.
    """
    if path in ("end", "exception"):
        robot.wait(STEP_TIMEOUT)
        return time.monotonic()
    if path == "fault":
        t = time.monotonic()
        host.command(f"inject {family['fault']}")
        return t
    sig = {
        "sigint": signal.SIGINT,
        "sigterm": signal.SIGTERM,
        "double_sigint": signal.SIGINT,
        "sigkill": signal.SIGKILL,
    }[path]
    t = time.monotonic()
    robot.send_signal(sig)
    if path == "double_sigint":  # the stop now waits for Stuck (up to 5 s): the second one
        host.wait("safe", since=t)
        time.sleep(0.2)
        second["t"] = time.monotonic()
        robot.send_signal(sig)
    return t


def why_not_netns() -> str:
    """Why the CAN process tests cannot run here, or ``""`` when they can.

    Returns:
        The missing requirement in a few words (root for ``unshare -n``, the ``unshare`` and
        ``ip`` commands, ``msgpack`` for python-can's ``udp_multicast``), or ``""``.
    """
    if os.geteuid() != 0:
        return "needs root for unshare -n"
    if not (shutil.which("unshare") and shutil.which("ip")):
        return "needs unshare and ip (iproute2)"
    if importlib.util.find_spec("msgpack") is None:
        return "python-can's udp_multicast interface needs msgpack"
    return ""


def in_netns(argv: Sequence[str], **run: Any) -> subprocess.CompletedProcess[Any]:
    """Run ``argv`` in a private network namespace with multicast routed on loopback.

    Args:
        argv: The command (its first word the program).
        **run: More keywords for :func:`subprocess.run` (``capture_output``, ``timeout``, ...).

    Returns:
        The finished process (its return code is not checked).
    """
    script = "ip link set lo up && ip route add 224.0.0.0/4 dev lo && exec " + " ".join(
        f"'{a}'" for a in argv
    )
    return subprocess.run(["unshare", "-n", "sh", "-c", script], check=False, **run)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m temoto.testing.exitpaths FAMILY PATH [--netns]``: print the result JSON.

    Args:
        argv: The arguments.

    Returns:
        0 when the path ran (whatever the device did), 2 for bad arguments.
    """
    parser = argparse.ArgumentParser(prog="python -m temoto.testing.exitpaths")
    parser.add_argument("family", choices=sorted(FAMILIES))
    parser.add_argument("path", choices=PATHS)
    parser.add_argument("--entry", help="the device entry as JSON (instead of the family's)")
    parser.add_argument(
        "--silent",
        help="more devices as JSON ({name: entry}), their links cut just before the path",
    )
    parser.add_argument("--netns", action="store_true", help="run inside unshare -n (root)")
    args = parser.parse_args(argv)
    if args.netns:
        rest = [args.family, args.path] + (["--entry", args.entry] if args.entry else [])
        rest += ["--silent", args.silent] if args.silent else []
        return in_netns([sys.executable, "-m", "temoto.testing.exitpaths", *rest]).returncode
    entry = json.loads(args.entry) if args.entry else None
    silent = json.loads(args.silent) if args.silent else None
    result = run_path(args.family, args.path, entry=entry, silent=silent)
    sys.stdout.write(json.dumps(result) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
