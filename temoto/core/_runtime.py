"""Run-time structures of the engine: graph runs and their nodes.

Engine internal. A :class:`GraphRun` is one execution of a :class:`~temoto.core.plan.Plan`
(a graph whose actions were resolved, :mod:`temoto.core.plan`, whose names this module
re-exports); a :class:`Node` is one action instance in it, plus the synthetic ``graph_entry``
and ``graph_exit`` nodes.

All mutable fields are guarded by the engine's lock.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

from temoto.clock import MonotonicClock
from temoto.core._fast import Evolution
from temoto.core.control import RunControl
from temoto.core.params import Parameter
from temoto.core.plan import (
    RESPONSES,
    RESULT_CODES,
    NodeKind,
    Plan,
    ResolvedAction,
    Wiring,
    wiring_of,
)
from temoto.core.states import ACTIVE_NODE_STATES, GraphState, NodeState, Result
from temoto.core.umrf import ENTRY_NAME, EXIT_NAME, Umrf

if TYPE_CHECKING:
    from temoto.clock import Clock
    from temoto.core.action import Action
    from temoto.core.executor import TimerHandle
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

_NO_NAMES: frozenset[str] = frozenset()  # responses of a relation without written conditions

# Enum members read per node or per action, as globals (a member lookup on the enum class costs
# several times a global's)
_UNINITIALIZED = NodeState.UNINITIALIZED
_LOCAL = NodeKind.LOCAL
_EXIT = NodeKind.EXIT

_ACTIVE = ACTIVE_NODE_STATES


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
        "log",
        "name",
        "native",
        "outputs",
        "plan",
        "remote_cancel",
        "required_inputs",
        "restart",
        "run",
        "spent",
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
        #: the previous run's instance, kept until this run's is made (see renew)
        self.spent: Action | None = None
        self.fresh_instance = False
        self.held: tuple[Result, dict[str, Any], BaseException | None] | None = None
        self.restart = False
        self.stop_timer: TimerHandle | None = None
        self.child_run: GraphRun | None = None
        self.remote_cancel: Callable[[], None] | None = None  # stops waiting for a remote actor
        self.error: BaseException | None = None
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
        The definition stays, and the data is what :meth:`define` gives a new node: the
        literals of its inputs.

        Args:
            run: The new run.

        Returns:
            None.
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
        data = self.data
        data.clear()  # never handed out (runs get copies): no new dict per node and run
        native: set[str] | frozenset[str] = _NO_NAMES
        params = self.umrf.input_parameters
        if params:  # the literals, as define() sets them for a new node
            for name, param in params.items():
                if param.has_value:
                    data[name] = param.value
                    if native is _NO_NAMES:
                        native = set()
                    native.add(name)  # type: ignore[union-attr]  # a set by now
        self.native = native
        self.gen += 1
        if self.instance is not None:
            # Freed when this run makes the node's new instance (Dispatcher._instantiate), not
            # now: an allocation and a free of a tracked object cancel out in the collector's
            # count, so a repeated run that replaces its instances one by one adds nothing for
            # it to scan (freed here, all at once, the new run's instances alone would trigger a
            # young collection per 700 actions).
            self.spent = self.instance
            self.instance = None
        self.fresh_instance = False
        self.held = None
        self.restart = False
        self.stop_timer = None
        self.child_run = None
        self.remote_cancel = None
        self.error = None
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
            new run's objects, which grows with the graph, is spared. The old run forgets them.
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
        self.entry: Node
        self.exit: Node
        self.nodes: dict[str, Node]
        self.order: list[Node]  # node by kernel number
        # Edges by kernel number, as parallel lists (no object per edge).
        # Node ``i``'s outgoing edges are ``edge_start[i]`` to ``edge_start[i + 1]``.
        self.edge_start: list[int]
        self.edge_parent: list[Node]
        self.edge_child: list[Node]
        self.edge_remap: list[dict[str, str]]  # output name -> input name
        self.wiring: Wiring
        if reuse is not None and reuse.plan is plan:
            # The ended run's nodes become this run's, as new (see Node.renew), and so do its
            # numbering and relations, which depend on the plan only: what wire() would make
            # again, node by node.
            order = reuse.order
            for node in order:
                node.renew(self)
            self.entry, self.exit, self.nodes, self.order = (
                reuse.entry,
                reuse.exit,
                reuse.nodes,
                order,
            )
            self.edge_start, self.edge_parent = reuse.edge_start, reuse.edge_parent
            self.edge_child, self.edge_remap = reuse.edge_child, reuse.edge_remap
            self.wiring = reuse.wiring
            reuse.forget()
            self.evolution = self.wiring.kernel()
        else:
            self.entry = Node(self, Umrf(ENTRY_NAME, "sync"), ResolvedAction(NodeKind.ENTRY))
            self.exit = Node(self, Umrf(EXIT_NAME, "sync"), ResolvedAction(NodeKind.EXIT))
            self.forget()  # no nodes or edges yet: wire() makes them
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
        flags = [received.get(key, 0) for key in wiring.slot_keys()] if received else None
        self.evolution = wiring.kernel(flags)

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
        """
        if plan is not self.plan or self.active or self.peers or self.stop_failed:
            return False
        for node in self.nodes.values():  # noqa: SIM110 - a loop: no generator step per node
            if node.acquired:
                return False
        return True

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
        """
        for node in self.all_nodes():
            node.child_run = None
            node.instance = None  # the action holds its node (its RunControl): a cycle
            node.spent = None
        self.forget()

    def forget(self) -> None:
        """Drop this run's references to its nodes and edges (the nodes are left as they are).

        Called by :meth:`dispose`, and for a run whose nodes a new run took over (``reuse``).

        Returns:
            None.
        """
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
        """
        return self.edge_child[self.edge_start[node.idx] : self.edge_start[node.idx + 1]]

    def received_any(self, node: Node) -> bool:
        """Whether any parent of ``node`` finished in this run.

        Args:
            node: A node of this run.

        Returns:
            True if one did.
        """
        return self.evolution.received_any(node.idx)

    def all_nodes(self) -> list[Node]:
        """Action nodes followed by the entry and exit nodes.

        Returns:
            The nodes.
        """
        return [*self.nodes.values(), self.entry, self.exit]
