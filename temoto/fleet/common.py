"""Helpers of the fleet services and of the managers that speak on the fleet link.

:mod:`temoto.fleet` and the managers that send their own messages on a
:class:`~temoto.transport.FleetLink` (the Context Manager) build on these: :func:`new` makes
an empty message of a generated LCM class, :func:`decode_or_count` opens an envelope's payload
and counts what it drops, :func:`check_name`, :func:`check_seconds` and :func:`check_clock`
check constructor arguments with clear errors, :class:`SpeakerCheck` drops a message whose
actor, robot or sender field names a member other than its envelope's authenticated sender,
:class:`CallQueue` runs callbacks off the
transport's receive thread, and :class:`Closing` gives ``with`` support to anything with a
``close()``. :class:`temoto.fleet.service.ServiceCore` is the state the parts of one service
share.
"""

from __future__ import annotations

import collections
import logging
import math
import threading
from collections.abc import Callable, Collection
from typing import Any

from temoto._closing import Closing
from temoto.clock import Clock
from temoto.errors import DecodeError
from temoto.transport import codec
from temoto.transport.auth import Opened
from temoto.transport.base import LogLimiter

__all__ = [
    "IMPOSTOR",
    "CallQueue",
    "Closing",
    "SpeakerCheck",
    "check_clock",
    "check_name",
    "check_seconds",
    "decode_or_count",
    "new",
]

logger = logging.getLogger(__name__)

# (sender, type, version) already warned about: a peer of another release is named once, not
# once per message. Bounded: past this many, further ones are logged at DEBUG only.
_VERSION_WARNED: set[tuple[str, str, int]] = set()
_VERSION_WARNED_MAX = 256
_version_lock = threading.Lock()


#: The counter of the messages a :class:`SpeakerCheck` drops (in every fleet service's stats).
IMPOSTOR = "impostor"
#: Seconds between two WARNING lines about the same sender naming the same other member.
_IMPOSTOR_LOG_S = 10.0


class SpeakerCheck:
    """A member speaks only as itself: its messages must name it, not another member.

    Every fleet message whose meaning depends on who sent it names its sender inside (the
    ``actor`` of a handshake, a notification, an acknowledgement, a command reply or feedback;
    the ``robot`` of a RIS advert, a withdrawal, a world-model update or digest; the
    ``requester`` of a request). It is accepted only when that name is the envelope's
    authenticated sender (:attr:`Opened.sender`: with a roster, the member whose key sealed
    it); otherwise it is dropped, counted as :data:`IMPOSTOR` and logged at WARNING with both
    names (at once for each sender, claimed name and type, then at most every 10 s with the
    count of those held back). docs/security.md lists the field of each message type.

    With a shared fleet key or ``--insecure`` the sender's name is not bound to a key (any
    member, or anyone, can write any sender name): the check then only keeps a member's
    messages consistent, it proves nothing.

    Args:
        service: Names the service in the log line (e.g. ``"actors"``).
    """

    def __init__(self, service: str) -> None:
        self.service = service
        self._log = LogLimiter(_IMPOSTOR_LOG_S)

    def __call__(
        self,
        opened: Opened,
        claimed: object,
        field: str,
        counts: dict[str, int],
        lock: threading.Lock | threading.RLock,
    ) -> bool:
        """Whether ``claimed`` is the authenticated sender; counts and logs when not.

        Args:
            opened: The envelope the message came in.
            claimed: The name the message gives for its sender (the value of ``field``).
            field: The message's field that names it, for the log line.
            counts: The service's counters; :data:`IMPOSTOR` is added to.
            lock: Guards ``counts`` (not held by the caller).

        Returns:
            True if the message may be used.
        """
        if claimed == opened.sender:
            return True
        with lock:
            counts[IMPOSTOR] = counts.get(IMPOSTOR, 0) + 1
        held = self._log.allow((opened.sender, claimed, opened.type))
        if held is not None:
            more = f"; {held} more since the last report" if held else ""
            logger.warning(
                "%s: dropped a %s on %r sent by %s whose %s names %s: a member speaks only as"
                " itself%s",
                self.service,
                opened.type,
                opened.channel,
                _quoted(opened.sender),
                field,
                _quoted(claimed),
                more,
            )
        return False


def _quoted(name: object) -> str:
    """A name from the network for a log line: quoted, escaped, cut to 64 characters."""
    text = repr(name if not isinstance(name, str) else name[:64])
    return text + "..." if isinstance(name, str) and len(name) > 64 else text


def new(cls: type[Any]) -> Any:
    """An empty message of a generated (untyped) LCM class.

    Args:
        cls: The generated class.

    Returns:
        A new instance with default field values.
    """
    return cls()


def check_name(what: str, value: object) -> str:
    """Check a non-empty string argument.

    Args:
        what: The argument's description, for the error.
        value: The value.

    Returns:
        The value.

    Raises:
        ValueError: If it is not a non-empty string.
    """
    if not isinstance(value, str) or not value:
        raise ValueError(f"{what} must be a non-empty string, got {value!r}")
    return value


def check_seconds(what: str, value: float, *, zero: bool = False) -> float:
    """Check a duration argument.

    Args:
        what: The argument's description, for the error.
        value: Seconds.
        zero: Whether 0 is allowed.

    Returns:
        The value as a float.

    Raises:
        ValueError: If it is not a finite number, is negative, or is 0 when not allowed.
    """
    ok = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
    if not ok or value < 0 or (value == 0 and not zero):
        raise ValueError(f"{what} must be a {'' if zero else 'positive '}number of seconds")
    return float(value)


def check_clock(what: str, value: object) -> Clock:
    """Check a clock argument: a :class:`~temoto.clock.Clock`, not a bare function.

    The fleet services read monotonic time (deadlines, silences), wall time (stamps, boot
    ids) and wait on conditions through one clock, like the engine and the managers.

    Args:
        what: The argument's description, for the error.
        value: The value.

    Returns:
        The value.

    Raises:
        TypeError: If it is not a Clock (a bare function such as ``time.monotonic`` is
            refused with a hint: pass ``temoto.clock.MonotonicClock()``, or a
            ``ManualClock`` in tests).
    """
    if isinstance(value, Clock):
        return value
    hint = (
        " (a function is no longer accepted: pass temoto.clock.MonotonicClock(),"
        " or a temoto.clock.ManualClock in tests)"
        if callable(value)
        else ""
    )
    raise TypeError(f"{what} must be a temoto.clock.Clock, got {value!r}{hint}")


class CallQueue:
    """Runs callables one at a time, in order, on one named thread.

    Used so that user callbacks and registrar calls never run on a transport's receive thread
    (a slow one would delay every message behind it). What a call raises is logged and
    counted in :attr:`errors`; it never stops the thread.

    Args:
        name: The thread's name.
        what: Describes the calls in log lines.
    """

    def __init__(self, name: str, what: str) -> None:
        self._what = what
        self._cond = threading.Condition()
        self._calls: collections.deque[Callable[[], None]] = collections.deque()
        self._closed = False
        self.errors = 0
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def put(self, call: Callable[[], None]) -> bool:
        """Queue a call.

        Args:
            call: Runs on the queue's thread.

        Returns:
            False if the queue is closed (the call is dropped).
        """
        with self._cond:
            if self._closed:
                return False
            self._calls.append(call)
            self._cond.notify()
            return True

    def close(self, *, drain: bool = False) -> None:
        """Stop the thread and join it (unless called from it). Idempotent.

        Args:
            drain: Run the calls already queued before stopping (else they are dropped).
        """
        with self._cond:
            self._closed = True
            if not drain:
                self._calls.clear()
            self._cond.notify()
        if self._thread is not threading.current_thread():
            self._thread.join()

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._calls and not self._closed:
                    self._cond.wait()
                if not self._calls:
                    return
                call = self._calls.popleft()
            try:
                call()
            except Exception:
                with self._cond:
                    self.errors += 1
                logger.exception("%s raised", self._what)


def decode_or_count(
    opened: Opened, expected: Collection[str], counts: dict[str, int], lock: threading.Lock
) -> Any:
    """The inner message of an envelope, or None (counted) if it is undecodable or unexpected.

    A message of a version this build does not speak (a peer of another release) is logged
    at WARNING, once per sender, type and version; other drops at DEBUG.

    Args:
        opened: The authenticated envelope.
        expected: The type names this channel carries.
        counts: The service's counters (``decode_errors``, ``unexpected``).
        lock: Guards ``counts``.

    Returns:
        The decoded message, or None.
    """
    try:
        msg = codec.decode(opened.type, opened.payload)
    except DecodeError as err:
        with lock:
            counts["decode_errors"] += 1
        if isinstance(err, codec.UnsupportedVersion):
            key = (opened.sender, opened.type, err.version)
            with _version_lock:
                first = key not in _VERSION_WARNED and len(_VERSION_WARNED) < _VERSION_WARNED_MAX
                if first:
                    _VERSION_WARNED.add(key)
            if first:
                logger.warning(
                    "dropping the messages of %r on %r: %s (this warning once per sender)",
                    opened.sender,
                    opened.channel,
                    err,
                )
                return None
        logger.debug("dropped a message from %r on %r: %s", opened.sender, opened.channel, err)
        return None
    if opened.type not in expected:
        with lock:
            counts["unexpected"] += 1
        logger.debug("dropped a %s from %r on %r", opened.type, opened.sender, opened.channel)
        return None
    return msg
