"""The evolution of graph runs: how nodes and runs change state, with the engine's lock held.

One part of the engine (see :mod:`temoto.core.engine`): :class:`RunEvolution` owns the engine's
lock, its runs, and every state change of a run and of its nodes, each through one checked
path (:meth:`RunEvolution.set_state` against :data:`~temoto.core.states.NODE_TRANSITIONS`,
:meth:`RunEvolution.set_run_state` against :data:`~temoto.core.states.GRAPH_TRANSITIONS`). A run
starts (the entry's result reaches its first actions), an action run finishes (its result is
applied: held while paused, turned into a stop or a restart, or recorded:
:meth:`RunEvolution.finished_next`, the one path of an action's end), the result propagates to
the children along the condition table (the evolution kernel, :mod:`temoto.core._fast`,
computes the wave), parameters are transferred along the relations, ready children start
(one path, whatever made them ready), and the run ends (finished, halted, stopped or failed)
and hands its result to a parent node when it is a sub-graph.

Everything here is plain computation under the engine's lock: it never waits and never calls
user code. What must happen outside the lock (run an action, call a hook, release resources,
talk to the actor link) goes into the :class:`~temoto.core.effects.Effects` ``fx`` for the
dispatcher (:mod:`temoto.core.dispatch`), which the evolution reaches through one port,
:attr:`RunEvolution.carry_out`, from the timer thread only (an action that ignores its stop).
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from collections.abc import Callable, Iterable, Mapping
from typing import TYPE_CHECKING, Any

from temoto.core._fast import P_BYPASS, P_IGNORE, P_LOOP, P_PAUSE, P_RUN, P_STOP, SHIFT
from temoto.core._runtime import RESULT_CODES as _RESULT_CODES
from temoto.core._runtime import GraphRun, Node, NodeKind
from temoto.core.effects import Effect, EffectKind, Effects
from temoto.core.instrument import Instrument
from temoto.core.snapshot import snapshot
from temoto.core.states import (
    ACTIVE_NODE_STATES,
    BUSY_GRAPH_STATES,
    ENDED_GRAPH_STATES,
    GRAPH_TRANSITIONS,
    NODE_TRANSITIONS,
    PAUSED_GRAPH_STATES,
    GraphState,
    NodeState,
    Result,
    check_graph_transition,
    check_node_transition,
)
from temoto.core.values import NO_VALUES
from temoto.errors import ActionError

if TYPE_CHECKING:
    from temoto.clock import Clock
    from temoto.core.action import Action
    from temoto.core.executor import DeadlineTimer, TimerHandle
    from temoto.core.shared import SharedRuns

__all__ = ["RunEvolution"]

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
_G_ERROR = GraphState.ERROR
_G_FINISHED = GraphState.FINISHED
_G_HALTED = GraphState.HALTED
_G_PAUSED = GraphState.PAUSED
_G_PAUSE_REQUESTED = GraphState.PAUSE_REQUESTED
_G_RUNNING = GraphState.RUNNING
_G_STOPPED = GraphState.STOPPED
_G_STOPPING = GraphState.STOPPING
_R_ERROR = Result.ERROR
_R_HALTED = Result.HALTED
_R_STOPPED = Result.STOPPED
_R_TRUE = Result.TRUE
_K_ENTRY = NodeKind.ENTRY
_K_EXIT = NodeKind.EXIT
_K_GRAPH = NodeKind.GRAPH
_K_LOCAL = NodeKind.LOCAL
_K_REMOTE = NodeKind.REMOTE
_E_HOOK = EffectKind.HOOK
_E_FINISH_SPONTANEOUS = EffectKind.FINISH_SPONTANEOUS
_E_RELEASE = EffectKind.RELEASE
_E_CALL = EffectKind.CALL

_ACTIVE = ACTIVE_NODE_STATES
_BUSY_GRAPH = BUSY_GRAPH_STATES
_ENDED_GRAPH = ENDED_GRAPH_STATES
_PAUSED_GRAPH = PAUSED_GRAPH_STATES
_NODE_NEXT = NODE_TRANSITIONS
_GRAPH_NEXT = GRAPH_TRANSITIONS
#: The node changes the fast paths make without a table lookup: an action's end in a RUNNING
#: node, and the start of an idle node. Each must be legal by :data:`NODE_TRANSITIONS`; an
#: engine checks them against the table when it is made (:func:`fast_changes_legal`), and
#: takes the checked path (:meth:`RunEvolution.set_state`) for every change if one is not.
FAST_CHANGES: tuple[tuple[NodeState, NodeState], ...] = (
    (_N_RUNNING, _N_FINISHED),
    *((old, _N_RUNNING) for old in NodeState if old not in ACTIVE_NODE_STATES),
)


def fast_changes_legal() -> bool:
    """Whether every change of :data:`FAST_CHANGES` is in :data:`NODE_TRANSITIONS` now."""
    return all(new in NODE_TRANSITIONS[old] for old, new in FAST_CHANGES)


#: the low bits of a wave step (``edge << SHIFT | response << 1 | ready``) for the response
#: `run` to a child whose every required parent was received
_RUN_READY = P_RUN << 1 | 1


class RunEvolution:
    """The engine's runs and every state change of them and of their nodes (lock held).

    A part of :class:`~temoto.core.engine.ActionEngine`. Methods whose docstring says "lock
    held" are called with :attr:`lock` held; they never wait and never call user code: what
    must happen outside the lock goes into the ``fx`` they are given, for the dispatcher
    (:class:`~temoto.core.dispatch.Dispatcher`). It is also the host of the shared-run
    protocol (:class:`~temoto.core.shared.RunHost`).

    Args:
        clock: Where time is read.
        stop_timeout: Clock seconds an action has to return after a stop.
        timer: The timer thread that enforces ``stop_timeout``.
        instruments: Observers of engine events.
        feedback_size: Whole-graph snapshots kept (one per node state change); 0 keeps none.
    """

    def __init__(
        self,
        clock: Clock,
        stop_timeout: float,
        timer: DeadlineTimer,
        instruments: Iterable[Instrument] = (),
        feedback_size: int = 0,
    ) -> None:
        self.clock = clock
        self.stop_timeout = stop_timeout
        self.timer = timer
        #: the engine's one lock: it guards every run, node and the fields below
        self.lock = threading.Lock()
        self._quiet = threading.Condition(self.lock)  # a node went idle (wait_quiet)
        self._quiet_waiters = 0
        #: every run by name, sub-graph runs and ended runs included
        self.runs: dict[str, GraphRun] = {}
        self._instruments = list(instruments)
        # the instruments that observe node transitions (two per action run: kept apart so an
        # instrument that only watches graph starts and ends costs nothing per action)
        self._watchers = [i for i in self._instruments if watches_transitions(i)]
        self._feedback: deque[dict[str, Any]] = deque(maxlen=max(feedback_size, 1))
        self._feedback_on = feedback_size > 0
        #: the fast paths' changes (FAST_CHANGES) are legal by the transition table
        self._fast_legal = fast_changes_legal()
        #: whether anything observes node transitions (watchers, feedback), or the fast paths'
        #: changes are not legal: the fast paths are taken only when neither is so
        self.observed = bool(self._watchers) or self._feedback_on or not self._fast_legal
        #: the shared-run protocol (temoto.core.shared), with an actor link only
        self.shared: SharedRuns | None = None
        #: carries out effects outside the lock (the dispatcher's); set by the engine
        self.carry_out: Callable[[Effects], None] = _no_port
        #: releases found under the lock, handed to workers by the next dispatch (read
        #: without the lock as a hint; taken with it, :meth:`take_releases`)
        self.releases: list[Effect] = []

    # ------------------------------------------------------------ observers, quiet, releases

    def add_instrument(self, instrument: Instrument) -> None:
        """Lock held: attach an observer."""
        self._instruments.append(instrument)
        if watches_transitions(instrument):
            self._watchers.append(instrument)
            self.observed = True

    def take_feedback(self) -> list[dict[str, Any]]:
        """Lock held: return and clear the buffered snapshots."""
        out = list(self._feedback)
        self._feedback.clear()
        return out

    def take_releases(self) -> list[Effect]:
        """Lock held: the resource releases found since the last call (for workers)."""
        out = self.releases
        self.releases = []
        return out

    def wait_quiet(self, busy: Callable[[], bool]) -> None:
        """Lock held: wait (releasing the lock) while ``busy()``, woken as nodes go idle."""
        self._quiet_waiters += 1
        try:
            while busy():
                self._quiet.wait()
        finally:
            self._quiet_waiters -= 1

    def wake(self) -> None:
        """Lock held: wake every :meth:`wait_quiet` (the engine shuts down)."""
        self._quiet.notify_all()

    def _drop_instrument(self, inst: Instrument) -> None:
        logger.exception("instrument %r raised; removing it", inst)
        if inst in self._instruments:
            self._instruments.remove(inst)
        if inst in self._watchers:
            self._watchers.remove(inst)
        self.observed = bool(self._watchers) or self._feedback_on or not self._fast_legal

    def _notify(self, hook: str, *args: Any) -> None:
        for inst in list(self._instruments):
            try:
                getattr(inst, hook)(*args)
            except Exception:
                self._drop_instrument(inst)

    # ------------------------------------------------------------ the two state paths

    def set_state(self, node: Node, new: NodeState) -> None:
        """Lock held: the one path of a node's state change (checked, counted, observed).

        Raises:
            StateError: The change is not in :data:`~temoto.core.states.NODE_TRANSITIONS`.
        """
        old = node.state
        if new not in _NODE_NEXT[old]:
            check_node_transition(node.run.name, node.name, old, new)
        node.state = new
        now = new in _ACTIVE
        if (old in _ACTIVE) is not now:
            run = node.run
            if now:
                run.active += 1
            else:
                run.active -= 1
                if self._quiet_waiters:
                    self._quiet.notify_all()
                if run.state in _ENDED_GRAPH:
                    self.release_node(node)
        if self.observed:
            self._observe(node, old, new)
        if old is _N_PAUSE_REQUESTED and node.run.state is _G_PAUSE_REQUESTED:
            self._pause_done(node.run)

    def _observe(self, node: Node, old: NodeState, new: NodeState) -> None:
        if self._watchers:
            t = self.clock.monotonic()
            for inst in list(self._watchers):
                try:
                    inst.node_transition(node.run.name, node.name, old, new, t)
                except Exception:
                    self._drop_instrument(inst)
        if self._feedback_on:
            self._feedback.append(snapshot(node.run))

    def set_run_state(self, run: GraphRun, new: GraphState) -> None:
        """Lock held: the one path of a run's state change (checked).

        Raises:
            StateError: The change is not in :data:`~temoto.core.states.GRAPH_TRANSITIONS`.
        """
        if new not in _GRAPH_NEXT[run.state]:
            check_graph_transition(run.name, run.state, new)
        run.state = new

    # ------------------------------------------------------------ runs

    def start_run(self, run: GraphRun, values: dict[str, Any], result: Result, fx: Effects) -> None:
        """Lock held: start a new run: the entry hands ``result`` and ``values`` on."""
        self.set_run_state(run, _G_RUNNING)
        run.started_at = self.clock.monotonic()
        if self._instruments:
            self._notify("graph_started", run.name, run.started_at)
        entry = run.entry
        entry.data = dict(values)
        steps = run.evolution.propagate(entry.idx, _RESULT_CODES[result])
        self._apply_wave(entry, result, values, steps, fx)
        self.after_change(run, fx)

    def pause_run(self, run: GraphRun, fx: Effects) -> None:
        """Lock held: pause a RUNNING run: its running nodes are paused.

        The run is PAUSE_REQUESTED until every node that was running has paused (its
        ``on_pause`` returned, its sub-graph paused), then PAUSED.
        """
        self.set_run_state(run, _G_PAUSE_REQUESTED)
        for node in list(run.nodes.values()):
            self._pause_node(node, fx)
        if run.state is _G_PAUSE_REQUESTED:
            self._pause_done(run)

    def _pause_done(self, run: GraphRun) -> None:
        """A pausing run is PAUSED once none of its nodes is still pausing (and so on up)."""
        for n in run.nodes.values():  # (RUNNING: pause_run has not reached it yet)
            if n.state is _N_PAUSE_REQUESTED or n.state is _N_RUNNING:
                return
        self.set_run_state(run, _G_PAUSED)
        parent = run.parent_node
        if parent is not None and parent.child_run is run and parent.state is _N_PAUSE_REQUESTED:
            self.set_state(parent, _N_PAUSED)  # which may complete its own run's pause

    def resume_run(self, run: GraphRun, continue_from: str | None, fx: Effects) -> None:
        """Lock held: resume a paused or halted run (or a running one's paused nodes)."""
        # The graph is RUNNING before any node is released, so a node finishing at once is
        # propagated (upstream releases nodes first and can drop that result).
        if run.state is _G_HALTED:
            run.done.clear()
            run.result = None
        if run.state is not _G_RUNNING:
            self.set_run_state(run, _G_RUNNING)
        for node in list(run.nodes.values()):
            if run.state is not _G_RUNNING:
                break
            self._resume_node(node, fx)
        if continue_from is not None and run.state is _G_RUNNING:
            self.run_node(run.nodes[continue_from], fx)
        self.after_change(run, fx)

    def stop_run(self, run: GraphRun, fx: Effects) -> None:
        """Lock held: stop a run (one that has ended stays as it is, a halted one stops)."""
        if run.state in (_G_FINISHED, _G_STOPPED, _G_ERROR, _G_STOPPING):
            return
        if run.state is _G_HALTED:
            run.done.clear()
        self.set_run_state(run, _G_STOPPING)
        for node in list(run.nodes.values()):
            self.stop_node(node, fx)
        self.after_change(run, fx)

    def fail_run(self, run: GraphRun, reason: BaseException, fx: Effects) -> None:
        """Lock held: end a run ERROR for a fault of the engine (not of an action)."""
        run.errors.append(reason)
        self.end_run(run, _G_ERROR, _R_ERROR, fx)

    def end_with_peer(self, run: GraphRun, result: Result, fx: Effects) -> None:
        """Lock held: a shared run ends here with the result another actor reached."""
        if result is _R_HALTED:
            self.end_run(run, _G_HALTED, result, fx)
            for node in list(run.nodes.values()):
                if node.active:
                    self.stop_node(node, fx)
        else:
            self.finish_run(run, result, fx)

    def take_peer_result(self, run: GraphRun, result: Result) -> None:
        """Lock held: a settling (aborted, ended) shared run takes a peer's result instead."""
        self.set_run_state(run, _G_HALTED if result is _R_HALTED else _G_FINISHED)
        run.result = result
        run.aborted = None

    def after_change(self, run: GraphRun, fx: Effects) -> None:
        """Lock held: end a run in which nothing is active any more (stopped, or halted)."""
        if run.active:
            return
        if run.state is _G_STOPPING:
            failed = run.stop_failed
            self.end_run(
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
            self.end_run(run, _G_HALTED, _R_HALTED, fx)

    def finish_run(self, run: GraphRun, result: Result, fx: Effects) -> None:
        """Lock held: a run reached its exit; actions still running are stopped."""
        run.outputs = dict(run.exit.data)
        self.end_run(run, _G_FINISHED, result, fx)
        # Actions still running are no longer needed: stop them (their results are ignored).
        for node in list(run.nodes.values()) if run.active else ():
            if node.state in _ACTIVE:
                self.stop_node(node, fx)

    def end_run(self, run: GraphRun, state: GraphState, result: Result, fx: Effects) -> None:
        """Lock held: a run ends in ``state`` with ``result``; its parent node finishes."""
        self.set_run_state(run, state)
        run.result = result
        if run.peers:
            assert self.shared is not None
            fx.other.append(Effect(_E_CALL, call=self.shared.end, args=(run,)))
        releases = self.releases
        for node in run.nodes.values():  # release_node for each idle one, inlined (all nodes)
            instance = node.instance
            if (
                node.acquired
                and instance is not None
                and node.state not in _ACTIVE
                and instance.holds_resources
            ):
                releases.append(Effect(_E_RELEASE, action=instance))
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
            self.action_finished(parent, parent.gen, result, outputs, error, fx)

    def release_node(self, node: Node) -> None:
        """Lock held: release the resources a node's action holds (idle, its run ended)."""
        instance = node.instance
        if instance is not None and instance.holds_resources:
            self.releases.append(Effect(_E_RELEASE, action=instance))

    # ------------------------------------------------------------ an action finished

    def adopt(self, node: Node, instance: Action) -> None:
        """Lock held: a node keeps the action that ran it and its log (its run ended).

        An inline node's instance is kept from its first run's end (the dispatcher makes it
        without the lock); a blocking node's is kept already.
        """
        if node.instance is None:
            node.instance = instance
        if node.log or node.logged:
            node.log = instance.log_snapshot()

    def action_finished(
        self,
        node: Node,
        gen: int,
        result: Result,
        outputs: dict[str, Any],
        error: BaseException | None,
        fx: Effects,
        instance: Action | None = None,
    ) -> None:
        """Lock held: an action run ended (returned, raised, timed out, or its sub-graph ended).

        :meth:`finished_next`, with the action it started queued in ``fx`` like every other.
        """
        child = self.finished_next(node, gen, result, outputs, error, fx, instance)
        if child is not None:
            fx.runs.append((child, child.gen))

    def finished_next(
        self,
        node: Node,
        gen: int,
        result: Result,
        outputs: dict[str, Any],
        error: BaseException | None,
        fx: Effects,
        instance: Action | None,
    ) -> Node | None:
        """Lock held: an action run ended; the one path of an action's end.

        Its result is held while the node is paused, turned into a stop or a restart, or
        recorded and propagated to the children. ``instance``: the action that ran (a worker's
        run), which the node keeps with its log. The dispatcher's fast paths (a chain, a
        batch's round) call it directly, :meth:`action_finished` for everyone else.

        Returns:
            The idle local child this end started when its wave was that one step: it is
            RUNNING but not queued in ``fx``, and the caller runs it (or queues it); the end
            then added nothing to ``fx`` either. None when the end started nothing so,
            everything it did being in ``fx``.
        """
        if gen != node.gen:
            return None  # a run the engine already gave up on (stop timeout)
        if instance is not None:  # adopt(), inlined
            if node.instance is None:
                node.instance = instance
            if node.logged:  # (a log is kept only once logged: adopt's `node.log or`, implied)
                node.log = instance.log_snapshot()
        run = node.run
        if (
            node.state is _N_RUNNING
            and run.state is _G_RUNNING
            and error is None
            and not self.observed
        ):
            # The commonest end (a run that returned, nothing observing): set_state's path
            # for RUNNING -> FINISHED, inlined (legal by the table: FAST_CHANGES). A RUNNING
            # node has no stop timer and no restart pending: both are STOPPING's, which the
            # table lets go to FINISHED or ERROR only, through _end_other or _stop_expired.
            # No data (no input) is the common case: two len() calls fewer.
            data = node.data
            if data and len(data) != len(node.native):
                node.clear_data()
            node.state = _N_FINISHED
            run.active -= 1
            if self._quiet_waiters:
                self._quiet.notify_all()
        else:
            passed = self._end_other(node, run, result, outputs, error, fx)
            if passed is None:
                return None
            result = passed
        # The result goes to the children (docs/design.md §4.3): the evolution kernel computes
        # the wave (responses, received parents, bypass chains), _apply_wave carries out
        # its steps. A wave of one `run` step (a chain's link, a fan-in's edge) is asked
        # for first (`advance`, which makes no list) and carried out here.
        evolution = run.evolution
        code = _RESULT_CODES[result]
        step = evolution.advance(node.idx, code)
        if step < 0:
            self._apply_wave(node, result, outputs, evolution.propagate(node.idx, code), fx)
        elif not step & 1:  # a fan-in: the child waits for other parents
            if outputs:  # advance's edge is this node's own relation
                edge = step >> 1
                _transfer(node, run.edge_child[edge], run.edge_remap[edge], outputs)
        else:
            edge = step >> 1
            child = run.edge_child[edge]
            if outputs:
                _transfer(node, child, run.edge_remap[edge], outputs)
            if (
                child.kind is _K_LOCAL
                and child.state not in _ACTIVE
                and (not child.required_inputs or child.inputs_ready())
            ):
                if self.observed:
                    self._ready_local(child)
                    return child
                # _ready_local, inlined for the chain's link (nothing observes)
                child.gen += 1
                child.held = None
                if child.condition is None:  # RunControl.reset, nobody waits to race with
                    child.stop = child.paused = False
                else:
                    child.reset()
                if child.fresh_instance:
                    child.instance = None
                    child.fresh_instance = False
                child.state = _N_RUNNING  # legal: FAST_CHANGES
                run.active += 1
                return child  # RUNNING: run.active is not 0
            else:
                self._apply_wave(node, result, NO_VALUES, [edge << SHIFT | _RUN_READY], fx)
        if not run.active:
            self.after_change(run, fx)
        return None

    def _end_other(
        self,
        node: Node,
        run: GraphRun,
        result: Result,
        outputs: dict[str, Any],
        error: BaseException | None,
        fx: Effects,
    ) -> Result | None:
        """Lock held: :meth:`finished_next` for every end but the commonest, up to its wave.

        Returns:
            The result the children receive (a stopped node's is STOPPED), or None when the
            end goes no further: held while paused, a restart, or a run no longer RUNNING.
        """
        state = node.state
        if state is not _N_RUNNING:
            if state is _N_PAUSE_REQUESTED or state is _N_PAUSED:
                node.held = (result, outputs, error)  # delivered on resume
                return None
            if state is _N_STOPPING:
                result = _R_STOPPED
        if node.stop_timer is not None:
            node.stop_timer.cancel()
            node.stop_timer = None
        if len(node.data) != len(node.native):
            node.clear_data()
        if node.restart:
            node.restart = False
            self.set_state(node, _N_FINISHED)
            if run.state is _G_RUNNING or run.state in _PAUSED_GRAPH:
                self.run_node(node, fx)
            self.after_change(run, fx)
            return None
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
        self.set_state(node, _N_ERROR if result is _R_ERROR else _N_FINISHED)
        if run.state is not _G_RUNNING:  # (the common end is in a RUNNING run)
            if not run.active:
                self.after_change(run, fx)
            return None
        return result

    def _apply_wave(
        self,
        node: Node,
        result: Result,
        outputs: Mapping[str, Any],
        steps: list[int],
        fx: Effects,
    ) -> None:
        """Carry out the steps of the wave the kernel computed for ``node``'s result."""
        run = node.run
        edge_child = run.edge_child
        for step in steps:
            edge = step >> SHIFT
            child = edge_child[edge]
            code = (step >> 1) & 7
            if code == P_IGNORE:
                continue
            if code == P_BYPASS:
                if child.kind is _K_EXIT:
                    self.finish_run(run, result, fx)
                    return
                if not child.active:
                    self.set_state(child, _N_BYPASSED)
                continue
            if code == P_LOOP:
                logger.warning(
                    "%s: bypass loops back to %s; stopping it there", run.name, child.name
                )
                continue
            if outputs and run.edge_parent[edge] is node:
                _transfer(node, child, run.edge_remap[edge], outputs)
            if not step & 1 or (child.required_inputs and not child.inputs_ready()):
                continue
            kind = child.kind
            if kind is _K_LOCAL and code == P_RUN and child.state not in _ACTIVE:
                # run_node's path for an idle local node: _ready_local, inlined when nothing
                # observes (a fan-out's start makes every branch ready here)
                if self.observed:
                    self._ready_local(child)
                else:
                    child.gen += 1
                    child.held = None
                    if child.condition is None:  # RunControl.reset, nobody waits to race with
                        child.stop = child.paused = False
                    else:
                        child.reset()
                    if child.fresh_instance:
                        child.instance = None
                        child.fresh_instance = False
                    child.state = _N_RUNNING  # legal: FAST_CHANGES
                    run.active += 1
                fx.runs.append((child, child.gen))
                continue
            if kind is _K_EXIT:
                self.finish_run(run, result, fx)
                return
            if code == P_RUN:
                self.run_node(child, fx)
            elif code == P_STOP:
                self.stop_node(child, fx)
            elif code == P_PAUSE:
                self._pause_node(child, fx)
            else:
                self._restart_node(child, fx)
            if run.state is not _G_RUNNING:
                return

    # ------------------------------------------------------------ nodes

    def _ready_local(self, node: Node) -> None:
        """Make an idle local node RUNNING: the one path that makes a run of an action ready."""
        node.gen += 1
        node.held = None
        if node.condition is None:  # RunControl.reset, nobody waits to race with
            node.stop = node.paused = False
        else:
            node.reset()  # the node is its action's RunControl
        if node.fresh_instance:
            node.instance = None  # the old one is stuck in a run we gave up on
            node.fresh_instance = False
        if self.observed:
            self.set_state(node, _N_RUNNING)
        else:  # set_state's path for an idle node, nothing observing (legal: FAST_CHANGES)
            node.state = _N_RUNNING
            node.run.active += 1

    def run_node(self, node: Node, fx: Effects) -> None:
        """Lock held: run a node (a paused one resumes; an active one is left as it is)."""
        if node.state in (_N_PAUSE_REQUESTED, _N_PAUSED) and node.run.state is _G_RUNNING:
            self._resume_node(node, fx)  # paused by a `pause` response: `run` resumes it
            return
        if node.state in _ACTIVE or node.kind in (_K_ENTRY, _K_EXIT):
            return
        if node.kind is _K_LOCAL:
            self._ready_local(node)
            fx.runs.append((node, node.gen))
            return
        run = node.run
        node.gen += 1
        node.held = None
        if node.kind is _K_REMOTE:
            self.set_state(node, _N_RUNNING)
            assert self.shared is not None
            fx.other.append(Effect(_E_CALL, call=self.shared.expect, args=(node, node.gen)))
            return
        assert node.plan is not None
        self.set_state(node, _N_RUNNING)
        child = GraphRun(
            f"{run.name}__{node.umrf.name}__{node.umrf.instance_id}",
            node.plan,
            parent_node=node,
            clock=self.clock,
        )
        node.child_run = child
        old = self.runs.get(child.name)
        if old is not None and old.state in _BUSY_GRAPH:
            logger.warning(
                "%s: replacing sub-graph run %s that was still %s",
                run.name,
                child.name,
                old.state.value,
            )
        self.runs[child.name] = child
        values = {k: v for k, v in node.data.items() if k in child.entry.inputs}
        node.clear_data()
        self.start_run(child, values, _R_TRUE, fx)

    def rerun(self, node: Node, fx: Effects) -> None:
        """Lock held: run a node again in its running run (a spontaneous action's next run)."""
        self.run_node(node, fx)
        self.after_change(node.run, fx)

    def stop_node(self, node: Node, fx: Effects) -> None:
        """Lock held: stop an active node (cooperative, with the ``stop_timeout`` deadline)."""
        if node.state not in (_N_RUNNING, _N_PAUSE_REQUESTED, _N_PAUSED):
            return
        self.set_state(node, _N_STOPPING)
        if node.kind is _K_GRAPH:
            if node.child_run is not None:
                self.stop_run(node.child_run, fx)
            return
        if node.kind is _K_REMOTE:  # nothing runs here: stop waiting for its actor
            if node.remote_cancel is not None:
                fx.other.append(Effect(_E_CALL, call=node.remote_cancel))
                node.remote_cancel = None
            self.action_finished(node, node.gen, _R_STOPPED, {}, None, fx)
            return
        node.request_stop()
        fx.other.append(Effect(_E_HOOK, node, node.gen, "on_stop"))
        node.stop_timer = self.call_later(
            self.clock.real_seconds(self.stop_timeout), self._stop_expired, node, node.gen
        )
        if node.held is not None:  # it had already finished while paused
            result, outputs, error = node.held
            node.held = None
            self.action_finished(node, node.gen, result, outputs, error, fx)

    def call_later(self, seconds: float, fn: Callable[..., Any], *args: Any) -> TimerHandle:
        """Call ``fn(*args)`` on the engine's timer thread after ``seconds`` (real time).

        Raises:
            RuntimeError: The timer is shut down.
        """
        return self.timer.call_later(seconds, fn, *args)

    def _stop_expired(self, node: Node, gen: int) -> None:
        """Timer thread: an action ignored its stop for ``stop_timeout``; its node is ERROR."""
        fx = Effects()
        with self.lock:
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
            self.set_state(node, _N_ERROR)
            if node.restart:
                node.restart = False
                if run.state is _G_RUNNING:
                    self.run_node(node, fx)
            self.after_change(run, fx)
        self.carry_out(fx)

    def _pause_node(self, node: Node, fx: Effects) -> None:
        if node.state is not _N_RUNNING:
            return
        if node.kind is _K_GRAPH:  # paused once its sub-graph has (_pause_done)
            self.set_state(node, _N_PAUSE_REQUESTED)
            if node.child_run is not None and node.child_run.state is _G_RUNNING:
                self.pause_run(node.child_run, fx)
            elif node.state is _N_PAUSE_REQUESTED:
                self.set_state(node, _N_PAUSED)
            return
        if node.kind is _K_REMOTE:  # its actor goes on; a result is held until resume
            self.set_state(node, _N_PAUSE_REQUESTED)
            self.set_state(node, _N_PAUSED)
            return
        self.set_state(node, _N_PAUSE_REQUESTED)
        node.set_paused(True)
        fx.other.append(Effect(_E_HOOK, node, node.gen, "on_pause"))

    def node_paused(self, node: Node, gen: int) -> None:
        """Lock held: a node's ``on_pause`` returned: the node is PAUSED (if still pausing)."""
        if node.gen == gen and node.state is _N_PAUSE_REQUESTED:
            self.set_state(node, _N_PAUSED)

    def _resume_node(self, node: Node, fx: Effects) -> None:
        if node.state not in (_N_PAUSE_REQUESTED, _N_PAUSED):
            return
        self.set_state(node, _N_RUNNING)
        if node.kind is _K_GRAPH:
            if node.child_run is not None and node.child_run.state in _PAUSED_GRAPH:
                self.resume_run(node.child_run, None, fx)
            return
        if node.kind is _K_REMOTE:
            if node.held is not None:
                result, outputs, error = node.held
                node.held = None
                self.action_finished(node, node.gen, result, outputs, error, fx)
            return
        node.set_paused(False)
        fx.other.append(Effect(_E_HOOK, node, node.gen, "on_resume"))
        if node.held is not None:
            result, outputs, error = node.held
            node.held = None
            if node.spontaneous:
                fx.other.append(
                    Effect(_E_FINISH_SPONTANEOUS, node, node.gen, ending=(result, outputs, error))
                )
            else:
                self.action_finished(node, node.gen, result, outputs, error, fx)

    def _restart_node(self, node: Node, fx: Effects) -> None:
        if node.active:
            node.restart = True
            self.stop_node(node, fx)
        else:
            self.run_node(node, fx)


def watches_transitions(instrument: Instrument) -> bool:
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


def _no_port(fx: Effects) -> None:
    """:attr:`RunEvolution.carry_out` before the engine connects its dispatcher."""
    raise RuntimeError(f"the evolution has no dispatcher to carry out {fx!r}")


def _transfer(
    parent: Node, child: Node, remap: Mapping[str, str], outputs: Mapping[str, Any]
) -> None:
    """Copy a parent's outputs into a child's inputs (parameter transfer, docs/design.md §4.4)."""
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


def _ready(node: Node) -> bool:
    """Whether a node's required parents were received and its required inputs are set."""
    return node.run.evolution.missing_parents(node.idx) == 0 and node.inputs_ready()
