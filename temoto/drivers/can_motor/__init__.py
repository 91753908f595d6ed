"""CAN motors over python-can: ODrive (CANSimple) and CubeMars/T-Motor MIT mode.

Modules: :mod:`~temoto.drivers.can_motor.cansimple` and :mod:`~temoto.drivers.can_motor.mitmode`
are the pure protocols; :mod:`~temoto.drivers.can_motor.odrive` (``driver: odrive_can``) and
:mod:`~temoto.drivers.can_motor.mit` (``driver: mit_can``) the drivers;
:mod:`~temoto.drivers.can_motor.sim` the simulators. The driver modules import python-can
(the ``can`` extra); this package itself imports nothing optional.
"""

from __future__ import annotations

__all__: list[str] = []
