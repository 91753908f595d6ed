"""One simulated DYNAMIXEL X-series servo: its control table and its motion model.

:class:`Servo` holds a servo's control table as the bytes a real one holds (every register of
its model, :class:`Layout` indexing them by name, by address and through the Indirect
Addresses) and the continuous state behind the registers (position, velocity, current, the
Bus Watchdog's clock). :func:`move` advances one servo's first-order model and refreshes its
Present registers; :func:`watchdog_expiry` and :func:`expire_watchdog` are its Bus Watchdog.
The behaviour is described in :mod:`~temoto.drivers.dynamixel.sim`; the instructions that act
on servos are in :mod:`~temoto.drivers.dynamixel.sim_instructions`. Pure data and functions:
no I/O, no threads, no lock (the chain holds its lock around every use).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Final

from temoto.drivers.dynamixel import control_table as ct
from temoto.drivers.dynamixel import protocol as p

__all__ = [
    "BAUD_BY_CODE",
    "CODE_BY_BAUD",
    "GENERIC_REGISTERS",
    "POSITION_MODES",
    "PWM_FULL",
    "TICKS_S_PER_UNIT",
    "Layout",
    "Servo",
    "expire_watchdog",
    "move",
    "watchdog_expiry",
]

_TAU: Final = 0.05  # s, time constant of position and velocity tracking

_SUBSTEP: Final = 0.001  # s, largest integration step

_SNAP_AFTER: Final = 1.0  # s, a longer step settles at once

TICKS_S_PER_UNIT: Final = 0.229 * 4096.0 / 60.0  # velocity unit in ticks per second

_LOAD_FULL: Final = 1000  # Present Load of a model without a current sensor: 0.1 % units

PWM_FULL: Final = 885  # the X series' largest PWM (Goal PWM and PWM Limit units)

#: Baud Rate register (8) values → bits per second (X series).
BAUD_BY_CODE: Final[Mapping[int, int]] = {
    0: 9600,
    1: 57600,
    2: 115200,
    3: 1_000_000,
    4: 2_000_000,
    5: 3_000_000,
    6: 4_000_000,
    7: 4_500_000,
}

CODE_BY_BAUD: Final[Mapping[int, int]] = {baud: code for code, baud in BAUD_BY_CODE.items()}

#: Every register of the X series by address (for an address a model lacks).
GENERIC_REGISTERS: Final = {r.address: r for r in ct.REGISTERS}
POSITION_MODES: Final = frozenset(
    {
        ct.OperatingMode.POSITION,
        ct.OperatingMode.EXTENDED_POSITION,
        ct.OperatingMode.CURRENT_BASED_POSITION,
    }
)


class Layout:
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


_LAYOUTS: dict[str, Layout] = {}


def _layout(model: ct.Model) -> Layout:
    found = _LAYOUTS.get(model.name)
    if found is None:
        found = _LAYOUTS[model.name] = Layout(model)
    return found


@dataclass
class Servo:
    """One simulated servo: its control table and the continuous state behind it."""

    start_id: int
    model: ct.Model
    layout: Layout = field(init=False)
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
        """The model's register of that name (None if the model has none)."""
        return self.layout.by_name.get(name)

    def get(self, reg: ct.Register) -> int:
        """A register's value."""
        at = reg.address
        return int.from_bytes(self.table[at : at + reg.size], "little", signed=reg.signed)

    def put(self, reg: ct.Register, value: int) -> None:
        """Store a register's value (unchecked: the instructions check writes)."""
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
        """Whether Torque Enable is 1."""
        return self.value("Torque Enable") == 1

    @property
    def hardware_error(self) -> int:
        """The Hardware Error Status register."""
        return self.value("Hardware Error Status")

    @property
    def current_limit(self) -> int:
        """The Current Limit, or 100.0 % for a model that reports load."""
        return self.value("Current Limit", _LOAD_FULL)


def move(servo: Servo, dt: float) -> None:
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
        vmax = limit_units * TICKS_S_PER_UNIT
        if mode in POSITION_MODES:
            profile = servo.value("Profile Velocity")
            if 0 < profile < limit_units:
                vmax = profile * TICKS_S_PER_UNIT
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
                goal_v = servo.value("Goal Velocity") * TICKS_S_PER_UNIT
            elif mode == ct.OperatingMode.PWM:  # crudely: the goal's share of full PWM
                goal_v = servo.value("Goal PWM") / PWM_FULL * vmax
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
    units = round(servo.velocity / TICKS_S_PER_UNIT)
    moving = abs(units) > servo.value("Moving Threshold", 10)
    in_position = servo.torque and mode in POSITION_MODES and abs(target - servo.position) < 1
    pwm_limit = servo.value("PWM Limit", PWM_FULL)
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


def watchdog_expiry(servo: Servo) -> float | None:
    """When the servo's armed Bus Watchdog expires (None: off, expired, or torque off)."""
    units = servo.value("Bus Watchdog")
    if units <= 0 or not servo.torque:
        return None
    return servo.heard + units * ct.BUS_WATCHDOG_UNIT


def expire_watchdog(servo: Servo) -> None:
    """The Bus Watchdog expired: the servo stops where it is and reads -1 until cleared."""
    servo.set("Bus Watchdog", ct.BUS_WATCHDOG_ERROR)
    servo.halted = True
    servo.velocity = 0.0
    servo.current = 0.0
