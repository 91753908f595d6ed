"""The profile entry of a MAVLink vehicle: its keys, as fields of the one profile reader.

:data:`PROFILE_FIELDS` declares every key of a ``driver: mavlink`` entry (besides ``driver`` and
``safe_state``) to :mod:`temoto.drivers.profile`, with its default and range; the constructor
of :class:`~temoto.drivers.mavlink.driver.MavlinkDriver` checks the keys that depend on each
other. :func:`read_sim` reads the entry's ``sim`` mapping (the simulated vehicle's model) and
:func:`failsafe_params` its ``gcs_failsafe``. ``docs/driver-mavlink.md`` lists the keys for
people.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, Final

from temoto.drivers.mavlink import protocol as p
from temoto.drivers.mavlink.link import parse_link
from temoto.drivers.mavlink.sim import DEFAULT_RATES, PARAMETERS
from temoto.drivers.profile import Field, ProfileReader, custom, integer, number
from temoto.drivers.realism import LEVEL_NAMES

__all__ = ["LINK_HINT", "PROFILE_FIELDS", "failsafe_params", "read_sim"]

#: What to write when ``link`` is missing.
LINK_HINT: Final = "where the vehicle is, e.g. udpin:127.0.0.1:14550"
#: ``gcs_failsafe`` keys → (ArduPilot parameter, low, high, integer); ranges from the
#: ArduCopter parameter documentation (FS_GCS_ENABLE values 0..7, FS_GCS_TIMEOUT 2..120 s).
_FAILSAFE_KEYS: Final[Mapping[str, tuple[str, float, float, bool]]] = {
    "enable": ("FS_GCS_ENABLE", 0, 7, True),
    "timeout": ("FS_GCS_TIMEOUT", 2, 120, False),
}
_SIM_KEYS: Final = frozenset(
    {
        "home",
        "battery",
        "cells",
        "min_arm_battery",
        "speed",
        "climb_rate",
        "descent_rate",
        "tau",
        "rtl_altitude",
        "drain_idle",
        "drain_flight",
        "step_rate",
        "rates",
        "params",
        "realism",
        "seed",
    }
)
_POSITIVE: Final = frozenset({"cells", "speed", "climb_rate", "descent_rate", "tau", "step_rate"})


def failsafe_params(raw: Any) -> dict[str, float]:
    """The ArduPilot parameters a ``gcs_failsafe`` mapping sets (checked).

    Args:
        raw: The mapping (``{enable: 5, timeout: 5}``), or None.

    Returns:
        ArduPilot parameter → value (empty for None).

    Raises:
        ValueError: Not a mapping, an unknown key, or a value out of ArduPilot's range (the
            message starts with the key path, ``gcs_failsafe.enable: ...``).
    """
    if raw is None:
        return {}
    if not isinstance(raw, Mapping):
        raise ValueError(
            f"gcs_failsafe: must be a mapping like {{enable: 5, timeout: 5}}, got {raw!r}"
        )
    out: dict[str, float] = {}
    for key, value in raw.items():
        if key not in _FAILSAFE_KEYS:
            known = ", ".join(_FAILSAFE_KEYS)
            raise ValueError(f"gcs_failsafe.{key}: unknown key (known: {known})")
        param, low, high, integer = _FAILSAFE_KEYS[key]
        number = isinstance(value, int | float) and not isinstance(value, bool)
        if integer and number and isinstance(value, float) and not value.is_integer():
            number = False
        if not (number and math.isfinite(value) and low <= value <= high):
            kind = "an integer" if integer else "a number"
            raise ValueError(
                f"gcs_failsafe.{key}: must be {kind} {low:g}..{high:g} ({param}), got {value!r}"
            )
        out[param] = float(value)
    return out


def read_sim(reader: ProfileReader, raw: Any, where: str) -> dict[str, Any]:
    """The ``sim`` mapping of a profile entry as SimVehicle keywords (checked).

    Args:
        reader: Where errors are raised.
        raw: The value.
        where: Its key path (``sim``).

    Returns:
        Keyword arguments of :class:`~temoto.drivers.mavlink.sim.SimVehicle`.

    Raises:
        ProfileError: Not a mapping, an unknown key, or a value out of range (named).
    """
    if not isinstance(raw, Mapping):
        reader.fail(where, "must be a mapping of simulator settings")
    unknown = sorted(set(raw) - _SIM_KEYS)
    if unknown:
        reader.fail(f"{where}.{unknown[0]}", f"unknown key (known: {', '.join(sorted(_SIM_KEYS))})")
    out: dict[str, Any] = {}
    for key, value in raw.items():
        if key == "home":
            ok = isinstance(value, list | tuple) and len(value) == 3
            ok = ok and all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
            if not ok or not (-90 <= value[0] <= 90 and -180 <= value[1] <= 180):
                reader.fail(f"{where}.home", f"must be [lat, lon, altitude AMSL], got {value!r}")
            out[key] = tuple(float(v) for v in value)
        elif key == "rates":
            if not isinstance(value, Mapping):
                reader.fail(f"{where}.rates", "must map message names to Hz")
            for msg, hz in value.items():
                if str(msg).upper() not in DEFAULT_RATES:
                    reader.fail(
                        f"{where}.rates.{msg}",
                        f"not a simulated stream (streams: {', '.join(DEFAULT_RATES)})",
                    )
                if isinstance(hz, bool) or not isinstance(hz, int | float) or not hz >= 0:
                    reader.fail(f"{where}.rates.{msg}", f"must be a rate in Hz, got {hz!r}")
            out[key] = {str(k): float(v) for k, v in value.items()}
        elif key == "params":
            if not isinstance(value, Mapping):
                reader.fail(f"{where}.params", "must map parameter names to numbers")
            for param, number in value.items():
                if param not in PARAMETERS:
                    reader.fail(
                        f"{where}.params.{param}",
                        f"not a simulated parameter (known: {', '.join(PARAMETERS)})",
                    )
                finite = isinstance(number, int | float) and math.isfinite(number)
                if isinstance(number, bool) or not finite:
                    reader.fail(f"{where}.params.{param}", f"must be a number, got {number!r}")
            out[key] = {str(k): float(v) for k, v in value.items()}
        elif key == "realism":
            if value not in LEVEL_NAMES:
                reader.fail(
                    f"{where}.realism", f"must be one of {', '.join(LEVEL_NAMES)}, got {value!r}"
                )
            out[key] = str(value)
        elif key == "seed":
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                reader.fail(f"{where}.seed", f"must be a non-negative integer, got {value!r}")
            out[key] = value
        else:
            if isinstance(value, bool) or not isinstance(value, int | float):
                reader.fail(f"{where}.{key}", f"must be a number, got {value!r}")
            if not math.isfinite(value) or value < 0 or (value == 0 and key in _POSITIVE):
                reader.fail(f"{where}.{key}", f"out of range: {value!r}")
            if key == "battery" and value > 100:
                reader.fail(f"{where}.battery", f"must be 0..100 %, got {value!r}")
            out[key] = int(value) if key == "cells" else float(value)
    return out


def _read_link(reader: ProfileReader, value: Any, key: str) -> str:
    if not isinstance(value, str):
        reader.fail(key, "must be text like udpin:127.0.0.1:14550")
    try:
        parse_link(value)
    except ValueError as err:
        reader.fail(key, str(err))
    return value


def _read_failsafe(reader: ProfileReader, value: Any, key: str) -> Mapping[str, Any]:
    try:
        failsafe_params(value)
    except ValueError as err:  # the message starts with the key path below the entry
        path, _, message = str(err).partition(": ")
        reader.fail(path, message)
    return dict(value)


#: The keys of a vehicle's entry with their defaults and ranges.
PROFILE_FIELDS: Final[Mapping[str, Field[Any]]] = {
    "link": custom(_read_link, hint=LINK_HINT),
    "system_id": integer(None, low=1, high=255),
    # component 0 is MAV_COMP_ID_ALL (common.xml: broadcast), nobody's own id
    "component_id": integer(p.MAV_COMP_ID_AUTOPILOT1, low=1, high=255),
    "gcs_system_id": integer(255, low=1, high=255),
    "gcs_component_id": integer(190, low=1, high=255),
    # at most half of ArduPilot's shortest FS_GCS_TIMEOUT (2 s; the constructor checks it
    # against gcs_failsafe.timeout when that is set)
    "heartbeat_period": number(1.0, high=1.0, unit="s"),
    # ArduPilot heartbeats once a second: a lost one (2 s) must not be a fault; no longer
    # than ArduPilot's longest FS_GCS_TIMEOUT (120 s)
    "heartbeat_timeout": number(
        3.0, low=2.0 * p.VEHICLE_HEARTBEAT_PERIOD, low_open=False, high=120.0, unit="s"
    ),
    # at least one of ArduPilot's heartbeat periods, or the first one may not have come
    "init_timeout": number(5.0, low=p.VEHICLE_HEARTBEAT_PERIOD, low_open=False, unit="s"),
    "command_timeout": number(1.0, unit="s"),
    "command_retries": integer(2, low=0, high=10),
    "mission_timeout": number(1.5, unit="s"),
    "mission_retries": integer(5, low=0, high=20),
    # ArduPilot's stream rates (SRn_* parameters) go up to 50 Hz
    "stream_rate": number(10.0, low=0, low_open=False, high=50, unit="Hz"),
    "status_texts": integer(20, low=1),
    "gcs_failsafe": custom(_read_failsafe, None),
    "sim": custom(read_sim, {}, init=False),  # checked here, used by simulate()
}
