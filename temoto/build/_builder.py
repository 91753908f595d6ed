"""Graphs built node by node: :class:`GraphBuilder` and its :class:`Node` handles.

Part of :mod:`temoto.build` (its docstring is the overview).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, TypeAlias

from temoto.build._actions import Param, description_of
from temoto.core.action import Action
from temoto.core.catalog import ActionCatalog
from temoto.core.graph import UmrfGraph, parse_graph
from temoto.core.params import NATIVE_TYPES, check_value, dump_parameter_tree
from temoto.core.umrf import Umrf
from temoto.errors import ActionNotFoundError

__all__ = ["ActionRef", "GraphBuilder", "Node"]


@dataclass(frozen=True, slots=True, eq=False)
class Node:
    """A node of a graph under construction (made by :meth:`GraphBuilder.add`).

    Attributes:
        name: The action's name.
        instance_id: Its instance in the graph.
    """

    name: str
    instance_id: int

    @property
    def full_name(self) -> str:
        """``<name>_<instance_id>``, the node's key in the graph."""
        return f"{self.name}_{self.instance_id}"


#: What a node runs: a decorated action class, an action's name in the builder's catalog, or a
#: graph (run as a sub-graph, with its signature as the node's parameters).
ActionRef: TypeAlias = "type[Action] | str | UmrfGraph"


class GraphBuilder:
    """Builds a graph node by node: ``add`` nodes, ``link`` them, name ``entry`` and ``exit``.

    Args:
        name: The graph's name.
        description: ``graph_description``.
        catalog: Where actions named by a string are looked up.
    """

    def __init__(
        self, name: str, *, description: str = "", catalog: ActionCatalog | None = None
    ) -> None:
        self.name = name
        self.description = description
        self.catalog = catalog
        self._nodes: dict[str, dict[str, Any]] = {}
        self._entry: list[dict[str, Any]] = []
        self._exit: list[dict[str, Any]] = []
        self._used: dict[str, set[int]] = {}  # instance ids by action name
        self._free: dict[str, int] = {}  # no free id below this, by action name

    def add(
        self,
        target: ActionRef,
        values: Mapping[str, Any] | None = None,
        /,
        *,
        instance: int | None = None,
        actor: str = "",
        **more: Any,
    ) -> Node:
        """Add a node with its action's parameters and the given literal input values.

        Args:
            target: A decorated action class, an action's name (looked up in the catalog) or a
                graph (a sub-graph node).
            values: Literal input values by parameter name (``a::b`` names too). A
                :class:`Param` value replaces the parameter's declaration for this node (its
                ``default`` is the literal).
            instance: Its instance id (default: the lowest free one for this name).
            actor: The actor that runs it (empty: this one).
            more: More literal input values, by keyword.

        Returns:
            The node.

        Raises:
            ValueError: The instance id is taken, or an input is unknown.
            TypeError: A value does not fit its input's type.
            temoto.errors.ActionNotFoundError: A named action is not in the catalog.
        """
        umrf = self._description(target)
        used = self._used.setdefault(umrf.name, set())
        if instance is None:
            instance = self._free.get(umrf.name, 0)
            while instance in used:
                instance += 1
            self._free[umrf.name] = instance + 1
        elif instance in used:
            raise ValueError(f"graph '{self.name}' already has a node {umrf.name}_{instance}")
        new = Node(umrf.name, instance)
        used.add(instance)
        given = {**(values or {}), **more}
        params = dict(umrf.input_parameters)
        literals: dict[str, Any] = {}
        for key, value in given.items():
            declared = params.get(key)
            if declared is None:
                known = ", ".join(params) or "none"
                raise ValueError(f"{new.full_name}: no input '{key}' (its inputs: {known})")
            if isinstance(value, Param):
                params[key] = value.parameter(key)
                continue
            if declared.type in NATIVE_TYPES:
                try:
                    value = check_value(declared.type, value)
                except TypeError as err:
                    raise TypeError(
                        f"{new.full_name}: input '{key}' ({declared.type}): {err}"
                    ) from None
            literals[key] = value
        params = {
            key: dataclasses.replace(p, value=literals[key]) if key in literals else p
            for key, p in params.items()
        }
        raw: dict[str, Any] = {"name": umrf.name, "instance_id": instance, "type": umrf.type}
        if actor:
            raw["actor"] = actor
        if params:
            raw["input_parameters"] = dump_parameter_tree(params)
        if umrf.output_parameters:
            raw["output_parameters"] = dump_parameter_tree(umrf.output_parameters)
        self._nodes[new.full_name] = raw
        return new

    def link(
        self,
        parent: Node,
        child: Node,
        *conditions: str,
        required: bool = True,
        remap: Mapping[str, str] | None = None,
    ) -> None:
        """Make ``child`` follow ``parent`` (both sides of the relation are written).

        Args:
            parent: The parent node.
            child: The child node.
            conditions: How the child answers the parent's results, in UMRF's form
                (``"on_false -> ignore"``); the others keep their defaults.
            required: Whether the child waits for this parent (False: the first non-required
                parent to end starts it).
            remap: The parent's outputs renamed for this child: ``{output: child's input}``.
        """
        mine = self._raw(parent)
        theirs = self._raw(child)
        down: dict[str, Any] = {"name": child.name, "instance_id": child.instance_id}
        if remap:
            down["remap"] = [{"from": f, "to": t} for f, t in remap.items()]
        mine.setdefault("children", []).append(down)
        theirs.setdefault("parents", []).append(_parent(parent, conditions, required))

    def entry(self, node: Node, *, remap: Mapping[str, str] | None = None) -> None:
        """Start the graph with ``node``.

        Args:
            node: An entry node.
            remap: The graph's inputs renamed for it: ``{graph input: node's input}``.
        """
        self._raw(node)
        rel: dict[str, Any] = {"name": node.name, "instance_id": node.instance_id}
        if remap:
            rel["remap"] = [{"from": f, "to": t} for f, t in remap.items()]
        self._entry.append(rel)

    def exit(self, node: Node, *conditions: str, required: bool = True) -> None:
        """End the graph with ``node`` (its outputs become the graph's).

        Args:
            node: An exit node.
            conditions: Which of its results end the graph (``"on_false -> ignore"``).
            required: With several required exits the graph ends when all have ended; a
                non-required one ends it alone.
        """
        self._raw(node)
        self._exit.append(_parent(node, conditions, required))

    def document(self) -> dict[str, Any]:
        """The graph as a UMRF JSON document (``json.dumps`` writes its ``.graph.json``).

        Returns:
            A new JSON-ready dict.
        """
        doc: dict[str, Any] = {"graph_name": self.name}
        if self.description:
            doc["graph_description"] = self.description
        doc["graph_entry"] = [dict(r) for r in self._entry]
        doc["graph_exit"] = [dict(r) for r in self._exit]
        doc["actions"] = [_copy(raw) for raw in self._nodes.values()]
        return doc

    def build(self) -> UmrfGraph:
        """Parse :meth:`document`: the graph its JSON would be.

        Returns:
            The graph.

        Raises:
            temoto.errors.GraphDefinitionError: What the JSON would be refused for.
        """
        return parse_graph(self.document())

    def _raw(self, node: Node) -> dict[str, Any]:
        found = self._nodes.get(node.full_name)
        if found is None:
            raise ValueError(f"graph '{self.name}' has no node {node.full_name}")
        return found

    def _description(self, target: ActionRef) -> Umrf:
        if isinstance(target, UmrfGraph):
            sig = target.signature()
            return Umrf(
                target.name,
                "sync",
                input_parameters=sig.inputs,
                output_parameters=sig.outputs,
            )
        if isinstance(target, str):
            found = None if self.catalog is None else self.catalog.find(target)
            if found is None:
                where = "its catalog" if self.catalog is not None else "no catalog (pass one)"
                raise ActionNotFoundError(
                    f"graph '{self.name}': no action named '{target}' in {where}"
                )
            return found
        return description_of(target)


def _copy(raw: dict[str, Any]) -> dict[str, Any]:
    out = dict(raw)
    for key in ("parents", "children"):
        if key in out:
            out[key] = [dict(r) for r in out[key]]
    return out


def _parent(node: Node, conditions: Sequence[str], required: bool) -> dict[str, Any]:
    rel: dict[str, Any] = {"name": node.name, "instance_id": node.instance_id}
    if not required:
        rel["required"] = False
    if conditions:
        rel["conditions"] = list(conditions)
    return rel
