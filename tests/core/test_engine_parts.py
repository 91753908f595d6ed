"""The engine's parts: every node and run state change goes through one checked path.

The evolution (:class:`temoto.core.evolution.RunEvolution`) owns every state change of a node
(checked against ``NODE_TRANSITIONS``) and of a run (against ``GRAPH_TRANSITIONS``), the
dispatcher's fast paths (a chain of actions on one thread, a round of a batch) included. These
tests take a transition out of a table and watch the engine refuse it: a path that wrote the
state directly would not notice.
"""

from __future__ import annotations

import threading
import time
from typing import Any

import pytest

from temoto import Action, ActionCatalog, ActionEngine, GraphState, NodeState, Result, build
from temoto.build import action
from temoto.core import evolution, shared, states
from temoto.errors import StateError

WAIT = 20.0  # real seconds a run may take on a loaded machine


@action
class Step(Action):
    """Blocking: returns True."""

    def on_run(self) -> bool:
        return True


@action
class InlineStep(Action):
    """Inline: returns True."""

    blocking = False

    def on_run(self) -> bool:
        return True


@action
class Hold(Action):
    """Blocking: waits until stopped."""

    def on_run(self) -> bool:
        self.wait_until_stopped()
        return True


def _catalog() -> ActionCatalog:
    return build.catalog(Step, InlineStep, Hold)


def _without(
    monkeypatch: pytest.MonkeyPatch, table: dict[Any, frozenset[Any]], old: Any, new: Any
) -> None:
    monkeypatch.setitem(table, old, table[old] - {new})


@pytest.mark.parametrize(
    "graph",
    [
        build.graph(Step, Step, Step, name="blocking_chain"),
        build.graph(InlineStep, InlineStep, InlineStep, name="inline_chain"),
        build.graph(build.parallel(InlineStep, InlineStep, InlineStep), Step, name="batch"),
    ],
    ids=lambda g: g.name,
)
def test_the_fast_paths_change_a_node_through_the_checked_path(
    monkeypatch: pytest.MonkeyPatch, graph: object
) -> None:
    # RUNNING -> FINISHED, the commonest change of all, is no longer legal: every action's end
    # must be refused (an engine error ends the run ERROR), not written past the table. The
    # fast paths write their changes (evolution.FAST_CHANGES) without a lookup per action, so
    # the engine reads the table when it is made and leaves them when it forbids one
    _without(monkeypatch, states.NODE_TRANSITIONS, NodeState.RUNNING, NodeState.FINISHED)
    with ActionEngine("me", actions=_catalog(), stop_timeout=1.0) as engine:
        name = engine.start(graph)  # type: ignore[arg-type]
        assert engine.wait(name, WAIT) is Result.ERROR
        outcome = engine.outcome(name)
    assert outcome.state is GraphState.ERROR
    assert any("illegal state change RUNNING -> FINISHED" in str(e) for e in outcome.errors)


def test_the_fast_paths_changes_are_legal_by_the_table() -> None:
    assert evolution.fast_changes_legal()
    assert (NodeState.RUNNING, NodeState.FINISHED) in evolution.FAST_CHANGES
    for old, new in evolution.FAST_CHANGES:
        assert new in states.NODE_TRANSITIONS[old]


def test_a_run_changes_state_through_the_checked_path(monkeypatch: pytest.MonkeyPatch) -> None:
    _without(monkeypatch, states.GRAPH_TRANSITIONS, GraphState.RUNNING, GraphState.PAUSE_REQUESTED)
    with ActionEngine("me", actions=_catalog(), stop_timeout=1.0) as engine:
        name = engine.start(build.graph(Hold, name="held"))
        with pytest.raises(
            StateError, match="illegal graph state change RUNNING -> PAUSE_REQUESTED"
        ):
            engine.pause(name)
        assert engine.outcome(name).state is GraphState.RUNNING
        assert engine.stop(name, WAIT) is Result.STOPPED


def test_every_graph_state_has_its_transitions() -> None:
    assert set(states.GRAPH_TRANSITIONS) == set(GraphState)
    # an ended run leaves its state only to take a shared run's result (FINISHED, HALTED),
    # except a halted one, which may be resumed (or modified) and stopped
    for ended in states.ENDED_GRAPH_STATES - {GraphState.HALTED}:
        assert states.GRAPH_TRANSITIONS[ended] <= {GraphState.FINISHED, GraphState.HALTED}
    assert states.GRAPH_TRANSITIONS[GraphState.HALTED] == {GraphState.RUNNING, GraphState.STOPPING}


@pytest.mark.parametrize(
    ("old", "new"),
    [
        (old, new)
        for old in GraphState
        for new in GraphState
        if new not in states.GRAPH_TRANSITIONS[old]
    ],
)
def test_an_illegal_run_change_raises_a_state_error_naming_the_run(
    old: GraphState, new: GraphState
) -> None:
    with pytest.raises(StateError, match=f"^g: illegal graph state change {old.value} -> "):
        states.check_graph_transition("g", old, new)


def test_the_shared_runs_use_the_one_definition_of_an_ended_run() -> None:
    assert shared._ENDED_GRAPH is states.ENDED_GRAPH_STATES


PAUSE_GATE = threading.Event()  # Slow's on_pause returns once this is set
IN_ON_PAUSE = threading.Event()


@action
class SlowToPause(Action):
    """Blocking: runs until stopped; its on_pause takes until PAUSE_GATE is set."""

    def on_run(self) -> bool:
        self.wait_until_stopped()
        return True

    def on_pause(self) -> None:
        IN_ON_PAUSE.set()
        PAUSE_GATE.wait(WAIT)


def _until(condition: Any, what: str) -> None:
    deadline = time.monotonic() + WAIT
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.005)


def test_a_run_is_paused_only_once_every_running_action_has_paused() -> None:
    PAUSE_GATE.clear()
    IN_ON_PAUSE.clear()
    graph = build.graph(build.parallel(SlowToPause, Hold), name="pausing")
    catalog = build.catalog(SlowToPause, Hold)
    with ActionEngine("me", actions=catalog, stop_timeout=1.0) as engine:
        name = engine.start(graph)
        _until(lambda: set(engine.node_states(name).values()) == {NodeState.RUNNING}, "running")
        engine.pause(name)
        assert IN_ON_PAUSE.wait(WAIT)
        # SlowToPause's on_pause has not returned: the run is not PAUSED yet (before: it was
        # PAUSED as soon as the pause was asked for)
        _until(lambda: engine.node_states(name)["Hold_0"] is NodeState.PAUSED, "Hold_0 paused")
        assert engine.node_states(name)["SlowToPause_0"] is NodeState.PAUSE_REQUESTED
        assert engine.outcome(name).state is GraphState.PAUSE_REQUESTED
        assert engine.running_graphs()[name] is GraphState.PAUSE_REQUESTED
        PAUSE_GATE.set()
        _until(lambda: engine.outcome(name).state is GraphState.PAUSED, "the run paused")
        assert engine.node_states(name)["SlowToPause_0"] is NodeState.PAUSED
        engine.resume(name)
        assert engine.outcome(name).state is GraphState.RUNNING
        assert engine.stop(name, WAIT) is Result.STOPPED
