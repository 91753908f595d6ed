"""An in-memory :class:`~temoto.core.remote.ActorLink` for tests of shared graphs.

Several engines in one process share a :class:`MemoryFleet`; each gets its own link with
:meth:`MemoryFleet.link`. Handshakes complete when every participant has called
``handshake`` for the same (graph, session); notifications reach the other links' expectations
and are acknowledged at once, unless the receiving actor was made deaf with :meth:`MemoryFleet.
silence`; :meth:`MemoryFleet.lose` reports an actor lost to everyone watching it. Callbacks run
on the fleet's own thread (``temoto-memfleet``), as a real link's run on its receive thread.
"""

from __future__ import annotations

import functools
import queue
import threading
from collections.abc import Callable, Mapping, Sequence
from typing import Any

from temoto.core.remote import Cancel, RemoteResult
from temoto.core.states import Result
from temoto.errors import FleetError

__all__ = ["MemoryActorLink", "MemoryFleet"]

_Key = tuple[str, str, str, str]  # graph, session, action, actor


class _Watcher:
    """One watch: actors, the run watched for, the callbacks."""

    def __init__(
        self,
        actors: Sequence[str],
        run: tuple[str, str],
        on_lost: Callable[[str, str], None],
        on_end: Callable[[str, Result], None] | None,
        on_abort: Callable[[str, str], None] | None,
    ) -> None:
        self.actors = frozenset(actors)
        self.run = run
        self.on_lost = on_lost
        self.on_end = on_end
        self.on_abort = on_abort


class MemoryFleet:
    """The shared state of the in-memory links of one test (close it when done)."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        #: (graph, session) -> actor -> how many handshakes it began for that session
        self._joined: dict[tuple[str, str], dict[str, int]] = {}
        self._results: dict[_Key, tuple[Result, dict[str, Any]]] = {}
        self._waiters: dict[_Key, list[RemoteResult]] = {}
        self._watchers: list[_Watcher] = []
        self._deaf: set[str] = set()
        self._lost: dict[str, str] = {}  # actor -> why it was lost
        self._calls: queue.SimpleQueue[Callable[[], None] | None] = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._deliver, name="temoto-memfleet", daemon=True)
        self._thread.start()

    def link(self, actor: str) -> MemoryActorLink:
        """A link for one actor.

        Args:
            actor: The actor's name.

        Returns:
            The link.
        """
        return MemoryActorLink(self, actor)

    def silence(self, actor: str) -> None:
        """Make ``actor`` stop acknowledging notifications (its notifiers time out).

        Args:
            actor: The actor.
        """
        with self._cond:
            self._deaf.add(actor)

    def lose(self, actor: str, reason: str = "silent") -> None:
        """Report ``actor`` lost to everyone watching it.

        Args:
            actor: The actor.
            reason: Why.
        """
        with self._cond:
            self._lost.setdefault(actor, reason)
            watchers = [w for w in self._watchers if actor in w.actors]
        for w in watchers:
            self._calls.put(functools.partial(w.on_lost, actor, reason))

    def close(self) -> None:
        """Stop the delivery thread."""
        self._calls.put(None)
        self._thread.join(5.0)

    # ---- used by the links --------------------------------------------------------------

    def _deliver(self) -> None:
        while True:
            call = self._calls.get()
            if call is None:
                return
            call()

    def _handshake(
        self, actor: str, graph: str, session: str, actors: Sequence[str], timeout: float
    ) -> str:
        key = (graph, session)
        with self._cond:
            rounds = self._joined.setdefault(key, {})
            mine = rounds[actor] = rounds.get(actor, 0) + 1  # a re-run of a session: a new round
            self._cond.notify_all()
            ok = self._cond.wait_for(lambda: all(rounds.get(a, 0) >= mine for a in actors), timeout)
            if not ok:
                missing = sorted(a for a in actors if rounds.get(a, 0) < mine)
                raise FleetError(f"handshake for {graph}: no answer from {', '.join(missing)}")
            return f"{session}#{mine}"  # the same on every participant of this round

    def _notify(
        self,
        sender: str,
        graph: str,
        session: str,
        action: str,
        result: Result,
        outputs: Mapping[str, Any],
        actors: Sequence[str],
    ) -> None:
        key = (graph, session, action, sender)
        with self._cond:
            lost = sorted(set(actors) & self._lost.keys())
            if lost:  # the same words as the engine's report of the loss, whichever comes first
                why = ", ".join(f"actor '{a}' was lost ({self._lost[a]})" for a in lost)
                raise FleetError(f"{action}: {why}")
            deaf = sorted(set(actors) & self._deaf)
            if deaf:
                raise FleetError(f"{action}: no acknowledgement from {', '.join(deaf)}")
            self._results[key] = (result, dict(outputs))
            waiters = self._waiters.pop(key, [])
        for on_result in waiters:
            self._calls.put(functools.partial(on_result, result, dict(outputs)))

    def _expect(self, key: _Key, on_result: RemoteResult) -> Cancel:
        with self._cond:
            stored = self._results.get(key)
            if stored is None:
                self._waiters.setdefault(key, []).append(on_result)
        if stored is not None:
            self._calls.put(lambda: on_result(stored[0], dict(stored[1])))

        def cancel() -> None:
            with self._cond:
                waiting = self._waiters.get(key, [])
                if on_result in waiting:
                    waiting.remove(on_result)

        return cancel

    def _watch(self, entry: _Watcher) -> Cancel:
        actors = entry.actors
        on_lost = entry.on_lost
        with self._cond:
            self._watchers.append(entry)
            already = sorted(set(actors) & self._lost.keys())
        for actor in already:
            self._calls.put(functools.partial(on_lost, actor, "lost before the run"))

        def cancel() -> None:
            with self._cond:
                if entry in self._watchers:
                    self._watchers.remove(entry)

        return cancel

    def _end(
        self, actor: str, graph: str, session: str, result: Result | None, reason: str
    ) -> None:
        with self._cond:
            for key in [k for k in self._waiters if k[:2] == (graph, session)]:
                del self._waiters[key]
            watchers = [
                w for w in self._watchers if actor in w.actors and w.run == (graph, session)
            ]
        for w in watchers:
            if result is not None and w.on_end is not None:
                self._calls.put(functools.partial(w.on_end, actor, result))
            elif reason and w.on_abort is not None:
                self._calls.put(functools.partial(w.on_abort, actor, reason))


class MemoryActorLink:
    """One actor's link to a :class:`MemoryFleet` (see the module docstring).

    Args:
        fleet: The shared fleet.
        actor: This actor's name.
    """

    def __init__(self, fleet: MemoryFleet, actor: str) -> None:
        self._fleet = fleet
        self._actor = actor
        self.notified: list[tuple[str, Result]] = []  # (action, result) this actor sent

    @property
    def actor(self) -> str:
        """This actor's name."""
        return self._actor

    def handshake(self, graph: str, session: str, actors: Sequence[str], timeout: float) -> str:
        """See :meth:`temoto.core.remote.ActorLink.handshake` (run ids: ``session#round``)."""
        return self._fleet._handshake(self._actor, graph, session, actors, timeout)

    def notify(
        self,
        graph: str,
        session: str,
        action: str,
        result: Result,
        outputs: Mapping[str, Any],
        actors: Sequence[str],
        timeout: float,
    ) -> None:
        """See :meth:`temoto.core.remote.ActorLink.notify`."""
        self.notified.append((action, result))
        self._fleet._notify(self._actor, graph, session, action, result, outputs, actors)

    def expect(
        self, graph: str, session: str, action: str, actor: str, on_result: RemoteResult
    ) -> Cancel:
        """See :meth:`temoto.core.remote.ActorLink.expect`."""
        return self._fleet._expect((graph, session, action, actor), on_result)

    def watch(
        self,
        actors: Sequence[str],
        on_lost: Callable[[str, str], None],
        *,
        graph: str = "",
        session: str = "",
        on_end: Callable[[str, Result], None] | None = None,
        on_abort: Callable[[str, str], None] | None = None,
    ) -> Cancel:
        """See :meth:`temoto.core.remote.ActorLink.watch` (nobody falls silent here)."""
        actors = [a for a in actors if a != self._actor]
        watcher = _Watcher(actors, (graph, session), on_lost, on_end, on_abort)
        return self._fleet._watch(watcher)

    def end(
        self,
        graph: str,
        session: str,
        *,
        gave_up: bool = False,
        result: Result | None = None,
        reason: str = "",
    ) -> None:
        """See :meth:`temoto.core.remote.ActorLink.end`."""
        self._fleet._end(self._actor, graph, session, result, reason)
        if gave_up and not reason:
            self._fleet.lose(self._actor, "left")
