"""Snapshots of graph runs as UMRF JSON: node states, current inputs and runtime logs.

What :meth:`~temoto.core.engine.ActionEngine.graph_json` returns and what the engine's feedback
buffer keeps (one per node state change, when ``feedback_size`` > 0). The caller holds the
engine's lock.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Any

from temoto.core.documents import dump_umrf, graph_to_dict
from temoto.core.params import dump_parameter_tree

if TYPE_CHECKING:
    from temoto.core._runtime import GraphRun

__all__ = ["snapshot"]


def snapshot(run: GraphRun) -> dict[str, Any]:
    """A graph run as a UMRF JSON document, in the canonical form, with its run-time state.

    Args:
        run: The run (the engine's lock held).

    Returns:
        A JSON-ready dict: the run's name and state, every action with its state, the input
        values it holds now and its runtime log (a running action's log as it grows).
    """
    actions = []
    for node in sorted(run.nodes.values(), key=lambda n: n.name):
        log = node.log
        if node.active and node.instance is not None:
            log = node.instance.log_snapshot()  # a running action's log, as it grows
        umrf = dataclasses.replace(node.umrf, state=node.state, runtime_messages=log)
        out = dump_umrf(umrf)
        if node.inputs:
            out["input_parameters"] = dump_parameter_tree(node.inputs, node.data)
        actions.append(out)
    graph = dataclasses.replace(run.plan.graph, name=run.name, state=run.state)
    return graph_to_dict(graph, actions)
