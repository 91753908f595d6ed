"""The simulated chain's servos and what they do with Protocol 2.0 instruction packets.

:class:`ServoChain` is the part of :class:`~temoto.drivers.dynamixel.sim.SimDynamixelChain`
that needs no I/O: the servos (:class:`~temoto.drivers.dynamixel.sim_servo.Servo`), stepped on
the injected clock, and one method per instruction, checked and answered as the e-Manual
describes them (the list is in :mod:`~temoto.drivers.dynamixel.sim`'s docstring): the routing
of a packet to its servos (broadcast, Secondary ID groups, the baud rate and protocol each servo
listens at), Status Return Level, READ/WRITE and their SYNC/BULK/FAST forms with the servos'
access, range, limit and length checks, REG_WRITE/ACTION, REBOOT, FACTORY_RESET and CLEAR.
:meth:`ServoChain._handle` takes one decoded packet and returns the status packets to send;
:class:`~temoto.drivers.dynamixel.sim.SimDynamixelChain` adds the pseudo-terminal around it.
"""

from __future__ import annotations

import contextlib
import math
import threading
from collections.abc import Iterable, Mapping
from typing import Any, Final

from temoto.clock import Clock, MonotonicClock
from temoto.drivers.dynamixel import control_table as ct
from temoto.drivers.dynamixel import protocol as p
from temoto.drivers.dynamixel.sim_servo import (
    BAUD_BY_CODE,
    CODE_BY_BAUD,
    POSITION_MODES,
    PWM_FULL,
    TICKS_S_PER_UNIT,
    Servo,
    expire_watchdog,
    move,
    watchdog_expiry,
)
from temoto.drivers.sim import Simulator

_RAD_PER_TICK: Final = 2.0 * math.pi / 4096.0  # Present Position's unit (0.088°)
_RAD_S_PER_UNIT: Final = TICKS_S_PER_UNIT * _RAD_PER_TICK  # Present Velocity's (0.229 rpm)

__all__ = ["ServoChain"]

_EXTENDED_GOAL: Final = 1_048_575  # |Goal Position| in the multi-turn modes (e-Manual)

_CLEAR_MULTI_TURN: Final = bytes([0x01, 0x44, 0x58, 0x4C, 0x22])

_TORQUE_ON_BY_GOAL: Final = 0x08  # Drive Mode bit 3 (firmware v45 on; v46 on the XL330)

_E = p.ErrorNumber

_I = p.Instruction

_KIND_BITS: Final[Mapping[str, int]] = {
    "overheat": p.HardwareError.OVERHEATING,
    "overload": p.HardwareError.OVERLOAD,
    "voltage": p.HardwareError.INPUT_VOLTAGE,
}

_GOAL_NAMES: Final = frozenset(r.name for r in ct.GOAL_REGISTERS)

#: Instructions answered at Status Return Level 1 (PING is answered at every level).
_READS: Final = frozenset(
    {_I.READ, _I.SYNC_READ, _I.BULK_READ, _I.FAST_SYNC_READ, _I.FAST_BULK_READ}
)

#: Models without Fast Sync/Bulk Read (e-Manual: "2XL/2XC Not Supported").
_NO_FAST_READ: Final = frozenset({"2XL430-W250"})


class _Reject(Exception):
    """An instruction a servo refuses: answered with this error number."""

    def __init__(self, number: int) -> None:
        super().__init__(number)
        self.number = number


def _answers(servo: Servo, inst: int) -> bool:
    """Whether the servo sends a status packet for ``inst`` (its Status Return Level)."""
    if inst == _I.PING:
        return True
    level = servo.value("Status Return Level", 2)
    return level >= 2 or (level == 1 and inst in _READS)


class ServoChain(Simulator):
    """A chain's servos and their answers to instruction packets (see the module docstring).

    Args:
        servos: Servo id → model name (as :class:`~temoto.drivers.dynamixel.sim.SimDynamixelChain`
            takes them).
        clock: Steps the motion model.
        baud: The servos' baud rate, or None (not modelled).

    Raises:
        ValueError: No servos, a bad id, an unknown model or a baud rate the X series lacks.
    """

    def __init__(
        self, servos: Mapping[int, str], *, clock: Clock | None = None, baud: int | None = None
    ) -> None:
        super().__init__()
        if not servos:
            raise ValueError("a chain needs at least one servo")
        if baud is not None and baud not in CODE_BY_BAUD:
            raise ValueError(f"baud must be one of {sorted(CODE_BY_BAUD)}, got {baud!r}")
        chain: list[Servo] = []
        for dxl_id, model in sorted(servos.items()):
            if not 0 <= dxl_id <= p.MAX_ID:
                raise ValueError(f"servo id must be 0..{p.MAX_ID}, got {dxl_id}")
            if model not in ct.MODELS:
                known = ", ".join(ct.MODELS)
                raise ValueError(f"servo {dxl_id}: unknown model {model!r} (known: {known})")
            servo = Servo(dxl_id, ct.MODELS[model])
            if baud is not None:
                if CODE_BY_BAUD[baud] not in servo.model.baud_codes:
                    raise ValueError(f"servo {dxl_id}: {model} has no {baud} baud")
                servo.set("Baud Rate", CODE_BY_BAUD[baud])
            chain.append(servo)
        self.baud = baud
        self.clock: Clock = clock or MonotonicClock()
        self._servos = chain
        self._state = threading.Lock()
        self._last_step = self.clock.monotonic()
        #: Clock seconds per real second of the Bus Watchdog (see :func:`watchdog_expiry`).
        self._watchdog_scale = max(1.0, 1.0 / self.clock.real_seconds(1.0))
        for servo in chain:
            servo.booted = self._last_step
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

    # ---- servos ------------------------------------------------------------------------------

    def _servo(self, dxl_id: int) -> Servo:
        for servo in self._servos:
            if servo.id == dxl_id:
                return servo
        raise KeyError(f"no servo answers to id {dxl_id}")

    def _targets(self, params: Mapping[str, Any]) -> list[Servo]:
        device = params.get("device")
        if device is None:
            return list(self._servos)
        found = [s for s in self._servos if s.id == device]
        if not found:
            raise ValueError(f"no servo {device} in this chain")
        return found

    def _raise_hardware_error(self, servo: Servo, kind: str) -> None:
        self._step_locked()
        servo.set("Hardware Error Status", servo.hardware_error | _KIND_BITS[kind])
        servo.set("Torque Enable", 0)
        if kind == "overheat":
            servo.temperature = servo.value("Temperature Limit") + 5.0
            servo.injected_heat = True
            servo.set("Present Temperature", servo.value("Temperature Limit") + 5)
        elif kind == "voltage":
            servo.set("Present Input Voltage", servo.value("Max Voltage Limit") + 10)

    def _silent(self, dxl_id: int) -> bool:
        params = self.fault("silence")
        return params is not None and params.get("device", dxl_id) == dxl_id

    def _absent(self, servo: Servo, line: int | None) -> bool:
        """Whether ``servo`` misses a packet: silenced, at another baud rate or protocol."""
        if self._silent(servo.id) or servo.value("Protocol Type", 2) != 2:
            return True
        return self.baud is not None and BAUD_BY_CODE.get(servo.value("Baud Rate")) != line

    # ---- instructions --------------------------------------------------------------------------

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
        self, servo: Servo, number: int, params: bytes = b"", dxl_id: int | None = None
    ) -> bytes:
        alert = p.ALERT_BIT if servo.hardware_error else 0
        return p.status_packet(servo.id if dxl_id is None else dxl_id, number | alert, params)

    def _unicast(self, servo: Servo, packet: p.Packet, *, shadow: bool = False) -> bytes:
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

    def _addressed(self, packet: p.Packet, line: int | None) -> list[Servo]:
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

    def _fast_read(self, packet: p.Packet, live: list[Servo]) -> bytes | None:
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

    def _reply_read(self, servo: Servo, address: int, length: int) -> bytes:
        try:
            return self._status(servo, 0, self._read(servo, address, length))
        except _Reject as reject:
            return self._status(servo, reject.number)

    @staticmethod
    def _quiet(act: Any, servo: Servo, address: int, data: bytes) -> None:
        with contextlib.suppress(_Reject):  # sync, bulk and broadcast writes have no status
            act(servo, address, data)

    def _read(self, servo: Servo, address: int, length: int) -> bytes:
        if length < 1 or address + length > servo.layout.size:
            raise _Reject(_E.ACCESS)
        return bytes(servo.table[servo.resolve(a)] for a in range(address, address + length))

    def _write(
        self, servo: Servo, address: int, data: bytes, *, dry: bool = False, ram_only: bool = False
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

    def _check(self, servo: Servo, reg: ct.Register, value: int, now: Any) -> None:
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
            if abs(value) > now("PWM Limit", PWM_FULL):
                raise _Reject(_E.DATA_LIMIT)
        elif reg.low is not None and reg.high is not None and not reg.low <= value <= reg.high:
            raise _Reject(_E.DATA_RANGE)

    def _register(self, servo: Servo, address: int, data: bytes, *, ram_only: bool = False) -> None:
        """REG_WRITE: check now, hold until ACTION."""
        self._write(servo, address, data, dry=True, ram_only=ram_only)
        servo.registered = (address, bytes(data))
        servo.set("Registered Instruction", 1)

    def _action(self, servo: Servo) -> None:
        """ACTION: carry out the registered write."""
        held, servo.registered = servo.registered, None
        servo.set("Registered Instruction", 0)
        if held is not None:
            self._write(servo, *held)

    def _reboot(self, servo: Servo) -> None:
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
        servo.traj_pos, servo.traj_vel = None, 0.0
        servo.registered = None
        servo.booted = self.clock.monotonic()
        if still and params is not None:
            self._raise_hardware_error(servo, str(params.get("kind", "overheat")))
        elif servo.value("Startup Configuration") & 0x01:
            servo.set("Torque Enable", 1)  # Startup Torque On

    def _factory_reset(self, servo: Servo, option: int) -> None:
        """FACTORY_RESET: every register to its factory value (but the ID / the baud rate)."""
        self.stats["factory_resets"] += 1
        keep = {"ID", "Baud Rate"} if option == 0x02 else {"ID"} if option == 0x01 else set()
        servo.position -= servo.value("Homing Offset")  # back to 0 with the rest
        for reg in servo.model.registers:
            if reg.eeprom and reg.name not in keep:
                servo.put(reg, reg.default)
        self._reboot(servo)

    def _clear(self, servo: Servo, params: bytes) -> None:
        """CLEAR 0x01: Present Position back within one turn (only while it stands still)."""
        if len(params) != len(_CLEAR_MULTI_TURN):
            raise _Reject(_E.DATA_LENGTH)
        if params != _CLEAR_MULTI_TURN:
            raise _Reject(_E.DATA_RANGE)
        if servo.value("Moving") or abs(servo.velocity) > TICKS_S_PER_UNIT:
            raise _Reject(_E.RESULT_FAIL)
        turns = math.floor((servo.position - servo.value("Homing Offset")) / 4096)
        servo.position -= turns * 4096
        if servo.traj_pos is not None:
            servo.traj_pos -= turns * 4096
        for name in ("Present Position", "Position Trajectory"):
            servo.set(name, round(servo.position))
        if servo.value("Operating Mode") in POSITION_MODES:  # keep standing where it is
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
            expiry = watchdog_expiry(servo, self._watchdog_scale)
            if expiry is not None and expiry < now:
                move(servo, max(expiry - start, 0.0))  # up to the moment it expired
                expire_watchdog(servo)
                move(servo, now - max(expiry, start))
            else:
                move(servo, dt)
            servo.set("Realtime Tick", int((now - servo.booted) * 1000) % 32768)
            if self.realism.enabled:
                self._noisy(servo)

    def _noisy(self, servo: Servo) -> None:
        """Present Position, Velocity, Current and Temperature as a sensor reports them."""
        r = self.realism
        ticks = r.noise("joint_position", 0.0) / _RAD_PER_TICK
        servo.set("Present Position", round(servo.position + ticks))
        rad_s = servo.velocity * _RAD_PER_TICK
        servo.set("Present Velocity", round(r.noise("joint_velocity", rad_s) / _RAD_S_PER_UNIT))
        unit = servo.model.current_unit
        if unit is not None:
            amps = r.noise("current", servo.current * unit)
            servo.set("Present Current", min(max(round(amps / unit), -32768), 32767))
        servo.set("Present Temperature", round(r.noise("temperature", servo.temperature)))

    def _hear(self, servos: Iterable[Servo]) -> None:
        """An instruction packet for ``servos`` arrived now: their Bus Watchdogs restart."""
        now = self.clock.monotonic()
        for servo in servos:
            servo.heard = now
