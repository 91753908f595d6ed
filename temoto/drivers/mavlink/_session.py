"""The MAVLink session under :class:`~temoto.drivers.mavlink.driver.MavlinkDriver`.

The lowest layer of the driver, by concept: the link and the two threads that serve it
(``temoto-mavlink-<name>-rx`` parses every datagram into the cache of what the vehicle said;
``temoto-mavlink-<name>-hb`` sends this ground station's heartbeat and watches the vehicle's,
its streams' ages and its health), and commands with their acknowledgement
(``COMMAND_LONG`` → ``COMMAND_ACK``, retried, with the vehicle's STATUSTEXT reasons). The
layers above add the parameter protocol (:mod:`~temoto.drivers.mavlink._parameters`), mission
transfers (:mod:`~temoto.drivers.mavlink._mission_transfer`) and the vehicle's verbs and safe
state (:mod:`~temoto.drivers.mavlink.driver`); the driver's docstring says what each does.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import math
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, ClassVar, Final

from temoto.clock import Clock
from temoto.drivers.base import Driver, DriverState
from temoto.drivers.capabilities import MissionProgress
from temoto.drivers.mavlink import missions
from temoto.drivers.mavlink import protocol as p
from temoto.drivers.mavlink.link import Link, LinkSpec, parse_link
from temoto.drivers.mavlink.protocol import Codec, Message
from temoto.drivers.mavlink.settings import failsafe_params
from temoto.drivers.supervision import FaultWindow, StreamAge
from temoto.errors import (
    DriverError,
    DriverOperationError,
    DriverTimeoutError,
    MavlinkCommandError,
    StateError,
)

__all__ = ["LINK_GAP", "ModeChange", "Session"]

logger = logging.getLogger(__name__)

_POLL: Final = 0.05  # real seconds per socket read (also how often waiters re-check)
_UNKNOWN_VOLTAGE: Final = 65535
_SEVERITY_LEVEL: Final = {0: 50, 1: 50, 2: 50, 3: 40, 4: 30, 5: 20, 6: 20, 7: 10}
_TEXT_QUIET: Final = 0.1  # once a refusal's text came: seconds without another end the wait
#: Clock seconds without any message of the autopilot after which its next one is a link gap
#: (logged at WARNING, counted in ``link_gaps``): one and a half of its heartbeat periods.
LINK_GAP: Final = 1.5 * p.VEHICLE_HEARTBEAT_PERIOD
#: Real seconds the receive thread may go without running (it reads every ``_POLL``) before
#: what it reads next is taken as a backlog queued while this process did not run.
_PAUSE: Final = 0.5
#: The autopilot's sequence number going back by more than :data:`SEQ_REORDER` this many times
#: within ``heartbeat_timeout`` means two senders use its ids: a duplicate system id. (A number
#: that stays the same is not counted: some senders never advance it.)
SEQ_JUMPS: Final = 3
#: A step back by at most this much is a reordering (a UDP network, or a sender whose threads
#: send what they packed out of order), not a second sender.
SEQ_REORDER: Final = 16
#: Real seconds, at least, the receive thread may go without coming round before the watch
#: reports it stuck (``heartbeat_timeout`` when that is longer in real seconds).
_STUCK: Final = 2.0
#: Clock seconds between two WARNING lines about the same ignored source.
_IGNORED_LOG_EVERY: Final = 60.0


@dataclass(frozen=True, slots=True)
class ModeChange:
    """A flight-mode change the autopilot's HEARTBEAT showed.

    Attributes:
        old: The mode before (``GUIDED``).
        new: The mode after (``RTL``).
        stamp: Clock seconds of the heartbeat that showed it.
        commanded: Whether this driver had asked for ``new`` shortly before (otherwise the
            vehicle changed by itself: a failsafe, a pilot's switch, another ground station).
    """

    old: str
    new: str
    stamp: float
    commanded: bool


class Session(Driver):
    """The link, the receive cache, supervision and commands of a MAVLink driver.

    Not used alone: :class:`~temoto.drivers.mavlink.driver.MavlinkDriver` is built on it, and
    its docstring lists the arguments.
    """

    #: Seconds (clock) after a FAILED or DENIED ack during which the vehicle's STATUSTEXTs are
    #: attached to the error (ArduPilot sends the reason after the ack).
    STATUS_TEXT_WINDOW: ClassVar[float] = 0.5

    def __init__(
        self,
        name: str,
        *,
        link: str,
        clock: Clock | None = None,
        system_id: int | None = None,
        component_id: int = 1,
        gcs_system_id: int = 255,
        gcs_component_id: int = 190,
        heartbeat_period: float = 1.0,
        heartbeat_timeout: float = 3.0,
        init_timeout: float = 5.0,
        command_timeout: float = 1.0,
        command_retries: int = 2,
        mission_timeout: float = 1.5,
        mission_retries: int = 5,
        stream_rate: float = 10.0,
        status_texts: int = 20,
        gcs_failsafe: Mapping[str, float] | None = None,
    ) -> None:
        super().__init__(name, clock=clock)
        self.link_spec: LinkSpec = parse_link(link)
        for key, ident, low in (
            ("system_id", system_id, 1),
            ("component_id", component_id, 0),
            ("gcs_system_id", gcs_system_id, 1),
            ("gcs_component_id", gcs_component_id, 0),
        ):
            if ident is not None and (
                isinstance(ident, bool) or not isinstance(ident, int) or not low <= ident <= 255
            ):
                raise ValueError(f"{key} must be an integer {low}..255, got {ident!r}")
        for key, value in (
            ("heartbeat_period", heartbeat_period),
            ("heartbeat_timeout", heartbeat_timeout),
            ("init_timeout", init_timeout),
            ("command_timeout", command_timeout),
            ("mission_timeout", mission_timeout),
        ):
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{key} must be a positive number of seconds, got {value!r}")
        if not (isinstance(command_retries, int) and 0 <= command_retries <= 10):
            raise ValueError(f"command_retries must be an integer 0..10, got {command_retries!r}")
        if not (isinstance(mission_retries, int) and 0 <= mission_retries <= 20):
            raise ValueError(f"mission_retries must be an integer 0..20, got {mission_retries!r}")
        if not (math.isfinite(stream_rate) and 0 <= stream_rate <= 1000):
            raise ValueError(f"stream_rate must be 0..1000 Hz, got {stream_rate!r}")
        if not (isinstance(status_texts, int) and status_texts >= 1):
            raise ValueError(f"status_texts must be a positive integer, got {status_texts!r}")
        if system_id is not None and system_id == gcs_system_id:
            raise ValueError(
                f"gcs_system_id must differ from the vehicle's system_id ({system_id}): the"
                " vehicle would take this ground station's messages for its own"
            )
        self.system_id = system_id
        self.component_id = component_id
        self.heartbeat_period = float(heartbeat_period)
        self.heartbeat_timeout = float(heartbeat_timeout)
        self.init_timeout = float(init_timeout)
        self.command_timeout = float(command_timeout)
        self.command_retries = command_retries
        self.mission_timeout = float(mission_timeout)
        self.mission_retries = mission_retries
        self.stream_rate = float(stream_rate)
        #: ArduPilot parameter → value, set at configure (from ``gcs_failsafe``).
        self.failsafe_params: dict[str, float] = failsafe_params(gcs_failsafe)
        timeout = self.failsafe_params.get("FS_GCS_TIMEOUT")
        if timeout is not None and self.heartbeat_period > timeout / 2:
            raise ValueError(
                f"heartbeat_period must be at most half the GCS failsafe timeout ({timeout:g} s),"
                f" got {self.heartbeat_period:g}: one lost heartbeat must not trigger it"
            )
        if timeout is not None and self.heartbeat_timeout > timeout:
            raise ValueError(
                f"heartbeat_timeout must be at most the GCS failsafe timeout"
                f" (gcs_failsafe.timeout, {timeout:g} s), got {self.heartbeat_timeout:g}: a link"
                " outage long enough to set off the vehicle's failsafe must be a fault here too"
            )
        self._gcs_ids = (gcs_system_id, gcs_component_id)
        self._codec = Codec(gcs_system_id, gcs_component_id)
        self._link: Link | None = None
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._cond = threading.Condition()  # the cache and the acks; notified on every read
        self._watch = threading.Condition()  # wakes the heartbeat thread
        self._command_lock = threading.Lock()
        self._param_lock = threading.Lock()  # one public parameter exchange at a time
        self._mission_lock = threading.Lock()  # one mission transfer at a time
        self._mission_listeners: list[Callable[[MissionProgress], None]] = []
        self._mode_listeners: list[Callable[[ModeChange], None]] = []
        self._eval_lock = threading.Lock()
        self._texts: collections.deque[str] = collections.deque(maxlen=status_texts)
        self._ages: dict[str, StreamAge] = {}
        self._bad_window = FaultWindow()
        self._seq_jumps = FaultWindow(SEQ_JUMPS, self.heartbeat_timeout)
        # ---- the driver's record of the modes: kept across a recovery's configure, so that
        # the safe state it sent before (LOITER, BRAKE) is still its own when the vehicle
        # shows it after the link came back ----
        self._last_mode: int | None = None  # the mode the newest HEARTBEAT showed
        # mode number → the autopilot's HEARTBEATs counted when this driver asked for it, until
        # a HEARTBEAT shows the change into it
        self._commanded: dict[int, int] = {}
        self._beats = 0  # the autopilot's HEARTBEATs heard by this driver
        self._reset()

    def _reset(self) -> None:
        self._target: int | None = self.system_id
        self._last_hb: float | None = None
        self._last_msg = self.clock.monotonic()
        self._autopilot = p.MAV_AUTOPILOT_INVALID
        self._armed = False
        self._custom_mode = 0
        self._position = (0.0, 0.0, 0.0)
        self._attitude = (0.0, 0.0, 0.0)
        self._voltage = math.nan
        self._remaining = -1
        self._home: tuple[float, float, float] | None = None
        self._landed_state = 0
        #: When this driver last asked the vehicle to arm or take off (clock seconds): until a
        #: newer heartbeat arrives, "disarmed" and "landed" are not to be trusted.
        self._moved_at: float | None = None
        self._landed_at: float | None = None  # when EXTENDED_SYS_STATE last said
        #: When this driver last asked for a take-off or a mission start, and when
        #: EXTENDED_SYS_STATE last said the vehicle was off the ground: between the two, an
        #: ON_GROUND report is a vehicle spooling up to leave it, not a landed one.
        self._lift_at: float | None = None
        self._off_ground_at: float | None = None
        self._unhealthy: tuple[str, ...] = ()
        self._bad_at_hb = 0  # the vehicle's bad frames when its newest heartbeat came
        self._vehicle_bad = 0  # bad frames from the vehicle's address (or a serial line)
        self._acks: dict[int, tuple[int, int]] = {}  # command → (result, arrival number)
        self._ack_count = 0
        self._text_count = 0
        self._mine = False  # the current FAULT was reported by this driver's watch
        self._texts.clear()
        self._received = 0
        self._params: dict[str, tuple[float, int]] = {}  # name → (value, MAV_PARAM_TYPE)
        self._param_count = 0  # PARAM_VALUE arrivals
        self._param_seen: dict[str, int] = {}  # name → arrival number of its newest value
        #: name → MAV_PARAM_ERROR of a PARAM_ERROR about it (newer ArduPilot answers an unknown
        #: name or a bad value so; older ones stay silent), since its exchange began.
        self._param_errors: dict[str, int] = {}
        #: Mission-transfer messages for this GCS: (arrival number, message), newest last.
        self._mission_rx: collections.deque[tuple[int, Message]] = collections.deque(maxlen=64)
        self._mission_seq = 0
        self._mission_total = 0  # items of the mission this driver uploaded or downloaded
        self._progress = MissionProgress()
        self._notify: list[tuple[Callable[[MissionProgress], None], MissionProgress]] = []
        self._ages.clear()
        self._stale: StreamAge | None = None  # the stream whose staleness is the fault
        self._bad_window.clear()
        self._drained_at: float | None = None  # clock time the link was last read empty
        self._beat_now = False  # send a heartbeat at once (the vehicle's address is new)
        self._foreign = 0  # bad frames from addresses other than the vehicle's
        self._foreign_seen: set[Any] = set()
        # ---- trust: only the autopilot (system _target, component component_id) ----
        self._vehicle_addr: Any = None  # where the autopilot's frames come from (UDP links)
        self._vehicle_at: float | None = None  # clock time of the autopilot's newest message
        self._last_seq: int | None = None
        self._last_frame: Message | None = None
        self._seq_jumps.clear()
        self._duplicate: str | None = None  # why two vehicles answer as this one
        self._duplicate_at = -math.inf
        self._ignored: dict[str, int] = {}  # source → messages ignored (not the autopilot)
        self._ignored_logged: dict[str, float] = {}  # source → clock time of its last line
        self._link_gaps = 0
        self._backlog = False  # reading what queued while this process did not run
        self._rx_turn = time.monotonic()  # real time the receive thread last came round
        # ---- flight modes since configure (the record of asks: see __init__) ----
        self._mode_change: ModeChange | None = None
        self._mode_notify: list[ModeChange] = []  # changes whose listeners are still to call
        self._uncommanded = 0

    def on_shutdown(self) -> None:
        """Stop and join the threads, close the link."""
        self._stop.set()
        with self._watch:
            self._watch.notify_all()
        with self._cond:
            self._cond.notify_all()
        for thread in self._threads:
            if thread is not threading.current_thread():
                thread.join()
        self._threads = []
        if self._link is not None:
            self._link.close()
            self._link = None

    def _best_effort(self, command: int, *params: float) -> bool:
        try:
            self._send_command(command, params, retries=0, texts=False)
        except DriverError as err:
            logger.info("driver %s: %s", self.name, err)
            return False
        return True

    def _require_link(self, what: str) -> None:
        if self._link is None or self.state in (DriverState.UNCONFIGURED, DriverState.FINALIZED):
            raise StateError(f"{self.name}: {what} needs a configured driver ({self.state.value})")

    @property
    def messages_received(self) -> int:
        """Valid messages received since configure (from any system)."""
        return self._received

    @property
    def foreign_frames(self) -> int:
        """Bad frames since configure from addresses other than the vehicle's (never a fault)."""
        return self._foreign

    @property
    def bad_frames(self) -> int:
        """Frames dropped since configure (bad CRC, unknown message id)."""
        return self._codec.bad_frames

    @property
    def ignored_messages(self) -> dict[str, int]:
        """Valid messages ignored since configure, by source: everything not the autopilot's.

        Keys read ``system 1 component 100`` (another component of the vehicle's system, or
        another system) or ``system 1 component 1 at 127.0.0.1:5760`` (a second sender using
        the autopilot's ids: a duplicate system id).
        """
        with self._cond:
            return dict(self._ignored)

    @property
    def link_gaps(self) -> int:
        """Gaps in the autopilot's messages longer than :data:`LINK_GAP` since configure."""
        return self._link_gaps

    @property
    def last_mode_change(self) -> ModeChange | None:
        """The newest flight-mode change the autopilot's HEARTBEAT showed, or None."""
        with self._cond:
            return self._mode_change

    @property
    def uncommanded_mode_changes(self) -> int:
        """Mode changes since configure that this driver had not asked for."""
        return self._uncommanded

    def add_mode_listener(self, listener: Callable[[ModeChange], None]) -> None:
        """Call ``listener`` with each flight-mode change (on the receive thread: be quick).

        Args:
            listener: Gets the :class:`ModeChange` (``commanded`` False: a failsafe, the pilot
                or another ground station changed the mode).
        """
        with self._cond:
            self._mode_listeners.append(listener)

    def _autopilot_name(self) -> str:
        """``system 1, component 1`` (the system once known)."""
        system = "?" if self._target is None else str(self._target)
        return f"system {system}, component {self.component_id}"

    def _note_mode(self, number: int) -> None:
        """Record that this driver asked for flight mode ``number`` (now)."""
        with self._cond:
            self._commanded[number] = self._beats

    # ---- commands ----------------------------------------------------------------------------
    def _send_command(
        self,
        command: int,
        params: tuple[float, ...],
        *,
        retries: int | None = None,
        frame: int | None = None,
        position: tuple[int, int, float] | None = None,
        texts: bool = True,
    ) -> None:
        """Send a command until acknowledged (COMMAND_INT when ``position`` is given).

        A refusal's error carries the STATUSTEXTs that arrived since the command was sent;
        after a FAILED or DENIED ack (and ``texts``), those arriving within
        :attr:`STATUS_TEXT_WINDOW` are waited for.
        """
        tries = 1 + (self.command_retries if retries is None else retries)
        values = [*params, *([0.0] * (7 - len(params)))]
        with self._command_lock:
            with self._cond:
                target = self._target or 1
                start_acks, start_texts = self._ack_count, self._text_count
            for attempt in range(tries):
                if position is None:
                    frame_bytes = self._codec.encode(
                        "COMMAND_LONG",
                        target_system=target,
                        target_component=self.component_id,
                        command=command,
                        confirmation=attempt,
                        param1=values[0],
                        param2=values[1],
                        param3=values[2],
                        param4=values[3],
                        param5=values[4],
                        param6=values[5],
                        param7=values[6],
                    )
                else:
                    frame_bytes = self._codec.encode(
                        "COMMAND_INT",
                        target_system=target,
                        target_component=self.component_id,
                        frame=frame or 0,
                        command=command,
                        current=0,
                        autocontinue=0,
                        param1=values[0],
                        param2=values[1],
                        param3=values[2],
                        param4=values[3],
                        x=position[0],
                        y=position[1],
                        z=position[2],
                    )
                self._write(frame_bytes)
                result = self._await_ack(command, start_acks, self.command_timeout)
                if result is None:
                    continue
                if result == p.MAV_RESULT_ACCEPTED:
                    return
                if texts and result in (p.MAV_RESULT_FAILED, p.MAV_RESULT_DENIED):
                    self._await_texts(start_texts)
                with self._cond:
                    count = self._text_count - start_texts
                    news = list(self._texts)[-count:] if count > 0 else []
                said = f" (vehicle: {'; '.join(news)})" if news else ""
                raise MavlinkCommandError(
                    f"{self.name}: {p.command_name(command)} refused by the autopilot"
                    f" ({self._autopilot_name()}): {p.result_name(result)}{said}",
                    command=command,
                    result=result,
                )
        raise DriverTimeoutError(
            f"{self.name}: no COMMAND_ACK for {p.command_name(command)} from the autopilot"
            f" ({self._autopilot_name()}) in {tries} tries of {self.command_timeout:g} s"
        )

    def _await_texts(self, after: int) -> None:
        """Wait for the STATUSTEXTs that follow a refusal (bounded by STATUS_TEXT_WINDOW).

        Ends when no text came within the window, or :data:`_TEXT_QUIET` seconds after the
        newest one (ArduPilot may send several "PreArm:" lines).
        """
        deadline = self.clock.monotonic() + self.STATUS_TEXT_WINDOW
        seen = after
        while (left := deadline - self.clock.monotonic()) > 0:
            wait = left if seen == after else min(left, _TEXT_QUIET)
            if not self._await(lambda n=seen: self._text_count > n, wait):  # type: ignore[misc]
                return
            with self._cond:
                seen = self._text_count

    def _await_ack(self, command: int, after: int, timeout: float) -> int | None:
        """The result of the first final ack of ``command`` newer than arrival ``after``."""
        got: list[int] = []

        def acked() -> bool:
            ack = self._acks.get(command)
            if ack is None or ack[1] <= after:
                return False
            if ack[0] == p.MAV_RESULT_IN_PROGRESS:
                return False  # the vehicle is still at it; the final ack comes later
            got.append(ack[0])
            return True

        return got[0] if self._await(acked, timeout) else None

    def _await(self, pred: Callable[[], bool], timeout: float) -> bool:
        """Wait (cache lock taken) until ``pred()``, for ``timeout`` clock seconds.

        The wait also ends after ``clock.real_seconds(timeout)`` real seconds, so a virtual
        clock nobody advances cannot hang a command forever.
        """
        deadline = self.clock.monotonic() + timeout
        real_deadline = time.monotonic() + self.clock.real_seconds(timeout) + _POLL
        with self._cond:
            while not pred():
                now = self.clock.monotonic()
                if now >= deadline or time.monotonic() >= real_deadline or self._stop.is_set():
                    return False
                self.clock.wait(self._cond, deadline - now)
        return True

    def _write(self, frame: bytes) -> bool:
        link = self._link
        if link is None:
            raise StateError(f"{self.name}: the link is closed")
        try:
            return link.write(frame)
        except OSError as err:
            raise DriverOperationError(f"{self.name}: sending failed: {err}") from err

    # ---- threads -----------------------------------------------------------------------------
    def _rx_loop(self) -> None:
        link = self._link
        assert link is not None
        last_turn = time.monotonic()
        while not self._stop.is_set():
            try:
                data, sender = link.receive(_POLL)
                turn = time.monotonic()
                if turn - last_turn > _PAUSE and not self._stop.is_set():
                    # what waits in the socket queued while we did not run: its gaps are ours
                    self._backlog = True
                    logger.warning(
                        "%s: this process did not run for %.1f s (paused or overloaded):"
                        " reading what the vehicle sent meanwhile",
                        self.name,
                        turn - last_turn,
                    )
                last_turn = self._rx_turn = turn
            except OSError as err:
                if self._stop.is_set():
                    break
                self._evaluate(DriverOperationError(f"{self.name}: the link failed: {err}"))
                self._stop.wait(_POLL)
                continue
            now = self.clock.monotonic()
            if not data:
                self._drained_at = now
                self._backlog = False
                with self._cond:
                    self._cond.notify_all()  # waiters re-check their real-time guards
                continue
            bad_before = self._codec.bad_frames
            if link.datagrams:
                messages = self._codec.decode_datagram(data)
            else:
                messages = self._codec.decode(data)
            bad = self._codec.bad_frames - bad_before
            self._received += len(messages)
            check = False
            with self._cond:
                duplicate_at = self._duplicate_at
                ours = False
                for msg in messages:
                    if self._trusted(msg, sender, now):
                        ours = True
                        check |= self._absorb(msg, now)
                check |= self._duplicate_at != duplicate_at
                if ours and link.accept_peer(sender):
                    logger.info("driver %s: the vehicle is at %s", self.name, sender)
                    self._beat_now = True  # greet it at once: its GCS failsafe starts then
                if bad:
                    check |= self._count_bad(bad, sender, link.peer, ours, now)
                if not link.pending():
                    self._drained_at = now
                    self._backlog = False
                self._cond.notify_all()
                notify, self._notify = self._notify, []
                changes, self._mode_notify = self._mode_notify, []
                mode_listeners = list(self._mode_listeners) if changes else []
            for listener, progress in notify:
                try:
                    listener(progress)
                except Exception:
                    logger.exception("driver %s: a mission listener raised", self.name)
            for change in changes:
                for on_change in mode_listeners:
                    try:
                        on_change(change)
                    except Exception:
                        logger.exception("driver %s: a mode listener raised", self.name)
            if self._beat_now:
                with self._watch:
                    self._watch.notify_all()
            if check:
                self._evaluate()

    def _count_bad(self, bad: int, sender: Any, peer: Any, ours: bool, now: float) -> bool:
        """Count bad frames (lock held): the vehicle's go to the fault window, others' not.

        Returns:
            True when the vehicle's bad frames may have made a fault.
        """
        if sender is None or ours or sender == peer:
            self._vehicle_bad += bad
            fault = False
            for _ in range(bad):
                fault = self._bad_window.add(now)
            return fault
        self._foreign += bad
        if sender not in self._foreign_seen:
            self._foreign_seen.add(sender)
            logger.warning(
                "driver %s: malformed datagrams from %s (not the vehicle): counted and dropped",
                self.name,
                sender,
            )
        return False

    def _trusted(self, msg: Message, sender: Any, now: float) -> bool:
        """Whether ``msg`` is the autopilot's (lock held); others are counted and ignored.

        The autopilot is component ``component_id`` (MAV_COMP_ID_AUTOPILOT1, 1, by default) of
        system ``system_id``, or, without a ``system_id``, of the system of the first
        HEARTBEAT from that component whose ``autopilot`` is not ``MAV_AUTOPILOT_INVALID`` and
        whose ``type`` is not ``MAV_TYPE_GCS``. On a UDP link its frames must come from the
        address its first frame came from: the same ids from another address while that one
        is still heard (within ``heartbeat_timeout``) are a second vehicle, a duplicate system
        id (after a silence as long, the vehicle is taken to have moved). On every link, its
        sequence number going back :data:`SEQ_JUMPS` times within ``heartbeat_timeout`` (two
        senders' counters interleaving) is a duplicate system id too. An exact repeat of the
        previous frame (a link that delivers twice) is dropped without counting.
        """
        if self._target is None:
            if (
                msg.name != "HEARTBEAT"
                or msg.src_component != self.component_id
                or msg.get_int("autopilot") == p.MAV_AUTOPILOT_INVALID
                or msg.get_int("type") == p.MAV_TYPE_GCS
            ):
                return False  # no vehicle chosen yet: nothing to compare with
            self._target = msg.src_system
        if msg.src_system != self._target or msg.src_component != self.component_id:
            self._ignore(msg, f"system {msg.src_system} component {msg.src_component}", now)
            return False
        if sender is not None and sender != self._vehicle_addr:
            if self._vehicle_addr is None:
                self._vehicle_addr = sender
            elif self._vehicle_at is not None and now - self._vehicle_at <= self.heartbeat_timeout:
                where = f"{_address(sender)} and {_address(self._vehicle_addr)}"
                self._duplicate_seen(f"the autopilot's messages come from {where}", now)
                source = f"system {msg.src_system} component {msg.src_component}"
                self._ignore(msg, f"{source} at {_address(sender)}", now)
                return False
            else:
                logger.warning(
                    "%s: the autopilot (%s) now sends from %s (was %s, silent for %.1f s)",
                    self.name,
                    self._autopilot_name(),
                    _address(sender),
                    _address(self._vehicle_addr),
                    math.inf if self._vehicle_at is None else now - self._vehicle_at,
                )
                self._vehicle_addr = sender
                self._last_seq = None
        if msg.seq >= 0:
            step = 1 if self._last_seq is None else (msg.seq - self._last_seq) & 0xFF
            if step == 0 and msg == self._last_frame:
                return False  # the same frame delivered twice
            if 128 < step < 256 - SEQ_REORDER and self._seq_jumps.add(now):
                self._duplicate_seen(
                    f"the autopilot's sequence numbers went back {SEQ_JUMPS} times within"
                    f" {self.heartbeat_timeout:g} s, as two senders' interleave",
                    now,
                )
            if step < 256 - SEQ_REORDER:  # a reordered frame does not move the count back
                self._last_seq = msg.seq
            self._last_frame = msg
        if self._vehicle_at is not None and now - self._vehicle_at > LINK_GAP:
            for age in self._ages.values():
                age.feed(now)  # the whole link was out, not a stream: judge them from now on
            gap = now - self._vehicle_at
            if not self._backlog:
                self._link_gaps += 1
                logger.warning(
                    "%s: no message from the autopilot (%s) for %.1f s: the link is back"
                    " (the vehicle may have changed its mode meanwhile)",
                    self.name,
                    self._autopilot_name(),
                    gap,
                )
        self._vehicle_at = now
        return True

    def _duplicate_seen(self, what: str, now: float) -> None:
        """Evidence of a second vehicle using the autopilot's ids (lock held)."""
        if self._duplicate is None:
            logger.error("%s: duplicate system id %s: %s", self.name, self._target, what)
        self._duplicate = f"{self.name}: duplicate system id {self._target}: {what}"
        self._duplicate_at = now

    def _ignore(self, msg: Message, source: str, now: float) -> None:
        """Count a message that is not the autopilot's; say so, rate-limited (lock held)."""
        count = self._ignored.get(source, 0) + 1
        self._ignored[source] = count
        if msg.name == "STATUSTEXT":
            logger.info("%s: %s says: %s", self.name, source, msg.get_text("text"))
        if msg.src_system != self._target:
            if count == 1:
                logger.info(
                    "%s: %s is not the vehicle (system %s): its messages are ignored",
                    self.name,
                    source,
                    self._target,
                )
            return
        last = self._ignored_logged.get(source)
        if last is None or now - last >= _IGNORED_LOG_EVERY:
            self._ignored_logged[source] = now
            logger.warning(
                "%s: ignored %s from %s: only the autopilot (%s) is trusted (%d ignored so far)",
                self.name,
                msg.name,
                source,
                self._autopilot_name(),
                count,
            )

    def _absorb(self, msg: Message, now: float) -> bool:
        """Update the cache with one of the autopilot's messages (lock held).

        Returns:
            True if health may have changed.
        """
        self._last_msg = max(self._last_msg, now)
        name = msg.name
        age = self._ages.get(name)
        changed = False
        if age is not None:
            age.feed(now)
            if self._stale is age:
                self._stale = None
                changed = True
        if name == "HEARTBEAT":
            self._last_hb = now
            self._beats += 1
            self._bad_at_hb = self._vehicle_bad
            self._autopilot = msg.get_int("autopilot")
            self._armed = bool(msg.get_int("base_mode") & p.MAV_MODE_FLAG_SAFETY_ARMED)
            mode = msg.get_int("custom_mode")
            if self._last_mode is not None and mode != self._last_mode:
                self._mode_changed(self._last_mode, mode, now)
            self._last_mode = mode
            self._custom_mode = mode
            return True
        if name == "GLOBAL_POSITION_INT":
            self._position = (
                msg.get_int("lat") / 1e7,
                msg.get_int("lon") / 1e7,
                msg.get_int("relative_alt") / 1000.0,
            )
        elif name == "ATTITUDE":
            self._attitude = (msg.get_float("roll"), msg.get_float("pitch"), msg.get_float("yaw"))
        elif name == "SYS_STATUS":
            millivolts = msg.get_int("voltage_battery")
            self._voltage = math.nan if millivolts == _UNKNOWN_VOLTAGE else millivolts / 1000.0
            self._remaining = msg.get_int("battery_remaining")
            enabled = msg.get_int("onboard_control_sensors_present") & msg.get_int(
                "onboard_control_sensors_enabled"
            )
            bad = enabled & ~msg.get_int("onboard_control_sensors_health")
            unhealthy = tuple(sorted(n for n, bit in p.SENSOR_BITS.items() if bad & bit))
            changed |= unhealthy != self._unhealthy
            self._unhealthy = unhealthy
            return changed
        elif name == "STATUSTEXT":
            text = msg.get_text("text")
            self._texts.append(text)
            self._text_count += 1
            level = _SEVERITY_LEVEL.get(msg.get_int("severity"), logging.INFO)
            logger.log(level, "vehicle %s: %s", self.name, text)
        elif name == "COMMAND_ACK":
            if msg.fields.get("target_system", 0) in (0, self._codec.system_id):
                self._ack_count += 1
                self._acks[msg.get_int("command")] = (msg.get_int("result"), self._ack_count)
        elif name == "HOME_POSITION":
            self._home = (
                msg.get_int("latitude") / 1e7,
                msg.get_int("longitude") / 1e7,
                msg.get_int("altitude") / 1000.0,
            )
        elif name == "EXTENDED_SYS_STATE":
            self._landed_state = msg.get_int("landed_state")
            self._landed_at = now
            if self._landed_state > p.MAV_LANDED_STATE_ON_GROUND:  # in the air, taking off, landing
                self._off_ground_at = now
        elif name in missions.MISSION_MESSAGES:
            for listener in self._absorb_mission(msg):
                self._notify.append((listener, self._progress))
        elif name == "PARAM_ERROR":
            if msg.fields.get("target_system", 0) in (0, self._codec.system_id):
                self._param_errors[msg.get_text("param_id")] = msg.get_int("error")
        elif name == "PARAM_VALUE":
            param = msg.get_text("param_id")
            self._params[param] = (msg.get_float("param_value"), msg.get_int("param_type"))
            self._param_count += 1
            self._param_seen[param] = self._param_count
        return changed

    def _mode_changed(self, old: int, new: int, now: float) -> None:
        """The autopilot's HEARTBEAT shows another mode (lock held): record it, say it.

        Commanded when this driver asked for ``new`` at most as many HEARTBEATs ago as its
        command takes with every retry, plus two (the vehicle shows a mode with its next
        HEARTBEAT, one a second on ArduPilot): counted in HEARTBEATs, not clock time, so a
        receive thread that ran late under load does not make its own command the vehicle's.
        The ask is used up by the change: the vehicle switching into that mode again later
        (a pilot's LOITER after a pause's LOITER and a resume) is its own.
        """
        asked = self._commanded.pop(new, None)
        wait = (1 + self.command_retries) * self.command_timeout
        beats = math.ceil(wait / p.VEHICLE_HEARTBEAT_PERIOD) + 2
        commanded = asked is not None and self._beats - asked <= beats
        change = ModeChange(p.mode_name(old), p.mode_name(new), now, commanded)
        self._mode_change = change
        self._mode_notify.append(change)
        if commanded:
            logger.info("%s: the vehicle switched %s -> %s", self.name, change.old, change.new)
            return
        self._uncommanded += 1
        logger.warning(
            "%s: the vehicle switched %s -> %s (not commanded by this driver: a failsafe, the"
            " pilot or another ground station; HEARTBEAT of %s)",
            self.name,
            change.old,
            change.new,
            self._autopilot_name(),
        )

    def _absorb_mission(self, msg: Message) -> list[Callable[[MissionProgress], None]]:
        """A mission message (lock held); the listeners to call when progress changed."""
        name = msg.name
        if name in missions.TRANSFER_MESSAGES:
            if msg.fields.get("target_system", 0) not in (0, self._codec.system_id):
                return []
            if msg.fields.get("mission_type", 0) != p.MAV_MISSION_TYPE_MISSION:
                return []
            self._mission_seq += 1
            self._mission_rx.append((self._mission_seq, msg))
            return []
        old = self._progress
        if name == "MISSION_CURRENT":
            total = msg.fields.get("total", 0)
            # MISSION_CURRENT.total leaves out a home item 0 (on the last item, seq == total)
            known = self._mission_total or (total if 0 < total < 0xFFFF else 0)
            finished = old.finished or (
                msg.fields.get("mission_state", 0) == p.MISSION_STATE_COMPLETE
            )
            new = MissionProgress(msg.get_int("seq"), known, old.reached, finished)
        else:  # MISSION_ITEM_REACHED
            seq = msg.get_int("seq")
            total = old.total
            new = MissionProgress(
                max(old.current, seq), total, seq, old.finished or (total > 0 and seq >= total)
            )
        if new == old:
            return []
        self._progress = new
        return list(self._mission_listeners)

    def _watch_loop(self) -> None:
        next_hb = self.clock.monotonic()
        check = min(0.1, self.heartbeat_timeout / 10)
        wake: float | None = None
        while not self._stop.is_set():
            now = self.clock.monotonic()
            with self._cond:
                periods = [age.period for age in self._ages.values()]
            shortest = min(periods, default=check)
            # A late wake-up means this process was not running: the streams' gaps may be
            # ours, not the vehicle's; judge them at the next, punctual, round.
            punctual = wake is None or now - wake <= shortest
            if now >= next_hb or self._beat_now:
                self._beat_now = False
                next_hb = now + self.heartbeat_period
                with contextlib.suppress(DriverError, StateError):  # rx loop reports the link
                    self._write(
                        self._codec.encode(
                            "HEARTBEAT",
                            type=p.MAV_TYPE_GCS,
                            autopilot=p.MAV_AUTOPILOT_INVALID,
                            base_mode=0,
                            custom_mode=0,
                            system_status=p.MAV_STATE_ACTIVE,
                            mavlink_version=3,
                        )
                    )
            self._evaluate(streams=punctual)
            with self._watch:
                if self._stop.is_set():
                    break
                timeout = max(min(next_hb - now, check, shortest), 0.0)
                wake = now + timeout
                self.clock.wait(self._watch, timeout)

    def _evaluate(self, link_error: DriverError | None = None, *, streams: bool = False) -> None:
        """Report a fault, or the recovery from one this driver reported.

        Args:
            link_error: The link failed.
            streams: Judge the streams' ages now (the watch thread, when it woke on time).
                A stream is stale when it was overdue both at a moment the link had been
                read empty (data waiting in the socket never counts as missing) and when
                another message of the vehicle arrived (the vehicle talks, but not this
                stream; a vehicle that says nothing at all is the heartbeat timeout's case).
        """
        now = self.clock.monotonic()
        with self._cond:
            if self._duplicate is not None and now - self._duplicate_at > self.heartbeat_timeout:
                self._duplicate = None  # the second sender has been silent long enough
            duplicate = self._duplicate
            last_hb, unhealthy = self._last_hb, self._unhealthy
            corrupt = self._vehicle_bad > self._bad_at_hb
            drained, talked = self._drained_at, self._last_msg
            if streams and drained is not None and self._stale is None:
                for age in self._ages.values():
                    seen = min(drained, talked)
                    if age.last is not None and seen - age.last > age.max_age:
                        self._stale = age
                        break
            stale = self._stale
            window = self._bad_window
            bursts = window.recent(now) >= window.limit
            source = self._autopilot_name()
            rx_turn = self._rx_turn
        stuck = max(self.clock.real_seconds(self.heartbeat_timeout), _STUCK)
        # a heartbeat is overdue only when it was at a moment the link had been read empty:
        # datagrams queued while this process did not run are no gap on the wire
        seen = now if drained is None else min(now, drained)
        if streams and now - seen > self.heartbeat_timeout:
            seen = now  # never read empty for that long on time: the receiver is behind
        error: DriverError | None = link_error
        if error is None and duplicate is not None:
            error = DriverOperationError(duplicate)
        elif error is None and bursts:
            error = DriverOperationError(
                f"{self.name}: corrupt frames (bad CRC) from the vehicle's address:"
                f" {window.limit} or more within {window.window:g} s"
            )
        elif error is None and streams and time.monotonic() - rx_turn > stuck:
            # real seconds: the receive thread comes round every _POLL whatever the clock
            error = DriverOperationError(
                f"{self.name}: the link to the autopilot ({source}) was not read for"
                f" {time.monotonic() - rx_turn:.1f} s: the receive thread is stuck or this"
                " process is starved"
            )
        elif error is None and (last_hb is None or seen - last_hb > self.heartbeat_timeout):
            if corrupt:
                error = DriverOperationError(
                    f"{self.name}: only corrupt frames (bad CRC), no valid heartbeat within"
                    f" {self.heartbeat_timeout:g} s from the autopilot ({source})"
                )
            else:
                error = DriverTimeoutError(
                    f"{self.name}: no heartbeat within {self.heartbeat_timeout:g} s from the"
                    f" autopilot ({source})"
                )
        elif error is None and stale is not None:
            error = DriverTimeoutError(
                f"{self.name}: {stale.name} stale: none for over {stale.max_age:g} s"
                f" (expected every {stale.period:g} s) from the autopilot ({source})"
            )
        elif error is None and unhealthy:
            error = DriverOperationError(
                f"{self.name}: hardware error: unhealthy {', '.join(unhealthy)}"
                f" (SYS_STATUS of the autopilot, {source})"
            )
        with self._eval_lock:
            state = self.state
            if error is not None:
                if state in (DriverState.INACTIVE, DriverState.ACTIVE) or (
                    state is DriverState.FAULT and self._mine
                ):
                    self._mine = True
                    self.report_fault(error)
            elif self._mine and state is DriverState.FAULT:
                self._mine = False
                self.report_recovered(f"{self.name}: the vehicle answers and is healthy")


def _address(addr: Any) -> str:
    """``127.0.0.1:14550`` for a (host, port) address."""
    if isinstance(addr, tuple) and len(addr) >= 2:
        return f"{addr[0]}:{addr[1]}"
    return str(addr)
