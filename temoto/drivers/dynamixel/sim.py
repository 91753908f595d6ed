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

Motion (first order, stepped on the injected clock whenever a packet arrives): in the position
modes the position approaches the goal with a time constant of 50 ms at no more than the profile
velocity (or the Velocity Limit register), within the position limits in Position mode; in
Velocity mode the velocity approaches the goal velocity; in Current mode it approaches the
speed that the goal current's share of the Current Limit gives, in PWM mode the goal PWM's
share of 885. Present Current (or Present Load) is the effort of that tracking (a proportional
share of the Current Limit, or of 100.0 %). Moving is 1 while the speed exceeds the Moving
Threshold; Moving Status bit 0 (in position) and bit 1 (profile ongoing), Present PWM, the
trajectories and Realtime Tick (ms since the last boot, modulo 32768) follow the model. Torque
off stops the servo.

Bus Watchdog (98), as the e-Manual describes it for the X series (firmware v38 on): 0 is off,
1..127 arms it in units of 20 ms. While Torque Enable is 1, a servo that hears no instruction
packet meant for it (one to its id, a broadcast, or a SYNC/BULK packet that lists it) for longer
than the set time stops where it is (torque stays on), the register reads -1, and the goal
registers (Goal PWM, Current, Velocity, Position) refuse writes with a Data Range error until 0
is written to it. Expiry is computed on the injected clock, at the exact instant it falls,
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
from dataclasses import dataclass, field
from typing import Any, ClassVar, Final

from temoto.clock import Clock, MonotonicClock
from temoto.drivers.dynamixel import control_table as ct
from temoto.drivers.dynamixel import protocol as p
from temoto.drivers.sim import Simulator

__all__ = ["SimDynamixelChain"]

logger = logging.getLogger(__name__)

_TAU: Final = 0.05  # s, time constant of position and velocity tracking
_SUBSTEP: Final = 0.001  # s, largest integration step
_SNAP_AFTER: Final = 1.0  # s, a longer step settles at once
_TICKS_S_PER_UNIT: Final = 0.229 * 4096.0 / 60.0  # velocity unit in ticks per second
_LOAD_FULL: Final = 1000  # Present Load of a model without a current sensor: 0.1 % units
_PWM_FULL: Final = 885
_EXTENDED_GOAL: Final = 1_048_575  # |Goal Position| in the multi-turn modes (e-Manual)
_CLEAR_MULTI_TURN: Final = bytes([0x01, 0x44, 0x58, 0x4C, 0x22])
_TORQUE_ON_BY_GOAL: Final = 0x08  # Drive Mode bit 3 (firmware v45 on; v46 on the XL330)
_E = p.ErrorNumber
_I = p.Instruction

#: Baud Rate register (8) values → bits per second (X series).
_BAUD_BY_CODE: Final[Mapping[int, int]] = {
    0: 9600,
    1: 57600,
    2: 115200,
    3: 1_000_000,
    4: 2_000_000,
    5: 3_000_000,
    6: 4_000_000,
    7: 4_500_000,
}
_CODE_BY_BAUD: Final[Mapping[int, int]] = {baud: code for code, baud in _BAUD_BY_CODE.items()}
#: ``termios`` speed constants → bits per second (those this platform has).
_LINE_SPEEDS: Final[Mapping[int, int]] = {
    getattr(termios, f"B{baud}"): baud
    for baud in _BAUD_BY_CODE.values()
    if hasattr(termios, f"B{baud}")
}

_KIND_BITS: Final[Mapping[str, int]] = {
    "overheat": p.HardwareError.OVERHEATING,
    "overload": p.HardwareError.OVERLOAD,
    "voltage": p.HardwareError.INPUT_VOLTAGE,
}
_GOAL_NAMES: Final = frozenset(r.name for r in ct.GOAL_REGISTERS)
_POSITION_MODES: Final = frozenset(
    {
        ct.OperatingMode.POSITION,
        ct.OperatingMode.EXTENDED_POSITION,
        ct.OperatingMode.CURRENT_BASED_POSITION,
    }
)
#: Instructions answered at Status Return Level 1 (PING is answered at every level).
_READS: Final = frozenset(
    {_I.READ, _I.SYNC_READ, _I.BULK_READ, _I.FAST_SYNC_READ, _I.FAST_BULK_READ}
)
#: Models without Fast Sync/Bulk Read (e-Manual: "2XL/2XC Not Supported").
_NO_FAST_READ: Final = frozenset({"2XL430-W250"})
_GENERIC: Final = {r.address: r for r in ct.REGISTERS}


class _Reject(Exception):
    """An instruction a servo refuses: answered with this error number."""

    def __init__(self, number: int) -> None:
        super().__init__(number)
        self.number = number


class _Layout:
    """A model's control table, indexed for the simulator (one per model, shared)."""

    def __init__(self, model: ct.Model) -> None:
        self.model = model
        self.size = model.table_end
        self.by_name: dict[str, ct.Register] = {r.name: r for r in model.registers}
        self.by_address: dict[int, ct.Register] = {r.address: r for r in model.registers}
        self.owner: list[ct.Register | None] = [None] * self.size
        for reg in model.registers:
            for at in range(reg.address, reg.address + reg.size):
                self.owner[at] = reg
        #: Indirect Data address → its Indirect Address register.
        self.indirect: dict[int, ct.Register] = {
            reg.default: reg for reg in model.registers if reg.name.startswith("Indirect Address")
        }


_LAYOUTS: dict[str, _Layout] = {}


def _layout(model: ct.Model) -> _Layout:
    found = _LAYOUTS.get(model.name)
    if found is None:
        found = _LAYOUTS[model.name] = _Layout(model)
    return found


@dataclass
class _Servo:
    """One simulated servo: its control table and the continuous state behind it."""

    start_id: int
    model: ct.Model
    layout: _Layout = field(init=False)
    table: bytearray = field(init=False)
    position: float = float(ct.POSITION_CENTER)  # ticks
    velocity: float = 0.0  # ticks/s
    current: float = 0.0  # current units (or load, 0.1 %)
    heard: float = 0.0  # clock time of the newest instruction packet meant for it
    booted: float = 0.0  # clock time of the last (re)boot: Realtime Tick counts from it
    halted: bool = False  # stopped by its Bus Watchdog; until torque off or a new goal
    registered: tuple[int, bytes] | None = None  # a REG_WRITE waiting for ACTION

    def __post_init__(self) -> None:
        self.layout = _layout(self.model)
        self.table = bytearray(self.layout.size)
        for reg in self.model.registers:
            self.put(reg, reg.default)
        self.set("ID", self.start_id)

    @property
    def id(self) -> int:
        """The id it answers to now (its ID register)."""
        return self.table[7]

    def reg(self, name: str) -> ct.Register | None:
        return self.layout.by_name.get(name)

    def get(self, reg: ct.Register) -> int:
        at = reg.address
        return int.from_bytes(self.table[at : at + reg.size], "little", signed=reg.signed)

    def put(self, reg: ct.Register, value: int) -> None:
        self.table[reg.address : reg.address + reg.size] = p.to_le(value, reg.size)

    def value(self, name: str, default: int = 0) -> int:
        """A register's value by name (``default`` if the model has no such register)."""
        reg = self.layout.by_name.get(name)
        if reg is None:
            return default
        at = reg.address
        return int.from_bytes(self.table[at : at + reg.size], "little", signed=reg.signed)

    def set(self, name: str, value: int) -> None:
        """Set a register by name (nothing if the model has no such register)."""
        reg = self.layout.by_name.get(name)
        if reg is not None:
            self.put(reg, value)

    def resolve(self, address: int) -> int:
        """The address a byte access really goes to (an Indirect Data byte: its target)."""
        pointer = self.layout.indirect.get(address)
        if pointer is None:
            return address
        target = self.get(pointer)
        if target in self.layout.indirect or not 0 <= target < self.layout.size:
            return address  # points at Indirect Data (or nowhere): the byte itself
        return target

    @property
    def torque(self) -> bool:
        return self.value("Torque Enable") == 1

    @property
    def hardware_error(self) -> int:
        return self.value("Hardware Error Status")

    @property
    def current_limit(self) -> int:
        """The Current Limit, or 100.0 % for a model that reports load."""
        return self.value("Current Limit", _LOAD_FULL)


class SimDynamixelChain(Simulator):
    """A chain of simulated X-series servos on a pseudo-terminal (see the module docstring).

    Args:
        servos: Servo id → model name (``{1: "XM430-W350", 2: "XL430-W250"}``; the names of
            :data:`~temoto.drivers.dynamixel.control_table.MODELS`).
        clock: Steps the motion model (a :class:`~temoto.clock.ManualClock` in tests).
        name: For the serving thread's name (``temoto-sim-dxl-<name>``).
        baud: The servos' baud rate (their Baud Rate register): they hear only packets sent
            at this rate (or at whatever the register says after a client changes it). None:
            the baud rate is not modelled, every packet is heard.

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
    ) -> None:
        super().__init__()
        if not servos:
            raise ValueError("a chain needs at least one servo")
        if baud is not None and baud not in _CODE_BY_BAUD:
            raise ValueError(f"baud must be one of {sorted(_CODE_BY_BAUD)}, got {baud!r}")
        chain: list[_Servo] = []
        for dxl_id, model in sorted(servos.items()):
            if not 0 <= dxl_id <= p.MAX_ID:
                raise ValueError(f"servo id must be 0..{p.MAX_ID}, got {dxl_id}")
            if model not in ct.MODELS:
                known = ", ".join(ct.MODELS)
                raise ValueError(f"servo {dxl_id}: unknown model {model!r} (known: {known})")
            servo = _Servo(dxl_id, ct.MODELS[model])
            if baud is not None:
                if _CODE_BY_BAUD[baud] not in servo.model.baud_codes:
                    raise ValueError(f"servo {dxl_id}: {model} has no {baud} baud")
                servo.set("Baud Rate", _CODE_BY_BAUD[baud])
            chain.append(servo)
        self.name = name
        self.baud = baud
        self.clock: Clock = clock or MonotonicClock()
        self._servos = chain
        self._state = threading.Lock()
        self._last_step = self.clock.monotonic()
        for servo in chain:
            servo.booted = self._last_step
        self._reader = p.PacketReader()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._closed = False
        self._corrupt_left: int | None = None  # corrupt replies still to send (replies=)
        #: Packets heard, replies sent, bad packets dropped, REBOOTs, FACTORY_RESETs, and
        #: accepted writes that touched the EEPROM area (a real servo's EEPROM wears with each).
        self.stats: dict[str, int] = {
            "packets": 0,
            "replies": 0,
            "bad_packets": 0,
            "reboots": 0,
            "factory_resets": 0,
            "eeprom_writes": 0,
        }
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
            reg = servo.layout.by_address.get(address) or _GENERIC.get(address)
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

    def _servo(self, dxl_id: int) -> _Servo:
        for servo in self._servos:
            if servo.id == dxl_id:
                return servo
        raise KeyError(f"no servo answers to id {dxl_id}")

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

    def _targets(self, params: Mapping[str, Any]) -> list[_Servo]:
        device = params.get("device")
        if device is None:
            return list(self._servos)
        found = [s for s in self._servos if s.id == device]
        if not found:
            raise ValueError(f"no servo {device} in this chain")
        return found

    def _raise_hardware_error(self, servo: _Servo, kind: str) -> None:
        self._step_locked()
        servo.set("Hardware Error Status", servo.hardware_error | _KIND_BITS[kind])
        servo.set("Torque Enable", 0)
        if kind == "overheat":
            servo.set("Present Temperature", servo.value("Temperature Limit") + 5)
        elif kind == "voltage":
            servo.set("Present Input Voltage", servo.value("Max Voltage Limit") + 10)

    def _silent(self, dxl_id: int) -> bool:
        params = self.fault("silence")
        return params is not None and params.get("device", dxl_id) == dxl_id

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
            if self.fault("link_loss") is not None:
                continue
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
                for reply in replies:
                    self._send(reply)

    def _line_baud(self) -> int | None:
        """The baud rate the client set on the line (None: unknown, or not modelled)."""
        if self.baud is None:
            return None
        try:
            speed = termios.tcgetattr(self._slave)[5]  # the client's output speed
        except (OSError, termios.error):
            return None
        return _LINE_SPEEDS.get(speed)

    def _absent(self, servo: _Servo, line: int | None) -> bool:
        """Whether ``servo`` misses a packet: silenced, at another baud rate or protocol."""
        if self._silent(servo.id) or servo.value("Protocol Type", 2) != 2:
            return True
        return self.baud is not None and _BAUD_BY_CODE.get(servo.value("Baud Rate")) != line

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
        self.stats["replies"] += 1

    def _handle(self, packet: p.Packet, line: int | None = None) -> list[bytes]:
        with self._state:
            self._step_locked()
            if packet.is_status:
                return []
            if packet.id == p.BROADCAST_ID:
                self._hear(self._addressed(packet, line))
                return self._broadcast(packet, line)
            replies: list[bytes] = []
            for servo in [s for s in self._servos if not self._absent(s, line)]:
                if servo.id != packet.id:
                    if servo.value("Secondary ID", 255) == packet.id:  # a group member
                        self._hear((servo,))
                        with contextlib.suppress(_Reject):  # no status packet, RAM only
                            self._unicast(servo, packet, shadow=True)
                    continue
                self._hear((servo,))
                answer_id, answers = servo.id, _answers(servo, packet.instruction)
                try:
                    params = self._unicast(servo, packet)
                except _Reject as reject:
                    params, number = b"", reject.number
                else:
                    number = 0
                if answers:
                    replies.append(self._status(servo, number, params, answer_id))
            return replies

    def _status(
        self, servo: _Servo, number: int, params: bytes = b"", dxl_id: int | None = None
    ) -> bytes:
        alert = p.ALERT_BIT if servo.hardware_error else 0
        return p.status_packet(servo.id if dxl_id is None else dxl_id, number | alert, params)

    def _unicast(self, servo: _Servo, packet: p.Packet, *, shadow: bool = False) -> bytes:
        """Carry out one instruction for one servo; the status packet's parameters.

        ``shadow``: the packet is addressed to the servo's Secondary ID, through which only the
        RAM area can be changed (and no status packet goes back).
        """
        inst, params = packet.instruction, packet.params
        if inst == _I.PING:
            return p.to_le(servo.value("Model Number"), 2) + bytes(
                [servo.value("Firmware Version")]
            )
        if inst == _I.READ:
            if len(params) != 4:
                raise _Reject(_E.DATA_LENGTH)
            return self._read(servo, p.from_le(params[:2]), p.from_le(params[2:]))
        if inst == _I.WRITE:
            if len(params) < 3:
                raise _Reject(_E.DATA_LENGTH)
            self._write(servo, p.from_le(params[:2]), params[2:], ram_only=shadow)
        elif inst == _I.REG_WRITE:
            if len(params) < 3:
                raise _Reject(_E.DATA_LENGTH)
            self._register(servo, p.from_le(params[:2]), params[2:], ram_only=shadow)
        elif inst == _I.ACTION:
            if servo.registered is None:
                raise _Reject(_E.INSTRUCTION)
            self._action(servo)
        elif inst == _I.REBOOT:
            self._reboot(servo)
        elif inst == _I.FACTORY_RESET:
            if shadow:
                raise _Reject(_E.ACCESS)  # it rewrites the EEPROM area
            if len(params) != 1:
                raise _Reject(_E.DATA_LENGTH)
            if params[0] not in (0xFF, 0x01, 0x02):
                raise _Reject(_E.DATA_RANGE)
            self._factory_reset(servo, params[0])
        elif inst == _I.CLEAR:
            self._clear(servo, params)
        else:
            raise _Reject(_E.INSTRUCTION)
        return b""

    def _broadcast(self, packet: p.Packet, line: int | None = None) -> list[bytes]:
        inst, params = packet.instruction, packet.params
        live = sorted((s for s in self._servos if not self._absent(s, line)), key=lambda s: s.id)
        replies: list[bytes] = []
        if inst == _I.PING:
            for servo in live:  # in ascending id order, each after the one before
                replies.append(self._status(servo, 0, self._unicast(servo, packet)))
        elif inst == _I.SYNC_READ and len(params) >= 4:
            address, length = p.from_le(params[:2]), p.from_le(params[2:4])
            for dxl_id in params[4:]:
                for found in (s for s in live if s.id == dxl_id):
                    if _answers(found, inst):
                        replies.append(self._reply_read(found, address, length))
        elif inst == _I.SYNC_WRITE and len(params) >= 4:
            address, length = p.from_le(params[:2]), p.from_le(params[2:4])
            for at in range(4, len(params) - length, length + 1):
                for found in (s for s in live if s.id == params[at]):
                    self._quiet(self._write, found, address, params[at + 1 : at + 1 + length])
        elif inst == _I.BULK_READ:
            for at in range(0, len(params) - 4, 5):
                for found in (s for s in live if s.id == params[at]):
                    if _answers(found, inst):
                        address = p.from_le(params[at + 1 : at + 3])
                        length = p.from_le(params[at + 3 : at + 5])
                        replies.append(self._reply_read(found, address, length))
        elif inst in (_I.FAST_SYNC_READ, _I.FAST_BULK_READ):
            reply = self._fast_read(packet, live)
            if reply is not None:
                replies.append(reply)
        elif inst == _I.BULK_WRITE:
            at = 0
            while at + 5 <= len(params):
                length = p.from_le(params[at + 3 : at + 5])
                for found in (s for s in live if s.id == params[at]):
                    address = p.from_le(params[at + 1 : at + 3])
                    self._quiet(self._write, found, address, params[at + 5 : at + 5 + length])
                at += 5 + length
        elif inst in (_I.WRITE, _I.REG_WRITE) and len(params) >= 3:
            act = self._write if inst == _I.WRITE else self._register
            for servo in live:
                self._quiet(act, servo, p.from_le(params[:2]), params[2:])
        elif inst == _I.ACTION:
            for servo in live:
                if servo.registered is not None:
                    with contextlib.suppress(_Reject):
                        self._action(servo)
        elif inst == _I.REBOOT:
            for servo in live:
                self._reboot(servo)
        elif inst == _I.FACTORY_RESET and len(params) == 1 and params[0] in (0x01, 0x02):
            for servo in live:  # the broadcast form of 0xFF (all) is ignored (firmware v42 on)
                self._factory_reset(servo, params[0])
        elif inst == _I.CLEAR:
            for servo in live:
                with contextlib.suppress(_Reject):
                    self._clear(servo, params)
        return replies

    def _addressed(self, packet: p.Packet, line: int | None) -> list[_Servo]:
        """The servos a broadcast instruction packet is meant for (those that hear it).

        A SYNC or BULK packet is meant for the ids it lists; any other broadcast for every
        servo. (The e-Manual counts "all instruction packets" as communication for the Bus
        Watchdog; a packet that names only other servos is taken as not meant for this one.)
        """
        inst, params = packet.instruction, packet.params
        ids: set[int] | None = None
        if inst in (_I.SYNC_READ, _I.FAST_SYNC_READ):
            ids = set(params[4:])
        elif inst == _I.SYNC_WRITE and len(params) >= 4:
            length = p.from_le(params[2:4])
            ids = {params[at] for at in range(4, len(params), length + 1)}
        elif inst in (_I.BULK_READ, _I.FAST_BULK_READ):
            ids = {params[at] for at in range(0, len(params), 5)}
        elif inst == _I.BULK_WRITE:
            ids, at = set(), 0
            while at + 5 <= len(params):
                ids.add(params[at])
                at += 5 + p.from_le(params[at + 3 : at + 5])
        return [
            s for s in self._servos if (ids is None or s.id in ids) and not self._absent(s, line)
        ]

    def _fast_read(self, packet: p.Packet, live: list[_Servo]) -> bytes | None:
        """FAST_SYNC_READ / FAST_BULK_READ: one status packet the listed servos build together.

        Each servo in turn appends its error, id, data and the CRC of the packet so far; the
        last CRC is the packet's (e-Manual: no byte stuffing in this reply). A listed servo that
        is absent, silent at this Status Return Level or of a model without the instruction
        leaves the packet unfinished: nothing goes out, and the client times out.
        """
        params = packet.params
        wanted: list[tuple[int, int, int]] = []
        if packet.instruction == _I.FAST_SYNC_READ:
            if len(params) < 5:
                return None
            address, length = p.from_le(params[:2]), p.from_le(params[2:4])
            wanted = [(dxl_id, address, length) for dxl_id in params[4:]]
        else:
            for at in range(0, len(params) - 4, 5):
                wanted.append(
                    (
                        params[at],
                        p.from_le(params[at + 1 : at + 3]),
                        p.from_le(params[at + 3 : at + 5]),
                    )
                )
        parts: list[bytes] = []
        for dxl_id, address, length in wanted:
            found = next((s for s in live if s.id == dxl_id), None)
            if (
                found is None
                or found.model.name in _NO_FAST_READ
                or not _answers(found, packet.instruction)
            ):
                return None
            try:
                data, number = self._read(found, address, length), 0
            except _Reject as reject:
                data, number = bytes(length), reject.number
            alert = p.ALERT_BIT if found.hardware_error else 0
            parts.append(bytes([number | alert, dxl_id]) + data)
        if not parts:
            return None
        size = 1 + sum(len(part) + 2 for part in parts)  # INST, then each part and its CRC
        out = bytearray(p.HEADER + bytes([p.BROADCAST_ID]) + p.to_le(size, 2) + bytes([_I.STATUS]))
        for part in parts:
            out += part
            out += p.to_le(p.crc16(out), 2)
        return bytes(out)

    def _reply_read(self, servo: _Servo, address: int, length: int) -> bytes:
        try:
            return self._status(servo, 0, self._read(servo, address, length))
        except _Reject as reject:
            return self._status(servo, reject.number)

    @staticmethod
    def _quiet(act: Any, servo: _Servo, address: int, data: bytes) -> None:
        with contextlib.suppress(_Reject):  # sync, bulk and broadcast writes have no status
            act(servo, address, data)

    # ---- the control table -------------------------------------------------------------------

    def _read(self, servo: _Servo, address: int, length: int) -> bytes:
        if length < 1 or address + length > servo.layout.size:
            raise _Reject(_E.ACCESS)
        return bytes(servo.table[servo.resolve(a)] for a in range(address, address + length))

    def _write(
        self, servo: _Servo, address: int, data: bytes, *, dry: bool = False, ram_only: bool = False
    ) -> None:
        """Check a write as the servo does and (unless ``dry``) carry it out.

        ``ram_only``: the EEPROM area is read-only (a write through the Secondary ID).
        """
        if not data:
            raise _Reject(_E.DATA_LENGTH)
        if address + len(data) > servo.layout.size:
            raise _Reject(_E.ACCESS)
        scratch = bytearray(servo.table)
        touched: dict[int, ct.Register] = {}
        covered: dict[int, int] = {}  # register address → bytes of it this write sets
        for offset, byte in enumerate(data):
            at = servo.resolve(address + offset)
            reg = servo.layout.owner[at]
            if reg is None:
                continue  # a reserved byte: ignored
            scratch[at] = byte
            touched[reg.address] = reg
            covered[reg.address] = covered.get(reg.address, 0) + 1
        if not touched:
            raise _Reject(_E.ACCESS)
        watchdog_error = servo.value("Bus Watchdog") == ct.BUS_WATCHDOG_ERROR
        for reg in touched.values():
            if not reg.writable or (reg.torque_locked and servo.torque):
                raise _Reject(_E.ACCESS)
            if ram_only and reg.eeprom:
                raise _Reject(_E.ACCESS)
            if reg.name in _GOAL_NAMES and watchdog_error:
                raise _Reject(_E.DATA_RANGE)  # goal values are read-only after it expired
        if any(covered[at] < reg.size for at, reg in touched.items()):
            raise _Reject(_E.DATA_LENGTH)  # only part of a register (2 bytes of a 4-byte one)

        def new(reg: ct.Register) -> int:
            return p.from_le(bytes(scratch[reg.address : reg.address + reg.size]), reg.signed)

        def now(name: str, default: int = 0) -> int:
            reg = servo.reg(name)
            return default if reg is None else new(reg)

        for reg in touched.values():
            self._check(servo, reg, new(reg), now)
        if dry:
            return
        if any(reg.eeprom for reg in touched.values()):
            self.stats["eeprom_writes"] += 1
        for reg in touched.values():
            value = new(reg)
            if reg.name == "Torque Enable" and value and servo.hardware_error:
                continue  # a servo with a hardware error keeps its torque off
            if (reg.name == "Torque Enable" and not value) or reg.name in _GOAL_NAMES:
                servo.halted = False
            if reg.name == "Homing Offset":  # Present Position = actual position + offset
                servo.position += value - servo.get(reg)
                servo.set("Present Position", round(servo.position))
            servo.put(reg, value)
        goal = any(reg.name in _GOAL_NAMES for reg in touched.values())
        if goal and servo.value("Drive Mode") & _TORQUE_ON_BY_GOAL and not servo.hardware_error:
            servo.set("Torque Enable", 1)  # Drive Mode bit 3: Torque On by Goal Update

    def _check(self, servo: _Servo, reg: ct.Register, value: int, now: Any) -> None:
        """Refuse ``value`` for ``reg`` as the e-Manual says (``now``: values after the write)."""
        name = reg.name
        mode = now("Operating Mode")
        if name == "Operating Mode":
            if value not in {int(m) for m in servo.model.modes}:
                raise _Reject(_E.DATA_RANGE)
        elif name == "Bus Watchdog":
            if not 0 <= value <= ct.BUS_WATCHDOG_MAX:
                raise _Reject(_E.DATA_RANGE)
            if value and servo.value("Bus Watchdog") == ct.BUS_WATCHDOG_ERROR:
                raise _Reject(_E.DATA_RANGE)  # only 0 clears the error
        elif name == "Drive Mode":
            if value & ~(reg.high or 0):
                raise _Reject(_E.DATA_RANGE)  # a bit the model does not have
        elif name == "Goal Position":
            if mode == ct.OperatingMode.POSITION:
                if not now("Min Position Limit") <= value <= now("Max Position Limit"):
                    raise _Reject(_E.DATA_LIMIT)
            elif abs(value) > _EXTENDED_GOAL:
                raise _Reject(_E.DATA_RANGE)
        elif name == "Goal Velocity":
            if abs(value) > now("Velocity Limit"):
                raise _Reject(_E.DATA_LIMIT)
        elif name == "Goal Current":
            if abs(value) > now("Current Limit"):
                raise _Reject(_E.DATA_LIMIT)
        elif name == "Goal PWM":
            if abs(value) > now("PWM Limit", _PWM_FULL):
                raise _Reject(_E.DATA_LIMIT)
        elif reg.low is not None and reg.high is not None and not reg.low <= value <= reg.high:
            raise _Reject(_E.DATA_RANGE)

    def _register(
        self, servo: _Servo, address: int, data: bytes, *, ram_only: bool = False
    ) -> None:
        """REG_WRITE: check now, hold until ACTION."""
        self._write(servo, address, data, dry=True, ram_only=ram_only)
        servo.registered = (address, bytes(data))
        servo.set("Registered Instruction", 1)

    def _action(self, servo: _Servo) -> None:
        """ACTION: carry out the registered write."""
        held, servo.registered = servo.registered, None
        servo.set("Registered Instruction", 0)
        if held is not None:
            self._write(servo, *held)

    def _reboot(self, servo: _Servo) -> None:
        """REBOOT: the RAM area back to its initial values, the multi-turn count dropped."""
        self.stats["reboots"] += 1
        params = self.fault("hardware_error")
        still = params is not None and params.get("device", servo.id) == servo.id
        for reg in servo.model.registers:
            if not reg.eeprom:
                servo.put(reg, reg.default)
        offset = servo.value("Homing Offset")
        servo.position = float((round(servo.position) - offset) % 4096 + offset)
        servo.set("Present Position", round(servo.position))
        servo.set("Position Trajectory", round(servo.position))
        servo.set("Goal Position", round(servo.position))
        servo.halted = False
        servo.velocity = 0.0
        servo.current = 0.0
        servo.registered = None
        servo.booted = self.clock.monotonic()
        if still and params is not None:
            self._raise_hardware_error(servo, str(params.get("kind", "overheat")))
        elif servo.value("Startup Configuration") & 0x01:
            servo.set("Torque Enable", 1)  # Startup Torque On

    def _factory_reset(self, servo: _Servo, option: int) -> None:
        """FACTORY_RESET: every register to its factory value (but the ID / the baud rate)."""
        self.stats["factory_resets"] += 1
        keep = {"ID", "Baud Rate"} if option == 0x02 else {"ID"} if option == 0x01 else set()
        servo.position -= servo.value("Homing Offset")  # back to 0 with the rest
        for reg in servo.model.registers:
            if reg.eeprom and reg.name not in keep:
                servo.put(reg, reg.default)
        self._reboot(servo)

    def _clear(self, servo: _Servo, params: bytes) -> None:
        """CLEAR 0x01: Present Position back within one turn (only while it stands still)."""
        if len(params) != len(_CLEAR_MULTI_TURN):
            raise _Reject(_E.DATA_LENGTH)
        if params != _CLEAR_MULTI_TURN:
            raise _Reject(_E.DATA_RANGE)
        if servo.value("Moving") or abs(servo.velocity) > _TICKS_S_PER_UNIT:
            raise _Reject(_E.RESULT_FAIL)
        turns = math.floor((servo.position - servo.value("Homing Offset")) / 4096)
        servo.position -= turns * 4096
        for name in ("Present Position", "Position Trajectory"):
            servo.set(name, round(servo.position))
        if servo.value("Operating Mode") in _POSITION_MODES:  # keep standing where it is
            servo.set("Goal Position", servo.value("Goal Position") - turns * 4096)

    # ---- motion ------------------------------------------------------------------------------

    def _step_locked(self) -> None:
        now = self.clock.monotonic()
        start = self._last_step
        dt = now - start
        self._last_step = now
        if dt <= 0:
            return
        for servo in self._servos:
            expiry = _watchdog_expiry(servo)
            if expiry is not None and expiry < now:
                _move(servo, max(expiry - start, 0.0))  # up to the moment it expired
                _expire_watchdog(servo)
                _move(servo, now - max(expiry, start))
            else:
                _move(servo, dt)
            servo.set("Realtime Tick", int((now - servo.booted) * 1000) % 32768)

    def _hear(self, servos: Iterable[_Servo]) -> None:
        """An instruction packet for ``servos`` arrived now: their Bus Watchdogs restart."""
        now = self.clock.monotonic()
        for servo in servos:
            servo.heard = now


def _answers(servo: _Servo, inst: int) -> bool:
    """Whether the servo sends a status packet for ``inst`` (its Status Return Level)."""
    if inst == _I.PING:
        return True
    level = servo.value("Status Return Level", 2)
    return level >= 2 or (level == 1 and inst in _READS)


def _move(servo: _Servo, dt: float) -> None:
    """Advance one servo's first-order model by ``dt`` seconds and refresh its registers."""
    mode = servo.value("Operating Mode")
    limit_units = max(servo.value("Velocity Limit"), 1)
    current_limit = max(servo.current_limit, 1)
    target = float(servo.value("Goal Position"))
    if not servo.torque or servo.halted:
        servo.velocity = 0.0
        servo.current = 0.0
        target = servo.position
    else:
        vmax = limit_units * _TICKS_S_PER_UNIT
        if mode in _POSITION_MODES:
            profile = servo.value("Profile Velocity")
            if 0 < profile < limit_units:
                vmax = profile * _TICKS_S_PER_UNIT
            if mode == ct.OperatingMode.POSITION:
                low = servo.value("Min Position Limit")
                target = min(max(target, low), servo.value("Max Position Limit", 4095))
            if dt >= _SNAP_AFTER:
                servo.position, servo.velocity = target, 0.0
            else:
                steps = max(1, math.ceil(dt / _SUBSTEP))
                h = dt / steps
                for _ in range(steps):
                    servo.velocity = min(max((target - servo.position) / _TAU, -vmax), vmax)
                    servo.position += servo.velocity * h
            share = (target - servo.position) / 512.0  # ~45° of error: the full share
            servo.current = min(max(share, -1.0), 1.0) * 0.5 * current_limit
        else:
            if mode == ct.OperatingMode.VELOCITY:
                goal_v = servo.value("Goal Velocity") * _TICKS_S_PER_UNIT
            elif mode == ct.OperatingMode.PWM:  # crudely: the goal's share of full PWM
                goal_v = servo.value("Goal PWM") / _PWM_FULL * vmax
            else:  # current: the goal's share of the limit sets the speed
                goal_v = servo.value("Goal Current") / current_limit * vmax
            goal_v = min(max(goal_v, -vmax), vmax)
            decay = 1.0 - math.exp(-dt / _TAU)
            start_v = servo.velocity
            servo.velocity += (goal_v - servo.velocity) * decay
            servo.position += (start_v + servo.velocity) / 2.0 * dt
            if mode == ct.OperatingMode.CURRENT:
                servo.current = float(servo.value("Goal Current"))
            else:
                share = (goal_v - servo.velocity) / vmax + 0.05 * math.copysign(
                    1.0 if servo.velocity else 0.0, servo.velocity
                )
                servo.current = min(max(share, -1.0), 1.0) * current_limit
            target = servo.position
    servo.position = min(max(servo.position, -(2.0**31) + 1), 2.0**31 - 1)
    units = round(servo.velocity / _TICKS_S_PER_UNIT)
    moving = abs(units) > servo.value("Moving Threshold", 10)
    in_position = servo.torque and mode in _POSITION_MODES and abs(target - servo.position) < 1
    pwm_limit = servo.value("PWM Limit", _PWM_FULL)
    if mode == ct.OperatingMode.PWM and servo.torque and not servo.halted:
        pwm = servo.value("Goal PWM")
    else:
        pwm = round(servo.current / current_limit * pwm_limit)
    servo.set("Present Position", round(servo.position))
    servo.set("Present Velocity", units)
    servo.set("Present Current", min(max(round(servo.current), -32768), 32767))
    servo.set("Present Load", min(max(round(servo.current), -_LOAD_FULL), _LOAD_FULL))
    servo.set("Present PWM", min(max(pwm, -pwm_limit), pwm_limit))
    servo.set("Velocity Trajectory", units)
    servo.set("Position Trajectory", round(target))
    servo.set("Moving", 1 if moving else 0)
    servo.set("Moving Status", (1 if in_position else 0) | (2 if moving else 0))


def _watchdog_expiry(servo: _Servo) -> float | None:
    """When the servo's armed Bus Watchdog expires (None: off, expired, or torque off)."""
    units = servo.value("Bus Watchdog")
    if units <= 0 or not servo.torque:
        return None
    return servo.heard + units * ct.BUS_WATCHDOG_UNIT


def _expire_watchdog(servo: _Servo) -> None:
    """The Bus Watchdog expired: the servo stops where it is and reads -1 until cleared."""
    servo.set("Bus Watchdog", ct.BUS_WATCHDOG_ERROR)
    servo.halted = True
    servo.velocity = 0.0
    servo.current = 0.0


def chain_from_ids(ids: Iterable[int], model: str = "XM430-W350") -> dict[int, str]:
    """``{id: model}`` for ids of one model (a helper for tests and benchmarks).

    Args:
        ids: Servo ids.
        model: Their model.

    Returns:
        The mapping :class:`SimDynamixelChain` takes.
    """
    return dict.fromkeys(ids, model)
