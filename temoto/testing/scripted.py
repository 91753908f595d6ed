"""Scripted actions: what each node returns, outputs and waits for is set by the test.

A :class:`Script` makes action classes (:meth:`Script.action`), says per node what each run
does (:meth:`Script.plan`) and records what ran (:attr:`Script.runs`, :attr:`Script.calls`),
in the spirit of py_trees' status queues::

    script = Script()
    step = script.action("Step", outputs={"out": str})
    script.plan("Step_1", False, Outcome(True, outputs={"out": "x"}))  # its 1st and 2nd runs
    with ActionEngine(actions=catalog(step)) as engine:
        engine.run(graph(step, step))
    assert script.started() == ["Step_0", "Step_1"]

A run waits (:attr:`Outcome.seconds` of the engine's clock, or until stopped) with the
action's own stop- and pause-aware helpers, so a :class:`~temoto.clock.ManualClock` drives it
without real sleeps. Each Script keeps its own records: nothing is shared between tests.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar

from temoto.build import ParamDecl, action
from temoto.core.action import Action

__all__ = ["Outcome", "Run", "Script", "ScriptedAction"]


@dataclass(frozen=True, slots=True)
class Outcome:
    """What one run of a scripted action does, in this order.

    Attributes:
        result: True or False (the result), or an exception the run raises (``on_error``).
        outputs: Output values to set, or a function of the run's input values that returns
            them.
        seconds: Clock seconds to wait first, from the run's start (stop- and pause-aware: a
            stop ends the run).
        until_stopped: Wait until the node is stopped, then finish with ``result``.
    """

    result: bool | BaseException = True
    outputs: Mapping[str, Any] | Callable[[Mapping[str, Any]], Mapping[str, Any]] = field(
        default_factory=dict
    )
    seconds: float = 0.0
    until_stopped: bool = False


@dataclass(frozen=True, slots=True)
class Run:
    """One run of a scripted node, recorded when it starts.

    Attributes:
        node: The node (``Step_0``).
        graph: The graph run it belongs to.
        inputs: The run's input values.
    """

    node: str
    graph: str
    inputs: Mapping[str, Any]


def _outcome(planned: Any) -> Outcome:
    if isinstance(planned, Outcome):
        return planned
    if isinstance(planned, bool | BaseException):
        return Outcome(planned)
    raise TypeError(f"a planned run is True, False, an exception or an Outcome, not {planned!r}")


class Script:
    """Scripted action classes and the record of their runs (thread-safe)."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._plans: dict[str, deque[Outcome]] = {}
        #: Every run, in the order they started.
        self.runs: list[Run] = []
        #: Every hook the engine called besides ``on_run``, as ``(node, "on_stop")`` pairs.
        self.calls: list[tuple[str, str]] = []

    def action(
        self,
        name: str,
        *,
        inputs: Mapping[str, ParamDecl] | None = None,
        outputs: Mapping[str, ParamDecl] | None = None,
        type: str = "sync",  # noqa: A002 - the UMRF key's name
        default: Any = True,
        blocking: bool = True,
    ) -> type[ScriptedAction]:
        """A new scripted action class, described as :func:`temoto.build.action` does.

        Args:
            name: The action's name.
            inputs: Its inputs (as :func:`temoto.build.action` takes them).
            outputs: Its outputs.
            type: ``sync``, ``async`` or ``spontaneous``.
            default: What a run does when its node has nothing planned: True, False, an
                exception or an :class:`Outcome`.
            blocking: False declares the action inline (its runs must then not wait).

        Returns:
            The class (register it with :func:`temoto.build.catalog`).

        Raises:
            TypeError: ``default`` is not a planned run.
        """
        namespace = {"script": self, "default": _outcome(default), "__qualname__": name}
        cls = type_of(name, namespace)
        return action(cls, inputs=inputs, outputs=outputs, type=type, blocking=blocking)

    def plan(self, node: str, *runs: Any) -> None:
        """Say what the next runs of a node do (after them, its action's default).

        Args:
            node: The node's full name (``Step_0``).
            runs: One entry per run: True, False, an exception or an :class:`Outcome`.

        Raises:
            TypeError: An entry is not a planned run.
        """
        outcomes = [_outcome(r) for r in runs]
        with self._cond:
            self._plans.setdefault(node, deque()).extend(outcomes)

    def started(self, graph: str | None = None) -> list[str]:
        """The nodes that started, in order, once per run.

        Args:
            graph: Only the runs of this graph run (default: all).

        Returns:
            Their full names.
        """
        with self._cond:
            return [r.node for r in self.runs if graph is None or r.graph == graph]

    def inputs(self, node: str, run: int = -1) -> Mapping[str, Any]:
        """The input values of one run of a node.

        Args:
            node: The node's full name.
            run: Which of its runs (0: the first; -1: the last).

        Returns:
            The values.

        Raises:
            IndexError: The node did not run that often.
        """
        with self._cond:
            mine = [r for r in self.runs if r.node == node]
        return mine[run].inputs

    def wait_started(self, node: str, count: int = 1, timeout: float | None = 10.0) -> bool:
        """Wait until a node has started ``count`` runs (no polling).

        Args:
            node: The node's full name.
            count: How many runs.
            timeout: Real seconds, or None to wait for ever.

        Returns:
            True if it had, False on timeout.
        """
        with self._cond:
            return self._cond.wait_for(
                lambda: sum(1 for r in self.runs if r.node == node) >= count, timeout
            )

    def _start(self, node: str, graph: str, inputs: Mapping[str, Any]) -> Outcome | None:
        """Record a run's start; its planned outcome (None: the action's default)."""
        with self._cond:
            self.runs.append(Run(node, graph, inputs))
            self._cond.notify_all()
            plan = self._plans.get(node)
            return plan.popleft() if plan else None

    def _call(self, node: str, hook: str) -> None:
        with self._cond:
            self.calls.append((node, hook))
            self._cond.notify_all()


def type_of(name: str, namespace: dict[str, Any]) -> type[ScriptedAction]:
    """A subclass of :class:`ScriptedAction` named ``name`` (its class attributes given).

    Args:
        name: The class's name.
        namespace: Its attributes.

    Returns:
        The class.
    """
    return type(name, (ScriptedAction,), {"__module__": __name__, **namespace})


class ScriptedAction(Action):
    """An action that does what its :class:`Script` planned for its node (see the module).

    Attributes:
        script: Class attribute: the Script that made the class.
        default: Class attribute: what a run does when nothing is planned for its node.
    """

    script: ClassVar[Script]
    default: ClassVar[Outcome]

    def on_run(self) -> bool:
        """Record the run, then wait, set outputs and return (or raise) as planned.

        Returns:
            The planned result.

        Raises:
            BaseException: The planned exception.
        """
        inputs = dict(self.inputs)
        # the wait is measured from before the start is recorded: a test that advances a manual
        # clock as soon as it sees the start cannot advance it before the wait begins
        began = self.clock.monotonic()
        outcome = self.script._start(self.name, self.graph_name, inputs) or self.default
        if outcome.seconds:
            self.sleep(max(0.0, outcome.seconds - (self.clock.monotonic() - began)))
        if outcome.until_stopped:
            self.wait_until_stopped()
        values = outcome.outputs(inputs) if callable(outcome.outputs) else outcome.outputs
        for key, value in values.items():
            self.outputs[key] = value
        if isinstance(outcome.result, BaseException):
            raise outcome.result
        return outcome.result

    def on_pause(self) -> None:
        """Record the call."""
        self.script._call(self.name, "on_pause")

    def on_resume(self) -> None:
        """Record the call."""
        self.script._call(self.name, "on_resume")

    def on_stop(self) -> None:
        """Record the call."""
        self.script._call(self.name, "on_stop")
