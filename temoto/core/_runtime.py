"""Run-time structures of the engine: resolved plans, graph runs and their nodes.

Engine internal. A :class:`Plan` is a graph whose actions were resolved (local class,
sub-graph plan or remote actor) and whose parameters were merged with the action
descriptions; a :class:`GraphRun` is one execution of a plan; a :class:`Node` is one action
instance in it, plus the synthetic ``graph_entry`` and ``graph_exit`` nodes.

All mutable fields are guarded by the engine's lock.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import Enum
from typing import TYPE_CHECKING, Any

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
from temoto.core.params import Parameter
from temoto.core.states import ACTIVE_NODE_STATES, GraphState, NodeState, Response, Result
from temoto.core.umrf import ENTRY_NAME, EXIT_NAME, ParentRelation, Umrf

if TYPE_CHECKING:
    from temoto.core.action import Action, RunControl
    from temoto.core.executor import TimerHandle
    from temoto.core.graph import UmrfGraph
    from temoto.core.umrf import LogMessage

__all__ = [
    "RESPONSES",
    "RESULT_CODES",
    "GraphRun",
    "Node",
    "NodeKind",
    "Plan",
    "ResolvedAction",
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
_NO_NAMES: frozenset[str] = frozenset()  # responses of a relation without written conditions


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
    """

    graph: UmrfGraph
    actions: dict[str, ResolvedAction]
    warnings: tuple[str, ...] = field(default=())


# Enum members read per node or per action, as globals (a member lookup on the enum class costs
# several times a global's)
_UNINITIALIZED = NodeState.UNINITIALIZED
_LOCAL = NodeKind.LOCAL
_EXIT = NodeKind.EXIT

_ACTIVE = ACTIVE_NODE_STATES


class Node:
    """One node of a graph run."""

    __slots__ = (
        "child_run",
        "cls",
        "control",
        "data",
        "error",
        "fresh_instance",
        "gen",
        "held",
        "idx",
        "inline",
        "inputs",
        "instance",
        "kind",
        "last_outputs",
        "log",
        "name",
        "native",
        "outputs",
        "parents",
        "plan",
        "remote_cancel",
        "required_inputs",
        "restart",
        "run",
        "spontaneous",
        "state",
        "stop_timer",
        "umrf",
    )

    def __init__(self, run: GraphRun, umrf: Umrf, resolved: ResolvedAction) -> None:
        self.run = run
        self.name = umrf.full_name
        self.kind = resolved.kind
        self.cls = resolved.cls
        self.plan = resolved.plan
        self.state = _UNINITIALIZED
        self.idx = 0  # number in the run's evolution kernel (set by GraphRun.wire)
        self.parents: dict[str, ParentRelation] = {}
        self.data: dict[str, Any] = {}
        #: inputs holding a literal of the definition (a set of its own once there is one)
        self.native: set[str] | frozenset[str] = _NO_NAMES
        self.gen = 0
        self.control: RunControl | None = None
        self.instance: Action | None = None
        self.fresh_instance = False
        self.held: tuple[Result, dict[str, Any], BaseException | None] | None = None
        self.restart = False
        self.stop_timer: TimerHandle | None = None
        self.child_run: GraphRun | None = None
        self.remote_cancel: Callable[[], None] | None = None  # stops waiting for a remote actor
        self.error: BaseException | None = None
        self.last_outputs: dict[str, Any] = {}
        self.log: tuple[LogMessage, ...] = ()
        self.umrf = umrf
        self.inputs: dict[str, Parameter] = {}
        self.outputs: dict[str, Parameter] = {}
        self.required_inputs: tuple[str, ...] = ()
        self.spontaneous = False
        self.inline = False
        self.define(umrf, resolved)

    def define(self, umrf: Umrf, resolved: ResolvedAction) -> None:
        """Take a (new) definition, keeping state, instance and received data.

        Updatable inputs take the new literal values; others keep theirs.

        Args:
            umrf: The effective action.
            resolved: How it runs.

        Returns:
            None.

        Raises:
            Nothing.
        """
        self.umrf = umrf
        self.kind = resolved.kind
        self.cls = resolved.cls
        self.plan = resolved.plan
        self.spontaneous = umrf.spontaneous
        # runs on the thread that evolves the graph (Action.blocking = False)
        cls = resolved.cls
        self.inline = resolved.kind is _LOCAL and cls is not None and not cls.blocking
        self.inputs = dict(umrf.input_parameters)
        self.outputs = dict(umrf.output_parameters)
        first = not self.native and not self.data
        for name in list(self.native):
            param = self.inputs.get(name)
            if param is None or (not param.has_value and param.updatable):
                self.native.discard(name)  # type: ignore[union-attr]  # no literal for it now
                self.data.pop(name, None)
        for name, param in self.inputs.items():
            if param.has_value and (first or param.updatable or name not in self.data):
                self.data[name] = param.value
                if self.native is _NO_NAMES:
                    self.native = set()
                self.native.add(name)  # type: ignore[union-attr]  # a set by now
        self.required_inputs = tuple(n for n, p in self.inputs.items() if p.required)

    @property
    def active(self) -> bool:
        """Whether the node is running, pausing, paused or stopping."""
        return self.state in _ACTIVE

    def inputs_ready(self) -> bool:
        """Whether every required input holds data (parents are the kernel's business).

        ``graph_exit`` needs no inputs: a missing graph output must not hang the graph.

        Returns:
            True if the inputs allow the node to start.

        Raises:
            Nothing.
        """
        if self.kind is _EXIT:
            return True
        data = self.data
        for name in self.required_inputs:  # noqa: SIM110 - per action: a generator costs more
            if name not in data:
                return False
        return True

    def clear_data(self) -> None:
        """Drop received (non-literal) data after a run; literals persist.

        Returns:
            None.

        Raises:
            Nothing.
        """
        if len(self.data) != len(self.native):
            native = self.native
            self.data = {k: v for k, v in self.data.items() if k in native}

    def __repr__(self) -> str:
        return f"<Node {self.run.name}/{self.name} {self.state.value}>"


class GraphRun:
    """One execution of a plan."""

    __slots__ = (
        "aborted",
        "active",
        "done",
        "edge_child",
        "edge_parent",
        "edge_remap",
        "edge_start",
        "entry",
        "errors",
        "evolution",
        "exit",
        "name",
        "nodes",
        "order",
        "outputs",
        "parent_node",
        "peers",
        "plan",
        "result",
        "session",
        "started_at",
        "state",
        "stop_failed",
        "unwatch",
    )

    def __init__(self, name: str, plan: Plan, parent_node: Node | None = None) -> None:
        self.name = name
        self.plan = plan
        self.parent_node = parent_node
        self.state = GraphState.INITIALIZED
        self.result: Result | None = None
        self.outputs: dict[str, Any] = {}
        self.done = threading.Event()
        self.active = 0
        self.errors: list[BaseException] = []
        self.stop_failed = False
        self.started_at = 0.0
        self.peers: tuple[str, ...] = ()  # the other actors of a shared graph
        self.unwatch: Callable[[], None] | None = None  # stops watching them
        self.session = name  # a shared run's run id, agreed in the handshake
        self.aborted: str | None = None  # why a shared run was aborted, the same on every actor
        signature = plan.graph.signature()
        entry_umrf = Umrf(ENTRY_NAME, "sync")
        exit_umrf = Umrf(EXIT_NAME, "sync")
        self.entry = Node(self, entry_umrf, ResolvedAction(NodeKind.ENTRY))
        self.exit = Node(self, exit_umrf, ResolvedAction(NodeKind.EXIT))
        self.entry.inputs = dict(signature.inputs)
        self.entry.outputs = dict(signature.inputs)
        self.exit.inputs = dict(signature.outputs)
        self.exit.outputs = dict(signature.outputs)
        self.nodes: dict[str, Node] = {}
        self.order: list[Node] = []  # node by kernel number
        # Edges by kernel number, as parallel lists (no object per edge: a big graph's objects
        # are all scanned by the garbage collector once or twice after it is built).
        # Node ``i``'s outgoing edges are ``edge_start[i]`` to ``edge_start[i + 1]``.
        self.edge_start: list[int] = [0]
        self.edge_parent: list[Node] = []
        self.edge_child: list[Node] = []
        self.edge_remap: list[dict[str, str]] = []  # output name -> input name
        self.evolution = Evolution(0, [0], [], [], [], [0], [])
        self.wire(plan)

    def wire(self, plan: Plan) -> None:
        """(Re)build nodes and relations from a plan; surviving nodes keep their run state.

        Args:
            plan: The plan (the current one, or a modification).

        Returns:
            None.

        Raises:
            Nothing (the plan was validated).
        """
        self.plan = plan
        graph = plan.graph
        received = self._received_by_slot()
        nodes: dict[str, Node] = {}
        for umrf in graph.actions:
            resolved = plan.actions[umrf.full_name]
            node = self.nodes.get(umrf.full_name)
            if node is None:
                node = Node(self, umrf, resolved)
            else:
                node.define(umrf, resolved)
            nodes[node.name] = node
        self.nodes = nodes
        entry, exit_ = self.entry, self.exit
        signature = graph.signature()
        entry.inputs = dict(signature.inputs)
        entry.outputs = dict(signature.inputs)
        exit_.inputs = dict(signature.outputs)
        exit_.outputs = dict(signature.outputs)
        entry_parent = ParentRelation(ENTRY_NAME, 0)
        entry_names = {rel.full_name for rel in graph.entry}
        for node in nodes.values():
            node.parents = {p.full_name: p for p in node.umrf.parents}
            if node.name in entry_names:
                node.parents[entry.name] = entry_parent
        exit_.parents = {rel.full_name: rel for rel in graph.exit}
        self._number(graph, received)

    def _received_by_slot(self) -> dict[tuple[str, str], int]:
        """The kernel's received flag of every (child, parent) pair of the current wiring."""
        if not self.order:
            return {}
        flags = self.evolution.received_flags()
        keys = [(node.name, parent) for node in self.order for parent in node.parents]
        return dict(zip(keys, flags, strict=True))

    def _number(self, graph: UmrfGraph, received: dict[tuple[str, str], int]) -> None:
        """Number nodes, edges and slots, and build the evolution kernel for them.

        Received parents survive a re-wiring: a slot whose (child, parent) pair existed before
        keeps its flag (``received``, read before the nodes took their new parents).
        """
        order = [self.entry, *self.nodes.values(), self.exit]
        slot_start = [0]
        flags: list[int] = []
        slot_of: dict[tuple[str, str], int] = {}
        required: list[int] = []
        for i, node in enumerate(order):
            node.idx = i
            name = node.name
            for parent, relation in node.parents.items():
                slot_of[name, parent] = len(required)
                required.append(1 if relation.required else 0)
                if received:
                    flags.append(received.get((name, parent), 0))
            slot_start.append(len(required))
        no_remap: dict[str, str] = {}
        exit_count: dict[str, int] = {}
        for rel in graph.exit:
            exit_count[rel.full_name] = exit_count.get(rel.full_name, 0) + 1
        nodes = self.nodes
        exit_ = self.exit
        edge_parent: list[Node] = []
        edge_child_node: list[Node] = []
        edge_remap: list[dict[str, str]] = []
        edge_start = [0]
        edge_child: list[int] = []
        edge_slot: list[int] = []
        edge_response: list[int] = []
        for node in order:
            if node is self.entry:
                targets = [(nodes[r.full_name], no_remap) for r in graph.entry]
            elif node is exit_:
                targets = []
            else:
                targets = [
                    (nodes[rel.full_name], {r.from_: r.to for r in rel.remap} if rel.remap else {})
                    for rel in node.umrf.children
                ]
                if node.name in exit_count:
                    targets += [(exit_, no_remap)] * exit_count[node.name]
            name = node.name
            for child, remap in targets:
                relation = child.parents[name]
                edge_parent.append(node)
                edge_child_node.append(child)
                edge_remap.append(remap)
                edge_child.append(child.idx)
                edge_slot.append(slot_of[child.name, name])
                conditions = relation.conditions
                if conditions:
                    for result in RESULT_CODES:
                        written = conditions.get(result)
                        edge_response.append(-1 if written is None else _RESPONSE_CODES[written])
                else:
                    edge_response += _NO_CONDITIONS
            edge_start.append(len(edge_child))
        self.order = order
        self.edge_start = edge_start
        self.edge_parent = edge_parent
        self.edge_child = edge_child_node
        self.edge_remap = edge_remap
        self.evolution = Evolution(
            len(order),
            edge_start,
            edge_child,
            edge_slot,
            edge_response,
            slot_start,
            required,
            self.exit.idx,
            flags or [0] * len(required),
        )

    def dispose(self) -> None:
        """Break the reference cycles between a forgotten run and its nodes.

        Called when a new run of the same name replaces an ended one with no active node: its
        nodes, edges and action instances are then freed at once by reference counting,
        instead of waiting for a full garbage collection (which, with a big graph, is a pause
        of tens of milliseconds in the middle of some later run).

        Returns:
            None.

        Raises:
            Nothing.
        """
        for node in self.all_nodes():
            node.child_run = None
        self.nodes = {}
        self.order = []
        self.edge_start = [0]
        self.edge_parent = []
        self.edge_child = []
        self.edge_remap = []

    def children(self, node: Node) -> list[Node]:
        """The children of ``node`` (one per relation, in the kernel's edge order).

        Args:
            node: A node of this run.

        Returns:
            The child nodes (``graph_exit`` included when the node is an exit action).

        Raises:
            Nothing.
        """
        return self.edge_child[self.edge_start[node.idx] : self.edge_start[node.idx + 1]]

    def received_any(self, node: Node) -> bool:
        """Whether any parent of ``node`` finished in this run.

        Args:
            node: A node of this run.

        Returns:
            True if one did.

        Raises:
            Nothing.
        """
        return self.evolution.received_any(node.idx)

    def all_nodes(self) -> list[Node]:
        """Action nodes followed by the entry and exit nodes.

        Returns:
            The nodes.

        Raises:
            Nothing.
        """
        return [*self.nodes.values(), self.entry, self.exit]
