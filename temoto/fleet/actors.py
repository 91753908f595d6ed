"""The engine's link to the other actors of shared graphs, over the fleet transport.

:class:`FleetActorLink` implements :class:`temoto.core.remote.ActorLink` (REFERENCE §2.14,
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
    ``grace_s`` after it. A ``JOIN`` of a run this actor has not started yet is kept (a peer
    may start earlier), for ``stray_s`` at most.

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
"""

from __future__ import annotations

import collections
import enum
import hashlib
import itertools
import json
import logging
import math
import re
import secrets
import struct
import threading
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Final, final

from temoto.clock import Clock
from temoto.core.remote import ActorLostError, Cancel, RemoteResult
from temoto.core.states import Result
from temoto.errors import FleetError, StateError, TransportError
from temoto.fleet.common import Closing, check_name, check_seconds, new
from temoto.fleet.service import ServiceCore
from temoto.lcm_types import action_ack_t, action_notification_t, handshake_t
from temoto.transport.auth import FleetLink, Opened
from temoto.transport.base import Subscription

__all__ = [
    "ACK_CHANNEL_PREFIX",
    "HANDSHAKE_CHANNEL",
    "NOTIFY_CHANNEL",
    "STATS",
    "FleetActorLink",
    "ack_channel",
]

logger = logging.getLogger(__name__)

#: Channel of ``handshake_t``: handshakes, heartbeats, leaving.
HANDSHAKE_CHANNEL: Final = "TEMOTO_HANDSHAKE"
#: Channel of ``action_notification_t``.
NOTIFY_CHANNEL: Final = "TEMOTO_NOTIFY"
#: The channels of ``action_ack_t``: this prefix and the notification sender (:func:`ack_channel`).
ACK_CHANNEL_PREFIX: Final = "TEMOTO_ACK_"
# What an actor name may be to name its acknowledgement channel as it is (else it is hashed).
_PLAIN_NAME = re.compile(r"[A-Za-z0-9_.:-]{1,40}")

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
)

_JOIN: Final = 1  # handshake_t.JOIN (the generated constants are untyped)
_READY: Final = 2
_LEAVE: Final = 3
_END: Final = 4
_PHASES: Final = frozenset((_JOIN, _READY, _LEAVE, _END))
# Deliveries a busy subscription keeps while the handlers catch up (LCM keeps 30 by default
# and drops the rest silently: a burst of notifications and heartbeats must not be lost).
_QUEUE_CAPACITY: Final = 1024

_SessionKey = tuple[str, str]  # graph, session
_NodeKey = tuple[str, str]  # action, actor

# Runs kept only because a peer spoke of them (not started here) beyond this are dropped,
# the least recently heard first: a fleet busy with runs this actor is not part of.
_MAX_STRAY_RUNS = 1024
_WARN_INTERVAL_S = 1.0
# A JOIN that answers newly heard peers waits this share of resend_s for more of them, so a
# fleet that starts at once exchanges a few JOINs per actor, not one per pair; READY answers
# to late JOINs are as rare.
_ANSWER_WINDOW = 0.25
# ... except the first few JOINs of a handshake, which answer at once.
_ANSWERS_AT_ONCE = 3
# Resends of a JOIN or a notification that brought nothing new slow down, to this many times
# resend_s.
_MAX_BACKOFF = 8
# A handshake of more actors than this sends its JOINs (and READY answers) at most every
# resend_s * actors / _ACTORS_PER_PERIOD: every JOIN is decoded by every other actor, so the
# whole fleet sends about as many JOINs per second as this many actors would, and the work
# of each actor per second does not grow with the fleet (50 actors: a JOIN every 0.5 s).
_ACTORS_PER_PERIOD = 10


def ack_channel(actor: str) -> str:
    """The channel on which ``actor`` receives the acknowledgements of its notifications.

    ``TEMOTO_ACK_<actor>`` for a name of at most 40 characters from ``A-Z a-z 0-9 _ . : -``;
    otherwise ``TEMOTO_ACK_`` and 16 hex digits of the name's BLAKE2b hash (a channel name is
    at most 63 characters). Two actors that share a channel only handle each other's
    acknowledgements too.

    Args:
        actor: The notifying actor's name.

    Returns:
        The channel name.

    Raises:
        ValueError: If ``actor`` is empty.
    """
    check_name("actor", actor)
    if _PLAIN_NAME.fullmatch(actor):
        return ACK_CHANNEL_PREFIX + actor
    return ACK_CHANNEL_PREFIX + hashlib.blake2b(actor.encode(), digest_size=8).hexdigest()


def _names(names: Sequence[str] | set[str]) -> str:
    return ", ".join(f"'{n}'" for n in sorted(names))


class _Phase(enum.Enum):
    """Where this actor is in the handshake of one run."""

    KEPT = "kept"  # not started here: what peers said of it is kept for a later handshake
    JOINING = "joining"  # handshake() is gathering peers
    READY = "ready"  # handshake done: the heard list is frozen; answering late peers


def _actors_text(actors: Sequence[str]) -> str:
    """A run's actor list as a handshake carries it: a compact JSON array (sorted by caller)."""
    return json.dumps(list(actors), ensure_ascii=False, separators=(",", ":"))


@dataclass(slots=True)
class _Peer:
    """What one peer said in its newest handshake of a run.

    ``stamps`` is its heard list by place in its actor list (``actors``, as sent); the list is
    parsed only when it differs from this actor's (:meth:`names`), so a report of a 50-actor
    run costs a few field reads, not 100 (see handshake_t.lcm).
    """

    stamp: int
    phase: int
    actors: str  # its actor list, as sent (JSON)
    stamps: tuple[int, ...]  # the stamps it heard, by place in its actor list; 0: not heard
    run_id: str = ""  # its proposal (JOIN) or the run id it agreed on (READY)
    full: bool = False  # it heard every actor of its list
    parsed: tuple[str, ...] | None = None  # its actor list, once parsed

    def names(self) -> tuple[str, ...]:
        """Its actor list (empty if it is not a JSON array of strings)."""
        if self.parsed is None:
            try:
                value = json.loads(self.actors) if self.actors else []
            except (ValueError, RecursionError):
                value = None
            ok = isinstance(value, list) and all(isinstance(a, str) for a in value)
            self.parsed = tuple(value) if ok and value is not None else ()
        return self.parsed

    def heard(self) -> dict[str, int]:
        """The actors it heard, with the stamp it echoes for each."""
        names = self.names()
        if len(names) != len(self.stamps):
            return {}
        return {a: t for a, t in zip(names, self.stamps, strict=True) if t > 0}


@dataclass(slots=True, eq=False)
class _Notice:
    """A received notification, taken once."""

    id: str
    result: Result
    outputs: dict[str, Any]


@dataclass(slots=True, eq=False)
class _Run:
    """Everything the link keeps for one run (graph, session)."""

    graph: str
    session: str
    touched: float  # our clock when a peer last spoke of it (expiry of a kept run)
    local: bool = False  # handshake, expect or notify was called for it here
    phase: _Phase = _Phase.KEPT
    actors: tuple[str, ...] = ()
    actors_text: str = ""  # actors as a handshake carries them (_actors_text)
    me: int = 0  # this actor's place in actors
    first_stamp: int = 0  # the stamp of the first JOIN of the current handshake call
    proposal: str = ""  # this actor's run id proposal in the current handshake call
    answer_at: float | None = None  # when to send the JOIN that answers newly heard peers
    last_join: float = -math.inf  # our clock when the newest JOIN went out
    joins: int = 0  # JOINs sent by the current handshake call
    next_ready_reply: float = 0.0  # READY answers to late JOINs: at most one per window
    run_id: str = ""  # the run id agreed on (once READY); the run is also kept under it
    frozen: dict[str, int] = field(default_factory=dict)  # our heard list once READY
    aborted: str | None = None  # why the running handshake must fail
    peers: dict[str, _Peer] = field(default_factory=dict)
    warned: set[str] = field(default_factory=set)  # peers whose actor list differs (logged)
    pending: dict[_NodeKey, collections.deque[_Notice]] = field(default_factory=dict)
    waiters: dict[_NodeKey, collections.deque[_Waiter]] = field(default_factory=dict)
    seen: set[str] = field(default_factory=set)  # notification ids taken
    ended_peers: dict[str, str] = field(default_factory=dict)  # peer -> result it ended with
    left_peers: set[str] = field(default_factory=set)  # peers that gave the run up (LEAVE)
    left_reasons: dict[str, str] = field(default_factory=dict)  # peer -> why it aborted


@dataclass(slots=True, eq=False)
class _Waiter:
    """One :meth:`FleetActorLink.expect`."""

    run: _Run
    key: _NodeKey
    on_result: RemoteResult
    active: bool = True


@dataclass(slots=True)
class _Ended:
    """What is kept of an ended run for ``grace_s``."""

    actors: tuple[str, ...]
    heard: dict[str, int] | None  # the frozen heard list, if the handshake had completed
    seen: set[str]  # notification ids taken: late resends stay duplicates
    until: float
    # (END or LEAVE, result, reason) said here: said again when the link closes, and to
    # peers still speaking of the run
    decision: tuple[int, str, str] | None = None
    decided: float = 0.0  # our clock when the decision was (last) made: repeated for silence_s
    next_repeat: float = 0.0
    out_key: _SessionKey | None = None  # (graph, run id) the decision is said for
    next_answer: float = 0.0  # answers to heartbeats of peers still in the run: rate-limited


@dataclass(slots=True, eq=False)
class _Outgoing:
    """A notification waiting for acknowledgements."""

    key: _SessionKey
    waiting: set[str]
    started: float
    aborted: str | None = None
    lost: tuple[str, str] | None = None  # (actor, why) when an actor waited for is gone


@dataclass(slots=True, eq=False)
class _Watch:
    """One :meth:`FleetActorLink.watch`."""

    actors: set[str]
    on_lost: Callable[[str, str], None]
    started: float
    key: _SessionKey | None = None  # the run watched for (END of a peer takes it off)
    on_end: Callable[[str, Result], None] | None = None
    on_abort: Callable[[str, str], None] | None = None
    aborts: set[tuple[str, str]] = field(default_factory=set)  # (actor, reason) reported
    reported: set[str] = field(default_factory=set)
    active: bool = True


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
        resend_s: Period of handshake and notification resends.
        silence_s: After this long without a message a watched actor is lost.
        grace_s: How long an ended run is still answered for.
        stray_s: How long a run never started here is kept.
        linger_s: How long :meth:`close` keeps answering after runs that just finished.
        heartbeat_s: Period of the READY heartbeats: ``5 * resend_s``, at most a third of
            ``silence_s``.

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
        self._core = core = ServiceCore(link, STATS, clock)
        self._link = link
        self._actor = check_name("actor", actor)
        self.resend_s = check_seconds("resend_s", resend_s)
        self.silence_s = check_seconds("silence_s", silence_s)
        self.grace_s = check_seconds("grace_s", grace_s, zero=True)
        self.stray_s = check_seconds("stray_s", stray_s)
        self.linger_s = check_seconds("linger_s", linger_s, zero=True)
        self.heartbeat_s = min(5 * self.resend_s, self.silence_s / 3)
        self._lock = core.lock
        self._changed = core.condition()  # handshake() and notify() wait on it
        self._timer_wake = core.condition()
        self._calls_ready = core.condition()
        # All below guarded by _lock.
        self._runs: dict[_SessionKey, _Run] = {}
        self._ended: dict[_SessionKey, _Ended] = {}
        self._outgoing: dict[str, _Outgoing] = {}
        self._watches: list[_Watch] = []
        self._heard_at: dict[str, float] = {}  # actor -> our clock when last heard (anything)
        self._left: set[str] = set()  # actors that left the fleet and were not heard since
        self._calls: collections.deque[Callable[[], None]] = collections.deque()
        self._ids = itertools.count(1)
        self._boot = f"{round(core.wall() * 1000):x}"  # keeps ids unique across restarts
        self._last_stamp = 0
        self._next_heartbeat = 0.0
        self._next_warning = 0.0
        self._subs: list[Subscription] = []
        try:
            for channel, handler in (
                (HANDSHAKE_CHANNEL, self._on_handshake),
                (NOTIFY_CHANNEL, self._on_notify),
                (ack_channel(self._actor), self._on_ack),
            ):
                self._subs.append(link.listen(channel, handler, queue_capacity=_QUEUE_CAPACITY))
        except BaseException:
            for sub in self._subs:
                sub.unsubscribe()
            raise
        self._timer = threading.Thread(
            target=self._run_timer, name="temoto-fleet-actors", daemon=True
        )
        self._caller = threading.Thread(
            target=self._run_calls, name="temoto-fleet-actors-calls", daemon=True
        )
        self._timer.start()
        self._caller.start()

    def __repr__(self) -> str:
        state = "closed" if self._core.closed else "open"
        return f"<FleetActorLink actor={self._actor!r} {state} on {self._link!r}>"

    # --- ActorLink ----------------------------------------------------------------------------

    @property
    def actor(self) -> str:
        """This engine's actor name."""
        return self._actor

    @property
    def stats(self) -> dict[str, int]:
        """A copy of the counters, one per name in :data:`STATS`."""
        return self._core.stats()

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
        check_name("graph", graph)
        check_name("session", session)
        timeout = check_seconds("timeout", timeout, zero=True)
        participants = tuple(sorted({check_name("an actor", a) for a in actors}))
        if self._actor not in participants:
            raise ValueError(f"actors {list(participants)} do not include this actor")
        if len(participants) == 1:
            return session
        key = (graph, session)
        with self._lock:
            self._check_open()
            now = self._core.now()
            run = self._runs.get(key)
            if run is not None and run.phase is _Phase.JOINING:
                raise StateError(f"a handshake of graph '{graph}' session '{session}' is running")
            if run is None:
                run = self._new_run(key, now)
            ended = self._ended.pop(key, None)
            if ended is not None:
                run.seen |= ended.seen
            run.local = True
            run.actors = participants
            run.actors_text = _actors_text(participants)
            run.me = participants.index(self._actor)
            run.phase = _Phase.JOINING
            run.proposal = f"{session}@{secrets.token_hex(6)}"
            run.joins = 0
            run.run_id = ""
            # what peers said of an earlier run of this session does not stand for this one
            run.ended_peers.clear()
            run.left_reasons.clear()
            run.aborted = None
            run.frozen = {}
            msg = self._join_msg(run)
            run.first_stamp = msg.stamp_us
        deadline = now + timeout
        ready: Any = None
        gap = self._gap(run)  # the least time between two JOINs
        period = gap  # doubles while a resend brings nothing new (to _MAX_BACKOFF)
        longest = max(gap, _MAX_BACKOFF * self.resend_s)
        unheard = math.inf  # reports missing at the last resend
        try:
            while ready is None:
                self._send(HANDSHAKE_CHANNEL, msg, "handshakes_sent")
                run.last_join = self._core.now()
                run.joins += 1
                next_send = run.last_join + period
                with self._lock:
                    while True:
                        self._check_joining(run)
                        missing = self._unheard(run)
                        if not missing:
                            run.phase = _Phase.READY
                            run.frozen = {p: peer.stamp for p, peer in run.peers.items()}
                            self._agree(run)
                            ready = self._ready_msg(run)
                            # READY goes out now: the next heartbeat can wait a period
                            self._next_heartbeat = self._core.now() + self.heartbeat_s
                            self._timer_wake.notify()
                            break
                        now = self._core.now()
                        if now >= deadline:
                            raise FleetError(
                                f"handshake of graph '{graph}' session '{session}' with "
                                f"{_names(participants)} timed out after {timeout:g} s: "
                                + self._status(run)
                            )
                        answer = run.answer_at
                        if answer is not None and now >= answer:  # newly heard peers
                            run.answer_at = None
                            msg = self._join_msg(run)
                            break
                        if now >= next_send:
                            slower = missing >= unheard and period < longest
                            period = min(period * 2, longest) if slower else gap
                            unheard = missing
                            msg = self._join_msg(run)
                            break
                        wake = min(next_send, deadline, math.inf if answer is None else answer)
                        self._core.wait(self._changed, wake - now)
        except BaseException:
            self._give_up(run)
            raise
        self._send_quietly(HANDSHAKE_CHANNEL, ready, "handshakes_sent")
        return run.run_id

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
        check_name("graph", graph)
        check_name("session", session)
        check_name("action", action)
        timeout = check_seconds("timeout", timeout, zero=True)
        if not isinstance(result, Result):
            raise ValueError(f"result must be a Result, got {result!r}")
        others = {check_name("an actor", a) for a in actors} - {self._actor}
        try:
            text = json.dumps(dict(outputs), sort_keys=True, separators=(",", ":"))
        except (TypeError, ValueError, RecursionError) as err:
            raise FleetError(f"the outputs of {action} are not JSON-ready: {err}") from err
        if not outputs:
            text = ""
        key = (graph, session)
        with self._lock:
            run = self._runs.get(key)
            left: set[str] = set()
            if run is not None:
                others -= set(run.ended_peers)  # finished there: they need nothing more
                left = run.left_peers
            gone = sorted(a for a in others if a in left or self._gone(a, self._core.now()))
        if gone:
            why = "left" if gone[0] in left else self._why_gone(gone[0])
            raise ActorLostError(
                f"{action} ({result.value}) of graph '{graph}' session '{session}': "
                + ", ".join(f"actor '{a}' was lost ({self._why_gone(a)})" for a in gone),
                actor=gone[0],
                why=why,
            )
        if not others:
            return
        msg = new(action_notification_t)
        msg.graph, msg.session, msg.action, msg.actor = graph, session, action, self._actor
        msg.result, msg.outputs = result.value, text
        with self._lock:
            self._check_open()
            serial = f"{self._boot}.{next(self._ids)}"
            msg.notification_id = f"{self._actor}/{graph}/{session}/{action}/{serial}"
            out = _Outgoing(key, set(others), self._core.now())
            self._outgoing[msg.notification_id] = out
            self._timer_wake.notify()  # it watches the silence of the actors waited for
        deadline = self._core.now() + timeout
        period = self.resend_s  # doubles with every copy (to _MAX_BACKOFF * resend_s)
        waiting = len(out.waiting)
        try:
            while True:
                self._send(NOTIFY_CHANNEL, msg, "notifications_sent")
                next_send = self._core.now() + period
                with self._lock:
                    while out.waiting:
                        if self._core.closed:
                            raise FleetError("the fleet link is closed")
                        if out.aborted is not None:
                            text = (
                                f"{action} ({result.value}) of graph '{graph}' session "
                                f"'{session}': {out.aborted} before {_names(out.waiting)} "
                                "acknowledged it"
                            )
                            if out.lost is not None:
                                raise ActorLostError(text, actor=out.lost[0], why=out.lost[1])
                            raise FleetError(text)
                        now = self._core.now()
                        if now >= deadline:
                            raise FleetError(
                                f"{action} ({result.value}) of graph '{graph}' session "
                                f"'{session}' was not acknowledged by {_names(out.waiting)} "
                                f"within {timeout:g} s"
                            )
                        if now >= next_send:
                            if len(out.waiting) < waiting:
                                # acknowledgements still coming in (a loaded fleet answers
                                # slowly): no copy yet, look again a resend_s later
                                waiting = len(out.waiting)
                                period = self.resend_s
                                next_send = now + period
                                continue
                            # a period without any acknowledgement: send again, later next time
                            period = min(period * 2, _MAX_BACKOFF * self.resend_s)
                            break
                        self._core.wait(self._changed, min(next_send, deadline) - now)
                    else:
                        return
        finally:
            with self._lock:
                self._outgoing.pop(msg.notification_id, None)

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
        key = (check_name("graph", graph), check_name("session", session))
        node = (check_name("action", action), check_name("actor", actor))
        with self._lock:
            self._check_open()
            run = self._runs.get(key)
            if run is None:
                run = self._new_run(key, self._core.now())
            run.local = True
            waiter = _Waiter(run, node, on_result)
            pending = run.pending.get(node)
            if pending:
                notice = pending.popleft()
                if not pending:
                    del run.pending[node]
                self._schedule_delivery(waiter, notice)
            else:
                run.waiters.setdefault(node, collections.deque()).append(waiter)

        def cancel() -> None:
            with self._lock:
                waiter.active = False
                waiters = run.waiters.get(node)
                if waiters is not None and waiter in waiters:
                    waiters.remove(waiter)
                    if not waiters:
                        del run.waiters[node]

        return cancel

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
        names = {check_name("an actor", a) for a in actors} - {self._actor}
        key = (graph, session) if graph or session else None
        with self._lock:
            self._check_open()
            run = self._runs.get(key) if key is not None else None
            watch = _Watch(names, on_lost, self._core.now(), key, on_end, on_abort)
            self._watches.append(watch)
            if run is not None:
                for actor, result in sorted(run.ended_peers.items()):
                    self._report_end(watch, actor, result)
                for actor, reason in sorted(run.left_reasons.items()):
                    self._report_abort(watch, actor, reason)
            for actor in sorted(names & self._left):
                self._report_lost(watch, actor, "left")
            self._timer_wake.notify()

        def cancel() -> None:
            with self._lock:
                watch.active = False
                if watch in self._watches:
                    self._watches.remove(watch)
                    self._timer_wake.notify()

        return cancel

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
        with self._lock:
            now = self._core.now()
            run = self._runs.pop(key, None)
            if run is not None:
                for other in ((run.graph, run.session), (run.graph, run.run_id)):
                    if self._runs.get(other) is run:
                        del self._runs[other]  # the same run under its other key
            ended = self._ended.get(key)
            if run is None and ended is not None and ended.decision is not None:
                # a new word on a run that ended here: an abort's reason, or a result taken
                # from a peer while the abort settled
                if gave_up:
                    ended.decision = (_LEAVE, "", reason)
                elif result is not None:
                    ended.decision = (_END, result.value, "")
                ended.decided, ended.next_repeat = now, now + self.resend_s
                if not self._core.closed:
                    leave = self._decision_msg(ended.out_key or key, ended.actors, ended.decision)
            finished = run is not None and not gave_up and run.phase is _Phase.READY
            if run is not None and (gave_up or finished):
                if gave_up:
                    decision = (_LEAVE, "", reason)
                else:
                    decision = (_END, "" if result is None else result.value, "")
                if not self._core.closed:
                    leave = self._decision_msg(key, run.actors, decision)
            if run is not None:
                for waiters in run.waiters.values():
                    for waiter in waiters:
                        waiter.active = False
                run.aborted = "the run was ended"
                done = run.phase is _Phase.READY
                if done or run.seen:
                    kept = _Ended(
                        run.actors,
                        run.frozen if done else None,
                        run.seen,
                        now + self.grace_s,
                        decision if done else None,
                        now,
                        now + self.resend_s,
                        key,
                    )
                    self._ended[key] = kept
                    self._ended[(run.graph, run.session)] = kept  # late JOINs name the session
            for out in self._outgoing.values():
                if out.key == key:
                    out.aborted = "the run was ended"
            self._changed.notify_all()
            self._timer_wake.notify()
        if leave is not None:
            self._send_quietly(HANDSHAKE_CHANNEL, leave, "handshakes_sent")

    def close(self) -> None:
        """Stop the link: LEAVE the active runs, unsubscribe, stop and join the threads.

        Waiting calls fail with FleetError; callbacks not run yet are dropped. Idempotent.
        """
        self._linger()
        with self._lock:
            if self._core.closed:
                return
            self._core.closed = True
            active = [r for r in self._distinct_runs() if r.local and r.phase is not _Phase.KEPT]
            leaves = [self._leave_msg(r.graph, r.session, r.actors) for r in active]
            self._calls.clear()
            self._changed.notify_all()
            self._timer_wake.notify()
            self._calls_ready.notify()
        for msg in leaves:
            self._send_quietly(HANDSHAKE_CHANNEL, msg, "handshakes_sent")
        for sub in self._subs:
            sub.unsubscribe()
        for thread in (self._timer, self._caller):
            if thread is not threading.current_thread():
                thread.join()

    def _linger(self) -> None:
        """Before closing: repeat END or LEAVE for runs that just ended here; keep answering.

        For ``linger_s``, so a peer whose last notification we acknowledged (an
        acknowledgement that may have been lost) is not left resending to nobody.
        """
        with self._lock:
            if self._core.closed:
                return
            now = self._core.now()
            ends = [
                self._decision_msg(key, e.actors, e.decision)
                for key, e in self._ended.items()
                if e.decision is not None and e.until > now and e.out_key in (None, key)
            ]
        if not ends or self.linger_s <= 0:
            return
        deadline = self._core.now() + self.linger_s
        while True:
            for msg in ends:
                self._send_quietly(HANDSHAKE_CHANNEL, msg, "handshakes_sent")
            remaining = deadline - self._core.now()
            if remaining <= 0:
                return
            with self._lock:
                self._core.wait(self._changed, min(self.resend_s, remaining))

    # --- receiving (the transport's thread) ---------------------------------------------------

    def _decode(self, opened: Opened, types: tuple[str, ...]) -> Any:
        """The inner message, or None (counted) if it cannot be decoded or is not expected."""
        return self._core.decode(opened, types)

    def _on_handshake(self, opened: Opened) -> None:
        msg = self._decode(opened, ("handshake_t",))
        if msg is None:
            return
        actor: str = msg.actor
        with self._lock:
            if self._core.closed:
                return
            if not actor or actor == self._actor or msg.phase not in _PHASES:
                self._core.count("unexpected")
                return
            self._core.count("handshakes_received")
            now = self._core.now()
            self._heard_at[actor] = now
            if msg.phase == _LEAVE:
                self._on_leave(actor, msg.graph, msg.session, msg.reason)
                return
            if msg.phase == _END:
                self._on_end(actor, (msg.graph, msg.session), msg.result)
                return
            self._left.discard(actor)
            reply = self._on_join_or_ready(msg, now) if msg.graph or msg.session else None
        if reply is not None:
            self._send_quietly(HANDSHAKE_CHANNEL, reply, "handshakes_sent")

    def _on_join_or_ready(self, msg: Any, now: float) -> Any:
        """Record a JOIN or READY of a run; the answer to send, if any. Lock held."""
        key: _SessionKey = (msg.graph, msg.session)
        actor: str = msg.actor
        run = self._runs.get(key)
        reply: Any = None
        if run is None or not run.local:
            ended = self._ended.get(key)
            known = ended is not None and actor in ended.actors
            if (
                known
                and msg.phase == _READY
                and ended is not None
                and ended.decision is not None
                and now >= ended.next_answer
            ):
                # a peer still in a run that ended here: tell it again how (END may be lost);
                # one answer per heartbeat period reaches every peer
                reply = self._decision_msg(ended.out_key or key, ended.actors, ended.decision)
                ended.next_answer = now + self.heartbeat_s / 2
            elif known and msg.phase == _JOIN and ended is not None and ended.heard is not None:
                reply = self._handshake_msg(_READY, *key, ended.actors, ended.heard)
            if msg.phase != _JOIN:
                return reply  # a READY of a run not started here: liveness only
            if run is None:
                run = self._new_run(key, now)
        if msg.phase == _READY and not msg.heard:
            return reply  # a heartbeat: liveness only; the peer's full READY still stands
        raw: bytes = msg.heard
        if len(raw) % 8:
            self._core.count("unexpected")  # not whole stamps
            return reply
        run.touched = now
        peer = run.peers.get(actor)
        first = peer is None
        rejoined = False
        if peer is None or msg.stamp_us > peer.stamp:
            rejoined = peer is not None and msg.phase == _JOIN and peer.phase != _JOIN
            stamps: tuple[int, ...] = struct.unpack(f">{len(raw) // 8}q", raw)
            full = bool(stamps) and min(stamps) > 0
            run.peers[actor] = _Peer(msg.stamp_us, msg.phase, msg.actors, stamps, msg.run_id, full)
        if run.phase is _Phase.JOINING:
            if actor in run.actors:
                self._check_same_actors(run, actor)
                if (first or rejoined) and run.answer_at is None:
                    # answered by the handshake's thread: the first few JOINs at once (a small
                    # fleet is done in a round trip or two), later ones with every peer heard
                    # meanwhile, and never sooner than a resend period after the last JOIN
                    run.answer_at = (
                        now
                        if run.joins < _ANSWERS_AT_ONCE
                        else max(
                            now + self.resend_s * _ANSWER_WINDOW, run.last_join + self._gap(run)
                        )
                    )
            self._changed.notify_all()
        elif (
            run.phase is _Phase.READY
            and msg.phase == _JOIN
            and actor in run.actors
            and now >= run.next_ready_reply  # one READY answers every late peer
        ):
            reply = self._ready_msg(run)
            run.next_ready_reply = now + self._gap(run)
        return reply

    def _on_leave(self, actor: str, graph: str, session: str, reason: str = "") -> None:
        """A peer gave up a run (or, with no graph and session, left the fleet). Lock held."""
        fleet = not graph and not session
        if fleet:
            self._left.add(actor)
            runs = self._distinct_runs()
        else:
            run = self._runs.get((graph, session))
            if run is None and reason and (graph, session) not in self._ended:
                run = self._new_run((graph, session), self._core.now())  # kept for a later watch
            runs = [] if run is None else [run]
        lost = fleet
        for run in runs:
            run.left_peers.add(actor)
            if reason and not fleet:
                run.left_reasons[actor] = reason
            if run.phase is not _Phase.JOINING:
                run.peers.pop(actor, None)  # kept: its JOIN no longer stands
            if not run.local or actor not in run.actors:
                continue
            if run.phase is _Phase.JOINING:
                run.aborted = f"'{actor}' {'left the fleet' if fleet else 'gave up'}"
                self._changed.notify_all()
            elif run.phase is _Phase.READY:
                lost = True
        why = "left the fleet" if fleet else "gave up the run"
        for out in self._outgoing.values():  # it will not acknowledge: do not wait for it
            if actor in out.waiting and (fleet or out.key == (graph, session)):
                out.aborted = f"'{actor}' {why}"
                out.lost = (actor, "left")
                self._changed.notify_all()
        for watch in self._watches:
            if reason and not fleet and watch.key == (graph, session):
                self._report_abort(watch, actor, reason)  # also once the run ended here
            elif lost:
                self._report_lost(watch, actor, "left")

    def _on_end(self, actor: str, key: _SessionKey, result: str = "") -> None:
        """A peer's run finished: stop waiting for it in that run, take its result. Lock held."""
        run = self._runs.get(key)
        if run is None and key not in self._ended:
            run = self._new_run(key, self._core.now())  # kept for a watch of a run not started yet
        if run is not None:
            run.ended_peers.setdefault(actor, result)
        for out in self._outgoing.values():
            if out.key == key and actor in out.waiting:
                out.waiting.discard(actor)  # it needs nothing more of this run
                self._changed.notify_all()
        for watch in self._watches:
            if watch.key == key:
                self._report_end(watch, actor, result)

    def _report_end(self, watch: _Watch, actor: str, result: str) -> None:
        """A watched peer's run finished with ``result``: stop watching it, tell. Lock held."""
        if not watch.active or actor not in watch.actors:
            return
        watch.actors.discard(actor)
        on_end = watch.on_end
        if on_end is None:
            return
        try:
            taken = Result(result)
        except ValueError:
            logger.warning("actor %r: END of %r with unknown result %r", self._actor, actor, result)
            return

        def call() -> None:
            with self._lock:
                if not watch.active:
                    return
            on_end(actor, taken)

        self._calls.append(call)
        self._calls_ready.notify()

    def _report_abort(self, watch: _Watch, actor: str, reason: str) -> None:
        """A watched peer aborted the run with ``reason``. Lock held."""
        on_abort = watch.on_abort
        if on_abort is None:
            self._report_lost(watch, actor, "left")
            return
        if not watch.active or (actor, reason) in watch.aborts:
            return
        watch.aborts.add((actor, reason))
        self._core.count("lost")

        def call() -> None:
            with self._lock:
                if not watch.active:
                    return
            on_abort(actor, reason)

        self._calls.append(call)
        self._calls_ready.notify()

    def _gone(self, actor: str, now: float) -> bool:
        """Whether a peer is gone: it left, or was heard once but not for ``silence_s``.

        Lock held.
        """
        heard = self._heard_at.get(actor)
        return actor in self._left or (heard is not None and now - heard >= self.silence_s)

    def _why_gone(self, actor: str) -> str:
        return "left" if actor in self._left else f"not heard for {self.silence_s:g} s"

    def _on_ack(self, opened: Opened) -> None:
        """An acknowledgement on this actor's :func:`ack_channel`."""
        msg = self._decode(opened, ("action_ack_t",))
        if msg is None:
            return
        actor: str = msg.actor
        with self._lock:
            if self._core.closed or not actor or actor == self._actor:
                return
            self._core.count("acks_received")
            self._heard_at[actor] = self._core.now()
            out = self._outgoing.get(msg.notification_id)
            if out is not None and actor in out.waiting:
                out.waiting.discard(actor)
                if not out.waiting:
                    self._changed.notify_all()

    def _on_notify(self, opened: Opened) -> None:
        msg = self._decode(opened, ("action_notification_t",))
        if msg is None:
            return
        actor: str = msg.actor
        with self._lock:
            if self._core.closed:
                return
            if not actor or actor == self._actor or not msg.notification_id:
                self._core.count("unexpected")
                return
            self._core.count("notifications_received")
            # Taken (its delivery queued) before the acknowledgement leaves: the sender's END,
            # which may follow the acknowledgement at once, is then handled after it.
            self._take(msg)
        ack = new(action_ack_t)
        ack.notification_id, ack.graph, ack.session = msg.notification_id, msg.graph, msg.session
        ack.actor = self._actor
        self._send_quietly(ack_channel(actor), ack, "acks_sent")

    def _take(self, msg: Any) -> None:
        """Store or deliver a notification unless it is a duplicate. Lock held."""
        if self._core.closed:
            return
        now = self._core.now()
        self._heard_at[msg.actor] = now
        key: _SessionKey = (msg.graph, msg.session)
        nid: str = msg.notification_id
        ended = self._ended.get(key)
        run = self._runs.get(key)
        if (run is not None and nid in run.seen) or (ended is not None and nid in ended.seen):
            self._core.count("duplicates")
            return
        if run is None:
            run = self._new_run(key, now)
        run.touched = now
        run.seen.add(nid)
        self._route(run, (msg.action, msg.actor), self._parse(msg))

    def _parse(self, msg: Any) -> _Notice:
        """Turn a notification into a notice; a bad result or outputs becomes an ERROR."""
        where = f"notification {msg.notification_id!r}"
        try:
            result = Result(msg.result)
        except ValueError:
            logger.warning("%s: unknown result %r, taken as on_error", where, msg.result)
            result = Result.ERROR
        outputs: Any = {}
        if msg.outputs:
            try:
                outputs = json.loads(msg.outputs)
            except (ValueError, RecursionError) as err:
                outputs = None
                logger.warning("%s: the outputs are not JSON (%s), taken as on_error", where, err)
            if not isinstance(outputs, dict):
                if outputs is not None:
                    logger.warning("%s: the outputs are not an object, taken as on_error", where)
                result, outputs = Result.ERROR, {}
        return _Notice(msg.notification_id, result, outputs)

    # --- the link's threads -------------------------------------------------------------------

    def _run_timer(self) -> None:
        """Heartbeats, silence checks, expiry of kept state."""
        while True:
            with self._lock:
                if self._core.closed:
                    return
                now = self._core.now()
                wake = math.inf
                ready = [r for r in self._distinct_runs() if r.local and r.phase is _Phase.READY]
                graced = any(e.heard is not None for e in self._ended.values())
                msgs: list[Any] = []
                if ready or graced or self._watches:
                    if now >= self._next_heartbeat:
                        msgs = [
                            self._heartbeat_msg(r) if self._all_ready(r) else self._ready_msg(r)
                            for r in ready
                        ]
                        if not msgs:
                            msgs.append(self._handshake_msg(_READY, "", "", (), None))
                        self._next_heartbeat = now + self.heartbeat_s
                    wake = self._next_heartbeat
                else:
                    self._next_heartbeat = now
                wake = min(wake, self._check_silences(now), self._expire(now))
                repeats, due = self._repeats(now)
                msgs += repeats
                wake = min(wake, due)
                if not msgs:
                    self._core.wait(
                        self._timer_wake, None if wake == math.inf else max(0.0, wake - now)
                    )
                    continue
            for msg in msgs:
                self._send_quietly(HANDSHAKE_CHANNEL, msg, "handshakes_sent")

    def _repeats(self, now: float) -> tuple[list[Any], float]:
        """The LEAVEs to say again, and when next to look. Lock held.

        Each is said every ``resend_s`` for ``silence_s`` after the abort: a peer that aborted
        the run too (settling there) no longer sends heartbeats of it to answer.
        """
        msgs: list[Any] = []
        wake = math.inf
        for key, ended in self._ended.items():
            if ended.decision is None or ended.decision[0] != _LEAVE:
                continue  # an END is answered to the heartbeats of peers still in the run
            if now >= ended.decided + self.silence_s:
                continue
            if ended.out_key not in (None, key):
                continue  # the same run under its session's name: said under its run id
            if now >= ended.next_repeat:
                msgs.append(self._decision_msg(key, ended.actors, ended.decision))
                ended.next_repeat = now + self.resend_s
            wake = min(wake, ended.next_repeat)
        return msgs, wake

    def _check_silences(self, now: float) -> float:
        """Report silent watched actors; fail notifications waiting for silent actors.

        Returns when the next may fall silent. Lock held.
        """
        wake = math.inf
        for out in self._outgoing.values():
            if out.aborted is not None:
                continue
            for actor in sorted(out.waiting):
                due = max(self._heard_at.get(actor, -math.inf), out.started) + self.silence_s
                if now >= due:
                    out.aborted = f"'{actor}' was not heard for {self.silence_s:g} s"
                    out.lost = (actor, f"not heard for {self.silence_s:g} s")
                    self._changed.notify_all()
                    break
                wake = min(wake, due)
        for watch in self._watches:
            for actor in watch.actors - watch.reported:
                due = max(self._heard_at.get(actor, -math.inf), watch.started) + self.silence_s
                if now >= due:
                    self._report_lost(watch, actor, f"not heard for {self.silence_s:g} s")
                else:
                    wake = min(wake, due)
        return wake

    def _expire(self, now: float) -> float:
        """Drop ended runs after their grace and stray runs; when next to look. Lock held."""
        wake = math.inf
        for key, ended in list(self._ended.items()):
            if now >= ended.until:
                del self._ended[key]
            else:
                wake = min(wake, ended.until)
        for key, run in list(self._runs.items()):
            if not run.local:
                due = run.touched + self.stray_s
                if now >= due:
                    del self._runs[key]
                else:
                    wake = min(wake, due)
        return wake

    def _run_calls(self) -> None:
        """Run the callbacks, in order."""
        while True:
            with self._lock:
                while not self._calls and not self._core.closed:
                    self._calls_ready.wait()
                if self._core.closed:
                    return
                call = self._calls.popleft()
            try:
                call()
            except Exception:
                with self._lock:
                    self._core.count("callback_errors")
                logger.exception("actor %r: a fleet callback raised", self._actor)

    # --- internals (lock held unless said otherwise) ------------------------------------------

    def _check_open(self) -> None:
        if self._core.closed:
            raise FleetError("the fleet link is closed")

    def _check_joining(self, run: _Run) -> None:
        """Raise if the running handshake of ``run`` cannot go on."""
        self._check_open()
        if run.aborted is not None:
            status = self._status(run)
            raise FleetError(
                f"handshake of graph '{run.graph}' session '{run.session}': {run.aborted}"
                + (f"; {status}" if status else "")
            )

    def _new_run(self, key: _SessionKey, now: float) -> _Run:
        stray = [r for r in self._runs.values() if not r.local]
        if len(stray) >= _MAX_STRAY_RUNS:
            oldest = min(stray, key=lambda r: r.touched)
            del self._runs[(oldest.graph, oldest.session)]
        run = _Run(key[0], key[1], now)
        self._runs[key] = run
        self._timer_wake.notify()  # it expires unless started here
        return run

    def _gap(self, run: _Run) -> float:
        """The least time between two JOINs (or READY answers) of ``run``.

        See ``_ACTORS_PER_PERIOD``.
        """
        return self.resend_s * max(1.0, len(run.actors) / _ACTORS_PER_PERIOD)

    def _report_done(self, run: _Run, actor: str, report: _Peer) -> bool:
        """Whether ``actor``'s newest report says it heard every other participant.

        This actor must be heard with a stamp of the current handshake call. Lock held.
        """
        if report.actors == run.actors_text:  # the same list: read the stamps by place
            stamps = report.stamps
            return (
                report.full and len(stamps) == len(run.actors) and stamps[run.me] >= run.first_stamp
            )
        heard = report.heard()
        for b in run.actors:
            if b != actor and heard.get(b, 0) < (run.first_stamp if b == self._actor else 1):
                return False
        return True

    def _unheard(self, run: _Run) -> int:
        """How many participants are not heard, or have no complete report, here.

        0: the handshake is done. Lock held.
        """
        count = 0
        for actor in run.actors:
            if actor == self._actor:
                continue
            report = run.peers.get(actor)
            if report is None or not self._report_done(run, actor, report):
                count += 1
        return count

    def _missing(self, run: _Run) -> dict[str, list[str]]:
        """Who has not (yet, freshly) been heard by whom: heard actor -> hearers."""
        me = self._actor
        missing: dict[str, list[str]] = {}
        for a in run.actors:
            report = run.peers.get(a)
            heard = {} if report is None else report.heard()
            for b in run.actors:
                if a == b:
                    continue
                if a == me:
                    ok = b in run.peers
                elif report is None:
                    ok = False
                elif b == me:
                    ok = heard.get(me, -1) >= run.first_stamp
                else:
                    ok = b in heard
                if not ok:
                    missing.setdefault(b, []).append(a)
        return missing

    def _status(self, run: _Run) -> str:
        """Why the handshake of ``run`` is not done yet, for an error message."""
        silent = [a for a in run.actors if a != self._actor and a not in run.peers]
        parts = []
        if silent:
            parts.append(f"no answer from {_names(silent)}")
        unheard = []
        for b, hearers in sorted(self._missing(run).items()):
            shown = [h for h in hearers if h not in silent]
            if shown:
                unheard.append(f"'{b}' by {_names(shown)}")
        if unheard:
            parts.append("not heard: " + ", ".join(unheard))
        for actor in sorted(run.warned):
            peer = run.peers.get(actor)
            if peer is not None:
                parts.append(f"'{actor}' lists the actors {list(peer.names())}")
        return "; ".join(parts)

    def _check_same_actors(self, run: _Run, actor: str) -> None:
        peer = run.peers.get(actor)
        if peer is None or actor in run.warned or peer.actors == run.actors_text:
            return
        if set(peer.names()) == set(run.actors):
            return
        run.warned.add(actor)
        logger.warning(
            "handshake of graph '%s' session '%s': '%s' lists the actors %s, this actor %s",
            run.graph,
            run.session,
            actor,
            list(peer.names()),
            list(run.actors),
        )

    def _give_up(self, run: _Run) -> None:
        """Not locked: a handshake failed; forget the run's handshake and LEAVE it."""
        key = (run.graph, run.session)
        with self._lock:
            if self._runs.get(key) is not run or run.phase is not _Phase.JOINING:
                return
            del self._runs[key]
            if run.seen:
                self._ended[key] = _Ended(
                    run.actors, None, run.seen, self._core.now() + self.grace_s
                )
            leave = (
                None if self._core.closed else self._leave_msg(run.graph, run.session, run.actors)
            )
        if leave is not None:
            self._send_quietly(HANDSHAKE_CHANNEL, leave, "handshakes_sent")

    def _route(self, run: _Run, node: _NodeKey, notice: _Notice, *, front: bool = False) -> None:
        """Give a notice to the oldest waiter of ``node``, or keep it for the next one."""
        waiters = run.waiters.get(node)
        while waiters:
            waiter = waiters.popleft()
            if not waiters:
                del run.waiters[node]
            if waiter.active:
                self._schedule_delivery(waiter, notice)
                return
        pending = run.pending.setdefault(node, collections.deque())
        if front:
            pending.appendleft(notice)
        else:
            pending.append(notice)

    def _schedule_delivery(self, waiter: _Waiter, notice: _Notice) -> None:
        def deliver() -> None:
            with self._lock:
                if not waiter.active:  # cancelled meanwhile: keep the notice for the next
                    run = waiter.run
                    if self._runs.get((run.graph, run.session)) is run:
                        self._route(run, waiter.key, notice, front=True)
                    return
                waiter.active = False
            waiter.on_result(notice.result, notice.outputs)

        self._calls.append(deliver)
        self._calls_ready.notify()

    def _report_lost(self, watch: _Watch, actor: str, reason: str) -> None:
        if not watch.active or actor not in watch.actors or actor in watch.reported:
            return
        watch.reported.add(actor)
        self._core.count("lost")

        def call() -> None:
            with self._lock:
                if not watch.active:
                    return
            watch.on_lost(actor, reason)

        self._calls.append(call)
        self._calls_ready.notify()

    def _stamp(self) -> int:
        """A handshake stamp: the wall clock in microseconds, strictly increasing."""
        self._last_stamp = max(self._last_stamp + 1, round(self._core.wall() * 1e6))
        return self._last_stamp

    def _handshake_msg(
        self,
        phase: int,
        graph: str,
        session: str,
        actors: Sequence[str],
        heard: Mapping[str, int] | None,
    ) -> Any:
        """A handshake_t; ``heard`` (None: no heard list) is written by place in ``actors``."""
        msg = new(handshake_t)
        msg.phase, msg.graph, msg.session, msg.actor = phase, graph, session, self._actor
        msg.stamp_us = self._stamp()
        msg.result, msg.reason, msg.run_id = "", "", ""
        msg.actors = _actors_text(actors) if actors else ""
        if heard is not None and actors:  # by place; this actor's place: this message's stamp
            own = {self._actor: msg.stamp_us}
            stamps = [own.get(a) or heard.get(a, 0) for a in actors]
            msg.heard = struct.pack(f">{len(stamps)}q", *stamps)
        else:
            msg.heard = b""
        return msg

    def _join_msg(self, run: _Run) -> Any:
        heard = {p: peer.stamp for p, peer in run.peers.items()}
        msg = self._handshake_msg(_JOIN, run.graph, run.session, run.actors, heard)
        msg.run_id = run.proposal
        return msg

    def _ready_msg(self, run: _Run) -> Any:
        msg = self._handshake_msg(_READY, run.graph, run.session, run.actors, run.frozen)
        msg.run_id = run.run_id
        return msg

    def _all_ready(self, run: _Run) -> bool:
        """Whether every other participant said READY (with its lists) in this run. Lock held.

        Until then the heartbeats of ``run`` are full READYs: a peer still in its handshake
        completes with one even if this actor's first READY was lost and it dies before
        answering a JOIN.
        """
        for actor in run.actors:
            if actor != self._actor:
                peer = run.peers.get(actor)
                if peer is None or peer.phase != _READY:
                    return False
        return True

    def _heartbeat_msg(self, run: _Run) -> Any:
        """A READY of ``run`` without the actor and heard lists: liveness, and "still in it".

        The first READY and the answers to late JOINs carry the lists; a heartbeat need not
        (decoding a 50-actor heard list 50 times a period was most of a fleet's work).
        """
        msg = self._handshake_msg(_READY, run.graph, run.session, (), None)
        msg.run_id = run.run_id
        return msg

    def _distinct_runs(self) -> list[_Run]:
        """Every run once (a run whose handshake is done is kept under two keys). Lock held."""
        return list({id(r): r for r in self._runs.values()}.values())

    def _agree(self, run: _Run) -> None:
        """The handshake of ``run`` is done: agree on its run id. Lock held.

        The run id is the smallest proposal; the run is kept under it too, with what peers
        that ran ahead already said under it.
        """
        proposals = [run.proposal]
        for actor in run.actors:
            peer = run.peers.get(actor)
            if peer is not None and peer.run_id:
                proposals.append(peer.run_id)
        run.run_id = min(proposals)
        key = (run.graph, run.run_id)
        early = self._runs.get(key)
        if early is not None and early is not run:  # peers that ran ahead spoke of it already
            for node, notices in early.pending.items():
                run.pending.setdefault(node, collections.deque()).extend(notices)
            run.seen |= early.seen
            for actor, result in early.ended_peers.items():
                run.ended_peers.setdefault(actor, result)
            run.left_reasons.update(early.left_reasons)
            run.left_peers |= early.left_peers
        self._runs[key] = run

    def _leave_msg(self, graph: str, session: str, actors: Sequence[str]) -> Any:
        return self._handshake_msg(_LEAVE, graph, session, actors, None)

    def _decision_msg(
        self, key: _SessionKey, actors: Sequence[str], decision: tuple[int, str, str]
    ) -> Any:
        """END with the run's result, or LEAVE with the abort's reason."""
        phase, result, reason = decision
        msg = self._handshake_msg(phase, key[0], key[1], actors, None)
        msg.result, msg.reason = result, reason
        return msg

    def _send(self, channel: str, msg: Any, counter: str) -> None:
        """Not locked: encode and send; FleetError if it cannot be sent."""
        try:
            self._core.send(channel, msg, counter)
        except (TransportError, ValueError) as err:
            raise FleetError(f"cannot send on {channel}: {err}") from err

    def _send_quietly(self, channel: str, msg: Any, counter: str) -> None:
        """Not locked: send from the link's threads; a failure is counted and logged."""
        try:
            self._send(channel, msg, counter)
        except FleetError as err:
            now = self._core.now()
            with self._lock:
                warn = now >= self._next_warning and not self._core.closed
                if warn:
                    self._next_warning = now + _WARN_INTERVAL_S
            if warn:
                logger.warning("actor %r: %s", self._actor, err)
            else:
                logger.debug("actor %r: %s", self._actor, err)
