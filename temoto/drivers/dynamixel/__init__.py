"""DYNAMIXEL X-series servos over Protocol 2.0 (dynamixel-sdk), and their simulator.

* :mod:`.protocol` -- packets, CRC-16, byte stuffing, status errors (pure functions);
* :mod:`.control_table` -- register addresses, sizes, units and models, as data;
* :mod:`.driver` -- :class:`~temoto.drivers.dynamixel.driver.DynamixelDriver` (imports
  dynamixel-sdk, the ``temoto[dynamixel]`` extra; the registry's name is ``dynamixel``);
* :mod:`.sim` -- :class:`SimDynamixelChain`, a chain answering on a pseudo-terminal.

Importing this package does not import dynamixel-sdk.
"""

from __future__ import annotations

from temoto.drivers.dynamixel.sim import SimDynamixelChain

__all__ = ["SimDynamixelChain"]
