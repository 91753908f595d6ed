"""One simulated DYNAMIXEL X-series servo: its control table and its motion model.

:class:`Servo` holds a servo's control table as the bytes a real one holds (every register of
its model, :class:`Layout` indexing them by name, by address and through the Indirect Addresses)
and the continuous state behind the registers (position, velocity, current, the Bus Watchdog's
clock, the winding's temperature). :func:`move` advances one servo's profile, torque and heat
and refreshes its Present registers; :func:`watchdog_expiry` and :func:`expire_watchdog` are its
Bus Watchdog. The behaviour is described in :mod:`~temoto.drivers.dynamixel.sim`; the
instructions that act on servos are in :mod:`~temoto.drivers.dynamixel.sim_instructions`. Pure
data and functions: no I/O, no threads, no lock (the chain holds its lock around every use).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Final

from temoto.drivers.dynamixel import control_table as ct
from temoto.drivers.dynamixel import protocol as p

__all__ = [
    "ACCEL_TICKS_PER_UNIT",
    "AMBIENT",
    "BAUD_BY_CODE",
    "CODE_BY_BAUD",
    "GENERIC_REGISTERS",
    "POSITION_MODES",
    "PWM_FULL",
    "THERMAL_CAPACITY",
    "THERMAL_RESISTANCE",
    "TICKS_S_PER_UNIT",
    "Layout",
    "Servo",
    "expire_watchdog",
    "move",
    "watchdog_expiry",
]

_SUBSTEP: Final = 0.001  # s, largest integration step

_MAX_INTEGRATED: Final = 1.0  # s of one step integrated; the rest goes on at the speed reached

#: Profile Acceleration's unit, 214.577 rev/min², in ticks/s² (X-series e-Manual, 108).
ACCEL_TICKS_PER_UNIT: Final = 214.577 / 3600.0 * 4096.0

_RAD: Final = 2.0 * math.pi / 4096.0  # rad per tick

#: rad/s: how stiffly the servo's position/velocity controller follows its profile (a
#: critically damped second-order loop: it settles in about 80 ms, as the old first-order
#: 50 ms model did).
_BANDWIDTH: Final = 60.0

#: Mechanics and heat of a servo without load, by its stall torque (assumed, not from the
#: e-Manual, which gives no inertia or thermal figures): output inertia (reflected rotor through
#: the ~1:200-1:350 gear) kg·m² per N·m of stall torque; viscous friction as 5 % of the stall
#: torque at the Velocity Limit; a thermal resistance and capacity that take a stalled servo
#: from 30 °C to an 80 °C limit in about half a minute and hold a lightly loaded one within a
#: few degrees of ambient.
_INERTIA_PER_NM: Final = 2.5e-4
_FRICTION_SHARE: Final = 0.05
THERMAL_RESISTANCE: Final = 10.0  # K/W
THERMAL_CAPACITY: Final = 15.0  # J/K
AMBIENT: Final = 30.0  # °C: Present Temperature's initial value in the simulator

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
    traj_pos: float | None = None  # the profile's position (ticks); None: start where it is
    traj_vel: float = 0.0  # the profile's velocity, ticks/s
    torque_out: float = 0.0  # the motor's torque at the output, N·m
    temperature: float = AMBIENT  # the winding, °C
    injected_heat: bool = False  # hot from an injected overheat fault (cools when cleared)
    load_inertia: float = 0.0  # what the horn carries, kg·m²
    load_torque: float = 0.0  # a constant torque against it (gravity of an arm, ...), N·m

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


def _torque_limit(servo: Servo, mode: int) -> float:
    """The most torque the servo may give now, N·m (its Current Limit's; PWM Limit's share).

    Goal Current as a limit in current-based position mode is not modelled: the stored
    e-Manual pages do not give its initial value, and with 0 such a servo would not move.
    """
    model = servo.model
    if model.current_unit is None:  # no current sensor: the PWM Limit's share of stall
        return model.stall_torque * servo.value("PWM Limit", PWM_FULL) / PWM_FULL
    amps = servo.current_limit * model.current_unit
    return min(amps * model.torque_constant, model.stall_torque)


def _profile(servo: Servo, target: float, vmax: float, amax: float, h: float) -> None:
    """One step of the velocity-based trapezoidal profile towards ``target`` (ticks)."""
    tp = servo.traj_pos if servo.traj_pos is not None else servo.position
    d = target - tp
    if amax == math.inf:
        tv = min(max(d / h, -vmax), vmax)
    else:
        stop = math.sqrt(2.0 * amax * abs(d))  # the speed it can still stop from in time
        want = math.copysign(min(vmax, stop), d) if d else 0.0
        tv = servo.traj_vel + min(max(want - servo.traj_vel, -amax * h), amax * h)
    new = tp + tv * h
    if (target - new) * d <= 0 and abs(target - new) < max(abs(tv) * h, 0.5):  # arrived
        new, tv = target, 0.0
    servo.traj_pos, servo.traj_vel = new, tv


def _velocity_profile(servo: Servo, goal: float, amax: float, h: float) -> None:
    """One step of the velocity profile towards ``goal`` (ticks/s); the position follows."""
    tv = servo.traj_vel
    step = amax * h
    tv = goal if amax == math.inf else tv + min(max(goal - tv, -step), step)
    tp = servo.traj_pos if servo.traj_pos is not None else servo.position
    servo.traj_vel, servo.traj_pos = tv, tp + tv * h


def move(servo: Servo, dt: float) -> None:
    """Advance one servo by ``dt`` seconds and refresh its Present registers.

    The servo's controller follows a profile (the e-Manual's velocity-based profile: Profile
    Velocity and Profile Acceleration, 0 = unlimited; the Velocity Limit bounds the speed) with
    the torque its Current Limit allows (and, in current-based position mode, its Goal
    Current); the torque accelerates the servo's and its load's inertia against friction and a
    load torque. The winding heats with the current's I²R and cools to ambient; past the
    Temperature Limit the Overheating bit of Hardware Error Status is set and, as Shutdown's
    bit 2 (set by default) asks, torque goes off.
    """
    mode = servo.value("Operating Mode")
    model = servo.model
    limit_units = max(servo.value("Velocity Limit"), 1)
    vlimit = limit_units * TICKS_S_PER_UNIT
    inertia = model.stall_torque * _INERTIA_PER_NM + servo.load_inertia
    friction = _FRICTION_SHARE * model.stall_torque / (vlimit * _RAD)  # N·m per rad/s
    kt = model.torque_constant
    stall_amps = model.stall_torque / kt
    resistance = model.nominal_voltage / stall_amps  # Ω
    target = float(servo.value("Goal Position"))
    driven = servo.torque and not servo.halted
    span = min(dt, _MAX_INTEGRATED)
    steps = max(1, math.ceil(span / _SUBSTEP)) if dt > 0 else 0
    h = span / steps if steps else 0.0
    vmax, amax = vlimit, math.inf
    if driven:
        profile = servo.value("Profile Velocity")
        if mode in POSITION_MODES and 0 < profile < limit_units:
            vmax = profile * TICKS_S_PER_UNIT
        accel = servo.value("Profile Acceleration")
        if accel > 0:
            amax = accel * ACCEL_TICKS_PER_UNIT
        if mode == ct.OperatingMode.POSITION:
            low = servo.value("Min Position Limit")
            target = min(max(target, low), servo.value("Max Position Limit", 4095))
        top = _torque_limit(servo, mode)
        goal_vel = min(max(servo.value("Goal Velocity") * TICKS_S_PER_UNIT, -vlimit), vlimit)
        pwm_share = servo.value("Goal PWM") / PWM_FULL
        goal_amps = servo.value("Goal Current") * (model.current_unit or 0.0)
    else:  # torque off: the gear's friction holds it (a servo is not backdriven)
        servo.traj_pos, servo.traj_vel = None, 0.0
        target = servo.position
        servo.velocity = servo.torque_out = 0.0
        steps = 0
    positional = mode in POSITION_MODES
    velocity_mode = mode == ct.OperatingMode.VELOCITY
    vtop = vlimit * _RAD
    kp = inertia * _BANDWIDTH**2  # N·m per rad
    kd = 2.0 * inertia * _BANDWIDTH  # N·m per rad/s
    heat = 0.0
    done = 0.0
    for _ in range(steps):
        vel = servo.velocity * _RAD
        if positional and servo.traj_pos == target and servo.traj_vel == 0.0:
            settled = abs(target - servo.position) < 0.01 and abs(servo.velocity) < 0.01
            if settled and not servo.load_torque:  # at rest on its goal: nothing changes
                servo.position, servo.velocity, servo.torque_out = target, 0.0, 0.0
                break
        if positional:
            _profile(servo, target, vmax, amax, h)
        elif velocity_mode:
            _velocity_profile(servo, goal_vel, amax, h)
        if positional or velocity_mode:
            tp = servo.traj_pos if servo.traj_pos is not None else servo.position
            error = (tp - servo.position) * _RAD
            if velocity_mode:  # no wind-up: the spring stays bounded
                error = min(max(error, -top / kp), top / kp)
                servo.traj_pos = servo.position + error / _RAD
            torque = kp * error + kd * (servo.traj_vel * _RAD - vel)
            torque = min(max(torque, -top), top)
        elif mode == ct.OperatingMode.PWM:  # a voltage: the back-EMF takes its share
            torque = model.stall_torque * (pwm_share - vel / vtop)
            torque = min(max(torque, -top), top)
        else:  # current
            torque = min(max(goal_amps * kt, -top), top)
        drive = torque - friction * vel - servo.load_torque
        vel += h * drive / inertia
        vel = min(max(vel, -vtop), vtop)
        servo.velocity = vel / _RAD
        servo.position += servo.velocity * h
        servo.torque_out = torque
        heat += resistance * min(abs(torque) / kt, stall_amps) ** 2 * h
        done += h
    rest = dt - done if steps else 0.0
    if rest > 0 and driven:
        if mode in POSITION_MODES:  # on at the speed reached, up to the goal
            gap = target - servo.position
            servo.position += math.copysign(min(abs(gap), abs(servo.velocity) * rest), gap)
            if servo.position == target:
                servo.velocity = 0.0
            servo.traj_pos, servo.traj_vel = servo.position, servo.velocity
        else:
            servo.position += servo.velocity * rest
            if servo.traj_pos is not None:
                servo.traj_pos += servo.traj_vel * rest
    _heat(servo, heat, dt, resistance * min(abs(servo.torque_out) / kt, stall_amps) ** 2)
    if not driven:
        servo.torque_out = 0.0
        target = servo.position
    amps = servo.torque_out / kt
    if mode == ct.OperatingMode.CURRENT and driven:
        servo.current = float(servo.value("Goal Current"))
    elif model.current_unit is not None:
        servo.current = amps / model.current_unit
    else:
        servo.current = servo.torque_out / model.stall_torque * _LOAD_FULL
    servo.position = min(max(servo.position, -(2.0**31) + 1), 2.0**31 - 1)
    units = round(servo.velocity / TICKS_S_PER_UNIT)
    moving = abs(units) > servo.value("Moving Threshold", 10)
    in_position = servo.torque and mode in POSITION_MODES and abs(target - servo.position) < 1
    pwm_limit = servo.value("PWM Limit", PWM_FULL)
    if mode == ct.OperatingMode.PWM and driven:
        pwm = servo.value("Goal PWM")
    else:
        pwm = round(servo.torque_out / model.stall_torque * pwm_limit)
    tp = servo.traj_pos if servo.traj_pos is not None and driven else servo.position
    ongoing = driven and mode in POSITION_MODES and abs(target - tp) >= 1
    servo.set("Present Position", round(servo.position))
    servo.set("Present Velocity", units)
    servo.set("Present Current", min(max(round(servo.current), -32768), 32767))
    servo.set("Present Load", min(max(round(servo.current), -_LOAD_FULL), _LOAD_FULL))
    servo.set("Present PWM", min(max(pwm, -pwm_limit), pwm_limit))
    servo.set("Velocity Trajectory", round(servo.traj_vel / TICKS_S_PER_UNIT) if driven else 0)
    servo.set("Position Trajectory", round(tp))
    servo.set("Present Temperature", round(servo.temperature))
    servo.set("Moving", 1 if moving else 0)
    servo.set("Moving Status", (1 if in_position else 0) | (2 if moving or ongoing else 0))


def _heat(servo: Servo, joules: float, dt: float, watts: float) -> None:
    """Heat the winding by ``joules`` over ``dt`` s (then ``watts`` on), cooling to ambient."""
    if dt <= 0:
        return
    span = min(dt, _MAX_INTEGRATED)
    t = servo.temperature
    t += joules / THERMAL_CAPACITY - (t - AMBIENT) / (THERMAL_RESISTANCE * THERMAL_CAPACITY) * span
    rest = dt - span
    if rest > 0:  # exact for a constant power
        settled = AMBIENT + watts * THERMAL_RESISTANCE
        t = settled + (t - settled) * math.exp(-rest / (THERMAL_RESISTANCE * THERMAL_CAPACITY))
    servo.temperature = t
    # e-Manual, Shutdown (63): an error whose bit is set there is detected, flagged in Hardware
    # Error Status and clears Torque Enable (the motor output becomes 0 %); bit 2 (set in the
    # initial value 52) is Overheating, past the Temperature Limit (31)
    watched = servo.value("Shutdown") & p.HardwareError.OVERHEATING
    if watched and t > servo.value("Temperature Limit", 80):
        servo.set("Hardware Error Status", servo.hardware_error | p.HardwareError.OVERHEATING)
        servo.set("Torque Enable", 0)


def watchdog_expiry(servo: Servo, scale: float = 1.0) -> float | None:
    """When the servo's armed Bus Watchdog expires (None: off, expired, or torque off).

    The watchdog is the servo's guard against a silent host, timed by the servo's own
    oscillator: real seconds. On a clock that runs faster than real time (a
    :class:`~temoto.clock.ScaledClock` above 1) the motion is sped up but the host's scheduling
    is not, so the window stays that many real seconds (``scale`` = clock seconds per real
    second); on real and virtual clocks it is the clock's seconds.

    Args:
        servo: The servo.
        scale: Clock seconds per real second of the window (1: the clock's seconds).

    Returns:
        The clock time of the expiry, or None.
    """
    units = servo.value("Bus Watchdog")
    if units <= 0 or not servo.torque:
        return None
    return servo.heard + units * ct.BUS_WATCHDOG_UNIT * scale


def expire_watchdog(servo: Servo) -> None:
    """The Bus Watchdog expired: the servo stops where it is and reads -1 until cleared."""
    servo.set("Bus Watchdog", ct.BUS_WATCHDOG_ERROR)
    servo.halted = True
    servo.velocity = 0.0
    servo.current = 0.0
