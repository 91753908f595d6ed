"""One DYNAMIXEL servo of a chain: its profile settings, its units, its slow readings.

:class:`ServoConfig` holds what a profile says of one servo (id, joint, model, operating mode,
limits, gear, offset) and converts between the servo's register units and the joint's SI
units; :class:`ServoStatus` is one reading of its temperature, voltage and hardware errors.
The driver (:mod:`~temoto.drivers.dynamixel.driver`) uses both.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Final

from temoto.drivers.capabilities import ControlMode
from temoto.drivers.dynamixel import control_table as ct
from temoto.drivers.dynamixel import protocol as p

__all__ = [
    "COMMAND_MODE",
    "MODES",
    "POSITION_MODES",
    "ServoConfig",
    "ServoFieldError",
    "ServoStatus",
]

#: Profile ``mode`` values → Operating Mode.
MODES: Final[Mapping[str, ct.OperatingMode]] = {
    "current": ct.OperatingMode.CURRENT,
    "velocity": ct.OperatingMode.VELOCITY,
    "position": ct.OperatingMode.POSITION,
    "extended_position": ct.OperatingMode.EXTENDED_POSITION,
    "current_based_position": ct.OperatingMode.CURRENT_BASED_POSITION,
}
#: The operating modes in which a joint takes position commands.
POSITION_MODES: Final = frozenset(
    {
        ct.OperatingMode.POSITION,
        ct.OperatingMode.EXTENDED_POSITION,
        ct.OperatingMode.CURRENT_BASED_POSITION,
    }
)
#: Operating Mode → the kind of joint command it takes.
COMMAND_MODE: Final[Mapping[ct.OperatingMode, ControlMode]] = {
    ct.OperatingMode.CURRENT: ControlMode.EFFORT,
    ct.OperatingMode.VELOCITY: ControlMode.VELOCITY,
    **dict.fromkeys(POSITION_MODES, ControlMode.POSITION),
}


class ServoFieldError(ValueError):
    """A bad :class:`ServoConfig` value.

    Args:
        key: The field (for profile key paths).
        message: What is wrong.
    """

    def __init__(self, key: str, message: str) -> None:
        super().__init__(message)
        self.key = key


@dataclass(frozen=True, slots=True)
class ServoConfig:
    """One servo of a chain (joint side values in SI units).

    Attributes:
        id: Its id on the chain (0 to 252).
        joint: The joint it moves.
        model: Its model name (``XM430-W350``); PING must report this model.
        mode: The operating mode (``position``, ``extended_position``,
            ``current_based_position``, ``velocity``, ``current``).
        min_position: The lowest joint position a command may ask for (rad); by default (NaN)
            the end of the servo's single turn (tick 0 or 4095, after gear and offset).
        max_position: The highest (rad); by default the other end of the single turn.
        velocity_limit: The largest joint speed a command may ask for (rad/s), or None.
        effort_limit: The largest joint effort a command may ask for (N·m), or None.
        gear: Motor turns per joint turn (negative reverses the direction).
        offset: Joint position (rad) at the servo's middle position (tick 2048).
        torque_constant: N·m per A of the motor, or None for the model's value.
        write_limits: Write the limits to the servo's Min/Max Position Limit registers at
            configure (only in ``position`` mode, the one mode where the servo applies them).

    Raises:
        ValueError: A value out of range.
    """

    id: int
    joint: str
    model: str
    mode: str = "position"
    min_position: float = math.nan
    max_position: float = math.nan
    velocity_limit: float | None = None
    effort_limit: float | None = None
    gear: float = 1.0
    offset: float = 0.0
    torque_constant: float | None = None
    write_limits: bool = False

    def __post_init__(self) -> None:
        if not 0 <= self.id <= p.MAX_ID:
            raise ServoFieldError("id", f"id must be 0..{p.MAX_ID}, got {self.id}")
        if not self.joint:
            raise ServoFieldError("joint", "joint must be a non-empty name")
        if self.model not in ct.MODELS:
            known = ", ".join(ct.MODELS)
            raise ServoFieldError("model", f"unknown model {self.model!r} (known: {known})")
        if self.mode not in MODES:
            raise ServoFieldError("mode", f"unknown mode {self.mode!r} (known: {', '.join(MODES)})")
        if MODES[self.mode] not in ct.MODELS[self.model].modes or (
            self.mode == "current" and ct.MODELS[self.model].current_unit is None
        ):
            raise ServoFieldError("mode", f"{self.model} has no {self.mode} mode")
        if not (math.isfinite(self.gear) and self.gear != 0):
            raise ServoFieldError("gear", f"gear must be finite and non-zero, got {self.gear}")
        if not math.isfinite(self.offset):
            raise ServoFieldError("offset", f"offset must be finite, got {self.offset}")
        ends = sorted((self.position(0), self.position(4095)))
        if math.isnan(self.min_position):  # the default: the servo's single turn
            object.__setattr__(self, "min_position", ends[0])
        if math.isnan(self.max_position):
            object.__setattr__(self, "max_position", ends[1])
        lo, hi = self.min_position, self.max_position
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise ServoFieldError(
                "max_position", f"need finite min_position < max_position, got {lo}, {hi}"
            )
        if MODES[self.mode] is ct.OperatingMode.POSITION:
            for key, bound in (("min_position", lo), ("max_position", hi)):
                if not 0 <= self.ticks(bound) <= 4095:
                    raise ServoFieldError(
                        key,
                        f"{bound} rad is outside the servo's single turn in position mode"
                        " (use extended_position)",
                    )
        for key in ("velocity_limit", "effort_limit", "torque_constant"):
            value = getattr(self, key)
            if value is not None and not (math.isfinite(value) and value > 0):
                raise ServoFieldError(key, f"{key} must be positive, got {value}")
        # The model's table (ROBOTIS e-Manual, each model's control table): Velocity Limit (44)
        # ranges 0..1023 (0..2047 on the XL330) in 0.229 rev/min, Current Limit (38) 0..its
        # model's maximum (1193 on the XM430-W350, in 2.69 mA).
        if self.velocity_limit is not None and self.velocity_limit > self.max_velocity:
            reg = self.spec.register("Velocity Limit")
            raise ServoFieldError(
                "velocity_limit",
                f"{self.velocity_limit:g} rad/s is above what a {self.model} can be set to:"
                f" Velocity Limit (44) at most {reg.high if reg else '?'} x 0.229 rev/min ="
                f" {self.max_velocity:.4g} rad/s at the joint (gear {self.gear:g})",
            )
        if self.effort_limit is not None and self.effort_limit > self.max_effort:
            reg = self.spec.register("Current Limit")
            unit = (self.spec.current_unit or 0) * 1000
            what = (
                f"Current Limit (38) at most {reg.high} x {unit:g} mA"
                if reg is not None and reg.high is not None
                else "100 % of its stall torque (it has no current sensor)"
            )
            raise ServoFieldError(
                "effort_limit",
                f"{self.effort_limit:g} N·m is above what a {self.model} can give: {what} ="
                f" {self.max_effort:.4g} N·m at the joint (gear {self.gear:g})",
            )

    @property
    def spec(self) -> ct.Model:
        """The model's data."""
        return ct.MODELS[self.model]

    @property
    def operating_mode(self) -> ct.OperatingMode:
        """The Operating Mode register's value."""
        return MODES[self.mode]

    @property
    def max_velocity(self) -> float:
        """The largest joint speed the model's Velocity Limit (44) allows (rad/s).

        The register's largest value (the e-Manual's Range column) in 0.229 rev/min units,
        through the gear.
        """
        reg = self.spec.register("Velocity Limit")
        high = reg.high if reg is not None and reg.high is not None else 0
        return high * ct.RAD_S_PER_UNIT / abs(self.gear)

    @property
    def max_effort(self) -> float:
        """The largest joint effort the model allows (N·m).

        Current Limit (38)'s largest value through the current unit, the torque constant and
        the gear; for a model without a current sensor its stall torque through the gear.
        """
        reg = self.spec.register("Current Limit")
        if self.spec.current_unit is None or reg is None or reg.high is None:
            return self.spec.stall_torque * abs(self.gear)
        return abs(self.effort(reg.high))

    @property
    def speed_limit(self) -> float:
        """The joint's largest speed: ``velocity_limit``, or else :attr:`max_velocity` (rad/s)."""
        return self.velocity_limit if self.velocity_limit is not None else self.max_velocity

    def limit_ticks(self) -> tuple[int, int]:
        """(Min Position Limit, Max Position Limit) register values for the joint limits."""
        a, b = self.ticks(self.min_position), self.ticks(self.max_position)
        return max(min(a, b), 0), min(max(a, b), 4095)

    def ticks(self, position: float) -> int:
        """Joint radians → Goal Position ticks."""
        return round((position - self.offset) * self.gear / ct.RAD_PER_TICK) + ct.POSITION_CENTER

    def position(self, ticks: int) -> float:
        """Present Position ticks → joint radians."""
        return (ticks - ct.POSITION_CENTER) * ct.RAD_PER_TICK / self.gear + self.offset

    def velocity(self, units: int) -> float:
        """Present Velocity units → joint rad/s."""
        return units * ct.RAD_S_PER_UNIT / self.gear

    def velocity_units(self, velocity: float) -> int:
        """Joint rad/s → Goal/Profile Velocity units."""
        return round(velocity * self.gear / ct.RAD_S_PER_UNIT)

    def _newton_metres_per_unit(self) -> float:
        spec = self.spec
        if spec.current_unit is None:  # XL430/XC430: Present Load, 0.1 % of the stall torque
            return 0.001 * spec.stall_torque * abs(self.gear)
        kt = self.torque_constant or spec.torque_constant
        return spec.current_unit * kt * abs(self.gear)

    def effort(self, units: int) -> float:
        """Present Current (or Load) units → joint N·m (the gear's sign included)."""
        return units * self._newton_metres_per_unit() * (1 if self.gear > 0 else -1)

    def current_units(self, effort: float) -> int:
        """Joint N·m → Goal Current units."""
        return round(effort / self._newton_metres_per_unit() * (1 if self.gear > 0 else -1))


@dataclass(frozen=True, slots=True)
class ServoStatus:
    """The slow readings of one servo.

    Attributes:
        id: The servo.
        joint: Its joint.
        temperature: °C.
        voltage: Input volts.
        hardware_error: The Hardware Error Status register.
        errors: Its bits by name (``overheating``, ...).
        stamp: Clock seconds of the reading.
    """

    id: int
    joint: str
    temperature: float
    voltage: float
    hardware_error: int
    errors: tuple[str, ...]
    stamp: float
