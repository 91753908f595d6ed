"""What the CAN motor drivers share: profile checks, opening the bus, joint limits."""

from __future__ import annotations

import math
import re
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Final

import can

from temoto.errors import DriverInitError, DriverUnavailableError, ProfileError

__all__ = ["JointLimits", "Profile", "check_limits", "open_bus"]

_NAME: Final = re.compile(r"^[A-Za-z][A-Za-z0-9_.-]{0,62}$")
_LINK_SCALARS: Final = (str, int, float, bool)


class Profile:
    """Reads one device entry and raises ``ProfileError("<where>.<key>: ...")``.

    Args:
        where: The entry's own key path (``sim_rover.yaml: devices.base``).
    """

    def __init__(self, where: str) -> None:
        self.where = where

    def fail(self, path: str, message: str) -> ProfileError:
        """The error for ``path`` (raise it).

        Args:
            path: The key path below the entry (``nodes[1].node_id``).
            message: What is wrong.

        Returns:
            The error.
        """
        where = f"{self.where}.{path}" if path else self.where
        return ProfileError(f"{where}: {message}")

    def mapping(self, value: object, path: str) -> Mapping[str, Any]:
        """``value`` as a mapping with text keys.

        Args:
            value: The value.
            path: Its key path.

        Returns:
            The mapping.

        Raises:
            ProfileError: Not a mapping.
        """
        if not isinstance(value, Mapping) or not all(isinstance(k, str) for k in value):
            raise self.fail(path, f"must be a mapping with text keys, got {value!r}")
        return value

    def known(self, value: Mapping[str, Any], keys: frozenset[str], path: str) -> None:
        """Raise for the first key of ``value`` not in ``keys``.

        Args:
            value: The mapping.
            keys: The allowed keys.
            path: Its key path ("" for the entry itself).

        Raises:
            ProfileError: An unknown key (named, with the known ones).
        """
        unknown = sorted(set(value) - keys)
        if unknown:
            where = f"{path}.{unknown[0]}" if path else unknown[0]
            raise self.fail(where, f"unknown key (known: {', '.join(sorted(keys))})")

    def entry(self, config: object, keys: frozenset[str], kind: str) -> Mapping[str, Any]:
        """A device entry checked as a whole: a mapping, known keys, its own ``driver``.

        Args:
            config: The entry.
            keys: The keys the driver knows.
            kind: The driver's name.

        Returns:
            The entry.

        Raises:
            ProfileError: Not a mapping, an unknown key, or another driver named.
        """
        cfg = self.mapping(config, "")
        self.known(cfg, keys, "")
        self.driver(cfg, kind)
        return cfg

    def driver(self, cfg: Mapping[str, Any], kind: str) -> None:
        """Check the entry's optional ``driver`` key: it may only name this driver.

        A profile's loader takes ``driver`` out before the driver reads the entry; an entry
        from :meth:`~temoto.drivers.base.Driver.detect` still has it.

        Args:
            cfg: The entry.
            kind: The driver's name.

        Raises:
            ProfileError: ``driver`` names another driver.
        """
        if cfg.get("driver", kind) != kind:
            raise self.fail("driver", f"must be {kind!r} for this driver, got {cfg['driver']!r}")

    def number(
        self,
        cfg: Mapping[str, Any],
        key: str,
        path: str,
        default: float,
        *,
        positive: bool = True,
    ) -> float:
        """An optional number.

        Args:
            cfg: The mapping holding it.
            key: Its key.
            path: The mapping's key path.
            default: When it is absent.
            positive: Whether it must be > 0.

        Returns:
            The value or the default.

        Raises:
            ProfileError: Not a (positive) finite number.
        """
        full = f"{path}.{key}" if path else key
        value = cfg.get(key)
        if value is None:
            return default
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise self.fail(full, f"must be a finite number, got {value!r}")
        if not math.isfinite(value):
            raise self.fail(full, f"must be a finite number, got {value!r}")
        if positive and value <= 0:
            raise self.fail(full, f"must be positive, got {value!r}")
        return float(value)

    def integer(self, cfg: Mapping[str, Any], key: str, path: str, lo: int, hi: int) -> int:
        """A required integer in ``lo..hi``.

        Args:
            cfg: The mapping holding it.
            key: Its key.
            path: The mapping's key path.
            lo: Smallest allowed.
            hi: Largest allowed.

        Returns:
            The value.

        Raises:
            ProfileError: Missing, not an integer or out of range.
        """
        full = f"{path}.{key}" if path else key
        value = cfg.get(key)
        if value is None:
            raise self.fail(full, "missing")
        if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
            raise self.fail(full, f"must be an integer {lo}..{hi}, got {value!r}")
        return value

    def name(self, cfg: Mapping[str, Any], key: str, path: str) -> str:
        """A required name (a joint's).

        Args:
            cfg: The mapping holding it.
            key: Its key.
            path: The mapping's key path.

        Returns:
            The name.

        Raises:
            ProfileError: Missing or not a name.
        """
        full = f"{path}.{key}" if path else key
        value = cfg.get(key)
        if value is None:
            raise self.fail(full, "missing: every node needs a joint name")
        if not isinstance(value, str) or not _NAME.match(value):
            raise self.fail(
                full, f"must be a name (a letter, then letters, digits, _.-): {value!r}"
            )
        return value

    def link(self, cfg: Mapping[str, Any]) -> dict[str, Any]:
        """The ``link`` mapping: python-can ``Bus`` keyword arguments.

        Args:
            cfg: The device entry.

        Returns:
            The keyword arguments (``interface`` and ``channel`` at least).

        Raises:
            ProfileError: Missing, or not a mapping of scalars with an interface and channel.
        """
        if "link" not in cfg:
            raise self.fail("link", "missing: e.g. {interface: socketcan, channel: can0}")
        link = dict(self.mapping(cfg["link"], "link"))
        for key in ("interface", "channel"):
            value = link.get(key)
            if not isinstance(value, str | int) or isinstance(value, bool) or value == "":
                raise self.fail(f"link.{key}", f"missing or not a text/number: {value!r}")
        for key, value in link.items():
            if not isinstance(value, _LINK_SCALARS):
                raise self.fail(f"link.{key}", f"must be a scalar, got {value!r}")
        return link

    def items(self, cfg: Mapping[str, Any], key: str) -> Sequence[Mapping[str, Any]]:
        """A required non-empty list of mappings (``nodes``, ``motors``).

        Args:
            cfg: The device entry.
            key: The list's key.

        Returns:
            The mappings.

        Raises:
            ProfileError: Missing, empty or not a list of mappings.
        """
        raw = cfg.get(key)
        if not isinstance(raw, list | tuple) or not raw:
            raise self.fail(key, f"must be a non-empty list, got {raw!r}")
        return [self.mapping(item, f"{key}[{i}]") for i, item in enumerate(raw)]

    def members(
        self,
        cfg: Mapping[str, Any],
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
            cfg: The device entry.
            key: The list's key (``nodes``, ``motors``).
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
        for i, member in enumerate(self.items(cfg, key)):
            path = f"{key}[{i}]"
            self.known(member, keys, path)
            bus_id = self.integer(member, id_key, path, *id_range)
            if bus_id in ids:
                raise self.fail(f"{path}.{id_key}", f"duplicate {id_word} {bus_id} ({ids[bus_id]})")
            joint = self.name(member, "joint", path)
            if joint in joints:
                raise self.fail(f"{path}.joint", f"duplicate joint {joint!r} ({joints[joint]})")
            ids[bus_id], joints[joint] = path, path
            yield path, member, bus_id, joint

    def limits(self, cfg: Mapping[str, Any], path: str) -> JointLimits:
        """The joint-side limits of one node or motor.

        Args:
            cfg: The node's mapping.
            path: Its key path.

        Returns:
            The limits.

        Raises:
            ProfileError: A bad number, or ``position_min >= position_max``.
        """
        lo = self.number(cfg, "position_min", path, -math.inf, positive=False)
        hi = self.number(cfg, "position_max", path, math.inf, positive=False)
        if lo >= hi:
            raise self.fail(f"{path}.position_min", f"must be below position_max ({lo} >= {hi})")
        vel = self.number(cfg, "velocity_limit", path, math.inf)
        torque = self.number(cfg, "torque_limit", path, math.inf)
        return JointLimits(lo, hi, vel, torque)


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
