"""Encoding and decoding of the inner fleet messages, the payloads of ``envelope_t``.

Every inner message is one of the generated classes of :mod:`temoto.lcm_types` whose first
field is ``int16_t version`` (docs/fleet.md lists them by channel). An envelope names its
payload's type, so a receiver decodes with::

    name, payload = encode(msg)           # sender: envelope.type = name, envelope.payload = ...
    msg = decode(envelope.type, envelope.payload)

:func:`decode` is strict: an unknown type, bytes of another type or of another definition of
the type (LCM fingerprint), a truncated payload, bytes after the end of the message, a negative
array size and an unknown version all raise :class:`~temoto.errors.DecodeError`, which the
receiver counts and drops. Each type has its version (:data:`VERSIONS`): a type whose format
changes gets a new version and a new LCM fingerprint, and a payload of another version is
refused naming both versions.

This module is the only hand-written code about the generated types (docs/development.md §8).
"""

from __future__ import annotations

import io
import struct
from typing import Any

import temoto.lcm_types as lcm_types
from temoto.errors import DecodeError

__all__ = ["TYPES", "VERSION", "VERSIONS", "UnsupportedVersion", "decode", "encode"]

#: The format version of the envelope and of every inner message not in :data:`VERSIONS`.
VERSION = 1

#: Inner messages whose format changed since :data:`VERSION`, and their version now:
#: ``handshake_t`` 2 (the actor list as one string, the heard list as stamps by place).
_CHANGED = {"handshake_t": 2}

#: The LCM fingerprints of the earlier versions of changed types, so that a message of an
#: older release is refused as that version (and said so), not as some unknown payload.
_EARLIER: dict[bytes, tuple[str, int]] = {
    bytes.fromhex("253b31dc311612e4"): ("handshake_t", 1),
}

#: The generated envelope; it carries inner messages but is not one.
_ENVELOPE = "envelope_t"


def _inner_types() -> dict[str, type[Any]]:
    """Find the inner message classes: generated classes whose first field is ``version``.

    Nested structs (``node_state_t``, ``ris_server_t``) have no version
    field and travel only inside an inner message.
    """
    found: dict[str, type[Any]] = {}
    for name, cls in sorted(vars(lcm_types).items()):
        if not isinstance(cls, type) or cls.__name__ != name or name == _ENVELOPE:
            continue
        if list(getattr(cls, "__slots__", ()))[:1] == ["version"]:
            found[name] = cls
    return found


#: Inner message classes by type name (the envelope's ``type``).
TYPES: dict[str, type[Any]] = _inner_types()

#: The version of each inner message (:func:`encode` writes it, :func:`decode` refuses any
#: other).
VERSIONS: dict[str, int] = {name: _CHANGED.get(name, VERSION) for name in TYPES}


class UnsupportedVersion(DecodeError):
    """A payload of a known type in a version this build does not speak (another release).

    Attributes:
        version: The payload's version.
        supported: The version this build speaks.
    """

    def __init__(self, message: str, *, version: int, supported: int) -> None:
        super().__init__(message)
        self.version = version
        self.supported = supported


class _Short(Exception):
    """A read past the end of the payload (internal to :func:`decode`)."""


class _ExactReader(io.BytesIO):
    """A byte stream whose reads return exactly the size asked for, or raise :class:`_Short`.

    The generated decoders read strings and byte arrays without checking the length they got,
    so a truncated payload would otherwise decode into shortened fields.
    """

    def read(self, size: int | None = -1, /) -> bytes:
        if size is None or size < 0:
            raise _Short(f"a read of undefined length ({size}) at byte {self.tell()}")
        start = self.tell()
        data = super().read(size)
        if len(data) != size:
            raise _Short(f"{size} bytes needed at byte {start}, {len(data)} left")
        return data


_ARRAYS: dict[type[Any], list[tuple[str, str, bool]]] = {}


def _arrays(msg: Any) -> list[tuple[str, str, bool]]:
    """The variable-size arrays of a message: (array field, size field, of structs) triples.

    Cached per class (the generated classes never change). Only arrays of structs are walked
    for nested arrays: a ``byte`` array of a few hundred stamps is not looked at item by item.
    """
    cls = type(msg)
    found = _ARRAYS.get(cls)
    if found is None:
        found = [
            (slot, dims[0], "." in typename)
            for slot, typename, dims in zip(
                msg.__slots__, msg.__typenames__, msg.__dimensions__, strict=True
            )
            if dims is not None and isinstance(dims[0], str)
        ]
        _ARRAYS[cls] = found
    return found


def _fill_sizes(msg: Any) -> None:
    """Set every array's size field from the array's length, in nested structs too."""
    for field, size_field, structs in _arrays(msg):
        items = getattr(msg, field)
        setattr(msg, size_field, len(items))
        if structs:
            for item in items:
                if hasattr(item, "__dimensions__"):
                    _fill_sizes(item)


def _negative_size(msg: Any) -> str | None:
    """The first size field holding a negative number, in nested structs too, or None."""
    for field, size_field, structs in _arrays(msg):
        if getattr(msg, size_field) < 0:
            return f"{size_field} = {getattr(msg, size_field)}"
        if not structs:
            continue
        for item in getattr(msg, field):
            if hasattr(item, "__dimensions__") and (bad := _negative_size(item)) is not None:
                return f"{field}: {bad}"
    return None


def encode(msg: Any) -> tuple[str, bytes]:
    """Encode an inner message for an envelope.

    The message is updated in place first: its ``version`` becomes its type's version
    (:data:`VERSIONS`) and every
    array size field (``actors_count``, ...) the length of its array, so callers fill lists
    and never the counts.

    Args:
        msg: An instance of one of the classes in :data:`TYPES`.

    Returns:
        The type name (the envelope's ``type``) and the LCM-encoded bytes (its ``payload``).

    Raises:
        TypeError: If ``msg`` is not an inner message.
        ValueError: If a field does not fit its LCM type (a number out of range, a string
            field holding something else, a nested struct of the wrong type).
    """
    cls = type(msg)
    name = cls.__name__
    if TYPES.get(name) is not cls:
        raise TypeError(f"{name} is not an inner fleet message; expected one of {', '.join(TYPES)}")
    msg.version = VERSIONS[name]
    try:
        _fill_sizes(msg)
        data: bytes = msg.encode()
    except (struct.error, AttributeError, TypeError, IndexError, UnicodeError) as err:
        raise ValueError(f"cannot encode {name}: {err}") from err
    return name, data


def decode(type_name: str, payload: bytes) -> Any:
    """Decode an inner message.

    Args:
        type_name: The type's name, as the envelope's ``type`` carries it.
        payload: The LCM-encoded message.

    Returns:
        An instance of ``TYPES[type_name]``.

    Raises:
        DecodeError: For an unknown type name; a payload that is not this type as defined
            here (another type, or another definition of it); a truncated payload or bytes
            after its end; a negative array size. :class:`UnsupportedVersion` (a
            DecodeError) for a version other than the type's (:data:`VERSIONS`).
    """
    cls = TYPES.get(type_name)
    if cls is None:
        raise DecodeError(f"unknown message type {type_name!r}")
    expected: bytes = cls._get_packed_fingerprint()
    fingerprint = bytes(payload[: len(expected)])
    if fingerprint != expected:
        if len(fingerprint) < len(expected):
            raise DecodeError(
                f"{type_name}: payload of {len(payload)} bytes is shorter than a fingerprint"
            )
        earlier = _EARLIER.get(fingerprint)
        if earlier is not None and earlier[0] == type_name:
            version = earlier[1]
            raise UnsupportedVersion(
                f"{type_name}: version {version} is not supported (this build speaks version"
                f" {VERSIONS[type_name]}; the sender runs another release)",
                version=version,
                supported=VERSIONS[type_name],
            )
        raise DecodeError(
            f"{type_name}: the payload is not a {type_name} as defined here (fingerprint"
            f" {fingerprint.hex()}, expected {expected.hex()}): another type, or another"
            " definition of this one"
        )
    reader = _ExactReader(payload)
    try:
        msg = cls.decode(reader)
    except _Short as err:
        raise DecodeError(f"{type_name}: truncated payload: {err}") from None
    except (struct.error, ValueError) as err:
        raise DecodeError(f"{type_name}: undecodable payload: {err}") from err
    if (left := len(payload) - reader.tell()) != 0:
        raise DecodeError(f"{type_name}: {left} unexpected bytes after the end of the message")
    if (bad := _negative_size(msg)) is not None:
        raise DecodeError(f"{type_name}: negative array size {bad}")
    if msg.version != VERSIONS[type_name]:
        raise UnsupportedVersion(
            f"{type_name}: version {msg.version} is not supported (this build speaks"
            f" version {VERSIONS[type_name]})",
            version=msg.version,
            supported=VERSIONS[type_name],
        )
    return msg
