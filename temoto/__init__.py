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

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
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

#: Where each public name lives. ``import temoto`` imports none of it: the names are imported
#: on first use (PEP 562), so a command starts without the engine and a Ctrl-C while the
#: command line loads its modules reaches ``temoto.__main__``'s handler, not the import.
_PUBLIC: dict[str, str] = {
    "GraphBuilder": "temoto.build",
    "Param": "temoto.build",
    "action": "temoto.build",
    "branch": "temoto.build",
    "catalog": "temoto.build",
    "graph": "temoto.build",
    "node": "temoto.build",
    "parallel": "temoto.build",
    "sequence": "temoto.build",
    "Clock": "temoto.clock",
    "ManualClock": "temoto.clock",
    "MonotonicClock": "temoto.clock",
    "ScaledClock": "temoto.clock",
    "Action": "temoto.core.action",
    "ActionCatalog": "temoto.core.catalog",
    "GraphIndex": "temoto.core.catalog",
    "dump_graph": "temoto.core.documents",
    "load_graph": "temoto.core.documents",
    "load_umrf": "temoto.core.documents",
    "parse_graph_text": "temoto.core.documents",
    "ActionEngine": "temoto.core.engine",
    "GraphOutcome": "temoto.core.engine",
    "UmrfGraph": "temoto.core.graph",
    "parse_graph": "temoto.core.graph",
    "Instrument": "temoto.core.instrument",
    "GraphState": "temoto.core.states",
    "NodeState": "temoto.core.states",
    "Response": "temoto.core.states",
    "Result": "temoto.core.states",
    "Umrf": "temoto.core.umrf",
    "parse_umrf": "temoto.core.umrf",
    "ValidationReport": "temoto.core.validation",
    "validate_graph": "temoto.core.validation",
    "ActionError": "temoto.errors",
    "ConfigError": "temoto.errors",
    "GraphDefinitionError": "temoto.errors",
    "GraphInputError": "temoto.errors",
    "PluginError": "temoto.errors",
    "StateError": "temoto.errors",
    "StopRequested": "temoto.errors",
    "TemotoError": "temoto.errors",
}


def __getattr__(name: str) -> Any:
    """Import a public name on first use and keep it in the package's namespace."""
    module = _PUBLIC.get(name)
    if module is None:
        raise AttributeError(f"module 'temoto' has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    """The public API and the module's own names."""
    return sorted({*globals(), *_PUBLIC})


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
