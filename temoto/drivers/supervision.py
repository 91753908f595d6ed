"""Small tools the drivers use to supervise what comes off the wire (``docs/safety.md``).

:class:`StreamAge` turns a feedback stream's arrival times into a staleness fault: a stream
configured at a period ``T`` is stale when nothing arrived for ``periods * T`` (3 by default).
:class:`FaultWindow` counts isolated bad events (malformed frames, CRC errors) and says when
there were too many in a sliding window: one bad frame is logged and counted, never a fault.

Both take times from the caller (the driver's clock), hold no thread and are not locked: each
is used by one thread, or under its driver's lock.
"""

from __future__ import annotations

import math
from collections import deque
from typing import Final

__all__ = [
    "BAD_FRAMES_LIMIT",
    "BAD_FRAMES_WINDOW",
    "STALE_PERIODS",
    "STALE_REAL_FLOOR",
    "STALE_REAL_FLOOR_IN_PROCESS",
    "FaultWindow",
    "StreamAge",
    "stale_periods",
]

#: Stream periods without data before a stream is stale.
STALE_PERIODS: Final = 3.0
#: Real seconds without data a stream is allowed in any case: a thread of a Python process
#: cannot be promised the CPU more often than a few of the GIL's 5 ms switch intervals on a
#: loaded machine. Equal to 3 periods of a 10 ms stream at real time, so it matters only for
#: faster streams or clocks running faster than real time.
STALE_REAL_FLOOR: Final = 0.03
#: The same for a device in our own process (a simulator on python-can's ``virtual`` bus,
#: which exists only inside one process): its sending threads compete with ours for the
#: cores and the GIL; at a load average of 9 on 2 cores one was seen silent for 101 ms.
STALE_REAL_FLOOR_IN_PROCESS: Final = 0.2
#: Bad frames within :data:`BAD_FRAMES_WINDOW` seconds that make a fault.
BAD_FRAMES_LIMIT: Final = 5
#: Seconds of the bad-frame window.
BAD_FRAMES_WINDOW: Final = 1.0


def _positive(name: str, value: float) -> float:
    if not (isinstance(value, int | float) and value > 0 and math.isfinite(value)):
        raise ValueError(f"{name} must be a positive number, got {value!r}")
    return float(value)


def stale_periods(period: float, real_per_clock: float, *, in_process: bool = False) -> float:
    """How many periods make a stream stale: :data:`STALE_PERIODS`, or more for the floor.

    Args:
        period: The stream's period, clock seconds.
        real_per_clock: Real seconds per clock second (``clock.real_seconds(1.0)``).
        in_process: The device runs in our process (:data:`STALE_REAL_FLOOR_IN_PROCESS`).

    Returns:
        ``max(STALE_PERIODS, floor / real_per_clock / period)``.
    """
    floor = STALE_REAL_FLOOR_IN_PROCESS if in_process else STALE_REAL_FLOOR
    return max(STALE_PERIODS, floor / real_per_clock / period)


class StreamAge:
    """The age of one feedback stream, and whether it is stale.

    Args:
        name: The stream, for messages (``"node 1 encoder estimates"``).
        period: Seconds between two messages of the stream as configured.
        periods: How many periods without a message make it stale.

    Raises:
        ValueError: ``period`` or ``periods`` is not positive.
    """

    __slots__ = ("last", "max_age", "name", "period")

    def __init__(self, name: str, period: float, periods: float = STALE_PERIODS) -> None:
        self.name = name
        self.period = _positive("period", period)
        self.max_age = self.period * _positive("periods", periods)
        #: Time of the newest message (None: none yet).
        self.last: float | None = None

    def feed(self, now: float) -> None:
        """A message of the stream arrived at ``now``."""
        self.last = now

    def reset(self) -> None:
        """Forget every message (a new link, a reconfigure)."""
        self.last = None

    def age(self, now: float) -> float:
        """Seconds since the newest message (infinite before the first)."""
        return math.inf if self.last is None else now - self.last

    def stale(self, now: float) -> str | None:
        """Why the stream is stale at ``now``, or None while it is fresh.

        A stream that never delivered is not stale here (the driver's configure waits for the
        first message); it becomes stale once it delivered and then stopped.
        """
        if self.last is None:
            return None
        age = now - self.last
        if age <= self.max_age:
            return None
        return f"{self.name} stale: none for {age:.3f} s (expected every {self.period:g} s)"


class FaultWindow:
    """Counts bad events; too many within a sliding window is a fault.

    Args:
        limit: Events within ``window`` that make a fault (1: every event is one).
        window: Seconds of the window.

    Raises:
        ValueError: ``limit`` is not a positive integer, or ``window`` not positive.
    """

    __slots__ = ("_times", "limit", "total", "window")

    def __init__(self, limit: int = BAD_FRAMES_LIMIT, window: float = BAD_FRAMES_WINDOW) -> None:
        if not (isinstance(limit, int) and not isinstance(limit, bool) and limit > 0):
            raise ValueError(f"limit must be a positive integer, got {limit!r}")
        self.limit = limit
        self.window = _positive("window", window)
        #: Every event ever added.
        self.total = 0
        self._times: deque[float] = deque()

    def add(self, now: float) -> bool:
        """One bad event at ``now``.

        Returns:
            Whether the window now holds ``limit`` events or more (a fault).
        """
        self.total += 1
        times = self._times
        times.append(now)
        while times and times[0] < now - self.window:
            times.popleft()
        return len(times) >= self.limit

    def recent(self, now: float) -> int:
        """Events within the window ending at ``now``."""
        times = self._times
        while times and times[0] < now - self.window:
            times.popleft()
        return len(times)

    def clear(self) -> None:
        """Forget the window (the total stays)."""
        self._times.clear()
