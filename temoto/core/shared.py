"""Shared runs: the engine's side of graphs shared by several actors.

A graph that names other actors is *shared*: every actor runs it in its own engine, and the
engines keep their runs in step through an :class:`~temoto.core.remote.ActorLink` (REFERENCE
§2.14, thesis §6.3.2; the wire protocol is ``temoto.fleet.actors``). The engine evolves one
graph and knows nothing of the protocol; :class:`SharedRuns` does the rest:

* the handshake before a shared run starts (:meth:`SharedRuns.handshake`);
* watching the peers of a running shared run: a peer lost (silent, or gave the run up) ends
  the run here in ERROR (:meth:`SharedRuns.watch`);
* notifying the peers of the end of a local action (:meth:`SharedRuns.notify`), and waiting
  for the notifications of remote actions (:meth:`SharedRuns.expect`);
* telling the link that a run ended (END when it finished here, LEAVE when it was given up:
  :meth:`SharedRuns.end`).

The methods are called by the engine outside its lock (effects, workers); link callbacks come
in on the link's thread and take the engine's lock to change the run.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from temoto.core._runtime import GraphRun, Node, Plan
from temoto.core.remote import ActorLink
from temoto.core.states import GraphState, Result
from temoto.errors import ActionError, FleetError

if TYPE_CHECKING:
    from temoto.core.engine import ActionEngine

__all__ = ["SharedRuns"]

logger = logging.getLogger(__name__)

_ENDED_GRAPH = frozenset(
    {GraphState.FINISHED, GraphState.STOPPED, GraphState.ERROR, GraphState.HALTED}
)


class SharedRuns:
    """The shared runs of one engine, over its actor link.

    Args:
        engine: The engine whose runs these are.
        link: The link to the other actors.
        handshake_timeout: Seconds the handshake before a shared run may take.
        notify_timeout: Seconds every other actor has to acknowledge a finished action.
    """

    def __init__(
        self,
        engine: ActionEngine,
        link: ActorLink,
        *,
        handshake_timeout: float,
        notify_timeout: float,
    ) -> None:
        self._engine = engine
        self.link = link
        self.handshake_timeout = handshake_timeout
        self.notify_timeout = notify_timeout

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

    def handshake(self, plan: Plan, run_name: str, peers: tuple[str, ...]) -> None:
        """Block until every participant of a run has heard every other.

        Args:
            plan: The run's plan.
            run_name: The run's name (its session).
            peers: The other participants.

        Raises:
            FleetError: The handshake did not complete within ``handshake_timeout``.
        """
        actors = sorted({self.link.actor, *peers})
        self.link.handshake(plan.graph.name, run_name, actors, self.handshake_timeout)

    def watch(self, run: GraphRun) -> None:
        """Have the link report a peer of ``run`` that falls silent or leaves."""
        engine = self._engine
        cancel = self.link.watch(
            run.peers,
            lambda actor, why: self._actor_lost(run, actor, why),
            graph=run.plan.graph.name,
            session=run.name,
        )
        with engine._lock:
            ended = run.state in _ENDED_GRAPH
            if not ended:
                run.unwatch = cancel
        if ended:
            cancel()

    def _actor_lost(self, run: GraphRun, actor: str, reason: str) -> None:
        """Link thread: a peer of a shared run is gone; the run ends in ERROR here too."""
        engine = self._engine
        fx: list[Any] = []
        with engine._lock:
            if run.state not in (GraphState.RUNNING, GraphState.PAUSED):
                return
            error = FleetError(f"graph {run.name}: actor '{actor}' was lost ({reason})")
            run.errors.append(error)
            run.stop_failed = True  # the stop ends the run in ERROR, not STOPPED
            logger.error("%s", error)
            engine._stop_run(run, fx)
        engine._dispatch(fx, closing=engine._closed)

    def end(self, run: GraphRun) -> None:
        """Stop watching the run's peers and let the link forget the run; then it is done."""
        engine = self._engine
        with engine._lock:
            unwatch, run.unwatch = run.unwatch, None
        try:
            if unwatch is not None:
                unwatch()
            # a run that did not finish here is abandoned by this actor: the others are told
            self.link.end(
                run.plan.graph.name, run.name, gave_up=run.state is not GraphState.FINISHED
            )
        finally:
            run.done.set()  # only now: a caller may close the link as soon as wait() returns

    def expect(self, node: Node, gen: int) -> None:
        """Wait (through the link) for the notification of a remote action's end."""
        engine = self._engine
        run = node.run
        cancel = self.link.expect(
            run.plan.graph.name,
            run.name,
            node.name,
            node.umrf.actor,
            lambda result, outputs: self._remote_finished(node, gen, result, outputs),
        )
        with engine._lock:
            current = node.gen == gen and node.active
            if current:
                node.remote_cancel = cancel
        if not current:
            cancel()

    def _remote_finished(
        self, node: Node, gen: int, result: Result, outputs: Mapping[str, Any]
    ) -> None:
        """Link thread: another actor finished the action this node stands for."""
        engine = self._engine
        fx: list[Any] = []
        with engine._lock:
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
            engine._on_finished(node, gen, result, dict(outputs), error, fx)
        engine._dispatch(fx, closing=engine._closed)

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
            The result and error the node finishes with here: an actor that does not
            acknowledge in time turns them into an error.
        """
        run = node.run
        try:
            self.link.notify(
                run.plan.graph.name,
                run.name,
                node.name,
                result,
                outputs,
                run.peers,
                self.notify_timeout,
            )
        except FleetError as err:
            failure = ActionError(
                f"{node.name}: the other actors were not told ({err})",
                graph=run.name,
                node=node.name,
            )
            failure.__cause__ = err
            return Result.ERROR, failure
        return result, error
