"""The Context Manager's fleet synchronisation: the protocol on :data:`CONTEXT_CHANNEL`.

:class:`ContextSync` is the part of :class:`~temoto.managers.context.manager.ContextManager`
that keeps its tree equal to the other robots' (the messages are described in
:mod:`~temoto.managers.context.manager`): it publishes local changes and whole trees (in chunks),
sends a digest every ``period_s``, answers requests for the tree (at most every
``_ANSWER_GAP_S``), asks a robot whose digest stayed different for two digests in a row,
expires tombstones, and merges what it receives by version. It runs the ``temoto-context``
thread and the link's receive handler; bad messages are counted, never raised. The manager
owns the tree, the lock, the counters, the store and the listeners; this class reaches them
through the attributes declared below and the two hooks :meth:`ContextSync._persist` and
:meth:`ContextSync._notify`.
"""

from __future__ import annotations

import logging
import math
import threading
from abc import ABC, abstractmethod
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, Final

from temoto.clock import Clock
from temoto.errors import TransportError
from temoto.fleet.common import SpeakerCheck, decode_or_count, new
from temoto.lcm_types import context_digest_t, context_request_t, context_update_t
from temoto.managers.context._wire import chunks, from_wire
from temoto.managers.context.tree import ContextTree, Record
from temoto.transport import codec

if TYPE_CHECKING:
    from temoto.transport.auth import Opened
    from temoto.transport.base import Subscription
    from temoto.transport.link import FleetLink

__all__ = ["CONTEXT_CHANNEL", "ContextSync"]

logger = logging.getLogger(__name__)

#: Channel of ``context_update_t``, ``context_request_t`` and ``context_digest_t``.
CONTEXT_CHANNEL: Final = "TEMOTO_CONTEXT"

_TYPES: Final = ("context_update_t", "context_request_t", "context_digest_t")
# Requests for our tree are answered at most this often (a flood gets no flood of trees).
_ANSWER_GAP_S: Final = 0.05
_MAX_PERIOD_MS: Final = 3_600_000


class ContextSync(ABC):
    """Keeps a Context Manager's tree equal to the fleet's (see the module docstring)."""

    # The manager's state this class uses (set by ContextManager.__init__ before
    # _init_sync); _tree, _counts and _closed are guarded by _lock.
    _robot: str
    _clock: Clock
    _lock: threading.Lock
    _wake: threading.Condition
    _tree: ContextTree
    _counts: dict[str, int]
    _closed: bool
    period_s: float
    tombstone_s: float

    def _init_sync(self, link: FleetLink | None) -> None:
        """Set up the synchronisation's own state (nothing runs yet)."""
        self._link = link
        self._answer: set[str] = set()  # robots waiting for our tree ("" for everyone)
        self._next_answer = -math.inf
        self._ask: set[str] = set()  # robots whose tree we want
        self._asked: dict[str, float] = {}  # robot -> when we last asked it
        self._mismatch: dict[str, int] = {}  # robot -> digests in a row that differed
        self._refused_senders: set[str] = set()  # members warned about (world.publish)
        self._speaks_as = SpeakerCheck("context")
        self._next_digest = -math.inf
        self._sub: Subscription | None = None
        self._timer: threading.Thread | None = None

    def _start_sync(self, queue_capacity: int) -> None:
        """Listen on the link, start the timer thread and ask every robot for its tree."""
        if self._link is None:
            return
        self._sub = self._link.listen(
            CONTEXT_CHANNEL, self._on_message, queue_capacity=queue_capacity
        )
        self._timer = threading.Thread(target=self._run_timer, name="temoto-context", daemon=True)
        self._timer.start()
        ask = new(context_request_t)
        ask.requester, ask.target = self._robot, ""
        self._send(ask, "requests_sent")

    def _stop_sync(self) -> None:
        """Stop listening and join the timer thread (after ``_closed`` was set and notified)."""
        if self._sub is not None:
            self._sub.unsubscribe()
        if self._timer is not None and self._timer is not threading.current_thread():
            self._timer.join()

    @abstractmethod
    def _persist(self, records: Sequence[Record]) -> None:
        """Write records the tree took to the store (lock held)."""

    @abstractmethod
    def _notify(self, names: tuple[str, ...], robot: str) -> None:
        """Tell the listeners that items changed (lock not held)."""

    # ================================================================ sending

    def _publish(self, records: Sequence[Record], requester: str, counter: str) -> None:
        if self._link is None:
            return
        parts = list(chunks(records))
        for index, part in enumerate(parts):
            msg = new(context_update_t)
            msg.robot, msg.requester = self._robot, requester
            msg.chunk, msg.chunks, msg.items = index, len(parts), part
            self._send(msg, counter)

    def _send(self, msg: Any, counter: str) -> None:
        """Encode and send; a failure is counted and logged, never raised (lock not held)."""
        assert self._link is not None
        try:
            name, payload = codec.encode(msg)
            self._link.send(CONTEXT_CHANNEL, name, payload)
        except (TransportError, ValueError) as err:
            with self._lock:
                self._counts["send_errors"] += 1
                closed = self._closed
            (logger.debug if closed else logger.warning)(
                "context %r: cannot send: %s", self._robot, err
            )
            return
        with self._lock:
            self._counts[counter] += 1

    def _run_timer(self) -> None:
        """Digests every period, state answers and requests when due, tombstone expiry."""
        while True:
            with self._lock:
                if self._closed:
                    return
                now = self._clock.monotonic()
                expired = self._tree.expire(now - self.tombstone_s)
                self._counts["tombstones_expired"] += expired
                digest = None
                if now >= self._next_digest:
                    self._next_digest = now + self.period_s
                    digest = self._tree.digest()
                answer: list[Record] | None = None
                to = ""
                if self._answer and now >= self._next_answer:
                    to = next(iter(self._answer)) if len(self._answer) == 1 else "*"
                    self._answer.clear()
                    self._next_answer = now + min(_ANSWER_GAP_S, self.period_s / 10)
                    answer = self._tree.records()
                ask, self._ask = sorted(self._ask), set()
                if digest is None and answer is None and not ask:
                    wake = self._next_digest
                    if self._answer:
                        wake = min(wake, self._next_answer)
                    self._clock.wait(self._wake, max(0.0, wake - now))
                    continue
            for robot in ask:
                msg = new(context_request_t)
                msg.requester, msg.target = self._robot, robot
                self._send(msg, "requests_sent")
            if answer is not None:
                self._publish(answer, to, "states_sent")
            if digest is not None:
                msg = new(context_digest_t)
                msg.robot, (msg.count, value) = self._robot, digest
                msg.digest = value - (1 << 64) if value >= 1 << 63 else value
                msg.period_ms = max(1, round(self.period_s * 1000))
                self._send(msg, "digests_sent")

    # ================================================================ receiving

    def _on_message(self, opened: Opened) -> None:
        msg = decode_or_count(opened, _TYPES, self._counts, self._lock)
        if msg is None:
            return
        # An update or digest names the robot it comes from, a request its requester: only
        # that robot may say so (docs/security.md).
        field = "requester" if opened.type == "context_request_t" else "robot"
        claimed = getattr(msg, field)
        if claimed and not self._speaks_as(opened, claimed, field, self._counts, self._lock):
            return
        if opened.type == "context_update_t":
            if self._refused(opened.sender):
                return
            self._on_update(msg)
        elif opened.type == "context_request_t":
            self._on_request(msg)
        else:
            self._on_digest(msg)

    def _refused(self, sender: str) -> bool:
        """Whether the fleet policy denies ``sender`` changing this robot's world model.

        The policy's ``world.publish`` on this robot (docs/security.md); a refusal is counted
        and logged at WARNING, once per sender (a refused member keeps publishing every period).
        """
        assert self._link is not None
        refusal = self._link.auth.refusal(sender, "world.publish", self._robot)
        if refusal is None:
            return False
        with self._lock:
            self._counts["updates_refused"] += 1
            first = sender not in self._refused_senders
            self._refused_senders.add(sender)
        if first:
            logger.warning("context: changes from %r ignored: %s", sender, refusal)
        return True

    def _foreign(self, robot: Any) -> bool:
        """Whether a sender name is another robot's (lock held; counts if not)."""
        ok = isinstance(robot, str) and bool(robot) and robot != self._robot
        if not ok:
            self._counts["unexpected"] += 1
        return ok

    def _on_update(self, msg: Any) -> None:
        records: list[Record] = []
        invalid = 0
        for wire in msg.items:
            try:
                records.append(from_wire(wire))
            except (ValueError, TypeError) as err:
                invalid += 1
                logger.debug("context: dropped a record from %r: %s", msg.robot, err)
        applied: list[Record] = []
        with self._lock:
            if self._closed or not self._foreign(msg.robot):
                return
            self._counts["updates_received"] += 1
            self._counts["records_invalid"] += invalid
            now = self._clock.monotonic()
            for record in records:
                if self._tree.merge(record, now):
                    applied.append(record)
            self._counts["records_applied"] += len(applied)
            self._counts["records_stale"] += len(records) - len(applied)
            self._persist(applied)
        self._notify(tuple(r.name for r in applied), msg.robot)

    def _on_request(self, msg: Any) -> None:
        with self._lock:
            if self._closed or not self._foreign(msg.requester):
                return
            self._counts["requests_received"] += 1
            if msg.target not in ("", self._robot):
                return
            self._answer.add(msg.requester)
            self._wake.notify_all()

    def _on_digest(self, msg: Any) -> None:
        with self._lock:
            if self._closed or not self._foreign(msg.robot):
                return
            if not 0 < msg.period_ms <= _MAX_PERIOD_MS or msg.count < 0:
                self._counts["unexpected"] += 1
                return
            self._counts["digests_received"] += 1
            count, value = self._tree.digest()
            if (count, value) == (msg.count, msg.digest & ((1 << 64) - 1)):
                self._mismatch.pop(msg.robot, None)
                return
            self._counts["digest_mismatches"] += 1
            # A change may be on its way: ask only if the difference lasts a whole period.
            seen = self._mismatch[msg.robot] = self._mismatch.get(msg.robot, 0) + 1
            now = self._clock.monotonic()
            if seen >= 2 and now >= self._asked.get(msg.robot, -math.inf) + self.period_s / 2:
                self._asked[msg.robot] = now
                self._mismatch.pop(msg.robot, None)
                self._ask.add(msg.robot)
                self._wake.notify_all()
