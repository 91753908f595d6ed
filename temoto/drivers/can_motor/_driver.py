"""The part of the CAN motor drivers that does not depend on the protocol.

One python-can bus per driver; a receive thread (``temoto-can-<name>-rx``) decodes frames into
a per-joint cache, and a supervisor thread (``temoto-can-<name>-sup``) wakes every
``supervise_period`` of the driver's clock to poll, re-send set-points and check the devices'
liveness. Stream ages are judged as of the receive thread's last look at the bus
(``_rx_seen``), so a process pause that wakes the supervisor first is not a stale stream. Both are
joined by ``shutdown``. Health is derived in one place (:meth:`CanMotorDriver._evaluate`): a
problem becomes :meth:`~temoto.drivers.base.Driver.report_fault`; when every device is fine
again the driver reports itself recovered, except after a motor fault, which stays latched
until :meth:`~temoto.drivers.base.Driver.recover` cleared it on the device.
"""

from __future__ import annotations

import logging
import threading
from abc import abstractmethod
from collections.abc import Callable, Mapping
from typing import Any, Final

import can

from temoto.clock import Clock
from temoto.drivers.base import Driver, DriverState
from temoto.drivers.can_motor._common import open_bus
from temoto.drivers.supervision import FaultWindow
from temoto.errors import DriverError, DriverOperationError, MotorFaultError, StateError

__all__ = ["CanMotorDriver"]

logger = logging.getLogger(__name__)

_RX_POLL: Final = 0.05  # real seconds between stop-flag checks of the receive thread


class CanMotorDriver(Driver):
    """Bus, threads, waiting and health for a CAN motor driver (subclasses add the protocol).

    Args:
        name: The device's name.
        link: python-can ``Bus`` arguments.
        clock: The driver's clock.
        init_timeout: Clock seconds a device may take to answer in configure / activate.
        supervise_period: Clock seconds between supervisor wake-ups.
    """

    def __init__(
        self,
        name: str,
        *,
        link: Mapping[str, Any],
        clock: Clock | None,
        init_timeout: float,
        supervise_period: float,
    ) -> None:
        super().__init__(name, clock=clock)
        self.link = dict(link)
        self.init_timeout = init_timeout
        self.supervise_period = supervise_period
        self._bus: can.BusABC | None = None
        self._stop = threading.Event()
        self._cond = threading.Condition()  # notified on replies (waiters) and on stop
        self._threads: list[threading.Thread] = []
        self._send_lock = threading.Lock()
        self._eval_lock = threading.Lock()
        self._supervising = False
        self._latched = False
        #: Malformed frames received since the driver was made (all devices).
        self.bad_frames = 0
        #: Clock time the receive thread last finished with a frame or found the bus quiet:
        #: a stream is judged stale as of then, not as of now (a paused process whose
        #: supervisor wakes before its receiver has not lost its streams).
        self._rx_seen = -float("inf")

    # ---- link and threads ------------------------------------------------------------------

    def _open(self) -> None:
        self._bus = open_bus(self.link, f"{self.name}")
        self._stop.clear()
        self._threads = [
            threading.Thread(target=self._rx_loop, name=f"temoto-can-{self.name}-rx"),
            threading.Thread(target=self._sup_loop, name=f"temoto-can-{self.name}-sup"),
        ]
        for thread in self._threads:
            thread.start()

    def on_shutdown(self) -> None:
        """Stop the threads and close the bus (safe for a dead device)."""
        self._supervising = False
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        for thread in self._threads:
            if thread is not threading.current_thread():
                thread.join()
        self._threads = []
        bus, self._bus = self._bus, None
        if bus is not None:
            bus.shutdown()

    def _send(self, arbitration_id: int, data: bytes, remote: bool = False) -> None:
        bus = self._bus
        if bus is None:
            raise StateError(f"{self.name}: the CAN bus is not open")
        msg = can.Message(
            arbitration_id=arbitration_id,
            data=data,
            is_extended_id=False,
            is_remote_frame=remote,
            dlc=len(data) if not remote else 8,
        )
        try:
            with self._send_lock:
                bus.send(msg)
        except can.CanError as err:
            raise DriverOperationError(f"{self.name}: CAN send failed: {err}") from err

    def _rx_loop(self) -> None:
        bus = self._bus
        assert bus is not None
        handle = self._on_frame
        stop = self._stop
        while not stop.is_set():
            try:
                msg = bus.recv(_RX_POLL)
            except can.CanError as err:
                logger.warning("driver %s: CAN receive failed: %s", self.name, err)
                stop.wait(_RX_POLL)
                continue
            if msg is not None and not (msg.is_error_frame or msg.is_remote_frame):
                try:
                    handle(msg)
                except Exception:  # one bad frame never kills the receive thread
                    logger.exception("driver %s: handling %s failed", self.name, msg)
            self._rx_seen = self.clock.monotonic()

    def _sup_loop(self) -> None:
        due = self.clock.monotonic()
        while True:
            with self._cond:
                while not self._stop.is_set():
                    left = due - self.clock.monotonic()
                    if left <= 0:
                        break
                    self.clock.wait(self._cond, left)
            if self._stop.is_set():
                return
            now = self.clock.monotonic()
            try:
                self._on_period(now)
                self._evaluate()
            except Exception:
                logger.exception("driver %s: supervision failed", self.name)
            due = max(due + self.supervise_period, now)

    def _notify(self) -> None:
        with self._cond:
            self._cond.notify_all()

    def _wait_for(
        self, pred: Callable[[], bool], timeout: float, nudge: Callable[[], None] | None = None
    ) -> bool:
        """Wait up to ``timeout`` clock seconds for ``pred``; call ``nudge`` now and then."""
        start = self.clock.monotonic()
        step = max(self.supervise_period, timeout / 10)
        next_nudge = start + step
        with self._cond:
            while not pred():
                now = self.clock.monotonic()
                if now - start >= timeout or self._stop.is_set():
                    return pred()
                left = timeout - (now - start)
                if nudge is not None:
                    if now >= next_nudge:
                        next_nudge = now + step
                        nudge()
                    left = min(left, next_nudge - now)
                self.clock.wait(self._cond, left)
        return True

    # ---- health ----------------------------------------------------------------------------

    def _evaluate(self) -> None:
        """Turn the devices' condition into a fault or a recovery report."""
        if not self._supervising:
            return
        with self._eval_lock:
            problem = self._problem(self.clock.monotonic())
            if problem is not None:
                if isinstance(problem, MotorFaultError):
                    self._latched = True
                self.report_fault(problem)
            elif not self._latched and self.state is DriverState.FAULT:
                self.report_recovered()

    def _require_open(self, verb: str) -> None:
        state = self.state
        if state in (DriverState.UNCONFIGURED, DriverState.FINALIZED):
            raise StateError(f"{self.name}: cannot {verb} while {state.value}")

    # ---- protocol hooks --------------------------------------------------------------------

    @abstractmethod
    def _on_frame(self, msg: can.Message) -> None:
        """Decode one received frame into the cache (receive thread)."""

    @abstractmethod
    def _on_period(self, now: float) -> None:
        """Poll or check liveness (supervisor thread)."""

    @abstractmethod
    def _problem(self, now: float) -> DriverError | None:
        """What is wrong with the devices now, or None."""

    def _count_malformed(
        self, window: FaultWindow, text: str, noun: str, now: float, *, latched: bool
    ) -> str | None:
        """Count one malformed frame in ``window`` and log it (the first, and a new fault).

        Args:
            window: The window it counts in.
            text: What was wrong, for people.
            noun: What they are, plural (``frames``, ``replies``).
            now: Clock seconds.
            latched: Whether such a fault is reported already.

        Returns:
            The fault's text when the window is full and none is latched, else None.
        """
        self.bad_frames += 1
        fault = window.add(now)
        recent = window.recent(now)
        if recent == 1 or (fault and not latched):
            logger.warning(
                "driver %s: %s; %d within %g s (a fault at %d), %d in all",
                self.name,
                text,
                recent,
                window.window,
                window.limit,
                self.bad_frames,
            )
        if fault and not latched:
            return f"{recent} malformed {noun} within {window.window:g} s, the newest: {text}"
        return None
