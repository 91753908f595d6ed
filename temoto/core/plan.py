"""Resolved plans: a graph's actions resolved and its relations numbered for the kernel.

Engine internal. A :class:`Plan` is a graph whose actions were resolved (local class,
sub-graph plan or remote actor) and whose parameters were merged with the action
descriptions; its :class:`Wiring` numbers its nodes, slots and edges for the evolution kernel
(:class:`~temoto.core._fast.Evolution`), once per plan. Runs of a plan are in
:mod:`temoto.core._runtime`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum
from typing import TYPE_CHECKING

from temoto.core._fast import (
    P_BYPASS,
    P_IGNORE,
    P_PAUSE,
    P_RESTART,
    P_RUN,
    P_STOP,
    R_ERROR,
    R_FALSE,
    R_STOPPED,
    R_TRUE,
    Evolution,
)
from temoto.core.states import Response, Result
from temoto.core.umrf import ENTRY_NAME, EXIT_NAME, ParentRelation

if TYPE_CHECKING:
    from temoto.core.action import Action
    from temoto.core.graph import UmrfGraph

__all__ = [
    "RESPONSES",
    "RESULT_CODES",
    "NodeKind",
    "Plan",
    "ResolvedAction",
    "Wiring",
    "wiring_of",
]

#: Result -> code of the evolution kernel (the order of the enum).
RESULT_CODES: dict[Result, int] = {
    Result.TRUE: R_TRUE,
    Result.FALSE: R_FALSE,
    Result.STOPPED: R_STOPPED,
    Result.ERROR: R_ERROR,
}
_RESPONSE_CODES: dict[Response, int] = {
    Response.RUN: P_RUN,
    Response.PAUSE: P_PAUSE,
    Response.RESTART: P_RESTART,
    Response.STOP: P_STOP,
    Response.BYPASS: P_BYPASS,
    Response.IGNORE: P_IGNORE,
}
#: Response code of the evolution kernel -> Response.
RESPONSES: tuple[Response, ...] = tuple(sorted(_RESPONSE_CODES, key=_RESPONSE_CODES.__getitem__))
_NO_CONDITIONS = (-1,) * len(RESULT_CODES)


class NodeKind(Enum):
    """How a node is executed."""

    ENTRY = "entry"
    EXIT = "exit"
    LOCAL = "local"
    GRAPH = "graph"
    REMOTE = "remote"


@dataclass(frozen=True, slots=True)
class ResolvedAction:
    """How one action of a plan runs.

    Attributes:
        kind: LOCAL, GRAPH or REMOTE.
        cls: The Action class (LOCAL).
        plan: The sub-graph's plan (GRAPH).
    """

    kind: NodeKind
    cls: type[Action] | None = None
    plan: Plan | None = None


@dataclass(frozen=True, slots=True)
class Plan:
    """A graph ready to run: effective actions and how each is executed.

    Attributes:
        graph: The graph with parameters merged from the action descriptions.
        actions: Resolution by full name.
        warnings: Validation warnings (already logged).
        wiring: The numbering of its nodes and relations for the evolution kernel, made once
            by its first run (:func:`wiring_of`).
    """

    graph: UmrfGraph
    actions: dict[str, ResolvedAction]
    warnings: tuple[str, ...] = field(default=())
    #: the numbering of its nodes and relations, made by the first run (:func:`wiring_of`)
    wiring: Wiring | None = field(default=None, init=False, compare=False, repr=False)


_ENTRY_FULL_NAME = f"{ENTRY_NAME}_0"
_EXIT_FULL_NAME = f"{EXIT_NAME}_0"
_NO_REMAP: dict[str, str] = {}  # the remap of every relation without one (never written)


class Wiring:
    """The numbering of a plan's nodes, slots and edges for the evolution kernel.

    It depends on the plan only, so it is made once per plan (:func:`wiring_of`) and shared by
    every run of it: a run adds its nodes, and nothing per relation (a big graph's objects are
    all scanned by the garbage collector once or twice after they are made).

    Node ``i`` of a run is ``names[i]``: ``graph_entry``, the actions in the graph's order,
    ``graph_exit``. The arrays are the kernel's (:class:`~temoto.core._fast.Evolution`);
    ``edge_parent`` is each edge's parent node, ``edge_remap`` its remap (output name -> input
    name), ``slot_parent`` each slot's parent name (:meth:`slot_keys` pairs it with the child's).
    ``signature`` (the graph's external inputs and outputs) and ``actors`` (the actors its
    actions name) are what starting a run reads of the graph, kept here so that a start of a
    planned graph does no work per action for them.
    """

    __slots__ = (
        "_kernel",
        "actors",
        "edge_child",
        "edge_parent",
        "edge_remap",
        "edge_response",
        "edge_slot",
        "edge_start",
        "names",
        "signature",
        "slot_parent",
        "slot_required",
        "slot_start",
    )

    def __init__(self, graph: UmrfGraph) -> None:
        self._kernel: Evolution | None = None  # the template of kernel(), made on first use
        self.signature = graph.signature()
        #: the actors the graph's actions name (empty: a graph of this actor only)
        self.actors = graph.actors
        names = [_ENTRY_FULL_NAME, *(umrf.full_name for umrf in graph.actions), _EXIT_FULL_NAME]
        index = {name: i for i, name in enumerate(names)}
        entry_names = {rel.full_name for rel in graph.entry}
        entry_parent = ParentRelation(ENTRY_NAME, 0)
        # parents by node (kernel order), as name -> relation
        parents: list[dict[str, ParentRelation]] = [{}]
        for umrf in graph.actions:
            mine = {p.full_name: p for p in umrf.parents}
            if umrf.full_name in entry_names:
                mine[_ENTRY_FULL_NAME] = entry_parent
            parents.append(mine)
        parents.append({rel.full_name: rel for rel in graph.exit})
        slot_start = [0]
        slot_parent: list[str] = []
        slot_of: dict[tuple[str, str], int] = {}
        required: list[int] = []
        for name, mine in zip(names, parents, strict=True):
            for parent, relation in mine.items():
                slot_of[name, parent] = len(required)
                slot_parent.append(parent)
                required.append(1 if relation.required else 0)
            slot_start.append(len(required))
        exit_count: dict[str, int] = {}
        for rel in graph.exit:
            exit_count[rel.full_name] = exit_count.get(rel.full_name, 0) + 1
        exit_idx = len(names) - 1
        edge_start = [0]
        edge_parent: list[int] = []
        edge_child: list[int] = []
        edge_slot: list[int] = []
        edge_remap: list[dict[str, str]] = []
        edge_response: list[int] = []
        for i, name in enumerate(names):
            if i == 0:
                targets = [(index[r.full_name], _NO_REMAP) for r in graph.entry]
            elif i == exit_idx:
                targets = []
            else:
                umrf = graph.actions[i - 1]
                targets = [
                    (
                        index[rel.full_name],
                        {r.from_: r.to for r in rel.remap} if rel.remap else _NO_REMAP,
                    )
                    for rel in umrf.children
                ]
                if name in exit_count:
                    targets += [(exit_idx, _NO_REMAP)] * exit_count[name]
            for child, remap in targets:
                child_name = names[child]
                relation = parents[child][name]
                edge_parent.append(i)
                edge_child.append(child)
                edge_remap.append(remap)
                edge_slot.append(slot_of[child_name, name])
                conditions = relation.conditions
                if conditions:
                    for result in RESULT_CODES:
                        written = conditions.get(result)
                        edge_response.append(-1 if written is None else _RESPONSE_CODES[written])
                else:
                    edge_response += _NO_CONDITIONS
            edge_start.append(len(edge_child))
        self.names = names
        self.slot_start = slot_start
        self.slot_parent = slot_parent
        self.slot_required = required
        self.edge_start = edge_start
        self.edge_parent = edge_parent
        self.edge_child = edge_child
        self.edge_slot = edge_slot
        self.edge_remap = edge_remap
        self.edge_response = edge_response

    def kernel(self, received: list[int] | None = None) -> Evolution:
        """A new evolution kernel for a run of the plan (node ``i`` is ``names[i]``).

        The first call builds a template (the kernel's constructor checks and converts every
        array); every run's kernel is then :meth:`Evolution.fresh
        <temoto.core._fast._evolution_py.Evolution.fresh>` of it, sharing the arrays.

        Args:
            received: The received flag of every slot, for a re-wired run that keeps what it
                received; nothing received if omitted.

        Returns:
            The kernel.

        Raises:
            ValueError: ``received`` has not one flag per slot.
        """
        n = len(self.names)
        shape = (
            n,
            self.edge_start,
            self.edge_child,
            self.edge_slot,
            self.edge_response,
            self.slot_start,
            self.slot_required,
            n - 1,
        )
        if received is not None:
            return Evolution(*shape, received)
        template = self._kernel
        if template is None:
            template = self._kernel = Evolution(*shape)
        return template.fresh()

    def slot_keys(self) -> list[tuple[str, str]]:
        """The (child, parent) pair of names of every slot, in slot order.

        Made on demand (a modification carries the received flags over by these keys), not
        kept: a pair per relation would be as many more objects per plan.

        Returns:
            The pairs.
        """
        names, start, parents = self.names, self.slot_start, self.slot_parent
        return [
            (names[c], parents[s]) for c in range(len(names)) for s in range(start[c], start[c + 1])
        ]


def wiring_of(plan: Plan) -> Wiring:
    """The plan's wiring, made on first use and kept with the plan (it never changes).

    Args:
        plan: A plan.

    Returns:
        Its wiring.
    """
    wiring = plan.wiring
    if wiring is None:
        wiring = Wiring(plan.graph)
        # a cache of a value derived from the frozen plan's own fields: set once, never changed
        object.__setattr__(plan, "wiring", wiring)
    return wiring
