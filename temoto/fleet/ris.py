"""The Resource Info Synchronizer (RIS): which robot serves which resources, and who is alive.

Thesis §7.2, docs/design.md §6, ``docs/ris.md``. One :class:`ResourceInfoSync` runs per robot
(TeMoto instance) on the channel :data:`RIS_CHANNEL`:

``ris_advert_t``
    Every ``period_s`` the robot advertises its manager (the registrar's name) and the servers
    it shares, each with its request type (``"module:QualName"``). Every robot advertises,
    even with no server to share: the advert is also its liveness signal. A robot advertises at
    once when it starts, when :meth:`~ResourceInfoSync.refresh` is called, and when asked.
``ris_request_t``
    Sent once at start: "advertise now", so a robot that joins learns the fleet within one
    round trip instead of one period. Answered at once, or if an answer went out less than
    50 ms (at most a tenth of the period) ago, that much later.
``ris_withdraw_t``
    Sent on :meth:`~ResourceInfoSync.close` (no servers: the robot leaves; its servers are
    forgotten and it is reported lost at once), or to stop offering some servers.

A robot not heard for ``missed`` of *its own* advertised periods is lost: it is forgotten and
reported to the subscribers (:meth:`~ResourceInfoSync.subscribe`); heard again, it joins
again. Every advert carries the sender's *boot id*, new at every start: a robot heard with
another boot id than before restarted, however quickly, and is reported lost ("restarted")
and joined again at once, so a provider releases what its previous start held without waiting
for a silence that never comes. Threads: ``temoto-fleet-ris`` sends the adverts and checks silences;
``temoto-fleet-ris-calls`` runs the subscribers' callbacks, so a slow callback never delays
an advert. Bad messages (undecodable, wrong type for the channel, empty or invalid fields, our
own robot's name from another sender, an older ``seq``) are dropped and counted in
:attr:`~ResourceInfoSync.stats`, never raised.
"""

from __future__ import annotations

import logging
import math
import secrets
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Final, final

from temoto.errors import TransportError
from temoto.fleet.common import CallQueue, Closing, check_name, check_seconds, new
from temoto.fleet.service import ServiceCore
from temoto.lcm_types import ris_advert_t, ris_request_t, ris_server_t, ris_withdraw_t

if TYPE_CHECKING:
    from temoto.clock import Clock
    from temoto.core.registrar import Registrar
    from temoto.transport.auth import Opened
    from temoto.transport.base import Subscription
    from temoto.transport.link import FleetLink

__all__ = ["RIS_CHANNEL", "RIS_STATS", "ResourceInfoSync", "RobotInfo", "ServerInfo"]

logger = logging.getLogger(__name__)

#: Channel of ``ris_advert_t``, ``ris_request_t`` and ``ris_withdraw_t``.
RIS_CHANNEL: Final = "TEMOTO_RIS"

#: The counters of :attr:`ResourceInfoSync.stats`.
RIS_STATS: Final = (
    "adverts_sent",
    "adverts_received",
    "requests_sent",
    "requests_received",
    "withdraws_sent",
    "withdraws_received",
    "decode_errors",  # payloads that codec.decode refused
    "unexpected",  # well-formed but meaningless: wrong type, empty names, our own robot name
    "stale",  # an advert with a lower seq than one already heard from that robot
    "send_errors",  # sends that failed (logged)
    "callback_errors",  # subscriber callbacks that raised (logged)
    "joined",  # robots heard for the first time (or again after being lost)
    "lost",  # robots reported lost (silent, or withdrawn)
    "impostor",  # naming another member than their authenticated sender (dropped)
)

#: The server that forwards requests to other robots is never advertised (it would loop).
REMOTE_SERVER: Final = "remote"

# Bounds on what another robot may claim (a bad advert is dropped, not trusted).
_MAX_PERIOD_MS: Final = 3_600_000
_MAX_ROBOTS: Final = 4096
# Requests are answered at most this often (or every tenth of the period, if shorter).
_ANSWER_GAP_S: Final = 0.05


@dataclass(frozen=True, slots=True)
class ServerInfo:
    """One server a robot offers.

    Attributes:
        name: The server's name in that robot's registrar.
        request_type: Its request class, ``"module:QualName"``.
        offer: What it can provide, as JSON defined by the server ("" for nothing more).
    """

    name: str
    request_type: str
    offer: str = ""


@dataclass(frozen=True, slots=True)
class RobotInfo:
    """What is known of another robot (a snapshot).

    Attributes:
        robot: Its name.
        manager: Its manager (registrar) name, which resource requests address.
        servers: The servers it offers, by name.
        period_s: Its advert period.
        heard: This robot's clock when it was last heard.
        seq: The ``seq`` of its newest advert.
        boot: Its boot id: new at every start of its manager ("" from a sender without).
    """

    robot: str
    manager: str
    servers: dict[str, ServerInfo]
    period_s: float
    heard: float
    seq: int
    boot: str = ""


@dataclass(slots=True, eq=False)
class _Subscriber:
    on_lost: Callable[[RobotInfo, str], None] | None
    on_joined: Callable[[RobotInfo], None] | None
    on_changed: Callable[[RobotInfo], None] | None
    active: bool = True


def type_name(cls: type[Any]) -> str:
    """The ``"module:QualName"`` of a class, as adverts carry request types.

    Args:
        cls: A class.

    Returns:
        Its module and qualified name.
    """
    return f"{cls.__module__}:{cls.__qualname__}"


@final
class ResourceInfoSync(Closing):
    """Advertises this robot's servers and keeps the table of the other robots' (thesis §7.2).

    It subscribes to :data:`RIS_CHANNEL`, starts its threads, asks the fleet to advertise and
    advertises itself at once. :meth:`close` (or leaving the ``with`` block) withdraws, stops
    and joins the threads; the fleet link and its transport stay the caller's to close.

    Args:
        link: Sends and receives authenticated fleet messages.
        registrar: This robot's registrar; its name is the advertised manager name.
        robot: This robot's name in the fleet.
        period_s: Seconds between adverts.
        missed: A robot not heard for this many of its advertised periods is lost.
        share: The servers to advertise (default: every registered server but ``"remote"``,
            looked up at every advert, so servers registered later are advertised too).
        clock: Where time is read: monotonic seconds (silences, periods) and the epoch
            seconds of the first ``seq`` (default: :class:`~temoto.clock.MonotonicClock`).

    Raises:
        ValueError: If ``robot`` is empty, ``period_s`` is not a positive number or
            ``missed`` is less than 1.
        TypeError: If ``clock`` is not a :class:`~temoto.clock.Clock`.
        TransportError: If the link's transport is closed.
    """

    def __init__(
        self,
        link: FleetLink,
        registrar: Registrar,
        robot: str,
        *,
        period_s: float = 1.0,
        missed: int = 3,
        share: Sequence[str] | None = None,
        clock: Clock | None = None,
    ) -> None:
        self._core = core = ServiceCore(link, RIS_STATS, clock)
        self._registrar = registrar
        self._robot = check_name("robot", robot)
        self.manager = check_name("the registrar's name", registrar.name)
        self.period_s = check_seconds("period_s", period_s)
        if isinstance(missed, bool) or not isinstance(missed, int) or missed < 1:
            raise ValueError(f"missed must be an int >= 1, got {missed!r}")
        self.missed = missed
        self._share = None if share is None else tuple(check_name("a server", s) for s in share)
        self._lock = core.lock
        self._wake = core.condition()
        # Guarded by _lock (and core.closed).
        self._robots: dict[str, RobotInfo] = {}
        # robot -> boot id of a start that withdrew as a whole (it shut down): an advert of that
        # start still in flight must not bring it back; a new start has a new boot id
        self._withdrawn: dict[str, str] = {}
        self._subscribers: list[_Subscriber] = []
        self._seq = round(core.wall() * 1e6)
        #: This start's boot id, carried by every advert.
        self.boot = f"{self._seq:x}-{secrets.token_hex(4)}"
        self._offer: tuple[ServerInfo, ...] | None = None
        self._hidden: set[str] = set()  # withdrawn: never advertised again
        self._next_advert = 0.0  # advertise at once
        self._next_answer = -math.inf
        self._calls = CallQueue("temoto-fleet-ris-calls", "a RIS subscriber callback")
        self._sub: Subscription | None = None
        try:
            self._sub = link.listen(RIS_CHANNEL, self._on_message)
        except BaseException:
            self._calls.close()
            raise
        self._timer = threading.Thread(target=self._run_timer, name="temoto-fleet-ris", daemon=True)
        self._timer.start()
        ask = new(ris_request_t)
        ask.requester, ask.manager = self._robot, ""
        self._send(ask, "requests_sent")

    def __repr__(self) -> str:
        state = "closed" if self._core.closed else "open"
        return f"<ResourceInfoSync robot={self._robot!r} manager={self.manager!r} {state}>"

    # --- queries ------------------------------------------------------------------------------

    @property
    def robot(self) -> str:
        """This robot's name."""
        return self._robot

    @property
    def stats(self) -> dict[str, int]:
        """A copy of the counters, one per name in :data:`RIS_STATS`."""
        counts = self._core.stats()
        counts["callback_errors"] += self._calls.errors
        return counts

    def robots(self) -> list[RobotInfo]:
        """The other robots heard and not lost.

        Returns:
            Snapshots, sorted by robot name.
        """
        with self._lock:
            return [self._robots[name] for name in sorted(self._robots)]

    def robot_info(self, robot: str) -> RobotInfo | None:
        """What is known of one robot.

        Args:
            robot: Its name.

        Returns:
            A snapshot, or None if it is not known (never heard, or lost).
        """
        with self._lock:
            return self._robots.get(robot)

    def by_manager(self, manager: str) -> RobotInfo | None:
        """The robot whose manager has this name.

        Args:
            manager: A manager (registrar) name.

        Returns:
            A snapshot, or None if no known robot has that manager.
        """
        with self._lock:
            for info in self._robots.values():
                if info.manager == manager:
                    return info
        return None

    def providers(self, server: str) -> list[str]:
        """The other robots that offer a server.

        Args:
            server: The server's name.

        Returns:
            Robot names, sorted.
        """
        with self._lock:
            return sorted(n for n, info in self._robots.items() if server in info.servers)

    def offered(self) -> list[ServerInfo]:
        """What this robot advertises now.

        Returns:
            The shared servers, sorted by name.
        """
        return list(self._current_offer())

    def subscribe(
        self,
        *,
        on_lost: Callable[[RobotInfo, str], None] | None = None,
        on_joined: Callable[[RobotInfo], None] | None = None,
        on_changed: Callable[[RobotInfo], None] | None = None,
    ) -> Callable[[], None]:
        """Be told when a robot joins (is heard first, or again after being lost) or is lost.

        Callbacks run on the ``temoto-fleet-ris-calls`` thread, in order; they may call this
        object. Robots already known are not reported as joined.

        Args:
            on_lost: Called with the robot's last snapshot and why (``"no adverts for 3
                periods"``, ``"withdrew"``).
            on_joined: Called with the robot's snapshot.
            on_changed: Called with the new snapshot when a known robot's servers change
                (an advert with another offer, or a partial withdrawal).

        Returns:
            A function that ends the subscription (idempotent).
        """
        sub = _Subscriber(on_lost, on_joined, on_changed)
        with self._lock:
            self._subscribers.append(sub)

        def cancel() -> None:
            with self._lock:
                sub.active = False
                if sub in self._subscribers:
                    self._subscribers.remove(sub)

        return cancel

    # --- actions ------------------------------------------------------------------------------

    def refresh(self) -> None:
        """Advertise now (after registering or removing servers).

        A failed send is counted and logged.
        """
        with self._lock:
            self._next_advert = -math.inf
            self._wake.notify()

    def withdraw(self, servers: Sequence[str]) -> None:
        """Tell the fleet that some servers are no longer offered.

        Later adverts leave them out for good.

        Args:
            servers: Server names (at least one; an empty list would withdraw the robot).

        Raises:
            ValueError: If ``servers`` is empty.
        """
        names = [check_name("a server", s) for s in servers]
        if not names:
            raise ValueError("name at least one server (close() withdraws the whole robot)")
        with self._lock:
            self._hidden.update(names)
            self._offer = None  # the next advert has a new seq
        self._send_withdraw(names)

    def close(self) -> None:
        """Withdraw this robot, unsubscribe, stop and join the threads. Idempotent."""
        with self._lock:
            if self._core.closed:
                return
            self._core.closed = True
            self._wake.notify()
        self._send_withdraw([])
        if self._sub is not None:
            self._sub.unsubscribe()
        if self._timer is not threading.current_thread():
            self._timer.join()
        self._calls.close()

    # --- sending ------------------------------------------------------------------------------

    def _current_offer(self) -> tuple[ServerInfo, ...]:
        """The servers to advertise, from the registrar (not locked: it takes its own lock)."""
        names = self._registrar.servers() if self._share is None else list(self._share)
        with self._lock:
            hidden = set(self._hidden)
        offer = []
        for name in sorted(set(names)):
            if name == REMOTE_SERVER or name in hidden:
                continue
            try:
                # the registrar has no public accessor for a server's request type
                server = self._registrar.server(name)
            except LookupError:
                continue  # shared, but not registered (yet)
            offer.append(ServerInfo(name, type_name(server.request_type)))
        return tuple(offer)

    def _advert(self) -> Any:
        offer = self._current_offer()
        with self._lock:
            if offer != self._offer:
                self._offer = offer
                self._seq += 1
            msg = new(ris_advert_t)
            msg.manager, msg.robot, msg.seq = self.manager, self._robot, self._seq
            msg.boot = self.boot
            msg.period_ms = max(1, round(self.period_s * 1000))
        msg.servers = []
        for info in offer:
            item = new(ris_server_t)
            item.name, item.request_type, item.offer = info.name, info.request_type, info.offer
            msg.servers.append(item)
        return msg

    def _send_withdraw(self, servers: list[str]) -> None:
        msg = new(ris_withdraw_t)
        msg.manager, msg.robot, msg.servers = self.manager, self._robot, servers
        self._send(msg, "withdraws_sent")

    def _send(self, msg: Any, counter: str) -> None:
        """Not locked: encode and send; a failure is counted and logged, never raised."""
        try:
            self._core.send(RIS_CHANNEL, msg, counter)
        except (TransportError, ValueError) as err:
            with self._lock:
                closed = self._core.closed
            log = logger.debug if closed else logger.warning
            log("RIS %r: cannot send: %s", self._robot, err)

    # --- the timer thread ---------------------------------------------------------------------

    def _run_timer(self) -> None:
        """Adverts every period; silences checked at every robot's deadline."""
        while True:
            with self._lock:
                if self._core.closed:
                    return
                now = self._core.now()
                due = now >= self._next_advert
                if due:
                    self._next_advert = now + self.period_s
                wake = min(self._next_advert, self._check_silences(now))
                if not due:
                    self._core.wait(self._wake, max(0.0, wake - now))
                    continue
            self._send(self._advert(), "adverts_sent")

    def _check_silences(self, now: float) -> float:
        """Forget and report robots silent for ``missed`` periods; the next deadline. Locked."""
        wake = math.inf
        for name, info in list(self._robots.items()):
            due = info.heard + self.missed * info.period_s
            if now >= due:
                self._lose(name, f"no adverts for {self.missed} periods")
            else:
                wake = min(wake, due)
        return wake

    def _lose(self, robot: str, reason: str) -> None:
        """Forget a robot and report it lost (lock held)."""
        info = self._robots.pop(robot)
        self._core.count("lost")
        logger.info("RIS %r: robot %r was lost: %s", self._robot, robot, reason)
        for sub in list(self._subscribers):
            if sub.on_lost is not None:
                self._schedule(sub, sub.on_lost, info, reason)

    def _changed(self, info: RobotInfo) -> None:
        """Report a robot whose servers changed (lock held)."""
        for sub in list(self._subscribers):
            if sub.on_changed is not None:
                self._schedule(sub, sub.on_changed, info)

    def _schedule(self, sub: _Subscriber, callback: Callable[..., None], *args: Any) -> None:
        def call() -> None:
            with self._lock:
                if not sub.active:
                    return
            callback(*args)

        self._calls.put(call)

    # --- receiving (the transport's thread) ---------------------------------------------------

    def _on_message(self, opened: Opened) -> None:
        handlers = {
            "ris_advert_t": self._on_advert,
            "ris_request_t": self._on_request,
            "ris_withdraw_t": self._on_withdraw,
        }
        msg = self._core.decode(opened, handlers)
        if msg is None:
            return
        # An advert or withdrawal names the robot it is about, a request its requester: only
        # the robot itself may say so (docs/security.md).
        field = "requester" if opened.type == "ris_request_t" else "robot"
        claimed = getattr(msg, field)
        if claimed and not self._core.speaks_as(opened, claimed, field):
            return
        handlers[opened.type](msg)

    def _valid_source(self, robot: Any, manager: Any) -> bool:
        """A robot and manager name another robot may use (lock held; counts if not)."""
        ok = (
            isinstance(robot, str)
            and isinstance(manager, str)
            and bool(robot)
            and bool(manager)
            and robot != self._robot
        )
        if not ok:
            self._core.count("unexpected")
        return ok

    def _on_advert(self, msg: Any) -> None:
        robot: str = msg.robot
        servers: dict[str, ServerInfo] = {}
        for item in msg.servers:
            if not item.name or item.name in servers:
                servers = {}
                break
            servers[item.name] = ServerInfo(item.name, item.request_type, item.offer)
        with self._lock:
            if self._core.closed or not self._valid_source(robot, msg.manager):
                return
            period_ms: int = msg.period_ms
            bad = not 0 < period_ms <= _MAX_PERIOD_MS or len(servers) != len(msg.servers)
            if bad or (robot not in self._robots and len(self._robots) >= _MAX_ROBOTS):
                self._core.count("unexpected")
                return
            old = self._robots.get(robot)
            boot: str = msg.boot
            if self._withdrawn.get(robot) == boot:
                self._core.count("stale")  # sent before its withdraw, heard after it
                return
            self._withdrawn.pop(robot, None)
            if old is not None and boot != old.boot:
                # restarted: what its previous start held goes now, not after a silence
                self._lose(robot, "restarted")
                old = None
            if old is not None and msg.seq < old.seq:
                self._core.count("stale")
                return
            self._core.count("adverts_received")
            info = RobotInfo(
                robot, msg.manager, servers, period_ms / 1000, self._core.now(), msg.seq, boot
            )
            self._robots[robot] = info
            self._wake.notify()  # its silence deadline may be the next one
            if old is not None and old.servers != servers:
                self._changed(info)
            if old is None:
                self._core.count("joined")
                logger.info(
                    "RIS %r: robot %r joined (%d servers)", self._robot, robot, len(info.servers)
                )
                for sub in list(self._subscribers):
                    if sub.on_joined is not None:
                        self._schedule(sub, sub.on_joined, info)

    def _on_request(self, msg: Any) -> None:
        with self._lock:
            if self._core.closed:
                return
            if not msg.requester or msg.requester == self._robot:
                self._core.count("unexpected")
                return
            self._core.count("requests_received")
            if msg.manager not in ("", self.manager):
                return
            # At once, but one answer per gap: a flood of requests gets no flood of adverts.
            answer = max(self._core.now(), self._next_answer)
            if answer < self._next_advert:
                self._next_advert = answer
                self._next_answer = answer + min(self.period_s / 10, _ANSWER_GAP_S)
                self._wake.notify()

    def _on_withdraw(self, msg: Any) -> None:
        robot: str = msg.robot
        with self._lock:
            if self._core.closed or not self._valid_source(robot, msg.manager):
                return
            self._core.count("withdraws_received")
            info = self._robots.get(robot)
            if info is None or info.manager != msg.manager:
                return
            names = [s for s in msg.servers if s]
            if not msg.servers:
                if len(self._withdrawn) >= _MAX_ROBOTS:
                    self._withdrawn.pop(next(iter(self._withdrawn)))
                self._withdrawn[robot] = info.boot
                self._lose(robot, "withdrew")
                return
            left = {n: s for n, s in info.servers.items() if n not in names}
            if left != info.servers:
                info = RobotInfo(
                    robot, info.manager, left, info.period_s, info.heard, info.seq, info.boot
                )
                self._robots[robot] = info
                self._changed(info)
