"""The evolution of graph runs: how nodes and runs change state, with the engine's lock held.

One layer of the engine (see :mod:`temoto.core.engine`): :class:`RunEvolution` holds every
state change of a run and of its nodes. A run starts (the entry's result reaches its first
actions), an action run finishes (its result is applied: held while paused, turned into a stop
or a restart, or recorded), the result propagates to the children along the condition table
(the evolution kernel, :mod:`temoto.core._fast`, computes the wave), parameters are transferred
along the relations, ready children start, and the run ends (finished, halted, stopped or
failed) and hands its result to a parent node when it is a sub-graph.

Everything here is plain computation under the engine's lock: it never waits and never calls
user code. What must happen outside the lock (run an action, call a hook, release resources,
talk to the actor link) goes into the :class:`~temoto.core.effects.Effects` ``fx`` for the
dispatcher (:mod:`temoto.core.dispatch`).
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

from temoto.core._fast import P_BYPASS, P_IGNORE, P_LOOP, P_PAUSE, P_RUN, P_STOP, SHIFT
from temoto.core._runtime import RESULT_CODES as _RESULT_CODES
from temoto.core._runtime import GraphRun, Node, NodeKind
from temoto.core.effects import Effect, EffectKind, Effects
from temoto.core.snapshot import snapshot
from temoto.core.states import (
    ACTIVE_NODE_STATES,
    BUSY_GRAPH_STATES,
    ENDED_GRAPH_STATES,
    GraphState,
    NodeState,
    Result,
    check_node_transition,
)
from temoto.errors import ActionError

if TYPE_CHECKING:
    from temoto.clock import Clock
    from temoto.core.executor import DeadlineTimer
    from temoto.core.instrument import Instrument
    from temoto.core.shared import SharedRuns

__all__ = ["RunEvolution"]

logger = logging.getLogger("temoto.core.engine")  # the engine's log lines keep their logger

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


class RunEvolution:
    """The engine's state changes of runs and nodes (engine lock held), as effects.

    A layer of :class:`~temoto.core.engine.ActionEngine`, which makes the state below in its
    ``__init__``; the dispatcher (:class:`~temoto.core.dispatch.EffectDispatcher`) subclasses
    this and carries out the effects.
    """

    # made by ActionEngine.__init__
    actor: str
    clock: Clock
    stop_timeout: float
    _lock: threading.Lock
    _quiet: threading.Condition
    _quiet_waiters: int
    _runs: dict[str, GraphRun]
    _timer: DeadlineTimer
    _instruments: list[Instrument]
    _watchers: list[Instrument]
    _feedback: deque[dict[str, Any]]
    _feedback_on: bool
    _shared: SharedRuns | None
    _closed: bool
    #: releases found under the lock, handed to workers by the next dispatch
    _releases: list[Effect]
    #: the timer's callback when an action ignores its stop (the dispatcher's)
    _stop_expired: Callable[[Node, int], None]

    def _set_state(self, node: Node, new: NodeState) -> None:
        old = node.state
        check_node_transition(node.run.name, node.name, old, new)
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
            self._feedback.append(snapshot(node.run))

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
        self, run: GraphRun, values: dict[str, Any], result: Result, fx: Effects
    ) -> None:
        run.state = _G_RUNNING
        run.started_at = self.clock.monotonic()
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
        fx: Effects,
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
        self, node: Node, result: Result, outputs: Mapping[str, Any], fx: Effects
    ) -> None:
        """Deliver a finished node's result and outputs to its children (REFERENCE §2.5).

        The evolution kernel computes the wave (responses, received parents, bypass chains);
        this carries out its steps: parameter transfer, input readiness, state changes.
        """
        self._apply_wave(
            node, result, outputs, node.run.evolution.propagate(node.idx, _RESULT_CODES[result]), fx
        )

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
        fast = not self._watchers and not self._feedback_on
        for step in steps:
            edge = step >> SHIFT
            child = edge_child[edge]
            code = (step >> 1) & 7
            if code == P_IGNORE:
                continue
            if code == P_BYPASS:
                if child.kind is _K_EXIT:
                    self._finish_run(run, result, fx)
                    return
                if not child.active:
                    self._set_state(child, _N_BYPASSED)
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
            if kind is _K_LOCAL and code == P_RUN and fast and child.state not in _ACTIVE:
                # _run_node's path for an idle local node, without observers to tell: every
                # idle state may go to RUNNING (NODE_TRANSITIONS)
                child.gen += 1
                child.held = None
                if child.condition is None:  # RunControl.reset, nobody waits to race with
                    child.stop = child.paused = False
                else:
                    child.reset()
                if child.fresh_instance:
                    child.instance = None  # the old one is stuck in a run we gave up on
                    child.fresh_instance = False
                child.state = _N_RUNNING
                run.active += 1
                fx.runs.append((child, child.gen))
                continue
            if kind is _K_EXIT:
                self._finish_run(run, result, fx)
                return
            if code == P_RUN:
                self._run_node(child, fx)
            elif code == P_STOP:
                self._stop_node(child, fx)
            elif code == P_PAUSE:
                self._pause_node(child, fx)
            else:
                self._restart_node(child, fx)
            if run.state is not _G_RUNNING:
                return

    def _run_node(self, node: Node, fx: Effects) -> None:
        if node.state in (_N_PAUSE_REQUESTED, _N_PAUSED) and node.run.state is _G_RUNNING:
            self._resume_node(node, fx)  # paused by a `pause` response: `run` resumes it
            return
        if node.state in _ACTIVE or node.kind in (_K_ENTRY, _K_EXIT):
            return
        run = node.run
        node.gen += 1
        node.held = None
        if node.kind is _K_LOCAL:
            node.reset()  # the node is its action's RunControl
            if node.fresh_instance:
                node.instance = None  # the old one is stuck in a run we gave up on
                node.fresh_instance = False
            self._set_state(node, _N_RUNNING)
            fx.runs.append((node, node.gen))
            return
        if node.kind is _K_REMOTE:
            self._set_state(node, _N_RUNNING)
            assert self._shared is not None
            fx.other.append(Effect(_E_CALL, call=self._shared.expect, args=(node, node.gen)))
            return
        assert node.plan is not None
        self._set_state(node, _N_RUNNING)
        child = GraphRun(
            f"{run.name}__{node.umrf.name}__{node.umrf.instance_id}",
            node.plan,
            parent_node=node,
            clock=self.clock,
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

    def _stop_node(self, node: Node, fx: Effects) -> None:
        if node.state not in (_N_RUNNING, _N_PAUSE_REQUESTED, _N_PAUSED):
            return
        self._set_state(node, _N_STOPPING)
        if node.kind is _K_GRAPH:
            if node.child_run is not None:
                self._stop_run(node.child_run, fx)
            return
        if node.kind is _K_REMOTE:  # nothing runs here: stop waiting for its actor
            if node.remote_cancel is not None:
                fx.other.append(Effect(_E_CALL, call=node.remote_cancel))
                node.remote_cancel = None
            self._on_finished(node, node.gen, _R_STOPPED, {}, None, fx)
            return
        node.request_stop()
        fx.other.append(Effect(_E_HOOK, node, node.gen, "on_stop"))
        node.stop_timer = self._timer.call_later(
            self.clock.real_seconds(self.stop_timeout), self._stop_expired, node, node.gen
        )
        if node.held is not None:  # it had already finished while paused
            result, outputs, error = node.held
            node.held = None
            self._on_finished(node, node.gen, result, outputs, error, fx)

    def _pause_node(self, node: Node, fx: Effects) -> None:
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
        self._set_state(node, _N_PAUSE_REQUESTED)
        node.set_paused(True)
        fx.other.append(Effect(_E_HOOK, node, node.gen, "on_pause"))

    def _resume_node(self, node: Node, fx: Effects) -> None:
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
                self._on_finished(node, node.gen, result, outputs, error, fx)

    def _restart_node(self, node: Node, fx: Effects) -> None:
        if node.active:
            node.restart = True
            self._stop_node(node, fx)
        else:
            self._run_node(node, fx)

    def _pause_run(self, run: GraphRun, fx: Effects) -> None:
        run.state = _G_PAUSED
        for node in list(run.nodes.values()):
            self._pause_node(node, fx)

    def _resume_run(self, run: GraphRun, continue_from: str | None, fx: Effects) -> None:
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

    def _stop_run(self, run: GraphRun, fx: Effects) -> None:
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

    def _after_change(self, run: GraphRun, fx: Effects) -> None:
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

    def _finish_run(self, run: GraphRun, result: Result, fx: Effects) -> None:
        run.outputs = dict(run.exit.data)
        self._end_run(run, _G_FINISHED, result, fx)
        # Actions still running are no longer needed: stop them (their results are ignored).
        for node in list(run.nodes.values()) if run.active else ():
            if node.state in _ACTIVE:
                self._stop_node(node, fx)

    def _release_node(self, node: Node) -> None:
        """Release the resources a node's action holds (it is idle and its run has ended)."""
        instance = node.instance
        if instance is not None and instance.holds_resources:
            self._releases.append(Effect(_E_RELEASE, action=instance))

    def _end_run(self, run: GraphRun, state: GraphState, result: Result, fx: Effects) -> None:
        run.state = state
        run.result = result
        if run.peers:
            assert self._shared is not None
            fx.other.append(Effect(_E_CALL, call=self._shared.end, args=(run,)))
        releases = self._releases
        for node in run.nodes.values():  # _release_node for each idle one, inlined (all nodes)
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
            self._on_finished(parent, parent.gen, result, outputs, error, fx)


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


def _ready(node: Node) -> bool:
    """Whether a node's required parents were received and its required inputs are set."""
    return node.run.evolution.missing_parents(node.idx) == 0 and node.inputs_ready()
