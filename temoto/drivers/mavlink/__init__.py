"""MAVLink 2 vehicles (ArduPilot Copter): driver, protocol adapter and simulator.

* :mod:`~temoto.drivers.mavlink.protocol`: encode and decode over pymavlink's
  ``ardupilotmega`` dialect (no I/O).
* :mod:`~temoto.drivers.mavlink.link`: UDP and serial links opened from URLs.
* :mod:`~temoto.drivers.mavlink.driver`: :class:`MavlinkDriver`, a
  :class:`~temoto.drivers.Vehicle` (profile ``driver: mavlink``).
* :mod:`~temoto.drivers.mavlink.sim`: :class:`SimVehicle`, a simulated ArduCopter on UDP
  loopback that the driver and MAVSDK can fly.

Importing this package imports pymavlink (``pip install 'temoto[mavlink]'``).
"""

from __future__ import annotations

from temoto.drivers.mavlink._session import ModeChange
from temoto.drivers.mavlink.driver import MavlinkDriver
from temoto.drivers.mavlink.sim import SimVehicle

__all__ = ["MavlinkDriver", "ModeChange", "SimVehicle"]
