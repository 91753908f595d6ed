"""The profile entry of a DYNAMIXEL chain: its keys, as fields of the one profile reader.

:data:`PROFILE_FIELDS` declares every key of a ``driver: dynamixel`` entry (besides ``driver``
and ``safe_state``) to :mod:`temoto.drivers.profile`; :func:`settings` turns the checked values
into :class:`~temoto.drivers.dynamixel.driver.DynamixelDriver` arguments and checks the keys
that depend on each other (the link's baud rate against ``baud``, the Bus Watchdog against the
poll rate). ``docs/driver-dynamixel.md`` lists the keys for people.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Final

from temoto.drivers.dynamixel import control_table as ct
from temoto.drivers.dynamixel import protocol as p
from temoto.drivers.dynamixel.servos import MODES, ServoConfig, ServoFieldError
from temoto.drivers.dynamixel.timing import return_delay_units, watchdog_units
from temoto.drivers.profile import Field, ProfileReader, custom, integer, number, text
from temoto.drivers.realism import SIM_KEYS, read_sim_realism

__all__ = ["BAUD_RATES", "LINK_HINT", "PROFILE_FIELDS", "read_link", "settings"]

#: Baud rates both the X series and dynamixel-sdk's port handler support.
BAUD_RATES: Final = frozenset({9600, 57600, 115200, 1_000_000, 2_000_000, 3_000_000, 4_000_000})
#: What to write when ``link`` is missing.
LINK_HINT: Final = "e.g. 'serial:/dev/ttyUSB0?baud=57600'"
_DEFAULT_BAUD: Final = 57600

_SERVO_KEYS: Final = frozenset(
    {
        "id",
        "joint",
        "model",
        "mode",
        "min_position",
        "max_position",
        "velocity_limit",
        "effort_limit",
        "gear",
        "offset",
        "torque_constant",
    }
)
_SERVO_NUMBERS: Final = (
    "min_position",
    "max_position",
    "velocity_limit",
    "effort_limit",
    "gear",
    "offset",
    "torque_constant",
)
_ANY_NUMBER: Final = number(low=None)


def read_link(reader: ProfileReader, link: object, key: str) -> tuple[str, int | None]:
    """A chain's ``link``: ``serial:<absolute device path>[?baud=<rate>]`` or a bare path.

    Args:
        reader: Where errors are raised.
        link: The value.
        key: Its key path.

    Returns:
        ``(device path, baud rate or None)``.

    Raises:
        ProfileError: Not a serial link, a relative path, an unknown option or a bad baud rate.
    """
    if not isinstance(link, str) or not link:
        reader.fail(key, "must be a string like 'serial:/dev/ttyUSB0?baud=57600'")
    rest = link
    if ":" in link.split("/", 1)[0]:
        scheme, _, rest = link.partition(":")
        if scheme != "serial":
            reader.fail(key, f"a Dynamixel chain needs a serial link, not {scheme!r}")
    path, _, query = rest.partition("?")
    if not path.startswith("/"):
        reader.fail(key, f"the serial device must be an absolute path, got {path!r}")
    baud: int | None = None
    for part in filter(None, query.split("&")):
        option, _, value = part.partition("=")
        if option != "baud":
            reader.fail(key, f"unknown link option {option!r} (known: baud)")
        if not value.isdigit():
            reader.fail(key, f"baud must be an integer, got {value!r}")
        baud = int(value)
        if baud not in BAUD_RATES:
            reader.fail(key, f"baud must be one of {sorted(BAUD_RATES)}, got {baud}")
    return path, baud


def _read_baud(reader: ProfileReader, value: object, key: str) -> int:
    if not isinstance(value, int) or isinstance(value, bool) or value not in BAUD_RATES:
        reader.fail(key, f"must be one of {sorted(BAUD_RATES)}, got {value!r}")
    return value


def _read_servo(reader: ProfileReader, entry: Mapping[str, Any], at: str) -> ServoConfig:
    reader.known(entry, _SERVO_KEYS, at)
    dxl_id = reader.field(entry, "id", integer(low=0, high=p.MAX_ID), at)
    joint = reader.field(entry, "joint", text(), at)
    model = entry.get("model")
    if model is None:
        reader.fail(f"{at}.model", f"missing (known: {', '.join(ct.MODELS)})")
    if model not in ct.MODELS:
        reader.fail(f"{at}.model", f"unknown model {model!r} (known: {', '.join(ct.MODELS)})")
    mode = entry.get("mode", "position")
    if mode not in MODES:
        reader.fail(f"{at}.mode", f"unknown mode {mode!r} (known: {', '.join(MODES)})")
    floats = {k: reader.field(entry, k, _ANY_NUMBER, at) for k in _SERVO_NUMBERS if k in entry}
    limits = mode == "position" and ("min_position" in floats or "max_position" in floats)
    try:
        return ServoConfig(
            id=dxl_id, joint=joint, model=model, mode=mode, write_limits=limits, **floats
        )
    except ServoFieldError as err:
        reader.fail(f"{at}.{err.key}", str(err))


def _read_servos(reader: ProfileReader, value: object, key: str) -> list[ServoConfig]:
    parsed: list[ServoConfig] = []
    ids: dict[int, int] = {}
    joints: dict[str, int] = {}
    for i, entry in enumerate(reader.items(value, key)):
        at = f"{key}[{i}]"
        servo = _read_servo(reader, entry, at)
        if servo.id in ids:
            reader.fail(f"{at}.id", f"duplicate id {servo.id} (also servos[{ids[servo.id]}])")
        if servo.joint in joints:
            reader.fail(
                f"{at}.joint",
                f"duplicate joint {servo.joint!r} (also servos[{joints[servo.joint]}])",
            )
        ids[servo.id] = i
        joints[servo.joint] = i
        parsed.append(servo)
    return parsed


def _read_sim(reader: ProfileReader, value: object, key: str) -> dict[str, Any] | None:
    """An entry's ``sim`` mapping: the simulator's ``realism`` and ``seed`` (nothing else)."""
    if value is None:
        return None
    sim = dict(reader.mapping(value, key))
    for name in sim:
        if name not in SIM_KEYS:
            reader.fail(f"{key}.{name}", "unknown; the simulator's settings are realism, seed")
    read_sim_realism(reader, sim)
    return sim


#: The keys of a chain's entry, in the order they are checked.
PROFILE_FIELDS: Final[Mapping[str, Field[Any]]] = {
    "sim": custom(_read_sim, None, init=False),  # the simulator's
    "link": custom(read_link, hint=LINK_HINT, init=False),
    "baud": custom(_read_baud, None),
    "poll_rate": number(50.0, low=0, high=1000, unit="Hz"),
    "reply_timeout": number(0.034, low=0, high=1, unit="s"),
    "status_every": integer(10, low=1),
    "timeout_polls": integer(3, low=1),
    "bus_watchdog": number(None, low=None, describe="a number of seconds"),
    "return_delay_time": number(None, low=None, describe="a number of seconds"),
    "servos": custom(_read_servos, hint="a non-empty list of servos"),
}


def settings(values: Mapping[str, Any], init: Mapping[str, Any], where: str) -> dict[str, Any]:
    """The driver's keyword arguments from a checked entry.

    Args:
        values: Every field's checked value (:meth:`~temoto.drivers.base.Driver.read_profile`).
        init: The fields that are constructor arguments as they are.
        where: The entry's place for messages.

    Returns:
        ``port``, ``baud`` and the other constructor arguments.

    Raises:
        ProfileError: ``baud`` contradicts the link's, or ``bus_watchdog`` or
            ``return_delay_time`` is out of its register's range (or shorter than two polls).
    """
    reader = ProfileReader.at(where)
    port, link_baud = values["link"]
    baud = values["baud"]
    if baud is None:
        baud = link_baud if link_baud is not None else _DEFAULT_BAUD
    elif link_baud is not None and baud != link_baud:
        reader.fail("baud", f"{baud} contradicts the link's baud={link_baud}")
    out = {**init, "port": port, "baud": baud}
    try:
        if out["bus_watchdog"] is not None:
            watchdog_units(out["bus_watchdog"], 1.0 / out["poll_rate"])
    except ValueError as err:
        reader.fail("bus_watchdog", str(err))
    try:
        return_delay_units(out["return_delay_time"])
    except ValueError as err:
        reader.fail("return_delay_time", str(err))
    return out
