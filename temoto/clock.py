"""Clocks: where the engine, actions and simulators read time.

Everything that measures or waits for a duration asks a :class:`Clock` instead of the ``time``
module, so tests can run timer-heavy graphs faster than real time without changing their
semantics (:class:`ScaledClock`).
"""

from __future__ import annotations

import threading
import time
from typing import Protocol, runtime_checkable

__all__ = ["Clock", "MonotonicClock", "ScaledClock"]


@runtime_checkable
class Clock(Protocol):
    """Where TeMoto reads time and how it waits.

    Durations are float seconds of *this clock's* time.
    """

    def monotonic(self) -> float:
        """Seconds on a monotonic scale (only differences are meaningful)."""
        ...

    def time(self) -> float:
        """Seconds since the Unix epoch (for log timestamps)."""
        ...

    def real_seconds(self, seconds: float) -> float:
        """Convert a duration of this clock into real seconds (for OS-level waits)."""
        ...

    def wait(self, cond: threading.Condition, seconds: float | None) -> bool:
        """Wait on a held condition for up to ``seconds`` of this clock's time.

        Returns:
            False if the wait timed out.
        """
        ...


class MonotonicClock:
    """Real time: ``time.monotonic`` and ``time.time``."""

    def monotonic(self) -> float:
        """Seconds from ``time.monotonic()``.

        Returns:
            The reading.

        Raises:
            Nothing.
        """
        return time.monotonic()

    def time(self) -> float:
        """Seconds since the epoch.

        Returns:
            The reading.

        Raises:
            Nothing.
        """
        return time.time()

    def real_seconds(self, seconds: float) -> float:
        """Identity: this clock runs in real time.

        Args:
            seconds: A duration.

        Returns:
            The same duration.

        Raises:
            Nothing.
        """
        return seconds

    def wait(self, cond: threading.Condition, seconds: float | None) -> bool:
        """Wait on a held condition.

        Args:
            cond: A condition whose lock the caller holds.
            seconds: The timeout, or None to wait until notified.

        Returns:
            False on timeout.

        Raises:
            RuntimeError: If the caller does not hold the lock.
        """
        return cond.wait(None if seconds is None else max(seconds, 0.0))


class ScaledClock(MonotonicClock):
    """Real time multiplied by a factor: ``ScaledClock(10)`` runs ten times faster.

    A 3 s timer action then takes 0.3 s of wall time and still reports 3 s. Ordering between
    concurrent timers is kept; only the scale changes, so keep the factor modest (≤ 20) where
    actions race each other.

    Args:
        factor: How many clock seconds pass per real second (> 0).

    Raises:
        ValueError: If ``factor`` is not positive.
    """

    def __init__(self, factor: float) -> None:
        if not factor > 0:
            raise ValueError(f"clock factor must be positive, got {factor!r}")
        self.factor = float(factor)
        self._origin = time.monotonic()
        self._epoch = time.time()

    def monotonic(self) -> float:
        """Scaled seconds since the clock was made.

        Returns:
            The reading.

        Raises:
            Nothing.
        """
        return (time.monotonic() - self._origin) * self.factor

    def time(self) -> float:
        """Scaled seconds since the epoch, starting at the real time when the clock was made.

        Returns:
            The reading.

        Raises:
            Nothing.
        """
        return self._epoch + self.monotonic()

    def real_seconds(self, seconds: float) -> float:
        """Clock seconds to real seconds.

        Args:
            seconds: A duration of this clock.

        Returns:
            ``seconds / factor``.

        Raises:
            Nothing.
        """
        return seconds / self.factor

    def wait(self, cond: threading.Condition, seconds: float | None) -> bool:
        """Wait on a held condition for a scaled duration.

        Args:
            cond: A condition whose lock the caller holds.
            seconds: Clock seconds, or None to wait until notified.

        Returns:
            False on timeout.

        Raises:
            RuntimeError: If the caller does not hold the lock.
        """
        return cond.wait(None if seconds is None else max(seconds / self.factor, 0.0))
