"""What the commands print for people while a graph runs (``--progress``, the robot command).

Not public API: :mod:`temoto.cli`'s commands share it (``temoto run``, the robot command).
"""

from __future__ import annotations

import logging
import threading
from typing import IO

from temoto.clock import Clock
from temoto.core.action import ACTION_LOGGER
from temoto.core.instrument import Instrument
from temoto.core.states import NodeState, Result

__all__ = ["ActionLogHandler", "Progress"]


class Progress(Instrument):
    """Prints a run for people (``--progress``) until its result is known.

    One line per node state change (with the node's result when its run ends: ``FINISHED
    on_false`` says which branch its children take) and per line of an action's log (the
    built-in robot actions log their progress: distance left, altitude, joints reached).
    What the engine does after the result (stopping a halted run, or actions still winding
    down, as it shuts down at exit) is not part of the run and is not printed.

    Args:
        stream: Where to print.
        clock: The engine's clock (action log lines are stamped with it).
        t0: Clock reading that times are measured from.
        states: Print only changes to these states (None: every change).
    """

    def __init__(
        self,
        stream: IO[str],
        clock: Clock,
        t0: float,
        *,
        states: frozenset[NodeState] | None = None,
    ) -> None:
        self.stream = stream
        self.clock = clock
        self.t0 = t0
        self.states = states
        self._lock = threading.Lock()
        self._finished = False
        self._results: dict[tuple[str, str], Result] = {}

    def _say(self, t: float, text: str) -> None:
        with self._lock:
            if not self._finished:
                self.stream.write(f"[{t - self.t0:8.3f}s] {text}\n")
                self.stream.flush()

    def graph_started(self, graph: str, t: float) -> None:
        """Print ``GRAPH: started``."""
        self._say(t, f"{graph}: started")

    def node_result(self, graph: str, node: str, result: Result, t: float) -> None:
        """Keep a node's result for the state change that follows it."""
        self._results[(graph, node)] = result  # printed with the state change that follows

    def node_transition(
        self, graph: str, node: str, old: NodeState, new: NodeState, t: float
    ) -> None:
        """Print ``GRAPH: NODE STATE [RESULT]`` (only the states asked for)."""
        result = self._results.pop((graph, node), None)
        if self.states is not None and new not in self.states:
            return
        suffix = f" {result.value}" if result is not None else ""
        self._say(t, f"{graph}: {node} {new.value}{suffix}")

    def graph_finished(self, graph: str, result: Result, t: float) -> None:
        """Print ``GRAPH: ended with RESULT``."""
        self._say(t, f"{graph}: ended with {result.value}")

    def action_log(self, record: logging.LogRecord) -> None:
        """A line of an action's log (logger ``temoto.action.<graph>.<node>``)."""
        where = record.name.removeprefix("temoto.action").lstrip(".")
        graph, _, node = where.rpartition(".")
        text = f"{graph}: {node}: {record.getMessage()}" if graph else record.getMessage()
        self._say(self.clock.monotonic(), text)

    def finish(self) -> None:
        """Print nothing more: the run's result is known."""
        with self._lock:
            self._finished = True


class ActionLogHandler(logging.Handler):
    """Hands the action logs (``temoto.action``) to ``--progress``, in its timeline.

    Installed for the run only (:meth:`install`, :meth:`remove`); while it is, action logs
    do not also reach the root handler (no line twice).
    """

    def __init__(self, progress: Progress) -> None:
        super().__init__(logging.INFO)
        self.progress = progress
        self._logger = logging.getLogger(ACTION_LOGGER)
        self._saved = (self._logger.level, self._logger.propagate)

    def emit(self, record: logging.LogRecord) -> None:
        """Print an action's log line in the timeline."""
        try:
            self.progress.action_log(record)
        except Exception:  # a closed stream: as logging does, never raise into the action
            self.handleError(record)

    def install(self) -> None:
        """Take the action logs (INFO and up) from here on."""
        self._logger.addHandler(self)
        self._logger.setLevel(logging.INFO)
        self._logger.propagate = False

    def remove(self) -> None:
        """Give the action logs back to the root handler, as before :meth:`install`."""
        self._logger.removeHandler(self)
        self._logger.setLevel(self._saved[0])
        self._logger.propagate = self._saved[1]
