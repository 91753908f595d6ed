"""The DYNAMIXEL X-series control table and models, as data (ROBOTIS e-Manual).

Addresses, sizes and units of the registers the driver and the simulator use, the operating
modes, and per model the number a PING answers with and the numbers that turn register units
into SI units.

Units (X-series): position 4096 ticks per revolution (2048 is the middle of the single-turn
range; the driver takes it as 0 rad before the profile's ``offset``); velocity 0.229 rev/min per
unit; current per unit depends on the model (2.69 mA for XM430/XH430/XM540, 1 mA for XL330;
XL430 has no current sensor and reports *load* in 0.1 % of its maximum torque at the same
address); input voltage 0.1 V per unit; temperature 1 °C per unit.

Effort: torque = current x torque constant, with the torque constant taken as stall torque /
stall current at the nominal voltage from the e-Manual's performance table (an approximation:
the real curve is not linear near stall; a profile can override ``torque_constant`` per servo).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Final

__all__ = [
    "BUS_WATCHDOG",
    "BUS_WATCHDOG_ERROR",
    "BUS_WATCHDOG_FIRMWARE",
    "BUS_WATCHDOG_MAX",
    "BUS_WATCHDOG_UNIT",
    "CURRENT",
    "FAST_READ",
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
    """

    name: str
    address: int
    size: int
    signed: bool = False
    writable: bool = True
    eeprom: bool = False
    default: int = 0


def _ee(name: str, address: int, size: int, default: int = 0, writable: bool = True) -> Register:
    return Register(name, address, size, False, writable, True, default)


def _ram(
    name: str, address: int, size: int, default: int = 0, signed: bool = False, rw: bool = True
) -> Register:
    return Register(name, address, size, signed, rw, False, default)


#: The X-series registers used here (XM430-W350 layout; shared by the X family).
REGISTERS: Final[tuple[Register, ...]] = (
    _ee("Model Number", 0, 2, writable=False),
    _ee("Model Information", 2, 4, writable=False),
    _ee("Firmware Version", 6, 1, 48, writable=False),
    _ee("ID", 7, 1, 1),
    _ee("Baud Rate", 8, 1, 1),
    _ee("Return Delay Time", 9, 1, 250),
    _ee("Drive Mode", 10, 1),
    _ee("Operating Mode", 11, 1, 3),
    _ee("Homing Offset", 20, 4),
    _ee("Temperature Limit", 31, 1, 80),
    _ee("Max Voltage Limit", 32, 2, 160),
    _ee("Min Voltage Limit", 34, 2, 95),
    _ee("Current Limit", 38, 2, 1193),
    _ee("Velocity Limit", 44, 4, 200),
    _ee("Max Position Limit", 48, 4, 4095),
    _ee("Min Position Limit", 52, 4, 0),
    _ee("Shutdown", 63, 1, 52),
    _ram("Torque Enable", 64, 1),
    _ram("LED", 65, 1),
    _ram("Status Return Level", 68, 1, 2),
    _ram("Bus Watchdog", 98, 1, signed=True),
    _ram("Hardware Error Status", 70, 1, rw=False),
    _ram("Goal PWM", 100, 2, signed=True),
    _ram("Goal Current", 102, 2, signed=True),
    _ram("Goal Velocity", 104, 4, signed=True),
    _ram("Profile Acceleration", 108, 4),
    _ram("Profile Velocity", 112, 4),
    _ram("Goal Position", 116, 4, 2048, signed=True),
    _ram("Moving", 122, 1, rw=False),
    _ram("Present Current", 126, 2, signed=True, rw=False),
    _ram("Present Velocity", 128, 4, signed=True, rw=False),
    _ram("Present Position", 132, 4, 2048, signed=True, rw=False),
    _ram("Present Input Voltage", 144, 2, 120, rw=False),
    _ram("Present Temperature", 146, 1, 30, rw=False),
)

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
        current_unit: Amperes per Present/Goal Current unit, or None (XL430 reports load).
        torque_constant: N·m per ampere (stall torque / stall current; approximate).
        stall_torque: N·m at the nominal voltage (for XL430 load: 100 % = this).
        modes: Operating modes it supports.
        nominal_voltage: Volts (the simulator's Present Input Voltage).
    """

    name: str
    number: int
    current_unit: float | None
    torque_constant: float
    stall_torque: float
    modes: frozenset[OperatingMode]
    nominal_voltage: float = 12.0


_ALL = frozenset(OperatingMode)
_NO_CURRENT = frozenset(
    {
        OperatingMode.VELOCITY,
        OperatingMode.POSITION,
        OperatingMode.EXTENDED_POSITION,
        OperatingMode.PWM,
    }
)

#: Models by name.
MODELS: Final[Mapping[str, Model]] = {
    m.name: m
    for m in (
        Model("XL430-W250", 1060, None, 1.5 / 1.4, 1.5, _NO_CURRENT),
        Model("XL330-M288", 1200, 0.001, 0.52 / 1.47, 0.52, _ALL, 5.0),
        Model("XM430-W210", 1030, 0.00269, 3.0 / 2.3, 3.0, _ALL),
        Model("XM430-W350", 1020, 0.00269, 4.1 / 2.3, 4.1, _ALL),
        Model("XH430-W210", 1010, 0.00269, 2.5 / 1.3, 2.5, _ALL),
        Model("XH430-W350", 1000, 0.00269, 3.4 / 1.3, 3.4, _ALL),
        Model("XM540-W150", 1130, 0.00269, 7.3 / 4.4, 7.3, _ALL),
        Model("XM540-W270", 1120, 0.00269, 10.6 / 4.4, 10.6, _ALL),
    )
}
#: Models by model number.
MODELS_BY_NUMBER: Final[Mapping[int, Model]] = {m.number: m for m in MODELS.values()}
