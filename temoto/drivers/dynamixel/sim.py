"""A simulated chain of DYNAMIXEL X-series servos answering Protocol 2.0 on a pseudo-terminal.

:class:`SimDynamixelChain` opens a pseudo-terminal **in its constructor** (so
:attr:`~SimDynamixelChain.path`, the slave's ``/dev/pts/N``, is known before anything starts),
serves the master end on a named thread between :meth:`~SimDynamixelChain.start` and
:meth:`~SimDynamixelChain.close`, and gives every servo its model's full control table
(:attr:`~temoto.drivers.dynamixel.control_table.Model.registers`, from the ROBOTIS e-Manual:
EEPROM and RAM areas, gains, limits, Indirect Address/Data, External Ports on the X540s).
Whatever opens the slave path -- dynamixel-sdk's ``PortHandler`` in the driver and the tests,
DYNAMIXEL Wizard through a serial bridge -- talks to it exactly as to a U2D2 and a chain.
A pseudo-terminal carries bytes whatever the baud rate; replies go out at once (no Return
Delay Time). A chain made with ``baud=`` models the baud rate all the same: each servo then
hears only the packets sent while the line is set (``termios``, as dynamixel-sdk's
``PortHandler`` sets it through pyserial) to the rate its Baud Rate register selects, as a
servo's UART hears only noise at another rate; without ``baud`` every packet is heard.

Instructions, as the e-Manual's Protocol 2.0 page describes them:

* PING (also broadcast: every servo answers, in ascending id order) answers with the Model
  Number register and the Firmware Version;
* READ (a range past the end of the table is an Access Error with no data; reserved bytes
  inside it read 0), SYNC_READ and BULK_READ;
* WRITE, SYNC_WRITE and BULK_WRITE, checked as a servo checks them: read-only registers and the
  torque-locked ones (the EEPROM area and the Indirect Addresses) while Torque Enable is 1 are
  an Access Error, a write that touches only reserved bytes too; a value outside the
  register's range (the e-Manual's Range column, the model's operating modes and baud codes)
  is a Data Range Error; a goal beyond its limit register (Goal Position outside Min/Max
  Position Limit in position mode, Goal Velocity/Current/PWM beyond Velocity/Current/PWM
  Limit) a Data Limit Error; a WRITE with no data, or with only part of a register's bytes, a
  Data Length Error (after the access checks). Writing ID makes the
  servo answer to the new id from the next packet on (the status packet still comes from the
  old one); writing Baud Rate makes it listen at the new rate likewise;
* REG_WRITE (checked like WRITE, held until ACTION; Registered Instruction reads 1) and ACTION
  (applies it; an ACTION with nothing registered is an Instruction Error);
* REBOOT: the RAM area returns to its initial values (torque off, gains, goals, Bus Watchdog,
  Indirect Addresses), the multi-turn count is dropped (Present Position within 0..4095) and a
  servo whose Startup Configuration has bit 0 set starts with its torque on;
* FACTORY_RESET (0xFF all, 0x01 all but the ID, 0x02 all but the ID and the baud rate; the
  broadcast form of 0xFF is ignored, as on firmware v42 on), then a reboot;
* CLEAR 0x01 with the fixed bytes 44 58 4C 22: Present Position back within one turn; Result
  Fail while the servo moves.

Anything else answers an Instruction Error. An instruction packet with a bad CRC is dropped.
Indirect Data *n* reads and writes the byte at the address Indirect Address *n* holds (the
checks above apply to the register behind it). Status Return Level, as set when the
instruction arrives: 0 answers PING only, 1 PING and the reads, 2 everything (broadcast
instructions other than PING and the SYNC/BULK reads are never answered). A servo whose
Protocol Type is set to anything but 2 no longer hears Protocol 2.0 (Protocol 1.0 is not
modelled). Secondary ID (0..252; 253..255 off): a packet to it is carried out by every servo
of that group whose own ID differs, RAM area only, without a status packet (the servo whose ID
it is answers as usual). Homing Offset shifts Present Position (actual position + offset; the
goal and limit registers are in the same shifted ticks). Drive Mode bit 3 (Torque On by Goal
Update): a goal accepted while torque is off switches it on. FAST_SYNC_READ and
FAST_BULK_READ (firmware v45 on; not the 2XL430) are answered with one status packet the listed
servos build together, as the e-Manual shows. Not modelled: Drive Mode's direction and
time-based profile bits, External Port levels, and Control Table Backup (0x20), which is
answered with an Instruction Error.

Motion (stepped on the injected clock whenever a packet arrives;
:func:`~temoto.drivers.dynamixel.sim_servo.move`): in the position modes the servo follows the
e-Manual's velocity-based trapezoidal profile (Profile Velocity and Profile Acceleration, 0 =
unlimited; the Velocity Limit bounds the speed) within the position limits in Position mode; in
Velocity mode the goal velocity, ramped at Profile Acceleration; in Current mode the goal
current's torque, in PWM mode the goal PWM's share of the stall torque less the back-EMF's. The
torque is bounded by the Current Limit and accelerates the servo's inertia and its load
(:meth:`SimDynamixelChain.set_load`) against friction; Present Current (or Present Load) is that
torque. The winding heats with the current (I²R) and cools to 30 °C; past the Temperature Limit,
with Shutdown's bit 2 set, Hardware Error Status bit 2 (Overheating) is set and torque goes off.
Moving is 1 while the speed exceeds the Moving Threshold; Moving Status bit 0 (in position) and
bit 1 (profile ongoing), Present PWM, the trajectories and Realtime Tick (ms since the last boot,
modulo 32768) follow the model. Torque off stops the servo.

Bus Watchdog (98), as the e-Manual describes it for the X series (firmware v38 on): 0 is off,
1..127 arms it in units of 20 ms. While Torque Enable is 1, a servo that hears no instruction
packet meant for it (one to its id, a broadcast, or a SYNC/BULK packet that lists it) for longer
than the set time stops where it is (torque stays on), the register reads -1, and the goal
registers (Goal PWM, Current, Velocity, Position) refuse writes with a Data Range error until 0
is written to it. Expiry is computed on the injected clock (its window in real seconds when
the clock runs faster than real time, as the servo's own oscillator does; see
:func:`~temoto.drivers.dynamixel.sim_servo.watchdog_expiry`), at the exact instant it falls,
whenever the model steps (on every packet, on a register read, and every 50 ms of real time
while the line is quiet). After the error is cleared the servo stays stopped until a new goal is
accepted or torque is switched off (the e-Manual does not say; this never moves a servo by
itself). Writing 1..127 while the error stands is refused (only 0 clears it).

Faults (:meth:`~temoto.drivers.sim.Simulator.inject`; ``device=<id>`` limits ``silence`` and
``hardware_error`` to one servo):

* ``silence`` -- the servos neither answer nor act on instructions;
* ``corrupt`` -- every reply goes out with a wrong CRC (``replies=N``: only the next N
  replies, then the fault clears itself);
* ``hardware_error`` with ``kind`` = ``overheat`` / ``overload`` / ``voltage`` -- sets the
  Hardware Error Status bit (overheating / overload / input voltage), raises the temperature or
  voltage reading to match, turns torque off, and puts the alert bit in every status packet.
  Like a real servo it stays so until a REBOOT, which clears it unless the fault is still
  injected;
* ``link_loss`` -- no bytes in either direction (the pseudo-terminal itself stays, because its
  path must stay valid for the reconnect; an adapter whose device node disappears is not
  modelled).

Realism (``realism=``, :mod:`temoto.drivers.realism`; figures in ``docs/simulators.md``,
"Realism"): at ``typical`` or ``harsh`` Present Position, Velocity, Current and Temperature
carry seeded gaussian noise (the model's true state does not; Moving and Moving Status follow
the true state), and the status packets that answer a SYNC_READ, FAST_SYNC_READ, BULK_READ or
FAST_BULK_READ (a host's poll) are lost now and then: the host sees a timeout. Replies to
single READs, PINGs and writes are never lost (a lost write status would make the host think a
goal was refused). Status packets also come late
(:class:`~temoto.drivers.realism.SerialReplyDelay`): every one waits the Return Delay Time
its servo's register 9 sets (2 µs a unit, as the e-Manual's Protocol 2.0 timing shows) plus a
small jitter, and a poll's packets now and then wait longer, as behind a USB adapter's latency
timer or a busy USB host: within dynamixel-sdk's 34 ms at ``typical``, past it now and then at
``harsh``. The serving thread waits meanwhile (a half-duplex line carries one packet at a
time): a host that gave up and asked again reads the late packets first. A delay under 1 ms is
not waited out (a sleep costs more than that on a loaded machine). At ``off`` replies go out at
once.

Code: this module is the pseudo-terminal, the serving thread, fault injection and the
inspection methods; :mod:`~temoto.drivers.dynamixel.sim_instructions` (:class:`ServoChain`)
carries out the instructions and :mod:`~temoto.drivers.dynamixel.sim_servo` models one servo.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import select
import termios
import threading
import tty
import warnings
from collections.abc import Iterable, Mapping
from typing import ClassVar, Final

from temoto.clock import Clock
from temoto.drivers.dynamixel import control_table as ct
from temoto.drivers.dynamixel import protocol as p
from temoto.drivers.dynamixel.sim_instructions import ServoChain
from temoto.drivers.dynamixel.sim_servo import AMBIENT, BAUD_BY_CODE, GENERIC_REGISTERS
from temoto.drivers.realism import Realism, SerialReplyDelay

__all__ = ["SimDynamixelChain"]

logger = logging.getLogger(__name__)

#: The instructions whose status packets realism may lose (a host's polls).
_POLLS: Final = frozenset(
    {
        p.Instruction.SYNC_READ,
        p.Instruction.FAST_SYNC_READ,
        p.Instruction.BULK_READ,
        p.Instruction.FAST_BULK_READ,
    }
)

#: The shortest delay of a status packet the serving thread waits out: a shorter sleep costs a
#: trip through the scheduler that, on a loaded machine, takes far longer than the delay (and
#: a pseudo-terminal adds its own latency of that order anyway).
_MIN_WAIT: Final = 0.001

#: ``termios`` speed constants → bits per second (those this platform has).
_LINE_SPEEDS: Final[Mapping[int, int]] = {
    getattr(termios, f"B{baud}"): baud
    for baud in BAUD_BY_CODE.values()
    if hasattr(termios, f"B{baud}")
}


class SimDynamixelChain(ServoChain):
    """A chain of simulated X-series servos on a pseudo-terminal (see the module docstring).

    Args:
        servos: Servo id → model name (``{1: "XM430-W350", 2: "XL430-W250"}``; the names of
            :data:`~temoto.drivers.dynamixel.control_table.MODELS`).
        clock: Steps the motion model (a :class:`~temoto.clock.ManualClock` in tests).
        name: For the serving thread's name (``temoto-sim-dxl-<name>``).
        baud: The servos' baud rate (their Baud Rate register): they hear only packets sent
            at this rate (or at whatever the register says after a client changes it). None:
            the baud rate is not modelled, every packet is heard.
        realism: ``off`` (default: the exact figures), ``typical``, ``harsh`` or a
            :class:`~temoto.drivers.realism.Realism` (see the module docstring).
        seed: The realism's top-level seed (None: a fresh one; ``realism.seed`` holds it).

    Raises:
        ValueError: No servos, a bad id, an unknown model or a baud rate the X series lacks.
        OSError: The pseudo-terminal cannot be opened.
    """

    FAULTS: ClassVar[frozenset[str]] = frozenset(
        {"silence", "corrupt", "hardware_error", "link_loss"}
    )

    def __init__(
        self,
        servos: Mapping[int, str],
        *,
        clock: Clock | None = None,
        name: str = "dxl",
        baud: int | None = None,
        realism: Realism | str = "off",
        seed: int | None = None,
    ) -> None:
        super().__init__(servos, clock=clock, baud=baud)
        self.name = name
        if not isinstance(realism, Realism):
            realism = Realism(realism, seed=seed, device=name)
            if realism.enabled:
                logger.info("%s: %s", name, realism.describe())
        self.realism = realism
        #: Status packets lost on purpose (realism), for tests and tools.
        self.replies_lost = 0
        #: Bytes read from the host and fully served (every reply they asked for written, or
        #: dropped by a fault): a host that wrote as many and read :attr:`bytes_sent` has
        #: nothing more coming, so a test's client can wait for these instead of a real-time
        #: timeout (for tests and tools).
        self.bytes_served = 0
        #: Bytes of status packets written to the host (counted before :attr:`bytes_served`).
        self.bytes_sent = 0
        #: The status packets' delays (realism other than ``off``; made for :attr:`realism` at
        #: the first reply, made again when it is replaced; tests may set other figures).
        self.reply_delays: SerialReplyDelay | None = None
        self._reader = p.PacketReader()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._closed = False
        self._corrupt_left: int | None = None  # corrupt replies still to send (replies=)
        self._master, self._slave = os.openpty()
        try:
            tty.setraw(self._slave)  # no echo, no line discipline, before anyone opens it
            os.set_blocking(self._master, False)
            self.path = os.ttyname(self._slave)
        except BaseException:
            os.close(self._master)
            os.close(self._slave)
            raise

    def __repr__(self) -> str:
        return f"<SimDynamixelChain {self.name!r} {self.path} ids={list(self.ids)}>"

    def __del__(self) -> None:
        if not getattr(self, "_closed", True):
            warnings.warn(f"{self!r} was not closed", ResourceWarning, stacklevel=1)
            self.close()

    # ---- lifecycle ---------------------------------------------------------------------------

    def start(self) -> None:
        """Start answering on the pseudo-terminal (idempotent).

        Raises:
            RuntimeError: After :meth:`close`.
        """
        if self._closed:
            raise RuntimeError(f"{self!r} is closed")
        if self._thread is not None:
            return
        self._thread = threading.Thread(
            target=self._serve, name=f"temoto-sim-dxl-{self.name}", daemon=True
        )
        self._thread.start()

    def close(self) -> None:
        """Stop the serving thread, join it and close the pseudo-terminal (idempotent)."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5.0)
            self._thread = None
        for fd in (self._master, self._slave):
            with contextlib.suppress(OSError):
                os.close(fd)

    # ---- inspection for tests ----------------------------------------------------------------

    @property
    def ids(self) -> tuple[int, ...]:
        """The ids the servos answer to now, ascending."""
        return tuple(sorted(s.id for s in self._servos))

    def model_of(self, dxl_id: int) -> ct.Model:
        """The model of the servo that answers to ``dxl_id``.

        Args:
            dxl_id: Its id now.

        Returns:
            Its model.

        Raises:
            KeyError: No servo answers to that id.
        """
        with self._state:
            return self._servo(dxl_id).model

    def set_load(self, dxl_id: int, *, inertia: float = 0.0, torque: float = 0.0) -> None:
        """What the servo's horn carries: an inertia and a constant torque against it.

        Args:
            dxl_id: Its id now.
            inertia: kg·m² at the output (a link and its payload).
            torque: N·m it must hold (gravity on an arm; positive opposes positive motion).

        Raises:
            KeyError: No servo answers to that id.
            ValueError: A negative or non-finite inertia, a non-finite torque.
        """
        if not (math.isfinite(inertia) and inertia >= 0 and math.isfinite(torque)):
            raise ValueError(
                f"load: inertia must be >= 0 kg·m² and torque finite, got {inertia!r}, {torque!r}"
            )
        with self._state:
            self._step_locked()
            servo = self._servo(dxl_id)
            servo.load_inertia, servo.load_torque = inertia, torque

    def read_register(self, dxl_id: int, address: int, size: int | None = None) -> int:
        """A register's value, as stored (stepping the model first; no Indirect Data mapping).

        Args:
            dxl_id: The servo (its id now).
            address: A register address of its model (or of the XM430-W350 table: a register
                the model lacks reads as the reserved bytes there, 0).
            size: Bytes to read (default: the register's size).

        Returns:
            The value (signed for signed registers).

        Raises:
            KeyError: No servo answers to ``dxl_id``, or no register starts at ``address``
                and no ``size`` is given.
        """
        with self._state:
            self._step_locked()
            servo = self._servo(dxl_id)
            reg = servo.layout.by_address.get(address) or GENERIC_REGISTERS.get(address)
            if reg is None and size is None:
                raise KeyError(f"no register at {address}")
            signed = reg.signed if reg is not None else False
            width = size if size is not None else reg.size if reg is not None else 1
            data = bytes(servo.table[address : address + width]).ljust(width, b"\x00")
            return p.from_le(data, signed)

    def write_register(self, dxl_id: int, address: int, value: int) -> None:
        """Set a register directly, bypassing access checks (for tests).

        Args:
            dxl_id: The servo (its id now).
            address: A register address of its model.
            value: The value.

        Raises:
            KeyError: No servo answers to ``dxl_id``, or its model has no register there.
        """
        with self._state:
            servo = self._servo(dxl_id)
            reg = servo.layout.by_address[address]
            servo.put(reg, value)
            if reg.name == "Present Position":
                servo.position = float(value)
                servo.traj_pos = None

    # ---- faults ------------------------------------------------------------------------------

    def on_fault_changed(self, fault: str, active: bool) -> None:
        """Raise hardware-error bits at once when ``hardware_error`` is injected."""
        if fault == "corrupt" and active:
            replies = (self.fault("corrupt") or {}).get("replies")
            if replies is not None and not (isinstance(replies, int) and replies > 0):
                self.clear("corrupt")
                raise ValueError(f"corrupt replies= must be a positive integer, got {replies!r}")
            self._corrupt_left = replies
        if fault == "hardware_error" and active:
            params = self.fault("hardware_error") or {}
            with self._state:
                for servo in self._targets(params):
                    self._raise_hardware_error(servo, str(params.get("kind", "overheat")))
        elif fault == "hardware_error":  # an injected overheat is over: the servo has cooled
            with self._state:
                for servo in self._servos:
                    if servo.injected_heat:
                        servo.temperature, servo.injected_heat = AMBIENT, False

    # ---- serving -----------------------------------------------------------------------------

    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([self._master], [], [], 0.05)
                if not ready:
                    with self._state:  # a Bus Watchdog expires without any packet too
                        self._step_locked()
                    continue
                data = os.read(self._master, 4096)
            except BlockingIOError:
                continue
            except OSError:  # no slave open (EIO): wait for one
                with self._state:  # the client is gone: its servos' watchdogs run on
                    self._step_locked()
                self._stop.wait(0.01)
                continue
            try:
                self._serve_data(data)
            finally:
                self.bytes_served += len(data)

    def _serve_data(self, data: bytes) -> None:
        """Carry out the packets in ``data`` (bytes from the host) and send their replies."""
        if self.fault("link_loss") is not None:
            return  # no bytes in either direction
        line = self._line_baud()
        for item in self._reader.feed(data):
            if isinstance(item, p.PacketError):
                self.stats["bad_packets"] += 1
                continue
            self.stats["packets"] += 1
            try:
                replies = self._handle(item, line)
            except Exception:  # a bug here must not kill the chain
                logger.exception("sim %s: handling %s failed", self.name, item)
                continue
            poll = item.instruction in _POLLS
            if replies and poll and self.realism.lost():
                self.replies_lost += 1  # lost on the way: the host's read times out
                continue
            if replies and self.realism.enabled:
                self._wait_before(replies, poll=poll)
            for reply in replies:
                self._send(reply)

    @property
    def replies_late(self) -> int:
        """Polls whose status packets were sent late on purpose (realism), for tests and tools."""
        return 0 if self.reply_delays is None else self.reply_delays.late

    @property
    def longest_late(self) -> float:
        """The longest such delay (s; the Return Delay Time not counted)."""
        return 0.0 if self.reply_delays is None else self.reply_delays.longest

    def _wait_before(self, replies: list[bytes], *, poll: bool) -> None:
        """Wait as long as ``replies`` take to reach the host (realism other than ``off``).

        Each servo waits its Return Delay Time (register 9) before its status packet; the
        line adds its jitter, and a poll's packets now and then come late
        (:class:`~temoto.drivers.realism.SerialReplyDelay`).
        """
        delays = self.reply_delays
        if delays is None or delays.realism is not self.realism:
            delays = self.reply_delays = SerialReplyDelay(self.realism)
        extra = delays.delay(poll=poll)
        units = 0
        with self._state:
            for reply in replies:
                with contextlib.suppress(KeyError, IndexError):
                    units += self._servo(reply[4]).value("Return Delay Time")
        wait = extra + units * ct.RETURN_DELAY_UNIT
        if wait >= _MIN_WAIT:
            self._stop.wait(wait)

    def _line_baud(self) -> int | None:
        """The baud rate the client set on the line (None: unknown, or not modelled)."""
        if self.baud is None:
            return None
        try:
            speed = termios.tcgetattr(self._slave)[5]  # the client's output speed
        except (OSError, termios.error):
            return None
        return _LINE_SPEEDS.get(speed)

    def _send(self, data: bytes) -> None:
        if self.fault("link_loss") is not None:
            return
        if self.fault("corrupt") is not None:
            data = data[:-1] + bytes([data[-1] ^ 0x5A])
            if self._corrupt_left is not None:
                self._corrupt_left -= 1
                if self._corrupt_left <= 0:
                    self.clear("corrupt")
        view = memoryview(data)
        while view and not self._stop.is_set():
            try:
                sent = os.write(self._master, view)
            except BlockingIOError:
                select.select([], [self._master], [], 0.05)
                continue
            except OSError:
                return
            view = view[sent:]
        self.bytes_sent += len(data) - len(view)
        self.stats["replies"] += 1


def chain_from_ids(ids: Iterable[int], model: str = "XM430-W350") -> dict[int, str]:
    """``{id: model}`` for ids of one model (a helper for tests and benchmarks).

    Args:
        ids: Servo ids.
        model: Their model.

    Returns:
        The mapping :class:`SimDynamixelChain` takes.
    """
    return dict.fromkeys(ids, model)
