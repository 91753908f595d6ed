"""Helpers of the RIS and remote-resource tests: robots on an in-process bus, a raw member."""

from __future__ import annotations

import os
import select
import threading
from collections.abc import Callable
from contextlib import ExitStack
from dataclasses import dataclass
from typing import Any

from temoto.core.registrar import Registrar
from temoto.fleet.resources import RemoteResources
from temoto.fleet.ris import ResourceInfoSync
from temoto.managers.process import ProcessManager
from temoto.transport import FleetAuth, FleetLink, InProcessTransport, codec

KEY = bytes(range(32))
FLEET = "ris-fleet"
WAIT_S = 5.0


class Got:
    """Records callback calls and waits for them (on a condition, no polling)."""

    def __init__(self) -> None:
        self.calls: list[tuple[Any, ...]] = []
        self.threads: list[str] = []
        self._cond = threading.Condition()

    def __call__(self, *args: Any) -> None:
        with self._cond:
            self.calls.append(args)
            self.threads.append(threading.current_thread().name)
            self._cond.notify_all()

    def wait_for(self, count: int, timeout: float = WAIT_S) -> list[tuple[Any, ...]]:
        with self._cond:
            ok = self._cond.wait_for(lambda: len(self.calls) >= count, timeout)
            assert ok, f"got {len(self.calls)} of {count} calls: {self.calls}"
            return list(self.calls)

    def wait_until(
        self, pred: Callable[[list[tuple[Any, ...]]], bool], timeout: float = WAIT_S
    ) -> list[tuple[Any, ...]]:
        with self._cond:
            ok = self._cond.wait_for(lambda: pred(self.calls), timeout)
            assert ok, f"condition not met by {len(self.calls)} calls: {self.calls}"
            return list(self.calls)

    def quiet_for(self, count: int, seconds: float) -> bool:
        """True if fewer than ``count`` calls arrived within ``seconds``."""
        with self._cond:
            return not self._cond.wait_for(lambda: len(self.calls) >= count, seconds)


class Raw:
    """A hand-driven fleet member: sends any message, records what comes on a channel."""

    def __init__(self, link: FleetLink, channel: str) -> None:
        self.link = link
        self.channel = channel
        self.got = Got()
        link.listen(channel, lambda opened: self.got(opened))

    def send(self, msg: Any, channel: str | None = None) -> None:
        self.link.send(channel or self.channel, *codec.encode(msg))

    def send_raw(self, type_name: str, payload: bytes, channel: str | None = None) -> None:
        self.link.send(channel or self.channel, type_name, payload)

    def decoded(self, type_name: str | None = None) -> list[Any]:
        return [
            codec.decode(o.type, o.payload)
            for (o,) in self.got.calls
            if type_name is None or o.type == type_name
        ]

    def wait_type(self, type_name: str, count: int = 1, timeout: float = WAIT_S) -> list[Any]:
        self.got.wait_until(
            lambda calls: sum(o.type == type_name for (o,) in calls) >= count, timeout
        )
        return self.decoded(type_name)


@dataclass
class Robot:
    name: str
    link: FleetLink
    registrar: Registrar
    ris: ResourceInfoSync
    remote: RemoteResources | None
    processes: ProcessManager | None


class Fleet:
    """Makes fleet members on one in-process bus; all are closed when the test ends."""

    def __init__(self, bus: str, stack: ExitStack) -> None:
        self.bus = bus
        self.stack = stack

    def link(self, sender: str) -> FleetLink:
        transport = self.stack.enter_context(InProcessTransport(self.bus))
        return FleetLink(transport, FleetAuth(FLEET, sender, KEY))

    def raw(self, sender: str, channel: str) -> Raw:
        return Raw(self.link(sender), channel)

    def robot(
        self,
        name: str,
        *,
        processes: bool = False,
        remote: bool = True,
        period_s: float = 0.1,
        missed: int = 3,
        share: list[str] | None = None,
        stack: ExitStack | None = None,
        **remote_args: Any,
    ) -> Robot:
        """A robot: registrar, optional process manager, RIS and remote resources.

        ``stack``: close it there instead of at the end of the test (to "kill" it early).
        """
        stack = stack or self.stack
        link = self.link(name) if stack is self.stack else self._own_link(name, stack)
        registrar = Registrar(name)
        stack.callback(registrar.close)
        manager = None
        if processes:
            manager = ProcessManager(registrar, grace=2.0)
            stack.callback(manager.shutdown)
        ris = stack.enter_context(
            ResourceInfoSync(link, registrar, name, period_s=period_s, missed=missed, share=share)
        )
        rem = None
        if remote:
            rem = stack.enter_context(RemoteResources(link, registrar, ris, **remote_args))
        return Robot(name, link, registrar, ris, rem, manager)

    def _own_link(self, sender: str, stack: ExitStack) -> FleetLink:
        transport = stack.enter_context(InProcessTransport(self.bus))
        return FleetLink(transport, FleetAuth(FLEET, sender, KEY))


def wait_exit(pid: int, timeout: float = WAIT_S) -> bool:
    """Wait (on a pidfd, no polling) until a process has exited; True if it did in time."""
    try:
        fd = os.pidfd_open(pid)
    except ProcessLookupError:
        return True
    try:
        return bool(select.select([fd], [], [], timeout)[0])
    finally:
        os.close(fd)


def alive(pid: int) -> bool:
    """True if the process exists and has not exited (a zombie counts as exited)."""
    return not wait_exit(pid, 0)
