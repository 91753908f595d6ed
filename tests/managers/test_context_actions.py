"""The built-in context actions in graphs, on an engine whose registrar has a Context Manager."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

import temoto.actions.builtin.context as context_actions
from temoto import ActionEngine, Result
from temoto.core.registrar import Registrar
from temoto.errors import ContextCycleError, ContextItemNotFoundError, ResourceNotFoundError
from temoto.managers.context import ContextClient, ContextManager, Pose

ACTIONS = Path(context_actions.__file__).resolve().parent
WAIT = 10.0


@pytest.fixture
def world() -> Iterator[tuple[Registrar, ContextManager]]:
    registrar = Registrar("test-context")
    manager = ContextManager("worker", registrar=registrar)
    try:
        yield registrar, manager
    finally:
        for ref in registrar.references():
            registrar.release(ref.id)
        manager.close()
        registrar.close()


def _value(kind: str, value: Any) -> dict[str, Any]:
    return {"pvf_type": kind, "pvf_value": value}


def chain(name: str, *steps: tuple[str, dict[str, Any]]) -> dict[str, Any]:
    """A graph running the steps one after the other (each step: action name, inputs)."""
    actions = []
    for i, (action, inputs) in enumerate(steps):
        node: dict[str, Any] = {
            "name": action,
            "instance_id": i,
            "type": "sync",
            "input_parameters": {
                key: _value(
                    "number"
                    if isinstance(v, float)
                    else "bool"
                    if isinstance(v, bool)
                    else "string",
                    v,
                )
                for key, v in inputs.items()
            },
        }
        if i:
            node["parents"] = [{"name": steps[i - 1][0], "instance_id": i - 1}]
        if i < len(steps) - 1:
            node["children"] = [{"name": steps[i + 1][0], "instance_id": i + 1}]
        actions.append(node)
    last = len(steps) - 1
    return {
        "graph_name": name,
        "graph_entry": [{"name": steps[0][0], "instance_id": 0}],
        "graph_exit": [{"name": steps[last][0], "instance_id": last}],
        "actions": actions,
    }


def test_add_move_and_query_an_item(world: tuple[Registrar, ContextManager]) -> None:
    registrar, manager = world
    graph = chain(
        "cleanup",
        ("AddItem", {"item": "map", "item_type": "map"}),
        ("AddItem", {"item": "worker_base", "item_type": "robot", "parent": "map", "x": 1.0}),
        (
            "AddItem",
            {"item": "trash", "parent": "map", "x": 3.0, "y": 1.0, "attributes": '{"tag": 7}'},
        ),
        ("MoveItem", {"item": "trash", "parent": "worker_base"}),  # picked up: stays put
        ("MoveItem", {"item": "worker_base", "x": 5.0}),  # the robot drives on
        ("GetItem", {"item": "trash"}),
    )
    with ActionEngine("worker", actions=[ACTIONS], registrar=registrar) as engine:
        outcome = engine.run(graph, timeout=WAIT)
    assert outcome.result is Result.TRUE, outcome.errors
    out = outcome.outputs
    assert (out["item_type_found"], out["item_parent"], out["item_maintainer"]) == (
        "object",
        "worker_base",
        "worker",
    )
    assert (out["world_x"], out["world_y"]) == pytest.approx((7.0, 1.0))
    assert manager.get("trash").attributes == {"tag": 7}
    assert manager.path("trash") == ["map", "worker_base", "trash"]


def test_find_and_remove(world: tuple[Registrar, ContextManager]) -> None:
    registrar, manager = world
    manager.add("map", "map")
    manager.add("a", "object", "map")
    manager.add("b", "object", "a")
    graph = chain(
        "tidy",
        ("FindItems", {"item_type": "object"}),
        ("RemoveItem", {"item": "a", "cascade": True}),
    )
    with ActionEngine("worker", actions=[ACTIONS], registrar=registrar) as engine:
        outcome = engine.run(graph, timeout=WAIT)
    assert outcome.result is Result.TRUE, outcome.errors
    assert outcome.outputs["removed_items"] == ["b", "a"]
    assert [i.name for i in manager.items()] == ["map"]
    with ActionEngine("worker", actions=[ACTIONS], registrar=registrar) as engine:
        outcome = engine.run(chain("none", ("FindItems", {"item_type": "object"})), timeout=WAIT)
    assert outcome.result is Result.FALSE


def test_bad_input_fails_the_action_with_a_typed_error(
    world: tuple[Registrar, ContextManager],
) -> None:
    registrar, manager = world
    manager.add("map", "map")
    with ActionEngine("worker", actions=[ACTIONS], registrar=registrar) as engine:
        missing = engine.run(
            chain("m", ("AddItem", {"item": "x", "parent": "shelf"})), timeout=WAIT
        )
        cycle = engine.run(chain("c", ("MoveItem", {"item": "map", "parent": "map"})), timeout=WAIT)
    assert missing.result is Result.ERROR
    assert isinstance(missing.errors[0].__cause__, ContextItemNotFoundError)
    assert cycle.result is Result.ERROR
    assert isinstance(cycle.errors[0].__cause__, ContextCycleError)
    assert [i.name for i in manager.items()] == ["map"]


def test_a_temporary_item_goes_when_the_graph_ends(
    world: tuple[Registrar, ContextManager],
) -> None:
    registrar, manager = world
    manager.add("map", "map")
    seen: list[bool] = []
    graph = chain(
        "scan",
        ("AddItem", {"item": "marker", "parent": "map", "temporary": True}),
        ("GetItem", {"item": "marker"}),
    )
    manager.listen(lambda change: seen.append("marker" in manager))
    with ActionEngine("worker", actions=[ACTIONS], registrar=registrar) as engine:
        outcome = engine.run(graph, timeout=WAIT)
    assert outcome.result is Result.TRUE, outcome.errors
    assert outcome.outputs["item_parent"] == "map"
    assert "marker" not in manager
    assert manager.removed("marker") is not None
    assert registrar.resources() == []


def test_get_item_waits_for_it(world: tuple[Registrar, ContextManager]) -> None:
    registrar, manager = world
    manager.add("map", "map")
    graph = chain("wait", ("GetItem", {"item": "bin", "timeout": 5.0}))
    with ActionEngine("worker", actions=[ACTIONS], registrar=registrar) as engine:
        engine.start(graph)
        manager.add("bin", "object", "map", Pose(1.0, 2.0))
        assert engine.wait("wait", WAIT) is Result.TRUE
        short = engine.run(
            chain("gone", ("GetItem", {"item": "nope", "timeout": 0.01})), timeout=WAIT
        )
    assert short.result is Result.FALSE


def test_the_client_needs_a_context_manager() -> None:
    with Registrar("empty") as registrar, pytest.raises(ResourceNotFoundError):
        ContextClient(registrar)
