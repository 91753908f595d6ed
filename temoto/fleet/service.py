"""The state that the parts of one fleet service share: :class:`ServiceCore`.

A fleet service (the actor link, the RIS, remote resources) is a public object whose work is
done by a few parts, each a concept of its own: the remote-resources service is a consumer
side and a provider side; the actor link is a handshake, a notification exchange and a
supervisor of silences. The parts do not reach into each other or into the public object;
what they have in common is one :class:`ServiceCore`:

``lock``
    The one lock of the service. Every other mutable field of the service and of its parts is
    guarded by it, and the conditions the parts wait on are made on it (:meth:`condition`),
    so a part that changes state can wake the threads of another.
``closed``
    Set (under the lock) when the service closes; every part checks it.
counters
    The service's ``stats``: :meth:`count` (lock held) and :meth:`stats` (a copy).
``send``
    :meth:`send` encodes a message and sends it on a channel of the link, counting it (or
    the failure, as ``send_errors``). It raises what the link or the codec raise; how a
    failure is reported (an error to the caller, a warning, a debug line) is the service's
    choice, so the services keep their own loggers and log lines.
``clock``
    A :class:`~temoto.clock.Clock`: :meth:`now` (monotonic seconds: deadlines, periods,
    silences), :meth:`wall` (epoch seconds: stamps, boot ids) and :meth:`wait` (a condition
    wait measured on the clock, so a :class:`~temoto.clock.ManualClock` drives the service's
    timers in tests and :meth:`~temoto.clock.ManualClock.advance` wakes them).

Order of locks: a part never calls the link, the codec, the registrar or a user callback while
it holds ``lock``; the link may deliver on its own thread at any time.
"""

from __future__ import annotations

import threading
from collections.abc import Collection, Iterable
from typing import TYPE_CHECKING, Any, final

from temoto.clock import Clock, MonotonicClock
from temoto.errors import TransportError
from temoto.fleet.common import SpeakerCheck, check_clock, decode_or_count
from temoto.transport import codec

if TYPE_CHECKING:
    from temoto.transport.auth import Opened
from temoto.transport.link import FleetLink

__all__ = ["ServiceCore"]


@final
class ServiceCore:
    """The lock, counters, sending and clock of one fleet service (module docstring).

    Args:
        link: Sends and receives the service's authenticated messages.
        counters: The names of the service's counters. ``send_errors``, ``decode_errors``
            and ``unexpected`` are counted here by :meth:`send` and :meth:`decode`, so a
            service that uses those lists them.
        clock: Where time is read (default: :class:`~temoto.clock.MonotonicClock`).

    Attributes:
        link: The fleet link.
        clock: The clock.
        lock: The service's lock.
        closed: Whether the service is closed (read and set with ``lock`` held).

    Raises:
        TypeError: If ``clock`` is not a :class:`~temoto.clock.Clock`.
    """

    __slots__ = ("_counts", "_speaker", "clock", "closed", "link", "lock")

    def __init__(
        self, link: FleetLink, counters: Iterable[str], clock: Clock | None = None
    ) -> None:
        self.link = link
        self.clock: Clock = MonotonicClock() if clock is None else check_clock("clock", clock)
        self.lock = threading.Lock()
        self.closed = False
        self._counts = dict.fromkeys(counters, 0)
        self._speaker = SpeakerCheck("fleet")

    def __repr__(self) -> str:
        return f"<ServiceCore {'closed' if self.closed else 'open'} on {self.link!r}>"

    # --- the lock ---------------------------------------------------------------------------

    def condition(self) -> threading.Condition:
        """A new condition on :attr:`lock` (for one kind of waiter).

        Returns:
            The condition.
        """
        return threading.Condition(self.lock)

    # --- counters ---------------------------------------------------------------------------

    def count(self, name: str, n: int = 1) -> None:
        """Add to a counter. The caller holds :attr:`lock`.

        Args:
            name: One of the service's counters.
            n: How much.

        Raises:
            KeyError: If ``name`` is not one of the counters.
        """
        self._counts[name] += n

    def stats(self) -> dict[str, int]:
        """A copy of the counters (the lock is taken).

        Returns:
            Counter name to value.
        """
        with self.lock:
            return dict(self._counts)

    # --- time -------------------------------------------------------------------------------

    def now(self) -> float:
        """Monotonic seconds of the clock.

        Returns:
            The reading.
        """
        return self.clock.monotonic()

    def wall(self) -> float:
        """Seconds since the epoch, of the clock.

        Returns:
            The reading.
        """
        return self.clock.time()

    def wait(self, cond: threading.Condition, seconds: float | None) -> bool:
        """Wait on a condition of :attr:`lock` (held) for clock seconds.

        Args:
            cond: A condition made by :meth:`condition`.
            seconds: Clock seconds, or None to wait until notified.

        Returns:
            False if the time passed.
        """
        return self.clock.wait(cond, seconds)

    # --- messages ---------------------------------------------------------------------------

    def send(self, channel: str, msg: Any, counter: str) -> None:
        """Encode and send a message; count it under ``counter``. Not locked.

        Args:
            channel: The channel.
            msg: A generated LCM message.
            counter: The counter of successful sends.

        Raises:
            TransportError: The link could not send it (counted as ``send_errors``).
            ValueError: It could not be encoded (counted as ``send_errors``).
        """
        try:
            name, payload = codec.encode(msg)
            self.link.send(channel, name, payload)
        except (TransportError, ValueError):
            with self.lock:
                self._counts["send_errors"] += 1
            raise
        with self.lock:
            self._counts[counter] += 1

    def decode(self, opened: Opened, expected: Collection[str]) -> Any:
        """The inner message of an envelope, or None (counted) if it cannot be used.

        See :func:`temoto.fleet.common.decode_or_count`.

        Args:
            opened: The authenticated envelope.
            expected: The type names the channel carries.

        Returns:
            The decoded message, or None.
        """
        return decode_or_count(opened, expected, self._counts, self.lock)

    def speaks_as(self, opened: Opened, claimed: object, field: str) -> bool:
        """Whether a message names its authenticated sender (else counted ``impostor``, logged).

        See :class:`temoto.fleet.common.SpeakerCheck`. Not locked (the lock is taken).

        Args:
            opened: The envelope the message came in.
            claimed: The sender's name the message gives.
            field: The field it is in (for the log line).

        Returns:
            True if the message may be used.
        """
        return self._speaker(opened, claimed, field, self._counts, self.lock)
