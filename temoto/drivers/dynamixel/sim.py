"""A simulated chain of DYNAMIXEL X-series servos answering Protocol 2.0 on a pseudo-terminal.

:class:`SimDynamixelChain` opens a pseudo-terminal **in its constructor** (so
:attr:`~SimDynamixelChain.path`, the slave's ``/dev/pts/N``, is known before anything starts),
serves the master end on a named thread between :meth:`~SimDynamixelChain.start` and
:meth:`~SimDynamixelChain.close`, and gives every servo a control table
(:mod:`~temoto.drivers.dynamixel.control_table`). Whatever opens the slave path -- dynamixel-sdk's
``PortHandler`` in the driver and the tests -- talks to it exactly as to a U2D2 and a chain.
A pseudo-terminal carries bytes whatever the baud rate; replies go out at once (no Return
Delay Time). A chain made with ``baud=`` models the baud rate all the same: each servo then
hears only the packets sent while the line is set (``termios``, as dynamixel-sdk's
``PortHandler`` sets it through pyserial) to the rate its Baud Rate register selects, as a
servo's UART hears only noise at another rate; without ``baud`` every packet is heard.

Instructions answered: PING (also broadcast: every servo answers, in ascending id order),
READ, WRITE, SYNC_READ, SYNC_WRITE, BULK_READ, BULK_WRITE and REBOOT; FACTORY_RESET is refused
(``RESULT_FAIL``), anything else answers ``INSTRUCTION``. PING answers with the Model Number
register, as a servo does. An instruction packet with a bad CRC is dropped. Writes check
access (read-only registers, the EEPROM area while torque is on), the operating modes of the
model, the Baud Rate codes and the limit registers (``DATA_LIMIT``), as a real servo does.

Motion (first order, stepped on the injected clock whenever a packet arrives): in the position
modes the position approaches the goal with a time constant of 50 ms at no more than the profile
velocity (or the Velocity Limit register), within the position limits in Position mode; in
Velocity mode the velocity approaches the goal velocity; in Current mode it approaches the
speed that the goal current's share of the Current Limit gives. Present Current is the effort
of that tracking (a proportional share of the Current Limit). Torque off stops the servo.

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
_TABLE_SIZE: Final = 256
_E = p.ErrorNumber

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


class _Reject(Exception):
    """An instruction a servo refuses: answered with this error number."""

    def __init__(self, number: int) -> None:
        super().__init__(number)
        self.number = number


@dataclass
class _Servo:
    """One simulated servo: its control table and the continuous state behind it."""

    id: int
    model: ct.Model
    table: bytearray = field(default_factory=lambda: bytearray(_TABLE_SIZE))
    position: float = float(ct.POSITION_CENTER)  # ticks
    velocity: float = 0.0  # ticks/s
    current: float = 0.0  # current units
    heard: float = 0.0  # clock time of the newest instruction packet meant for it
    halted: bool = False  # stopped by its Bus Watchdog; until torque off or a new goal

    def __post_init__(self) -> None:
        for reg in ct.REGISTERS:
            self.put(reg, reg.default)
        self.put(ct.MODEL_NUMBER, self.model.number)
        self.put(_REG["ID"], self.id)
        self.put(ct.PRESENT_INPUT_VOLTAGE, round(self.model.nominal_voltage * 10))

    def get(self, reg: ct.Register) -> int:
        data = self.table[reg.address : reg.address + reg.size]
        return p.from_le(bytes(data), reg.signed)

    def put(self, reg: ct.Register, value: int) -> None:
        self.table[reg.address : reg.address + reg.size] = p.to_le(value, reg.size)

    @property
    def torque(self) -> bool:
        return self.get(ct.TORQUE_ENABLE) == 1

    @property
    def hardware_error(self) -> int:
        return self.get(ct.HARDWARE_ERROR_STATUS)


_REG: Final = {r.name: r for r in ct.REGISTERS}
_BY_ADDRESS: Final = {r.address: r for r in ct.REGISTERS}


class SimDynamixelChain(Simulator):
    """A chain of simulated X-series servos on a pseudo-terminal (see the module docstring).

    Args:
        servos: Servo id → model name (``{1: "XM430-W350", 2: "XL430-W250"}``).
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
        chain: dict[int, _Servo] = {}
        for dxl_id, model in sorted(servos.items()):
            if not 0 <= dxl_id <= p.MAX_ID:
                raise ValueError(f"servo id must be 0..{p.MAX_ID}, got {dxl_id}")
            if model not in ct.MODELS:
                raise ValueError(f"servo {dxl_id}: unknown model {model!r}")
            chain[dxl_id] = _Servo(dxl_id, ct.MODELS[model])
            if baud is not None:
                chain[dxl_id].put(_REG["Baud Rate"], _CODE_BY_BAUD[baud])
        self.name = name
        self.baud = baud
        self.clock: Clock = clock or MonotonicClock()
        self._servos = chain
        self._state = threading.Lock()
        self._last_step = self.clock.monotonic()
        self._reader = p.PacketReader()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._closed = False
        self._corrupt_left: int | None = None  # corrupt replies still to send (replies=)
        #: Packets heard, replies sent, bad packets dropped, REBOOTs, and accepted writes that
        #: touched the EEPROM area (a real servo's EEPROM wears with each).
        self.stats: dict[str, int] = {
            "packets": 0,
            "replies": 0,
            "bad_packets": 0,
            "reboots": 0,
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
        return f"<SimDynamixelChain {self.name!r} {self.path} ids={list(self._servos)}>"

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
        """The servo ids, ascending."""
        return tuple(self._servos)

    def read_register(self, dxl_id: int, address: int) -> int:
        """A register's value (stepping the model first).

        Args:
            dxl_id: The servo.
            address: A register address from :data:`~control_table.REGISTERS`.

        Returns:
            The value.
        """
        reg = _BY_ADDRESS[address]
        with self._state:
            self._step_locked()
            return self._servos[dxl_id].get(reg)

    def write_register(self, dxl_id: int, address: int, value: int) -> None:
        """Set a register directly, bypassing access checks (for tests).

        Args:
            dxl_id: The servo.
            address: A register address.
            value: The value.
        """
        reg = _BY_ADDRESS[address]
        with self._state:
            servo = self._servos[dxl_id]
            servo.put(reg, value)
            if reg is ct.PRESENT_POSITION:
                servo.position = float(value)

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
            return list(self._servos.values())
        if device not in self._servos:
            raise ValueError(f"no servo {device} in this chain")
        return [self._servos[device]]

    def _raise_hardware_error(self, servo: _Servo, kind: str) -> None:
        self._step_locked()
        servo.put(ct.HARDWARE_ERROR_STATUS, servo.hardware_error | _KIND_BITS[kind])
        servo.put(ct.TORQUE_ENABLE, 0)
        if kind == "overheat":
            servo.put(ct.PRESENT_TEMPERATURE, servo.get(_REG["Temperature Limit"]) + 5)
        elif kind == "voltage":
            servo.put(ct.PRESENT_INPUT_VOLTAGE, servo.get(_REG["Max Voltage Limit"]) + 10)

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
        """Whether ``servo`` misses a packet: silenced, or listening at another baud rate."""
        if self._silent(servo.id):
            return True
        return self.baud is not None and _BAUD_BY_CODE.get(servo.get(_REG["Baud Rate"])) != line

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
            servo = self._servos.get(packet.id)
            if servo is None or self._absent(servo, line):
                return []
            self._hear((servo,))
            try:
                params = self._unicast(servo, packet)
            except _Reject as reject:
                return [self._status(servo, reject.number)]
            if params is None:
                return []
            return [self._status(servo, 0, params)]

    def _status(self, servo: _Servo, number: int, params: bytes = b"") -> bytes:
        alert = p.ALERT_BIT if servo.hardware_error else 0
        return p.status_packet(servo.id, number | alert, params)

    def _unicast(self, servo: _Servo, packet: p.Packet) -> bytes | None:
        inst, params = packet.instruction, packet.params
        if inst == p.Instruction.PING:
            number = servo.get(ct.MODEL_NUMBER)
            return p.to_le(number, 2) + bytes([servo.get(_REG["Firmware Version"])])
        if inst == p.Instruction.READ:
            if len(params) != 4:
                raise _Reject(_E.DATA_LENGTH)
            return self._read(servo, p.from_le(params[:2]), p.from_le(params[2:]))
        if inst == p.Instruction.WRITE:
            if len(params) < 3:
                raise _Reject(_E.DATA_LENGTH)
            self._write(servo, p.from_le(params[:2]), params[2:])
            return b""
        if inst == p.Instruction.REBOOT:
            self._reboot(servo)
            return b""
        if inst == p.Instruction.FACTORY_RESET:
            raise _Reject(_E.RESULT_FAIL)
        raise _Reject(_E.INSTRUCTION)

    def _broadcast(self, packet: p.Packet, line: int | None = None) -> list[bytes]:
        inst, params = packet.instruction, packet.params
        live = [s for s in self._servos.values() if not self._absent(s, line)]
        replies: list[bytes] = []
        if inst == p.Instruction.PING:
            for servo in live:  # in ascending id order, each after the one before
                replies.append(self._status(servo, 0, self._unicast(servo, packet) or b""))
        elif inst == p.Instruction.SYNC_READ and len(params) >= 4:
            address, length = p.from_le(params[:2]), p.from_le(params[2:4])
            for dxl_id in params[4:]:
                found = self._servos.get(dxl_id)
                if found is not None and found in live:
                    replies.append(self._reply_read(found, address, length))
        elif inst == p.Instruction.SYNC_WRITE and len(params) >= 4:
            address, length = p.from_le(params[:2]), p.from_le(params[2:4])
            for at in range(4, len(params) - length, length + 1):
                found = self._servos.get(params[at])
                if found is not None and found in live:
                    self._quiet_write(found, address, params[at + 1 : at + 1 + length])
        elif inst == p.Instruction.BULK_READ:
            for at in range(0, len(params) - 4, 5):
                found = self._servos.get(params[at])
                if found is not None and found in live:
                    address = p.from_le(params[at + 1 : at + 3])
                    replies.append(
                        self._reply_read(found, address, p.from_le(params[at + 3 : at + 5]))
                    )
        elif inst == p.Instruction.BULK_WRITE:
            at = 0
            while at + 5 <= len(params):
                length = p.from_le(params[at + 3 : at + 5])
                found = self._servos.get(params[at])
                if found is not None and found in live:
                    address = p.from_le(params[at + 1 : at + 3])
                    self._quiet_write(found, address, params[at + 5 : at + 5 + length])
                at += 5 + length
        elif inst == p.Instruction.WRITE and len(params) >= 3:
            for servo in live:
                self._quiet_write(servo, p.from_le(params[:2]), params[2:])
        return replies

    def _addressed(self, packet: p.Packet, line: int | None) -> list[_Servo]:
        """The servos a broadcast instruction packet is meant for (those that hear it).

        A SYNC or BULK packet is meant for the ids it lists; any other broadcast for every
        servo. (The e-Manual counts "all instruction packets" as communication for the Bus
        Watchdog; a packet that names only other servos is taken as not meant for this one.)
        """
        inst, params = packet.instruction, packet.params
        ids: set[int] | None = None
        if inst in (p.Instruction.SYNC_READ, p.Instruction.FAST_SYNC_READ):
            ids = set(params[4:])
        elif inst == p.Instruction.SYNC_WRITE and len(params) >= 4:
            length = p.from_le(params[2:4])
            ids = {params[at] for at in range(4, len(params), length + 1)}
        elif inst == p.Instruction.BULK_READ:
            ids = {params[at] for at in range(0, len(params), 5)}
        elif inst == p.Instruction.BULK_WRITE:
            ids, at = set(), 0
            while at + 5 <= len(params):
                ids.add(params[at])
                at += 5 + p.from_le(params[at + 3 : at + 5])
        return [
            s
            for s in self._servos.values()
            if (ids is None or s.id in ids) and not self._absent(s, line)
        ]

    def _reply_read(self, servo: _Servo, address: int, length: int) -> bytes:
        try:
            return self._status(servo, 0, self._read(servo, address, length))
        except _Reject as reject:
            return self._status(servo, reject.number)

    def _quiet_write(self, servo: _Servo, address: int, data: bytes) -> None:
        with contextlib.suppress(_Reject):  # sync and bulk writes have no status packet
            self._write(servo, address, data)

    # ---- the control table -------------------------------------------------------------------

    def _read(self, servo: _Servo, address: int, length: int) -> bytes:
        if length < 1 or address + length > _TABLE_SIZE:
            raise _Reject(_E.ACCESS)
        return bytes(servo.table[address : address + length])

    def _write(self, servo: _Servo, address: int, data: bytes) -> None:
        end = address + len(data)
        if end > _TABLE_SIZE:
            raise _Reject(_E.ACCESS)
        touched = [r for r in ct.REGISTERS if r.address < end and address < r.address + r.size]
        for reg in touched:
            if not reg.writable or (reg.eeprom and servo.torque):
                raise _Reject(_E.ACCESS)
            if reg in ct.GOAL_REGISTERS and servo.get(ct.BUS_WATCHDOG) == ct.BUS_WATCHDOG_ERROR:
                raise _Reject(_E.DATA_RANGE)  # goal values are read-only after it expired
        scratch = bytearray(servo.table)
        scratch[address:end] = data
        for reg in touched:
            value = p.from_le(bytes(scratch[reg.address : reg.address + reg.size]), reg.signed)
            self._check(servo, reg, value)
        if any(reg.eeprom for reg in touched):
            self.stats["eeprom_writes"] += 1
        for reg in touched:
            value = p.from_le(bytes(scratch[reg.address : reg.address + reg.size]), reg.signed)
            if reg is ct.TORQUE_ENABLE and value and servo.hardware_error:
                continue  # a servo with a hardware error keeps its torque off
            if (reg is ct.TORQUE_ENABLE and not value) or reg in ct.GOAL_REGISTERS:
                servo.halted = False
            servo.put(reg, value)

    def _check(self, servo: _Servo, reg: ct.Register, value: int) -> None:
        mode = servo.get(ct.OPERATING_MODE)
        if reg is ct.OPERATING_MODE:
            if value not in {int(m) for m in servo.model.modes}:
                raise _Reject(_E.DATA_RANGE)
        elif reg is ct.TORQUE_ENABLE:
            if value not in (0, 1):
                raise _Reject(_E.DATA_RANGE)
        elif reg is _REG["Baud Rate"]:
            if value not in _BAUD_BY_CODE:
                raise _Reject(_E.DATA_RANGE)
        elif reg is ct.BUS_WATCHDOG:
            if not 0 <= value <= ct.BUS_WATCHDOG_MAX:
                raise _Reject(_E.DATA_RANGE)
            if value and servo.get(ct.BUS_WATCHDOG) == ct.BUS_WATCHDOG_ERROR:
                raise _Reject(_E.DATA_RANGE)  # only 0 clears the error
        elif reg is ct.RETURN_DELAY_TIME:
            if value > ct.RETURN_DELAY_MAX:
                raise _Reject(_E.DATA_RANGE)
        elif reg in (ct.MIN_POSITION_LIMIT, ct.MAX_POSITION_LIMIT):
            if not 0 <= value <= 4095:
                raise _Reject(_E.DATA_RANGE)
        elif reg is ct.GOAL_POSITION and mode == ct.OperatingMode.POSITION:
            if (
                not servo.get(_REG["Min Position Limit"])
                <= value
                <= servo.get(_REG["Max Position Limit"])
            ):
                raise _Reject(_E.DATA_LIMIT)
        elif reg is ct.GOAL_VELOCITY:
            if abs(value) > servo.get(_REG["Velocity Limit"]):
                raise _Reject(_E.DATA_LIMIT)
        elif reg is ct.GOAL_CURRENT:
            if servo.model.current_unit is None:
                raise _Reject(_E.ACCESS)
            if abs(value) > servo.get(_REG["Current Limit"]):
                raise _Reject(_E.DATA_LIMIT)

    def _reboot(self, servo: _Servo) -> None:
        self.stats["reboots"] += 1
        params = self.fault("hardware_error")
        still = params is not None and params.get("device", servo.id) == servo.id
        servo.put(ct.TORQUE_ENABLE, 0)
        servo.put(ct.HARDWARE_ERROR_STATUS, 0)
        servo.put(ct.PRESENT_TEMPERATURE, _REG["Present Temperature"].default)
        servo.put(ct.PRESENT_INPUT_VOLTAGE, round(servo.model.nominal_voltage * 10))
        servo.put(ct.GOAL_VELOCITY, 0)
        servo.put(ct.GOAL_CURRENT, 0)
        servo.put(ct.GOAL_POSITION, round(servo.position))
        servo.put(ct.BUS_WATCHDOG, 0)
        servo.halted = False
        servo.velocity = 0.0
        servo.current = 0.0
        if still and params is not None:
            self._raise_hardware_error(servo, str(params.get("kind", "overheat")))

    # ---- motion ------------------------------------------------------------------------------

    def _step_locked(self) -> None:
        now = self.clock.monotonic()
        start = self._last_step
        dt = now - start
        self._last_step = now
        if dt <= 0:
            return
        for servo in self._servos.values():
            expiry = _watchdog_expiry(servo)
            if expiry is not None and expiry < now:
                _move(servo, max(expiry - start, 0.0))  # up to the moment it expired
                _expire_watchdog(servo)
                _move(servo, now - max(expiry, start))
            else:
                _move(servo, dt)

    def _hear(self, servos: Iterable[_Servo]) -> None:
        """An instruction packet for ``servos`` arrived now: their Bus Watchdogs restart."""
        now = self.clock.monotonic()
        for servo in servos:
            servo.heard = now


def _move(servo: _Servo, dt: float) -> None:
    """Advance one servo's first-order model by ``dt`` seconds and refresh its registers."""
    if not servo.torque or servo.halted:
        servo.velocity = 0.0
        servo.current = 0.0
    else:
        mode = servo.get(ct.OPERATING_MODE)
        limit_units = max(servo.get(_REG["Velocity Limit"]), 1)
        current_limit = max(servo.get(_REG["Current Limit"]), 1)
        vmax = limit_units * _TICKS_S_PER_UNIT
        if mode in (
            ct.OperatingMode.POSITION,
            ct.OperatingMode.EXTENDED_POSITION,
            ct.OperatingMode.CURRENT_BASED_POSITION,
        ):
            profile = servo.get(ct.PROFILE_VELOCITY)
            if 0 < profile < limit_units:
                vmax = profile * _TICKS_S_PER_UNIT
            target = float(servo.get(ct.GOAL_POSITION))
            if mode == ct.OperatingMode.POSITION:
                low = servo.get(_REG["Min Position Limit"])
                target = min(max(target, low), servo.get(_REG["Max Position Limit"]))
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
                goal_v = servo.get(ct.GOAL_VELOCITY) * _TICKS_S_PER_UNIT
            else:  # current (and PWM, crudely): the goal's share of the limit sets the speed
                goal_v = servo.get(ct.GOAL_CURRENT) / current_limit * vmax
            goal_v = min(max(goal_v, -vmax), vmax)
            decay = 1.0 - math.exp(-dt / _TAU)
            start_v = servo.velocity
            servo.velocity += (goal_v - servo.velocity) * decay
            servo.position += (start_v + servo.velocity) / 2.0 * dt
            if mode == ct.OperatingMode.VELOCITY:
                share = (goal_v - servo.velocity) / vmax + 0.05 * math.copysign(
                    1.0 if servo.velocity else 0.0, servo.velocity
                )
                servo.current = min(max(share, -1.0), 1.0) * current_limit
            else:
                servo.current = float(servo.get(ct.GOAL_CURRENT))
    servo.position = min(max(servo.position, -(2.0**31) + 1), 2.0**31 - 1)
    servo.put(ct.PRESENT_POSITION, round(servo.position))
    servo.put(ct.PRESENT_VELOCITY, round(servo.velocity / _TICKS_S_PER_UNIT))
    servo.put(ct.PRESENT_CURRENT, min(max(round(servo.current), -32768), 32767))
    servo.put(_REG["Moving"], 1 if abs(servo.velocity) > _TICKS_S_PER_UNIT else 0)


def _watchdog_expiry(servo: _Servo) -> float | None:
    """When the servo's armed Bus Watchdog expires (None: off, expired, or torque off)."""
    units = servo.get(ct.BUS_WATCHDOG)
    if units <= 0 or not servo.torque:
        return None
    return servo.heard + units * ct.BUS_WATCHDOG_UNIT


def _expire_watchdog(servo: _Servo) -> None:
    """The Bus Watchdog expired: the servo stops where it is and reads -1 until cleared."""
    servo.put(ct.BUS_WATCHDOG, ct.BUS_WATCHDOG_ERROR)
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
