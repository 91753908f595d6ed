"""What the live view's JSON API returns: runs, and one run's picture.

These functions read an :class:`~temoto.core.engine.ActionEngine` through its public
snapshots (``running_graphs``, ``outcome``, ``graph_json``) and, for the resources each action
holds, the engine's registrar (an action's references have the client ``"<run>/<node>"``).
They return JSON-ready dicts; the page draws them. Nothing here holds a lock across calls:
every snapshot is consistent on its own, and the page re-fetches after every change.
"""

from __future__ import annotations

import dataclasses
import enum
import json
import math
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from temoto.errors import GraphNotFoundError, ResourceNotFoundError
from temoto.web.layout import layered_layout

if TYPE_CHECKING:
    from temoto.core.engine import ActionEngine

__all__ = ["ENTRY", "EXIT", "edge_status", "graph_picture", "graph_view", "graphs_list", "to_json"]

#: Names of the two pseudo-nodes drawn for ``graph_entry`` and ``graph_exit`` (no action's
#: full name can be one of them: those end in ``_<instance id>``).
ENTRY = "graph_entry"
EXIT = "graph_exit"

#: The newest log lines of a node that a view carries.
MAX_LOG_LINES = 200

#: Longest error text a view carries per error.
MAX_ERROR_CHARS = 2000


def graphs_list(engine: ActionEngine) -> dict[str, Any]:
    """Every run the engine knows, in start order.

    Args:
        engine: The engine.

    Returns:
        ``{"actor": str, "graphs": [{"name", "state", "result"}, ...]}``.
    """
    graphs = []
    for name in engine.running_graphs():
        try:
            outcome = engine.outcome(name)
        except GraphNotFoundError:  # removed meanwhile
            continue
        graphs.append(
            {
                "name": name,
                "state": outcome.state.value,
                "result": outcome.result.value if outcome.result else None,
            }
        )
    return {"actor": engine.actor, "graphs": graphs}


def graph_view(
    engine: ActionEngine, run: str, timeline: dict[str, Any] | None = None
) -> dict[str, Any]:
    """One run's picture: nodes with state, logs and held resources; edges; a layout.

    Args:
        engine: The engine.
        run: The run's name.
        timeline: The run's timeline (:meth:`EventHub.timeline`), if known: it gives each
            node's result where the events tell it, and the page's Gantt chart.

    Returns:
        A JSON-ready dict (its keys are described in ``docs/live-view.md``).

    Raises:
        GraphNotFoundError: No run of that name.
    """
    snapshot = engine.graph_json(run)
    outcome = engine.outcome(run)
    answer = graph_picture(snapshot, _held_resources(engine, run), timeline)
    answer.update(
        {
            "name": run,
            "state": outcome.state.value,
            "result": outcome.result.value if outcome.result else None,
            "errors": [_error_text(e) for e in outcome.errors],
            "timeline": timeline,
            "now": engine.clock.monotonic(),
        }
    )
    return answer


def graph_picture(
    snapshot: Mapping[str, Any],
    held: Mapping[str, list[dict[str, Any]]] | None = None,
    timeline: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """The drawing of a graph in UMRF JSON form (a run's snapshot, or a graph file's dict).

    Args:
        snapshot: The graph as :func:`~temoto.core.documents.graph_to_dict` writes it (with
            run-time states and logs when it is a run's snapshot).
        held: Resources held, by node name.
        timeline: The run's timeline: each node's result is its newest span's.

    Returns:
        ``{"description", "nodes", "edges", "width", "height"}``; each edge has a ``status``:
        ``taken`` (its parent ended and its child ran), ``skipped`` (its child was bypassed)
        or ``pending``.
    """
    actions: list[dict[str, Any]] = snapshot.get("actions", [])
    held = held or {}
    results: dict[str, str | None] = {}
    for span in (timeline or {}).get("spans", []):
        results[span["node"]] = span.get("result")

    nodes: list[dict[str, Any]] = []
    edges: list[dict[str, Any]] = []
    entry = [_full_name(e) for e in snapshot.get("graph_entry", [])]
    exits = snapshot.get("graph_exit", [])
    if entry:
        nodes.append({"id": ENTRY, "kind": "entry", "label": "entry", "state": None})
        edges.extend({"from": ENTRY, "to": e, "required": True, "conditions": []} for e in entry)
    for action in actions:
        node_id = _full_name(action)
        runtime = action.get("runtime") or {}
        logs = [
            {"t": m.get("timestamp"), "message": str(m.get("message", ""))}
            for m in (runtime.get("messages") or [])[:MAX_LOG_LINES]
        ]
        nodes.append(
            {
                "id": node_id,
                "kind": "action",
                "label": node_id,
                "name": action.get("name", ""),
                "instance_id": action.get("instance_id"),
                "type": action.get("type", ""),
                "actor": action.get("actor", ""),
                "description": action.get("description", ""),
                "state": action.get("state"),
                "result": results.get(node_id),
                "inputs": _parameters(action.get("input_parameters")),
                "logs": logs,
                "resources": held.get(node_id, []),
            }
        )
        edges.extend(
            {
                "from": _full_name(parent),
                "to": node_id,
                "required": bool(parent.get("required", True)),
                "conditions": list(parent.get("conditions", [])),
            }
            for parent in action.get("parents", [])
        )
    if exits:
        nodes.append({"id": EXIT, "kind": "exit", "label": "exit", "state": None})
        edges.extend(
            {
                "from": _full_name(e),
                "to": EXIT,
                "required": bool(e.get("required", True)),
                "conditions": list(e.get("conditions", [])),
            }
            for e in exits
        )

    layout = layered_layout([n["id"] for n in nodes], [(e["from"], e["to"]) for e in edges])
    states = {n["id"]: n["state"] for n in nodes}
    for node in nodes:
        node["x"], node["y"] = layout.positions[node["id"]]
        node["layer"] = layout.layers[node["id"]]
    for edge in edges:
        edge["back"] = (edge["from"], edge["to"]) in layout.back_edges
        edge["status"] = edge_status(states.get(edge["from"]), states.get(edge["to"]), edge)
    return {
        "description": snapshot.get("graph_description", ""),
        "nodes": nodes,
        "edges": edges,
        "width": layout.width,
        "height": layout.height,
    }


_ENDED = frozenset({"FINISHED", "ERROR"})
_STARTED = frozenset({"RUNNING", "PAUSE_REQUESTED", "PAUSED", "STOPPING", "FINISHED", "ERROR"})


def edge_status(parent: str | None, child: str | None, edge: Mapping[str, Any]) -> str:
    """``taken``, ``skipped`` or ``pending``: what an edge did, from its ends' states."""
    parent_ended = edge["from"] == ENTRY or parent in _ENDED
    if not parent_ended:
        return "pending"
    if child == "BYPASSED":
        return "skipped"
    if edge["to"] == EXIT or child in _STARTED:
        return "taken"
    return "pending"


def _full_name(ref: Mapping[str, Any]) -> str:
    return f"{ref.get('name', '')}_{ref.get('instance_id', 0)}"


def _error_text(error: BaseException) -> str:
    return f"{type(error).__name__}: {error}"[:MAX_ERROR_CHARS]


def _parameters(params: Any) -> dict[str, Any]:
    """Input parameters as ``{name: value}`` (the value absent when not set)."""
    if not isinstance(params, Mapping):
        return {}
    out: dict[str, Any] = {}
    for name, spec in params.items():
        if isinstance(spec, Mapping) and "pvf_type" in spec:
            entry: dict[str, Any] = {"type": spec["pvf_type"]}
            if spec.get("pvf_value") is not None:  # unset: no value (the page says so)
                entry["value"] = spec["pvf_value"]
            out[str(name)] = entry
        elif isinstance(spec, Mapping):  # a nested parameter tree
            for sub, value in _parameters(spec).items():
                out[f"{name}::{sub}"] = value
    return out


def _held_resources(engine: ActionEngine, run: str) -> dict[str, list[dict[str, Any]]]:
    """The resources each node of a run holds, by node name, from the engine's registrar."""
    registrar = engine.registrar
    if registrar is None:
        return {}
    prefix = f"{run}/"
    held: dict[str, list[dict[str, Any]]] = {}
    for ref in registrar.references():
        if not ref.client.startswith(prefix):
            continue
        node = ref.client[len(prefix) :]
        if "/" in node:  # a client of a run whose name extends this one's
            continue
        try:
            info = registrar.info(ref.resource_id)
        except ResourceNotFoundError:  # released meanwhile
            continue
        held.setdefault(node, []).append(
            {
                "reference": ref.id,
                "resource": ref.resource_id,
                "server": info.server,
                "request": _plain(info.request),
                "exclusive": ref.exclusive,
                "suspended": ref.suspended,
                "failed": info.failed,
            }
        )
    return held


def _plain(value: Any) -> Any:
    """A JSON-ready copy of a request (dataclasses become dicts, anything odd its repr)."""

    def default(obj: Any) -> Any:
        if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
            return dataclasses.asdict(obj)
        if isinstance(obj, enum.Enum):
            return obj.value
        if isinstance(obj, set | frozenset):
            return sorted(obj, key=repr)
        return repr(obj)

    try:
        return json.loads(json.dumps(value, default=default))
    except (TypeError, ValueError):  # circular, or NaN-like trouble
        return repr(value)


def to_json(value: Any) -> str:
    """Serialise an API answer as strict JSON (what browsers parse).

    Non-finite floats (a NaN parameter value) become the strings ``"NaN"``, ``"Infinity"``
    and ``"-Infinity"``; values JSON does not know become their ``repr``.

    Args:
        value: The answer.

    Returns:
        The JSON text (ASCII only).
    """
    try:
        return json.dumps(value, allow_nan=False, default=repr)
    except ValueError:
        return json.dumps(_finite(value), allow_nan=False, default=repr)


def _finite(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return "NaN" if math.isnan(value) else "Infinity" if value > 0 else "-Infinity"
    if isinstance(value, Mapping):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(v) for v in value]
    return value
