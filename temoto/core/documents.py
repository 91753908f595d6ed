"""UMRF documents: load, decode and dump action descriptions and graphs.

The models and their parsers live elsewhere: :mod:`temoto.core.umrf` (actions,
:func:`~temoto.core.umrf.parse_umrf`), :mod:`temoto.core.graph` (graphs,
:func:`~temoto.core.graph.parse_graph`) and :mod:`temoto.core.legacy` (pre-2023 documents,
converted to the current format). This module is where a document meets a file or a string:
reading JSON with errors that name the file, telling the two formats apart, and writing
upstream's canonical form. It imports the three others, and none of them imports it.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

from temoto._files import read_regular_text
from temoto.core._gc import collector_paused
from temoto.core.graph import UmrfGraph, parse_graph
from temoto.core.params import dump_parameter_tree
from temoto.core.states import GraphState
from temoto.core.umrf import (
    CONDITION_RESULTS,
    ChildRelation,
    ErrorFactory,
    ParentRelation,
    Umrf,
    parse_umrf,
)
from temoto.errors import ConfigError, GraphDefinitionError, UmrfError

__all__ = [
    "decode_json",
    "dump_child",
    "dump_graph",
    "dump_parent",
    "dump_umrf",
    "graph_from_document",
    "graph_to_dict",
    "load_graph",
    "load_json",
    "load_umrf",
    "parse_graph_text",
]


def _reject_constant(name: str) -> Any:
    raise ValueError(f"{name} is not valid JSON")


def load_json(path: str | Path, error: ErrorFactory = ConfigError) -> Any:
    """Read and decode a JSON file, turning every failure into a ConfigError.

    Args:
        path: The file.
        error: The ConfigError subclass to raise.

    Returns:
        The decoded document.

    Raises:
        ConfigError: (the ``error`` subclass) if the file cannot be read or is not JSON.
    """
    file = str(path)
    try:
        text = read_regular_text(path)
    except UnicodeDecodeError as err:
        raise error(f"not UTF-8 text ({err.reason} at byte {err.start})", file=file) from None
    except OSError as err:
        raise error(f"cannot read: {err.strerror or err}", file=file) from None
    return decode_json(text, file=file, error=error)


def decode_json(text: str, *, file: str | None = None, error: ErrorFactory = ConfigError) -> Any:
    """Decode JSON text, turning every failure into a ConfigError.

    Args:
        text: The JSON text.
        file: Where it came from, for messages.
        error: The ConfigError subclass to raise.

    Returns:
        The decoded document.

    Raises:
        ConfigError: (the ``error`` subclass) if the text is not valid JSON, or holds a lone
            UTF-16 surrogate (an escape in D800-DFFF without its pair: no character).
    """
    try:
        doc = json.loads(text, parse_constant=_reject_constant)
    except json.JSONDecodeError as err:
        raise error(
            f"invalid JSON at line {err.lineno} column {err.colno}: {err.msg}", file=file
        ) from None
    except ValueError as err:
        raise error(f"invalid JSON: {err}", file=file) from None
    except RecursionError:
        raise error("invalid JSON: nested too deeply", file=file) from None
    if _SURROGATE_ESCAPE.search(text):
        where = _lone_surrogate(doc, "")
        if where is not None:
            raise error(
                "a lone UTF-16 surrogate (\\ud800-\\udfff without its pair) is no character",
                file=file,
                path=where,
            )
    return doc


#: a JSON escape of a UTF-16 surrogate: the only way one gets into a decoded document
_SURROGATE_ESCAPE = re.compile(r"\\u[dD][89a-fA-F]")


def _lone_surrogate(value: Any, path: str) -> str | None:
    """The key path of the first string (key or value) holding a lone surrogate, or None."""
    if isinstance(value, str):
        try:
            value.encode("utf-8")
        except UnicodeEncodeError:
            return path
        return None
    if isinstance(value, dict):
        for key, item in value.items():
            inner = f"{path}.{key}" if path else str(key)
            found = _lone_surrogate(key, path or "(a key)")
            if found is not None:
                return found
            found = _lone_surrogate(item, inner)
            if found is not None:
                return found
    elif isinstance(value, list):
        for i, item in enumerate(value):
            found = _lone_surrogate(item, f"{path}[{i}]")
            if found is not None:
                return found
    return None


def load_umrf(path: str | Path, *, warnings: list[str] | None = None) -> Umrf:
    """Read an action description file (``<snake_name>.umrf.json``).

    Legacy (pre-2023) descriptions are converted, with a warning that says what changed.

    Args:
        path: The file.
        warnings: A list that receives warnings.

    Returns:
        The description.

    Raises:
        UmrfError: If the file cannot be read or is invalid.
    """
    from temoto.core import legacy  # legacy is only needed for old files

    raw = load_json(path, UmrfError)
    if legacy.is_legacy_umrf(raw):
        raw = legacy.convert_umrf(raw, file=str(path), warnings=warnings)
    return parse_umrf(raw, file=str(path), warnings=warnings)


def dump_umrf(action: Umrf, *, with_relations: bool = True) -> dict[str, Any]:
    """Serialise an action in upstream's canonical form.

    Args:
        action: The action.
        with_relations: Emit ``parents``/``children`` (graph nodes) or not (descriptions).

    Returns:
        A JSON-ready dict.
    """
    out: dict[str, Any] = {
        "name": action.name,
        "instance_id": action.instance_id,
        "description": action.description,
        "type": action.type,
        "state": action.state.value,
    }
    if action.actor:
        out["actor"] = action.actor
    if action.input_parameters:
        out["input_parameters"] = dump_parameter_tree(action.input_parameters)
    if action.output_parameters:
        out["output_parameters"] = dump_parameter_tree(action.output_parameters)
    if with_relations:
        parents = [dump_parent(p) for p in action.parents]
        if parents:
            out["parents"] = parents
        children = [dump_child(c) for c in action.children]
        if children:
            out["children"] = children
    if action.gui_attributes is not None:
        out["gui_attributes"] = action.gui_attributes
    if action.runtime_messages:
        out["runtime"] = {
            "messages": [
                {"timestamp": m.timestamp_ms, "message": m.message} for m in action.runtime_messages
            ]
        }
    return out


def dump_parent(rel: ParentRelation, *, conditions: bool = True) -> dict[str, Any]:
    """Serialise a parent relation (all four conditions, in upstream's order).

    Args:
        rel: The relation.
        conditions: Whether to emit conditions (``graph_exit`` entries omit them upstream).

    Returns:
        A JSON-ready dict.
    """
    out: dict[str, Any] = {
        "name": rel.name,
        "instance_id": rel.instance_id,
        "required": rel.required,
    }
    if conditions:
        out["conditions"] = [f"{r.value} -> {rel.response(r).value}" for r in CONDITION_RESULTS]
    return out


def dump_child(rel: ChildRelation) -> dict[str, Any]:
    """Serialise a child relation.

    Args:
        rel: The relation.

    Returns:
        A JSON-ready dict.
    """
    out: dict[str, Any] = {"name": rel.name, "instance_id": rel.instance_id}
    if rel.remap:
        out["remap"] = [{"from": r.from_, "to": r.to} for r in rel.remap]
    return out


def parse_graph_text(text: str, *, file: str | None = None) -> UmrfGraph:
    """Parse a graph from JSON text (either format).

    Args:
        text: JSON text.
        file: Where it came from, for messages.

    Returns:
        The graph (legacy documents converted, with a warning).

    Raises:
        GraphDefinitionError: If the text is not JSON or not a valid graph.
    """
    with collector_paused():
        raw = decode_json(text, file=file, error=GraphDefinitionError)
        return graph_from_document(raw, file=file)


def load_graph(path: str | Path) -> UmrfGraph:
    """Read a graph file; legacy (pre-2023) documents are converted with a warning.

    Args:
        path: The file.

    Returns:
        The graph.

    Raises:
        GraphDefinitionError: If the file cannot be read, is not JSON, or is not a valid graph.
    """
    with collector_paused():
        return graph_from_document(load_json(path, GraphDefinitionError), file=str(path))


def graph_from_document(raw: object, *, file: str | None = None) -> UmrfGraph:
    """Parse a decoded graph document of either format.

    Args:
        raw: The decoded JSON document.
        file: Where it came from, for messages.

    Returns:
        The graph (legacy documents converted, with a warning).

    Raises:
        GraphDefinitionError: If it is not a valid graph.
    """
    from temoto.core import legacy  # only needed for old documents

    if legacy.is_legacy_graph(raw):
        return legacy.convert_graph(raw, file=file)
    return parse_graph(raw, file=file)


def graph_to_dict(graph: UmrfGraph, actions: list[dict[str, Any]] | None = None) -> dict[str, Any]:
    """Serialise a graph in upstream's canonical form.

    ``graph_state`` only if set and not UNINITIALIZED; ``graph_entry`` and ``graph_exit``
    always (exit entries carry ``conditions`` only when some were written, which upstream
    drops); ``actions`` sorted by full name.

    Args:
        graph: The graph.
        actions: Pre-serialised actions (feedback snapshots with run-time states); default
            is the graph's own actions.

    Returns:
        A JSON-ready dict that :func:`parse_graph` reads back to a graph with the same
        meaning (actions sorted by full name, every condition written out).
    """
    out: dict[str, Any] = {"graph_name": graph.name, "graph_description": graph.description}
    if graph.state is not GraphState.UNINITIALIZED:
        out["graph_state"] = graph.state.value
    out["graph_entry"] = [{"name": r.name, "instance_id": r.instance_id} for r in graph.entry]
    out["graph_exit"] = [dump_parent(r, conditions=bool(r.conditions)) for r in graph.exit]
    if actions is None:
        actions = [dump_umrf(a) for a in sorted(graph.actions, key=lambda a: a.full_name)]
    out["actions"] = actions
    return out


def dump_graph(graph: UmrfGraph, *, indent: int | None = 2) -> str:
    """Serialise a graph to JSON text (canonical form).

    Args:
        graph: The graph.
        indent: JSON indentation, or None for one line.

    Returns:
        JSON text.
    """
    return json.dumps(graph_to_dict(graph), indent=indent, ensure_ascii=False)
