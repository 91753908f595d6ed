"""Dispatch: carrying out the engine's effects, and the workers that run actions.

One part of the engine (see :mod:`temoto.core.engine`): :class:`Dispatcher` owns the workers;
it takes the effects the evolution (:class:`~temoto.core.evolution.RunEvolution`) produced under
the lock and carries them out with the lock released. Ready actions go to the
:class:`~temoto.core.executor.WorkerPool` as one batch; a worker runs an action
(:meth:`Action.run_once <temoto.core.action.Action.run_once>`), takes the lock once to apply
the results of its round (:meth:`RunEvolution.finished_next
<temoto.core.evolution.RunEvolution.finished_next>`, the one path of an action's end), and goes
on itself with what became ready: every inline action, or else the first blocking one, so a
chain continues on one thread without a hand-off. Hooks (``on_stop``, ``on_pause``,
``on_resume``), resource releases and the end of spontaneous actions run on workers too; calls
to the actor link are made in the dispatching thread.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any

from temoto.core._runtime import Node, NodeKind
from temoto.core.action import Action
from temoto.core.effects import Effect, EffectKind, Effects, Run
from temoto.core.evolution import RunEvolution
from temoto.core.executor import WorkerPool
from temoto.core.registrar.registry import Registrar
from temoto.core.states import ACTIVE_NODE_STATES, GraphState, NodeState, Result
from temoto.core.values import NO_VALUES
from temoto.errors import ActionError

if TYPE_CHECKING:
    from temoto.core.shared import SharedRuns

__all__ = ["Dispatcher"]

logger = logging.getLogger(__name__)

_N_ERROR = NodeState.ERROR
_N_FINISHED = NodeState.FINISHED
_N_PAUSE_REQUESTED = NodeState.PAUSE_REQUESTED
_N_PAUSED = NodeState.PAUSED
_N_RUNNING = NodeState.RUNNING
_N_STOPPING = NodeState.STOPPING
_G_ERROR = GraphState.ERROR
_G_PAUSED = GraphState.PAUSED
_G_PAUSE_REQUESTED = GraphState.PAUSE_REQUESTED
_G_RUNNING = GraphState.RUNNING
_G_STOPPING = GraphState.STOPPING
_R_ERROR = Result.ERROR
_R_STOPPED = Result.STOPPED
_K_EXIT = NodeKind.EXIT
_K_LOCAL = NodeKind.LOCAL
_E_HOOK = EffectKind.HOOK
_E_FINISH_SPONTANEOUS = EffectKind.FINISH_SPONTANEOUS
_E_RELEASE = EffectKind.RELEASE
_E_CALL = EffectKind.CALL
_ACTIVE = ACTIVE_NODE_STATES

# a run prepared under the lock: (node, gen, its instance or None, input values)
_Todo = tuple[Node, int, Action | None, dict[str, Any]]
# a run's end, applied under the lock: (node, gen, instance, result, outputs, error)
_Done = tuple[Node, int, Action | None, Result, dict[str, Any], BaseException | None]


class Dispatcher:
    """Carries out effects (lock released) and runs actions on the engine's workers.

    A part of :class:`~temoto.core.engine.ActionEngine`. Every state change it makes goes
    through the evolution (:class:`~temoto.core.evolution.RunEvolution`), under its lock.

    Args:
        evolution: The engine's evolution (its lock, its runs, its state changes).
        pool: The workers.
        actor: The engine's actor (its actions of a shared run notify the others).
        registrar: Where actions acquire resources.
    """

    def __init__(
        self,
        evolution: RunEvolution,
        pool: WorkerPool,
        actor: str,
        registrar: Registrar | None,
    ) -> None:
        self._evolution = evolution
        self._lock = evolution.lock
        self.pool = pool
        self.actor = actor
        self.registrar = registrar
        #: the shared-run protocol, with an actor link only (set by the engine)
        self.shared: SharedRuns | None = None
        #: the engine is shut down (set under the lock): effects are carried out in the
        #: calling thread, not refused
        self.closed = False

    def carry_out(self, fx: Effects) -> None:
        """Carry out effects from any thread, the lock released (the evolution's port)."""
        self.dispatch(fx, closing=self.closed)

    def dispatch(self, fx: Effects, *, closing: bool = False) -> None:
        """Carry out effects (lock released): calls here, actions and hooks on workers.

        Ready actions leave as one batch: the inline ones together as one worker job that runs
        them back to back (:meth:`_run_batch`), each blocking one as a job of its own, all
        handed to the pool under one lock of its own (:meth:`WorkerPool.submit_many`).

        Args:
            fx: The effects.
            closing: The engine is shutting down: what the pool refuses is carried out here.

        Raises:
            RuntimeError: The pool is shut down and the engine is not closing.
        """
        other = fx.other
        evolution = self._evolution
        if evolution.releases:
            with self._lock:
                other = [*other, *evolution.take_releases()]
        for effect in other:
            if effect.kind is _E_CALL:
                try:
                    assert effect.call is not None
                    effect.call(*effect.args)
                except Exception:
                    logger.exception("call to the actor link failed: %r", effect.call)
                continue
            try:
                self._submit(effect)
            except RuntimeError:
                if not (closing or self.closed):  # shut down since the caller looked
                    raise
                self._settle_closed(effect)
        if not fx.runs:
            return
        inline: list[Run] = []
        jobs: list[tuple[Any, ...]] = []
        for run in fx.runs:
            if run[0].inline:
                inline.append(run)
            else:
                jobs.append(([run],))
        if inline:
            jobs.insert(0, (inline,))
        try:
            self.pool.submit_many(self._run_batch, jobs)
        except RuntimeError:
            if not (closing or self.closed):
                raise
            for node, gen in fx.runs:
                self._settle_closed_run(node, gen)

    def _submit(self, effect: Effect) -> None:
        """Hand a HOOK, RELEASE or FINISH_SPONTANEOUS effect to a worker (RuntimeError: shut)."""
        kind = effect.kind
        if kind is _E_RELEASE:
            assert effect.action is not None
            self.pool.submit(_release_resources, effect.action)
            return
        node = effect.node
        assert node is not None
        if kind is _E_HOOK:
            self.pool.submit(self._call_hook, node, effect.gen, effect.hook)
        elif kind is _E_FINISH_SPONTANEOUS:
            assert effect.ending is not None
            self.pool.submit(self._finish_spontaneous, node, effect.gen, *effect.ending)
        else:
            raise ValueError(f"not an effect for a worker: {kind}")

    def _settle_closed(self, effect: Effect) -> None:
        """The pool is shut down: carry out an effect in this thread."""
        kind = effect.kind
        node = effect.node
        if kind is _E_RELEASE:
            assert effect.action is not None
            _release_resources(effect.action)
            return
        assert node is not None
        if kind is _E_HOOK:
            self._call_hook(node, effect.gen, effect.hook)
        elif kind is _E_FINISH_SPONTANEOUS:
            assert effect.ending is not None
            self._finish_spontaneous(node, effect.gen, *effect.ending)

    def _settle_closed_run(self, node: Node, gen: int) -> None:
        """The pool is shut down: a run that cannot start ends STOPPED, so no node stays active."""
        fx = Effects()
        with self._lock:
            if node.gen == gen and node.active:
                self._evolution.action_finished(node, gen, _R_STOPPED, {}, None, fx)

    def _run_batch(self, batch: list[tuple[Node, int]]) -> None:
        """Worker: run a batch (:meth:`_run_rounds`); an error of the engine ends its runs.

        An action's own errors never get here (they are the node's result); what does is a
        fault of the engine itself (a bug, a ``RecursionError``, ``MemoryError``): the top-level
        run of every node of the batch ends ``on_error`` with the reason (:meth:`_job_failed`),
        rather than the pool logging it and the run never ending.
        """
        try:
            self._run_rounds(batch)
        except Exception as err:
            self._job_failed(batch, err)

    def _job_failed(self, batch: list[tuple[Node, int]], err: Exception) -> None:
        """End ``on_error`` the top-level runs of a batch whose worker job raised ``err``."""
        logger.error("engine error in a worker job: %s: %s", type(err).__name__, err, exc_info=err)
        fx = Effects()
        with self._lock:
            ended: set[int] = set()
            for node, _gen in batch:
                run = node.run
                while run.parent_node is not None:
                    run = run.parent_node.run
                if id(run) in ended or run.state not in (
                    _G_RUNNING,
                    _G_PAUSE_REQUESTED,
                    _G_PAUSED,
                    _G_STOPPING,
                ):
                    continue
                ended.add(id(run))
                reason = ActionError(
                    f"engine error while running {node.name}: {type(err).__name__}: {err}",
                    graph=run.name,
                    node=node.name,
                )
                self._evolution.fail_run(run, reason, fx)
        try:
            self.dispatch(fx, closing=True)
        except Exception:
            logger.exception("engine error: cannot carry out the end of the failed runs")

    def _run_rounds(self, batch: list[tuple[Node, int]]) -> None:
        """Worker: run actions, evolve, and go on with what became ready, batch by batch.

        Each round runs the prepared actions back to back outside the lock, then takes the
        lock once to apply every result (:meth:`_settle`) and to prepare the next round: the
        inline actions that became ready, or, when none did, the first ready blocking action
        (a chain continues on this thread without a hand-off: :meth:`_run_chain`). Further
        blocking actions go to other workers. One lock per round, not per action.
        """
        lock = self._lock
        evolution = self._evolution
        finished = evolution.finished_next
        settle = self._settle
        todo: list[_Todo] = []
        # what evolution decides; after _collect, what this thread leaves to others
        fx = Effects()
        runs, other = fx.runs, fx.other  # emptied in place each round
        # the round's lists are reused: fewer objects for the collector per action
        done: list[_Done] = []
        with lock:
            for node, gen in batch:
                if gen == node.gen and node.state is _N_RUNNING:  # _prep's common case
                    data = node.data
                    todo.append((node, gen, node.instance, dict(data) if data else NO_VALUES))
                else:
                    self._prep(node, gen, todo, fx)
            self._collect(fx, todo)
        running = _N_RUNNING
        while True:
            if runs or other or evolution.releases:  # an ended run's releases may be all
                self.dispatch(fx, closing=self.closed)
                runs.clear()
                other.clear()
            if not todo:
                return
            if len(todo) == 1 and not todo[0][0].run.peers:  # a chain: one action at a time
                self._run_chain(*todo.pop(), fx, todo)
                continue
            done.clear()
            for node, gen, instance, values in todo:  # the actions, outside the lock
                if node.run.peers:
                    done.append(self._call(node, gen, instance, values))
                    continue
                if instance is None:
                    try:
                        instance = self._instantiate(node, gen)
                    except Exception as err:
                        done.append((node, gen, None, _R_ERROR, NO_VALUES, _init_error(node, err)))
                        continue
                result, outputs, error = instance.run_once(values)
                done.append((node, gen, instance, result, outputs, error))
            todo.clear()
            with lock:
                for node, gen, instance, result, outputs, error in done:
                    if node.spontaneous:
                        settle(node, gen, instance, result, outputs, error, fx)
                        continue
                    child = finished(node, gen, result, outputs, error, fx, instance)
                    if child is not None:  # the child it started, for this round to queue
                        runs.append((child, child.gen))
                if len(runs) == 1 and not other:  # a chain: _collect's common case
                    node, gen = runs[0]
                    if node.inline and gen == node.gen and node.state is running:
                        data = node.data
                        todo.append((node, gen, node.instance, dict(data) if data else NO_VALUES))
                        runs.clear()
                        continue
                self._collect(fx, todo)

    def _run_chain(
        self,
        node: Node,
        gen: int,
        instance: Action | None,
        values: dict[str, Any],
        fx: Effects,
        todo: list[_Todo],
    ) -> None:
        """Worker: :meth:`_run_rounds`'s rounds of one action each, for as long as they last.

        A chain is a round per action: the action, then the lock once to apply its result
        (:meth:`_settle`) and to start the one child it made ready, which runs next on this
        thread (inline or blocking: :meth:`_collect` keeps the first blocking run for this
        thread too), without the round's lists and records. Returns (lock released) as soon
        as a round is anything else, leaving ``fx`` and ``todo`` as :meth:`_run_rounds`'s
        round would have (``fx`` holds no effect on entry).
        """
        lock = self._lock
        acquire, release = lock.acquire, lock.release
        evolution = self._evolution
        finished = evolution.finished_next
        settle = self._settle
        runs, other = fx.runs, fx.other
        running = _N_RUNNING
        while True:
            if instance is None:
                try:
                    instance = self._instantiate(node, gen)
                except Exception as err:
                    with lock:
                        settle(node, gen, None, _R_ERROR, NO_VALUES, _init_error(node, err), fx)
                        self._collect(fx, todo)
                    return
            result, outputs, error = instance.run_once(values)
            acquire()  # not `with lock`: its __enter__ and __exit__ cost as much again
            try:
                if node.spontaneous:
                    settle(node, gen, instance, result, outputs, error, fx)
                    child = None
                else:
                    child = finished(node, gen, result, outputs, error, fx, instance)
                if child is not None:
                    # the next link of the chain, started by this result (same run): it runs
                    # here, unless there are releases to carry out first (``fx`` held no effect
                    # on entry, and an end that returns a child adds none: finished_next)
                    if not evolution.releases:
                        data = child.data
                        node, gen, instance = child, child.gen, child.instance
                        values = dict(data) if data else NO_VALUES
                        continue
                    runs.append((child, child.gen))
                elif len(runs) == 1 and not other and not evolution.releases:
                    # the next link made ready through the general path: it runs here too
                    child, child_gen = runs[0]
                    if (
                        child_gen == child.gen
                        and child.state is running
                        and not child.run.peers  # (a sub-graph's end may reach a shared run)
                    ):
                        runs.clear()
                        data = child.data
                        node, gen, instance = child, child_gen, child.instance
                        values = dict(data) if data else NO_VALUES
                        continue
                self._collect(fx, todo)
                return
            finally:
                release()

    def _prep(self, node: Node, gen: int, todo: list[_Todo], fx: Effects) -> None:
        """Lock held: queue a ready node's run with what it reads, unless it is stale."""
        if gen != node.gen or node.state not in _ACTIVE:
            return
        if node.state is _N_STOPPING:  # stopped before a worker got to it: do not start
            self._evolution.action_finished(node, gen, _R_STOPPED, {}, None, fx)
            return
        todo.append((node, gen, node.instance, dict(node.data) if node.data else NO_VALUES))

    def _collect(self, fx: Effects, todo: list[_Todo]) -> None:
        """Lock held: take the runs this thread goes on with (``todo``); ``fx`` keeps the rest.

        Inline runs are prepared here (a stale or stopped one may add effects, which are
        collected too); the first blocking run is kept only when no inline run is. What is left
        in ``fx`` (other blocking runs, every other effect) is for :meth:`dispatch`.
        """
        runs = fx.runs
        blocking: list[Run] = []
        i = 0
        while True:
            while i < len(runs):
                run = runs[i]
                node, gen = run
                i += 1
                if not node.inline:
                    blocking.append(run)
                elif gen == node.gen and node.state is _N_RUNNING:  # _prep's common case
                    data = node.data
                    todo.append((node, gen, node.instance, dict(data) if data else NO_VALUES))
                else:
                    self._prep(node, gen, todo, fx)
            if todo or not blocking:
                break
            first, first_gen = blocking.pop(0)
            self._prep(first, first_gen, todo, fx)
        runs[:] = blocking

    def _call(self, node: Node, gen: int, instance: Action | None, values: dict[str, Any]) -> _Done:
        """No lock: one run of an action of a shared run (its instance made first if need be).

        An action of this actor tells the other actors how it ended
        (:meth:`SharedRuns.notify <temoto.core.shared.SharedRuns.notify>`).
        """
        if instance is None:
            try:
                instance = self._instantiate(node, gen)
            except Exception as err:
                return node, gen, None, _R_ERROR, NO_VALUES, _init_error(node, err)
        result, outputs, error = instance.run_once(values)
        if node.run.peers and result is not _R_STOPPED and node.umrf.actor == self.actor:
            assert self.shared is not None
            result, error = self.shared.notify(node, result, outputs, error)
        return node, gen, instance, result, outputs, error

    def _settle(
        self,
        node: Node,
        gen: int,
        instance: Action | None,
        result: Result,
        outputs: dict[str, Any],
        error: BaseException | None,
        fx: Effects,
    ) -> None:
        """Lock held: apply the end of an action run that may be a spontaneous action's.

        A spontaneous action's end is carried out on a worker (what runs downstream of it
        stops first: :meth:`_finish_spontaneous`); every other end is the evolution's one path,
        :meth:`RunEvolution.action_finished <temoto.core.evolution.RunEvolution.action_finished>`,
        which the workers' rounds call directly for an action that is not spontaneous.
        """
        if (
            node.spontaneous
            and gen == node.gen
            and node.run.state is not _G_PAUSED
            and node.run.state is not _G_PAUSE_REQUESTED
            and not node.restart
        ):
            if instance is not None:
                self._evolution.adopt(node, instance)
            ending = (result, outputs, error)
            fx.other.append(Effect(_E_FINISH_SPONTANEOUS, node, gen, ending=ending))
            return
        self._evolution.action_finished(node, gen, result, outputs, error, fx, instance)

    def _instantiate(self, node: Node, gen: int) -> Action:
        """No lock: make a node's action instance and initialise it (``on_init``).

        A blocking node's instance is registered at once, so that ``on_stop`` and ``on_pause``
        reach its first run; an inline node's is registered with its first result
        (:meth:`_settle`), saving a lock per new node: its run does not wait for hooks.
        """
        assert node.cls is not None
        instance = node.cls()
        node.spent = None  # after the allocation: the collector's count sees a replacement
        instance.initialize(  # positional: one per node and run, on the hot path
            node, node.name, node.run.name, node.inputs, node.outputs, self.registrar
        )
        if not node.inline:
            lock = self._lock
            lock.acquire()  # not `with`: its __enter__ and __exit__ cost as much again
            node.instance = instance  # (a store into a slot: nothing to release the lock for)
            lock.release()
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
                self._evolution.node_paused(node, gen)

    def _finish_spontaneous(
        self,
        node: Node,
        gen: int,
        result: Result,
        outputs: dict[str, Any],
        error: BaseException | None,
    ) -> None:
        """Worker: stop everything downstream of a spontaneous action, then propagate and re-run."""
        evolution = self._evolution
        fx = Effects()
        with self._lock:
            downstream = _downstream(node)
            for other in downstream:
                if other.active:
                    evolution.stop_node(other, fx)
        self.dispatch(fx, closing=self.closed)
        fx = Effects()
        with self._lock:
            evolution.wait_quiet(
                lambda: any(n.active for n in downstream) and not self.closed and node.gen == gen
            )
            if node.gen != gen:
                return
            rerun = node.state is _N_RUNNING and node.run.state is _G_RUNNING and not self.closed
            evolution.action_finished(node, gen, result, outputs, error, fx)
            if rerun and node.state is _N_FINISHED and node.run.state is _G_RUNNING:
                evolution.rerun(node, fx)
        # the re-run (or the first action that became ready) continues on this worker
        nxt = fx.runs.pop(0) if fx.runs else None
        self.dispatch(fx, closing=self.closed)
        if nxt is not None:
            self._run_batch([nxt])


def _downstream(start: Node) -> list[Node]:
    """Every node reachable from ``start`` along its run's relations (the exit excluded)."""
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


def _init_error(node: Node, err: Exception) -> ActionError:
    """The error of a node whose action could not be made or initialised (``on_init``)."""
    error = ActionError(
        f"{node.name} could not be initialised: {err}", graph=node.run.name, node=node.name
    )
    error.__cause__ = err
    return error


def _release_resources(action: Action) -> None:
    """Worker: release what a node's action acquired (RAII at graph end / node removal)."""
    try:
        count = action.release_resources()
    except Exception:
        logger.exception("releasing the resources of %s failed", action.name)
        return
    if count:
        logger.debug("released %d resources of %s", count, action.name)
