"""TeMoto for Python: a framework for dependable, adaptive, collaborative robots.

The public API::

    from temoto import ActionEngine, Action, load_graph

    with ActionEngine("robot_1", actions=["examples/actions/conformance"]) as engine:
        outcome = engine.run(load_graph("my.graph.json"))
        print(outcome.result)

Actions and graphs can also be written in Python (:mod:`temoto.build`, ``docs/python-api.md``)::

    from temoto import ActionEngine, action, catalog, graph

    @action(inputs={"text": str}, outputs={"text": str})
    def shout(text):
        return {"text": text.upper() + "!"}

    with ActionEngine(actions=catalog(shout)) as engine:
        print(engine.run(graph(shout), {"text": "hi"}).outputs)  # {'text': 'HI!'}
"""

from __future__ import annotations

from temoto.build import (
    GraphBuilder,
    Param,
    action,
    branch,
    catalog,
    graph,
    node,
    parallel,
    sequence,
)
from temoto.clock import Clock, ManualClock, MonotonicClock, ScaledClock
from temoto.core.action import Action
from temoto.core.catalog import ActionCatalog, GraphIndex
from temoto.core.documents import dump_graph, load_graph, load_umrf, parse_graph_text
from temoto.core.engine import ActionEngine, GraphOutcome
from temoto.core.graph import UmrfGraph, parse_graph
from temoto.core.instrument import Instrument
from temoto.core.states import GraphState, NodeState, Response, Result
from temoto.core.umrf import Umrf, parse_umrf
from temoto.core.validation import ValidationReport, validate_graph
from temoto.errors import (
    ActionError,
    ConfigError,
    GraphDefinitionError,
    GraphInputError,
    PluginError,
    StateError,
    StopRequested,
    TemotoError,
)

__version__ = "0.1.0"

__all__ = [
    "Action",
    "ActionCatalog",
    "ActionEngine",
    "ActionError",
    "Clock",
    "ConfigError",
    "GraphBuilder",
    "GraphDefinitionError",
    "GraphIndex",
    "GraphInputError",
    "GraphOutcome",
    "GraphState",
    "Instrument",
    "ManualClock",
    "MonotonicClock",
    "NodeState",
    "Param",
    "PluginError",
    "Response",
    "Result",
    "ScaledClock",
    "StateError",
    "StopRequested",
    "TemotoError",
    "Umrf",
    "UmrfGraph",
    "ValidationReport",
    "__version__",
    "action",
    "branch",
    "catalog",
    "dump_graph",
    "graph",
    "load_graph",
    "load_umrf",
    "node",
    "parallel",
    "parse_graph",
    "parse_graph_text",
    "parse_umrf",
    "sequence",
    "validate_graph",
]
