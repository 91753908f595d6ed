"""Engine events for the live view's clients: an instrument that fans them out to queues.

The :class:`EventHub` is an engine :class:`~temoto.core.instrument.Instrument`. Its hooks run
under the engine's lock, so they only build a small dict and append it to each subscriber's
bounded queue; nothing here calls the engine. A client that falls behind by more than its
queue loses the backlog and is told to re-synchronise (fetch a fresh snapshot) instead, so a
slow browser can never make the engine wait or the process grow.

The hub also keeps each run's **timeline**: one span per action run (start, end, the state it
ended in and its result: ``on_true``, ``on_false``, ... from the engine's
:meth:`~temoto.core.instrument.Instrument.node_result` hook), bounded per run and in the number
of runs, for the page's Gantt chart.
"""

from __future__ import annotations

import threading
from collections import deque
from typing import TYPE_CHECKING, Any, final

from temoto.core.instrument import Instrument

if TYPE_CHECKING:
    from temoto.core.states import NodeState, Result

__all__ = ["Batch", "EventHub", "Subscription"]

#: Longest error text an event carries (the full error is in the run's snapshot).
MAX_ERROR_CHARS = 500

#: Runs whose timeline is kept (the oldest are dropped), and spans kept per run.
MAX_TIMELINES = 50
MAX_SPANS = 5000

_ACTIVE = frozenset({"RUNNING", "PAUSE_REQUESTED", "PAUSED", "STOPPING"})


def span_result(span: dict[str, Any]) -> str | None:
    """A span's result: the one the engine gave, else what its states tell, else None.

    The engine's ``node_result`` hook gives every ended run's result (``on_true``,
    ``on_false``, ``on_stopped``, ``on_error``); a span it did not reach (a run that ended
    before the hub was an instrument) falls back to its states: ``on_error`` for ERROR,
    ``on_stopped`` for a stopped run, otherwise not known.

    Args:
        span: A timeline span.

    Returns:
        The result's name, or None.
    """
    given = span.get("result")
    if isinstance(given, str):
        return given
    if span["state"] == "ERROR":
        return "on_error"
    if span["state"] == "FINISHED" and span.get("stopping"):
        return "on_stopped"
    return None


@final
class Batch:
    """What a subscriber receives in one wait.

    Attributes:
        events: The events, oldest first (each a JSON-ready dict with ``seq`` and ``kind``).
        resync: Events were dropped: the client must fetch fresh snapshots.
        closed: The hub closed (or the subscription was cancelled): stop reading.
    """

    __slots__ = ("closed", "events", "resync")

    def __init__(self, events: list[dict[str, Any]], resync: bool, closed: bool) -> None:
        self.events = events
        self.resync = resync
        self.closed = closed


@final
class Subscription:
    """One client's queue of events (made by :meth:`EventHub.subscribe`).

    Args:
        hub: The hub it belongs to.
        size: How many events it keeps before it overflows.
    """

    def __init__(self, hub: EventHub, size: int) -> None:
        self._hub = hub
        self._queue: deque[dict[str, Any]] = deque()
        self._size = size
        self._overflowed = False
        self._cancelled = False

    def _push(self, event: dict[str, Any]) -> None:
        # hub lock held
        if len(self._queue) >= self._size:
            self._queue.clear()
            self._overflowed = True
        else:
            self._queue.append(event)

    def get(self, timeout: float | None) -> Batch:
        """Wait for events.

        Args:
            timeout: Seconds to wait at most (None: until something happens).

        Returns:
            The events that arrived (possibly none, after the timeout).
        """
        return self._hub._take(self, timeout)

    def cancel(self) -> None:
        """Stop this subscription (wakes a waiting :meth:`get`; idempotent).

        Returns:
            None.
        """
        self._hub._remove(self)


@final
class EventHub(Instrument):
    """Fans engine events out to a bounded number of subscribers, each with a bounded queue.

    Events (JSON-ready dicts, ``seq`` increasing by one per event):

    * ``{"kind": "node", "graph", "node", "old", "state", "t"}``: a node changed state; the
      change that ends a node's run (to ``FINISHED`` or ``ERROR``) also has ``"result"``
      (``on_true``, ``on_false``, ``on_stopped`` or ``on_error``: which branch its children
      take);
    * ``{"kind": "graph", "graph", "state": "RUNNING", "t"}``: a run started;
    * ``{"kind": "graph", "graph", "state": "ENDED", "result", "t"}``: a run ended;
    * ``{"kind": "failed", "graph", "node", "error"}``: an action raised.

    Args:
        max_clients: Subscribers allowed at once.
        queue_size: Events a subscriber may have waiting before it must re-synchronise.

    Raises:
        ValueError: If a bound is smaller than 1.
    """

    def __init__(self, max_clients: int = 8, queue_size: int = 1000) -> None:
        if max_clients < 1 or queue_size < 1:
            raise ValueError("max_clients and queue_size must be at least 1")
        self.max_clients = max_clients
        self.queue_size = queue_size
        self._cond = threading.Condition()
        self._subs: list[Subscription] = []
        self._seq = 0
        self._closed = False
        self._timelines: dict[str, dict[str, Any]] = {}
        self._results: dict[tuple[str, str], str] = {}  # node results until their change
        self._earlier: dict[str, dict[str, Any]] = {}  # ended runs whose name was used again

    # ------------------------------------------------------------------ subscribers

    def subscribe(self) -> Subscription | None:
        """Add a subscriber.

        Returns:
            Its subscription, or None when ``max_clients`` are subscribed or the hub closed.
        """
        with self._cond:
            if self._closed or len(self._subs) >= self.max_clients:
                return None
            sub = Subscription(self, self.queue_size)
            self._subs.append(sub)
            return sub

    @property
    def subscribers(self) -> int:
        """How many subscribers there are now."""
        with self._cond:
            return len(self._subs)

    def close(self) -> None:
        """Close: every waiting subscriber wakes and is told to stop; later events are dropped.

        Returns:
            None.
        """
        with self._cond:
            self._closed = True
            for sub in self._subs:
                sub._cancelled = True
            self._subs.clear()
            self._cond.notify_all()

    def _remove(self, sub: Subscription) -> None:
        with self._cond:
            sub._cancelled = True
            if sub in self._subs:
                self._subs.remove(sub)
            self._cond.notify_all()

    def _take(self, sub: Subscription, timeout: float | None) -> Batch:
        with self._cond:
            self._cond.wait_for(
                lambda: bool(sub._queue) or sub._overflowed or sub._cancelled, timeout
            )
            events = list(sub._queue)
            sub._queue.clear()
            resync, sub._overflowed = sub._overflowed, False
            return Batch(events, resync, sub._cancelled)

    def timeline(self, graph: str) -> dict[str, Any] | None:
        """A run's timeline (copied), or None for a run it has not seen start.

        Args:
            graph: The run's name.

        Returns:
            ``{"start": t, "end": t or None, "spans": [{"node", "start", "end", "state",
            "result"}]}`` in engine clock seconds; a running span has ``end`` None.
        """
        with self._cond:
            line = self._timelines.get(graph)
            if line is None:
                return None
            spans = [
                {
                    "node": sp["node"],
                    "start": sp["start"],
                    "end": sp["end"],
                    "state": sp["state"],
                    "result": span_result(sp),
                }
                for sp in line["spans"]
            ]
            return {"start": line["start"], "end": line["end"], "spans": spans}

    def earlier_runs(self) -> list[dict[str, Any]]:
        """The ended runs whose name a later run took (the engine forgot them), oldest first.

        Returns:
            ``[{"name": "<run> #<k>", "run": "<run>", "result", "timeline"}]``: ``k`` counts
            the runs of that name from 1; ``timeline`` as :meth:`timeline` gives it. At most
            ``MAX_TIMELINES`` are kept.
        """
        with self._cond:
            return [dict(e) for e in self._earlier.values()]

    def _archive(self, graph: str, line: dict[str, Any]) -> None:
        # hub lock held: an ended run's name is used again; keep its timeline under a new name
        k = 1 + sum(1 for e in self._earlier.values() if e["run"] == graph)
        name = f"{graph} #{k}"
        while len(self._earlier) >= MAX_TIMELINES:
            del self._earlier[next(iter(self._earlier))]
        spans = [
            {
                "node": sp["node"],
                "start": sp["start"],
                "end": sp["end"],
                "state": sp["state"],
                "result": span_result(sp),
            }
            for sp in line["spans"]
        ]
        self._earlier[name] = {
            "name": name,
            "run": graph,
            "result": line.get("result"),
            "timeline": {"start": line["start"], "end": line["end"], "spans": spans},
        }

    def _record(self, graph: str, node: str, old: str, new: str, t: float) -> None:
        # hub lock held
        line = self._timelines.get(graph)
        if line is None:  # a run started before the view: its spans from now on
            line = self._new_timeline(graph, t)
        spans: list[dict[str, Any]] = line["spans"]
        open_span = line["open"].get(node)
        if new == "RUNNING" and open_span is None:
            if len(spans) >= MAX_SPANS:
                return
            open_span = {"node": node, "start": t, "end": None, "state": new}
            spans.append(open_span)
            line["open"][node] = open_span
            return
        if new == "BYPASSED" and len(spans) < MAX_SPANS:
            spans.append({"node": node, "start": t, "end": t, "state": new})
            return
        if open_span is None:
            return
        open_span["state"] = new
        if new == "STOPPING":
            open_span["stopping"] = True
        if new not in _ACTIVE:
            open_span["end"] = t
            del line["open"][node]

    def _new_timeline(self, graph: str, t: float) -> dict[str, Any]:
        while len(self._timelines) >= MAX_TIMELINES:
            del self._timelines[next(iter(self._timelines))]
        line: dict[str, Any] = {"start": t, "end": None, "spans": [], "open": {}}
        self._timelines[graph] = line
        return line

    def _publish(self, event: dict[str, Any]) -> None:
        # called with the engine lock held: append and notify, nothing more
        with self._cond:
            if not self._subs:
                return
            self._seq += 1
            event["seq"] = self._seq
            for sub in self._subs:
                sub._push(event)
            self._cond.notify_all()

    # ------------------------------------------------------------------ engine hooks

    def graph_started(self, graph: str, t: float) -> None:
        """Publish a run's start."""
        with self._cond:
            old = self._timelines.pop(graph, None)  # a name used again: a new timeline
            if old is not None and old["end"] is not None:
                self._archive(graph, old)  # the earlier run stays listed
            self._new_timeline(graph, t)
        self._publish({"kind": "graph", "graph": graph, "state": "RUNNING", "t": t})

    def node_result(self, graph: str, node: str, result: Result, t: float) -> None:
        """Keep a node's result for its run's span and for the state change that comes next."""
        with self._cond:
            self._results[(graph, node)] = result.value
            line = self._timelines.get(graph)
            open_span = line["open"].get(node) if line is not None else None
            if open_span is not None:
                open_span["result"] = result.value

    def node_transition(
        self, graph: str, node: str, old: NodeState, new: NodeState, t: float
    ) -> None:
        """Publish a node's state change (and add it to the run's timeline)."""
        with self._cond:
            self._record(graph, node, old.value, new.value, t)
            result = self._results.pop((graph, node), None)
        event: dict[str, Any] = {
            "kind": "node",
            "graph": graph,
            "node": node,
            "old": old.value,
            "state": new.value,
            "t": t,
        }
        if result is not None:
            event["result"] = result
        self._publish(event)

    def graph_finished(self, graph: str, result: Result, t: float) -> None:
        """Publish a run's end."""
        with self._cond:
            line = self._timelines.get(graph)
            if line is not None:
                line["end"] = t
                line["result"] = result.value
        self._publish(
            {"kind": "graph", "graph": graph, "state": "ENDED", "result": result.value, "t": t}
        )

    def action_failed(self, graph: str, node: str, error: BaseException) -> None:
        """Publish an action's failure (its text, cut to ``MAX_ERROR_CHARS``)."""
        text = f"{type(error).__name__}: {error}"[:MAX_ERROR_CHARS]
        self._publish({"kind": "failed", "graph": graph, "node": node, "error": text})
