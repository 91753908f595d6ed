"""Run-time structures of the engine: resolved plans, graph runs and their nodes.

Engine internal. A :class:`Plan` is a graph whose actions were resolved (local class,
sub-graph plan or remote actor) and whose parameters were merged with the action
descriptions; a :class:`GraphRun` is one execution of a plan; a :class:`Node` is one action
instance in it, plus the synthetic ``graph_entry`` and ``graph_exit`` nodes.

All mutable fields are guarded by the engine's lock.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from enum import Enum
from typing import TYPE_CHECKING, Any

from temoto.core.params import Parameter
from temoto.core.states import GraphState, NodeState, Result
from temoto.core.umrf import ENTRY_NAME, EXIT_NAME, ChildRelation, ParentRelation, Umrf

if TYPE_CHECKING:
    from temoto.core.action import Action, RunControl
    from temoto.core.executor import TimerHandle
    from temoto.core.graph import UmrfGraph
    from temoto.core.umrf import LogMessage

__all__ = ["GraphRun", "Node", "NodeKind", "Plan", "ResolvedAction"]


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


_ACTIVE = frozenset(
    {NodeState.RUNNING, NodeState.PAUSE_REQUESTED, NodeState.PAUSED, NodeState.STOPPING}
)


class Node:
    """One node of a graph run."""

    __slots__ = (
        "child_run",
        "children",
        "cls",
        "control",
        "data",
        "error",
        "fresh_instance",
        "gen",
        "held",
        "inputs",
        "instance",
        "kind",
        "last_outputs",
        "log",
        "missing",
        "name",
        "native",
        "outputs",
        "parents",
        "plan",
        "received",
        "required_inputs",
        "required_parents",
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
        self.state = NodeState.UNINITIALIZED
        self.parents: dict[str, ParentRelation] = {}
        #: (child node, remap from->to, the child's relation to this node)
        self.children: list[tuple[Node, dict[str, str], ParentRelation]] = []
        self.received: set[str] = set()
        self.data: dict[str, Any] = {}
        self.native: set[str] = set()
        self.gen = 0
        self.control: RunControl | None = None
        self.instance: Action | None = None
        self.fresh_instance = False
        self.held: tuple[Result, dict[str, Any], BaseException | None] | None = None
        self.restart = False
        self.stop_timer: TimerHandle | None = None
        self.child_run: GraphRun | None = None
        self.error: BaseException | None = None
        self.last_outputs: dict[str, Any] = {}
        self.log: tuple[LogMessage, ...] = ()
        self.umrf = umrf
        self.inputs: dict[str, Parameter] = {}
        self.outputs: dict[str, Parameter] = {}
        self.required_inputs: tuple[str, ...] = ()
        self.required_parents: frozenset[str] = frozenset()
        self.missing = 0  # required parents not received yet
        self.spontaneous = False
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
        self.inputs = dict(umrf.input_parameters)
        self.outputs = dict(umrf.output_parameters)
        first = not self.native and not self.data
        for name in list(self.native):
            param = self.inputs.get(name)
            if param is None or (not param.has_value and param.updatable):
                self.native.discard(name)  # the new definition has no literal for it
                self.data.pop(name, None)
        for name, param in self.inputs.items():
            if param.has_value and (first or param.updatable or name not in self.data):
                self.data[name] = param.value
                self.native.add(name)
        self.required_inputs = tuple(n for n, p in self.inputs.items() if p.required)

    @property
    def active(self) -> bool:
        """Whether the node is running, pausing, paused or stopping."""
        return self.state in _ACTIVE

    def ready(self) -> bool:
        """Readiness: all required inputs hold data and all required parents were received.

        ``graph_exit`` checks parents only: a missing graph output must not hang the graph.

        Returns:
            True if the node may start.

        Raises:
            Nothing.
        """
        if self.missing:
            return False
        if self.kind is NodeKind.EXIT:
            return True
        data = self.data
        return all(name in data for name in self.required_inputs)

    def receive(self, parent: str) -> None:
        """Mark a parent as received (it finished at least once); never reset during a run.

        Args:
            parent: The parent's full name.

        Returns:
            None.

        Raises:
            Nothing.
        """
        if parent not in self.received:
            self.received.add(parent)
            if parent in self.required_parents:
                self.missing -= 1

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
        "active",
        "done",
        "entry",
        "errors",
        "exit",
        "name",
        "nodes",
        "outputs",
        "parent_node",
        "plan",
        "result",
        "started_at",
        "state",
        "stop_failed",
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
            node.children = []
        exit_.parents = {rel.full_name: rel for rel in graph.exit}
        entry.children = [self._edge(entry, rel) for rel in graph.entry]
        for node in nodes.values():
            node.children = [self._edge(node, rel) for rel in node.umrf.children]
        no_remap: dict[str, str] = {}
        for rel in graph.exit:
            nodes[rel.full_name].children.append((exit_, no_remap, rel))
        for node in (*nodes.values(), exit_):
            node.required_parents = frozenset(n for n, p in node.parents.items() if p.required)
            node.missing = len(node.required_parents - node.received)

    def _edge(
        self, parent: Node, rel: ChildRelation
    ) -> tuple[Node, dict[str, str], ParentRelation]:
        child = self.nodes[rel.full_name]
        back = child.parents[parent.name]
        return child, {r.from_: r.to for r in rel.remap}, back

    def all_nodes(self) -> list[Node]:
        """Action nodes followed by the entry and exit nodes.

        Returns:
            The nodes.

        Raises:
            Nothing.
        """
        return [*self.nodes.values(), self.entry, self.exit]
