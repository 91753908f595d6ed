"""A message sink for tests: a callable handler that records what it gets and can be waited on."""

from __future__ import annotations

import threading

__all__ = ["Inbox"]


class Inbox:
    """Collects ``(channel, data, receiving thread's name)`` from a transport handler.

    Use the instance itself as the handler; :meth:`wait_for` blocks (on a condition, no
    polling) until enough messages arrived.

    Args:
        timeout: Default seconds :meth:`wait_for` waits.
    """

    def __init__(self, timeout: float = 5.0) -> None:
        self.items: list[tuple[str, bytes, str]] = []
        self.timeout = timeout
        self._cond = threading.Condition()

    def __call__(self, channel: str, data: bytes) -> None:
        with self._cond:
            self.items.append((channel, data, threading.current_thread().name))
            self._cond.notify_all()

    def wait_for(self, count: int, timeout: float | None = None) -> list[tuple[str, bytes, str]]:
        """Wait until at least ``count`` messages arrived.

        Args:
            count: How many.
            timeout: Seconds (default: the inbox's).

        Returns:
            Every message so far.

        Raises:
            AssertionError: Fewer arrived in time (the message lists what did).
        """
        with self._cond:
            ok = self._cond.wait_for(
                lambda: len(self.items) >= count, self.timeout if timeout is None else timeout
            )
            if not ok:
                raise AssertionError(f"got {len(self.items)} of {count} messages: {self.items}")
            return list(self.items)

    @property
    def data(self) -> list[bytes]:
        """The payloads so far, in order."""
        with self._cond:
            return [d for _, d, _ in self.items]
