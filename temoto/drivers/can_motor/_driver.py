"""The part of the CAN motor drivers that does not depend on the protocol.

One python-can bus per driver; a receive thread (``temoto-can-<name>-rx``) decodes frames into
a per-joint cache, and a supervisor thread (``temoto-can-<name>-sup``) wakes every
``supervise_period`` of the driver's clock to poll, re-send set-points and check the devices'
liveness. Both are joined by ``shutdown``.

**The link as last seen.** The receive thread drains the bus (every frame queued is handled
before it waits again) and notes when it found the queue empty (``_rx_seen``). A stream is judged
stale as of that look, or as of now while the receive thread is waiting on an empty queue
(:meth:`CanMotorDriver._link_seen`): a process pause that wakes the supervisor before the
receive thread has not lost its streams, and a stream that really stopped is seen at once.

**Gaps in the driver's own loop** (a process pause, a GC, a busy core): when the supervisor
wakes more than ``gap_limit`` clock seconds (and at least :data:`GAP_MIN` real seconds, or the
gap limit if shorter) after its previous wake (or ``command`` finds it so late), no set-point
goes out until every device sent feedback *after* the receive thread drained what queued
during the gap; the driver then judges that feedback (:meth:`_problem`) and either
reports the fault or resumes the held set-points (``docs/driver-can.md``, "Pauses").

Health is derived in one place (:meth:`CanMotorDriver._evaluate`): a problem becomes
:meth:`~temoto.drivers.base.Driver.report_fault`; when every device is fine again the driver
reports itself recovered, except after a motor fault, which stays latched until
:meth:`~temoto.drivers.base.Driver.recover` cleared it on the device.
"""

from __future__ import annotations

import logging
import threading
import time
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
#: Supervisor periods a wake may be late by before it is a gap in the driver's loop ...
GAP_PERIODS: Final = 3.0
#: ... and real seconds, at least (a busy core delays a wake by tens of ms, no more).
GAP_MIN: Final = 0.05
#: Real seconds configure and activate listen for a second device's answers after the first
#: device answered every probe (two devices on one bus answer within microseconds).
DUPLICATE_LISTEN: Final = 0.05
#: Probes (requests every device answers) sent to each id to find a second device on it.
DUPLICATE_PROBES: Final = 6


class CanMotorDriver(Driver):
    """Bus, threads, waiting and health for a CAN motor driver (subclasses add the protocol).

    Args:
        name: The device's name.
        link: python-can ``Bus`` arguments.
        clock: The driver's clock.
        init_timeout: Clock seconds a device may take to answer in configure / activate.
        supervise_period: Clock seconds between supervisor wake-ups.
        gap_limit: Clock seconds between two supervisor wakes that make a gap (default
            :data:`GAP_PERIODS` supervisor periods, at least :data:`GAP_MIN` real seconds).
    """

    def __init__(
        self,
        name: str,
        *,
        link: Mapping[str, Any],
        clock: Clock | None,
        init_timeout: float,
        supervise_period: float,
        gap_limit: float | None = None,
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
        #: Clock time the receive thread last found the bus's queue empty: a stream is judged
        #: stale as of then (or now, while it waits: :meth:`_link_seen`).
        self._rx_seen = -float("inf")
        self._rx_idle = False  # the receive thread waits on an empty queue
        self._seen_hi = -float("inf")  # the latest _link_seen answer: it never goes back
        self._rx_count = 0  # frames handled (numbers feedback: fresh after a gap or not)
        floor = GAP_MIN / self.clock.real_seconds(1.0)  # GAP_MIN real seconds, on the clock
        if gap_limit is None:
            gap_limit = max(GAP_PERIODS * supervise_period, floor)
        self.gap_limit = gap_limit
        self._gap_lock = threading.Lock()
        self._loop_at: float | None = None  # clock time of the supervisor's latest wake
        self._loop_real = 0.0  # ... and its real time (time.monotonic)
        #: Real seconds that must have passed too for a gap (a clock of a test may race ahead
        #: of the threads without any pause of the process).
        self._gap_real = min(GAP_MIN, self.clock.real_seconds(gap_limit))
        #: While not None: the clock time a gap in the loop was found; no set-point goes out
        #: until fresh feedback was judged (:meth:`_resync_step`).
        self._resync: float | None = None
        self._resync_gen = 0  # counts gaps; a drain counts for a gap it started after
        self._drain_mark: int | None = None  # _rx_count when the receiver drained after it
        #: The longest gap found in the loop (clock seconds), and how many there were.
        self.gap_longest = 0.0
        self.gaps = 0

    # ---- link and threads ------------------------------------------------------------------

    def _open(self) -> None:
        self._bus = open_bus(self.link, f"{self.name}")
        self._stop.clear()
        self._loop_at = None
        self._seen_hi = -float("inf")
        self._end_resync()
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

    def _send(
        self, arbitration_id: int, data: bytes, remote: bool = False, *, setpoint: bool = False
    ) -> bool:
        """Send one frame; a ``setpoint`` only if no gap in the loop is being judged.

        A set-point's check is made under the send lock, just before the frame goes to the bus:
        a caller that decided to send before a pause of the process (a SIGSTOP between its
        decision and the send, or while it waited for a lock) does not send it after the
        SIGCONT before the devices' feedback was judged.

        Args:
            arbitration_id: The frame's id.
            data: Its data.
            remote: A remote (RTR) frame.
            setpoint: A set-point, held back while a gap is judged.

        Returns:
            Whether the frame went out (False: a set-point held back).

        Raises:
            StateError: The bus is not open.
            DriverOperationError: The bus refused the frame.
        """
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
                if setpoint and self._check_gap(self.clock.monotonic()):
                    return False
                bus.send(msg)
        except can.CanError as err:
            raise DriverOperationError(f"{self.name}: CAN send failed: {err}") from err
        # python-can packs the frame before its system call: a process stopped in between
        # sends it after SIGCONT. Such a frame cannot be recalled; it is superseded at once.
        if setpoint and self._check_gap(self.clock.monotonic()):
            logger.warning(
                "driver %s: a set-point to id 0x%x was being sent when the loop stalled",
                self.name,
                arbitration_id,
            )
            self._sent_late(arbitration_id)
        return True

    def _rx_loop(self) -> None:
        bus = self._bus
        assert bus is not None
        stop = self._stop
        while not stop.is_set():
            gen = self._resync_gen  # read before the look at the queue it stands for
            self._rx_seen = self.clock.monotonic()  # the queue is empty as of now
            self._rx_idle = True
            try:
                msg = bus.recv(_RX_POLL)
            except can.CanError as err:
                self._rx_idle = False
                logger.warning("driver %s: CAN receive failed: %s", self.name, err)
                stop.wait(_RX_POLL)
                continue
            self._rx_idle = False
            while msg is not None and not stop.is_set():  # drain what queued
                self._handle(msg)
                try:
                    msg = bus.recv(0)
                except can.CanError:
                    msg = None
            if self._resync is not None and self._drain_mark is None and gen == self._resync_gen:
                self._drain_mark = self._rx_count  # what comes now came after the gap

    def _handle(self, msg: can.Message) -> None:
        if msg.is_error_frame or msg.is_remote_frame:
            return
        self._rx_count += 1
        try:
            self._on_frame(msg)
        except Exception:  # one bad frame never kills the receive thread
            logger.exception("driver %s: handling %s failed", self.name, msg)

    def _link_seen(self, now: float) -> float:
        """The clock time as of which the receive thread has handled everything on the link.

        Now while it waits on an empty queue (and no gap in the loop is being judged), else the
        time it last found the queue empty; never earlier than an answer given before (the
        supervisor's and the receive thread's judgements agree).
        """
        seen = now if self._rx_idle and self._resync is None else min(now, self._rx_seen)
        if seen > self._seen_hi:  # each answer was true when given: later ones never go back
            self._seen_hi = seen
        return self._seen_hi

    def _sup_loop(self) -> None:
        due = last = self.clock.monotonic()
        while True:
            with self._cond:
                while not self._stop.is_set():
                    wake = due
                    # no stream is judged stale while a gap is (the link is seen as before it)
                    deadline = self._deadline() if self._resync is None else due
                    if deadline < due:  # never sooner than an eighth of a period after the last
                        wake = max(deadline, last + self.supervise_period / 8)
                    left = wake - self.clock.monotonic()
                    if left <= 0:
                        break
                    self.clock.wait(self._cond, left)
            if self._stop.is_set():
                return
            now = last = self.clock.monotonic()
            try:
                self._check_gap(now, supervisor=True)
                if now >= due:
                    self._on_period(now)
                    due = max(due + self.supervise_period, now)
                else:
                    self._on_deadline(now)
                if self._resync is not None:
                    self._resync_step(now)
                self._evaluate()
            except Exception:
                logger.exception("driver %s: supervision failed", self.name)

    # ---- gaps in the loop ------------------------------------------------------------------

    def _check_gap(self, now: float, *, supervisor: bool = False) -> bool:
        """Find a gap in the supervisor's loop at ``now``; whether set-points must wait.

        Args:
            now: Clock seconds.
            supervisor: The supervisor's own wake (it moves the loop's time on).

        Returns:
            Whether a gap is being judged (no set-point may go out).
        """
        real = time.monotonic()
        with self._gap_lock:
            last = self._loop_at
            late = last is not None and now - last > self.gap_limit
            # a new gap while one is judged starts the judging again: the feedback that
            # came before it (fresh for the first gap) says nothing about the devices now
            if late and real - self._loop_real > self._gap_real:
                assert last is not None
                gap = now - last
                self.gaps += 1
                self.gap_longest = max(self.gap_longest, gap)
                self._drain_mark = None
                self._resync_gen += 1
                self._resync = now
                logger.warning(
                    "driver %s: its loop stalled for %.3f s (a pause of the process?): set-points"
                    " wait for the devices' feedback",
                    self.name,
                    gap,
                )
                self._on_gap(now, gap)
            if supervisor:
                self._loop_at, self._loop_real = now, real
            return self._resync is not None

    def _end_resync(self) -> None:
        with self._gap_lock:
            self._resync = None
            self._drain_mark = None

    def _resync_step(self, now: float) -> None:
        """After a gap: once every device's feedback is fresh, judge it; fine: resume."""
        mark = self._drain_mark
        if mark is None or not self._fresh(mark):
            self._ask_feedback(now)
            return
        if self._problem(now) is not None:
            return  # reported by _evaluate; the held set-points stay unsent
        with self._gap_lock:
            if self._drain_mark != mark:
                return
            self._resync = None
            self._drain_mark = None
        logger.info("driver %s: fresh feedback after the gap, set-points resume", self.name)
        self._resume()

    def _deadline(self) -> float:
        """The clock time a stream becomes stale (the supervisor wakes then), or infinity."""
        return float("inf")

    def _on_deadline(self, now: float) -> None:
        """Judge the streams at a deadline of :meth:`_deadline` (supervisor thread)."""

    def _on_gap(self, now: float, gap: float) -> None:
        """A gap of ``gap`` clock seconds ended at ``now`` (``_gap_lock`` held)."""

    def _fresh(self, mark: int) -> bool:
        """Whether every device sent feedback numbered above ``mark`` (after the gap)."""
        return True

    def _ask_feedback(self, now: float) -> None:
        """Ask the devices for feedback while a gap is judged (supervisor thread)."""

    def _resume(self) -> None:
        """Send the held set-points after a gap was judged fine (supervisor thread)."""

    def _sent_late(self, arbitration_id: int) -> None:
        """A set-point to ``arbitration_id`` went out as a gap in the loop was found."""

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

    def _listen_real(self, seconds: float) -> None:
        """Let the receive thread take answers for ``seconds`` of real time.

        Real time, like the safe state's confirmation: the clock of a test may stand still.
        """
        deadline = time.monotonic() + seconds
        with self._cond:
            while (left := deadline - time.monotonic()) > 0 and not self._stop.is_set():
                self._cond.wait(left)

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
