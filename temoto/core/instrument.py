"""Instruments: the engine's observability seam.

An :class:`Instrument` receives engine events through hooks that default to doing nothing.
The engine calls them **while it holds its lock**, in the order the events happen, so they must
be quick and must not call back into the engine; an instrument that raises is logged and
removed. Trace files, logging and test recorders are all instruments.
"""

from __future__ import annotations

import json
import logging
import threading
from typing import IO, TYPE_CHECKING

if TYPE_CHECKING:
    from temoto.core.states import NodeState, Result

__all__ = ["Instrument", "LoggingInstrument", "RecordingInstrument", "TraceInstrument"]


class Instrument:
    """Base class of engine observers; override the hooks you need."""

    def graph_started(self, graph: str, t: float) -> None:
        """A graph run started (``t``: clock seconds)."""

    def node_transition(
        self, graph: str, node: str, old: NodeState, new: NodeState, t: float
    ) -> None:
        """A node changed state (``node`` is ``<Name>_<instance_id>``)."""

    def graph_finished(self, graph: str, result: Result, t: float) -> None:
        """A graph run ended (finished, halted, stopped or failed) with ``result``."""

    def node_result(self, graph: str, node: str, result: Result, t: float) -> None:
        """A node's run ended with ``result``: which branch its children take.

        ``on_true``, ``on_false``, ``on_stopped`` or ``on_error`` (a sub-graph node: the
        sub-graph's result). Called just before the node's change to FINISHED (ERROR for
        ``on_error``), so the result tells which of its children's conditions apply.
        """

    def action_failed(self, graph: str, node: str, error: BaseException) -> None:
        """An action raised (its result is ``on_error``)."""


class LoggingInstrument(Instrument):
    """Logs every event at INFO (transitions at DEBUG) on ``temoto.engine.events``.

    Args:
        logger: The logger to use instead.
    """

    def __init__(self, logger: logging.Logger | None = None) -> None:
        self.logger = logger or logging.getLogger("temoto.engine.events")

    def graph_started(self, graph: str, t: float) -> None:
        """Log the start."""
        self.logger.info("graph %s started", graph)

    def node_transition(
        self, graph: str, node: str, old: NodeState, new: NodeState, t: float
    ) -> None:
        """Log a transition."""
        self.logger.debug("%s: %s %s -> %s", graph, node, old.value, new.value)

    def graph_finished(self, graph: str, result: Result, t: float) -> None:
        """Log the end."""
        self.logger.info("graph %s ended: %s", graph, result.value)

    def action_failed(self, graph: str, node: str, error: BaseException) -> None:
        """Log a failure."""
        self.logger.warning("%s: %s failed: %s", graph, node, error)


class RecordingInstrument(Instrument):
    """Keeps every event in lists, for tests.

    Attributes:
        transitions: ``(graph, node, old, new)`` tuples in order.
        finished: ``(graph, result)`` tuples in order.
        failures: ``(graph, node, error)`` tuples in order.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.transitions: list[tuple[str, str, NodeState, NodeState]] = []
        self.finished: list[tuple[str, Result]] = []
        self.failures: list[tuple[str, str, BaseException]] = []

    def node_transition(
        self, graph: str, node: str, old: NodeState, new: NodeState, t: float
    ) -> None:
        """Record a transition."""
        with self._lock:
            self.transitions.append((graph, node, old, new))

    def graph_finished(self, graph: str, result: Result, t: float) -> None:
        """Record the end."""
        with self._lock:
            self.finished.append((graph, result))

    def action_failed(self, graph: str, node: str, error: BaseException) -> None:
        """Record a failure."""
        with self._lock:
            self.failures.append((graph, node, error))

    def started(self, graph: str | None = None) -> list[str]:
        """Nodes in the order they entered RUNNING (a node appears once per run).

        Args:
            graph: Only this graph run (None: all).

        Returns:
            Full node names.
        """
        resumed = ("PAUSED", "PAUSE_REQUESTED")
        with self._lock:
            return [
                n
                for g, n, old, new in self.transitions
                if new.value == "RUNNING" and old.value not in resumed and graph in (None, g)
            ]


class TraceInstrument(Instrument):
    """Writes the ``temoto run --trace`` JSON lines (one per node state change).

    Lines: ``{"t": s, "graph": name, "node": "<Name>_<id>", "state": "RUNNING"}`` (a line of
    a node's run ending, ``FINISHED`` or ``ERROR``, also has ``"node_result": "on_false"``: which
    branch its children take) and, when the top-level graph ends, ``{"graph": name, "result":
    "on_true"}`` (the only lines with a ``"result"`` key).

    Args:
        stream: A text stream to write to (flushed after every line).
        graph: The top-level graph whose end writes the result line (None: every graph).
        t0: Clock reading that ``t`` is measured from.
    """

    def __init__(self, stream: IO[str], graph: str | None = None, t0: float = 0.0) -> None:
        self.stream = stream
        self.graph = graph
        self.t0 = t0
        self._results: dict[tuple[str, str], str] = {}  # node results until their state line

    def _write(self, record: dict[str, object]) -> None:
        self.stream.write(json.dumps(record, ensure_ascii=False) + "\n")
        self.stream.flush()

    def node_transition(
        self, graph: str, node: str, old: NodeState, new: NodeState, t: float
    ) -> None:
        """Write a state line (with the node's result when its run ended)."""
        record: dict[str, object] = {
            "t": round(t - self.t0, 6),
            "graph": graph,
            "node": node,
            "state": new.value,
        }
        result = self._results.pop((graph, node), None)
        if result is not None:
            record["node_result"] = result
        self._write(record)

    def node_result(self, graph: str, node: str, result: Result, t: float) -> None:
        """Keep a node's result for the line of its state change, which comes next."""
        self._results[(graph, node)] = result.value

    def graph_finished(self, graph: str, result: Result, t: float) -> None:
        """Write the result line of the top-level graph."""
        if self.graph is None or graph == self.graph:
            self._write({"graph": graph, "result": result.value})
