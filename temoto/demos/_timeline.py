"""What every demonstration prints and returns."""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from typing import IO, Any

__all__ = ["DemoReport", "Timeline"]


@dataclass
class DemoReport:
    """The outcome of a demonstration.

    Attributes:
        ok: Whether it showed what it is meant to show.
        facts: Named results (timings, which robot or sensor ran, final states) for tests.
        events: ``(seconds since the start, who, what)``, in order.
    """

    ok: bool = False
    facts: dict[str, Any] = field(default_factory=dict)
    events: list[tuple[float, str, str]] = field(default_factory=list)


class Timeline:
    """Prints ``[  1.23s] who: what`` lines from any thread, and keeps them.

    Args:
        out: Where the lines go.
        title: Printed first.
    """

    def __init__(self, out: IO[str], title: str) -> None:
        self.out = out
        self.t0 = time.monotonic()
        self.events: list[tuple[float, str, str]] = []
        self._lock = threading.Lock()
        self.out.write(f"== {title}\n")
        self.out.flush()

    def now(self) -> float:
        """Seconds since the demonstration started."""
        return time.monotonic() - self.t0

    def say(self, who: str, what: str) -> float:
        """Print one event.

        Args:
            who: The robot, operator or component it concerns.
            what: What happened.

        Returns:
            Its time (seconds since the start).
        """
        t = self.now()
        with self._lock:
            self.events.append((t, who, what))
            self.out.write(f"[{t:7.2f}s] {who}: {what}\n")
            self.out.flush()
        return t

    def close(self, report: DemoReport) -> None:
        """Print the summary and hand the events to the report."""
        report.events = list(self.events)
        with self._lock:
            self.out.write(f"== {'done' if report.ok else 'FAILED'} in {self.now():.1f} s\n")
            for name, value in report.facts.items():
                self.out.write(f"   {name}: {value}\n")
            self.out.flush()
