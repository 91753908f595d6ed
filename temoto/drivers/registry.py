"""Driver classes by the name a hardware profile uses (``driver: odrive_can``).

Built-in drivers are listed here as ``"module:Class"`` strings and imported on first use;
packages add their own through the ``temoto.drivers`` entry-point group. A missing optional
dependency becomes :class:`~temoto.errors.DriverUnavailableError` with the ``pip`` command that
installs it.
"""

from __future__ import annotations

import importlib
import importlib.metadata
from collections.abc import Mapping
from typing import Final

from temoto.drivers.base import Driver
from temoto.errors import DriverNotFoundError, DriverUnavailableError, PluginLoadError

__all__ = ["BUILTIN_DRIVERS", "ENTRY_POINT_GROUP", "driver_class", "driver_names"]

#: Entry-point group where other packages offer drivers (name → ``module:Class``).
ENTRY_POINT_GROUP: Final = "temoto.drivers"

#: The drivers shipped with TeMoto: name → (``module:Class``, the extra that installs its library).
BUILTIN_DRIVERS: Final[Mapping[str, tuple[str, str]]] = {
    "odrive_can": ("temoto.drivers.can_motor.odrive:ODriveDriver", "can"),
    "mit_can": ("temoto.drivers.can_motor.mit:MitMotorDriver", "can"),
    "dynamixel": ("temoto.drivers.dynamixel.driver:DynamixelDriver", "dynamixel"),
    "mavlink": ("temoto.drivers.mavlink.driver:MavlinkDriver", "mavlink"),
}


def driver_names() -> list[str]:
    """Every driver name known: built-in and offered through entry points.

    Returns:
        Sorted names.
    """
    names = set(BUILTIN_DRIVERS)
    names.update(ep.name for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP))
    return sorted(names)


def driver_class(name: str) -> type[Driver]:
    """The driver class a profile's ``driver`` value names.

    Args:
        name: The driver's name.

    Returns:
        The class.

    Raises:
        DriverNotFoundError: No driver has that name (the message lists the known ones).
        DriverUnavailableError: Its library is not installed (the message says how).
        PluginLoadError: Importing it failed otherwise.
    """
    spec, extra = BUILTIN_DRIVERS.get(name, ("", ""))
    if not spec:
        for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP):
            if ep.name == name:
                spec = ep.value
                break
    if not spec:
        raise DriverNotFoundError(f"no driver named {name!r} (known: {', '.join(driver_names())})")
    module_name, _, attr = spec.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as err:
        if extra and err.name and not err.name.startswith("temoto"):
            raise DriverUnavailableError(
                f"driver {name!r} needs {err.name}, which is not installed:"
                f" pip install 'temoto[{extra}]'"
            ) from err
        raise PluginLoadError(f"driver {name!r}: cannot import {module_name}: {err}") from err
    except Exception as err:
        raise PluginLoadError(f"driver {name!r}: importing {module_name} failed: {err}") from err
    cls = getattr(module, attr, None)
    if not (isinstance(cls, type) and issubclass(cls, Driver)):
        raise PluginLoadError(f"driver {name!r}: {spec} is not a Driver class")
    return cls
