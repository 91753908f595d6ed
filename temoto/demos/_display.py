"""The operator's display of demonstrations 1 and 2: reads a component's channel on a thread."""

from __future__ import annotations

import threading
import time

from temoto.demos._timeline import Timeline
from temoto.managers.component import ChannelReader

__all__ = ["Display"]


class Display:
    """Reads ``<source> <seq>`` datagrams; prints the first reading of each source.

    Args:
        reader: The channel the display listens on (the consumer's end).
        timeline: Where ``display: <verb> <source>`` is printed.
        verb: What the display does with a source (``receiving from``, ``showing``).
    """

    def __init__(self, reader: ChannelReader, timeline: Timeline, verb: str) -> None:
        self.reader = reader
        self.timeline = timeline
        self.verb = verb
        self.cond = threading.Condition()
        self.first: dict[str, float] = {}  # source -> monotonic time of its first reading
        self.count: dict[str, int] = {}
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._read, name="demo-display", daemon=True)
        self.thread.start()

    def _read(self) -> None:
        while not self._stop.is_set():
            data = self.reader.recv(0.1)
            if not data:
                continue
            source = data.split(b" ", 1)[0].decode(errors="replace")
            with self.cond:
                self.count[source] = self.count.get(source, 0) + 1
                if source not in self.first:
                    self.first[source] = time.monotonic()
                    self.timeline.say("display", f"{self.verb} {source}")
                    self.cond.notify_all()

    def wait_for(self, source: str, timeout: float) -> float:
        """When the first reading of ``source`` arrived (waiting for it up to ``timeout`` s).

        Raises:
            TimeoutError: None came.
        """
        with self.cond:
            if not self.cond.wait_for(lambda: source in self.first, timeout):
                raise TimeoutError(f"no reading from {source} within {timeout:g} s")
            return self.first[source]

    def order(self) -> list[str]:
        """The sources in the order they first fed the display."""
        with self.cond:
            return sorted(self.first, key=self.first.__getitem__)

    def close(self) -> None:
        """Stop reading (the reader stays the caller's to close)."""
        self._stop.set()
        self.thread.join(5.0)
