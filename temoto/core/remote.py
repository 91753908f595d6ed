"""What the engine needs from a fleet link to run graphs shared by several actors.

Every actor (robot) runs the same graph in its own engine (docs/design.md §4.6, thesis §6.3.2):

- before the run, the participating actors perform the N-to-N handshake (thesis Algorithm 3);
- an action whose ``actor`` is this engine's runs here, and its result and outputs are sent
  to every other participant, each of which acknowledges;
- an action of another actor is a *remote* node here: it waits for that notification and then
  finishes with the received result and outputs, as if it had run locally;
- actions with no ``actor`` run in every engine.

The engine sees the fleet only through :class:`ActorLink`; ``temoto.core`` never imports the
transport. ``temoto.fleet.FleetActorLink`` implements it over LCM; tests use an in-memory one.
All methods may be called from any thread; callbacks are called from the link's own thread
and must not block.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any, Protocol

from temoto.core.states import Result
from temoto.errors import FleetError

__all__ = ["ActorLink", "ActorLostError", "Cancel", "RemoteResult"]

#: Called with the result and outputs of a remote action (``on_true`` ... ``on_error``).
RemoteResult = Callable[[Result, Mapping[str, Any]], None]

#: Undoes a registration (idempotent).
Cancel = Callable[[], None]


class ActorLostError(FleetError):
    """A notification was not acknowledged because an actor is gone.

    Args:
        message: What happened, for people.
        actor: The actor that is gone.
        why: ``left`` (it left the run or the fleet), or ``not heard for N s``.

    Attributes:
        actor: The actor that is gone.
        why: Why it is taken as gone.
    """

    def __init__(self, message: str, *, actor: str, why: str) -> None:
        super().__init__(message)
        self.actor = actor
        self.why = why


class ActorLink(Protocol):
    """The engine's view of the other actors of a shared graph."""

    @property
    def actor(self) -> str:
        """This engine's actor name."""
        ...

    def handshake(self, graph: str, session: str, actors: Sequence[str], timeout: float) -> str:
        """Block until every pair of ``actors`` has heard each other for this session.

        Args:
            graph: The graph's name (the handshake token).
            session: Names this run of the graph, the same on every actor.
            actors: Every participating actor, this one included.
            timeout: Seconds to wait at most.

        Returns:
            The run id the participants agreed on, unique to this run: the ``session`` of
            every later call for the run (notify, expect, watch, end).

        Raises:
            FleetError: Not every actor answered in time (the message names them).
        """
        ...

    def notify(
        self,
        graph: str,
        session: str,
        action: str,
        result: Result,
        outputs: Mapping[str, Any],
        actors: Sequence[str],
        timeout: float,
    ) -> None:
        """Tell ``actors`` that a local action finished; block until each acknowledged.

        Args:
            graph: The graph's name.
            session: The run's session.
            action: The action's full name (``Name_instance``).
            result: Its result.
            outputs: Its output values (JSON-ready: UMRF parameter values).
            actors: The other participants.
            timeout: Seconds to wait for every acknowledgement (resending meanwhile).

        Raises:
            ActorLostError: An actor it was meant for is gone (silent, or left).
            FleetError: Some actor did not acknowledge in time (the message names it).
        """
        ...

    def expect(
        self, graph: str, session: str, action: str, actor: str, on_result: RemoteResult
    ) -> Cancel:
        """Call ``on_result`` once when ``actor`` notifies the end of ``action``.

        A notification that arrived before this call is delivered at once (from the link's
        thread). Every notification is acknowledged by the link, whether expected or not.

        Args:
            graph: The graph's name.
            session: The run's session.
            action: The remote action's full name.
            actor: The actor that runs it.
            on_result: The callback.

        Returns:
            A function that cancels the expectation.
        """
        ...

    def watch(
        self,
        actors: Sequence[str],
        on_lost: Callable[[str, str], None],
        *,
        graph: str = "",
        session: str = "",
        on_end: Callable[[str, Result], None] | None = None,
        on_abort: Callable[[str, str], None] | None = None,
    ) -> Cancel:
        """Call ``on_lost(actor, reason)`` if one of ``actors`` falls silent or leaves.

        An actor whose run (``graph``, ``session``) finished is no longer watched for that
        run (it may go quiet once it has nothing more to do) and ``on_end(actor, result)``
        is called; an actor that aborted the run is reported to ``on_abort(actor, reason)``
        with its reason, word for word. What a peer said before this call is reported too.

        Args:
            actors: The actors to watch (the other participants of a run).
            on_lost: The callback, at most once per actor.
            graph: The run's graph.
            session: The run's session.
            on_end: Called when an actor's run finished, with its result.
            on_abort: Called when an actor aborted the run, with the reason.

        Returns:
            A function that stops watching.
        """
        ...

    def end(
        self,
        graph: str,
        session: str,
        *,
        gave_up: bool = False,
        result: Result | None = None,
        reason: str = "",
    ) -> None:
        """Forget what the link keeps for an ended run (received notifications, waiters).

        Args:
            graph: The graph's name.
            session: The run's session.
            gave_up: The run was aborted here (stopped, failed): the other actors are told,
                and abort it too with ``reason`` (without one, they report this actor lost
                for the run, reason "left").
            result: How the run finished here, if it did: the other actors are told, and
                end it with that result too.
            reason: Why the run was aborted.
        """
        ...
