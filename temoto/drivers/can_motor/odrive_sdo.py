"""ODrive 0.6 parameter access over CAN (``RxSdo`` / ``TxSdo``) and the endpoints read with it.

CANSimple has no message that reports how an axis is configured (its velocity limit, current
limits, torque constant). ODrive 0.6 reads and writes any property of the device over CAN by
its *endpoint id*, the number the firmware release's ``flat_endpoints.json`` gives each path:

* ``RxSdo`` (cmd 0x04, host → ODrive), 8 bytes: ``Opcode`` u8 (0 read, 1 write),
  ``Endpoint_ID`` u16, ``Reserved`` u8, ``Value`` 4 bytes (a write's value, little-endian in the
  endpoint's type; 0 for a read);
* ``TxSdo`` (cmd 0x05, ODrive → host), the answer to a read: ``Reserved0`` u8, ``Endpoint_ID``
  u16, ``Reserved1`` u8, ``Value`` 4 bytes.

Sources: the official DBC ``odrive-cansimple-0.6.10.dbc`` (signals and bit positions of both
messages; the tests decode these frames with it) and ODrive's example
``examples/can_param_access.py`` (odriverobotics/ODriveResources: opcodes 0/1, the ``<BHB``
prefix, the value packed after it; ``flat_endpoints.json`` checked against ``Get_Version``'s
firmware *and* hardware version, since the ids differ between releases and boards; a write is
confirmed by a ``TxSdo`` only from firmware 0.6.11 on). What firmware does with an endpoint id
it does not have is not documented: the simulator sends nothing, and the driver's read of it
times out (named).

The ids TeMoto knows (:data:`KNOWN_ENDPOINTS`) are those of the version the simulator reports
(``Get_Version``: firmware 0.6.10, hardware 4.4-58, an ODrive Pro). They come from a public
endpoint map (the generated ``endpointIdMap`` of a TypeScript ODrive CAN library, which does not
say its firmware version); ODrive's released ``flat_endpoints.json`` for 0.6.10 could not be
consulted when this was written. For other firmware, or to be sure, give the driver the
release's own file (profile key ``flat_endpoints``, :func:`load_flat_endpoints`).

No I/O here: frames are bytes.
"""

from __future__ import annotations

import json
import math
import struct
from collections.abc import Mapping
from pathlib import Path
from typing import Final, NamedTuple

from temoto.drivers.can_motor import cansimple as cs

__all__ = [
    "CURRENT_SOFT_MAX",
    "KNOWN_ENDPOINTS",
    "LIMIT_PATHS",
    "OPCODE_READ",
    "OPCODE_WRITE",
    "TORQUE_CONSTANT",
    "VEL_LIMIT",
    "Endpoint",
    "decode_rxsdo",
    "decode_txsdo",
    "encode_rxsdo",
    "encode_txsdo",
    "finite_positive",
    "float_value",
    "limit_problems",
    "load_flat_endpoints",
    "read_float",
    "version_key",
]

#: ``RxSdo`` opcodes.
OPCODE_READ: Final = 0
OPCODE_WRITE: Final = 1

_SDO: Final = struct.Struct("<BHB4s")  # opcode (or reserved), endpoint id, reserved, value
_F32: Final = struct.Struct("<f")

#: The endpoints the driver reads to check a profile's limits (axis 0: one axis per board).
VEL_LIMIT: Final = "axis0.controller.config.vel_limit"  # turn/s: what the controller allows
CURRENT_SOFT_MAX: Final = "axis0.config.motor.current_soft_max"  # A: what it commands at most
TORQUE_CONSTANT: Final = "axis0.config.motor.torque_constant"  # N·m per A
LIMIT_PATHS: Final = (VEL_LIMIT, CURRENT_SOFT_MAX, TORQUE_CONSTANT)


class Endpoint(NamedTuple):
    """One property of the device: its id and its type as ``flat_endpoints.json`` names them."""

    id: int
    type: str


def version_key(version: cs.Version) -> tuple[str, str]:
    """``(firmware, hardware)`` of a ``Get_Version`` as ``flat_endpoints.json`` spells them.

    Args:
        version: The decoded ``Get_Version``.

    Returns:
        ``("0.6.10", "4.4.58")``; an unreleased firmware keeps its ``-dev`` (its ids are not
        a release's).
    """
    return version.firmware, f"{version.hw_major}.{version.hw_minor}.{version.hw_variant}"


#: Endpoint ids known for a ``(firmware, hardware)`` (see the module docstring for the source).
KNOWN_ENDPOINTS: Final[Mapping[tuple[str, str], Mapping[str, Endpoint]]] = {
    ("0.6.10", "4.4.58"): {
        VEL_LIMIT: Endpoint(388, "float"),
        CURRENT_SOFT_MAX: Endpoint(271, "float"),
        TORQUE_CONSTANT: Endpoint(259, "float"),
        "axis0.config.motor.current_hard_max": Endpoint(272, "float"),
    },
}


def encode_rxsdo(opcode: int, endpoint_id: int, value: bytes = b"\0\0\0\0") -> bytes:
    """An ``RxSdo`` payload (8 bytes).

    Args:
        opcode: :data:`OPCODE_READ` or :data:`OPCODE_WRITE`.
        endpoint_id: 0..65535.
        value: The value's 4 bytes (a read sends zeros).

    Returns:
        The payload.

    Raises:
        ValueError: An opcode, id or value that does not fit.
    """
    if opcode not in (OPCODE_READ, OPCODE_WRITE):
        raise ValueError(f"RxSdo opcode must be 0 (read) or 1 (write), got {opcode}")
    if not 0 <= endpoint_id <= 0xFFFF:
        raise ValueError(f"endpoint id must fit in 16 bits, got {endpoint_id}")
    if len(value) != 4:
        raise ValueError(f"an RxSdo value is 4 bytes, got {len(value)}")
    return _SDO.pack(opcode, endpoint_id, 0, value)


def decode_rxsdo(data: bytes | bytearray) -> tuple[int, int, bytes]:
    """Parse an ``RxSdo`` payload.

    Args:
        data: 8 bytes.

    Returns:
        ``(opcode, endpoint_id, value bytes)``.

    Raises:
        ValueError: Wrong length.
    """
    if len(data) != 8:
        raise ValueError(f"RxSdo: expected 8 data bytes, got {len(data)}")
    opcode, endpoint_id, _, value = _SDO.unpack(data)
    return int(opcode), int(endpoint_id), bytes(value)


def encode_txsdo(endpoint_id: int, value: bytes) -> bytes:
    """A ``TxSdo`` payload (8 bytes: reserved, endpoint id, reserved, value).

    Args:
        endpoint_id: 0..65535.
        value: 4 bytes.

    Returns:
        The payload.

    Raises:
        ValueError: An id or value that does not fit.
    """
    if not 0 <= endpoint_id <= 0xFFFF:
        raise ValueError(f"endpoint id must fit in 16 bits, got {endpoint_id}")
    if len(value) != 4:
        raise ValueError(f"a TxSdo value is 4 bytes, got {len(value)}")
    return _SDO.pack(0, endpoint_id, 0, value)


def decode_txsdo(data: bytes | bytearray) -> tuple[int, bytes]:
    """Parse a ``TxSdo`` payload.

    Args:
        data: 8 bytes.

    Returns:
        ``(endpoint_id, value bytes)``.

    Raises:
        ValueError: Wrong length.
    """
    if len(data) != 8:
        raise ValueError(f"TxSdo: expected 8 data bytes, got {len(data)}")
    _, endpoint_id, _, value = _SDO.unpack(data)
    return int(endpoint_id), bytes(value)


def float_value(value: float) -> bytes:
    """The 4 bytes of a ``float`` endpoint's value (float32, little-endian)."""
    return _F32.pack(value)


def read_float(value: bytes) -> float:
    """A ``float`` endpoint's value from its 4 bytes."""
    return float(_F32.unpack(value)[0])


def load_flat_endpoints(path: str | Path) -> tuple[tuple[str, str], dict[str, Endpoint]]:
    """The ids of a firmware release's ``flat_endpoints.json`` (ODrive's releases page).

    Args:
        path: The file.

    Returns:
        ``((fw_version, hw_version), {path: Endpoint})`` for the endpoints the driver reads
        (each must be there, of type ``float``).

    Raises:
        ValueError: The file cannot be read, is not such a file, or lacks an endpoint (the
            message names it).
    """
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ValueError(f"cannot read {path}: {err}") from None
    if not isinstance(data, dict) or not isinstance(data.get("endpoints"), dict):
        raise ValueError(f"{path} has no 'endpoints' mapping (not a flat_endpoints.json)")
    fw, hw = data.get("fw_version"), data.get("hw_version")
    if not isinstance(fw, str) or not isinstance(hw, str):
        raise ValueError(f"{path} names no fw_version and hw_version")
    found: dict[str, Endpoint] = {}
    for name in LIMIT_PATHS:
        entry = data["endpoints"].get(name)
        ok = isinstance(entry, dict) and isinstance(entry.get("id"), int)
        if not ok or entry.get("type") != "float":
            raise ValueError(f"{path} has no float endpoint {name}")
        found[name] = Endpoint(int(entry["id"]), "float")
    return (fw, hw), found


def finite_positive(value: float) -> bool:
    """Whether a value read from the device is a usable limit (finite, > 0)."""
    return math.isfinite(value) and value > 0


#: Relative slack for float32 rounding when a profile limit is compared with the device's.
_SLACK: Final = 1e-6


def limit_problems(
    node_id: int,
    joint: str,
    gear_ratio: float,
    velocity: float,
    torque: float,
    values: Mapping[str, float],
) -> list[tuple[str, str]]:
    """A node's profile limits against its device's settings; the problems as (key, text).

    ``velocity_limit`` (rad/s at the joint) must not exceed ``vel_limit`` (turn/s at the
    motor: the controller clamps every velocity set-point to it); ``torque_limit`` (N·m at the
    joint) must not exceed ``torque_constant`` x ``current_soft_max`` (the most torque the
    current limit lets the motor make). An infinite profile limit (none set) is not checked; a
    device value that is not positive (or NaN) cannot be checked and is a problem itself.

    Args:
        node_id: The node, for messages.
        joint: Its joint, for messages.
        gear_ratio: Motor turns per joint turn.
        velocity: The profile's ``velocity_limit``, rad/s (inf: none).
        torque: The profile's ``torque_limit``, N·m (inf: none).
        values: ``{endpoint path: value}`` read from the device (:data:`LIMIT_PATHS`).

    Returns:
        ``[("velocity_limit" | "torque_limit", what is wrong), ...]``.
    """
    who = f"node {node_id} ({joint})"
    problems: list[tuple[str, str]] = []
    if math.isfinite(velocity):
        device = values[VEL_LIMIT]
        motor = velocity * gear_ratio / (2.0 * math.pi)
        if not device > 0:
            problems.append(("velocity_limit", f"{who} reports vel_limit {device:g}: cannot check"))
        elif motor > device * (1.0 + _SLACK):
            most = device * 2.0 * math.pi / gear_ratio
            problems.append(
                (
                    "velocity_limit",
                    f"{velocity:g} rad/s is {motor:.4g} turn/s at the motor (gear_ratio"
                    f" {gear_ratio:g}), above the {device:.4g} turn/s {who} is configured for"
                    f" ({VEL_LIMIT}, read over CAN): at most {most:.4g} rad/s, or raise the"
                    " device's vel_limit",
                )
            )
    if math.isfinite(torque):
        kt, amps = values[TORQUE_CONSTANT], values[CURRENT_SOFT_MAX]
        motor = torque / gear_ratio
        if not (kt > 0 and amps > 0):
            problems.append(
                (
                    "torque_limit",
                    f"{who} reports torque_constant {kt:g}, current_soft_max"
                    f" {amps:g}: cannot check",
                )
            )
        elif motor > kt * amps * (1.0 + _SLACK):
            most = kt * amps * gear_ratio
            problems.append(
                (
                    "torque_limit",
                    f"{torque:g} N·m is {motor:.4g} N·m at the motor (gear_ratio"
                    f" {gear_ratio:g}), above the {kt * amps:.4g} N·m {who} can make"
                    f" (torque_constant {kt:g} N·m/A x current_soft_max {amps:g} A, read over"
                    f" CAN): at most {most:.4g} N·m, or raise the device's current_soft_max",
                )
            )
    return problems
