"""A graph may leave out an action's optional inputs and its outputs; not its required inputs."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from temoto import ActionEngine, Result
from temoto.errors import GraphDefinitionError

DESCRIPTION = {
    "name": "Greet",
    "type": "sync",
    "input_parameters": {
        "who": {"pvf_type": "string"},
        "punctuation": {"pvf_type": "string", "pvf_required": False},
    },
    "output_parameters": {"text": {"pvf_type": "string"}},
}
CODE = """
from temoto import Action


class Greet(Action):
    def on_run(self) -> bool:
        end = self.inputs.get("punctuation", ".")
        self.outputs["text"] = "hello " + self.inputs.get_string("who") + end
        return True
"""


def graph(inputs: dict[str, Any]) -> dict[str, Any]:
    return {
        "graph_name": "greeting",
        "graph_entry": [{"name": "Greet", "instance_id": 0}],
        "graph_exit": [{"name": "Greet", "instance_id": 0}],
        "actions": [
            {"name": "Greet", "instance_id": 0, "type": "sync", "input_parameters": inputs}
        ],
    }


@pytest.fixture
def actions(tmp_path: Path) -> Path:
    (tmp_path / "greet.umrf.json").write_text(json.dumps(DESCRIPTION))
    (tmp_path / "greet.py").write_text(CODE)
    return tmp_path


def test_optional_inputs_and_outputs_may_be_left_out(actions: Path) -> None:
    with ActionEngine(actions=[actions]) as engine:
        outcome = engine.run(graph({"who": {"pvf_type": "string", "pvf_value": "robot"}}))
    assert outcome.result is Result.TRUE, outcome.errors
    assert outcome.outputs == {"text": "hello robot."}


def test_a_required_input_may_not(actions: Path) -> None:
    with (
        ActionEngine(actions=[actions]) as engine,
        pytest.raises(GraphDefinitionError, match="lacks inputs who"),
    ):
        engine.run(graph({"punctuation": {"pvf_type": "string", "pvf_value": "!"}}))


def test_a_type_that_differs_from_the_description_is_refused(actions: Path) -> None:
    with (
        ActionEngine(actions=[actions]) as engine,
        pytest.raises(GraphDefinitionError, match="'who' is number in the graph but string"),
    ):
        engine.run(graph({"who": {"pvf_type": "number", "pvf_value": 1}}))
