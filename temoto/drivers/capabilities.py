"""What drivers can do, in SI units: joints (:class:`Actuator`) and vehicles (:class:`Vehicle`).

A driver declares a capability by implementing the protocol; the Robot Manager and the robot
actions use only these, never a device's registers or frames. Units: radians, radians per
second, newton-metres, metres, seconds, volts; angles of a vehicle in radians, positions as
WGS-84 latitude/longitude in degrees with the altitude in metres above the home position.
A motor with a gearbox reports the *joint* side (the driver applies the ratio).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

__all__ = [
    "Actuator",
    "ControlMode",
    "GeoPoint",
    "JointCommand",
    "JointState",
    "JointStates",
    "Vehicle",
    "VehicleTelemetry",
]


class ControlMode(enum.Enum):
    """What a joint command sets."""

    POSITION = "position"  # rad
    VELOCITY = "velocity"  # rad/s
    EFFORT = "effort"  # N·m


@dataclass(frozen=True, slots=True)
class JointCommand:
    """One joint's set-point.

    Attributes:
        joint: The joint's name (from the profile).
        mode: What ``value`` is.
        value: The set-point in SI units (rad, rad/s or N·m).
        velocity_limit: For a position command, the largest speed to use (rad/s), or None.

    Raises:
        ValueError: ``value`` is not finite.
    """

    joint: str
    mode: ControlMode
    value: float
    velocity_limit: float | None = None

    def __post_init__(self) -> None:
        if not math.isfinite(self.value):
            raise ValueError(f"joint {self.joint}: the set-point must be finite, got {self.value}")


@dataclass(frozen=True, slots=True)
class JointState:
    """One joint as measured.

    Attributes:
        joint: The joint's name.
        position: rad.
        velocity: rad/s.
        effort: N·m (0.0 when the device does not measure it).
        stamp: Clock seconds of the measurement.
    """

    joint: str
    position: float
    velocity: float
    effort: float
    stamp: float


@dataclass(frozen=True, slots=True)
class JointStates:
    """Every joint of a driver at once.

    Attributes:
        stamp: Clock seconds of the newest measurement.
        joints: States by joint name.
    """

    stamp: float
    joints: Mapping[str, JointState]


@runtime_checkable
class Actuator(Protocol):
    """Joints: CAN motors, Dynamixel servos."""

    @property
    def joint_names(self) -> tuple[str, ...]:
        """The joints this driver moves, in profile order."""
        ...

    def command(self, commands: Iterable[JointCommand]) -> None:
        """Send set-points (only ``ACTIVE``; a joint not named keeps its set-point).

        Raises:
            StateError: Not active.
            ValueError: An unknown joint, or a mode the device does not support.
            DriverError: The device refused or did not answer.
        """
        ...

    def read_state(self) -> JointStates:
        """The newest measurement of every joint (no bus traffic: the driver's cache).

        Raises:
            StateError: Never configured, or finalized.
        """
        ...


@dataclass(frozen=True, slots=True)
class GeoPoint:
    """A position on the Earth.

    Attributes:
        lat: Latitude, degrees.
        lon: Longitude, degrees.
        alt: Metres above the home position.

    Raises:
        ValueError: Out of range or not finite.
    """

    lat: float
    lon: float
    alt: float

    def __post_init__(self) -> None:
        if not all(math.isfinite(v) for v in (self.lat, self.lon, self.alt)):
            raise ValueError(f"a position must be finite: {self}")
        if not (-90.0 <= self.lat <= 90.0 and -180.0 <= self.lon <= 180.0):
            raise ValueError(f"latitude/longitude out of range: {self.lat}, {self.lon}")


@dataclass(frozen=True, slots=True)
class VehicleTelemetry:
    """The newest state of a vehicle.

    Attributes:
        stamp: Clock seconds of the newest message.
        armed: Whether the motors are armed.
        mode: The flight mode's name (``GUIDED``, ``LAND``, ...).
        position: Where it is (altitude above home).
        attitude: Roll, pitch, yaw in radians.
        battery_voltage: Volts.
        battery_remaining: Percent (0 to 100), or -1 if unknown.
        status_texts: The newest ``STATUSTEXT`` messages, oldest first.
        heartbeat_age: Seconds since the last heartbeat.
    """

    stamp: float
    armed: bool
    mode: str
    position: GeoPoint
    attitude: tuple[float, float, float]
    battery_voltage: float
    battery_remaining: int
    status_texts: tuple[str, ...]
    heartbeat_age: float


@runtime_checkable
class Vehicle(Protocol):
    """A vehicle that flies or drives to positions: MAVLink autopilots."""

    def arm(self) -> None:
        """Arm the motors (waits for the acknowledgement).

        Raises:
            MavlinkCommandError: Refused (e.g. pre-arm checks failed).
            DriverTimeoutError: No acknowledgement in time.
        """
        ...

    def disarm(self) -> None:
        """Disarm."""
        ...

    def set_mode(self, mode: str) -> None:
        """Switch the flight mode by name."""
        ...

    def takeoff(self, altitude: float) -> None:
        """Take off to ``altitude`` metres above home (returns when commanded, not reached)."""
        ...

    def goto(self, target: GeoPoint) -> None:
        """Fly to a position (returns when commanded, not reached)."""
        ...

    def land(self) -> None:
        """Land where it is."""
        ...

    def return_to_launch(self) -> None:
        """Fly home and land."""
        ...

    def telemetry(self) -> VehicleTelemetry:
        """The newest telemetry (the driver's cache)."""
        ...
