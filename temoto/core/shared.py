"""Shared runs: the engine's side of graphs shared by several actors.

A graph that names other actors is *shared*: every actor runs it in its own engine, and the
engines keep their runs in step through an :class:`~temoto.core.remote.ActorLink` (docs/design.md
§4.6, thesis §6.3.2; the wire protocol is ``temoto.fleet.actors``). The engine evolves one
graph and knows nothing of the protocol; :class:`SharedRuns` does the rest:

* the handshake before a shared run starts (:meth:`SharedRuns.handshake`);
* notifying the peers of the end of a local action (:meth:`SharedRuns.notify`), and waiting
  for the notifications of remote actions (:meth:`SharedRuns.expect`);
* watching the peers of a running shared run (:meth:`SharedRuns.watch`) and telling them how
  it ended here (:meth:`SharedRuns.end`).

*One outcome per shared run.* A shared run either ends with the same result on every actor,
or is aborted on every actor with the same reason (:attr:`GraphOutcome.aborted
<temoto.core.engine.GraphOutcome>`, and an ERROR result):

* the first actor to reach the end of the run (the graph's exit, or a halt) tells the others
  its result (END); an actor still running the run ends it with that result at once, as it
  would have once the last notifications arrived, and tells the others in turn;
* a notification that is not acknowledged in time, a lost peer (silent, or gone without a
  word) or a stop here aborts the run here, and the reason goes to the others word for word
  (LEAVE): they abort the run with it and pass it on. A failing action is not a reason to
  abort: its ERROR is notified like any result and the graph handles it the same everywhere.

So no actor waits for a node of an actor that has ended or left the run: it hears how the run
ended (the link repeats it to peers that still speak of the run) or, if every word is lost,
finds the actor silent after the link's ``silence_s``.

The methods are called by the engine outside its lock (effects, workers); link callbacks come
in on the link's thread and take the engine's lock to change the run. The protocol reaches the
engine only through :class:`RunHost` (its lock, the changes of a run it may ask for, the
timer, and a way to carry out effects), which the engine's
:class:`~temoto.core.evolution.RunEvolution` implements.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any, Protocol

from temoto.core._runtime import GraphRun, Node, Plan
from temoto.core.effects import Effects
from temoto.core.remote import ActorLink, ActorLostError
from temoto.core.states import ENDED_GRAPH_STATES, GraphState, Result
from temoto.errors import ActionError, FleetError

if TYPE_CHECKING:
    from temoto.core.executor import TimerHandle

__all__ = ["RunHost", "SharedRuns"]

logger = logging.getLogger(__name__)

_ENDED_GRAPH = ENDED_GRAPH_STATES
#: a shared run that has not ended and was not asked to stop
_LIVE_GRAPH = frozenset({GraphState.RUNNING, GraphState.PAUSE_REQUESTED, GraphState.PAUSED})


class RunHost(Protocol):
    """What the shared-run protocol asks of the engine (its evolution implements it).

    The methods that take ``fx`` are called with :attr:`lock` held; they change the run and
    add what must happen outside the lock to ``fx``, which :meth:`carry_out` then does (the
    lock released).
    """

    #: the engine's lock: it guards the runs and their nodes
    lock: threading.Lock
    #: carries out effects, the lock released
    carry_out: Callable[[Effects], None]

    def stop_run(self, run: GraphRun, fx: Effects) -> None:
        """Lock held: stop a run."""

    def end_with_peer(self, run: GraphRun, result: Result, fx: Effects) -> None:
        """Lock held: end a run with the result another actor reached."""

    def take_peer_result(self, run: GraphRun, result: Result) -> None:
        """Lock held: an ended (aborted, settling) run takes another actor's result instead."""

    def action_finished(
        self,
        node: Node,
        gen: int,
        result: Result,
        outputs: dict[str, Any],
        error: BaseException | None,
        fx: Effects,
    ) -> None:
        """Lock held: an action run of ``node`` (generation ``gen``) ended."""

    def call_later(self, seconds: float, fn: Callable[..., Any], *args: Any) -> TimerHandle:
        """Call ``fn(*args)`` on the engine's timer thread (RuntimeError: shut down)."""
        ...


class SharedRuns:
    """The shared runs of one engine, over its actor link.

    Args:
        host: The engine whose runs these are (its evolution).
        link: The link to the other actors.
        handshake_timeout: Seconds the handshake before a shared run may take.
        notify_timeout: Seconds every other actor has to acknowledge a finished action.
        settle_timeout: Real seconds an aborted run still listens to its peers before it is
            done (a peer's result, or a smaller reason, may still change its outcome).
    """

    def __init__(
        self,
        host: RunHost,
        link: ActorLink,
        *,
        handshake_timeout: float,
        notify_timeout: float,
        settle_timeout: float = 1.0,
    ) -> None:
        self._host = host
        self.link = link
        self.handshake_timeout = handshake_timeout
        self.notify_timeout = notify_timeout
        self.settle_timeout = settle_timeout
        self._settling: set[GraphRun] = set()  # aborted runs not done yet (engine lock)

    @staticmethod
    def peers(actor: str, plan: Plan) -> tuple[str, ...]:
        """The other actors a plan's graph is shared with (empty for a local graph).

        Args:
            actor: This engine's actor.
            plan: The plan.

        Returns:
            Their names, sorted.
        """
        actors = {a.actor for a in plan.graph.actions if a.actor and a.actor != actor}
        return tuple(sorted(actors))

    def handshake(self, plan: Plan, run_name: str, peers: tuple[str, ...]) -> str:
        """Block until every participant of a run has heard every other.

        Args:
            plan: The run's plan.
            run_name: The run's name (the handshake's session).
            peers: The other participants.

        Returns:
            The run id the participants agreed on (the session of every later message).

        Raises:
            FleetError: The handshake did not complete within ``handshake_timeout``.
        """
        actors = sorted({self.link.actor, *peers})
        return self.link.handshake(plan.graph.name, run_name, actors, self.handshake_timeout)

    def watch(self, run: GraphRun) -> None:
        """Have the link report a peer of ``run`` that ends, aborts, falls silent or leaves."""
        cancel = self.link.watch(
            run.peers,
            lambda actor, why: self._actor_lost(run, actor, why),
            graph=run.plan.graph.name,
            session=run.session,
            on_end=lambda actor, result: self._peer_ended(run, actor, result),
            on_abort=lambda actor, reason: self.abort(run, reason),
        )
        with self._host.lock:
            ended = run.state in _ENDED_GRAPH and run not in self._settling
            if not ended:
                run.unwatch = cancel
        if ended:
            cancel()

    def _actor_lost(self, run: GraphRun, actor: str, why: str) -> None:
        """Link thread: a peer fell silent or left without a word; the run is aborted."""
        with self._host.lock:
            if run.state not in _LIVE_GRAPH:
                return  # a settling abort takes words from peers only (they agree on those)
            logger.error("%s: actor '%s' was lost (%s)", run.name, actor, why)
        # the same words on every actor, whoever it misses (a partition: each side another)
        self.abort(run, f"an actor was lost ({why})")

    def abort(self, run: GraphRun, reason: str) -> None:
        """Abort a shared run here: it ends in ERROR, and the others are told why.

        Called from any thread, outside the engine's lock. A run that has ended here is left
        as it is, except while an abort settles (``settle_timeout``): then the smaller of
        the two reasons is kept, and told to the others, so that actors that aborted at the
        same time for different reasons end with the same one.

        Args:
            run: The run.
            reason: Why, in the words every actor reports.
        """
        host = self._host
        fx = Effects()
        with host.lock:
            if run.state in _LIVE_GRAPH:
                run.aborted = reason
                error = FleetError(f"shared run {run.name} aborted: {reason}")
                run.errors.append(error)
                run.stop_failed = True  # the stop ends the run in ERROR, not STOPPED
                logger.error("%s", error)
                host.stop_run(run, fx)
            elif run in self._settling and run.aborted is not None and reason < run.aborted:
                run.aborted = reason
            else:
                return
        if fx:
            host.carry_out(fx)
        else:
            self.link.end(run.plan.graph.name, run.session, gave_up=True, reason=reason)

    def _peer_ended(self, run: GraphRun, actor: str, result: Result) -> None:
        """Link thread: a peer reached the end of the run; it ends here with its result."""
        host = self._host
        fx = Effects()
        with host.lock:
            if run.state in _LIVE_GRAPH:
                logger.info(
                    "%s: actor '%s' ended the run %s; so does this one", run.name, actor, result
                )
                host.end_with_peer(run, result, fx)
            elif run in self._settling:
                # a peer had reached the end when this actor aborted: its result stands
                logger.warning(
                    "%s: actor '%s' ended the run %s; aborted here (%s), it takes that result",
                    run.name,
                    actor,
                    result,
                    run.aborted,
                )
                self._settling.discard(run)
                host.take_peer_result(run, result)
                unwatch, run.unwatch = run.unwatch, None
            else:
                return
        if fx:
            host.carry_out(fx)
            return
        try:
            if unwatch is not None:
                unwatch()
            self.link.end(run.plan.graph.name, run.session, result=result)
        finally:
            run.done.set()

    def end(self, run: GraphRun) -> None:
        """Tell the peers how the run ended here; then (an abort: once settled) it is done.

        A run that reached its end here (finished, or halted) says its result (END) and is
        done. Any other (aborted, stopped, failed) says its reason (LEAVE) and is done after
        ``settle_timeout``, during which a peer's result or a smaller reason can still change
        its outcome (see :meth:`abort`).
        """
        host = self._host
        me = self.link.actor
        with host.lock:
            reached = run.state in (GraphState.FINISHED, GraphState.HALTED)
            if reached:
                unwatch, run.unwatch = run.unwatch, None
            else:
                unwatch = None
                if run.aborted is None:
                    run.aborted = (
                        f"actor '{me}' stopped the run"
                        if run.state is GraphState.STOPPED
                        else f"the run failed on actor '{me}'"
                    )
                self._settling.add(run)
            result, reason = run.result, run.aborted or ""
        graph = run.plan.graph.name
        if not reached:
            self.link.end(graph, run.session, gave_up=True, reason=reason)
            try:
                host.call_later(self.settle_timeout, self._settled, run)
            except RuntimeError:  # the engine's timer is shut down: no time to settle
                self._settled(run)
            return
        try:
            if unwatch is not None:
                unwatch()
            self.link.end(graph, run.session, result=result)
        finally:
            run.done.set()  # only now: a caller may close the link as soon as wait() returns

    def _settled(self, run: GraphRun) -> None:
        """Timer thread: an aborted run's outcome is final."""
        with self._host.lock:
            if run not in self._settling:
                return  # a peer's result was taken meanwhile
            self._settling.discard(run)
            unwatch, run.unwatch = run.unwatch, None
        try:
            if unwatch is not None:
                unwatch()
        finally:
            run.done.set()

    def expect(self, node: Node, gen: int) -> None:
        """Wait (through the link) for the notification of a remote action's end."""
        run = node.run
        cancel = self.link.expect(
            run.plan.graph.name,
            run.session,
            node.name,
            node.umrf.actor,
            lambda result, outputs: self._remote_finished(node, gen, result, outputs),
        )
        with self._host.lock:
            current = node.gen == gen and node.active
            if current:
                node.remote_cancel = cancel
        if not current:
            cancel()

    def _remote_finished(
        self, node: Node, gen: int, result: Result, outputs: Mapping[str, Any]
    ) -> None:
        """Link thread: another actor finished the action this node stands for."""
        host = self._host
        fx = Effects()
        with host.lock:
            if node.gen != gen or not node.active:
                return  # stopped meanwhile, or a notification for an earlier run of the node
            node.remote_cancel = None
            error: BaseException | None = None
            if result is Result.ERROR:
                error = ActionError(
                    f"{node.name} failed on actor '{node.umrf.actor}'",
                    graph=node.run.name,
                    node=node.name,
                )
            host.action_finished(node, gen, result, dict(outputs), error, fx)
        host.carry_out(fx)

    def notify(
        self, node: Node, result: Result, outputs: dict[str, Any], error: BaseException | None
    ) -> tuple[Result, BaseException | None]:
        """Worker: tell the other actors that a local action finished (they acknowledge).

        Args:
            node: The action's node.
            result: Its result.
            outputs: Its outputs.
            error: What it raised, if anything.

        Returns:
            The result and error the node finishes with here. An actor that does not
            acknowledge in time aborts the run (on every actor: the reason goes to them), so
            the node ends STOPPED here.
        """
        run = node.run
        try:
            self.link.notify(
                run.plan.graph.name,
                run.session,
                node.name,
                result,
                outputs,
                run.peers,
                self.notify_timeout,
            )
        except ActorLostError as err:
            if err.why != "left":  # one that left is reported by the watch, with its reason
                self._actor_lost(run, err.actor, err.why)
        except FleetError as err:
            self.abort(run, str(err))
        return result, error
