"""Run-time structures of the engine: resolved plans, graph runs and their nodes.

Engine internal. A :class:`Plan` is a graph whose actions were resolved (local class,
sub-graph plan or remote actor) and whose parameters were merged with the action
descriptions; a :class:`GraphRun` is one execution of a plan; a :class:`Node` is one action
instance in it, plus the synthetic ``graph_entry`` and ``graph_exit`` nodes.

All mutable fields are guarded by the engine's lock.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from enum import Enum
from typing import TYPE_CHECKING, Any

from temoto.clock import MonotonicClock
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
from temoto.core.control import RunControl
from temoto.core.params import Parameter
from temoto.core.states import ACTIVE_NODE_STATES, GraphState, NodeState, Response, Result
from temoto.core.umrf import ENTRY_NAME, EXIT_NAME, ParentRelation, Umrf

if TYPE_CHECKING:
    from temoto.clock import Clock
    from temoto.core.action import Action
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
        wiring: The numbering of its nodes and relations for the evolution kernel, made once
            by its first run (:func:`wiring_of`).
    """

    graph: UmrfGraph
    actions: dict[str, ResolvedAction]
    warnings: tuple[str, ...] = field(default=())
    #: the numbering of its nodes and relations, made by the first run (:func:`wiring_of`)
    wiring: Wiring | None = field(default=None, init=False, compare=False, repr=False)


# Enum members read per node or per action, as globals (a member lookup on the enum class costs
# several times a global's)
_UNINITIALIZED = NodeState.UNINITIALIZED
_LOCAL = NodeKind.LOCAL
_EXIT = NodeKind.EXIT

_ACTIVE = ACTIVE_NODE_STATES

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
    """

    __slots__ = (
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
        self.signature = graph.signature()
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

    def slot_keys(self) -> list[tuple[str, str]]:
        """The (child, parent) pair of names of every slot, in slot order.

        Made on demand (a modification carries the received flags over by these keys), not
        kept: a pair per relation would be as many more objects per plan.

        Returns:
            The pairs.

        Raises:
            Nothing.
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

    Raises:
        Nothing (the plan was validated).
    """
    wiring = plan.wiring
    if wiring is None:
        wiring = Wiring(plan.graph)
        # a cache of a value derived from the frozen plan's own fields: set once, never changed
        object.__setattr__(plan, "wiring", wiring)
    return wiring


class Node(RunControl):
    """One node of a graph run; it is also the node's :class:`RunControl`.

    The node carries its action's stop and pause signals itself (the action's helpers wait on
    them), so a node costs one object, not two, for the garbage collector to scan.
    """

    __slots__ = (
        "child_run",
        "cls",
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
        # RunControl's fields, set here (no call of its __init__ per node)
        self.clock = run.clock
        self.condition = None
        self.stop = False
        self.paused = False
        self.broken = None
        self.logged = False
        self.acquired = False
        self.run = run
        self.name = umrf.full_name
        self.state = _UNINITIALIZED
        self.idx = 0  # number in the run's evolution kernel (set by GraphRun.wire)
        self.data: dict[str, Any] = {}
        #: inputs holding a literal of the definition (a set of its own once there is one)
        self.native: set[str] | frozenset[str] = _NO_NAMES
        self.gen = 0
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
        # the definition's own mappings (never written here): no copy per node
        self.inputs: Mapping[str, Parameter] = umrf.input_parameters
        self.outputs: Mapping[str, Parameter] = umrf.output_parameters
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
        self.required_inputs = (
            tuple(n for n, p in self.inputs.items() if p.required) if self.inputs else ()
        )

    def renew(self, run: GraphRun) -> None:
        """Become a fresh node of ``run``, a new run of the same plan (this node's run ended).

        Everything of the old run is forgotten (state, data, action instance, signals, log)
        except the generation counter, which moves on: anything still addressed to the old
        run's node (a hook, a late result) is stale and dropped, as for any earlier run.
        The caller re-applies the definition (:meth:`define`, through ``GraphRun.wire``).

        Args:
            run: The new run.

        Returns:
            None.

        Raises:
            Nothing.
        """
        self.run = run
        self.clock = run.clock
        self.condition = None
        self.stop = False
        self.paused = False
        self.broken = None
        self.logged = False
        self.acquired = False
        self.state = _UNINITIALIZED
        self.data = {}
        self.native = _NO_NAMES
        self.gen += 1
        self.instance = None
        self.fresh_instance = False
        self.held = None
        self.restart = False
        self.stop_timer = None
        self.child_run = None
        self.remote_cancel = None
        self.error = None
        self.last_outputs = {}
        self.log = ()

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
    """One execution of a plan.

    Args:
        name: The run's name.
        plan: The plan it executes.
        parent_node: The node whose sub-graph this run is, if it is one.
        clock: The engine's clock (read by the actions' helpers); real time if omitted.
        reuse: An ended run of the same plan that nobody needs any more
            (:meth:`can_lend_nodes`): its node objects are taken over, renewed
            (:meth:`Node.renew`), instead of made anew. A robot that runs the
            same task again then makes no object per node: the garbage collector's scan of a
            new run's objects, which grows with the graph, is spared. The old run is disposed.
    """

    __slots__ = (
        "aborted",
        "active",
        "clock",
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
        "wiring",
    )

    def __init__(
        self,
        name: str,
        plan: Plan,
        parent_node: Node | None = None,
        *,
        clock: Clock | None = None,
        reuse: GraphRun | None = None,
    ) -> None:
        self.name = name
        self.plan = plan
        self.clock: Clock = clock if clock is not None else MonotonicClock()
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
        self.nodes: dict[str, Node] = {}
        self.entry: Node
        self.exit: Node
        if reuse is not None and reuse.plan is plan:
            # the ended run's nodes become this run's, as new (see Node.renew)
            entry, exit_, nodes = reuse.entry, reuse.exit, reuse.nodes
            reuse.dispose()
            for node in (entry, exit_, *nodes.values()):
                node.renew(self)
            self.entry, self.exit, self.nodes = entry, exit_, nodes
        else:
            self.entry = Node(self, Umrf(ENTRY_NAME, "sync"), ResolvedAction(NodeKind.ENTRY))
            self.exit = Node(self, Umrf(EXIT_NAME, "sync"), ResolvedAction(NodeKind.EXIT))
        self.order: list[Node] = []  # node by kernel number
        # Edges by kernel number, as parallel lists (no object per edge).
        # Node ``i``'s outgoing edges are ``edge_start[i]`` to ``edge_start[i + 1]``.
        self.edge_start: list[int] = [0]
        self.edge_parent: list[Node] = []
        self.edge_child: list[Node] = []
        self.edge_remap: list[dict[str, str]] = []  # output name -> input name
        self.evolution = Evolution(0, [0], [], [], [], [0], [])
        self.wiring = wiring_of(plan)
        self.wire(plan)

    def wire(self, plan: Plan) -> None:
        """(Re)build nodes and relations from a plan; surviving nodes keep their run state.

        Received parents survive a re-wiring: a slot whose (child, parent) pair existed before
        keeps its flag.

        Args:
            plan: The plan (the current one, or a modification).

        Returns:
            None.

        Raises:
            Nothing (the plan was validated).
        """
        received = self._received_by_slot() if self.order else {}
        self.plan = plan
        wiring = wiring_of(plan)
        self.wiring = wiring
        graph = plan.graph
        old = self.nodes
        nodes: dict[str, Node] = {}
        for umrf in graph.actions:
            resolved = plan.actions[umrf.full_name]
            node = old.get(umrf.full_name) if old else None
            if node is None:
                node = Node(self, umrf, resolved)
            else:
                node.define(umrf, resolved)
            nodes[node.name] = node
        self.nodes = nodes
        entry, exit_ = self.entry, self.exit
        signature = wiring.signature
        entry.inputs = signature.inputs
        entry.outputs = signature.inputs
        exit_.inputs = signature.outputs
        exit_.outputs = signature.outputs
        order = [entry, *nodes.values(), exit_]
        for i, node in enumerate(order):
            node.idx = i
        self.order = order
        self.edge_start = wiring.edge_start
        self.edge_parent = [order[i] for i in wiring.edge_parent]
        self.edge_child = [order[i] for i in wiring.edge_child]
        self.edge_remap = wiring.edge_remap
        flags = (
            [received.get(key, 0) for key in wiring.slot_keys()]
            if received
            else [0] * len(wiring.slot_required)
        )
        self.evolution = Evolution(
            len(order),
            wiring.edge_start,
            wiring.edge_child,
            wiring.edge_slot,
            wiring.edge_response,
            wiring.slot_start,
            wiring.slot_required,
            exit_.idx,
            flags,
        )

    def can_lend_nodes(self, plan: Plan) -> bool:
        """Whether a new run of ``plan`` may take over this ended run's nodes (``reuse``).

        Only if nothing can still reach a node through this run's action instances: no node
        is active, no action was given up on after a failed stop (it may still be running and
        must keep seeing its stop), no action acquired a resource (the registrar may still
        report on it, through the instance, until the release has run), and the run is not
        shared with other actors (their link keeps it).

        Args:
            plan: The new run's plan (it must be this run's).

        Returns:
            True if the nodes may be renewed for the new run.

        Raises:
            Nothing.
        """
        return (
            plan is self.plan
            and not self.active
            and not self.peers
            and not self.stop_failed
            and not any(node.acquired for node in self.nodes.values())
        )

    def _received_by_slot(self) -> dict[tuple[str, str], int]:
        """The kernel's received flag of every (child, parent) pair of the current wiring."""
        if not self.order:
            return {}
        flags = self.evolution.received_flags()
        return dict(zip(self.wiring.slot_keys(), flags, strict=True))

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
            node.instance = None  # the action holds its node (its RunControl): a cycle
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
