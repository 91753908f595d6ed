"""What the parts of one :class:`~temoto.fleet.actors.FleetActorLink` share.

Private to :mod:`temoto.fleet.actors`. The link is three parts, each a module: the handshake
(:mod:`temoto.fleet._handshake`), the notification exchange (:mod:`temoto.fleet._notify`) and
the supervision of silences, ends and aborts with the link's two threads
(:mod:`temoto.fleet._supervision`). They share one :class:`LinkState`: the service's
:class:`~temoto.fleet.service.ServiceCore` (lock, counters, sending, clock), the tables of runs
and notifications every part reads, the conditions the parts wake each other with, and the
queue of callbacks. Every table is guarded by the core's lock. This module also holds the
records of those tables (:class:`Run`, :class:`Peer`, :class:`Ended`, :class:`Outgoing`,
:class:`Watch`, ...) and the channels (:data:`HANDSHAKE_CHANNEL`, :data:`NOTIFY_CHANNEL`,
:func:`ack_channel`), which :mod:`temoto.fleet.actors` exports.
"""

from __future__ import annotations

import collections
import enum
import hashlib
import json
import logging
import math
import re
from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Final

from temoto.core.remote import RemoteResult
from temoto.core.states import Result
from temoto.errors import FleetError, TransportError
from temoto.fleet.common import check_name

if TYPE_CHECKING:
    from temoto.fleet.service import ServiceCore
    from temoto.transport.auth import Opened

__all__ = [
    "ACK_CHANNEL_PREFIX",
    "HANDSHAKE_CHANNEL",
    "NOTIFY_CHANNEL",
    "LinkState",
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


JOIN: Final = 1  # handshake_t.JOIN (the generated constants are untyped)
READY: Final = 2
LEAVE: Final = 3
END: Final = 4
PHASES: Final = frozenset((JOIN, READY, LEAVE, END))

SessionKey = tuple[str, str]  # graph, session
NodeKey = tuple[str, str]  # action, actor

# Runs kept only because a peer spoke of them (not started here) beyond this are dropped,
# the least recently heard first: a fleet busy with runs this actor is not part of.
_MAX_STRAY_RUNS = 1024
_WARN_INTERVAL_S = 1.0
# Resends of a JOIN or a notification that brought nothing new slow down, to this many times
# resend_s.
MAX_BACKOFF = 8


def quoted(names: Sequence[str] | set[str]) -> str:
    """Names for a message: ``'a', 'b'``, sorted."""
    return ", ".join(f"'{n}'" for n in sorted(names))


class Phase(enum.Enum):
    """Where this actor is in the handshake of one run."""

    KEPT = "kept"  # not started here: what peers said of it is kept for a later handshake
    JOINING = "joining"  # handshake() is gathering peers
    READY = "ready"  # handshake done: the heard list is frozen; answering late peers


def actors_json(actors: Sequence[str]) -> str:
    """A run's actor list as a handshake carries it: a compact JSON array (sorted by caller)."""
    return json.dumps(list(actors), ensure_ascii=False, separators=(",", ":"))


@dataclass(slots=True)
class Peer:
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
class Notice:
    """A received notification, taken once."""

    id: str
    result: Result
    outputs: dict[str, Any]


@dataclass(slots=True, eq=False)
class Run:
    """Everything the link keeps for one run (graph, session)."""

    graph: str
    session: str
    touched: float  # our clock when a peer last spoke of it (expiry of a kept run)
    local: bool = False  # handshake, expect or notify was called for it here
    phase: Phase = Phase.KEPT
    actors: tuple[str, ...] = ()
    actors_text: str = ""  # actors as a handshake carries them (actors_json)
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
    peers: dict[str, Peer] = field(default_factory=dict)
    warned: set[str] = field(default_factory=set)  # peers whose actor list differs (logged)
    pending: dict[NodeKey, collections.deque[Notice]] = field(default_factory=dict)
    waiters: dict[NodeKey, collections.deque[Waiter]] = field(default_factory=dict)
    seen: set[str] = field(default_factory=set)  # notification ids taken
    ended_peers: dict[str, str] = field(default_factory=dict)  # peer -> result it ended with
    left_peers: set[str] = field(default_factory=set)  # peers that gave the run up (LEAVE)
    left_reasons: dict[str, str] = field(default_factory=dict)  # peer -> why it aborted


@dataclass(slots=True, eq=False)
class Waiter:
    """One :meth:`FleetActorLink.expect`."""

    run: Run
    key: NodeKey
    on_result: RemoteResult
    active: bool = True


@dataclass(slots=True)
class Ended:
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
    out_key: SessionKey | None = None  # (graph, run id) the decision is said for
    next_answer: float = 0.0  # answers to heartbeats of peers still in the run: rate-limited
    # Peers that still spoke of the run after it ended here, by time.monotonic(): a
    # notification (they wait for our acknowledgement) or a heartbeat of it (our END or LEAVE
    # has not reached them); a peer's END or LEAVE removes it. Closing the link waits
    # while they keep speaking (FleetActorLink._linger).
    speaking: dict[str, float] = field(default_factory=dict)
    # The run id agreed in the handshake: READY answers to late JOINs carry it, or a peer that
    # completes with one would agree on its own proposal and never hear our END under it.
    run_id: str = ""


@dataclass(slots=True, eq=False)
class Outgoing:
    """A notification waiting for acknowledgements."""

    key: SessionKey
    waiting: set[str]
    started: float
    aborted: str | None = None
    lost: tuple[str, str] | None = None  # (actor, why) when an actor waited for is gone


@dataclass(slots=True, eq=False)
class Watch:
    """One :meth:`FleetActorLink.watch`."""

    actors: set[str]
    on_lost: Callable[[str, str], None]
    started: float
    key: SessionKey | None = None  # the run watched for (END of a peer takes it off)
    on_end: Callable[[str, Result], None] | None = None
    on_abort: Callable[[str, str], None] | None = None
    aborts: set[tuple[str, str]] = field(default_factory=set)  # (actor, reason) reported
    reported: set[str] = field(default_factory=set)
    active: bool = True


class LinkState:
    """The state the parts of one link share; every table is guarded by ``core.lock``.

    Args:
        core: The link's lock, counters, sending and clock.
        actor: This actor's name.
        resend_s: Period of handshake and notification resends.
        silence_s: A watched actor not heard for this long is lost.
        grace_s: How long an ended run is still answered for.
        stray_s: How long a run never started here is kept.
        heartbeat_s: Period of the READY heartbeats.
    """

    def __init__(
        self,
        core: ServiceCore,
        actor: str,
        *,
        resend_s: float,
        silence_s: float,
        grace_s: float,
        stray_s: float,
        heartbeat_s: float,
    ) -> None:
        self.core = core
        self.lock = core.lock
        self.actor = actor
        self.resend_s = resend_s
        self.silence_s = silence_s
        self.grace_s = grace_s
        self.stray_s = stray_s
        self.heartbeat_s = heartbeat_s
        self.changed = core.condition()  # handshake() and notify() wait on it
        self.timer_wake = core.condition()  # the timer thread waits on it
        self.calls_ready = core.condition()  # the callback thread waits on it
        # All below guarded by the lock.
        self.runs: dict[SessionKey, Run] = {}
        self.ended: dict[SessionKey, Ended] = {}
        self.outgoing: dict[str, Outgoing] = {}
        self.watches: list[Watch] = []
        self.heard_at: dict[str, float] = {}  # actor -> our clock when last heard (anything)
        self.left: set[str] = set()  # actors that left the fleet and were not heard since
        self.calls: collections.deque[Callable[[], None]] = collections.deque()
        self.next_heartbeat = 0.0
        self.next_warning = 0.0

    def check_open(self) -> None:
        """Raise FleetError if the link is closed. Lock held."""
        if self.core.closed:
            raise FleetError("the fleet link is closed")

    def new_run(self, key: SessionKey, now: float) -> Run:
        """Start keeping a run (the least recently heard stray run makes room). Lock held."""
        stray = [r for r in self.runs.values() if not r.local]
        if len(stray) >= _MAX_STRAY_RUNS:
            oldest = min(stray, key=lambda r: r.touched)
            del self.runs[(oldest.graph, oldest.session)]
        run = Run(key[0], key[1], now)
        self.runs[key] = run
        self.timer_wake.notify()  # it expires unless started here
        return run

    def distinct_runs(self) -> list[Run]:
        """Every run once (a run whose handshake is done is kept under two keys). Lock held."""
        return list({id(r): r for r in self.runs.values()}.values())

    def schedule(self, call: Callable[[], None]) -> None:
        """Queue a callback for the callback thread. Lock held."""
        self.calls.append(call)
        self.calls_ready.notify()

    def gone(self, actor: str, now: float) -> bool:
        """Whether a peer is gone: it left, or was heard once but not for ``silence_s``.

        Lock held.
        """
        heard = self.heard_at.get(actor)
        return actor in self.left or (heard is not None and now - heard >= self.silence_s)

    def why_gone(self, actor: str) -> str:
        """Why :meth:`gone` says so, for a message. Lock held."""
        return "left" if actor in self.left else f"not heard for {self.silence_s:g} s"

    def decode(self, opened: Opened, types: Collection[str]) -> Any:
        """The inner message, or None (counted) if it cannot be decoded or is not expected."""
        return self.core.decode(opened, types)

    def send(self, channel: str, msg: Any, counter: str) -> None:
        """Not locked: encode and send; FleetError if it cannot be sent."""
        try:
            self.core.send(channel, msg, counter)
        except (TransportError, ValueError) as err:
            raise FleetError(f"cannot send on {channel}: {err}") from err

    def send_quietly(self, channel: str, msg: Any, counter: str) -> None:
        """Not locked: send from the link's threads; a failure is counted and logged."""
        try:
            self.send(channel, msg, counter)
        except FleetError as err:
            now = self.core.now()
            with self.lock:
                warn = now >= self.next_warning and not self.core.closed
                if warn:
                    self.next_warning = now + _WARN_INTERVAL_S
            if warn:
                logger.warning("actor %r: %s", self.actor, err)
            else:
                logger.debug("actor %r: %s", self.actor, err)
