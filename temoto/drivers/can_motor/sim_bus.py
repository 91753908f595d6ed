"""The CAN side shared by the simulated motors: a python-can bus, a receive thread, a tick thread.

:class:`CanDeviceSim` is the base of :class:`~temoto.drivers.can_motor.sim.SimODrive` and
:class:`~temoto.drivers.can_motor.sim.SimMitMotor`: it opens the bus on
:meth:`~CanDeviceSim.start`, hands each received frame to :meth:`~CanDeviceSim.on_frame` and
calls :meth:`~CanDeviceSim.on_tick` every ``tick`` seconds of the injected clock (waiting with
``clock.wait``, so a :class:`~temoto.clock.ManualClock` runs it in virtual time), and applies
the faults every device shares (``silence`` and ``link_loss``: nothing in or out; ``corrupt``:
frames go out truncated) in :meth:`~CanDeviceSim.send`. A frame may also be sent later
(:meth:`~CanDeviceSim.send_at`: the realism's jitter and late frames); the tick thread wakes
for it too and sends it at its clock time.
"""

from __future__ import annotations

import heapq
import itertools
import logging
import threading
from abc import abstractmethod
from collections.abc import Mapping
from typing import Any, ClassVar, Final

import can

from temoto.clock import Clock
from temoto.drivers.can_motor._common import open_bus
from temoto.drivers.sim import Simulator

__all__ = ["CanDeviceSim"]

logger = logging.getLogger(__name__)

_RX_POLL: Final = 0.05  # real seconds between stop-flag checks of a receive thread


class CanDeviceSim(Simulator):
    """A python-can bus, a receive thread and a clock-driven tick thread."""

    FAULTS: ClassVar[frozenset[str]] = frozenset(
        {"silence", "corrupt", "hardware_error", "link_loss"}
    )
    _KIND: ClassVar[str] = "can"

    def __init__(self, link: Mapping[str, Any], clock: Clock, tick: float) -> None:
        super().__init__()
        self.link = dict(link)
        self.clock = clock
        self.tick = tick
        self._cond = threading.Condition()
        self._stop = False
        self._bus: can.BusABC | None = None
        self._threads: list[threading.Thread] = []
        self._send_lock = threading.Lock()
        #: Frames to send later: (clock time, order, arbitration id, data, node); under _cond.
        self._later: list[tuple[float, int, int, bytes, int]] = []
        self._order = itertools.count()

    def __repr__(self) -> str:
        return f"<{type(self).__name__} on {self.link.get('channel')!r}>"

    def start(self) -> None:
        """Open the bus and start answering.

        Raises:
            RuntimeError: Already started.
            DriverInitError: The bus cannot be opened.
        """
        if self._bus is not None:
            raise RuntimeError(f"{self!r} is already started")
        self._bus = open_bus(self.link, repr(self))
        self._stop = False
        channel = self.link.get("channel")
        self._threads = [
            threading.Thread(target=self._rx_loop, name=f"temoto-sim-{self._KIND}-{channel}-rx"),
            threading.Thread(
                target=self._tick_loop, name=f"temoto-sim-{self._KIND}-{channel}-tick"
            ),
        ]
        for thread in self._threads:
            thread.start()

    def close(self) -> None:
        """Stop, join the threads and close the bus (idempotent)."""
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        for thread in self._threads:
            thread.join()
        self._threads = []
        if self._bus is not None:
            self._bus.shutdown()
            self._bus = None

    # ---- faults ----------------------------------------------------------------------------

    def _faulted(self, name: str, node: int) -> bool:
        params = self.fault(name)
        if params is None:
            return False
        which = params.get("node")
        return which is None or which == node

    def _mute(self, node: int) -> bool:
        return self.fault("link_loss") is not None or self._faulted("silence", node)

    def send(self, arbitration_id: int, data: bytes, node: int) -> None:
        """Send a frame from ``node`` (unless muted; truncated when corrupting)."""
        if self._mute(node):
            return
        if data and self._faulted("corrupt", node):
            data = data[: max(1, len(data) // 2 - 1)]
        msg = can.Message(arbitration_id=arbitration_id, data=data, is_extended_id=False)
        bus = self._bus
        if bus is None:
            return
        try:
            with self._send_lock:
                bus.send(msg)
        except can.CanError as err:
            logger.debug("%r: send failed: %s", self, err)

    def send_at(self, when: float, arbitration_id: int, data: bytes, node: int) -> None:
        """Send a frame from ``node`` at clock time ``when`` (now if it is past).

        Frames due at the same time leave in the order they were given.
        """
        if when <= self.clock.monotonic():
            self.send(arbitration_id, data, node)
            return
        with self._cond:
            heapq.heappush(self._later, (when, next(self._order), arbitration_id, data, node))
            self._cond.notify_all()

    def send_due(self, now: float) -> float:
        """Send the frames of :meth:`send_at` due by ``now``; when the next one is due.

        Args:
            now: Clock seconds.

        Returns:
            The clock time of the next frame held (infinity: none).
        """
        due: list[tuple[int, bytes, int]] = []
        with self._cond:
            later = self._later
            while later and later[0][0] <= now:
                _, _, aid, data, node = heapq.heappop(later)
                due.append((aid, data, node))
            nxt = later[0][0] if later else float("inf")
        for aid, data, node in due:
            self.send(aid, data, node)
        return nxt

    # ---- threads ---------------------------------------------------------------------------

    def _rx_loop(self) -> None:
        bus = self._bus
        assert bus is not None
        while not self._stop:
            try:
                msg = bus.recv(_RX_POLL)
            except can.CanError as err:  # pragma: no cover - a broken backend
                logger.warning("%r: receive failed: %s", self, err)
                continue
            if msg is None or msg.is_error_frame or self.fault("link_loss") is not None:
                continue
            try:
                self.on_frame(msg)
            except Exception:  # a simulator never dies of one bad frame
                logger.exception("%r: handling %s failed", self, msg)

    def _tick_loop(self) -> None:
        due = self.clock.monotonic()
        while True:
            with self._cond:
                while not self._stop:
                    wake = min(due, self._later[0][0]) if self._later else due
                    left = wake - self.clock.monotonic()
                    if left <= 0:
                        break
                    self.clock.wait(self._cond, left)
                if self._stop:
                    return
            now = self.clock.monotonic()
            if now >= due:
                due = max(due + self.tick, now)
                try:
                    self.on_tick(now)
                except Exception:
                    logger.exception("%r: tick failed", self)
            try:
                self.send_due(self.clock.monotonic())
            except Exception:
                logger.exception("%r: sending held frames failed", self)

    @abstractmethod
    def on_frame(self, msg: can.Message) -> None:
        """Handle one received frame (on the receive thread)."""

    @abstractmethod
    def on_tick(self, now: float) -> None:
        """Step the models and send what is due (on the tick thread)."""
