"""The servo chain under the DYNAMIXEL driver: its port, its polls and their supervision.

The lower layer of the driver, by concept: the serial port and its transactions (READ, WRITE,
SYNC_READ, SYNC_WRITE through dynamixel-sdk, retried, their failures typed), the poll thread
(``temoto-dxl-<name>``) that reads the chain every period, feeds the goals to the servos' Bus
Watchdog and reads their status, and the supervision that turns what it finds into faults and
recoveries (stale feedback, bad packets, silent servos, hardware errors, an expired Bus
Watchdog). The driver above adds the profile, the lifecycle, the commands and the safe state;
its module docstring says what each does.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from typing import Final

from temoto.clock import Clock
from temoto.drivers.base import Driver, DriverState
from temoto.drivers.capabilities import JointState, JointStates
from temoto.drivers.dynamixel import _sdk
from temoto.drivers.dynamixel import control_table as ct
from temoto.drivers.dynamixel import protocol as p
from temoto.drivers.dynamixel.servos import (
    POSITION_MODES,
    ServoConfig,
    ServoStatus,
)
from temoto.drivers.dynamixel.settings import BAUD_RATES
from temoto.drivers.dynamixel.timing import (
    return_delay_units,
    watchdog_units,
)
from temoto.drivers.supervision import FaultWindow, StreamAge
from temoto.errors import (
    DriverError,
    DriverInitError,
    DriverOperationError,
    DriverTimeoutError,
    DynamixelHardwareError,
    StateError,
)

__all__ = ["BusLock", "ServoChain", "register_label"]

logger = logging.getLogger(__name__)

_PING_TRIES: Final = 3


def register_label(address: int, length: int) -> str:
    """The registers ``length`` bytes from ``address`` cover, for messages.

    Args:
        address: The first address.
        length: Bytes.

    Returns:
        ``Present Position (132)`` for one register, ``Present Current, Present Velocity,
        Present Position (126..135)`` for a span, ``address 200 (4 bytes)`` for unnamed bytes.
    """
    names = [r.name for r in ct.REGISTERS if address <= r.address < address + length]
    if not names:
        return f"address {address} ({length} bytes)"
    first = next(r for r in ct.REGISTERS if r.name == names[0])
    if len(names) == 1 and first.address == address and first.size == length:
        return f"{names[0]} ({address})"
    return f"{', '.join(names)} ({address}..{address + length - 1})"


_TRIES: Final = 3  # attempts of a single READ or WRITE (they are idempotent)


class BusLock:
    """The chain's bus: one transaction at a time, set-points before polls.

    A re-entrant lock (``with bus:``, ``acquire``/``release`` as :class:`threading.RLock`)
    with one addition: :meth:`urgent` (a set-point, a hold, the safe state) goes before every
    ordinary acquisition that is waiting or comes later. A half-duplex transaction in flight
    (a SYNC_READ waiting for its status packets) cannot be cut short, so an urgent write waits
    for that one, and no further: the poll thread, which releases the bus between its
    transactions, cannot take it again while an urgent write is waiting (a plain RLock lets
    the thread that just released it take it again first, poll after poll).
    """

    def __init__(self) -> None:
        self._cond = threading.Condition(threading.Lock())
        self._owner: int | None = None
        self._depth = 0
        self._urgent = 0  # urgent acquisitions waiting

    def acquire(self, blocking: bool = True, timeout: float = -1, *, urgent: bool = False) -> bool:
        """Take the bus (re-entrant).

        Args:
            blocking: Wait for it (else only take it if free).
            timeout: Real seconds to wait at most (negative: no limit).
            urgent: Go before the ordinary acquisitions waiting.

        Returns:
            Whether it was taken.
        """
        me = threading.get_ident()
        with self._cond:
            if self._owner == me:
                self._depth += 1
                return True
            if urgent:
                self._urgent += 1
            try:

                def free() -> bool:
                    return self._owner is None and (urgent or self._urgent == 0)

                if not blocking:
                    got = free()
                else:
                    got = self._cond.wait_for(free, None if timeout < 0 else timeout)
                if got:
                    self._owner, self._depth = me, 1
                return got
            finally:
                if urgent:
                    self._urgent -= 1
                    if not self._urgent:
                        self._cond.notify_all()  # the ordinary waiters may go on

    def release(self) -> None:
        """Give the bus back (the owner only).

        Raises:
            RuntimeError: The calling thread does not hold it.
        """
        with self._cond:
            if self._owner != threading.get_ident():
                raise RuntimeError("release of a bus lock this thread does not hold")
            self._depth -= 1
            if not self._depth:
                self._owner = None
                self._cond.notify_all()

    @property
    def urgent_waiting(self) -> bool:
        """Whether an urgent acquisition is waiting (a poll between transactions yields)."""
        return self._urgent > 0

    def __enter__(self) -> BusLock:
        self.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()

    @contextmanager
    def urgent(self) -> Iterator[None]:
        """Hold the bus, taken before the ordinary acquisitions (set-points, holds)."""
        self.acquire(urgent=True)
        try:
            yield
        finally:
            self.release()


class ServoChain(Driver):
    """The port, the poll thread and the supervision of a DYNAMIXEL chain.

    Not used alone: :class:`~temoto.drivers.dynamixel.driver.DynamixelDriver` is built on it,
    and its docstring lists the arguments.
    """

    def __init__(
        self,
        name: str,
        *,
        port: str,
        servos: Sequence[ServoConfig],
        baud: int = 57600,
        poll_rate: float = 50.0,
        status_every: int = 10,
        timeout_polls: int = 3,
        reply_timeout: float = 0.034,
        bus_watchdog: float | None = None,
        return_delay_time: float | None = None,
        clock: Clock | None = None,
    ) -> None:
        super().__init__(name, clock=clock)
        if not servos:
            raise ValueError("a chain needs at least one servo")
        if len({s.id for s in servos}) != len(servos):
            raise ValueError("servo ids must be unique")
        if len({s.joint for s in servos}) != len(servos):
            raise ValueError("joint names must be unique")
        if baud not in BAUD_RATES:
            raise ValueError(f"baud must be one of {sorted(BAUD_RATES)}, got {baud}")
        if not (math.isfinite(poll_rate) and 0 < poll_rate <= 1000):
            raise ValueError(f"poll_rate must be in (0, 1000] Hz, got {poll_rate}")
        if not (math.isfinite(reply_timeout) and 0 < reply_timeout <= 1):
            raise ValueError(f"reply_timeout must be in (0, 1] s, got {reply_timeout}")
        if status_every < 1 or timeout_polls < 1:
            raise ValueError("status_every and timeout_polls must be at least 1")
        self.watchdog_units = watchdog_units(bus_watchdog, 1.0 / poll_rate)
        self.return_delay_units = return_delay_units(return_delay_time)
        self.port = port
        self.baud = baud
        self.servos: tuple[ServoConfig, ...] = tuple(servos)
        self.period = 1.0 / poll_rate
        self.status_every = status_every
        self.timeout_polls = timeout_polls
        self.reply_timeout = reply_timeout
        self._by_joint = {s.joint: s for s in self.servos}
        self._by_id = {s.id: s for s in self.servos}
        self._ids = [s.id for s in self.servos]
        self._bus = BusLock()  # one transaction on the wire at a time, set-points first
        self._sdk: _sdk.SdkPort | None = None
        self._fast: _sdk.SyncReader | None = None
        self._slow: _sdk.SyncReader | None = None
        self._errors: _sdk.SyncReader | None = None
        self._torques: _sdk.SyncReader | None = None
        self._writers: dict[int, _sdk.SyncWriter] = {}
        self._limits: dict[int, tuple[int, int]] = {}  # id → (velocity limit, current limit)
        self._cache = threading.Lock()
        self._states: JointStates | None = None
        self._status: dict[int, ServoStatus] = {}
        self._poller: threading.Thread | None = None
        self._stop = threading.Event()
        self._wake = threading.Condition()
        self._failures = 0
        self._comm_fault = False
        self._hw_fault = False
        self._watchdogs: _sdk.SyncReader | None = None
        #: Each servo's goal register and value, written every poll while ACTIVE.
        self._goals: dict[int, tuple[ct.Register, bytes]] = {}
        # A good poll is due every period; one whose replies time out takes a reply timeout
        # more (real time, so as many seconds of the clock as pass meanwhile: three times
        # as many on a ScaledClock(3)), so the age limit allows for that: a lost reply is
        # not a fault.
        real_rate = self.clock.real_seconds(1.0)
        reply_clock_s = reply_timeout / real_rate if real_rate > 0 else reply_timeout
        self._feedback = StreamAge(f"{name} present position", self.period + reply_clock_s)
        self._bad_packets = FaultWindow()
        self._last_failure = ""

    @property
    def bus_watchdog(self) -> float:
        """The Bus Watchdog time armed at :meth:`activate` (s; 0: off)."""
        return self.watchdog_units * ct.BUS_WATCHDOG_UNIT

    def _hold_goals(self, fast: Mapping[int, bytes]) -> dict[int, tuple[ct.Register, bytes]]:
        """Each servo's goal that keeps it where a fast read found it (velocity/current 0)."""
        goals: dict[int, tuple[ct.Register, bytes]] = {}
        for servo in self.servos:
            if servo.operating_mode in POSITION_MODES:
                goals[servo.id] = (ct.GOAL_POSITION, bytes(fast[servo.id][6:10]))
            elif servo.mode == "velocity":
                goals[servo.id] = (ct.GOAL_VELOCITY, p.to_le(0, 4))
            else:
                goals[servo.id] = (ct.GOAL_CURRENT, p.to_le(0, 2))
        return goals

    def _write_goals(self, goals: Mapping[int, tuple[ct.Register, bytes]]) -> int:
        """One SYNC_WRITE per goal register; the first failing result (or success)."""
        by_register: dict[int, dict[int, bytes]] = {}
        registers: dict[int, ct.Register] = {}
        for dxl_id, (reg, value) in goals.items():
            by_register.setdefault(reg.address, {})[dxl_id] = value
            registers[reg.address] = reg
        outcome = _sdk.COMM_SUCCESS
        for address, values in by_register.items():
            result = self._writer(registers[address]).write(values)
            if result != _sdk.COMM_SUCCESS and outcome == _sdk.COMM_SUCCESS:
                outcome = result
        return outcome

    def _ping(self, dxl_id: int, tries: int = _PING_TRIES) -> int:
        port = self._port()
        result = _sdk.COMM_TX_FAIL
        for _ in range(tries):
            model, result, _ = port.ping(dxl_id)
            if result == _sdk.COMM_SUCCESS:
                return model
        joint = self._by_id[dxl_id].joint
        raise DriverInitError(
            f"{self.name}: servo {dxl_id} ({joint}): {port.result_text(result)} to PING"
            f" on {self.port} ({tries} tries)"
        )

    # ---- polling ------------------------------------------------------------------------------
    def _start_polling(self) -> None:
        self._stop.clear()
        self._poller = threading.Thread(target=self._run, name=f"temoto-dxl-{self.name}")
        self._poller.start()

    def _stop_polling(self) -> None:
        thread, self._poller = self._poller, None
        if thread is None:
            return
        with self._wake:
            self._stop.set()
            self._wake.notify_all()
        thread.join(10.0)

    def _run(self) -> None:
        count = 0
        deadline = self.clock.monotonic()
        while not self._stop.is_set():
            count += 1
            try:
                # the poll first: after a stall of this process (a loaded machine) the chain
                # answers the next poll, and the stream is judged by the wire, not the stall
                good = self._poll_fast()
                self._check_stale()
                self._feed_goals()
                if good and count % self.status_every == 0:
                    self._poll_status()
            except Exception:  # keep polling; a bug must not silently end the thread
                logger.exception("%s: poll failed", self.name)
            deadline += self.period
            with self._wake:
                if self._stop.is_set():
                    break
                remaining = deadline - self.clock.monotonic()
                if remaining > 0:
                    self.clock.wait(self._wake, remaining)
                else:
                    deadline = self.clock.monotonic()  # late: do not try to catch up

    @property
    def feedback_max_age(self) -> float:
        """Clock seconds without a good poll after which the present position is stale.

        :data:`~temoto.drivers.supervision.STALE_PERIODS` (3) times a poll period plus one
        ``reply_timeout`` (the time a poll whose reply is lost takes on top of its period: real
        seconds, counted here in seconds of the driver's clock).
        """
        return self._feedback.max_age

    def _check_stale(self) -> None:
        """Report a fault when the present-position stream is older than its limit."""
        now = self.clock.monotonic()
        age = self._feedback.age(now)
        if self._feedback.last is None or age <= self._feedback.max_age:
            return
        if self.state not in (DriverState.INACTIVE, DriverState.ACTIVE):
            return
        last = f"; last poll: {self._last_failure}" if self._last_failure else ""
        self._comm_fault = True
        self.report_fault(
            DriverTimeoutError(
                f"{self.name}: present position stale: no good poll for {age:.3f} s (limit"
                f" {self._feedback.max_age:.3f} s at {1.0 / self.period:g} Hz){last}"
            )
        )

    def _feed_goals(self) -> None:
        """While ACTIVE, write every servo's newest goal again (the Bus Watchdog's feed)."""
        if self.state is not DriverState.ACTIVE:
            return
        with self._bus:
            if not self._goals or self._sdk is None or self.state is not DriverState.ACTIVE:
                return
            result = self._write_goals(self._goals)
        if result != _sdk.COMM_SUCCESS:
            logger.debug("%s: goal feed: %s", self.name, self._port().result_text(result))

    def _poll_fast(self) -> bool:
        """One SyncRead of the chain; faults and recovery follow from it. True if it worked.

        A reply with a bad CRC or garbage is counted in a sliding window (a fault only when
        :data:`~temoto.drivers.supervision.BAD_FRAMES_LIMIT` fall within
        :data:`~temoto.drivers.supervision.BAD_FRAMES_WINDOW`); a poll without replies counts
        towards ``timeout_polls`` in a row.
        """
        with self._bus:
            reader = self._fast
            if reader is None:
                return False
            result, data, errors = reader.read()
            failed, bad = dict(reader.failed), reader.bad_packets
        stamp = self.clock.monotonic()
        if result != _sdk.COMM_SUCCESS:
            self._last_failure = self._sync_failure(reader.address, reader.length, failed, result)
            full = False
            for _ in range(bad):  # each bad status packet counts, not the poll
                full = self._bad_packets.add(stamp) or full
            if bad:
                window = self._bad_packets
                logger.info(
                    "%s: %s (%d within %g s, %d in all)",
                    self.name,
                    "a bad status packet" if bad == 1 else f"{bad} bad status packets",
                    window.recent(stamp),
                    window.window,
                    window.total,
                )
                if full:
                    self._comm_fault = True
                    self.report_fault(
                        DriverOperationError(
                            f"{self.name}: {window.recent(stamp)} bad status packets within"
                            f" {window.window:g} s (CRC errors or garbage); last:"
                            f" {self._last_failure}"
                        )
                    )
                    return False
            if failed and all(code == _sdk.COMM_RX_CORRUPT for code in failed.values()):
                return False  # replies came, garbled: the window above decides
            self._failures += 1
            if self._failures >= self.timeout_polls:
                self._comm_fault = True
                timeout = result == _sdk.COMM_RX_TIMEOUT
                kind: type[DriverError] = DriverTimeoutError if timeout else DriverOperationError
                self.report_fault(
                    kind(
                        f"{self.name}: {self._failures} polls in a row failed: {self._last_failure}"
                    )
                )
            return False
        self._failures = 0
        self._last_failure = ""
        self._feedback.feed(stamp)
        joints: dict[str, JointState] = {}
        for servo in self.servos:
            raw = data[servo.id]
            current = p.from_le(raw[0:2], signed=True)
            velocity = p.from_le(raw[2:6], signed=True)
            position = p.from_le(raw[6:10], signed=True)
            joints[servo.joint] = JointState(
                servo.joint,
                servo.position(position),
                servo.velocity(velocity),
                servo.effort(current),
                stamp,
            )
        with self._cache:
            self._states = JointStates(stamp, joints)
        if any(e & p.ALERT_BIT for e in errors.values()):
            self._poll_status()
        elif self._comm_fault and not self._hw_fault:
            self._comm_fault = False
            self._after_link_came_back()
        return True

    def _after_link_came_back(self) -> None:
        was_active = self.state is DriverState.FAULT and self._before_fault is DriverState.ACTIVE
        if was_active:
            with self._bus:
                result, data, _ = self._reader("torques").read()
            if result != _sdk.COMM_SUCCESS:
                self._comm_fault = True
                return
            off = [i for i in self._ids if data[i][0] == 0]
            if off:
                self.report_fault(
                    DriverOperationError(
                        f"{self.name}: servo(s) {', '.join(map(str, off))} lost torque while"
                        " unreachable (power cycled?); recover() and activate() again"
                    )
                )
                return
            expired = self._expired_watchdogs()
            if expired:
                try:
                    self._rearm(expired)
                except DriverError as err:
                    self.report_fault(err)
                    return
                self.report_recovered(
                    f"the chain answers again; the Bus Watchdog had stopped servo"
                    f" {', '.join(map(str, expired))}: it holds where it stopped"
                )
                return
        self.report_recovered("the chain answers again")

    def _rearm(self, expired: Sequence[int]) -> None:
        """Clear expired Bus Watchdogs, hold those servos where they stopped, arm again."""
        with self._bus:
            for dxl_id in expired:
                self._write(dxl_id, ct.BUS_WATCHDOG, 0, "bus watchdog clear")
            result, data, _ = self._read_twice(self._reader("fast"))
            if result != _sdk.COMM_SUCCESS:
                raise self._sync_error(self._reader("fast"), result, "read after the bus watchdog")
            holds = self._hold_goals(data)
            for dxl_id in expired:
                self._goals[dxl_id] = holds[dxl_id]
            self._check_tx(self._write_goals({i: holds[i] for i in expired}), "hold goals")
            for dxl_id in expired:
                self._write(dxl_id, ct.BUS_WATCHDOG, self.watchdog_units, "bus watchdog")

    def _expired_watchdogs(self) -> list[int]:
        """The servos whose Bus Watchdog reads -1 (expired); empty when off or unreadable."""
        if not self.watchdog_units:
            return []
        with self._bus:
            reader = self._watchdogs
            if reader is None:
                return []
            result, data, _ = reader.read()
        if result != _sdk.COMM_SUCCESS:
            return []
        return [i for i in self._ids if p.from_le(data[i], signed=True) < 0]

    def _poll_status(self) -> None:
        """Read voltage, temperature and hardware error status; report hardware errors."""
        # one transaction per taking of the bus: a set-point waiting goes between them
        with self._bus:
            if self._slow is None:
                return
            result, slow, _ = self._slow.read()
        if result != _sdk.COMM_SUCCESS:
            return  # the fast poll counts communication failures
        with self._bus:
            if self._errors is None:
                return
            result, bits, _ = self._errors.read()
        if result != _sdk.COMM_SUCCESS:
            return
        expired = self._expired_watchdogs()
        if expired and self.state is DriverState.ACTIVE:
            self._hw_fault = True  # stays until recover()
            self.report_fault(
                DriverOperationError(
                    f"{self.name}: the Bus Watchdog of servo {', '.join(map(str, expired))}"
                    f" expired (no instruction for over {self.bus_watchdog:g} s): stopped, goals"
                    " refused; recover() and activate() again"
                )
            )
        stamp = self.clock.monotonic()
        status: dict[int, ServoStatus] = {}
        failing: list[tuple[int, int]] = []
        for servo in self.servos:
            value = bits[servo.id][0]
            status[servo.id] = ServoStatus(
                servo.id,
                servo.joint,
                float(slow[servo.id][2]),
                p.from_le(slow[servo.id][0:2]) * ct.VOLT_PER_UNIT,
                value,
                p.decode_hardware_error(value),
                stamp,
            )
            if value:
                failing.append((servo.id, value))
        with self._cache:
            self._status = status
        if failing:
            self._hw_fault = True
            self.report_fault(self._hardware_error(*failing[0], also=failing[1:]))

    # ---- helpers ------------------------------------------------------------------------------
    def _port(self) -> _sdk.SdkPort:
        if self._sdk is None:
            raise StateError(f"{self.name}: the port is not open")
        return self._sdk

    def _read_twice(self, reader: _sdk.SyncReader) -> tuple[int, dict[int, bytes], dict[int, int]]:
        """A one-shot SyncRead (not a poll) that needs every reply: asked again after a timeout.

        A status packet lost on the wire (a noisy RS-485 line, the simulator's realism) is no
        reason to refuse an activation or a hold; a servo that is really gone times out twice.
        """
        result, data, errors = reader.read()
        if result == _sdk.COMM_RX_TIMEOUT:
            logger.info("%s: a SyncRead timed out; asking once more", self.name)
            result, data, errors = reader.read()
        return result, data, errors

    def _reader(self, which: str) -> _sdk.SyncReader:
        reader = {"fast": self._fast, "torques": self._torques}[which]
        if reader is None:
            raise StateError(f"{self.name}: not configured")
        return reader

    def _writer(self, reg: ct.Register) -> _sdk.SyncWriter:
        writer = self._writers.get(reg.address)
        if writer is None:
            writer = self._port().sync_writer(reg.address, reg.size)
            self._writers[reg.address] = writer
        return writer

    def _check_tx(self, result: int, what: str = "SyncWrite") -> None:
        if result != _sdk.COMM_SUCCESS:
            raise self._comm_error(what, result)

    def _read(self, dxl_id: int, reg: ct.Register, what: str = "", alert_ok: bool = False) -> int:
        """READ one register of one servo (retried); errors name the servo and the register."""
        for _ in range(_TRIES):
            value, result, error = self._port().read(dxl_id, reg.address, reg.size)
            if result == _sdk.COMM_SUCCESS:
                break
        action = f"reading {register_label(reg.address, reg.size)}"
        self._check_reply(dxl_id, action, result, error & ~p.ALERT_BIT if alert_ok else error)
        if reg.signed and value >= 1 << (8 * reg.size - 1):
            value -= 1 << (8 * reg.size)
        return value

    def _write(self, dxl_id: int, reg: ct.Register, value: int, what: str = "") -> None:
        """WRITE one register of one servo (retried); errors name the servo and the register."""
        for _ in range(_TRIES):
            result, error = self._port().write(dxl_id, reg.address, reg.size, value)
            if result == _sdk.COMM_SUCCESS:
                break
        action = f"writing {register_label(reg.address, reg.size)} = {value}"
        self._check_reply(dxl_id, action, result, error)

    def _check_reply(self, dxl_id: int, action: str, result: int, error: int) -> None:
        if result != _sdk.COMM_SUCCESS:
            raise self._comm_error(f"servo {dxl_id}: {self._words(result)} {action}", None)
        if error & p.ALERT_BIT:
            bits, result, _ = self._port().read(dxl_id, ct.HARDWARE_ERROR_STATUS.address, 1)
            raise self._hardware_error(dxl_id, bits if result == _sdk.COMM_SUCCESS else 0)
        if error:
            number = error & 0x7F
            name = p.ErrorNumber(number).name if number <= 7 else str(number)
            raise DriverOperationError(
                f"{self.name}: servo {dxl_id} refused {action}: {name} error"
            )

    def _raise_alerts(self, errors: Mapping[int, int]) -> None:
        for dxl_id, error in errors.items():
            if error & p.ALERT_BIT:
                bits, result, _ = self._port().read(dxl_id, ct.HARDWARE_ERROR_STATUS.address, 1)
                raise self._hardware_error(dxl_id, bits if result == _sdk.COMM_SUCCESS else 0)

    def _words(self, result: int) -> str:
        return _sdk.RESULT_WORDS.get(result, f"dynamixel-sdk result {result}")

    def _sync_failure(
        self, address: int, length: int, failed: Mapping[int, int], result: int
    ) -> str:
        """What went wrong in a SYNC_READ, naming the servos and the registers.

        Returns:
            ``servo 3: no status packet reading Present Position (132)``, with every failing
            servo (``servos 3, 4: ...; servo 5: ...``), or the whole read's failure.
        """
        span = register_label(address, length)
        if not failed:
            return f"{self._words(result)} for SYNC_READ of {span}"
        by_code: dict[int, list[int]] = {}
        for dxl_id, code in failed.items():
            by_code.setdefault(code, []).append(dxl_id)
        return "; ".join(
            f"servo{'s' if len(ids) > 1 else ''} {', '.join(map(str, ids))}:"
            f" {self._words(code)} reading {span}"
            for code, ids in by_code.items()
        )

    def _sync_error(self, reader: _sdk.SyncReader, result: int, what: str = "") -> DriverError:
        """A typed error for a failed SYNC_READ (its text from :meth:`_sync_failure`)."""
        text = self._sync_failure(reader.address, reader.length, reader.failed, result)
        return self._comm_error(f"{what}: {text}" if what else text, result)

    def _comm_error(self, what: str, result: int | None) -> DriverError:
        """``<device>: <what>`` as a DriverTimeoutError (no reply) or DriverOperationError.

        Args:
            what: The failure, naming the servo and the register.
            result: The result code, or None when ``what`` already says it (a timeout is then
                recognised by its words).
        """
        if result is not None and result != _sdk.COMM_SUCCESS and self._words(result) not in what:
            what = f"{what}: {self._words(result)}"
        message = f"{self.name}: {what}"
        timeout = _sdk.RESULT_WORDS[_sdk.COMM_RX_TIMEOUT]
        if result == _sdk.COMM_RX_TIMEOUT or (result is None and timeout in what):
            return DriverTimeoutError(message)
        return DriverOperationError(message)

    def _hardware_error(
        self, dxl_id: int, bits: int, also: Sequence[tuple[int, int]] = ()
    ) -> DynamixelHardwareError:
        servo = self._by_id[dxl_id]
        names = ", ".join(p.decode_hardware_error(bits)) or "alert bit"
        more = "".join(f"; servo {i}: {', '.join(p.decode_hardware_error(b))}" for i, b in also)
        return DynamixelHardwareError(
            f"{self.name}: servo {dxl_id} ({servo.joint}) hardware error: {names}{more}"
            " (recover() reboots it)",
            servo_id=dxl_id,
            error=bits,
        )
