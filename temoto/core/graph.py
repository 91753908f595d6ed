"""The UMRF graph model: actions, entry and exit relations, signature; and its parser.

This module only describes graphs; :mod:`temoto.core.validation` checks that a graph can run
and :mod:`temoto.core.engine` runs it. :func:`parse_graph` is the only code that reads a raw
graph document (current format; legacy documents are converted by :mod:`temoto.core.legacy`
first). Files, text and serialisation are :mod:`temoto.core.documents`
(:func:`~temoto.core.documents.load_graph`, :func:`~temoto.core.documents.graph_to_dict`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

from temoto.core.params import Parameter, kind_of
from temoto.core.states import GraphState
from temoto.core.umrf import (
    ENTRY_NAME,
    EXIT_NAME,
    ChildRelation,
    ParentRelation,
    Umrf,
    UmrfReader,
)
from temoto.errors import GraphDefinitionError

__all__ = [
    "GraphSignature",
    "UmrfGraph",
    "parse_graph",
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
