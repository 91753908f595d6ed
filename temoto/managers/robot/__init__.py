"""The Robot Manager: robots from hardware profiles (``python -m temoto.managers.robot``).

* :class:`RobotManager` (:mod:`.manager`): the ``"robot"`` and ``"driver"`` registrar servers.
* :class:`RobotManagerClient`, :class:`RobotHandle`, :func:`follow` (:mod:`.client`): what
  actions use.
* :mod:`.features`: drive, arm and flight controllers, and :class:`Motion`.

Running the package (``__main__``) starts a whole robot instance from a profile.
"""

from __future__ import annotations

from temoto.managers.robot.client import RobotHandle, RobotManagerClient, follow
from temoto.managers.robot.features import Motion
from temoto.managers.robot.manager import (
    DriverRequest,
    DriverResponse,
    Robot,
    RobotManager,
    RobotRequest,
    RobotResponse,
)

__all__ = [
    "DriverRequest",
    "DriverResponse",
    "Motion",
    "Robot",
    "RobotHandle",
    "RobotManager",
    "RobotManagerClient",
    "RobotRequest",
    "RobotResponse",
    "follow",
]
