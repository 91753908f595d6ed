"""The offline task source: words to a UMRF graph that the engine accepts."""

from __future__ import annotations

import pytest

from temoto.actions.builtin import ROBOT_ACTIONS
from temoto.core.documents import graph_from_document
from temoto.core.engine import ActionEngine
from temoto.errors import TaskParseError
from temoto.tasking import RuleBasedTaskSource, TaskSource

PLACES = {"workshop": (2.0, 0.5), "lobby": (-1.0, 1.0)}


@pytest.fixture
def source() -> RuleBasedTaskSource:
    return RuleBasedTaskSource(PLACES)


@pytest.mark.parametrize(
    ("text", "actions"),
    [
        ("go to the workshop", ["NavigateTo"]),
        (
            "Drive to Workshop, grab the box, then head to the lobby.",
            ["NavigateTo", "MoveJoints", "NavigateTo"],
        ),
        ("pick up the cup and put it down", ["MoveJoints", "MoveJoints"]),
        ("move the arm to home; take off to 10 m; land", ["MoveJoints", "TakeOff", "Land"]),
    ],
)
def test_phrasings(source: RuleBasedTaskSource, text: str, actions: list[str]) -> None:
    assert [s.action for s in source.steps(text)] == actions


def test_the_graph_is_a_sequence_the_engine_can_plan(source: RuleBasedTaskSource) -> None:
    assert isinstance(source, TaskSource)
    doc = source.graph("go to the workshop, pick up the object, then go to the lobby")
    assert [a["instance_id"] for a in doc["actions"]] == [0, 0, 1]
    assert doc["actions"][2]["input_parameters"]["x"]["pvf_value"] == -1.0
    assert doc["graph_exit"] == [{"name": "NavigateTo", "instance_id": 1}]
    graph = graph_from_document(doc)
    with ActionEngine(actions=[ROBOT_ACTIONS]) as engine:
        plan = engine.plan(graph)
    assert len(plan.actions) == 3


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("", "the task is empty"),
        ("go to the moon", "unknown place 'moon' (known places: lobby, workshop)"),
        ("dance a little", "'dance a little': not understood"),
    ],
)
def test_what_it_cannot_understand_is_a_clear_error(
    source: RuleBasedTaskSource, text: str, message: str
) -> None:
    with pytest.raises(TaskParseError) as err:
        source.graph(text)
    assert message in str(err.value)


def test_bad_places_are_refused() -> None:
    with pytest.raises(ValueError, match="a place needs a name"):
        RuleBasedTaskSource({" ": (0.0, 0.0)})
