"""The DYNAMIXEL X-series control table and models, as data (ROBOTIS e-Manual).

Addresses, sizes and units of the registers the driver and the simulator use, the operating
modes, and per model the number a PING answers with and the numbers that turn register units
into SI units.

Units (X-series): position 4096 ticks per revolution (2048 is the middle of the single-turn
range; the driver takes it as 0 rad before the profile's ``offset``); velocity 0.229 rev/min per
unit; current per unit depends on the model (2.69 mA for XM430, XH430-W, XD, XW and the X540s,
1.34 mA for XH430-V, 1 mA for XL330; XL430, 2XL430 and XC430 have no current sensor and report
*load* in 0.1 % of their maximum torque at the same address); input voltage 0.1 V per unit;
temperature 1 °C per unit.

Each :class:`Model` carries its whole control table (:attr:`Model.registers`): every register
of its e-Manual page with address, size, access, initial value and range. :data:`REGISTERS` is
the XM430-W350's, the layout the family shares; the module-level register constants
(:data:`GOAL_POSITION`, ...) are from it and hold for every model that has the register.

Effort: torque = current x torque constant, with the torque constant taken as stall torque /
stall current at the nominal voltage from the e-Manual's performance table (an approximation:
the real curve is not linear near stall; a profile can override ``torque_constant`` per servo).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Final

__all__ = [
    "BUS_WATCHDOG",
    "BUS_WATCHDOG_ERROR",
    "BUS_WATCHDOG_FIRMWARE",
    "BUS_WATCHDOG_MAX",
    "BUS_WATCHDOG_UNIT",
    "CURRENT",
    "FAST_READ",
    "FIRMWARE",
    "FIRMWARE_VERSION",
    "GOAL_CURRENT",
    "GOAL_POSITION",
    "GOAL_PWM",
    "GOAL_REGISTERS",
    "GOAL_VELOCITY",
    "HARDWARE_ERROR_STATUS",
    "MAX_POSITION_LIMIT",
    "MIN_POSITION_LIMIT",
    "MODELS",
    "MODELS_BY_NUMBER",
    "MODEL_NUMBER",
    "OPERATING_MODE",
    "POSITION_CENTER",
    "PRESENT_CURRENT",
    "PRESENT_INPUT_VOLTAGE",
    "PRESENT_POSITION",
    "PRESENT_TEMPERATURE",
    "PRESENT_VELOCITY",
    "PROFILE_VELOCITY",
    "RAD_PER_TICK",
    "RAD_S_PER_UNIT",
    "REGISTERS",
    "RETURN_DELAY_MAX",
    "RETURN_DELAY_TIME",
    "RETURN_DELAY_UNIT",
    "STATUS_READ",
    "TORQUE_ENABLE",
    "VOLT_PER_UNIT",
    "Model",
    "OperatingMode",
    "Register",
    "table_of",
]


@dataclass(frozen=True, slots=True)
class Register:
    """One control-table entry.

    Attributes:
        name: The e-Manual's name.
        address: Its address.
        size: Bytes (1, 2 or 4).
        signed: Two's complement.
        writable: Read/write (else read-only).
        eeprom: In the EEPROM area (writable only while torque is off).
        default: The factory value (the simulator's start value).
        low: The smallest value a write may set (the e-Manual's Range column), or None where
            the range is another register (goal values) or not stated.
        high: The largest value a write may set, or None likewise.
    """

    name: str
    address: int
    size: int
    signed: bool = False
    writable: bool = True
    eeprom: bool = False
    default: int = 0
    low: int | None = None
    high: int | None = None

    @property
    def torque_locked(self) -> bool:
        """Writable only while Torque Enable is 0: the EEPROM area and the Indirect Addresses."""
        return self.eeprom or self.name.startswith("Indirect Address")


def _ee(
    name: str,
    address: int,
    size: int,
    default: int = 0,
    low: int | None = None,
    high: int | None = None,
    *,
    writable: bool = True,
    signed: bool = False,
) -> Register:
    return Register(name, address, size, signed, writable, True, default, low, high)


def _ram(
    name: str,
    address: int,
    size: int,
    default: int = 0,
    low: int | None = None,
    high: int | None = None,
    *,
    signed: bool = False,
    rw: bool = True,
) -> Register:
    return Register(name, address, size, signed, rw, False, default, low, high)


#: The firmware version the simulated servos report (v45 on has Startup Configuration and
#: Backup Ready; v38 on has the Bus Watchdog).
FIRMWARE: Final = 48
_GAIN_MAX: Final = 16383
_HOMING_MAX: Final = 1_044_479


def _indirect(count: int) -> list[Register]:
    """Indirect Address 1..count and Indirect Data 1..count (e-Manual, X series).

    Indirect Address *n* (2 bytes) holds the address Indirect Data *n* (1 byte) stands for;
    each starts out pointing at its own Indirect Data. Entries 1..28 (1..20 on XL330) sit at
    168.., their data right after them; entries 29..56 at 578.., data at 634.. .
    """
    first = min(count, 28)
    data_at = [168 + 2 * first + k for k in range(first)]
    addr_at = [168 + 2 * k for k in range(first)]
    if count > 28:
        addr_at += [578 + 2 * k for k in range(count - 28)]
        data_at += [634 + k for k in range(count - 28)]
    last = data_at[-1]
    regs = [
        _ram(f"Indirect Address {n + 1}", addr_at[n], 2, data_at[n], 64, last) for n in range(count)
    ]
    regs += [_ram(f"Indirect Data {n + 1}", data_at[n], 1, 0, 0, 255) for n in range(count)]
    return regs


def _table(
    number: int,
    *,
    velocity_limit: int,
    current_limit: int | None = None,
    velocity_max: int = 1023,
    voltage: tuple[int, int, int, int] = (160, 95, 95, 160),
    volts_now: int = 120,
    temperature: int = 80,
    gains: tuple[int, int, int, int, int] = (1920, 100, 0, 0, 800),
    baud_max: int = 7,
    protocol: tuple[int, int] = (1, 2),
    shutdown: int = 52,
    indirect: int = 56,
    led: bool = True,
    external_ports: bool = False,
    pwm_slope: bool = False,
) -> tuple[Register, ...]:
    """One model's control table, from the rows its e-Manual page lists.

    Args:
        number: Model Number.
        velocity_limit: Velocity Limit's initial value.
        current_limit: Current Limit's initial value (also its largest), or None: the model
            has no current sensor (Present Load at 126, no Current Limit, no Goal Current).
        velocity_max: Velocity Limit's largest value.
        voltage: Max Voltage Limit and Min Voltage Limit initial values, then their range.
        volts_now: The Present Input Voltage the simulator reports (0.1 V).
        temperature: Temperature Limit's initial value.
        gains: Velocity I, Velocity P, Position D, Position I, Position P initial values.
        baud_max: Baud Rate's largest code.
        protocol: Protocol Type's range.
        shutdown: Shutdown's initial value.
        indirect: Indirect Address/Data pairs.
        led: The model has an LED (65).
        external_ports: External Port Mode 1..3 (56..58) and Data 1..3 (152..156).
        pwm_slope: PWM Slope (62).

    Returns:
        The registers in address order.
    """
    vmax, vmin, vlow, vhigh = voltage
    vi, vp, pd, pi, pp = gains
    regs = [
        _ee("Model Number", 0, 2, number, writable=False),
        _ee("Model Information", 2, 4, 0, writable=False),
        _ee("Firmware Version", 6, 1, FIRMWARE, writable=False),
        _ee("ID", 7, 1, 1, 0, 252),
        _ee("Baud Rate", 8, 1, 1, 0, baud_max),
        _ee("Return Delay Time", 9, 1, 250, 0, 254),
        # Drive Mode bits: 0 reverse, 1 dual joint (X540 M/H/D only), 2 time-based profile,
        # 3 torque on by goal update; ``high`` is the mask of the bits the model has.
        _ee("Drive Mode", 10, 1, 0, 0, 0x0F if external_ports else 0x0D),
        _ee("Operating Mode", 11, 1, 3, 0, 16),
        # 0..252 sets it; 253..255 switch it off (255 is the factory value).
        _ee("Secondary ID", 12, 1, 255, 0, 255),
        _ee("Protocol Type", 13, 1, 2, *protocol),
        _ee("Homing Offset", 20, 4, 0, -_HOMING_MAX, _HOMING_MAX, signed=True),
        _ee("Moving Threshold", 24, 4, 10, 0, 1023),
        _ee("Temperature Limit", 31, 1, temperature, 0, 100),
        _ee("Max Voltage Limit", 32, 2, vmax, vlow, vhigh),
        _ee("Min Voltage Limit", 34, 2, vmin, vlow, vhigh),
        _ee("PWM Limit", 36, 2, 885, 0, 885),
    ]
    if current_limit is not None:
        regs.append(_ee("Current Limit", 38, 2, current_limit, 0, current_limit))
    regs += [
        _ee("Velocity Limit", 44, 4, velocity_limit, 0, velocity_max),
        _ee("Max Position Limit", 48, 4, 4095, 0, 4095),
        _ee("Min Position Limit", 52, 4, 0, 0, 4095),
    ]
    if external_ports:
        regs += [_ee(f"External Port Mode {n}", 55 + n, 1, 3, 0, 3) for n in (1, 2, 3)]
    regs.append(_ee("Startup Configuration", 60, 1, 0, 0, 3))
    if pwm_slope:
        regs.append(_ee("PWM Slope", 62, 1, 140, 1, 255))
    regs.append(_ee("Shutdown", 63, 1, shutdown, 0, 255))
    regs.append(_ram("Torque Enable", 64, 1, 0, 0, 1))
    if led:
        regs.append(_ram("LED", 65, 1, 0, 0, 1))
    regs += [
        _ram("Status Return Level", 68, 1, 2, 0, 2),
        _ram("Registered Instruction", 69, 1, rw=False),
        _ram("Hardware Error Status", 70, 1, rw=False),
        _ram("Velocity I Gain", 76, 2, vi, 0, _GAIN_MAX),
        _ram("Velocity P Gain", 78, 2, vp, 0, _GAIN_MAX),
        _ram("Position D Gain", 80, 2, pd, 0, _GAIN_MAX),
        _ram("Position I Gain", 82, 2, pi, 0, _GAIN_MAX),
        _ram("Position P Gain", 84, 2, pp, 0, _GAIN_MAX),
        _ram("Feedforward 2nd Gain", 88, 2, 0, 0, _GAIN_MAX),
        _ram("Feedforward 1st Gain", 90, 2, 0, 0, _GAIN_MAX),
        _ram("Bus Watchdog", 98, 1, signed=True),
        _ram("Goal PWM", 100, 2, signed=True),
    ]
    if current_limit is not None:
        regs.append(_ram("Goal Current", 102, 2, signed=True))
    regs += [
        _ram("Goal Velocity", 104, 4, signed=True),
        _ram("Profile Acceleration", 108, 4, 0, 0, 32767),
        _ram("Profile Velocity", 112, 4, 0, 0, 32767),
        _ram("Goal Position", 116, 4, 2048, signed=True),
        _ram("Realtime Tick", 120, 2, rw=False),
        _ram("Moving", 122, 1, rw=False),
        _ram("Moving Status", 123, 1, rw=False),
        _ram("Present PWM", 124, 2, signed=True, rw=False),
        _ram(
            "Present Current" if current_limit is not None else "Present Load",
            126,
            2,
            signed=True,
            rw=False,
        ),
        _ram("Present Velocity", 128, 4, signed=True, rw=False),
        _ram("Present Position", 132, 4, 2048, signed=True, rw=False),
        _ram("Velocity Trajectory", 136, 4, signed=True, rw=False),
        _ram("Position Trajectory", 140, 4, 2048, signed=True, rw=False),
        _ram("Present Input Voltage", 144, 2, volts_now, rw=False),
        _ram("Present Temperature", 146, 1, 30, rw=False),
        _ram("Backup Ready", 147, 1, rw=False),
    ]
    if external_ports:
        regs += [_ram(f"External Port Data {n}", 150 + 2 * n, 2) for n in (1, 2, 3)]
    regs += _indirect(indirect)
    return tuple(sorted(regs, key=lambda r: r.address))


#: The XM430-W350's control table (the layout the X series shares; :attr:`Model.registers`
#: has each model's own, with its rows and initial values).
REGISTERS: Final[tuple[Register, ...]] = _table(1020, velocity_limit=200, current_limit=1193)

_BY_NAME: Final = {r.name: r for r in REGISTERS}
MODEL_NUMBER: Final = _BY_NAME["Model Number"]
OPERATING_MODE: Final = _BY_NAME["Operating Mode"]
TORQUE_ENABLE: Final = _BY_NAME["Torque Enable"]
FIRMWARE_VERSION: Final = _BY_NAME["Firmware Version"]
RETURN_DELAY_TIME: Final = _BY_NAME["Return Delay Time"]
MAX_POSITION_LIMIT: Final = _BY_NAME["Max Position Limit"]
MIN_POSITION_LIMIT: Final = _BY_NAME["Min Position Limit"]
BUS_WATCHDOG: Final = _BY_NAME["Bus Watchdog"]
GOAL_PWM: Final = _BY_NAME["Goal PWM"]
HARDWARE_ERROR_STATUS: Final = _BY_NAME["Hardware Error Status"]
GOAL_CURRENT: Final = _BY_NAME["Goal Current"]
GOAL_VELOCITY: Final = _BY_NAME["Goal Velocity"]
PROFILE_VELOCITY: Final = _BY_NAME["Profile Velocity"]
GOAL_POSITION: Final = _BY_NAME["Goal Position"]
PRESENT_CURRENT: Final = _BY_NAME["Present Current"]
PRESENT_VELOCITY: Final = _BY_NAME["Present Velocity"]
PRESENT_POSITION: Final = _BY_NAME["Present Position"]
PRESENT_INPUT_VOLTAGE: Final = _BY_NAME["Present Input Voltage"]
PRESENT_TEMPERATURE: Final = _BY_NAME["Present Temperature"]
CURRENT: Final = PRESENT_CURRENT  # alias: "Present Load" on XL430, same address and size

#: The block the driver reads every poll: present current, velocity and position (126..135).
FAST_READ: Final = (PRESENT_CURRENT.address, 10)
#: The block read every few polls: present input voltage and temperature (144..146).
STATUS_READ: Final = (PRESENT_INPUT_VOLTAGE.address, 3)
#: The writable upper end of the EEPROM area.
EEPROM_END: Final = TORQUE_ENABLE.address

#: The goal registers (Goal PWM, Current, Velocity, Position): read-only while a Bus Watchdog
#: error stands (a write is answered with a Data Range error).
GOAL_REGISTERS: Final = (GOAL_PWM, GOAL_CURRENT, GOAL_VELOCITY, GOAL_POSITION)

#: Bus Watchdog (98), RAM, 1 byte (e-Manual, X series, firmware v38 and later): 0 switches it off
#: and clears a Bus Watchdog error; 1..127 arm it in units of 20 ms; it reads -1 after it expired.
#: While Torque Enable is 1, a servo that receives no instruction packet for longer than the
#: set time stops and refuses goal values until 0 is written here.
BUS_WATCHDOG_UNIT: Final = 0.020
BUS_WATCHDOG_MAX: Final = 127
BUS_WATCHDOG_ERROR: Final = -1
BUS_WATCHDOG_FIRMWARE: Final = 38
#: Return Delay Time (9), EEPROM: the delay before a status packet, 2 µs per unit, 0..254
#: (factory 250 = 500 µs).
RETURN_DELAY_UNIT: Final = 2e-6
RETURN_DELAY_MAX: Final = 254

POSITION_CENTER: Final = 2048
RAD_PER_TICK: Final = 2.0 * math.pi / 4096.0
RAD_S_PER_UNIT: Final = 0.229 * 2.0 * math.pi / 60.0
VOLT_PER_UNIT: Final = 0.1


class OperatingMode(enum.IntEnum):
    """Values of the Operating Mode register (11)."""

    CURRENT = 0
    VELOCITY = 1
    POSITION = 3
    EXTENDED_POSITION = 4
    CURRENT_BASED_POSITION = 5
    PWM = 16


@dataclass(frozen=True, slots=True)
class Model:
    """One servo model.

    Attributes:
        name: ``XM430-W350`` etc.
        number: What its Model Number register (and PING) says.
        current_unit: Amperes per Present/Goal Current unit, or None (no current sensor: the
            model reports *load* in 0.1 % at 126 and has no current-based modes).
        torque_constant: N·m per ampere (stall torque / stall current; approximate).
        stall_torque: N·m at the nominal voltage (for a load-reporting model: 100 % = this).
        modes: Operating modes it supports.
        nominal_voltage: Volts (the simulator's Present Input Voltage).
        registers: Its control table, in address order (:func:`table_of`).
    """

    name: str
    number: int
    current_unit: float | None
    torque_constant: float
    stall_torque: float
    modes: frozenset[OperatingMode]
    nominal_voltage: float = 12.0
    registers: tuple[Register, ...] = REGISTERS

    def register(self, name: str) -> Register | None:
        """The register called ``name`` in this model's table, or None if it has none."""
        return next((r for r in self.registers if r.name == name), None)

    @property
    def baud_codes(self) -> range:
        """The Baud Rate register values this model accepts."""
        reg = self.register("Baud Rate")
        high = reg.high if reg is not None and reg.high is not None else 7
        return range(high + 1)

    @property
    def table_end(self) -> int:
        """One past the last address of the table (a read or write beyond is an Access Error)."""
        last = self.registers[-1]
        return last.address + last.size


_ALL = frozenset(OperatingMode)
_NO_CURRENT = frozenset(
    {
        OperatingMode.VELOCITY,
        OperatingMode.POSITION,
        OperatingMode.EXTENDED_POSITION,
        OperatingMode.PWM,
    }
)
_MA_269: Final = 0.00269  # A per unit: XM/XH(-W)/XD/XW and X540 current registers
_MA_134: Final = 0.00134  # XH430-V


def _m(
    name: str,
    number: int,
    current_unit: float | None,
    stall: tuple[float, float],
    volts: float = 12.0,
    **table: Any,
) -> Model:
    """A model: ``stall`` is (stall torque N·m, stall current A) at ``volts``."""
    torque, amps = stall
    regs = _table(number, volts_now=round(volts * 10), **table)
    modes = _ALL if current_unit is not None else _NO_CURRENT
    return Model(name, number, current_unit, torque / amps, torque, modes, volts, regs)


_XL430: Final[dict[str, Any]] = {
    "voltage": (140, 60, 60, 140),
    "temperature": 72,
}
_XC430: Final[dict[str, Any]] = {"voltage": (160, 60, 60, 160)}
_XL330: Final[dict[str, Any]] = {
    "velocity_max": 2047,
    "voltage": (70, 35, 31, 70),
    "temperature": 70,
    "baud_max": 6,
    "protocol": (2, 22),
    "shutdown": 53,
    "indirect": 20,
    "pwm_slope": True,
}
_V24: Final[dict[str, Any]] = {"voltage": (300, 110, 110, 300)}
_XH430: Final[dict[str, Any]] = {"gains": (1920, 100, 0, 0, 900)}
_X540: Final[dict[str, Any]] = {"external_ports": True}
_XW: Final[dict[str, Any]] = {"led": False}

#: Models by name. Numbers, initial values and ranges from each model's ROBOTIS e-Manual page
#: (control table and specifications); stall torque/current at the recommended voltage. The
#: XD servos are the XH's long-life versions with identical tables (the e-Manual says so); their
#: model numbers are the XH's plus one, as ROBOTIS's DYNAMIXEL Wizard and SDKs list them (the
#: XD430-T210 page prints 1,010, the XH430-W210's number, which a chain could not tell apart).
#: The XW430 pages print Protocol Type 1 as the initial value; the servo ships speaking Protocol
#: 2.0 (its Model Number is read over 2.0), so the simulator starts at 2. Drive Mode takes the
#: bits the e-Manual's Drive Mode section gives each group (0, 2, 3; and 1, dual joint, on the
#: X540 M/H/D), where some pages' Range column (0 ~ 1, 0 ~ 5) predates bits 2 and 3. Stall
#: values marked ``~`` were not in the stored e-Manual pages and are the sibling model's (the
#: effort estimate only; a profile can set ``torque_constant``).
MODELS: Final[Mapping[str, Model]] = {
    m.name: m
    for m in (
        _m(
            "XL430-W250",
            1060,
            None,
            (1.5, 1.4),
            velocity_limit=265,
            gains=(1000, 100, 4000, 0, 640),
            **_XL430,
        ),
        _m(
            "2XL430-W250",
            1090,
            None,
            (1.5, 1.4),
            velocity_limit=250,
            gains=(1800, 100, 2000, 0, 640),
            **_XL430,
        ),
        _m(
            "XC430-W150",
            1070,
            None,
            (1.6, 1.4),
            velocity_limit=460,
            gains=(1920, 100, 0, 0, 460),
            **_XC430,
        ),
        _m(
            "XC430-W240",
            1080,
            None,
            (1.9, 1.4),
            velocity_limit=306,
            gains=(1920, 100, 0, 0, 700),
            **_XC430,
        ),
        _m(
            "XL330-M077",
            1190,
            0.001,
            (0.215, 1.47),
            5.0,
            velocity_limit=1620,
            current_limit=1750,
            gains=(400, 40, 0, 400, 400),
            **_XL330,
        ),
        _m(
            "XL330-M288",
            1200,
            0.001,
            (0.52, 1.47),
            5.0,
            velocity_limit=445,
            current_limit=1750,
            gains=(1600, 180, 0, 0, 400),
            **_XL330,
        ),
        _m("XM430-W210", 1030, _MA_269, (3.0, 2.3), velocity_limit=330, current_limit=1193),
        _m("XM430-W350", 1020, _MA_269, (4.1, 2.3), velocity_limit=200, current_limit=1193),
        _m(
            "XH430-W210", 1010, _MA_269, (2.5, 1.3), velocity_limit=210, current_limit=648, **_XH430
        ),
        _m(
            "XH430-W350", 1000, _MA_269, (3.4, 1.3), velocity_limit=130, current_limit=648, **_XH430
        ),
        _m(
            "XH430-V210",
            1050,
            _MA_134,
            (2.6, 0.7),
            24.0,
            velocity_limit=380,
            current_limit=689,
            **_V24,
        ),
        _m(
            "XH430-V350",
            1040,
            _MA_134,
            (3.3, 0.7),
            24.0,
            velocity_limit=285,
            current_limit=689,
            **_V24,
        ),
        _m(
            "XD430-T210", 1011, _MA_269, (2.5, 1.3), velocity_limit=210, current_limit=648, **_XH430
        ),
        _m(
            "XD430-T350", 1001, _MA_269, (3.4, 1.3), velocity_limit=130, current_limit=648, **_XH430
        ),
        _m(
            "XM540-W150", 1130, _MA_269, (7.3, 4.4), velocity_limit=230, current_limit=2047, **_X540
        ),
        _m(
            "XM540-W270",
            1120,
            _MA_269,
            (10.6, 4.4),
            velocity_limit=128,
            current_limit=2047,
            **_X540,
        ),
        _m(
            "XH540-W150",
            1110,
            _MA_269,
            (7.5, 4.9),
            velocity_limit=300,  # ~ stall
            current_limit=2047,
            **_X540,
        ),
        _m(
            "XH540-W270",
            1100,
            _MA_269,
            (10.6, 4.4),
            velocity_limit=167,  # ~ stall
            current_limit=2047,
            **_X540,
        ),
        _m(
            "XH540-V150",
            1150,
            _MA_269,
            (6.4, 2.4),
            24.0,
            velocity_limit=230,
            current_limit=2047,
            **_X540,
            **_V24,
        ),
        _m(
            "XH540-V270",
            1140,
            _MA_269,
            (9.2, 2.4),
            24.0,
            velocity_limit=128,
            current_limit=2047,
            **_X540,
            **_V24,
        ),
        _m(
            "XD540-T150",
            1111,
            _MA_269,
            (7.5, 4.9),
            velocity_limit=300,  # ~ stall
            current_limit=2047,
            **_X540,
        ),
        _m(
            "XD540-T270",
            1101,
            _MA_269,
            (10.6, 4.4),
            velocity_limit=167,  # ~ stall
            current_limit=2047,
            **_X540,
        ),
        _m(
            "XW430-T200",
            1280,
            _MA_269,
            (2.5, 1.3),
            velocity_limit=235,  # ~ stall
            current_limit=2047,
            **_XH430,
            **_XW,
        ),
        _m(
            "XW430-T333",
            1270,
            _MA_269,
            (3.4, 1.3),
            velocity_limit=139,  # ~ stall
            current_limit=2047,
            **_XH430,
            **_XW,
        ),
        _m("XW540-T140", 1180, _MA_269, (6.9, 4.9), velocity_limit=304, current_limit=2047, **_XW),
        _m("XW540-T260", 1170, _MA_269, (9.5, 4.9), velocity_limit=167, current_limit=2047, **_XW),
    )
}
#: Models by model number.
MODELS_BY_NUMBER: Final[Mapping[int, Model]] = {m.number: m for m in MODELS.values()}


def table_of(model: str) -> tuple[Register, ...]:
    """A model's control table.

    Args:
        model: A name from :data:`MODELS`.

    Returns:
        Its registers in address order.

    Raises:
        KeyError: An unknown model.
    """
    return MODELS[model].registers
