"""The Action Engine: runs UMRF graphs.

One engine per actor (robot). It resolves each action of a graph to a local plugin, an indexed
sub-graph (same name and signature) or a remote actor, validates the graph, and evolves it:
when an action finishes, its result is propagated to its children through the condition
table, data flows along the relations, and ready children are dispatched to the worker pool.

Concurrency model (see ``docs/engine.md``):

* One engine lock guards every graph run. Evolution is plain computation under that lock and
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

import dataclasses
import logging
import threading
from collections import deque
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from temoto.clock import Clock, MonotonicClock
from temoto.core._gc import collector_paused
from temoto.core._runtime import RESULT_CODES as _RESULT_CODES
from temoto.core._runtime import GraphRun, Node, NodeKind, Plan
from temoto.core.action import NO_VALUES, Action, RunControl
from temoto.core.catalog import ActionCatalog, GraphIndex
from temoto.core.documents import dump_umrf, graph_from_document, graph_to_dict
from temoto.core.executor import DeadlineTimer, WorkerPool
from temoto.core.graph import UmrfGraph
from temoto.core.instrument import Instrument
from temoto.core.params import dump_parameter_tree
from temoto.core.planning import Planner, graph_inputs
from temoto.core.registrar.registry import Registrar
from temoto.core.remote import ActorLink
from temoto.core.shared import SharedRuns
from temoto.core.states import NODE_TRANSITIONS, GraphState, NodeState, Result
from temoto.errors import (
    ActionError,
    GraphNotFoundError,
    StateError,
    StopRequested,
)

__all__ = ["ActionEngine", "GraphOutcome"]

logger = logging.getLogger(__name__)

# Enum members as module constants: `NodeState.RUNNING` is a class attribute lookup through
# the enum's metaclass (about 70 ns on CPython 3.11, against about 10 ns for a global), and
# the evolution path reads a dozen of them per action.
_N_BYPASSED = NodeState.BYPASSED
_N_ERROR = NodeState.ERROR
_N_FINISHED = NodeState.FINISHED
_N_PAUSED = NodeState.PAUSED
_N_PAUSE_REQUESTED = NodeState.PAUSE_REQUESTED
_N_RUNNING = NodeState.RUNNING
_N_STOPPING = NodeState.STOPPING
_N_UNINITIALIZED = NodeState.UNINITIALIZED
_G_CLEARING = GraphState.CLEARING
_G_ERROR = GraphState.ERROR
_G_FINISHED = GraphState.FINISHED
_G_HALTED = GraphState.HALTED
_G_PAUSED = GraphState.PAUSED
_G_RUNNING = GraphState.RUNNING
_G_STOPPED = GraphState.STOPPED
_G_STOPPING = GraphState.STOPPING
_R_ERROR = Result.ERROR
_R_FALSE = Result.FALSE
_R_HALTED = Result.HALTED
_R_STOPPED = Result.STOPPED
_R_TRUE = Result.TRUE
_K_ENTRY = NodeKind.ENTRY
_K_EXIT = NodeKind.EXIT
_K_GRAPH = NodeKind.GRAPH
_K_LOCAL = NodeKind.LOCAL
_K_REMOTE = NodeKind.REMOTE

#: A run of at least this many actions has its new objects collected (young generations only)
#: before its first action starts (see :mod:`temoto.core._gc`).
YOUNG_COLLECT_AT_START = 1000

_ACTIVE = frozenset({_N_RUNNING, _N_PAUSE_REQUESTED, _N_PAUSED, _N_STOPPING})
_BUSY_GRAPH = frozenset({_G_RUNNING, _G_PAUSED, _G_STOPPING, _G_CLEARING})
_ENDED_GRAPH = frozenset({_G_FINISHED, _G_STOPPED, _G_ERROR, _G_HALTED})

# effect kinds (tuples in an effect list, executed after the engine lock is released)
_RUN = 0  # (_RUN, node, gen): run the action on a worker
_HOOK = 1  # (_HOOK, node, gen, hook name): call on_stop / on_pause / on_resume on a worker
_SPONT = 2  # (_SPONT, node, gen, result, outputs, error): finish a spontaneous run on a worker
_RELEASE = 3  # (_RELEASE, action instance): release the resources a node acquired
_CALL = 4  # (_CALL, function, *args): a short call to the actor link, made outside the lock

Effect = tuple[Any, ...]
# a run prepared under the lock: (node, gen, its instance or None, input values)
_Todo = tuple[Node, int, Action | None, dict[str, Any]]
# a run's end, applied under the lock: (node, gen, instance, result, outputs, error)
_Done = tuple[Node, int, Action | None, Result, dict[str, Any], BaseException | None]

# response codes of the evolution kernel (temoto.core._fast._evolution_py)
_SHIFT = 4
_P_RUN, _P_PAUSE, _P_RESTART, _P_STOP, _P_BYPASS, _P_IGNORE, _P_LOOP = range(7)


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
        # the shared-run protocol's engine side (temoto.core.shared), with a link only
        self._shared = (
            None
            if link is None
            else SharedRuns(
                self,
                link,
                handshake_timeout=handshake_timeout,
                notify_timeout=notify_timeout,
                settle_timeout=settle_timeout,
            )
        )
        self.catalog = (
            actions if isinstance(actions, ActionCatalog) else ActionCatalog(actions or ())
        )
        self.graphs = graphs if isinstance(graphs, GraphIndex) else GraphIndex(graphs or ())
        self._planner = Planner(actor, self.catalog, self.graphs, remote=link is not None)
        self.clock: Clock = clock or MonotonicClock()
        self.stop_timeout = stop_timeout
        self.registrar = registrar
        self._instruments = list(instruments)
        # the instruments that observe node transitions (two per action run: kept apart so an
        # instrument that only watches graph starts and ends costs nothing per action)
        self._watchers = [i for i in self._instruments if _watches_transitions(i)]
        self._lock = threading.Lock()
        self._quiet = threading.Condition(self._lock)
        self._quiet_waiters = 0
        self._runs: dict[str, GraphRun] = {}
        self._pool = WorkerPool(max_workers)
        self._timer = DeadlineTimer()
        self._feedback: deque[dict[str, Any]] = deque(maxlen=max(feedback_size, 1))
        self._feedback_on = feedback_size > 0
        self._closed = False
        # releases found under the lock, handed to workers by the next _dispatch
        self._releases: list[Effect] = []

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
        fx: list[Effect] = []
        with collector_paused():  # a big graph is a burst of long-lived objects
            plan = self.plan(model)
            values = graph_inputs(plan.graph, params or {})
        peers = SharedRuns.peers(self.actor, plan)
        session = run_name
        if peers:
            assert self._shared is not None  # the planner refuses remote actions without a link
            session = self._shared.handshake(plan, run_name, peers)
        with collector_paused() as pause:
            with self._lock:
                if self._closed:
                    raise StateError("the engine is shut down")
                old = self._runs.get(run_name)
                if old is not None and old.state in _BUSY_GRAPH:
                    raise StateError(f"graph '{run_name}' is already active ({old.state.value})")
                run = GraphRun(run_name, plan)
                run.peers = peers
                run.session = session
                self._runs[run_name] = run
                if old is not None and not old.active:
                    old.dispose()  # its memory comes back now, not at a later full collection
                self._start_run(run, values, result, fx)
            if len(run.nodes) >= YOUNG_COLLECT_AT_START:
                pause.collect_young()  # outside the lock; before the first action
        if peers:
            assert self._shared is not None
            self._shared.watch(run)
        self._dispatch(fx)
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
        fx: list[Effect] = []
        with self._lock:
            self._stop_run(run, fx)
        self._dispatch(fx)
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
        fx: list[Effect] = []
        with self._lock:
            if run.state is not _G_RUNNING:
                raise StateError(f"graph '{name}' is {run.state.value}, not RUNNING")
            self._pause_run(run, fx)
        self._dispatch(fx)

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
            StateError: The run is not PAUSED, HALTED or RUNNING.
            KeyError: ``continue_from`` names no node of the graph.
        """
        run = self._get(name)
        fx: list[Effect] = []
        with self._lock:
            if run.state not in (_G_PAUSED, _G_HALTED, _G_RUNNING):
                raise StateError(f"graph '{name}' is {run.state.value}, not PAUSED or HALTED")
            if continue_from is not None and continue_from not in run.nodes:
                raise KeyError(f"graph '{name}' has no action '{continue_from}'")
            self._resume_run(run, continue_from, fx)
        self._dispatch(fx)

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
        fx: list[Effect] = []
        with self._lock:
            if run.state not in (_G_RUNNING, _G_PAUSED, _G_HALTED):
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
            for node in run.nodes.values():
                if node.name not in new_names:
                    self._release_node(node)
            run.wire(plan)
            logger.info("graph %s modified (%d actions)", name, len(run.nodes))
            if run.state is _G_HALTED or (continue_from and run.state is _G_PAUSED):
                self._resume_run(run, continue_from, fx)
            elif continue_from is not None:
                self._run_node(run.nodes[continue_from], fx)
                self._after_change(run, fx)
            else:
                self._after_change(run, fx)
        self._dispatch(fx)

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

        Raises:
            Nothing.
        """
        with self._lock:
            return {name: run.state for name, run in self._runs.items()}

    def indexed_graphs(self) -> list[UmrfGraph]:
        """Graphs found in the graph directories.

        Returns:
            The graphs.

        Raises:
            Nothing.
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
            return self._snapshot(run)

    def read_feedback(self) -> list[dict[str, Any]]:
        """Return and clear the buffered snapshots (needs ``feedback_size`` > 0).

        Returns:
            Snapshots, oldest first.

        Raises:
            Nothing.
        """
        with self._lock:
            out = list(self._feedback)
            self._feedback.clear()
            return out

    def add_instrument(self, instrument: Instrument) -> None:
        """Attach an observer.

        Args:
            instrument: The observer.

        Returns:
            None.

        Raises:
            Nothing.
        """
        with self._lock:
            self._instruments.append(instrument)
            if _watches_transitions(instrument):
                self._watchers.append(instrument)

    def shutdown(self, timeout: float = 10.0) -> None:
        """Stop every graph, then join the engine's threads. Idempotent.

        Args:
            timeout: Real seconds to wait for actions to return.

        Returns:
            None.

        Raises:
            Nothing.
        """
        fx: list[Effect] = []
        with self._lock:
            if self._closed:
                return
            self._closed = True
            runs = [r for r in self._runs.values() if r.parent_node is None]
            for run in runs:
                self._stop_run(run, fx)
            # a finished graph may still have actions winding down
            for run in self._runs.values():
                for node in run.nodes.values():
                    if node.active:
                        self._stop_node(node, fx)
        self._dispatch(fx, closing=True)
        for run in runs:
            run.done.wait(timeout)
        with self._lock:
            self._quiet.notify_all()
        stuck = self._pool.shutdown(timeout)
        self._timer.shutdown()
        if stuck:
            logger.error("actions still running at shutdown (threads %s)", ", ".join(stuck))

    # ================================================================ planning

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

    # ================================================================ effects

    def _dispatch(self, fx: list[Effect], *, closing: bool = False) -> None:
        """Carry out effects (lock released): calls here, actions and hooks on workers.

        Ready actions leave as one batch: the inline ones together as one worker job that runs
        them back to back (:meth:`_run_batch`), each blocking one as a job of its own, all
        handed to the pool under one lock of its own (:meth:`WorkerPool.submit_many`).
        """
        if self._releases:
            with self._lock:
                fx = [*fx, *self._releases]
                self._releases.clear()
        inline: list[tuple[Node, int]] = []
        runs: list[tuple[Node, int]] = []
        for effect in fx:
            kind = effect[0]
            if kind == _RUN:
                node = effect[1]
                (inline if node.inline else runs).append((node, effect[2]))
                continue
            if kind == _CALL:
                try:
                    effect[1](*effect[2:])
                except Exception:
                    logger.exception("call to the actor link failed: %r", effect[1])
                continue
            try:
                if kind == _HOOK:
                    self._pool.submit(self._call_hook, effect[1], effect[2], effect[3])
                elif kind == _RELEASE:
                    self._pool.submit(_release_resources, effect[1])
                else:
                    self._pool.submit(self._finish_spontaneous, *effect[1:])
            except RuntimeError:
                if not (closing or self._closed):  # shut down since the caller looked
                    raise
                self._settle_closed(effect)
        if not (inline or runs):
            return
        jobs: list[tuple[Any, ...]] = [(inline,)] if inline else []
        jobs += [([run],) for run in runs]
        try:
            self._pool.submit_many(self._run_batch, jobs)
        except RuntimeError:
            if not (closing or self._closed):
                raise
            for node, gen in inline + runs:
                self._settle_closed((_RUN, node, gen))

    def _settle_closed(self, effect: Effect) -> None:
        """The pool is shut down: settle an effect in this thread so no node stays active."""
        if effect[0] == _RUN:
            node, gen = effect[1], effect[2]
            fx: list[Effect] = []
            with self._lock:
                if node.gen == gen and node.active:
                    self._on_finished(node, gen, _R_STOPPED, {}, None, fx)
        elif effect[0] == _HOOK:
            self._call_hook(effect[1], effect[2], effect[3])
        elif effect[0] == _RELEASE:
            _release_resources(effect[1])
        else:
            self._finish_spontaneous(*effect[1:])

    def _run_batch(self, batch: list[tuple[Node, int]]) -> None:
        """Worker: run actions, evolve, and go on with what became ready, batch by batch.

        Each round runs the prepared actions back to back outside the lock, then takes the
        lock once to apply every result (evolution) and to prepare the next round: the inline
        actions that became ready, or, when none did, the first ready blocking action (a chain
        continues on this thread without a hand-off). Further blocking actions go to other
        workers. One lock per round, not per action.

        The common end of a run (the current run of a RUNNING node that returned True or
        False in a RUNNING graph, nobody observing transitions) is applied here directly;
        it does what :meth:`_settle` and :meth:`_on_finished` do for that case.
        """
        lock = self._lock
        todo: list[_Todo] = []
        rest: list[Effect] = []
        fx: list[Effect] = []
        # the round's lists are reused: fewer objects for the collector per action
        done: list[_Done] = []
        with lock:
            for node, gen in batch:
                self._prep(node, gen, todo, fx)
            self._collect(fx, todo, rest)
        running = _N_RUNNING
        graph_running = _G_RUNNING
        true, false = _R_TRUE, _R_FALSE
        while True:
            if rest or self._releases:  # an ended run's releases may be all there is
                self._dispatch(rest, closing=self._closed)
                rest.clear()
            if not todo:
                return
            done.clear()
            for node, gen, instance, values in todo:  # the actions, outside the lock
                if node.run.peers:
                    done.append(self._call(node, gen, instance, values))
                    continue
                error: BaseException | None = None
                if instance is None:
                    try:
                        instance = self._instantiate(node, gen)
                    except Exception as err:
                        error = ActionError(
                            f"{node.name} could not be initialised: {err}",
                            graph=node.run.name,
                            node=node.name,
                        )
                        error.__cause__ = err
                        done.append((node, gen, None, _R_ERROR, NO_VALUES, error))
                        continue
                if values or instance._input_params or instance._output_params:
                    instance._begin(values)  # else: the shared empty views it holds already
                try:
                    ok = instance.on_run()
                    if ok is True:
                        result = true
                    elif ok is False:
                        result = false
                    else:
                        raise TypeError(
                            f"on_run() must return True or False, not {type(ok).__name__}"
                        )
                except StopRequested:
                    result = _R_STOPPED
                except BaseException as err:
                    result = _R_ERROR
                    error = ActionError(
                        f"{node.name} failed: {err}", graph=node.run.name, node=node.name
                    )
                    error.__cause__ = err
                written = instance._outputs
                outputs = written._taken() if written._values else NO_VALUES
                done.append((node, gen, instance, result, outputs, error))
            todo.clear()
            fx.clear()
            with lock:
                fast = not self._watchers and not self._feedback_on
                for item in done:
                    node, gen, instance, result, outputs, error = item
                    run = node.run
                    if not (
                        fast
                        and error is None
                        and gen == node.gen
                        and node.state is running
                        and run.state is graph_running
                        and not node.restart
                        and not node.spontaneous
                        and node.stop_timer is None
                        and instance is not None
                    ):
                        self._settle(item, fx)
                        continue
                    if node.instance is None:
                        node.instance = instance
                    if instance._log is not None or node.log:
                        node.log = instance._log_snapshot()
                    if len(node.data) != len(node.native):
                        node.clear_data()
                    node.last_outputs = outputs
                    node.state = _N_FINISHED  # RUNNING -> FINISHED, in a RUNNING graph
                    run.active -= 1
                    if self._quiet_waiters:
                        self._quiet.notify_all()
                    self._propagate(node, result, outputs, fx)
                    if not run.active:
                        self._after_change(run, fx)
                if len(fx) == 1 and fx[0][0] == _RUN:  # a chain: _collect's common case
                    _, node, gen = fx[0]
                    if node.inline and gen == node.gen and node.state is running:
                        data = node.data
                        todo.append((node, gen, node.instance, dict(data) if data else NO_VALUES))
                        continue
                self._collect(fx, todo, rest)

    def _prep(self, node: Node, gen: int, todo: list[_Todo], fx: list[Effect]) -> None:
        """Lock held: queue a ready node's run with what it reads, unless it is stale."""
        if gen != node.gen or node.state not in _ACTIVE:
            return
        if node.state is _N_STOPPING:  # stopped before a worker got to it: do not start
            self._on_finished(node, gen, _R_STOPPED, {}, None, fx)
            return
        todo.append((node, gen, node.instance, dict(node.data) if node.data else NO_VALUES))

    def _collect(self, fx: list[Effect], todo: list[_Todo], rest: list[Effect]) -> None:
        """Lock held: split effects into runs for this thread (``todo``) and the rest.

        Inline runs are prepared here (a stale or stopped one may add effects, which are
        collected too); the first blocking run is kept only when no inline run is.
        """
        blocking: list[Effect] = []
        i = 0
        while True:
            while i < len(fx):
                effect = fx[i]
                i += 1
                if effect[0] != _RUN:
                    rest.append(effect)
                    continue
                node = effect[1]
                if not node.inline:
                    blocking.append(effect)
                elif effect[2] == node.gen and node.state is _N_RUNNING:  # _prep's common case
                    data = node.data
                    todo.append((node, effect[2], node.instance, dict(data) if data else NO_VALUES))
                else:
                    self._prep(node, effect[2], todo, fx)
            if todo or not blocking:
                break
            first = blocking.pop(0)
            self._prep(first[1], first[2], todo, fx)
        rest += blocking

    def _call(self, node: Node, gen: int, instance: Action | None, values: dict[str, Any]) -> _Done:
        """No lock: one run of an action's ``on_run`` (its instance made first if need be)."""
        run = node.run
        error: BaseException | None = None
        if instance is None:
            try:
                instance = self._instantiate(node, gen)
            except Exception as err:
                error = ActionError(
                    f"{node.name} could not be initialised: {err}", graph=run.name, node=node.name
                )
                error.__cause__ = err
        outputs: dict[str, Any] = NO_VALUES
        result = _R_ERROR
        if instance is not None:
            instance._begin(values)
            try:
                ok = instance.on_run()
                if type(ok) is not bool:
                    raise TypeError(f"on_run() must return True or False, not {type(ok).__name__}")
                result = _R_TRUE if ok else _R_FALSE
            except StopRequested:
                result = _R_STOPPED
            except BaseException as err:
                error = ActionError(f"{node.name} failed: {err}", graph=run.name, node=node.name)
                error.__cause__ = err
            outputs = instance._outputs._taken()
        if run.peers and result is not _R_STOPPED and node.umrf.actor == self.actor:
            assert self._shared is not None
            result, error = self._shared.notify(node, result, outputs, error)
        return node, gen, instance, result, outputs, error

    def _settle(self, done: _Done, fx: list[Effect]) -> None:
        """Lock held: apply the end of an action run (evolution)."""
        node, gen, instance, result, outputs, error = done
        if instance is not None and gen == node.gen:
            if node.instance is None:  # an inline node's first run (see _instantiate)
                node.instance = instance
            node.log = instance._log_snapshot()
        if (
            node.spontaneous
            and gen == node.gen
            and node.run.state is not _G_PAUSED
            and not node.restart
        ):
            fx.append((_SPONT, node, gen, result, outputs, error))
        else:
            self._on_finished(node, gen, result, outputs, error, fx)

    def _instantiate(self, node: Node, gen: int) -> Action:
        """No lock: make a node's action instance and call its ``on_init``.

        A blocking node's instance is registered at once, so that ``on_stop`` and ``on_pause``
        reach its first run; an inline node's is registered with its first result
        (:meth:`_settle`), saving a lock per new node: its run does not wait for hooks.
        """
        assert node.cls is not None
        assert node.control is not None
        instance = node.cls()
        instance._bind(  # positional: one action binding per node and run, on the hot path
            node.control, node.name, node.run.name, node.inputs, node.outputs, self.registrar
        )
        instance.on_init()
        if not node.inline:
            with self._lock:
                node.instance = instance
        return instance

    def _call_hook(self, node: Node, gen: int, hook: str) -> None:
        with self._lock:
            # a hook meant for an earlier run (e.g. on_stop before a restart) is dropped
            instance = node.instance if node.gen == gen else None
        if instance is not None:
            try:
                getattr(instance, hook)()
            except Exception:
                logger.exception("%s/%s: %s() raised", node.run.name, node.name, hook)
        if hook == "on_pause":
            with self._lock:
                if node.gen == gen and node.state is _N_PAUSE_REQUESTED:
                    self._set_state(node, _N_PAUSED)

    def _finish_spontaneous(
        self,
        node: Node,
        gen: int,
        result: Result,
        outputs: dict[str, Any],
        error: BaseException | None,
    ) -> None:
        """Worker: stop everything downstream of a spontaneous action, then propagate and re-run."""
        fx: list[Effect] = []
        with self._lock:
            downstream = self._downstream(node)
            for other in downstream:
                if other.active:
                    self._stop_node(other, fx)
        self._dispatch(fx, closing=self._closed)
        fx = []
        with self._lock:
            self._quiet_waiters += 1
            try:
                while any(n.active for n in downstream) and not self._closed and node.gen == gen:
                    self._quiet.wait()
            finally:
                self._quiet_waiters -= 1
            if node.gen != gen:
                return
            rerun = node.state is _N_RUNNING and node.run.state is _G_RUNNING and not self._closed
            self._on_finished(node, gen, result, outputs, error, fx)
            if rerun and node.state is _N_FINISHED and node.run.state is _G_RUNNING:
                self._run_node(node, fx)
                self._after_change(node.run, fx)
        # the re-run (or the first action that became ready) continues on this worker
        nxt = next((e for e in fx if e[0] == _RUN), None)
        if nxt is not None:
            fx.remove(nxt)
        self._dispatch(fx, closing=self._closed)
        if nxt is not None:
            self._run_batch([(nxt[1], nxt[2])])

    def _downstream(self, start: Node) -> list[Node]:
        seen = {start.name}
        out: list[Node] = []
        todo = [start]
        while todo:
            node = todo.pop()
            for child in node.run.children(node):
                if child.kind is _K_EXIT or child.name in seen:
                    continue
                seen.add(child.name)
                out.append(child)
                todo.append(child)
        return out

    # ================================================================ evolution (lock held)

    def _set_state(self, node: Node, new: NodeState) -> None:
        old = node.state
        if new not in NODE_TRANSITIONS[old]:
            raise StateError(
                f"{node.run.name}/{node.name}: illegal state change {old.value} -> {new.value}"
            )
        node.state = new
        was, now = old in _ACTIVE, new in _ACTIVE
        if was != now:
            node.run.active += 1 if now else -1
            if not now:
                if self._quiet_waiters:
                    self._quiet.notify_all()
                if node.run.state in _ENDED_GRAPH:
                    self._release_node(node)
        if self._watchers:
            t = self.clock.monotonic()
            for inst in list(self._watchers):
                try:
                    inst.node_transition(node.run.name, node.name, old, new, t)
                except Exception:
                    self._drop_instrument(inst)
        if self._feedback_on:
            self._feedback.append(self._snapshot(node.run))

    def _drop_instrument(self, inst: Instrument) -> None:
        logger.exception("instrument %r raised; removing it", inst)
        if inst in self._instruments:
            self._instruments.remove(inst)
        if inst in self._watchers:
            self._watchers.remove(inst)

    def _notify(self, hook: str, *args: Any) -> None:
        for inst in list(self._instruments):
            try:
                getattr(inst, hook)(*args)
            except Exception:
                self._drop_instrument(inst)

    def _start_run(
        self, run: GraphRun, values: dict[str, Any], result: Result, fx: list[Effect]
    ) -> None:
        run.state = _G_RUNNING
        # every local node's control is made now, with the graph's other long-lived objects,
        # not one by one on the action path (a node added by `modify` gets its own at its run)
        clock = self.clock
        for node in run.nodes.values():
            if node.control is None and node.kind is _K_LOCAL:
                node.control = RunControl(clock)
        run.started_at = clock.monotonic()
        if self._instruments:
            self._notify("graph_started", run.name, run.started_at)
        entry = run.entry
        entry.data = dict(values)
        self._propagate(entry, result, values, fx)
        self._after_change(run, fx)

    def _on_finished(
        self,
        node: Node,
        gen: int,
        result: Result,
        outputs: dict[str, Any],
        error: BaseException | None,
        fx: list[Effect],
    ) -> None:
        """An action run ended (returned, raised, timed out, or its sub-graph ended)."""
        if gen != node.gen:
            return  # a run the engine already gave up on (stop timeout)
        run = node.run
        if node.state in (_N_PAUSE_REQUESTED, _N_PAUSED):
            node.held = (result, outputs, error)  # delivered on resume
            return
        if node.state is _N_STOPPING:
            result = _R_STOPPED
        if node.stop_timer is not None:
            node.stop_timer.cancel()
            node.stop_timer = None
        if len(node.data) != len(node.native):
            node.clear_data()
        node.last_outputs = outputs
        if node.restart:
            node.restart = False
            self._set_state(node, _N_FINISHED)
            if run.state in (_G_RUNNING, _G_PAUSED):
                self._run_node(node, fx)
            self._after_change(run, fx)
            return
        if error is not None and result is _R_ERROR:
            node.error = error
            run.errors.append(error)
            logger.warning("%s: %s", run.name, error)
            if self._instruments:
                self._notify("action_failed", run.name, node.name, error)
        if self._watchers:  # the result, then the state change it leads to
            t = self.clock.monotonic()
            for inst in list(self._watchers):
                try:
                    inst.node_result(run.name, node.name, result, t)
                except Exception:
                    self._drop_instrument(inst)
        self._set_state(node, _N_ERROR if result is _R_ERROR else _N_FINISHED)
        if run.state is _G_RUNNING:
            self._propagate(node, result, outputs, fx)
        if not run.active:
            self._after_change(run, fx)

    def _propagate(
        self, node: Node, result: Result, outputs: Mapping[str, Any], fx: list[Effect]
    ) -> None:
        """Deliver a finished node's result and outputs to its children (REFERENCE §2.5).

        The evolution kernel computes the wave (responses, received parents, bypass chains);
        this carries out its steps: parameter transfer, input readiness, state changes.
        """
        run = node.run
        edge_child = run.edge_child
        fast = not self._watchers and not self._feedback_on
        for step in run.evolution.propagate(node.idx, _RESULT_CODES[result]):
            edge = step >> _SHIFT
            child = edge_child[edge]
            code = (step >> 1) & 7
            if code == _P_IGNORE:
                continue
            if code == _P_BYPASS:
                if child.kind is _K_EXIT:
                    self._finish_run(run, result, fx)
                    return
                if not child.active:
                    self._set_state(child, _N_BYPASSED)
                continue
            if code == _P_LOOP:
                logger.warning(
                    "%s: bypass loops back to %s; stopping it there", run.name, child.name
                )
                continue
            if outputs and run.edge_parent[edge] is node:
                _transfer(node, child, run.edge_remap[edge], outputs)
            if not step & 1 or (child.required_inputs and not child.inputs_ready()):
                continue
            kind = child.kind
            if kind is _K_LOCAL and code == _P_RUN and fast and child.state not in _ACTIVE:
                # _run_node's path for an idle local node, without observers to tell: every
                # idle state may go to RUNNING (NODE_TRANSITIONS)
                child.gen += 1
                child.held = None
                control = child.control
                if control is None:
                    child.control = RunControl(self.clock)
                elif control._cond is None:  # RunControl.reset without a waiter to race with
                    control.stop = control.paused = False
                else:
                    control.reset()
                if child.fresh_instance:
                    child.instance = None  # the old one is stuck in a run we gave up on
                    child.fresh_instance = False
                child.state = _N_RUNNING
                run.active += 1
                fx.append((_RUN, child, child.gen))
                continue
            if kind is _K_EXIT:
                self._finish_run(run, result, fx)
                return
            if code == _P_RUN:
                self._run_node(child, fx)
            elif code == _P_STOP:
                self._stop_node(child, fx)
            elif code == _P_PAUSE:
                self._pause_node(child, fx)
            else:
                self._restart_node(child, fx)
            if run.state is not _G_RUNNING:
                return

    def _run_node(self, node: Node, fx: list[Effect]) -> None:
        if node.state in (_N_PAUSE_REQUESTED, _N_PAUSED) and node.run.state is _G_RUNNING:
            self._resume_node(node, fx)  # paused by a `pause` response: `run` resumes it
            return
        if node.state in _ACTIVE or node.kind in (_K_ENTRY, _K_EXIT):
            return
        run = node.run
        node.gen += 1
        node.held = None
        if node.kind is _K_LOCAL:
            if node.control is None:
                node.control = RunControl(self.clock)
            else:
                node.control.reset()
            if node.fresh_instance:
                node.instance = None  # the old one is stuck in a run we gave up on
                node.fresh_instance = False
            self._set_state(node, _N_RUNNING)
            fx.append((_RUN, node, node.gen))
            return
        if node.kind is _K_REMOTE:
            self._set_state(node, _N_RUNNING)
            assert self._shared is not None
            fx.append((_CALL, self._shared.expect, node, node.gen))
            return
        assert node.plan is not None
        self._set_state(node, _N_RUNNING)
        child = GraphRun(
            f"{run.name}__{node.umrf.name}__{node.umrf.instance_id}", node.plan, parent_node=node
        )
        node.child_run = child
        old = self._runs.get(child.name)
        if old is not None and old.state in _BUSY_GRAPH:
            logger.warning(
                "%s: replacing sub-graph run %s that was still %s",
                run.name,
                child.name,
                old.state.value,
            )
        self._runs[child.name] = child
        values = {k: v for k, v in node.data.items() if k in child.entry.inputs}
        node.clear_data()
        self._start_run(child, values, _R_TRUE, fx)

    def _stop_node(self, node: Node, fx: list[Effect]) -> None:
        if node.state not in (_N_RUNNING, _N_PAUSE_REQUESTED, _N_PAUSED):
            return
        self._set_state(node, _N_STOPPING)
        if node.kind is _K_GRAPH:
            if node.child_run is not None:
                self._stop_run(node.child_run, fx)
            return
        if node.kind is _K_REMOTE:  # nothing runs here: stop waiting for its actor
            if node.remote_cancel is not None:
                fx.append((_CALL, node.remote_cancel))
                node.remote_cancel = None
            self._on_finished(node, node.gen, _R_STOPPED, {}, None, fx)
            return
        assert node.control is not None
        node.control.request_stop()
        fx.append((_HOOK, node, node.gen, "on_stop"))
        node.stop_timer = self._timer.call_later(
            self.clock.real_seconds(self.stop_timeout), self._stop_expired, node, node.gen
        )
        if node.held is not None:  # it had already finished while paused
            result, outputs, error = node.held
            node.held = None
            self._on_finished(node, node.gen, result, outputs, error, fx)

    def _stop_expired(self, node: Node, gen: int) -> None:
        """Timer thread: an action ignored its stop for ``stop_timeout``."""
        fx: list[Effect] = []
        with self._lock:
            if node.gen != gen or node.state is not _N_STOPPING:
                return
            run = node.run
            node.gen += 1  # its late return is ignored
            node.fresh_instance = True
            node.stop_timer = None
            error = ActionError(
                f"{node.name} did not stop within {self.stop_timeout} s; marked ERROR",
                graph=run.name,
                node=node.name,
            )
            node.error = error
            run.errors.append(error)
            run.stop_failed = True
            logger.error("%s: %s", run.name, error)
            self._set_state(node, _N_ERROR)
            if node.restart:
                node.restart = False
                if run.state is _G_RUNNING:
                    self._run_node(node, fx)
            self._after_change(run, fx)
        self._dispatch(fx, closing=self._closed)

    def _pause_node(self, node: Node, fx: list[Effect]) -> None:
        if node.state is not _N_RUNNING:
            return
        if node.kind is _K_GRAPH:
            self._set_state(node, _N_PAUSE_REQUESTED)
            self._set_state(node, _N_PAUSED)
            if node.child_run is not None and node.child_run.state is _G_RUNNING:
                self._pause_run(node.child_run, fx)
            return
        if node.kind is _K_REMOTE:  # its actor goes on; a result is held until resume
            self._set_state(node, _N_PAUSE_REQUESTED)
            self._set_state(node, _N_PAUSED)
            return
        assert node.control is not None
        self._set_state(node, _N_PAUSE_REQUESTED)
        node.control.set_paused(True)
        fx.append((_HOOK, node, node.gen, "on_pause"))

    def _resume_node(self, node: Node, fx: list[Effect]) -> None:
        if node.state not in (_N_PAUSE_REQUESTED, _N_PAUSED):
            return
        self._set_state(node, _N_RUNNING)
        if node.kind is _K_GRAPH:
            if node.child_run is not None and node.child_run.state is _G_PAUSED:
                self._resume_run(node.child_run, None, fx)
            return
        if node.kind is _K_REMOTE:
            if node.held is not None:
                result, outputs, error = node.held
                node.held = None
                self._on_finished(node, node.gen, result, outputs, error, fx)
            return
        assert node.control is not None
        node.control.set_paused(False)
        fx.append((_HOOK, node, node.gen, "on_resume"))
        if node.held is not None:
            result, outputs, error = node.held
            node.held = None
            if node.spontaneous:
                fx.append((_SPONT, node, node.gen, result, outputs, error))
            else:
                self._on_finished(node, node.gen, result, outputs, error, fx)

    def _restart_node(self, node: Node, fx: list[Effect]) -> None:
        if node.active:
            node.restart = True
            self._stop_node(node, fx)
        else:
            self._run_node(node, fx)

    def _pause_run(self, run: GraphRun, fx: list[Effect]) -> None:
        run.state = _G_PAUSED
        for node in list(run.nodes.values()):
            self._pause_node(node, fx)

    def _resume_run(self, run: GraphRun, continue_from: str | None, fx: list[Effect]) -> None:
        # The graph is RUNNING before any node is released, so a node finishing at once is
        # propagated (upstream releases nodes first and can drop that result).
        if run.state is _G_HALTED:
            run.done.clear()
            run.result = None
        run.state = _G_RUNNING
        for node in list(run.nodes.values()):
            if run.state is not _G_RUNNING:
                break
            self._resume_node(node, fx)
        if continue_from is not None and run.state is _G_RUNNING:
            self._run_node(run.nodes[continue_from], fx)
        self._after_change(run, fx)

    def _stop_run(self, run: GraphRun, fx: list[Effect]) -> None:
        if run.state in (
            _G_FINISHED,
            _G_STOPPED,
            _G_ERROR,
            _G_STOPPING,
        ):
            return
        if run.state is _G_HALTED:
            run.done.clear()
        run.state = _G_STOPPING
        for node in list(run.nodes.values()):
            self._stop_node(node, fx)
        self._after_change(run, fx)

    def _after_change(self, run: GraphRun, fx: list[Effect]) -> None:
        if run.active:
            return
        if run.state is _G_STOPPING:
            failed = run.stop_failed
            self._end_run(
                run,
                _G_ERROR if failed else _G_STOPPED,
                _R_ERROR if failed else _R_STOPPED,
                fx,
            )
        elif run.state is _G_RUNNING:
            waiting = sorted(
                n.name
                for n in run.nodes.values()
                if n.state is _N_UNINITIALIZED and run.received_any(n) and not _ready(n)
            )
            if waiting:
                logger.warning(
                    "graph %s halted: nothing runs, and %s still wait for parents or inputs",
                    run.name,
                    ", ".join(waiting),
                )
            else:
                logger.info("graph %s halted: nothing runs and its exit was not reached", run.name)
            self._end_run(run, _G_HALTED, _R_HALTED, fx)

    def _finish_run(self, run: GraphRun, result: Result, fx: list[Effect]) -> None:
        run.outputs = dict(run.exit.data)
        self._end_run(run, _G_FINISHED, result, fx)
        # Actions still running are no longer needed: stop them (their results are ignored).
        for node in list(run.nodes.values()) if run.active else ():
            if node.state in _ACTIVE:
                self._stop_node(node, fx)

    def _release_node(self, node: Node) -> None:
        """Release the resources a node's action holds (it is idle and its run has ended)."""
        instance = node.instance
        if instance is not None and instance._resources:
            self._releases.append((_RELEASE, instance))

    def _end_run(self, run: GraphRun, state: GraphState, result: Result, fx: list[Effect]) -> None:
        run.state = state
        run.result = result
        if run.peers:
            assert self._shared is not None
            fx.append((_CALL, self._shared.end, run))
        releases = self._releases
        for node in run.nodes.values():  # _release_node for each idle one, inlined (all nodes)
            instance = node.instance
            if instance is not None and instance._resources and node.state not in _ACTIVE:
                releases.append((_RELEASE, instance))
        if self._instruments:
            self._notify("graph_finished", run.name, result, self.clock.monotonic())
        if not run.peers:
            run.done.set()  # a shared run is done once the link has forgotten it (SharedRuns.end)
        parent = run.parent_node
        if parent is not None and parent.child_run is run and parent.active:
            error: BaseException | None = None
            if result is _R_HALTED:
                result = _R_ERROR
                error = ActionError(
                    f"sub-graph {run.name} halted without reaching its exit",
                    graph=parent.run.name,
                    node=parent.name,
                )
            elif result is _R_ERROR and run.errors:
                error = run.errors[-1]
            outputs = {k: v for k, v in run.outputs.items() if k in parent.outputs}
            self._on_finished(parent, parent.gen, result, outputs, error, fx)

    # ================================================================ helpers (lock held)

    def _get(self, name: str) -> GraphRun:
        with self._lock:
            run = self._runs.get(name)
        if run is None:
            raise GraphNotFoundError(f"no graph run named '{name}'")
        return run

    def _snapshot(self, run: GraphRun) -> dict[str, Any]:
        actions = []
        for node in sorted(run.nodes.values(), key=lambda n: n.name):
            log = node.log
            if node.active and node.instance is not None:
                log = node.instance._log_snapshot()  # a running action's log, as it grows
            umrf = dataclasses.replace(node.umrf, state=node.state, runtime_messages=log)
            out = dump_umrf(umrf)
            if node.inputs:
                out["input_parameters"] = dump_parameter_tree(node.inputs, node.data)
            actions.append(out)
        graph = dataclasses.replace(run.plan.graph, name=run.name, state=run.state)
        return graph_to_dict(graph, actions)


def _transfer(
    parent: Node, child: Node, remap: Mapping[str, str], outputs: Mapping[str, Any]
) -> None:
    """Copy a parent's outputs into a child's inputs (REFERENCE §2.5, parameter transfer)."""
    inputs = child.inputs
    kinds = parent.outputs
    for name, value in outputs.items():
        target = remap.get(name, name)
        param = inputs.get(target)
        if param is None:
            continue
        source = kinds.get(name)
        if source is not None and source.type != param.type:
            continue
        if not param.updatable and target in child.data:
            continue
        if param.allowed_values and not param.accepts(value):
            continue
        child.data[target] = value
        if target in child.native:
            child.native.discard(target)  # type: ignore[union-attr]  # non-empty: a set


def _watches_transitions(instrument: Instrument) -> bool:
    """Whether an instrument overrides a hook called per action run.

    Those are :meth:`Instrument.node_transition` and :meth:`Instrument.node_result`.
    """
    kind = type(instrument)
    return any(
        getattr(kind, hook, base) is not base
        for hook, base in (
            ("node_transition", Instrument.node_transition),
            ("node_result", Instrument.node_result),
        )
    )


def _ready(node: Node) -> bool:
    """Whether a node's required parents were received and its required inputs are set."""
    return node.run.evolution.missing_parents(node.idx) == 0 and node.inputs_ready()


def _release_resources(instance: Any) -> None:
    """Worker: release what a node's action acquired (RAII at graph end / node removal)."""
    try:
        count = instance._release_resources()
    except Exception:
        logger.exception("releasing the resources of %s failed", instance.name)
        return
    if count:
        logger.debug("released %d resources of %s", count, instance.name)
