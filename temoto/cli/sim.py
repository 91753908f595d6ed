"""``temoto sim``: the device simulators as a standalone command, for real tools to use.

``temoto sim quad|odrive|mit|dynamixel ...`` starts one simulator; ``temoto sim --profile
FILE`` starts the simulator of every device of a hardware profile (each built by its driver's
``simulate()``, so the profile's simulator settings apply). Either way the command prints what
it serves, then keeps serving until SIGINT or SIGTERM, and exits 0 (docs/design.md §8: a
server stopped by a signal); invalid input is exit status 2 with a one-line message.

What it prints on standard output, per device, is the ``link`` line a profile uses to reach the
simulator from another process (``link: {interface: udp_multicast, channel: 239.74.163.2}``,
``link: serial:/dev/pts/7``, ``link: udpout:127.0.0.1:5760``), and how the usual tools connect
(MAVProxy, python-can's ``can.viewer``, a serial terminal); then a line whenever a client starts
or stops talking to a simulator (none of these links has a connect of its own: UDP, CAN and a
pseudo-terminal only show traffic), and, for a MAVLink vehicle, the first time each message
arrives. With ``--json`` standard output carries JSON lines only (one per endpoint, then one per
event) and the text goes to standard error. ``docs/simulators.md`` is the guide.

Kept apart from :mod:`temoto.cli` so that other commands import no driver code. Like
:mod:`temoto.cli`, this module prints.

The command is in three modules: :mod:`temoto.cli.sim_args` (the arguments),
:mod:`temoto.cli.sim_devices` (starting each simulator and describing its endpoint) and this one
(running: printing endpoints, watching traffic, stopping on a signal).
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from collections.abc import Iterator, Mapping, Sequence
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, Final

from temoto.cli.realism_opts import announce_realism, resolve_seed
from temoto.cli.sim_args import (
    DEFAULT_CAN_GROUP,
    DEFAULT_OUT,
    DEFAULT_PORT,
    add_sim,
    parse_udp_address,
)
from temoto.cli.sim_devices import Endpoint, Served, endpoint_for, serve_kind, serve_profile
from temoto.errors import ConfigError

__all__ = [
    "DEFAULT_CAN_GROUP",
    "DEFAULT_OUT",
    "DEFAULT_PORT",
    "Endpoint",
    "add_parser",
    "endpoint_for",
    "main",
    "parse_udp_address",
]

#: Seconds without traffic after which a client counts as gone (and its return as a new one).
QUIET_S: Final = 2.0
#: Real seconds between two looks at the simulators' traffic.
WATCH_PERIOD_S: Final = 0.1


def add_parser(sub: Any) -> None:
    """Add ``temoto sim`` and its forms (:func:`temoto.cli.sim_args.add_sim`)."""
    add_sim(sub)


class _Printer:
    """Text lines (and JSON lines with ``--json``) from several threads."""

    def __init__(self, as_json: bool, out: IO[str] | None = None) -> None:
        self.as_json = as_json
        self.out = out or sys.stdout
        self.text = sys.stderr if as_json else self.out
        self.broken = False  # a reader went away (``temoto sim quad | head -1``)
        self._lock = threading.Lock()

    def say(self, line: str, event: Mapping[str, Any] | None = None) -> None:
        with self._lock:
            if self.broken:
                return
            try:
                self.text.write(line + "\n")
                self.text.flush()
                if self.as_json and event is not None:
                    self.out.write(json.dumps(event, sort_keys=True) + "\n")
                    self.out.flush()
            except BrokenPipeError:
                self.broken = True


def main(args: argparse.Namespace, out: IO[str] | None = None) -> int:
    """Run ``temoto sim`` until SIGINT or SIGTERM.

    Args:
        args: The parsed arguments.
        out: Where endpoints and events go (default standard output).

    Returns:
        0 (stopped by a signal); 2 for invalid input (with a message on stderr).

    Raises:
        ConfigError: Invalid input (a bad profile, neither or both of KIND and --profile).
        BrokenPipeError: The reader of the output went away (the simulators are closed).
    """
    from temoto.cli.signals import FORCE_EXIT_S, SignalExit

    kind = getattr(args, "sim_kind", None)
    profile = getattr(args, "profile", None)
    if (kind is None) == (profile is None):
        raise ConfigError(
            "temoto sim: say what to simulate: a KIND (quad, odrive, mit, dynamixel) or"
            " --profile FILE, not both"
        )
    resolve_seed(args)
    announce_realism(args, sys.stderr)
    printer = _Printer(bool(getattr(args, "json", False)), out)
    with SignalExit(force_exit=FORCE_EXIT_S, force_exit_code=0) as signals, ExitStack() as stack:
        if kind is None:
            served = serve_profile(Path(str(profile)), args, stack)
        else:
            served = [serve_kind(str(kind), args, stack)]
        _announce(printer, served, profile)
        if printer.broken:
            raise BrokenPipeError("the reader of temoto sim's output went away")
        watcher = threading.Thread(
            target=_watch, args=(printer, served, signals.stop), name="temoto-sim-watch"
        )
        watcher.start()
        try:
            while not signals.stop.wait(WATCH_PERIOD_S) and not printer.broken:
                pass
        finally:
            signals.stop.set()
            watcher.join()
    if printer.broken:
        raise BrokenPipeError("the reader of temoto sim's output went away")
    return 0


def _announce(printer: _Printer, served: Sequence[Served], profile: str | None) -> None:
    if profile is not None:
        printer.say(
            f"temoto sim: {profile}: a copy of the profile with `sim: false` and these links"
            " drives the simulators from another process:"
        )
    for one in served:
        printer.say(one.endpoint.line(), {"endpoint": one.endpoint.json()})
        for tool in one.endpoint.tools:
            printer.say(f"  {tool}")
    printer.say("temoto sim: serving; Ctrl-C stops")


def _watch(printer: _Printer, served: Sequence[Served], stop: threading.Event) -> None:
    """Say when a client starts or stops talking to each simulator (and new MAVLink messages)."""
    state = {id(s): _Traffic() for s in served}
    while not stop.wait(WATCH_PERIOD_S):
        now = time.monotonic()
        for one in served:
            for line, event in state[id(one)].update(one.endpoint.device, one.traffic(), now):
                printer.say(line, event)


@dataclass
class _Traffic:
    """One simulator's traffic as last seen."""

    count: int = 0
    names: set[str] = field(default_factory=set)
    last: float | None = None  # when traffic was last seen (None: the client is quiet)

    def update(
        self, device: str, seen: tuple[int, set[str]], now: float
    ) -> Iterator[tuple[str, dict[str, Any]]]:
        count, names = seen
        if count > self.count:
            if self.last is None:
                yield (
                    f"{device}: a client is talking ({count - self.count} messages so far)",
                    {"event": "client", "device": device, "talking": True},
                )
            self.last = now
        elif self.last is not None and now - self.last >= QUIET_S:
            yield (
                f"{device}: the client went quiet ({QUIET_S:g} s without traffic)",
                {"event": "client", "device": device, "talking": False},
            )
            self.last = None
        for name in sorted(names - self.names):
            yield (
                f"{device}: first {name}",
                {"event": "message", "device": device, "name": name},
            )
        self.count = count
        self.names |= names


if __name__ == "__main__":  # python -m temoto.cli.sim: temoto sim, on its own
    from temoto.cli import command_main

    sys.exit(command_main("sim"))
