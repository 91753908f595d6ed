"""Faults of the engine itself (not of an action) end a run; sub-graph nesting has a limit.

An error raised by the engine's own code in a worker (a bug, a ``RecursionError`` of sub-graphs
nested 200 deep) ends the run on ERROR with the reason, not a log line with the run left going;
nesting beyond what the engine can end is refused when the graph is planned.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from temoto import ActionCatalog, ActionEngine, GraphIndex, GraphState, Result, build
from temoto.build import action
from temoto.core.action import Action
from temoto.core.documents import load_graph
from temoto.core.evolution import RunEvolution
from temoto.core.planning import MAX_SUBGRAPH_DEPTH
from temoto.errors import GraphDefinitionError

WAIT = 20.0  # real seconds a run may take on a loaded machine
GUIDE_ACTIONS = Path(__file__).resolve().parents[2] / "examples" / "umrf-guide" / "actions"


@action
class Fine(Action):
    def on_run(self) -> bool:
        return True


def test_an_engine_error_in_a_worker_ends_the_run_on_error_with_the_reason(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    def broken(self: Any, *args: Any) -> None:
        raise RuntimeError("injected engine fault")

    # the end of a run is the engine's code, run on the worker that ran the last action
    monkeypatch.setattr(RunEvolution, "finish_run", broken)
    graph = build.graph(Fine, Fine, name="faulty")
    with ActionEngine("me", actions=build.catalog(Fine), stop_timeout=1.0) as engine:
        name = engine.start(graph)
        engine.wait(name, WAIT)  # not a TimeoutError: the run ends
        outcome = engine.outcome(name)
    assert outcome.result is Result.ERROR
    assert outcome.state is GraphState.ERROR
    assert any("injected engine fault" in str(e) for e in outcome.errors), outcome.errors


def _chain(folder: Path, depth: int) -> Path:
    """Graphs G0 (returned) -> G1 -> ... -> G<depth>, the last using the guide's Add."""
    graphs = folder / "graphs"
    graphs.mkdir()
    top = folder / "top.graph.json"
    for i in range(depth + 1):
        last = i == depth
        inner = "Add" if last else f"G{i + 1}"
        inputs: dict[str, Any] = {"a": {"pvf_type": "number"}}
        if last:
            inputs["b"] = {"pvf_type": "number", "pvf_value": 1}
        if i == 0:
            inputs["a"]["pvf_value"] = 1
        doc = {
            "graph_name": f"G{i}",
            "graph_entry": [{"name": inner, "instance_id": 0}],
            "graph_exit": [{"name": inner, "instance_id": 0}],
            "actions": [
                {
                    "name": inner,
                    "instance_id": 0,
                    "type": "sync",
                    "input_parameters": inputs,
                    "output_parameters": {"sum": {"pvf_type": "number"}},
                }
            ],
        }
        path = top if i == 0 else graphs / f"g{i}.graph.json"
        path.write_text(json.dumps(doc), encoding="utf-8")
    return top


def test_sub_graphs_nested_to_the_limit_run(tmp_path: Path) -> None:
    top = _chain(tmp_path, MAX_SUBGRAPH_DEPTH)
    with ActionEngine(
        "", actions=ActionCatalog([GUIDE_ACTIONS]), graphs=GraphIndex([tmp_path / "graphs"])
    ) as engine:
        outcome = engine.run(load_graph(top), timeout=WAIT)
    assert outcome.result is Result.TRUE
    assert outcome.outputs == {"sum": 2.0}


def test_sub_graphs_nested_beyond_the_limit_are_refused_naming_it(tmp_path: Path) -> None:
    top = _chain(tmp_path, 2 * MAX_SUBGRAPH_DEPTH)
    with (
        ActionEngine(
            "", actions=ActionCatalog([GUIDE_ACTIONS]), graphs=GraphIndex([tmp_path / "graphs"])
        ) as engine,
        pytest.raises(GraphDefinitionError, match=rf"more than {MAX_SUBGRAPH_DEPTH} deep"),
    ):
        engine.start(load_graph(top))
