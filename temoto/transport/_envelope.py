"""A fast reader and writer of ``envelope_t``, byte for byte LCM's encoding (docs/security.md).

Private to :mod:`temoto.transport.auth` and :mod:`temoto.transport._secure`. Every fleet message
is one envelope; lcm-gen's Python code reads and writes it through a ``BytesIO`` one field at a
time, and checking that an envelope is canonical took a decode and a re-encode. That was most
of the per-message work of a sealed message (the cipher itself is a few µs), so the hot path
reads and writes the same bytes here with a few ``struct`` calls. The generated
:class:`~temoto.lcm_types.envelope_t` stays the definition: the tests compare both on every
field and on garbage. :func:`parse_hello` reads the body of a keyed fleet's hello.
"""

from __future__ import annotations

import struct
from typing import Final

from temoto.lcm_types import envelope_t

#: The ``type`` of a keyed fleet's hello envelope (:mod:`temoto.transport._secure`).
HELLO_TYPE: Final = "fleet_hello"
_FINGERPRINT: Final[bytes] = envelope_t._get_packed_fingerprint()  # type: ignore[no-untyped-call]
_H_I: Final = struct.Struct(">hI")  # version, then the fleet's length
_I: Final = struct.Struct(">I")
_QQI: Final = struct.Struct(">qqI")  # seq, stamp_us, then the type's length
_i: Final = struct.Struct(">i")
_h: Final = struct.Struct(">h")
_INT16_MAX: Final = 0x7FFF
_INT32_MAX: Final = 0x7FFF_FFFF


def parse(data: bytes) -> envelope_t | None:
    """The envelope ``data`` encodes canonically, or None.

    Canonical: exactly what LCM's encoder writes for the fields it holds, so no message has a
    second spelling (LCM's own decoder ignores trailing bytes, reads short arrays and replaces
    bad UTF-8). Strings must be valid UTF-8 and end in their NUL.

    Args:
        data: The received bytes.

    Returns:
        The envelope (a :class:`~temoto.lcm_types.envelope_t`), or None if ``data`` is not one.
    """
    try:
        if data[:8] != _FINGERPRINT:
            return None
        version, size = _H_I.unpack_from(data, 8)
        at = 14
        end = at + size
        if size < 1 or data[end - 1] != 0:
            return None
        fleet = data[at : end - 1].decode("utf-8")
        (size,) = _I.unpack_from(data, end)
        at = end + 4
        end = at + size
        if size < 1 or data[end - 1] != 0:
            return None
        sender = data[at : end - 1].decode("utf-8")
        seq, stamp_us, size = _QQI.unpack_from(data, end)
        at = end + 20
        end = at + size
        if size < 1 or data[end - 1] != 0:
            return None
        type_name = data[at : end - 1].decode("utf-8")
        (size,) = _i.unpack_from(data, end)
        at = end + 4
        end = at + size
        if size < 0 or end > len(data):
            return None
        payload = data[at:end]
        (mac_size,) = _h.unpack_from(data, end)
        at = end + 2
        if mac_size < 0 or at + mac_size != len(data):
            return None
        mac = data[at:]
    except (struct.error, IndexError, TypeError, UnicodeDecodeError):
        return None
    env = envelope_t.__new__(envelope_t)
    env.version = version
    env.fleet = fleet
    env.sender = sender
    env.seq = seq
    env.stamp_us = stamp_us
    env.type = type_name
    env.payload_size = len(payload)
    env.payload = bytes(payload)
    env.mac_size = mac_size
    env.mac = bytes(mac)
    return env


class Writer:
    """Writes the envelopes of one sender (its version, fleet and name encoded once).

    Args:
        version: The envelope version.
        fleet: The fleet name.
        sender: The sender's name.
    """

    __slots__ = ("_head", "_sender")

    def __init__(self, version: int, fleet: str, sender: str) -> None:
        f, s = fleet.encode("utf-8"), sender.encode("utf-8")
        self._head = b"".join(
            (_FINGERPRINT, _H_I.pack(version, len(f) + 1), f, b"\0", _I.pack(len(s) + 1), s, b"\0")
        )

    def write(self, seq: int, stamp_us: int, type_name: str, payload: bytes, mac: bytes) -> bytes:
        """One envelope, as ``envelope_t.encode()`` writes it.

        Args:
            seq: The sequence number.
            stamp_us: The stamp (insecure fleets) or session id (keyed fleets).
            type_name: The inner message's type name.
            payload: The inner message (encrypted in a keyed fleet).
            mac: The mac (may be empty).

        Returns:
            The encoded envelope.

        Raises:
            ValueError: If the payload or the mac is too long for its size field.
            struct.error: If ``seq`` or ``stamp_us`` do not fit in 64 bits.
        """
        if len(payload) > _INT32_MAX or len(mac) > _INT16_MAX:
            raise ValueError("an envelope's payload or mac is too long")
        t = type_name.encode("utf-8")
        return b"".join(
            (
                self._head,
                _QQI.pack(seq, stamp_us, len(t) + 1),
                t,
                b"\0",
                _i.pack(len(payload)),
                payload,
                _h.pack(len(mac)),
                mac,
            )
        )


def parse_hello(
    body: bytes, hint_size: int, grant_size: int, max_asked: int
) -> tuple[bytes, dict[str, list[tuple[bytes, bytes]]], dict[tuple[str, int], list[int]]]:
    """Ephemeral key, grants and what its sender missed, of a keyed fleet's hello body.

    The layout is :mod:`temoto.transport._secure`'s (it writes hellos): a 32-byte key; a count
    and that many grants (a name, a key hint of ``hint_size`` bytes, a grant of
    ``grant_size``); a count and that many asks (a name, a session, up to ``max_asked``
    sequence numbers). Grants map a recipient to ``[(key hint, grant)]``; what was missed maps
    ``(sender, session)`` to sequence numbers (none: only the grant is asked for).

    Raises:
        ValueError: The body is not such a hello.
    """
    if len(body) < 34:
        raise ValueError("short hello")
    e_pub, (count,) = body[:32], struct.unpack_from(">H", body, 32)
    at = 34
    grants: dict[str, list[tuple[bytes, bytes]]] = {}
    for _ in range(count):
        if at + 4 > len(body):
            raise ValueError("short hello")
        (size,) = struct.unpack_from(">I", body, at)
        end = at + 4 + size + hint_size + grant_size
        if end > len(body):
            raise ValueError("short hello")
        name = body[at + 4 : at + 4 + size].decode("utf-8", "surrogatepass")
        hint = body[at + 4 + size : at + 4 + size + hint_size]
        grants.setdefault(name, []).append((hint, body[at + 4 + size + hint_size : end]))
        at = end
    if at + 2 > len(body):
        raise ValueError("short hello")
    (count,) = struct.unpack_from(">H", body, at)
    at += 2
    wants: dict[tuple[str, int], list[int]] = {}
    for _ in range(count):
        if at + 4 > len(body):
            raise ValueError("short hello")
        (size,) = struct.unpack_from(">I", body, at)
        if at + 4 + size + 10 > len(body):
            raise ValueError("short hello")
        name = body[at + 4 : at + 4 + size].decode("utf-8", "surrogatepass")
        session, n = struct.unpack_from(">QH", body, at + 4 + size)
        at += 4 + size + 10
        if n > max_asked or at + 8 * n > len(body):
            raise ValueError("bad hello")
        wants[name, session] = list(struct.unpack_from(f">{n}Q", body, at))
        at += 8 * n
    if at != len(body):
        raise ValueError("trailing bytes")
    return e_pub, grants, wants
