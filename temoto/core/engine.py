"""The Action Engine: runs UMRF graphs.

One engine per actor (robot). It resolves each action of a graph to a local plugin, an indexed
sub-graph (same name and signature) or a remote actor, validates the graph, and evolves it:
when an action finishes, its result is propagated to its children through the condition
table, data flows along the relations, and ready children are dispatched to the worker pool.

The engine holds its parts, one concept per module (``docs/engine.md``):

* :mod:`temoto.core.engine` (this module): :class:`ActionEngine`, the public API: start, wait,
  stop, pause, resume, modify, snapshots and feedback, shutdown. It makes the parts below and
  connects them.
* :mod:`temoto.core.evolution`: :class:`~temoto.core.evolution.RunEvolution`, the engine's lock,
  its runs and every state change of a run and of its nodes (one checked path each), under the
  lock, producing :class:`~temoto.core.effects.Effects`.
* :mod:`temoto.core.dispatch`: :class:`~temoto.core.dispatch.Dispatcher`, which owns the
  workers: it carries out effects with the lock released, and its workers run actions
  (:meth:`Action.run_once <temoto.core.action.Action.run_once>`) and hand each end to the
  evolution.
* :mod:`temoto.core.shared`: the engine's side of graphs shared with other actors; it reaches
  the engine through :class:`~temoto.core.shared.RunHost`, which the evolution implements.

Concurrency model:

* One engine lock guards every graph run. RunEvolution is plain computation under that lock and
  never waits on user code; user hooks (``on_run``, ``on_stop``, ...) run on the bounded
  :class:`~temoto.core.executor.WorkerPool`.
* A worker that finishes an action evolves the graph and goes on itself with what became
  ready: every inline action (``Action.blocking = False``, run back to back, one lock per
  round), or else the first blocking one (no queue hand-off in a chain); further blocking
  actions go to other workers, handed to the pool as one batch.
* Stops are cooperative with a deadline (``stop_timeout``, clock seconds) enforced by one
  timer thread; a node that does not stop in time goes to ERROR.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from temoto.clock import Clock, MonotonicClock
from temoto.core._gc import collector_paused
from temoto.core._runtime import GraphRun, Plan, wiring_of
from temoto.core.catalog import ActionCatalog, GraphIndex
from temoto.core.dispatch import Dispatcher
from temoto.core.documents import graph_from_document
from temoto.core.effects import Effects
from temoto.core.evolution import RunEvolution
from temoto.core.executor import DeadlineTimer, WorkerPool
from temoto.core.graph import UmrfGraph
from temoto.core.instrument import Instrument
from temoto.core.planning import Planner, graph_inputs
from temoto.core.registrar.registry import Registrar
from temoto.core.remote import ActorLink
from temoto.core.shared import SharedRuns
from temoto.core.snapshot import snapshot
from temoto.core.states import BUSY_GRAPH_STATES, GraphState, NodeState, Result
from temoto.errors import GraphNotFoundError, StateError

__all__ = ["ActionEngine", "GraphOutcome"]

logger = logging.getLogger(__name__)

_G_HALTED = GraphState.HALTED
_G_PAUSED = GraphState.PAUSED
_G_PAUSE_REQUESTED = GraphState.PAUSE_REQUESTED
_G_RUNNING = GraphState.RUNNING
_BUSY_GRAPH = BUSY_GRAPH_STATES

#: A run of at least this many new actions has its new objects collected (young generations
#: only) before its first action starts (see :mod:`temoto.core._gc`); a run that reuses an ended
#: run's nodes is not.
YOUNG_COLLECT_AT_START = 1000


@dataclass(frozen=True, slots=True)
class GraphOutcome:
    """How a graph run ended (or where it is).

    Attributes:
        graph: The run's name.
        state: Its state.
        result: Its result, or None while it runs.
        outputs: The graph's outputs (the exit actions' outputs), by name.
        errors: Errors raised by its actions, in order.
        aborted: Why a shared run was aborted (the same words on every actor), or None.
    """

    graph: str
    state: GraphState
    result: Result | None
    outputs: dict[str, Any]
    errors: tuple[BaseException, ...]
    aborted: str | None = None


class ActionEngine:
    """Runs UMRF graphs: start, wait, stop, pause, resume, modify; feedback.

    Args:
        actor: This engine's actor (robot) name. Actions whose ``actor`` is empty or equal run
            here; others are remote.
        actions: An action catalog, or directories to scan for actions.
        graphs: A graph index, or directories to scan for graphs (sub-graphs, start by name).
        clock: Where time is read (default: real time).
        max_workers: Upper bound on worker threads running actions.
        stop_timeout: Clock seconds an action has to return after a stop before its node goes
            to ERROR (upstream: 5).
        instruments: Observers of engine events.
        feedback_size: Keep this many whole-graph snapshots (one per node state change) for
            :meth:`read_feedback`; 0 (default) keeps none, because a snapshot costs time
            proportional to the graph's size.
        registrar: Where actions acquire resources (``Action.acquire``); they are released
            when the graph run ends or the node is removed.
        link: The other actors of shared graphs (``temoto.fleet``). Without one, a graph that
            names another actor is refused at start.
        handshake_timeout: Seconds the handshake before a shared graph may take.
        notify_timeout: Seconds every other actor has to acknowledge a finished action; one
            that does not aborts the shared run on every actor.
        settle_timeout: Real seconds an aborted shared run keeps listening to the other actors
            before :meth:`wait` returns: a peer that reached the end meanwhile gives its result,
            concurrent aborts agree on one reason (``docs/fleet.md``).

    Raises:
        ConfigError: If an action or graph directory does not exist.
    """

    def __init__(
        self,
        actor: str = "",
        *,
        actions: ActionCatalog | Iterable[str | Path] | None = None,
        graphs: GraphIndex | Iterable[str | Path] | None = None,
        clock: Clock | None = None,
        max_workers: int = 64,
        stop_timeout: float = 5.0,
        instruments: Iterable[Instrument] = (),
        feedback_size: int = 0,
        registrar: Registrar | None = None,
        link: ActorLink | None = None,
        handshake_timeout: float = 5.0,
        notify_timeout: float = 5.0,
        settle_timeout: float = 1.0,
    ) -> None:
        if link is not None and link.actor != actor:
            raise ValueError(f"the link speaks for actor '{link.actor}', the engine is '{actor}'")
        self.actor = actor
        self.link = link
        self.handshake_timeout = handshake_timeout
        self.notify_timeout = notify_timeout
        self.catalog = (
            actions if isinstance(actions, ActionCatalog) else ActionCatalog(actions or ())
        )
        self.graphs = graphs if isinstance(graphs, GraphIndex) else GraphIndex(graphs or ())
        self._planner = Planner(actor, self.catalog, self.graphs, remote=link is not None)
        self.clock: Clock = clock or MonotonicClock()
        self.stop_timeout = stop_timeout
        self.registrar = registrar
        # the parts: the evolution (lock, runs, state changes), the dispatcher (workers), and
        # with a link the shared-run protocol, which reaches the engine through the evolution
        self._timer = DeadlineTimer()
        self._evolution = RunEvolution(
            self.clock, stop_timeout, self._timer, instruments, feedback_size
        )
        self._lock = self._evolution.lock
        self._runs: dict[str, GraphRun] = self._evolution.runs
        self._pool = WorkerPool(max_workers)
        self._dispatcher = Dispatcher(self._evolution, self._pool, actor, registrar)
        self._evolution.carry_out = self._dispatcher.carry_out
        self._shared = (
            None
            if link is None
            else SharedRuns(
                self._evolution,
                link,
                handshake_timeout=handshake_timeout,
                notify_timeout=notify_timeout,
                settle_timeout=settle_timeout,
            )
        )
        self._evolution.shared = self._dispatcher.shared = self._shared

    # ================================================================ public API

    def __enter__(self) -> ActionEngine:
        return self

    def __exit__(self, *exc: object) -> None:
        self.shutdown()

    def start(
        self,
        graph: str | UmrfGraph | Mapping[str, Any],
        params: Mapping[str, Any] | None = None,
        *,
        result: Result = Result.TRUE,
        name: str | None = None,
    ) -> str:
        """Start a graph, by indexed name or as a graph object.

        A graph of the same name that has ended (finished, halted, stopped, failed) is
        replaced by a fresh run (new nodes, new action instances).

        Args:
            graph: An indexed graph's name, a graph, or a decoded UMRF JSON document.
            params: Values for the graph's external inputs, by name.
            result: The result ``graph_entry`` hands to the entry actions (default on_true).
            name: Run under this name instead of the graph's name.

        Returns:
            The run's name (for :meth:`wait`, :meth:`stop`, ...).

        Raises:
            GraphNotFoundError: No indexed graph has that name.
            GraphDefinitionError: The graph cannot run (all problems listed).
            GraphInputError: A required input is missing, unknown or of the wrong type.
            ActionNotFoundError, PluginConflictError, PluginLoadError: An action cannot be loaded.
            StateError: A run of that name is active, or the engine is shut down.
            FleetError: The graph is shared with other actors and the handshake with them did
                not complete within ``handshake_timeout``.
        """
        if isinstance(graph, str):
            model = self.graphs.get(graph)
        elif isinstance(graph, UmrfGraph):
            model = graph
        else:
            model = graph_from_document(graph)
        run_name = name or model.name
        fx = Effects()
        with collector_paused():  # a big graph is a burst of long-lived objects
            plan = self.plan(model)
            wiring = wiring_of(plan)  # made once per plan: what start() needs of the graph
            values = graph_inputs(plan.graph, params or {}, wiring.signature)
        peers = SharedRuns.peers(self.actor, plan) if wiring.actors else ()
        session = run_name
        if peers:
            assert self._shared is not None  # the planner refuses remote actions without a link
            session = self._shared.handshake(plan, run_name, peers)
        with collector_paused() as pause:
            with self._lock:
                if self._dispatcher.closed:
                    raise StateError("the engine is shut down")
                old = self._runs.get(run_name)
                if old is not None and old.state in _BUSY_GRAPH:
                    raise StateError(f"graph '{run_name}' is already active ({old.state.value})")
                # an ended run of the same plan lends its nodes to the new one (GraphRun)
                reuse = old if old is not None and old.can_lend_nodes(plan) else None
                run = GraphRun(run_name, plan, clock=self.clock, reuse=reuse)
                run.peers = peers
                run.session = session
                self._runs[run_name] = run
                if old is not None and reuse is None and not old.active:
                    old.dispose()  # its memory comes back now, not at a later full collection
                self._evolution.start_run(run, values, result, fx)
            if reuse is None and len(run.nodes) >= YOUNG_COLLECT_AT_START:
                # outside the lock; before the first action. A run that took over an ended
                # run's nodes made few new objects: nothing for such a scan to do
                pause.collect_young()
        if peers:
            assert self._shared is not None
            self._shared.watch(run)
        self._dispatcher.dispatch(fx)
        return run_name

    def wait(self, name: str, timeout: float | None = None) -> Result:
        """Block until a graph run ends (finished, halted, stopped or failed).

        Args:
            name: The run's name.
            timeout: Real seconds, or None to wait without limit.

        Returns:
            The run's result.

        Raises:
            GraphNotFoundError: No run of that name.
            TimeoutError: The run did not end in time.
        """
        run = self._get(name)
        if not run.done.wait(timeout):
            raise TimeoutError(f"graph '{name}' did not end within {timeout} s")
        with self._lock:
            assert run.result is not None
            return run.result

    def run(
        self,
        graph: str | UmrfGraph | Mapping[str, Any],
        params: Mapping[str, Any] | None = None,
        timeout: float | None = None,
    ) -> GraphOutcome:
        """Start a graph and wait for it; on timeout, stop it.

        Args:
            graph: An indexed graph's name, or a graph.
            params: Values for the graph's external inputs.
            timeout: Real seconds to wait before stopping it, or None.

        Returns:
            The outcome.

        Raises:
            Everything :meth:`start` raises.
        """
        name = self.start(graph, params)
        try:
            self.wait(name, timeout)
        except TimeoutError:
            logger.warning("graph %s did not end within %s s; stopping it", name, timeout)
            self.stop(name)
        return self.outcome(name)

    def stop(self, name: str, timeout: float | None = None) -> Result:
        """Stop a graph run and wait until its actions have stopped.

        Args:
            name: The run's name.
            timeout: Real seconds to wait, or None (the stop itself is bounded by
                ``stop_timeout`` per action).

        Returns:
            ``on_stopped``, or ``on_error`` if an action did not stop in time; for a run that
            had already ended, its result.

        Raises:
            GraphNotFoundError: No run of that name.
            TimeoutError: The stop did not complete in time.
        """
        run = self._get(name)
        fx = Effects()
        with self._lock:
            self._evolution.stop_run(run, fx)
        self._dispatcher.dispatch(fx)
        return self.wait(name, timeout)

    def pause(self, name: str) -> None:
        """Pause a running graph: running actions are paused and no action starts.

        An action that finishes while paused keeps its result until :meth:`resume`.

        Args:
            name: The run's name.

        Returns:
            None.

        Raises:
            GraphNotFoundError: No run of that name.
            StateError: The run is not RUNNING.
        """
        run = self._get(name)
        fx = Effects()
        with self._lock:
            if run.state is not _G_RUNNING:
                raise StateError(f"graph '{name}' is {run.state.value}, not RUNNING")
            self._evolution.pause_run(run, fx)
        self._dispatcher.dispatch(fx)

    def resume(self, name: str, continue_from: str | None = None) -> None:
        """Resume a paused or halted graph, optionally running one node directly.

        A RUNNING graph may be "resumed" too: actions that a ``pause`` response paused go on.

        Args:
            name: The run's name.
            continue_from: A node's full name (``TaRelayString_1``) to run now, regardless of
                its parents.

        Returns:
            None.

        Raises:
            GraphNotFoundError: No run of that name.
            StateError: The run is not PAUSED (or PAUSE_REQUESTED), HALTED or RUNNING.
            KeyError: ``continue_from`` names no node of the graph.
        """
        run = self._get(name)
        fx = Effects()
        with self._lock:
            if run.state not in (_G_PAUSED, _G_PAUSE_REQUESTED, _G_HALTED, _G_RUNNING):
                raise StateError(f"graph '{name}' is {run.state.value}, not PAUSED or HALTED")
            if continue_from is not None and continue_from not in run.nodes:
                raise KeyError(f"graph '{name}' has no action '{continue_from}'")
            self._evolution.resume_run(run, continue_from, fx)
        self._dispatcher.dispatch(fx)

    def modify(self, name: str, graph: UmrfGraph, continue_from: str | None = None) -> None:
        """Replace the structure of a running, paused or halted graph.

        Nodes absent from ``graph`` are removed (refused if one is active), new nodes are
        added (resolved like at start), surviving nodes keep their state, action instance
        and received data and take the new relations and updatable literals. The change is
        applied atomically; a paused run stays paused unless ``continue_from`` is given, a
        halted one resumes.

        Args:
            name: The run's name (``graph.name`` may differ).
            graph: The new graph.
            continue_from: A node to run right after the change.

        Returns:
            None.

        Raises:
            GraphNotFoundError: No run of that name.
            GraphDefinitionError: The new graph cannot run.
            StateError: The run has ended, or an active node would be removed.
            KeyError: ``continue_from`` names no node of the new graph.
        """
        run = self._get(name)
        with collector_paused():
            plan = self.plan(graph)
        fx = Effects()
        with self._lock:
            if run.state not in (_G_RUNNING, _G_PAUSE_REQUESTED, _G_PAUSED, _G_HALTED):
                raise StateError(
                    f"graph '{name}' is {run.state.value};"
                    " only running, paused or halted graphs can be modified"
                )
            new_names = set(plan.actions)
            busy = sorted(
                n.name for n in run.nodes.values() if n.name not in new_names and n.active
            )
            if busy:
                raise StateError(f"graph '{name}': cannot remove active actions {', '.join(busy)}")
            if continue_from is not None and continue_from not in new_names:
                raise KeyError(f"the new graph has no action '{continue_from}'")
            evolution = self._evolution
            for node in run.nodes.values():
                if node.name not in new_names:
                    evolution.release_node(node)
            run.wire(plan)
            logger.info("graph %s modified (%d actions)", name, len(run.nodes))
            if run.state is _G_HALTED or (
                continue_from and run.state in (_G_PAUSED, _G_PAUSE_REQUESTED)
            ):
                evolution.resume_run(run, continue_from, fx)
            elif continue_from is not None:
                evolution.rerun(run.nodes[continue_from], fx)
            else:
                evolution.after_change(run, fx)
        self._dispatcher.dispatch(fx)

    def outcome(self, name: str) -> GraphOutcome:
        """Where a graph run is, or how it ended.

        Args:
            name: The run's name.

        Returns:
            The outcome.

        Raises:
            GraphNotFoundError: No run of that name.
        """
        run = self._get(name)
        with self._lock:
            return GraphOutcome(
                run.name,
                run.state,
                run.result,
                dict(run.outputs),
                tuple(run.errors),
                run.aborted,
            )

    def node_states(self, name: str) -> dict[str, NodeState]:
        """The state of every node of a run (cheaper than :meth:`graph_json`).

        Args:
            name: The run's name.

        Returns:
            States by node name (``<Name>_<instance_id>``), sorted by name.

        Raises:
            GraphNotFoundError: No run of that name.
        """
        run = self._get(name)
        with self._lock:
            return {n: run.nodes[n].state for n in sorted(run.nodes)}

    def running_graphs(self) -> dict[str, GraphState]:
        """Every graph run the engine knows (including ended ones and sub-graphs).

        Returns:
            States by run name.
        """
        with self._lock:
            return {name: run.state for name, run in self._runs.items()}

    def indexed_graphs(self) -> list[UmrfGraph]:
        """Graphs found in the graph directories.

        Returns:
            The graphs.
        """
        return self.graphs.all()

    def graph_json(self, name: str) -> dict[str, Any]:
        """A snapshot of a run as UMRF JSON, with node states, current inputs and logs.

        Args:
            name: The run's name.

        Returns:
            A JSON-ready dict in the canonical form.

        Raises:
            GraphNotFoundError: No run of that name.
        """
        run = self._get(name)
        with self._lock:
            return snapshot(run)

    def read_feedback(self) -> list[dict[str, Any]]:
        """Return and clear the buffered snapshots (needs ``feedback_size`` > 0).

        Returns:
            Snapshots, oldest first.
        """
        with self._lock:
            return self._evolution.take_feedback()

    def add_instrument(self, instrument: Instrument) -> None:
        """Attach an observer.

        Args:
            instrument: The observer.

        Returns:
            None.
        """
        with self._lock:
            self._evolution.add_instrument(instrument)

    def shutdown(self, timeout: float = 10.0) -> None:
        """Stop every graph, then join the engine's threads. Idempotent.

        Args:
            timeout: Real seconds to wait for actions to return.

        Returns:
            None.
        """
        fx = Effects()
        evolution = self._evolution
        with self._lock:
            if self._dispatcher.closed:
                return
            self._dispatcher.closed = True
            runs = [r for r in self._runs.values() if r.parent_node is None]
            for run in runs:
                evolution.stop_run(run, fx)
            # a finished graph may still have actions winding down
            for run in self._runs.values():
                for node in run.nodes.values():
                    if node.active:
                        evolution.stop_node(node, fx)
        self._dispatcher.dispatch(fx, closing=True)
        for run in runs:
            run.done.wait(timeout)
        with self._lock:
            evolution.wake()
        stuck = self._pool.shutdown(timeout)
        self._timer.shutdown()
        if stuck:
            logger.error("actions still running at shutdown (threads %s)", ", ".join(stuck))

    def plan(self, graph: UmrfGraph) -> Plan:
        """Resolve and validate a graph without running it.

        Args:
            graph: The graph.

        Returns:
            The plan: effective actions and how each runs.

        Raises:
            GraphDefinitionError, ActionNotFoundError, PluginConflictError, PluginLoadError:
                As for :meth:`start`.
        """
        return self._planner.plan(graph)

    def _get(self, name: str) -> GraphRun:
        with self._lock:
            run = self._runs.get(name)
        if run is None:
            raise GraphNotFoundError(f"no graph run named '{name}'")
        return run
