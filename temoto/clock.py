"""Clocks: where the engine, actions and simulators read time.

Everything that measures or waits for a duration asks a :class:`Clock` instead of the ``time``
module, so tests can run timer-heavy graphs faster than real time without changing their
semantics (:class:`ScaledClock`).
"""

from __future__ import annotations

import math
import threading
import time
from typing import Protocol, runtime_checkable

__all__ = ["Clock", "ManualClock", "MonotonicClock", "ScaledClock"]


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
        """
        return time.monotonic()

    def time(self) -> float:
        """Seconds since the epoch.

        Returns:
            The reading.
        """
        return time.time()

    def real_seconds(self, seconds: float) -> float:
        """Identity: this clock runs in real time.

        Args:
            seconds: A duration.

        Returns:
            The same duration.
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
        """
        return (time.monotonic() - self._origin) * self.factor

    def time(self) -> float:
        """Scaled seconds since the epoch, starting at the real time when the clock was made.

        Returns:
            The reading.
        """
        return self._epoch + self.monotonic()

    def real_seconds(self, seconds: float) -> float:
        """Clock seconds to real seconds.

        Args:
            seconds: A duration of this clock.

        Returns:
            ``seconds / factor``.
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


class ManualClock:
    """Virtual time that moves only when :meth:`advance` (or :meth:`set`) is called.

    For tests and simulators: a simulated motor's physics, a driver's poll period and a
    timeout all read this clock, and the test moves it, so nothing sleeps and every run is the
    same. :meth:`wait` blocks (in real time) until the clock reaches the deadline or the
    condition is notified; :meth:`advance` wakes every waiter so it can check again.

    Args:
        start: The first reading of :meth:`monotonic`.
        epoch: What :meth:`time` reads when :meth:`monotonic` reads ``start``.

    Raises:
        ValueError: If a reading is not finite.
    """

    def __init__(self, start: float = 0.0, epoch: float = 1_700_000_000.0) -> None:
        if not (math.isfinite(start) and math.isfinite(epoch)):
            raise ValueError("clock readings must be finite")
        self._now = float(start)
        self._epoch = float(epoch) - float(start)
        self._lock = threading.Lock()
        self._waiting: list[threading.Condition] = []  # one entry per waiting thread
        self._moves = 0  # how many times time moved
        self._seen = threading.local()  # per thread: _moves when it last read the time

    def monotonic(self) -> float:
        """The current virtual time.

        Returns:
            Seconds.
        """
        with self._lock:
            self._seen.moves = self._moves
            return self._now

    def time(self) -> float:
        """The virtual wall-clock time (epoch seconds).

        Returns:
            Seconds since the epoch.
        """
        with self._lock:
            self._seen.moves = self._moves
            return self._epoch + self._now

    def real_seconds(self, seconds: float) -> float:
        """Virtual time has no real-time rate: the duration is returned as it is.

        Args:
            seconds: A duration.

        Returns:
            The same duration (callers use it only as an upper bound of a real wait).
        """
        return seconds

    def advance(self, seconds: float) -> float:
        """Move time forward and wake every waiter.

        Args:
            seconds: How far (≥ 0).

        Returns:
            The new reading.

        Raises:
            ValueError: If ``seconds`` is negative or not finite.
        """
        if not (math.isfinite(seconds) and seconds >= 0):
            raise ValueError(f"a clock advances by a finite, non-negative duration: {seconds!r}")
        with self._lock:
            self._now += seconds
            self._moves += 1
            now = self._now
            waiting = list({id(c): c for c in self._waiting}.values())
        for cond in waiting:
            with cond:
                cond.notify_all()
        return now

    def set(self, reading: float) -> float:
        """Move time forward to ``reading`` (never back).

        Args:
            reading: The new reading.

        Returns:
            The new reading.

        Raises:
            ValueError: If ``reading`` is earlier than now.
        """
        with self._lock:
            step = reading - self._now
        if step < 0:
            raise ValueError(f"a clock does not go back ({reading} < {reading - step})")
        return self.advance(step)

    def wait(self, cond: threading.Condition, seconds: float | None) -> bool:
        """Wait on a held condition until notified or until virtual time passes ``seconds``.

        A caller computes ``seconds`` from its last reading of the clock; if time moved since
        this thread last read it (an :meth:`advance` between the reading and this call, which
        could not wake a thread that was not waiting yet), the wait returns at once, as a
        spurious wake-up, so the caller reads the clock again instead of sleeping through the
        step it missed.

        Args:
            cond: A condition whose lock the caller holds.
            seconds: Virtual seconds, or None to wait until notified.

        Returns:
            False if the deadline passed (in virtual time).

        Raises:
            RuntimeError: If the caller does not hold the lock.
        """
        with self._lock:
            seen = getattr(self._seen, "moves", self._moves)
            self._seen.moves = self._moves
            if seen != self._moves:  # time moved since this thread looked: look again
                return True
            deadline = None if seconds is None else self._now + max(seconds, 0.0)
            if deadline is not None and self._now >= deadline:
                return False
            self._waiting.append(cond)
        try:
            cond.wait()
        finally:
            with self._lock:
                self._waiting.remove(cond)
        with self._lock:
            return deadline is None or self._now < deadline
