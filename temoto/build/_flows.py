"""Graphs composed of steps: :func:`sequence`, :func:`parallel`, :func:`branch`, :func:`graph`.

Part of :mod:`temoto.build` (its docstring is the overview).
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, TypeAlias

from temoto.build._builder import GraphBuilder, Node
from temoto.core.action import Action
from temoto.core.catalog import ActionCatalog
from temoto.core.graph import UmrfGraph

__all__ = [
    "Flow",
    "Leaf",
    "Step",
    "branch",
    "graph",
    "graph_builder",
    "graph_document",
    "node",
    "parallel",
    "sequence",
]


@dataclass(frozen=True, slots=True)
class Leaf:
    """One node of a composition, with its literal values (made by :func:`node`).

    Attributes:
        target: What the node runs (see :class:`GraphBuilder.add`).
        values: Literal input values.
        instance: Its instance id, or None for the lowest free one.
        actor: The actor that runs it (empty: this one).
        remap: Its outputs renamed for the steps after it: ``{output: their input}``.
    """

    target: type[Action] | str | UmrfGraph
    values: Mapping[str, Any]
    instance: int | None = None
    actor: str = ""
    remap: Mapping[str, str] | None = None


@dataclass(frozen=True, slots=True)
class Flow:
    """A composition of steps (made by :func:`sequence`, :func:`parallel`, :func:`branch`).

    Attributes:
        kind: ``sequence``, ``parallel`` or ``branch``.
        steps: The steps (for a branch: the condition alone).
        arms: A branch's steps by the result that runs them (``on_true``, ``on_false``,
            ``on_error``).
    """

    kind: str
    steps: tuple[Step, ...]
    arms: Mapping[str, Step] = dataclasses.field(default_factory=dict)


#: What a composition is made of: an action (class, catalog name, sub-graph), a :class:`Leaf`
#: or another :class:`Flow`.
Step: TypeAlias = "type[Action] | str | UmrfGraph | Leaf | Flow"


def node(
    target: type[Action] | str | UmrfGraph,
    values: Mapping[str, Any] | None = None,
    /,
    *,
    instance: int | None = None,
    actor: str = "",
    remap: Mapping[str, str] | None = None,
    **more: Any,
) -> Leaf:
    """A step that runs ``target`` with literal input values.

    Args:
        target: A decorated action class, an action's name in the graph's catalog, or a graph.
        values: Literal input values by name (also ``a::b`` names; a :class:`Param` value
            redeclares that input for this node).
        instance: Its instance id (default: the lowest free one).
        actor: The actor that runs it (empty: this one).
        remap: Its outputs renamed for the steps that follow: ``{output: their input}``.
        more: More literal input values, by keyword.

    Returns:
        The step.
    """
    return Leaf(target, {**(values or {}), **more}, instance, actor, remap)


def sequence(*steps: Step) -> Flow:
    """Steps that run one after the other; each one's outputs reach the next by name.

    Args:
        steps: The steps, first first.

    Returns:
        The composition.

    Raises:
        ValueError: No steps.
    """
    if not steps:
        raise ValueError("sequence() needs at least one step")
    return Flow("sequence", steps)


def parallel(*steps: Step) -> Flow:
    """Steps that start together; what follows waits for all of them (a join).

    Args:
        steps: The steps.

    Returns:
        The composition.

    Raises:
        ValueError: No steps.
    """
    if not steps:
        raise ValueError("parallel() needs at least one step")
    return Flow("parallel", steps)


def branch(
    condition: Step,
    *,
    on_true: Step | None = None,
    on_false: Step | None = None,
    on_error: Step | None = None,
) -> Flow:
    """Run ``condition``, then the arm its result names; what follows waits for that arm.

    A result without an arm goes straight to the steps after the branch (``on_error``, by
    default, as an error: the graph then ends ``on_error``). Given an ``on_error`` arm, an
    error runs only that arm.

    Args:
        condition: The step whose result decides (it must end in one node).
        on_true: What runs when it ends ``on_true``.
        on_false: What runs when it ends ``on_false``.
        on_error: What runs when it fails.

    Returns:
        The composition.

    Raises:
        ValueError: No arm is given.
    """
    arms = {
        key: arm
        for key, arm in (("on_true", on_true), ("on_false", on_false), ("on_error", on_error))
        if arm is not None
    }
    if not arms:
        raise ValueError("branch() needs at least one of on_true, on_false, on_error")
    return Flow("branch", (condition,), arms)


def graph(
    *steps: Step, name: str = "graph", description: str = "", catalog: ActionCatalog | None = None
) -> UmrfGraph:
    """A graph that runs ``steps`` in sequence.

    Args:
        steps: The steps (actions, :func:`node` leaves, compositions).
        name: The graph's name.
        description: ``graph_description``.
        catalog: Where actions named by a string are looked up (their parameters come from
            its descriptions).

    Returns:
        The graph, as :func:`~temoto.core.graph.parse_graph` reads its JSON
        (:func:`graph_document` gives that JSON).

    Raises:
        ValueError: No steps, or a composition UMRF cannot express (see ``branch``/``parallel``).
        TypeError: A step is not an action, leaf or composition, or a value does not fit.
        temoto.errors.GraphDefinitionError: The graph is refused as its JSON would be.
    """
    return graph_builder(*steps, name=name, description=description, catalog=catalog).build()


def graph_document(
    *steps: Step, name: str = "graph", description: str = "", catalog: ActionCatalog | None = None
) -> dict[str, Any]:
    """The UMRF JSON document of :func:`graph` (for a ``.graph.json`` file or another tool).

    Args:
        steps: As :func:`graph`.
        name: As :func:`graph`.
        description: As :func:`graph`.
        catalog: As :func:`graph`.

    Returns:
        A JSON-ready dict.

    Raises:
        ValueError: As :func:`graph`.
        TypeError: As :func:`graph`.
    """
    return graph_builder(*steps, name=name, description=description, catalog=catalog).document()


def graph_builder(
    *steps: Step, name: str = "graph", description: str = "", catalog: ActionCatalog | None = None
) -> GraphBuilder:
    """A :class:`GraphBuilder` holding ``steps`` in sequence, to add more by hand.

    Args:
        steps: As :func:`graph`.
        name: As :func:`graph`.
        description: As :func:`graph`.
        catalog: As :func:`graph`.

    Returns:
        The builder, its entry and exit set.

    Raises:
        ValueError: As :func:`graph`.
        TypeError: As :func:`graph`.
    """
    builder = GraphBuilder(name, description=description, catalog=catalog)
    part = _place(builder, sequence(*steps))
    for head in part.heads:
        builder.entry(head)
    for tail in part.tails:
        builder.exit(tail.node, *tail.conditions, required=tail.required)
    return builder


@dataclass(frozen=True, slots=True)
class _Tail:
    """A node that ends a placed part, and how what follows it answers it."""

    node: Node
    conditions: tuple[str, ...] = ()
    required: bool = True
    remap: Mapping[str, str] | None = None


@dataclass(frozen=True, slots=True)
class _Part:
    heads: list[Node]
    tails: list[_Tail]


def _connect(builder: GraphBuilder, tails: Sequence[_Tail], heads: Sequence[Node]) -> None:
    for tail in tails:
        for head in heads:
            builder.link(
                tail.node, head, *tail.conditions, required=tail.required, remap=tail.remap
            )


def _place(builder: GraphBuilder, step: Step) -> _Part:
    """Add a step's nodes and inner links; return where it starts and ends."""
    if isinstance(step, Flow):
        if step.kind == "sequence":
            parts = [_place(builder, s) for s in step.steps]
            for before, after in itertools.pairwise(parts):
                _connect(builder, before.tails, after.heads)
            return _Part(parts[0].heads, parts[-1].tails)
        if step.kind == "parallel":
            parts = [_place(builder, s) for s in step.steps]
            tails = [t for p in parts for t in p.tails]
            if any(not t.required for t in tails):
                raise ValueError(
                    "parallel(): a branch() cannot end a parallel step (UMRF cannot wait for"
                    " 'all of these and one of those'); follow the branch with a step in a"
                    " sequence()"
                )
            return _Part([h for p in parts for h in p.heads], tails)
        return _place_branch(builder, step)
    if isinstance(step, Leaf):
        added = builder.add(step.target, step.values, instance=step.instance, actor=step.actor)
        return _Part([added], [_Tail(added, remap=step.remap)])
    if isinstance(step, type | str | UmrfGraph):
        added = builder.add(step)
        return _Part([added], [_Tail(added)])
    raise TypeError(
        f"{step!r} is not a step: use an action class, an action's name, a graph, node(...),"
        " sequence(...), parallel(...) or branch(...)"
    )


#: The conditions of each arm's link from the condition (the error arm's are fixed).
_IGNORE = {"on_true": "on_true -> ignore", "on_false": "on_false -> ignore"}


def _place_branch(builder: GraphBuilder, flow: Flow) -> _Part:
    cond = _place(builder, flow.steps[0])
    if len(cond.tails) != 1 or not cond.tails[0].required or cond.tails[0].conditions:
        raise ValueError("branch(): the condition must end in one node (an action or a sequence)")
    decider = cond.tails[0]
    on_error = "on_error" in flow.arms
    tails: list[_Tail] = []
    for key, arm in flow.arms.items():
        if key == "on_error":
            conditions: tuple[str, ...] = ("on_error -> run", *_IGNORE.values())
        else:
            other = "on_false" if key == "on_true" else "on_true"
            conditions = (_IGNORE[other], *(("on_error -> ignore",) if on_error else ()))
        part = _place(builder, arm)
        _connect(builder, [dataclasses.replace(decider, conditions=conditions)], part.heads)
        if len(part.tails) > 1 and any(t.required for t in part.tails):
            raise ValueError(
                f"branch(): the {key} arm ends in several nodes at once; end it with one step"
                " (sequence(parallel(...), join_step))"
            )
        tails += [dataclasses.replace(t, required=False) for t in part.tails]
    # results without an arm of their own pass on from the condition itself
    passing = [_IGNORE[k] for k in ("on_true", "on_false") if k in flow.arms]
    if len(passing) < 2:
        if on_error:
            passing.append("on_error -> ignore")
        tails.append(dataclasses.replace(decider, conditions=tuple(passing), required=False))
    return _Part(cond.heads, tails)
