"""What drivers can do, in SI units: joints (:class:`Actuator`) and vehicles (:class:`Vehicle`).

Vehicles that fly stored missions also implement :class:`MissionVehicle` (a mission is a list
of :class:`MissionItem`; its progress a :class:`MissionProgress`).

A driver declares a capability by implementing the protocol; the Robot Manager and the robot
actions use only these, never a device's registers or frames. Units: radians, radians per
second, newton-metres, metres, seconds, volts; angles of a vehicle in radians, positions as
WGS-84 latitude/longitude in degrees with the altitude in metres above the home position.
A motor with a gearbox reports the *joint* side (the driver applies the ratio).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Final, Protocol, runtime_checkable

__all__ = [
    "MISSION_KINDS",
    "Actuator",
    "ControlMode",
    "GeoPoint",
    "JointCommand",
    "JointState",
    "JointStates",
    "MissionItem",
    "MissionProgress",
    "MissionVehicle",
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


#: The kinds of :class:`MissionItem`, in the order a mission usually has them.
MISSION_KINDS: Final = ("takeoff", "waypoint", "loiter_time", "speed", "land", "rtl")


def _finite(value: float | None) -> bool:
    return value is None or (
        isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
    )


@dataclass(frozen=True, slots=True)
class MissionItem:
    """One item of a vehicle's stored mission, in geodetic coordinates.

    Build one with the class methods (:meth:`waypoint`, :meth:`takeoff`, :meth:`loiter_time`,
    :meth:`change_speed`, :meth:`land`, :meth:`rtl`). Latitude and longitude are WGS-84
    degrees; ``alt`` is metres above the home position (MAVLink's relative-altitude frame).
    A position left None means "where the vehicle is when it gets to this item" (ArduPilot's
    zero latitude/longitude).

    Attributes:
        kind: One of :data:`MISSION_KINDS`.
        lat: Latitude (degrees), or None.
        lon: Longitude (degrees), or None.
        alt: Metres above home, or None (where it is; ``land`` and ``rtl`` have none).
        seconds: ``waypoint``: seconds to hold there; ``loiter_time``: seconds to loiter.
        speed: ``speed``: the horizontal speed (m/s) from this item on.

    Raises:
        ValueError: An unknown kind, a missing or out-of-range value (the message names it).
    """

    kind: str
    lat: float | None = None
    lon: float | None = None
    alt: float | None = None
    seconds: float = 0.0
    speed: float = 0.0

    def __post_init__(self) -> None:
        if self.kind not in MISSION_KINDS:
            raise ValueError(
                f"mission item kind must be one of {', '.join(MISSION_KINDS)}, got {self.kind!r}"
            )
        for name in ("lat", "lon", "alt", "seconds", "speed"):
            if not _finite(getattr(self, name)):
                raise ValueError(
                    f"{self.kind} item: {name} must be a finite number, got {getattr(self, name)!r}"
                )
        if (self.lat is None) != (self.lon is None):
            raise ValueError(f"{self.kind} item: give both lat and lon, or neither")
        if self.lat is not None and self.lon is not None:
            if not (-90.0 <= self.lat <= 90.0 and -180.0 <= self.lon <= 180.0):
                raise ValueError(
                    f"{self.kind} item: latitude/longitude out of range: {self.lat}, {self.lon}"
                )
            if self.lat == 0.0 and self.lon == 0.0:
                raise ValueError(
                    f"{self.kind} item: (0, 0) means 'where the vehicle is' to an autopilot;"
                    " leave lat and lon None for that"
                )
        if self.seconds < 0:
            raise ValueError(f"{self.kind} item: seconds must be >= 0, got {self.seconds!r}")
        needs = {
            "takeoff": "alt",
            "waypoint": "position",
        }.get(self.kind)
        if needs == "alt" and (self.alt is None or self.alt <= 0):
            raise ValueError(f"takeoff item: alt must be positive metres, got {self.alt!r}")
        if needs == "position" and (self.lat is None or self.alt is None):
            raise ValueError("waypoint item: needs lat, lon and alt")
        if self.kind == "loiter_time" and self.seconds <= 0:
            raise ValueError(f"loiter_time item: seconds must be positive, got {self.seconds!r}")
        if self.kind == "speed" and self.speed <= 0:
            raise ValueError(f"speed item: speed must be positive m/s, got {self.speed!r}")
        if self.kind in ("rtl", "speed") and (self.lat is not None or self.alt is not None):
            raise ValueError(f"{self.kind} item: has no position")
        if self.kind == "land" and self.alt is not None:
            raise ValueError("land item: has no altitude (it lands)")

    @classmethod
    def waypoint(cls, lat: float, lon: float, alt: float, hold: float = 0.0) -> MissionItem:
        """Fly to a position (``MAV_CMD_NAV_WAYPOINT``).

        Args:
            lat: Latitude, degrees.
            lon: Longitude, degrees.
            alt: Metres above home.
            hold: Seconds to stay there.

        Returns:
            The item.

        Raises:
            ValueError: A bad value.
        """
        return cls("waypoint", lat, lon, alt, seconds=hold)

    @classmethod
    def takeoff(cls, alt: float) -> MissionItem:
        """Take off where the vehicle is to ``alt`` m above home (``MAV_CMD_NAV_TAKEOFF``).

        Args:
            alt: Metres above home (> 0).

        Returns:
            The item.

        Raises:
            ValueError: A bad value.
        """
        return cls("takeoff", alt=alt)

    @classmethod
    def loiter_time(
        cls,
        seconds: float,
        lat: float | None = None,
        lon: float | None = None,
        alt: float | None = None,
    ) -> MissionItem:
        """Loiter for ``seconds`` at a position, or where it is (``MAV_CMD_NAV_LOITER_TIME``).

        Args:
            seconds: How long (> 0).
            lat: Latitude, or None (where it is).
            lon: Longitude, or None.
            alt: Metres above home, or None (its altitude).

        Returns:
            The item.

        Raises:
            ValueError: A bad value.
        """
        return cls("loiter_time", lat, lon, alt, seconds=seconds)

    @classmethod
    def change_speed(cls, speed: float) -> MissionItem:
        """Fly the following items at ``speed`` m/s (``MAV_CMD_DO_CHANGE_SPEED``).

        Args:
            speed: Horizontal speed, m/s (> 0).

        Returns:
            The item.

        Raises:
            ValueError: A bad value.
        """
        return cls("speed", speed=speed)

    @classmethod
    def land(cls, lat: float | None = None, lon: float | None = None) -> MissionItem:
        """Land at a position, or where it is (``MAV_CMD_NAV_LAND``).

        Args:
            lat: Latitude, or None (where it is).
            lon: Longitude, or None.

        Returns:
            The item.

        Raises:
            ValueError: A bad value.
        """
        return cls("land", lat, lon)

    @classmethod
    def rtl(cls) -> MissionItem:
        """Return to launch and land (``MAV_CMD_NAV_RETURN_TO_LAUNCH``).

        Returns:
            The item.
        """
        return cls("rtl")


@dataclass(frozen=True, slots=True)
class MissionProgress:
    """How a vehicle's mission goes (items counted from 1, as a person counts them).

    Attributes:
        current: The item the vehicle is at (1..total), 0 before the mission started.
        total: The mission's items (0: unknown, nothing uploaded by this driver).
        reached: The newest item the vehicle reported reached or done, 0 for none.
        finished: The vehicle completed its last item.
    """

    current: int = 0
    total: int = 0
    reached: int = 0
    finished: bool = False


@runtime_checkable
class MissionVehicle(Vehicle, Protocol):
    """A :class:`Vehicle` that stores and flies missions: MAVLink autopilots."""

    def upload_mission(self, items: Sequence[MissionItem]) -> None:
        """Replace the vehicle's mission with ``items`` (returns when the vehicle accepted it).

        Raises:
            ValueError: No items, or more than the protocol carries.
            DriverOperationError: The vehicle refused it.
            DriverTimeoutError: The vehicle did not answer.
        """
        ...

    def start_mission(self) -> None:
        """Fly the stored mission (arming and taking off from the ground as needed)."""
        ...

    def clear_mission(self) -> None:
        """Delete the vehicle's mission."""
        ...

    @property
    def mission_progress(self) -> MissionProgress:
        """The newest progress the vehicle reported."""
        ...
