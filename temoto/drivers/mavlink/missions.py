"""Missions and parameters on the MAVLink wire: MissionItem ↔ MISSION_ITEM_INT, typed values.

Pure functions for :class:`~temoto.drivers.mavlink.driver.MavlinkDriver`'s mission and parameter
microservices (no I/O, no threads): how each :class:`~temoto.drivers.capabilities.MissionItem`
kind goes into a MISSION_ITEM_INT as ArduCopter reads its parameters, and back; ArduPilot's
home item 0; which answers end a mission-transfer step; a PARAM_VALUE's value typed by its
``MAV_PARAM_TYPE`` and the values a parameter type can hold.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, Final

from temoto.drivers.capabilities import MissionItem
from temoto.drivers.mavlink import protocol as p
from temoto.drivers.mavlink.protocol import Message
from temoto.errors import DriverOperationError

__all__ = [
    "ITEM_COMMANDS",
    "MISSION_MESSAGES",
    "TRANSFER_MESSAGES",
    "ack_answer",
    "check_param_value",
    "count_answer",
    "decoded_item",
    "home_fields",
    "item_answer",
    "item_fields",
    "typed_param_value",
    "upload_answer",
]

#: Mission-transfer messages kept for the mission waiters (the rest is progress).
TRANSFER_MESSAGES: Final = frozenset(
    {"MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_ACK", "MISSION_COUNT", "MISSION_ITEM_INT"}
)
MISSION_MESSAGES: Final = TRANSFER_MESSAGES | {"MISSION_CURRENT", "MISSION_ITEM_REACHED"}


def upload_answer(msg: Message) -> bool:
    """Whether ``msg`` answers an upload step (a request for an item, or the ack).

    Args:
        msg: A mission-transfer message from the vehicle.

    Returns:
        True for MISSION_REQUEST_INT, MISSION_REQUEST and MISSION_ACK.
    """
    return msg.name in ("MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_ACK")


def count_answer(msg: Message) -> bool:
    """Whether ``msg`` answers MISSION_REQUEST_LIST (MISSION_COUNT).

    Args:
        msg: A mission-transfer message from the vehicle.

    Returns:
        True for MISSION_COUNT.
    """
    return msg.name == "MISSION_COUNT"


def ack_answer(msg: Message) -> bool:
    """Whether ``msg`` is a MISSION_ACK.

    Args:
        msg: A mission-transfer message from the vehicle.

    Returns:
        True for MISSION_ACK.
    """
    return msg.name == "MISSION_ACK"


def item_answer(seq: int) -> Callable[[Message], bool]:
    """The test for the answer to MISSION_REQUEST_INT ``seq`` of a download.

    Args:
        seq: The item asked for.

    Returns:
        A predicate, true for the MISSION_ITEM_INT of that item.
    """

    def accept(msg: Message) -> bool:
        return msg.name == "MISSION_ITEM_INT" and msg.get_int("seq") == seq

    return accept


#: MissionItem kind → its MAV_CMD.
ITEM_COMMANDS: Final[Mapping[str, int]] = {
    "takeoff": p.MAV_CMD_NAV_TAKEOFF,
    "waypoint": p.MAV_CMD_NAV_WAYPOINT,
    "loiter_time": p.MAV_CMD_NAV_LOITER_TIME,
    "speed": p.MAV_CMD_DO_CHANGE_SPEED,
    "land": p.MAV_CMD_NAV_LAND,
    "rtl": p.MAV_CMD_NAV_RETURN_TO_LAUNCH,
}
ITEM_KINDS: Final[Mapping[int, str]] = {command: kind for kind, command in ITEM_COMMANDS.items()}


def home_fields(home: tuple[float, float, float] | None) -> dict[str, Any]:
    """Item 0, ArduPilot's home: the home position (AMSL) when known, else zeros.

    Args:
        home: Latitude, longitude (degrees), altitude AMSL (m), or None.

    Returns:
        MISSION_ITEM_INT fields (without ids, sequence and flags).
    """
    lat, lon, alt = home if home is not None else (0.0, 0.0, 0.0)
    return {
        "frame": int(p.MAV_FRAME_GLOBAL),
        "command": p.MAV_CMD_NAV_WAYPOINT,
        "param1": 0.0,
        "param2": 0.0,
        "param3": 0.0,
        "param4": 0.0,
        "x": p.deg_e7(lat),
        "y": p.deg_e7(lon),
        "z": float(alt),
    }


def item_fields(item: MissionItem) -> dict[str, Any]:
    """A MissionItem as MISSION_ITEM_INT fields (ArduCopter's use of each command's params).

    Args:
        item: The item.

    Returns:
        Frame, command, param1..4, x, y, z (positions in MAV_FRAME_GLOBAL_RELATIVE_ALT; a
        position left None as 0, 0: "where the vehicle is").
    """
    params = [0.0, 0.0, 0.0, 0.0]
    frame = p.MAV_FRAME_GLOBAL_RELATIVE_ALT
    if item.kind == "waypoint" or item.kind == "loiter_time":
        params[0] = item.seconds  # hold time / loiter time, s
    elif item.kind == "speed":
        params[:3] = [1.0, item.speed, -1.0]  # ground speed, m/s, throttle unchanged
    if item.kind in ("speed", "rtl"):
        frame = p.MAV_FRAME_MISSION
    return {
        "frame": frame,
        "command": ITEM_COMMANDS[item.kind],
        "param1": params[0],
        "param2": params[1],
        "param3": params[2],
        "param4": params[3],
        "x": 0 if item.lat is None else p.deg_e7(item.lat),
        "y": 0 if item.lon is None else p.deg_e7(item.lon),
        "z": 0.0 if item.alt is None else float(item.alt),
    }


def decoded_item(name: str, msg: Message, home: tuple[float, float, float] | None) -> MissionItem:
    """A downloaded MISSION_ITEM_INT as a MissionItem.

    Args:
        name: The driver's name (for messages).
        msg: The MISSION_ITEM_INT.
        home: The home position (for altitudes above sea level), or None.

    Returns:
        The item.

    Raises:
        DriverOperationError: A command or frame MissionItem cannot represent.
    """
    seq, command, frame = msg.get_int("seq"), msg.get_int("command"), msg.get_int("frame")
    kind = ITEM_KINDS.get(command)
    if kind is None:
        raise DriverOperationError(
            f"{name}: mission item {seq} is {p.command_name(command)}, which a MissionItem"
            f" cannot hold (kinds: {', '.join(ITEM_COMMANDS)})"
        )
    x, y, z = msg.get_int("x"), msg.get_int("y"), msg.get_float("z")
    lat, lon = (None, None) if x == 0 and y == 0 else (x / 1e7, y / 1e7)
    alt: float | None = z
    if kind in ("speed", "rtl"):
        lat = lon = alt = None
    elif frame in p.MAV_FRAME_GLOBAL_INT_FRAMES:
        if home is None:
            raise DriverOperationError(
                f"{name}: mission item {seq} has an altitude above sea level"
                f" ({p.enum_name('MAV_FRAME', frame)}) and the home position is unknown"
            )
        alt = z - home[2]
    elif frame not in p.MAV_FRAME_RELATIVE_FRAMES:
        raise DriverOperationError(
            f"{name}: mission item {seq} ({p.command_name(command)}) is in"
            f" {p.enum_name('MAV_FRAME', frame)}; only global frames are supported"
        )
    if kind == "land":
        alt = None
    elif kind == "takeoff":
        lat = lon = None
    elif kind == "loiter_time" and lat is None and alt == 0.0:
        alt = None
    seconds = msg.get_float("param1") if kind in ("waypoint", "loiter_time") else 0.0
    speed = msg.get_float("param2") if kind == "speed" else 0.0
    try:
        return MissionItem(kind, lat, lon, alt, seconds=seconds, speed=speed)
    except ValueError as err:
        raise DriverOperationError(f"{name}: mission item {seq}: {err}") from None


def typed_param_value(value: float, param_type: int) -> float | int:
    """A PARAM_VALUE's value as its MAV_PARAM_TYPE says (ArduPilot's float-carried ints).

    Args:
        value: The float of the PARAM_VALUE.
        param_type: Its MAV_PARAM_TYPE.

    Returns:
        An int for the integer types, else the float.
    """
    if param_type in p.PARAM_INT_RANGES:
        return round(value)
    return value


def check_param_value(name: str, value: float, param_type: int) -> None:
    """Check that ``value`` fits a parameter of ``param_type`` (as ArduPilot carries it).

    Args:
        name: The parameter (for messages).
        value: The value to set.
        param_type: Its MAV_PARAM_TYPE.

    Raises:
        ValueError: A fraction for an integer type, out of the type's range, beyond what a
            float32 carries exactly, or a type this driver does not set.
    """
    limits = p.PARAM_INT_RANGES.get(param_type)
    if limits is None:
        if param_type not in (p.MAV_PARAM_TYPE_REAL32, p.MAV_PARAM_TYPE_REAL64):
            raise ValueError(f"{name}: unsupported parameter type {p.param_type_name(param_type)}")
        return
    kind = p.param_type_name(param_type)
    if isinstance(value, float) and not value.is_integer():
        raise ValueError(f"{name} is an integer ({kind}), got {value!r}")
    low, high = limits
    if not low <= value <= high:
        raise ValueError(f"{name} ({kind}) must be {low}..{high}, got {value:g}")
    if abs(value) > p.FLOAT32_EXACT_INT:
        raise ValueError(
            f"{name}: {value:g} does not survive ArduPilot's float32 encoding of integer"
            f" parameters (at most {p.FLOAT32_EXACT_INT} in size)"
        )
