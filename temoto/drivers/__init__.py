"""Device drivers: the hardware layer under the Robot Manager (docs/design.md §7).

Three layers per device: a link (a python-can Bus, a serial port or pseudo-terminal, UDP), a
pure protocol module (frames and packets to typed values), and a :class:`Driver` with the
shared lifecycle (:mod:`temoto.drivers.base`) and capability verbs in SI units
(:mod:`temoto.drivers.capabilities`). Every driver has a simulator that speaks the device's
side of the same wire protocol, so the production driver is what every test runs.

Importing this package imports no device library; :func:`driver_class` imports a driver (and
its library) on first use. A driver reads its profile entry with the one profile reader,
:mod:`temoto.drivers.profile`, from the fields it declares (:meth:`Driver.from_profile`); each
driver package finds its devices in a ``detect`` module of its own.
"""

from __future__ import annotations

from temoto.drivers.base import (
    Driver,
    DriverState,
    Health,
    HealthListener,
    live_drivers,
    make_all_safe,
)
from temoto.drivers.capabilities import (
    Actuator,
    ControlMode,
    GeoPoint,
    JointCommand,
    JointState,
    JointStates,
    MissionItem,
    MissionProgress,
    MissionVehicle,
    Vehicle,
    VehicleTelemetry,
)
from temoto.drivers.registry import driver_class, driver_names

__all__ = [
    "Actuator",
    "ControlMode",
    "Driver",
    "DriverState",
    "GeoPoint",
    "Health",
    "HealthListener",
    "JointCommand",
    "JointState",
    "JointStates",
    "MissionItem",
    "MissionProgress",
    "MissionVehicle",
    "Vehicle",
    "VehicleTelemetry",
    "driver_class",
    "driver_names",
    "live_drivers",
    "make_all_safe",
]
