"""What the CAN motor drivers share: the profile reader's CAN parts, the bus, joint limits."""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any, Final

import can

from temoto.drivers.profile import ProfileReader, integer, name, number
from temoto.errors import DriverInitError, DriverUnavailableError

__all__ = [
    "LINK_HINT",
    "JointLimits",
    "check_limits",
    "open_bus",
    "read_limits",
    "read_link",
    "read_members",
]

_LINK_SCALARS: Final = (str, int, float, bool)


#: The ``link`` of a CAN entry when it is missing: what to write.
LINK_HINT: Final = "e.g. {interface: socketcan, channel: can0}"


def read_link(reader: ProfileReader, value: object, key: str = "link") -> dict[str, Any]:
    """A ``link`` mapping: python-can ``Bus`` keyword arguments.

    Args:
        reader: Where errors are raised.
        value: The value.
        key: Its key path.

    Returns:
        The keyword arguments (``interface`` and ``channel`` at least).

    Raises:
        ProfileError: Not a mapping of scalars with an interface and a channel.
    """
    link = dict(reader.mapping(value, key))
    for part in ("interface", "channel"):
        item = link.get(part)
        if not isinstance(item, str | int) or isinstance(item, bool) or item == "":
            reader.fail(f"{key}.{part}", f"missing or not a text/number: {item!r}")
    for part, item in link.items():
        if not isinstance(item, _LINK_SCALARS):
            reader.fail(f"{key}.{part}", f"must be a scalar, got {item!r}")
    return link


def read_members(
    reader: ProfileReader,
    value: object,
    key: str,
    keys: frozenset[str],
    id_key: str,
    id_range: tuple[int, int],
    *,
    id_word: str = "id",
    reserved: Mapping[int, str] | None = None,
) -> Iterator[tuple[str, Mapping[str, Any], int, str]]:
    """The motors of a bus entry, each checked: known keys, a unique id, a unique joint.

    Args:
        reader: Where errors are raised.
        value: The list (``nodes``, ``motors``).
        key: Its key.
        keys: The keys a member may have.
        id_key: The member's bus id key (``node_id``, ``motor_id``).
        id_range: The lowest and highest id allowed.
        id_word: How messages call the id (``node id``).
        reserved: Ids taken by something else, with what takes them (``host_id``).

    Yields:
        ``(path, member, id, joint)`` for each member, in order.

    Raises:
        ProfileError: The first problem, naming its key path.
    """
    ids: dict[int, str] = dict(reserved or {})
    joints: dict[str, str] = {}
    bus_id_field = integer(low=id_range[0], high=id_range[1])
    for i, member in enumerate(reader.items(value, key)):
        path = f"{key}[{i}]"
        reader.known(member, keys, path)
        bus_id = reader.field(member, id_key, bus_id_field, path)
        if bus_id in ids:
            reader.fail(f"{path}.{id_key}", f"duplicate {id_word} {bus_id} ({ids[bus_id]})")
        joint = reader.field(member, "joint", _JOINT, path)
        if joint in joints:
            reader.fail(f"{path}.joint", f"duplicate joint {joint!r} ({joints[joint]})")
        ids[bus_id], joints[joint] = path, path
        yield path, member, bus_id, joint


def read_limits(reader: ProfileReader, cfg: Mapping[str, Any], path: str) -> JointLimits:
    """The joint-side limits of one node or motor.

    Args:
        reader: Where errors are raised.
        cfg: The node's mapping.
        path: Its key path.

    Returns:
        The limits.

    Raises:
        ProfileError: A bad number, or ``position_min >= position_max``.
    """
    lo = reader.field(cfg, "position_min", number(-math.inf, low=None), path)
    hi = reader.field(cfg, "position_max", number(math.inf, low=None), path)
    if lo >= hi:
        reader.fail(f"{path}.position_min", f"must be below position_max ({lo} >= {hi})")
    vel = reader.field(cfg, "velocity_limit", number(math.inf), path)
    torque = reader.field(cfg, "torque_limit", number(math.inf), path)
    return JointLimits(lo, hi, vel, torque)


_JOINT: Final = name(hint="every node needs a joint name")


@dataclass(frozen=True, slots=True)
class JointLimits:
    """Joint-side limits a command must respect (rad, rad/s, N·m; infinite = none).

    Attributes:
        position_min: rad.
        position_max: rad.
        velocity: Largest |velocity| set-point, rad/s.
        torque: Largest |torque| set-point, N·m.
    """

    position_min: float = -math.inf
    position_max: float = math.inf
    velocity: float = math.inf
    torque: float = math.inf


def check_limits(joint: str, limits: JointLimits, mode: str, value: float) -> None:
    """Raise ``ValueError`` when a set-point is outside the joint's limits.

    Args:
        joint: The joint, for the message.
        limits: Its limits.
        mode: ``position``, ``velocity`` or ``effort``.
        value: The set-point (SI).

    Raises:
        ValueError: Out of limits.
    """
    if mode == "position":
        if not limits.position_min <= value <= limits.position_max:
            raise ValueError(
                f"joint {joint}: position {value} rad outside"
                f" [{limits.position_min}, {limits.position_max}]"
            )
    elif mode == "velocity":
        if abs(value) > limits.velocity:
            raise ValueError(f"joint {joint}: |velocity| {value} rad/s above {limits.velocity}")
    elif abs(value) > limits.torque:
        raise ValueError(f"joint {joint}: |effort| {value} N·m above {limits.torque}")


def open_bus(link: Mapping[str, Any], what: str) -> can.BusABC:
    """Open a python-can bus from a profile's ``link`` keyword arguments.

    Args:
        link: ``interface``, ``channel`` and any other ``can.Bus`` arguments.
        what: The device, for messages.

    Returns:
        The open bus.

    Raises:
        DriverUnavailableError: The interface or its library is missing.
        DriverInitError: The bus could not be opened.
    """
    try:
        return can.Bus(**dict(link))
    except (ImportError, NotImplementedError) as err:
        interface = link.get("interface")
        raise DriverUnavailableError(f"{what}: CAN interface {interface!r}: {err}") from err
    except (can.CanError, OSError, ValueError, TypeError) as err:
        raise DriverInitError(f"{what}: cannot open CAN bus {dict(link)}: {err}") from err
