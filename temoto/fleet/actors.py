"""The engine's link to the other actors of shared graphs, over the fleet transport.

:class:`FleetActorLink` implements :class:`temoto.core.remote.ActorLink` (docs/design.md §4.6,
thesis §6.3.2) with the messages of ``temoto/lcm_types/defs`` on two channels:

``TEMOTO_HANDSHAKE`` (``handshake_t``)
    *The N-to-N handshake* (thesis Algorithm 3). Each participant broadcasts a ``JOIN`` naming
    the run (graph and session), the participants, and the peers it has heard in this run with
    the stamp of their newest handshake (``handshake_t`` version 2: the participants as one
    JSON string, the stamps as one byte array by place in it, read without parsing by a
    receiver whose list is the same). It does so every ``resend_s`` (for N > 10 participants
    at most every ``resend_s * N / 10``: the fleet's JOINs per second do not grow with it) and
    at once when it hears a peer for the first time, so a handshake takes about one network
    round trip. It is done
    when every ordered pair ``(a, b)`` of participants is known to be heard: ``a`` heard ``b``
    according to ``a``'s newest heard list (our own for ``a`` = this actor). A pair
    ``(peer, this actor)`` needs a *fresh* stamp: the peer must echo a stamp of this call, so a
    report left over from an earlier run of the same session never completes a new one. Once
    done, the actor freezes its heard list, says ``READY``, and keeps answering the JOINs of
    that run (a peer may complete later) until :meth:`~FleetActorLink.end`, and for
    ``grace_s`` after it, with READYs that carry the agreed run id. A ``JOIN`` of a run this
    actor has not started yet is kept (a peer may start earlier), for ``stray_s`` at most.

    ``LEAVE`` means that the sender gave up the run: its handshake timed out, or its link was
    closed while the run was active. A peer still in the handshake fails at once; a peer
    already running reports the sender lost to its watchers (reason ``left``). An actor that
    merely ended the run says nothing.

``TEMOTO_NOTIFY`` (``action_notification_t``)
    *Notifications*: the end of a local action, with its result and outputs (JSON), is
    published, and published again until every other participant acknowledged it, but only
    after a period in which no acknowledgement came in (a loaded fleet acknowledges slowly, and
    each copy costs every actor a decode and an acknowledgement). The period is ``resend_s``
    after an acknowledgement and doubles with each copy, up to ``8 * resend_s``. A receiver
    acknowledges every copy of every notification of another actor, whether it expects it or
    not, and takes each notification (by its id) once: the first copy goes to the oldest
    :meth:`~FleetActorLink.expect` of that (graph, session, action, actor) or waits for one. A
    node in a cycle finishes more than once per run; each time is a new notification.

``TEMOTO_ACK_<sender>`` (``action_ack_t``, see :func:`ack_channel`)
    *Acknowledgements* go to the notification's sender alone: each actor listens on its own
    acknowledgement channel, so an acknowledgement is handled by one process, not by the whole
    fleet (a notification to N actors costs the fleet N handled acknowledgements per copy, not
    N * N; LCM drops the other channels before Python sees them).

*Liveness*: while a run is active or something is watched, the link sends a ``READY``
handshake every ``heartbeat_s`` (``5 * resend_s``, at most a third of ``silence_s``); a
watched actor from which nothing at all was heard for ``silence_s`` is reported lost. A
heartbeat names its run but carries no actor or heard list (a READY without a heard list
changes nothing in a handshake) once every participant said READY with its lists; until then
heartbeats are full READYs, as are the first READY and the answers to late JOINs.

Threads: receiving runs on the transport's thread; one thread (``temoto-fleet-actors``)
sends heartbeats, checks silences and forgets expired state; another
(``temoto-fleet-actors-calls``) runs the callbacks, so a slow callback never delays an
acknowledgement or a heartbeat. Resending is done by the thread that waits in
:meth:`~FleetActorLink.handshake` or :meth:`~FleetActorLink.notify`.

Code: this module is the link's API and what concerns all of a run (its end, the link's
close, the dispatch of handshake messages). The work is done by three parts that share one
:class:`~temoto.fleet._actor_state.LinkState` (the :class:`~temoto.fleet.service.ServiceCore`
and the tables of runs): :mod:`temoto.fleet._handshake`, :mod:`temoto.fleet._notify` and
:mod:`temoto.fleet._supervision` (watches, silences and the two threads).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any, Final, final

from temoto.clock import Clock
from temoto.core.remote import Cancel, RemoteResult
from temoto.core.states import Result
from temoto.fleet._actor_state import (
    ACK_CHANNEL_PREFIX,
    END,
    HANDSHAKE_CHANNEL,
    LEAVE,
    NOTIFY_CHANNEL,
    PHASES,
    Ended,
    LinkState,
    Phase,
    ack_channel,
)
from temoto.fleet._handshake import Handshakes
from temoto.fleet._notify import Notices
from temoto.fleet._supervision import Supervisor
from temoto.fleet.common import Closing, check_name, check_seconds
from temoto.fleet.service import ServiceCore
from temoto.transport.auth import Opened
from temoto.transport.base import Subscription
from temoto.transport.link import FleetLink

__all__ = [
    "ACK_CHANNEL_PREFIX",
    "HANDSHAKE_CHANNEL",
    "NOTIFY_CHANNEL",
    "STATS",
    "FleetActorLink",
    "ack_channel",
]

#: The counters of :attr:`FleetActorLink.stats`.
STATS: Final = (
    "handshakes_sent",  # every handshake_t: JOIN, READY (heartbeats too), LEAVE
    "handshakes_received",
    "notifications_sent",  # resends included
    "notifications_received",  # duplicates included
    "duplicates",  # copies of a notification taken already
    "acks_sent",
    "acks_received",
    "decode_errors",  # payloads that codec.decode refused
    "unexpected",  # well-formed but meaningless here: wrong type for the channel, bad phase, ...
    "send_errors",  # sends that failed on the link's own threads (logged)
    "callback_errors",  # callbacks that raised (logged)
    "lost",  # actors reported to on_lost
    "impostor",  # naming another member than their authenticated sender (dropped)
)

# Deliveries a busy subscription keeps while the handlers catch up (LCM keeps 30 by default
# and drops the rest silently: a burst of notifications and heartbeats must not be lost).
_QUEUE_CAPACITY: Final = 1024


@final
class FleetActorLink(Closing):
    """The :class:`~temoto.core.remote.ActorLink` of one actor over a fleet link.

    It subscribes to :data:`HANDSHAKE_CHANNEL`, :data:`NOTIFY_CHANNEL` and its own
    :func:`ack_channel` of ``link`` and starts its threads at once; :meth:`close` (or leaving
    the ``with`` block) stops them. The fleet link and its transport stay the caller's to
    close, after this link.

    Args:
        link: Sends and receives authenticated fleet messages.
        actor: This actor's name, as the graphs name it.
        resend_s: Period of handshake and notification resends.
        silence_s: A watched actor not heard for this long is lost.
        grace_s: How long an ended run's handshake is still answered and its notification ids
            remembered (so late resends are not taken again).
        stray_s: How long a run that was never started here is kept since a peer last spoke
            of it.
        linger_s: On close, how long to keep answering (and repeating END) after runs that
            just finished here (0: close at once).
        clock: Where time is read: monotonic seconds (deadlines, silences) and the epoch
            seconds of handshake stamps and notification ids (default:
            :class:`~temoto.clock.MonotonicClock`).

    Attributes:
        linger_s: How long :meth:`close` keeps answering after runs that just finished.

    Raises:
        ValueError: If ``actor`` is empty or a duration is not a positive number.
        TypeError: If ``clock`` is not a :class:`~temoto.clock.Clock`.
        TransportError: If the link's transport is closed.
    """

    def __init__(
        self,
        link: FleetLink,
        actor: str,
        *,
        resend_s: float = 0.1,
        silence_s: float = 3.0,
        grace_s: float = 5.0,
        stray_s: float = 60.0,
        linger_s: float = 0.3,
        clock: Clock | None = None,
    ) -> None:
        self._link = link
        actor = check_name("actor", actor)
        resend_s = check_seconds("resend_s", resend_s)
        silence_s = check_seconds("silence_s", silence_s)
        self.linger_s = check_seconds("linger_s", linger_s, zero=True)
        # The one state the parts share: each holds it by reference.
        self._st = st = LinkState(
            ServiceCore(link, STATS, clock),
            actor,
            resend_s=resend_s,
            silence_s=silence_s,
            grace_s=check_seconds("grace_s", grace_s, zero=True),
            stray_s=check_seconds("stray_s", stray_s),
            heartbeat_s=min(5 * resend_s, silence_s / 3),
        )
        self._handshakes = Handshakes(st)
        self._notices = Notices(st)
        self._supervisor = Supervisor(st, self._handshakes)
        self._subs: list[Subscription] = []
        try:
            for channel, handler in (
                (HANDSHAKE_CHANNEL, self._on_handshake),
                (NOTIFY_CHANNEL, self._notices.on_notify),
                (ack_channel(self._st.actor), self._notices.on_ack),
            ):
                self._subs.append(link.listen(channel, handler, queue_capacity=_QUEUE_CAPACITY))
        except BaseException:
            for sub in self._subs:
                sub.unsubscribe()
            raise
        self._timer = threading.Thread(
            target=self._supervisor.run_timer, name="temoto-fleet-actors", daemon=True
        )
        self._caller = threading.Thread(
            target=self._supervisor.run_calls, name="temoto-fleet-actors-calls", daemon=True
        )
        self._timer.start()
        self._caller.start()

    def __repr__(self) -> str:
        state = "closed" if self._st.core.closed else "open"
        return f"<FleetActorLink actor={self._st.actor!r} {state} on {self._link!r}>"

    @property
    def actor(self) -> str:
        """This engine's actor name."""
        return self._st.actor

    @property
    def resend_s(self) -> float:
        """Period of handshake and notification resends."""
        return self._st.resend_s

    @property
    def silence_s(self) -> float:
        """After this long without a message a watched actor is lost."""
        return self._st.silence_s

    @property
    def grace_s(self) -> float:
        """How long an ended run is still answered for."""
        return self._st.grace_s

    @property
    def stray_s(self) -> float:
        """How long a run never started here is kept."""
        return self._st.stray_s

    @property
    def heartbeat_s(self) -> float:
        """Period of the READY heartbeats: ``5 * resend_s``, at most a third of ``silence_s``."""
        return self._st.heartbeat_s

    @property
    def stats(self) -> dict[str, int]:
        """A copy of the counters, one per name in :data:`STATS`."""
        return self._st.core.stats()

    def handshake(self, graph: str, session: str, actors: Sequence[str], timeout: float) -> str:
        """Block until every pair of ``actors`` has heard each other in this run.

        Each participant proposes a random run id in its JOINs; the run id of the run is the
        smallest proposal, which every participant knows once the handshake is done. Every
        later message of the run (notifications, acknowledgements, END, LEAVE) carries it as
        its session, so two runs of the same graph and session name never mix, however
        quickly one follows the other.

        Args:
            graph: The graph's name (the handshake token).
            session: Names this run of the graph, the same on every actor.
            actors: Every participating actor, this one included.
            timeout: Seconds to wait at most.

        Returns:
            The run id: the session of :meth:`notify`, :meth:`expect`, :meth:`watch` and
            :meth:`end` for this run (``session`` itself for a run of this actor alone).

        Raises:
            FleetError: Not every pair heard each other in time (the message names who was
                not heard by whom), a participant gave up, the run was ended meanwhile, or the
                link is closed or cannot send. This actor then sends LEAVE for the run.
            StateError: A handshake of this run is already running here.
            ValueError: An argument is invalid, or ``actors`` lacks this actor.
        """
        return self._handshakes.run(graph, session, actors, timeout)

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

        The notification is published again after each period without an acknowledgement
        (``resend_s`` after an acknowledgement, doubling with each copy up to
        ``8 * resend_s``) until then.

        Args:
            graph: The graph's name.
            session: The run's session.
            action: The action's full name (``Name_instance``).
            result: Its result.
            outputs: Its output values by name (JSON-ready).
            actors: The other participants (this actor, if listed, is left out).
            timeout: Seconds to wait for every acknowledgement.

        Raises:
            ActorLostError: An actor waited for is gone: it left the run or the fleet, or was
                not heard for ``silence_s``.
            FleetError: Some actor did not acknowledge in time (the message names it), the
                run was ended meanwhile, the link is closed or cannot send, or the outputs
                are not JSON-ready.
            ValueError: An argument is invalid.
        """
        self._notices.notify(graph, session, action, result, outputs, actors, timeout)

    def expect(
        self, graph: str, session: str, action: str, actor: str, on_result: RemoteResult
    ) -> Cancel:
        """Call ``on_result`` once when ``actor`` notifies the end of ``action``.

        Notifications that arrived before are delivered at once, oldest first, one per call.
        The callback runs on the link's callback thread and must not block.

        Args:
            graph: The graph's name.
            session: The run's session.
            action: The remote action's full name.
            actor: The actor that runs it.
            on_result: Called with the result and the outputs.

        Returns:
            A function that cancels the expectation (idempotent); a notification it would
            have received is kept for the next one.

        Raises:
            FleetError: The link is closed.
            ValueError: An argument is invalid.
        """
        return self._notices.expect(graph, session, action, actor, on_result)

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

        An actor is lost when nothing was heard from it for ``silence_s`` (counted from this
        call at the earliest), or when it gave up a run this actor takes part in (LEAVE
        without a reason). The callbacks run on the link's callback thread, at most one per
        actor. Watching for a run (``graph`` and ``session``), an actor whose run finished
        there (END) is no longer watched (it may go quiet) and ``on_end(actor, result)`` is
        called; an actor that aborted the run (LEAVE with a reason) is reported to
        ``on_abort(actor, reason)``. What a peer said of the run before this call is
        reported too.

        Args:
            actors: The actors to watch (this actor, if listed, is left out).
            on_lost: The callback.
            graph: The run's graph, if the watch is for a run.
            session: The run's session.
            on_end: Called when a watched actor's run finished (END), with its result.
            on_abort: Called when a watched actor aborted the run, with its reason.

        Returns:
            A function that stops watching (idempotent).

        Raises:
            FleetError: The link is closed.
            ValueError: An actor name is invalid.
        """
        return self._supervisor.watch(
            actors, on_lost, graph=graph, session=session, on_end=on_end, on_abort=on_abort
        )

    def end(
        self,
        graph: str,
        session: str,
        *,
        gave_up: bool = False,
        result: Result | None = None,
        reason: str = "",
    ) -> None:
        """Forget an ended run: its notifications, waiters and handshake state.

        A handshake or notify of that run still waiting fails. For ``grace_s`` the run's ids
        stay known (late resends are acknowledged, not taken) and, if its handshake had
        completed, peers still in it are answered, heartbeats go on, and a peer heard
        speaking of the run is told again how it ended here (END or LEAVE), in case the
        first word was lost.

        Args:
            graph: The graph's name.
            session: The run's session.
            gave_up: The run did not finish here: LEAVE is sent for it, so the peers abort it
                too, with ``reason`` (without one, they report this actor lost, "left"), at
                once instead of after ``silence_s``.
            result: How the run finished here (END carries it; the peers take it).
            reason: Why the run was aborted (LEAVE carries it word for word).
        """
        key = (graph, session)
        leave = None
        decision: tuple[int, str, str] | None = None
        with self._st.lock:
            now = self._st.core.now()
            run = self._st.runs.pop(key, None)
            if run is not None:
                for other in ((run.graph, run.session), (run.graph, run.run_id)):
                    if self._st.runs.get(other) is run:
                        del self._st.runs[other]  # the same run under its other key
            ended = self._st.ended.get(key)
            if run is None and ended is not None and ended.decision is not None:
                # a new word on a run that ended here: an abort's reason, or a result taken
                # from a peer while the abort settled
                if gave_up:
                    ended.decision = (LEAVE, "", reason)
                elif result is not None:
                    ended.decision = (END, result.value, "")
                ended.decided, ended.next_repeat = now, now + self._st.resend_s
                if not self._st.core.closed:
                    leave = self._handshakes.decision_msg(
                        ended.out_key or key, ended.actors, ended.decision
                    )
            finished = run is not None and not gave_up and run.phase is Phase.READY
            if run is not None and (gave_up or finished):
                if gave_up:
                    decision = (LEAVE, "", reason)
                else:
                    decision = (END, "" if result is None else result.value, "")
                if not self._st.core.closed:
                    leave = self._handshakes.decision_msg(key, run.actors, decision)
            if run is not None:
                for waiters in run.waiters.values():
                    for waiter in waiters:
                        waiter.active = False
                run.aborted = "the run was ended"
                done = run.phase is Phase.READY
                if done or run.seen:
                    kept = Ended(
                        run.actors,
                        run.frozen if done else None,
                        run.seen,
                        now + self._st.grace_s,
                        decision if done else None,
                        now,
                        now + self._st.resend_s,
                        key,
                        run_id=run.run_id,
                    )
                    self._st.ended[key] = kept
                    self._st.ended[(run.graph, run.session)] = kept  # late JOINs name the session
            for out in self._st.outgoing.values():
                if out.key == key:
                    out.aborted = "the run was ended"
            self._st.changed.notify_all()
            self._st.timer_wake.notify()
        if leave is not None:
            self._st.send_quietly(HANDSHAKE_CHANNEL, leave, "handshakes_sent")

    def close(self) -> None:
        """Stop the link: LEAVE the active runs, unsubscribe, stop and join the threads.

        Waiting calls fail with FleetError; callbacks not run yet are dropped. Idempotent.
        """
        self._linger()
        with self._st.lock:
            if self._st.core.closed:
                return
            self._st.core.closed = True
            active = [r for r in self._st.distinct_runs() if r.local and r.phase is not Phase.KEPT]
            leaves = [self._handshakes.leave_msg(r.graph, r.session, r.actors) for r in active]
            self._st.calls.clear()
            self._st.changed.notify_all()
            self._st.timer_wake.notify()
            self._st.calls_ready.notify()
        for msg in leaves:
            self._st.send_quietly(HANDSHAKE_CHANNEL, msg, "handshakes_sent")
        for sub in self._subs:
            sub.unsubscribe()
        for thread in (self._timer, self._caller):
            if thread is not threading.current_thread():
                thread.join()

    def _linger(self) -> None:
        """Before closing: repeat END or LEAVE for runs that just ended here; keep answering.

        For ``linger_s``, so a peer whose last notification we acknowledged (an
        acknowledgement that may have been lost) is not left resending to nobody; then for as
        long as a peer keeps sending notifications of such a run (it waits for our
        acknowledgement, so ours, and our END, have not reached it) or heartbeats of it (our
        END has not reached it; each is answered with it), at most ``silence_s``,
        after which it would find us lost anyway. Over a lossy TCP link (Zenoh) both can be
        held up for seconds; a process that exited meanwhile took them along, and its peers
        aborted the run it had ended (tests/fleet/test_zenoh_netns.py, 2 runs in 7).
        """
        with self._st.lock:
            if self._st.core.closed:
                return
            now = self._st.core.now()
            ends = [
                self._handshakes.decision_msg(key, e.actors, e.decision)
                for key, e in self._st.ended.items()
                if e.decision is not None and e.until > now and e.out_key in (None, key)
            ]
        if not ends or self.linger_s <= 0:
            return
        # Real time, not the link's clock: closing must not wait for a virtual clock to move.
        deadline = time.monotonic() + self.linger_s
        while True:
            for msg in ends:
                self._st.send_quietly(HANDSHAKE_CHANNEL, msg, "handshakes_sent")
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                break
            with self._st.lock:
                self._st.changed.wait(min(self._st.resend_s, remaining))
        # Peers that still send us notifications or heartbeats of such a run are acknowledged
        # and told END again until they go quiet: answered, ended, or gone.
        until = time.monotonic() + self._st.silence_s
        with self._st.lock:
            while not self._st.core.closed:
                now = time.monotonic()
                recent = now - 2 * self._st.heartbeat_s
                if now >= until or not any(
                    heard >= recent
                    for e in self._st.ended.values()
                    if e.decision is not None
                    for heard in e.speaking.values()
                ):
                    return
                self._st.changed.wait(min(self._st.heartbeat_s, until - now))

    # --- receiving (the transport's thread) ---------------------------------------------------

    def _on_handshake(self, opened: Opened) -> None:
        """A ``handshake_t``: liveness, then a LEAVE, an END, or a JOIN or READY of a run."""
        msg = self._st.decode(opened, ("handshake_t",))
        if msg is None:
            return
        actor: str = msg.actor
        if actor and not self._st.core.speaks_as(opened, actor, "actor"):
            return  # a member speaking as another (docs/security.md)
        with self._st.lock:
            if self._st.core.closed:
                return
            if not actor or actor == self._st.actor or msg.phase not in PHASES:
                self._st.core.count("unexpected")
                return
            self._st.core.count("handshakes_received")
            now = self._st.core.now()
            self._st.heard_at[actor] = now
            if msg.phase == LEAVE:
                self._supervisor.on_leave(actor, msg.graph, msg.session, msg.reason)
                return
            if msg.phase == END:
                self._supervisor.on_end(actor, (msg.graph, msg.session), msg.result)
                return
            self._st.left.discard(actor)
            reply = (
                self._handshakes.on_join_or_ready(msg, now) if msg.graph or msg.session else None
            )
        if reply is not None:
            self._st.send_quietly(HANDSHAKE_CHANNEL, reply, "handshakes_sent")
