"""The state sets and the one transition check of ``temoto.core.states``, which the engine uses."""

from __future__ import annotations

import pytest

from temoto.core import _runtime, dispatch, evolution
from temoto.core.states import (
    ACTIVE_NODE_STATES,
    BUSY_GRAPH_STATES,
    ENDED_GRAPH_STATES,
    NODE_TRANSITIONS,
    GraphState,
    NodeState,
    check_node_transition,
)
from temoto.errors import StateError


def test_every_node_state_has_its_transitions() -> None:
    assert set(NODE_TRANSITIONS) == set(NodeState)


@pytest.mark.parametrize(
    ("old", "new"),
    [(old, new) for old in NodeState for new in NodeState if new not in NODE_TRANSITIONS[old]],
)
def test_an_illegal_change_raises_a_state_error_naming_the_node(
    old: NodeState, new: NodeState
) -> None:
    with pytest.raises(StateError, match=f"^g/Act_1: illegal state change {old.value} -> "):
        check_node_transition("g", "Act_1", old, new)


def test_a_legal_change_passes() -> None:
    for old, allowed in NODE_TRANSITIONS.items():
        for new in allowed:
            check_node_transition("g", "Act_1", old, new)


def test_the_graph_state_sets_do_not_overlap() -> None:
    assert not BUSY_GRAPH_STATES & ENDED_GRAPH_STATES
    assert GraphState.HALTED in ENDED_GRAPH_STATES  # a halted run may be started afresh
    assert NodeState.STOPPING in ACTIVE_NODE_STATES


def test_the_engine_uses_the_one_definition_of_each_set() -> None:
    for module in (_runtime, dispatch, evolution):
        assert module._ACTIVE is ACTIVE_NODE_STATES, module.__name__
    assert evolution._BUSY_GRAPH is BUSY_GRAPH_STATES
    assert evolution._ENDED_GRAPH is ENDED_GRAPH_STATES
