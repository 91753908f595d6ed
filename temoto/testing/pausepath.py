"""Pauses of the robot command (SIGSTOP, then SIGCONT) while CAN wheels drive, seen on the wire.

``python -m temoto.testing.pausepath FAMILY SECONDS [--pauses N] [--netns]`` starts the wheels'
simulator in a process of its own (:mod:`temoto.testing.simhost`), a robot command
(``python -m temoto.managers.robot --mission ... --local``) in another one driving them with a
``NavigateTo`` mission, and listens to the CAN link itself (python-can's ``udp_multicast``, a
plain listener: this process decodes nothing, it records every frame with the kernel's receive
time). Once the wheels turn, it stops the robot command with SIGSTOP for ``SECONDS``, ``N``
times, each time until every thread of the command is stopped, then SIGCONT. It waits for the
command to exit and prints one JSON object (the tests in ``tests/safety/test_pause_on_wire.py``
decode the frames by the vendors' layouts and judge their order).

Families (:data:`PAUSE_FAMILIES`): ``odrive`` (two ODrive axes, CANSimple, the axes' watchdog
1 s) and ``mit`` (two MIT-mode motors as wheels, their CAN timeout 1 s), both a differential
drive base with the robot's own navigation.

The result's keys: ``family``, ``pause_s``, ``rc`` (None if the command did not exit within
:data:`EXIT_TIMEOUT`), ``pauses`` (each ``{"stopped": t, "cont": t}``: wall-clock seconds, the
moment every thread of the command was seen stopped and the moment just before SIGCONT; the
same moments on CLOCK_MONOTONIC as ``stopped_mono`` and ``cont_mono``),
``frames`` (``[t, arbitration_id, remote, data_hex]``, ``t`` the kernel's receive time,
wall clock), ``states`` (the simulator's state lines, ``t`` on CLOCK_MONOTONIC), ``stdout``,
``stderr``, ``leftovers`` (processes of the command alive after it exited). The CAN link needs a
network namespace of its own with multicast on loopback: ``--netns`` (root) re-runs the command
under ``unshare -n`` as :mod:`temoto.testing.exitpaths` does.
"""

from __future__ import annotations

import argparse
import json
import os
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
from typing import Any, Final

from temoto.testing.exitpaths import CAN_LINK, SimHost, in_netns, marked_pids, slurp

__all__ = ["EXIT_TIMEOUT", "PAUSE_FAMILIES", "main", "run_pauses"]

#: Seconds the command may take to end its mission after the last pause (a loaded machine).
EXIT_TIMEOUT: Final = 90.0
#: Seconds the runner waits for the wheels to start turning.
START_TIMEOUT: Final = 40.0
#: Seconds of driving before the first pause and between two pauses.
DRIVE_BEFORE: Final = 0.6

_BASE: Final[Mapping[str, Any]] = {
    "type": "differential_drive",
    "left_wheel": "left_wheel",
    "right_wheel": "right_wheel",
    "wheel_radius": 0.08,
    "wheel_separation": 0.42,
    "max_turn_rate": 1.0,
    "tolerance": 0.05,
}

#: Per family: the device entry, the navigation feature and the goal (x, metres).
PAUSE_FAMILIES: Final[Mapping[str, Mapping[str, Any]]] = {
    "odrive": {
        "device": {
            "driver": "odrive_can",
            "link": CAN_LINK,
            "heartbeat_period": 0.1,  # no heartbeat within 0.3 s is a fault: the case
            # estimates stale after 0.15 s: a loaded machine can hold the simulator's process
            # back for tens of ms (a pause of the robot's is 0.5 s or more)
            "encoder_period": 0.05,
            "command_period": 0.05,
            "watchdog_timeout": 1.0,
            "nodes": [
                {"node_id": 1, "joint": "left_wheel", "velocity_limit": 20.0},
                {"node_id": 2, "joint": "right_wheel", "velocity_limit": 20.0},
            ],
        },
        "navigation": {**_BASE, "max_speed": 0.6},
        "goal": 4.0,
    },
    "mit": {
        "device": {
            "driver": "mit_can",
            "link": CAN_LINK,
            "poll_rate": 100,
            "can_timeout": 1.0,
            "timeout_periods": 10,  # 0.1 s without replies (a loaded machine; a pause is 0.5 s)
            "motors": [
                {"motor_id": 1, "joint": "left_wheel", "model": "AK80-9"},
                {"motor_id": 2, "joint": "right_wheel", "model": "AK80-9"},
            ],
        },
        # the MIT position field is ±12.5 rad: 1 m of travel on 0.08 m wheels, so go slowly
        "navigation": {**_BASE, "max_speed": 0.15},
        "goal": 0.7,
    },
}


def _mission(goal: float) -> dict[str, Any]:
    action = {
        "name": "NavigateTo",
        "instance_id": 0,
        "type": "sync",
        "input_parameters": {
            "x": {"pvf_type": "number", "pvf_value": goal},
            "y": {"pvf_type": "number", "pvf_value": 0.0},
        },
    }
    first = {"name": "NavigateTo", "instance_id": 0}
    graph = {"graph_name": "pause", "graph_entry": [first], "graph_exit": [first]}
    return {**graph, "actions": [action]}


class _Listener:
    """A plain python-can listener on the link: every frame with the kernel's receive time."""

    def __init__(self, link: Mapping[str, Any]) -> None:
        import can  # the CAN extra: only this runner needs it

        self._bus = can.Bus(**dict(link))
        self.frames: list[list[Any]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="temoto-pausepath-listener")
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            msg = self._bus.recv(0.05)
            if msg is not None:
                data = bytes(msg.data).hex()
                self.frames.append([msg.timestamp, msg.arbitration_id, msg.is_remote_frame, data])

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        self._bus.shutdown()


def _all_stopped(pid: int) -> bool:
    """Whether every thread of ``pid`` is stopped (state T in ``/proc/PID/task/*/stat``)."""
    try:
        for task in Path(f"/proc/{pid}/task").iterdir():
            stat = (task / "stat").read_text()
            if stat[stat.rindex(")") + 2] not in "Tt":
                return False
    except (OSError, ValueError):
        return False
    return True


def run_pauses(family_name: str, pause_s: float, pauses: int = 1) -> dict[str, Any]:
    """Pause the driving robot command ``pauses`` times and report the wire (module docstring).

    Args:
        family_name: A key of :data:`PAUSE_FAMILIES`.
        pause_s: Seconds of each pause.
        pauses: How many pauses.

    Returns:
        The result mapping.

    Raises:
        ValueError: An unknown family.
        TimeoutError: The wheels never turned.
    """
    if family_name not in PAUSE_FAMILIES:
        raise ValueError(f"unknown family {family_name!r}")
    family = PAUSE_FAMILIES[family_name]
    mark = secrets.token_hex(8)
    env = {**os.environ, "TEMOTO_EXITPATH_MARK": mark}
    env.pop("TEMOTO_FLEET_KEY", None)
    host_env = {k: v for k, v in env.items() if k != "TEMOTO_EXITPATH_MARK"}
    work = Path(tempfile.mkdtemp(prefix="temoto-pausepath-"))
    listener = _Listener(family["device"]["link"])
    host = SimHost(family["device"], host_env)
    robot: subprocess.Popen[str] | None = None
    try:
        profile = {
            "robot": f"pause_{family_name}",
            "sim": False,
            "devices": {"base": host.config},
            "features": {"navigation": family["navigation"]},
        }
        (work / "profile.json").write_text(json.dumps(profile))
        (work / "mission.json").write_text(json.dumps(_mission(family["goal"])))
        argv = [sys.executable, "-m", "temoto.managers.robot", "--local"]
        argv += ["--profile", str(work / "profile.json"), "--mission", str(work / "mission.json")]
        robot = subprocess.Popen(
            argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env
        )
        out: dict[str, str] = {}
        moving = threading.Event()
        readers = [
            threading.Thread(
                target=slurp,
                args=(robot.stdout, out, "stdout", {"NavigateTo_0 RUNNING": moving}),
                daemon=True,
            ),
            threading.Thread(target=slurp, args=(robot.stderr, out, "stderr", {}), daemon=True),
        ]
        for reader in readers:
            reader.start()
        deadline = time.monotonic() + START_TIMEOUT
        while not moving.wait(0.05) and robot.poll() is None and time.monotonic() < deadline:
            pass
        if not moving.is_set():
            robot.kill()
            robot.wait()
            for reader in readers:
                reader.join(5)
            said = out.get("stderr", "")[-2000:]
            raise TimeoutError(
                f"the mission did not start (exit {robot.returncode}); the robot command's"
                f" stderr:\n{said}"
            )
        host.wait("acting")
        taken: list[dict[str, float]] = []
        for _ in range(pauses):
            time.sleep(DRIVE_BEFORE)
            if robot.poll() is not None:
                break
            robot.send_signal(signal.SIGSTOP)
            while not _all_stopped(robot.pid):
                time.sleep(0.001)
            stopped, stopped_mono = time.time(), time.monotonic()
            time.sleep(pause_s)
            cont, cont_mono = time.time(), time.monotonic()
            robot.send_signal(signal.SIGCONT)
            taken.append(
                {"stopped": stopped, "cont": cont, "stopped_mono": stopped_mono}
                | {"cont_mono": cont_mono}
            )
        try:
            rc: int | None = robot.wait(EXIT_TIMEOUT)
        except subprocess.TimeoutExpired:
            rc = None
        for reader in readers:
            reader.join(5)
        time.sleep(0.1)  # the last frames reach the listener
        return {
            "family": family_name,
            "pause_s": pause_s,
            "rc": rc,
            "pauses": taken,
            "frames": list(listener.frames),
            "states": list(host.states),
            "stdout": out.get("stdout", ""),
            "stderr": out.get("stderr", ""),
            "leftovers": marked_pids(mark) if rc is not None else [],
        }
    finally:
        if robot is not None and robot.poll() is None:
            robot.send_signal(signal.SIGCONT)
            robot.kill()
            robot.wait()
        host.close()
        listener.close()
        shutil.rmtree(work, ignore_errors=True)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m temoto.testing.pausepath FAMILY SECONDS [--pauses N] [--netns]``.

    Args:
        argv: The arguments.

    Returns:
        0 when the pauses ran (whatever the wire showed), 2 for bad arguments.
    """
    parser = argparse.ArgumentParser(prog="python -m temoto.testing.pausepath")
    parser.add_argument("family", choices=sorted(PAUSE_FAMILIES))
    parser.add_argument("seconds", type=float)
    parser.add_argument("--pauses", type=int, default=1)
    parser.add_argument("--netns", action="store_true", help="run inside unshare -n (root)")
    args = parser.parse_args(argv)
    if args.netns:
        inner = [sys.executable, "-m", "temoto.testing.pausepath", args.family, str(args.seconds)]
        inner += ["--pauses", str(args.pauses)]
        return in_netns(inner).returncode
    result = run_pauses(args.family, args.seconds, args.pauses)
    sys.stdout.write(json.dumps(result) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
