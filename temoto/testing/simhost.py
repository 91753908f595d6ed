"""One device simulator in a process of its own, reporting the device's state on every change.

Run it as ``python -m temoto.testing.simhost DEVICE-ENTRY-JSON``: the argument is a profile's
device entry (``{"driver": "odrive_can", "link": {...}, "nodes": [...]}``). The host builds the
simulator with the driver's own ``simulate()`` (so the entry's simulator settings, watchdogs
included, apply), starts it, and prints JSON lines on standard output:

* first ``{"config": {...}}``: the entry a driver in *another* process uses to reach the
  simulator (for Dynamixel the pseudo-terminal's path, for MAVLink the UDP port; for CAN the
  same entry: give it a link that crosses processes, python-can's ``udp_multicast``);
* then ``{"t": <CLOCK_MONOTONIC seconds>, "active": bool, "safe": bool, "state": {...}}``
  whenever the device's state changes (read every :data:`PERIOD` seconds), and once at start.

``active`` says the device acts (every ODrive axis in CLOSED_LOOP_CONTROL, every MIT motor in
motor mode, every Dynamixel servo's torque on, the vehicle armed; a Dynamixel chain's state
also says which servos move and their goals, in ticks); ``safe`` says it is in a
safe state as ``docs/safety.md`` defines them (every axis IDLE; every MIT motor out of motor
mode or commanded zero torque; every servo's torque off or stopped by its Bus Watchdog; the
vehicle disarmed, on the ground, or in a hold, land or return mode). This is what a person
watching the device sees; the robot process under test never talks to the host except over
the device's own link.

Commands on standard input, one per line: ``inject FAULT [KEY=VALUE]...``, ``clear [FAULT]``,
``quit``. Each is answered ``{"ok": ...}`` or ``{"error": ...}``. The host stops at ``quit``,
at the end of its input, and on SIGTERM or SIGINT (exit 0).

The exit-path tests and the ``safe_stop_ms`` benchmark (:mod:`temoto.testing.exitpaths`) use
it: a SIGKILL of the robot process leaves the simulator running, so the device's watchdog can be
seen doing its work.
"""

from __future__ import annotations

import json
import sys
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any, Final

from temoto.cli.signals import stop_on_signals
from temoto.clock import MonotonicClock
from temoto.drivers import driver_class
from temoto.drivers.sim import Simulator

__all__ = ["PERIOD", "main", "snapshot"]

#: Seconds between two reads of the device's state.
PERIOD: Final = 0.002

#: MAVLink modes that hold, land or return: safe for a vehicle in the air.
SAFE_MODES: Final = frozenset({"LOITER", "BRAKE", "LAND", "RTL", "SMART_RTL", "POSHOLD"})


def _odrive(sim: Any) -> tuple[bool, bool, dict[str, Any]]:
    from temoto.drivers.can_motor import cansimple as cs

    states = {str(n): cs.AxisState(a.state).name for n, a in sorted(sim.axes.items())}
    values = set(states.values())
    return values == {"CLOSED_LOOP_CONTROL"}, values == {"IDLE"}, {"axes": states}


def _mit(sim: Any) -> tuple[bool, bool, dict[str, Any]]:
    motors = list(sim.motors.values())
    enabled = {str(m.motor_id): bool(m.enabled) for m in motors}
    # zero gains and feed-forward: no torque, in or out of motor mode (a CAN timeout of the
    # motor controller zeroes the command and stays in motor mode)
    zero = {str(m.motor_id): m.command.kp == m.command.kd == m.command.t == 0 for m in motors}
    safe = all(not enabled[i] or zero[i] for i in enabled)
    return all(enabled.values()), safe, {"motor_mode": enabled, "zero_torque": zero}


#: The X series' Moving register (ROBOTIS e-Manual, XM430-W350 control table, address 122).
_DXL_MOVING: Final = 122


def _dynamixel(sim: Any) -> tuple[bool, bool, dict[str, Any]]:
    from temoto.drivers.dynamixel import control_table as ct

    torque = {str(i): sim.read_register(i, ct.TORQUE_ENABLE.address) for i in sim.ids}
    # the Bus Watchdog's expiry stops a servo with its torque on (e-Manual, address 98)
    expired = {
        str(i): sim.read_register(i, ct.BUS_WATCHDOG.address) in (ct.BUS_WATCHDOG_ERROR, 0xFF)
        for i in sim.ids
    }
    active = all(torque.values()) and not any(expired.values())
    safe = all(not torque[i] or expired[i] for i in torque)
    # motion (the stop and pause tests): Moving (e-Manual, address 122) and the goal, in ticks
    moving = {str(i): bool(sim.read_register(i, _DXL_MOVING)) for i in sim.ids}
    goal = {str(i): sim.read_register(i, ct.GOAL_POSITION.address) for i in sim.ids}
    state = {"torque": torque, "watchdog_expired": expired, "moving": moving, "goal": goal}
    return active, safe, state


def _mavlink(sim: Any) -> tuple[bool, bool, dict[str, Any]]:
    armed, airborne, mode = bool(sim.armed), bool(sim.airborne), str(sim.mode)
    safe = not armed or not airborne or mode in SAFE_MODES
    return armed, safe, {"armed": armed, "airborne": airborne, "mode": mode}


_SNAPSHOTS: Final[Mapping[str, Callable[[Any], tuple[bool, bool, dict[str, Any]]]]] = {
    "odrive_can": _odrive,
    "mit_can": _mit,
    "dynamixel": _dynamixel,
    "mavlink": _mavlink,
}


def snapshot(kind: str, sim: Simulator) -> tuple[bool, bool, dict[str, Any]]:
    """``(active, safe, state)`` of a running simulator (see the module docstring).

    Args:
        kind: The driver's profile name (``odrive_can``, ``mit_can``, ``dynamixel``,
            ``mavlink``).
        sim: Its simulator.

    Returns:
        Whether the device acts, whether it is safe, and its state as JSON values.

    Raises:
        ValueError: An unknown ``kind``.
    """
    try:
        read = _SNAPSHOTS[kind]
    except KeyError:
        raise ValueError(f"no snapshot for driver {kind!r}") from None
    return read(sim)


def _emit(line: Mapping[str, Any], lock: threading.Lock) -> None:
    text = json.dumps(line, sort_keys=True)
    with lock:
        sys.stdout.write(text + "\n")
        sys.stdout.flush()


def _command(sim: Simulator, words: list[str]) -> dict[str, Any]:
    if words[0] == "inject" and len(words) >= 2:
        params: dict[str, Any] = {}
        for word in words[2:]:
            key, _, value = word.partition("=")
            params[key] = int(value) if value.lstrip("-").isdigit() else value
        sim.inject(words[1], **params)
    elif words[0] == "clear":
        sim.clear(*words[1:2])
    else:
        raise ValueError(f"unknown command {' '.join(words)!r}")
    return {"ok": " ".join(words)}


def main(argv: list[str] | None = None) -> int:
    """Run the host (see the module docstring).

    Args:
        argv: ``[DEVICE-ENTRY-JSON]``.

    Returns:
        The exit status (0; 2 for a bad argument).
    """
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        sys.stderr.write("usage: python -m temoto.testing.simhost DEVICE-ENTRY-JSON\n")
        return 2
    entry = json.loads(args[0])
    kind = str(entry["driver"])
    cls: Any = driver_class(kind)
    config = {k: v for k, v in entry.items() if k != "driver"}
    sim, settings = cls.simulate("device", config, clock=MonotonicClock())
    stop = threading.Event()
    lock = threading.Lock()
    # set on a thread of its own: a handler setting it could interrupt stop.wait() and hang
    with stop_on_signals(stop), sim:
        _emit({"config": {"driver": kind, **settings}}, lock)
        reader = threading.Thread(target=_read_commands, args=(sim, stop, lock), daemon=True)
        reader.start()
        last: tuple[bool, bool, dict[str, Any]] | None = None
        while not stop.is_set():
            now = snapshot(kind, sim)
            if now != last:
                active, safe, state = now
                _emit({"t": time.monotonic(), "active": active, "safe": safe, "state": state}, lock)
                last = now
            stop.wait(PERIOD)
    return 0


def _read_commands(sim: Simulator, stop: threading.Event, lock: threading.Lock) -> None:
    for line in sys.stdin:
        words = line.split()
        if not words:
            continue
        if words == ["quit"]:
            break
        try:
            reply = _command(sim, words)
        except Exception as err:  # a bad command is answered, never fatal
            reply = {"error": str(err)}
        _emit(reply, lock)
    stop.set()


if __name__ == "__main__":
    sys.exit(main())
