"""The transport interface: publish bytes on named channels, subscribe handlers to them.

A :class:`Transport` moves opaque byte strings; what they mean (envelopes, authentication,
inner messages) is the business of the layers above (:mod:`temoto.transport.auth`,
:mod:`temoto.transport.codec`). The base class owns the public calls and their checks
(template method, docs/development.md §2); an implementation fills in ``_publish``, ``_subscribe``
and ``_close``, and hands every received message to :meth:`Transport._deliver`, which runs the
handler, logs and counts what it raises, and never lets it escape into the receive thread.

Handlers always run on the transport's receive thread, never on the publisher's: code that
publishes while holding a lock cannot deadlock against its own handler.
"""

from __future__ import annotations

import collections
import logging
import re
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Hashable
from typing import Self

from temoto._closing import Closing
from temoto.errors import TransportError

__all__ = [
    "CHANNEL_MAX_LEN",
    "Handler",
    "LogLimiter",
    "QueuedSubscription",
    "Subscription",
    "Transport",
    "check_channel",
]

logger = logging.getLogger(__name__)

#: A message handler: called with the channel name and the message bytes.
Handler = Callable[[str, bytes], None]

#: LCM's limit on channel names (``LCM_MAX_CHANNEL_NAME_LENGTH``); every transport keeps it,
#: so a name that works in-process also works on the wire.
CHANNEL_MAX_LEN = 63

# LCM subscribes by POSIX regular expression; channel names are restricted to characters with no
# special meaning there (the dot excepted, which the LCM transport filters exactly), so a
# subscription means the same on every transport.
_CHANNEL_RE = re.compile(r"[A-Za-z0-9_./:-]+")


def check_channel(channel: str) -> str:
    """Check that a channel name is valid on every transport.

    Args:
        channel: The name: 1 to 63 characters from ``A-Z a-z 0-9 _ . / : -``.

    Returns:
        The name, unchanged.

    Raises:
        ValueError: If the name is empty, too long or has another character.
    """
    if not isinstance(channel, str) or not _CHANNEL_RE.fullmatch(channel):
        raise ValueError(
            f"invalid channel name {channel!r}: use 1 to {CHANNEL_MAX_LEN} characters from "
            "A-Z a-z 0-9 _ . / : -"
        )
    if len(channel) > CHANNEL_MAX_LEN:
        raise ValueError(
            f"channel name {channel[:20]!r}... is {len(channel)} characters long; "
            f"LCM allows at most {CHANNEL_MAX_LEN}"
        )
    return channel


class LogLimiter:
    """Lets one log line per key through per interval and counts the ones held back.

    For the transports and the fleet's services: a peer's flood is logged, not repeated.

    Args:
        interval_s: Seconds between two lines for the same key.
    """

    def __init__(self, interval_s: float = 1.0) -> None:
        self._interval_s = interval_s
        self._next: dict[Hashable, float] = {}
        self._held: dict[Hashable, int] = {}
        self._mutex = threading.Lock()

    def allow(self, key: Hashable) -> int | None:
        """Ask whether a line for ``key`` may be logged now.

        Args:
            key: What the line is about (a reason, a channel).

        Returns:
            None if the line must be dropped; otherwise how many lines for ``key`` were
            dropped since the last one let through.
        """
        now = time.monotonic()
        with self._mutex:
            if now < self._next.get(key, now):
                self._held[key] = self._held.get(key, 0) + 1
                return None
            self._next[key] = now + self._interval_s
            return self._held.pop(key, 0)


class Subscription(ABC):
    """One handler subscribed to one channel of a transport (made by :meth:`Transport.subscribe`).

    Args:
        channel: The channel name.
        handler: Called with the channel and the message bytes on the receive thread.

    Attributes:
        channel: The channel name.
        handler: The handler.
    """

    def __init__(self, channel: str, handler: Handler) -> None:
        self.channel = channel
        self.handler = handler
        self._active = True
        self._handler_errors = 0

    @property
    def active(self) -> bool:
        """Whether the handler still receives messages (False after :meth:`unsubscribe`)."""
        return self._active

    @property
    def handler_errors(self) -> int:
        """How many times the handler raised."""
        return self._handler_errors

    def unsubscribe(self) -> None:
        """Stop delivering to the handler; idempotent, safe from any thread and from a handler.

        A handler call already running finishes; no call starts after this returns, except
        on the receive thread itself when called from another handler of the same message.
        """
        if not self._active:
            return
        self._active = False
        self._on_unsubscribe()

    def detach(self) -> None:
        """Stop delivering, without the release hook.

        For its transport, which is closing and releases every subscription itself.
        """
        self._active = False

    @abstractmethod
    def _on_unsubscribe(self) -> None:
        """Release the implementation's resources; called once, by :meth:`unsubscribe`."""

    def __repr__(self) -> str:
        state = "active" if self._active else "unsubscribed"
        return f"<{type(self).__name__} {self.channel!r} {state}>"


class QueuedSubscription(Subscription):
    """A subscription with a bounded queue of its own, drained by its transport's one thread.

    The transport, holding its lock, :meth:`offer` s each message to the subscriptions of its
    channel and :meth:`take` s one on its dispatch thread per token in its ready queue; a
    subscription that was emptied (:meth:`discard_pending`, when unsubscribed) leaves stale
    tokens that the dispatcher skips.

    Args:
        channel: The channel name.
        handler: Called with the channel and the message bytes on the dispatch thread.
        queue_capacity: The most messages that wait for the handler (None: no limit); when
            full, the oldest is dropped for the new one.

    Attributes:
        queue_capacity: As given.
    """

    def __init__(self, channel: str, handler: Handler, queue_capacity: int | None) -> None:
        super().__init__(channel, handler)
        self.queue_capacity = queue_capacity
        # Guarded by the transport's lock.
        self._pending: collections.deque[bytes] = collections.deque()
        self._dropped = 0

    @property
    def dropped(self) -> int:
        """How many messages were dropped because the queue was full."""
        return self._dropped

    def offer(self, data: bytes, ready: collections.deque[Self]) -> None:
        """Queue ``data`` (transport lock held); a token goes to ``ready`` unless one is dropped.

        A full queue drops its oldest message for this one: the dispatcher's tokens still
        match the messages waiting, so none is added.
        """
        capacity = self.queue_capacity
        if capacity is not None and len(self._pending) >= capacity:
            self._pending.popleft()
            self._dropped += 1
        else:
            ready.append(self)
        self._pending.append(data)

    def take(self) -> bytes | None:
        """The oldest message waiting, or None (a stale token); transport lock held."""
        return self._pending.popleft() if self._pending else None

    def discard_pending(self) -> None:
        """Drop the messages waiting (removed from its channel); transport lock held."""
        self._pending.clear()

    def detach(self) -> None:
        """Stop delivering and drop the messages waiting, without the release hook.

        For its transport, which is closing and releases every subscription itself.
        """
        self._active = False
        self._pending.clear()


class Transport(Closing, ABC):
    """Publishes byte strings on named channels and delivers them to subscribed handlers.

    Use it as a context manager or call :meth:`close`. Implementations override the hooks
    ``_publish``, ``_subscribe`` and ``_close`` and call :meth:`_deliver` on their receive
    thread for every message of a subscription.
    """

    def __init__(self) -> None:
        self._closed = False
        self._close_lock = threading.Lock()
        self._handler_errors = 0
        self._errors_lock = threading.Lock()
        self._error_log = LogLimiter()

    # --- the calls (not overridden) -----------------------------------------------------------

    def publish(self, channel: str, data: bytes) -> None:
        """Send ``data`` to every subscriber of ``channel`` (subscribers of this transport too).

        Args:
            channel: The channel name (see :func:`check_channel`).
            data: The message.

        Raises:
            ValueError: If the channel name is invalid.
            TypeError: If ``data`` is not bytes-like.
            TransportError: If the transport is closed or sending failed.
        """
        check_channel(channel)
        if not isinstance(data, bytes | bytearray | memoryview):
            raise TypeError(f"data must be bytes, got {type(data).__name__}")
        data = bytes(data)  # the same object when it is bytes already
        self._check_open()
        self._publish(channel, data)

    def subscribe(
        self, channel: str, handler: Handler, *, queue_capacity: int | None = None
    ) -> Subscription:
        """Call ``handler(channel, data)`` on the receive thread for every message on ``channel``.

        Args:
            channel: The channel name (see :func:`check_channel`); no patterns.
            handler: Called with the channel and the message bytes; what it raises is logged
                and counted (:attr:`handler_errors`), never propagated.
            queue_capacity: At most this many messages wait for the handler; when more arrive
                the oldest are dropped. None keeps the implementation's default.

        Returns:
            The subscription; :meth:`Subscription.unsubscribe` ends it.

        Raises:
            ValueError: If the channel name or the capacity is invalid.
            TypeError: If ``handler`` is not callable.
            TransportError: If the transport is closed.
        """
        check_channel(channel)
        if not callable(handler):
            raise TypeError(f"handler must be callable, got {type(handler).__name__}")
        if queue_capacity is not None and (
            isinstance(queue_capacity, bool)
            or not isinstance(queue_capacity, int)
            or queue_capacity < 1
        ):
            raise ValueError(
                f"queue_capacity must be a positive int or None, got {queue_capacity!r}"
            )
        self._check_open()
        return self._subscribe(channel, handler, queue_capacity)

    def close(self) -> None:
        """Stop receiving, end every subscription and join the receive thread; idempotent.

        Messages not yet handed to a handler are discarded. Called from a handler, it does not
        wait for the receive thread (which is the caller), but the thread ends after the handler
        returns.
        """
        with self._close_lock:
            if self._closed:
                return
            self._closed = True
        self._close()

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` was called."""
        return self._closed

    @property
    def handler_errors(self) -> int:
        """How many times a handler of this transport raised."""
        return self._handler_errors

    # --- for implementations ------------------------------------------------------------------

    def _check_open(self) -> None:
        if self._closed:
            raise TransportError(f"{type(self).__name__} is closed")

    def _deliver(self, sub: Subscription, channel: str, data: bytes) -> None:
        """Run a subscription's handler on the receive thread, containing what it raises.

        Args:
            sub: The subscription; nothing happens when it has been unsubscribed.
            channel: The channel the message came on.
            data: The message.

        Raises:
            BaseException: A ``KeyboardInterrupt`` or ``SystemExit`` of the handler propagates;
                an ``Exception`` is counted and logged.
        """
        if not sub.active:
            return
        try:
            sub.handler(channel, data)
        except Exception:
            with self._errors_lock:
                self._handler_errors += 1
                sub._handler_errors += 1
            held = self._error_log.allow(channel)
            if held is not None:
                more = f" ({held} more since the last report)" if held else ""
                logger.exception(
                    "%s: handler %r of channel %r raised%s",
                    type(self).__name__,
                    sub.handler,
                    channel,
                    more,
                )

    @abstractmethod
    def _publish(self, channel: str, data: bytes) -> None:
        """Send a checked message; runs on the caller's thread, possibly on several at once."""

    @abstractmethod
    def _subscribe(
        self, channel: str, handler: Handler, queue_capacity: int | None
    ) -> Subscription:
        """Create a subscription for checked arguments."""

    @abstractmethod
    def _close(self) -> None:
        """Release everything; called once, by :meth:`close`."""
