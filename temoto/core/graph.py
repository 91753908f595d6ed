"""The UMRF graph model: actions, entry and exit relations, signature; parse and serialise.

This module only describes graphs; :mod:`temoto.core.validation` checks that a graph can run
and :mod:`temoto.core.engine` runs it. :func:`parse_graph` is the only code that reads a raw
graph document (current format; legacy documents are converted by :mod:`temoto.core.legacy`
first, see :func:`load_graph`).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from temoto.core._gc import collector_paused
from temoto.core.params import Parameter
from temoto.core.params import _kind as kind_of
from temoto.core.states import GraphState
from temoto.core.umrf import (
    ENTRY_NAME,
    EXIT_NAME,
    ChildRelation,
    ParentRelation,
    Umrf,
    UmrfReader,
    decode_json,
    dump_parent,
    dump_umrf,
    load_json,
)
from temoto.errors import GraphDefinitionError

__all__ = [
    "GraphSignature",
    "UmrfGraph",
    "dump_graph",
    "graph_from_document",
    "graph_to_dict",
    "load_graph",
    "parse_graph",
    "parse_graph_text",
]

_GRAPH_KEYS = frozenset(
    {"graph_name", "graph_description", "graph_state", "graph_entry", "graph_exit", "actions"}
)


@dataclass(frozen=True, slots=True)
class GraphSignature:
    """What a graph looks like from outside, when used as an action of another graph.

    Attributes:
        inputs: The external inputs: entry actions' inputs that have no literal value.
        outputs: The exit actions' outputs.
    """

    inputs: Mapping[str, Parameter]
    outputs: Mapping[str, Parameter]

    def matches(self, action: Umrf) -> bool:
        """Whether an action of another graph can be run by this graph (same parameter names).

        Args:
            action: The action that names this graph.

        Returns:
            True if the input and output name sets are equal.

        Raises:
            Nothing.
        """
        return set(self.inputs) == set(action.input_parameters) and set(self.outputs) == set(
            action.output_parameters
        )


@dataclass(frozen=True, slots=True)
class UmrfGraph:
    """A UMRF graph as written (no run-time state besides the written states).

    Attributes:
        name: ``graph_name``; also the name by which other graphs use it as a sub-graph.
        actions: The actions, in document order.
        entry: ``graph_entry``: the actions started first.
        exit: ``graph_exit``: the actions whose results end the graph.
        description: ``graph_description``.
        state: ``graph_state`` as written (UNINITIALIZED if absent).
        source: The file it was read from, if any.
        warnings: Things the parser accepted but doubts (unknown keys, legacy conversion).
    """

    name: str
    actions: tuple[Umrf, ...]
    entry: tuple[ChildRelation, ...]
    exit: tuple[ParentRelation, ...]
    description: str = ""
    state: GraphState = GraphState.UNINITIALIZED
    source: str | None = field(default=None, compare=False)
    warnings: tuple[str, ...] = field(default=(), compare=False)

    def action(self, full_name: str) -> Umrf:
        """Find an action by full name.

        Args:
            full_name: ``<name>_<instance_id>``.

        Returns:
            The action.

        Raises:
            KeyError: If no action has that full name.
        """
        for act in self.actions:
            if act.full_name == full_name:
                return act
        raise KeyError(full_name)

    @property
    def actors(self) -> frozenset[str]:
        """Actors named by the graph's actions (empty names excluded)."""
        return frozenset(a.actor for a in self.actions if a.actor)

    def signature(self) -> GraphSignature:
        """The graph's external inputs and outputs.

        Returns:
            Inputs: entry actions' inputs without a literal; outputs: exit actions' outputs.

        Raises:
            Nothing.
        """
        by_name = {a.full_name: a for a in self.actions}
        inputs: dict[str, Parameter] = {}
        for rel in self.entry:
            act = by_name.get(rel.full_name)
            if act is not None:
                for name, param in act.input_parameters.items():
                    if not param.has_value:
                        inputs.setdefault(name, param)
        outputs: dict[str, Parameter] = {}
        for prel in self.exit:
            act = by_name.get(prel.full_name)
            if act is not None:
                for name, param in act.output_parameters.items():
                    outputs.setdefault(name, param)
        return GraphSignature(inputs, outputs)

    def to_dict(self) -> dict[str, Any]:
        """Serialise canonically (see :func:`graph_to_dict`).

        Returns:
            A JSON-ready dict.

        Raises:
            Nothing.
        """
        return graph_to_dict(self)


def parse_graph(raw: object, *, file: str | None = None) -> UmrfGraph:
    """Parse a current-format graph document.

    Args:
        raw: The decoded JSON document.
        file: The file it came from, for messages.

    Returns:
        The graph. A single action without ``graph_entry``/``graph_exit`` becomes both.

    Raises:
        GraphDefinitionError: With the file and key path of the first problem.
    """
    reader = UmrfReader(file, GraphDefinitionError)
    doc = reader.obj(raw, "")
    if "actions" not in doc and "umrf_actions" in doc:
        raise reader.fail("", "legacy (pre-2023) format: load it with load_graph() to convert it")
    name = reader.string(doc, "graph_name", "", required=True, empty=False)
    if "actions" not in doc:
        raise reader.fail("", "missing required key 'actions'")
    raw_actions = reader.array(doc, "actions", "")
    if not raw_actions:
        raise reader.fail("actions", "a graph needs at least one action")
    actions = tuple(reader.umrf(item, f"actions[{i}]") for i, item in enumerate(raw_actions))
    seen: dict[str, int] = {}
    for i, act in enumerate(actions):
        if act.name in (ENTRY_NAME, EXIT_NAME):
            raise reader.fail(
                f"actions[{i}].name", f"'{act.name}' is reserved for the graph's own node"
            )
        if act.full_name in seen:
            raise reader.fail(
                f"actions[{i}]",
                f"duplicate action '{act.full_name}' (also actions[{seen[act.full_name]}]);"
                " give one of them another instance_id",
            )
        seen[act.full_name] = i
    has_entry, has_exit = "graph_entry" in doc, "graph_exit" in doc
    if not has_entry and not has_exit and len(actions) == 1:
        only = actions[0]
        entry: tuple[ChildRelation, ...] = (ChildRelation(only.name, only.instance_id),)
        exit_: tuple[ParentRelation, ...] = (ParentRelation(only.name, only.instance_id),)
    else:
        for key, present in (("graph_entry", has_entry), ("graph_exit", has_exit)):
            if not present:
                why = (
                    "a graph of several actions"
                    if len(actions) > 1
                    else "a graph that has the other one"
                )
                raise reader.fail("", f"missing '{key}' (required in {why})")
        entry = tuple(
            reader.child(r, f"graph_entry[{i}]")
            for i, r in enumerate(reader.array(doc, "graph_entry", ""))
        )
        exit_ = tuple(
            reader.parent(r, f"graph_exit[{i}]")
            for i, r in enumerate(reader.array(doc, "graph_exit", ""))
        )
        listed: tuple[tuple[str, list[str]], ...] = (
            ("graph_entry", [r.full_name for r in entry]),
            ("graph_exit", [r.full_name for r in exit_]),
        )
        for key, full_names in listed:
            names: set[str] = set()
            for i, full_name in enumerate(full_names):
                if full_name not in seen:
                    raise reader.fail(f"{key}[{i}]", f"unknown action '{full_name}'")
                if full_name in names:
                    raise reader.fail(f"{key}[{i}]", f"'{full_name}' is listed twice")
                names.add(full_name)
    state = GraphState.UNINITIALIZED
    if "graph_state" in doc:
        try:
            state = GraphState(doc["graph_state"])
        except (ValueError, TypeError):
            choices = ", ".join(s.value for s in GraphState)
            raise reader.fail(
                "graph_state",
                f"unknown graph state {kind_of(doc['graph_state'])} (expected one of {choices})",
            ) from None
    reader.unknown(doc, _GRAPH_KEYS, "")
    return UmrfGraph(
        name=name,
        actions=actions,
        entry=entry,
        exit=exit_,
        description=reader.string(doc, "graph_description", ""),
        state=state,
        source=file,
        warnings=tuple(reader.warnings),
    )


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

    Raises:
        Nothing.
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

    Raises:
        Nothing.
    """
    return json.dumps(graph_to_dict(graph), indent=indent, ensure_ascii=False)
