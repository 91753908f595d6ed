"""States of nodes and graphs, action results, condition responses, and legal transitions.

Enum values are the exact strings of the UMRF JSON format, so ``NodeState("RUNNING")`` parses
a document and ``state.value`` writes one; no hand-kept string maps exist.
"""

from __future__ import annotations

from enum import Enum

from temoto.errors import StateError

__all__ = [
    "ACTIVE_NODE_STATES",
    "BUSY_GRAPH_STATES",
    "ENDED_GRAPH_STATES",
    "GRAPH_TRANSITIONS",
    "NODE_TRANSITIONS",
    "PAUSED_GRAPH_STATES",
    "GraphState",
    "NodeState",
    "Response",
    "Result",
    "check_graph_transition",
    "check_node_transition",
]


class NodeState(Enum):
    """State of one action instance (a node) in a graph."""

    __hash__ = object.__hash__  # members are singletons; Enum's own hash is slow Python code

    UNINITIALIZED = "UNINITIALIZED"
    INITIALIZED = "INITIALIZED"
    RUNNING = "RUNNING"
    PAUSE_REQUESTED = "PAUSE_REQUESTED"
    PAUSED = "PAUSED"
    STOPPING = "STOPPING"
    FINISHED = "FINISHED"
    BYPASSED = "BYPASSED"
    ERROR = "ERROR"


class GraphState(Enum):
    """State of a graph."""

    __hash__ = object.__hash__

    UNINITIALIZED = "UNINITIALIZED"
    INITIALIZED = "INITIALIZED"
    RUNNING = "RUNNING"
    #: ``pause`` was asked for; some running action has not paused yet (its ``on_pause``
    #: has not returned, or its sub-graph is still pausing). No action starts.
    PAUSE_REQUESTED = "PAUSE_REQUESTED"
    #: every action that was running has paused
    PAUSED = "PAUSED"
    STOPPING = "STOPPING"
    STOPPED = "STOPPED"
    FINISHED = "FINISHED"
    ERROR = "ERROR"
    HALTED = "HALTED"
    CLEARING = "CLEARING"


class Result(Enum):
    """The result of an action run (the first four) or of a whole graph (all five)."""

    __hash__ = object.__hash__

    TRUE = "on_true"
    FALSE = "on_false"
    STOPPED = "on_stopped"
    ERROR = "on_error"
    HALTED = "on_halted"


class Response(Enum):
    """How a child reacts to a parent's result (the right side of ``"on_true -> run"``)."""

    __hash__ = object.__hash__

    RUN = "run"
    PAUSE = "pause"
    RESTART = "restart"
    STOP = "stop"
    BYPASS = "bypass"
    IGNORE = "ignore"


_S = NodeState

#: Legal node state changes, checked in one place (:func:`check_node_transition`).
NODE_TRANSITIONS: dict[NodeState, frozenset[NodeState]] = {
    _S.UNINITIALIZED: frozenset({_S.RUNNING, _S.BYPASSED, _S.ERROR}),
    _S.INITIALIZED: frozenset({_S.RUNNING, _S.BYPASSED, _S.ERROR}),
    _S.RUNNING: frozenset({_S.PAUSE_REQUESTED, _S.STOPPING, _S.FINISHED, _S.ERROR}),
    _S.PAUSE_REQUESTED: frozenset({_S.PAUSED, _S.RUNNING, _S.STOPPING, _S.FINISHED, _S.ERROR}),
    _S.PAUSED: frozenset({_S.RUNNING, _S.STOPPING, _S.ERROR}),
    _S.STOPPING: frozenset({_S.FINISHED, _S.ERROR}),
    _S.FINISHED: frozenset({_S.RUNNING, _S.BYPASSED, _S.ERROR}),
    _S.BYPASSED: frozenset({_S.RUNNING, _S.BYPASSED, _S.ERROR}),
    _S.ERROR: frozenset({_S.RUNNING, _S.BYPASSED, _S.ERROR}),
}

#: States in which a node occupies (or is about to occupy) an executor, or holds a result.
ACTIVE_NODE_STATES: frozenset[NodeState] = frozenset(
    {_S.RUNNING, _S.PAUSE_REQUESTED, _S.PAUSED, _S.STOPPING}
)

_G = GraphState

#: States of a graph run that has not ended: a run of the same name cannot start.
BUSY_GRAPH_STATES: frozenset[GraphState] = frozenset(
    {_G.RUNNING, _G.PAUSE_REQUESTED, _G.PAUSED, _G.STOPPING, _G.CLEARING}
)

#: States of a paused run, or of one that is pausing: no action starts, results are held.
PAUSED_GRAPH_STATES: frozenset[GraphState] = frozenset({_G.PAUSE_REQUESTED, _G.PAUSED})

#: States of a graph run that has ended (its result is set; it may be started afresh).
ENDED_GRAPH_STATES: frozenset[GraphState] = frozenset(
    {_G.FINISHED, _G.STOPPED, _G.ERROR, _G.HALTED}
)


#: Legal graph run state changes, checked in one place (:func:`check_graph_transition`).
#:
#: A run starts (INITIALIZED to RUNNING), is paused (PAUSE_REQUESTED until every running
#: action has paused, then PAUSED) and resumed, stopped (STOPPING, then
#: STOPPED, or ERROR when an action did not stop in time), or ends by itself: FINISHED at its
#: exit, HALTED when nothing runs and the exit was not reached, ERROR on a fault of the engine.
#: A halted run may be resumed (or modified) and stopped. An ended shared run that is still
#: settling (an abort, ``temoto.core.shared``) takes a peer's result: STOPPED or ERROR to
#: FINISHED or HALTED.
GRAPH_TRANSITIONS: dict[GraphState, frozenset[GraphState]] = {
    _G.UNINITIALIZED: frozenset({_G.RUNNING}),
    _G.INITIALIZED: frozenset({_G.RUNNING}),
    _G.RUNNING: frozenset({_G.PAUSE_REQUESTED, _G.STOPPING, _G.FINISHED, _G.HALTED, _G.ERROR}),
    _G.PAUSE_REQUESTED: frozenset(
        {_G.PAUSED, _G.RUNNING, _G.STOPPING, _G.FINISHED, _G.HALTED, _G.ERROR}
    ),
    _G.PAUSED: frozenset({_G.RUNNING, _G.STOPPING, _G.FINISHED, _G.HALTED, _G.ERROR}),
    _G.STOPPING: frozenset({_G.STOPPED, _G.ERROR}),
    _G.HALTED: frozenset({_G.RUNNING, _G.STOPPING}),
    _G.STOPPED: frozenset({_G.FINISHED, _G.HALTED}),
    _G.ERROR: frozenset({_G.FINISHED, _G.HALTED}),
    _G.FINISHED: frozenset(),
    _G.CLEARING: frozenset(),
}


def check_graph_transition(graph: str, old: GraphState, new: GraphState) -> None:
    """Raise if a graph run may not go from ``old`` to ``new``.

    Args:
        graph: The run's name, for the message.
        old: The current state.
        new: The requested state.

    Raises:
        StateError: If the transition is not in :data:`GRAPH_TRANSITIONS`.
    """
    if new not in GRAPH_TRANSITIONS[old]:
        raise StateError(f"{graph}: illegal graph state change {old.value} -> {new.value}")


def check_node_transition(graph: str, node: str, old: NodeState, new: NodeState) -> None:
    """Raise if a node may not go from ``old`` to ``new``.

    Args:
        graph: The node's graph run, for the message.
        node: The node's full name, for the message.
        old: The current state.
        new: The requested state.

    Raises:
        StateError: If the transition is not in :data:`NODE_TRANSITIONS`.
    """
    if new not in NODE_TRANSITIONS[old]:
        raise StateError(f"{graph}/{node}: illegal state change {old.value} -> {new.value}")
