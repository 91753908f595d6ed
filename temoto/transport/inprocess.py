"""In-process transport: every instance on the same bus name in one process hears the others.

This is python-can's virtual channel for fleets: tests (and demos) run several TeMoto instances
in one process, each with its own :class:`InProcessTransport` on a shared bus name, and they
exchange messages as robots do over LCM multicast, own messages included. Each instance delivers
on one dispatch thread of its own (``temoto-inproc-<bus>``), so handlers never run on the
publisher's thread, as with LCM.

The bus registry is module state, acceptable for a test bus only (docs/development.md §10) and
guarded by a lock; :func:`live_buses` reports what is open, for leak checks.
"""

from __future__ import annotations

import collections
import threading
from typing import final

from temoto.transport.base import Handler, QueuedSubscription, Transport

__all__ = ["InProcessSubscription", "InProcessTransport", "live_buses"]

_registry: dict[str, list[InProcessTransport]] = {}
_registry_lock = threading.Lock()


def live_buses() -> dict[str, int]:
    """List the open in-process transports, for leak checks.

    Returns:
        Bus name to the number of open instances on it (buses without any are left out).
    """
    with _registry_lock:
        return {bus: len(members) for bus, members in _registry.items() if members}


@final
class InProcessSubscription(QueuedSubscription):
    """A subscription of an :class:`InProcessTransport`, with its own bounded queue.

    Attributes:
        channel: The channel name.
        queue_capacity: The most messages that wait for the handler (None: no limit).
    """

    def __init__(
        self,
        transport: InProcessTransport,
        channel: str,
        handler: Handler,
        queue_capacity: int | None,
    ) -> None:
        super().__init__(channel, handler, queue_capacity)
        self._transport = transport

    def _on_unsubscribe(self) -> None:
        self._transport._remove(self)


@final
class InProcessTransport(Transport):
    """A transport connecting every instance on the same bus name in this process.

    Args:
        bus: The bus name; instances with equal names see each other's messages and their own.

    Raises:
        ValueError: If ``bus`` is empty.
    """

    def __init__(self, bus: str = "default") -> None:
        if not isinstance(bus, str) or not bus:
            raise ValueError(f"bus name must be a non-empty string, got {bus!r}")
        super().__init__()
        self.bus = bus
        self._cond = threading.Condition()
        # Guarded by _cond: subscriptions by channel, and one token per message waiting in a
        # subscription's queue, in arrival order across subscriptions (a full queue drops its
        # oldest message and keeps its token count, so the tokens stay bounded too).
        self._subs: dict[str, list[InProcessSubscription]] = {}
        self._ready: collections.deque[InProcessSubscription] = collections.deque()
        self._busy = False  # the dispatcher is running a handler
        self._stopping = False
        self._thread = threading.Thread(target=self._run, name=f"temoto-inproc-{bus}", daemon=True)
        with _registry_lock:
            _registry.setdefault(bus, []).append(self)
        self._thread.start()

    def __repr__(self) -> str:
        state = "closed" if self.closed else "open"
        return f"<InProcessTransport bus={self.bus!r} {state}>"

    @property
    def channels(self) -> frozenset[str]:
        """The channels this member has active subscriptions on."""
        with self._cond:
            return frozenset(self._subs)

    def flush(self, timeout: float | None = None) -> bool:
        """Wait until every message queued for this member so far has been handled.

        Messages are queued when they are published, so after ``publish`` returns on any
        member of the bus, ``flush`` on the receiver waits for their handlers (tests use it
        instead of sleeping).

        Args:
            timeout: Seconds to wait at most, or None.

        Returns:
            True if everything was handled, False on timeout or when closed.
        """
        with self._cond:
            return (
                self._cond.wait_for(
                    lambda: self._stopping or (not self._ready and not self._busy), timeout
                )
                and not self._stopping
            )

    # --- Transport hooks ----------------------------------------------------------------------

    def _publish(self, channel: str, data: bytes) -> None:
        with _registry_lock:
            members = list(_registry.get(self.bus, ()))
        for member in members:
            member._enqueue(channel, data)

    def _subscribe(
        self, channel: str, handler: Handler, queue_capacity: int | None
    ) -> InProcessSubscription:
        sub = InProcessSubscription(self, channel, handler, queue_capacity)
        with self._cond:
            self._subs.setdefault(channel, []).append(sub)
        return sub

    def _close(self) -> None:
        with _registry_lock:
            members = _registry.get(self.bus, [])
            if self in members:
                members.remove(self)
            if not members:
                _registry.pop(self.bus, None)
        with self._cond:
            self._stopping = True
            subs = [sub for subs in self._subs.values() for sub in subs]
            self._subs.clear()
            self._ready.clear()
            self._cond.notify_all()
        for sub in subs:
            sub.detach()
        if threading.current_thread() is not self._thread:
            self._thread.join()

    # --- internals ----------------------------------------------------------------------------

    def _enqueue(self, channel: str, data: bytes) -> None:
        with self._cond:
            if self._stopping:
                return
            for sub in self._subs.get(channel, ()):
                sub.offer(data, self._ready)
            self._cond.notify_all()  # the dispatcher, and flushes waiting

    def _remove(self, sub: InProcessSubscription) -> None:
        with self._cond:
            subs = self._subs.get(sub.channel)
            if subs is not None and sub in subs:
                subs.remove(sub)
                if not subs:
                    del self._subs[sub.channel]
            # Its tokens stay in _ready; the dispatcher skips them (the queue is empty).
            sub.discard_pending()

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._ready and not self._stopping:
                    self._cond.wait()
                if self._stopping:
                    return
                sub = self._ready.popleft()
                data = sub.take()
                if data is None:
                    if not self._ready:
                        self._cond.notify_all()  # a flush may be waiting
                    continue
                self._busy = True
            try:
                self._deliver(sub, sub.channel, data)
            finally:
                with self._cond:
                    self._busy = False
                    if not self._ready:
                        self._cond.notify_all()
