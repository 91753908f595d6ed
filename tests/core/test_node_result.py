"""Instrument.node_result: each node's result, just before its state change."""

from __future__ import annotations

from pathlib import Path

from temoto.core.catalog import ActionCatalog
from temoto.core.documents import load_graph
from temoto.core.engine import ActionEngine
from temoto.core.instrument import Instrument
from temoto.core.states import NodeState, Result

GUIDE = Path(__file__).resolve().parents[2] / "examples" / "umrf-guide"


class _Results(Instrument):
    """Overrides only node_result: the engine must call it all the same."""

    def __init__(self) -> None:
        self.results: list[tuple[str, str]] = []

    def node_result(self, graph: str, node: str, result: Result, t: float) -> None:
        self.results.append((node, result.value))


class _Both(_Results):
    """Also watches transitions: the result comes right before the change it leads to."""

    def __init__(self) -> None:
        super().__init__()
        self.events: list[str] = []

    def node_result(self, graph: str, node: str, result: Result, t: float) -> None:
        super().node_result(graph, node, result, t)
        self.events.append(f"{node} {result.value}")

    def node_transition(
        self, graph: str, node: str, old: NodeState, new: NodeState, t: float
    ) -> None:
        self.events.append(f"{node} {new.value}")


def _run(graph_file: str, params: dict[str, object], *instruments: Instrument) -> Result | None:
    engine = ActionEngine("me", actions=ActionCatalog([GUIDE / "actions"]), instruments=instruments)
    with engine:
        name = engine.start(load_graph(GUIDE / "graphs" / graph_file), params)
        engine.wait(name, 10)
        return engine.outcome(name).result


def test_every_node_result_reaches_an_instrument_that_only_wants_results() -> None:
    only = _Results()
    assert _run("03_branch.graph.json", {"value": 3.0}, only) is Result.TRUE
    assert only.results == [("AtLeast_0", "on_false"), ("Say_1", "on_true")]


def test_the_result_comes_just_before_the_state_change_and_errors_end_in_error() -> None:
    both = _Both()
    assert _run("07_recover.graph.json", {}, both) is Result.TRUE
    assert both.events == [
        "Divide_0 RUNNING",
        "Divide_0 on_error",
        "Divide_0 ERROR",
        "Say_0 RUNNING",
        "Say_0 on_true",
        "Say_0 FINISHED",
    ]
