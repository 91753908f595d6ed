"""The journal's frames read back: verification, torn tails, preallocated zeros, corruption.

Registrar internal: :meth:`~temoto.core.registrar.journal.Journal.open` reads a file with
:func:`parse`; the format and the rules are :mod:`~temoto.core.registrar.journal`'s docstring.
"""

from __future__ import annotations

import json
import struct
import zlib
from typing import Any

from temoto.errors import CatalogCorruptError

__all__ = [
    "FORMAT_VERSION",
    "FRAME",
    "FRAME_HEAD",
    "HEADER",
    "MAGIC",
    "MAX_RECORD_BYTES",
    "content_end",
    "parse",
]

#: The first eight bytes of every journal file.
MAGIC = b"TEMOTOJ1"
#: The format version byte that follows the magic.
FORMAT_VERSION = 1
#: The largest payload a frame may carry; longer ones are refused (append) or corrupt (open).
MAX_RECORD_BYTES = 64 * 1024 * 1024
#: The file's header.
HEADER = MAGIC + bytes([FORMAT_VERSION])
#: A frame's head: length, crc, seq.
FRAME = struct.Struct("<IIQ")
FRAME_HEAD = FRAME.size


def parse(data: bytes, name: str) -> tuple[list[dict[str, Any]], int]:
    """Verify and decode a journal's frames (after its header).

    Args:
        data: The whole file; its header was checked by the caller.
        name: The file's name, for errors.

    Returns:
        The records, and the end of the last whole frame: anything after it is a torn tail, or
        zeros (see :func:`content_end`).

    Raises:
        CatalogCorruptError: If the frames are damaged other than by a torn tail.
    """
    view = memoryview(data)
    n = len(data)
    unpack = FRAME.unpack_from
    crc32 = zlib.crc32
    records: list[dict[str, Any]] = []
    seq = 0
    off = len(HEADER)
    content = content_end(data)  # zeros after it: preallocated space (or a torn tail)
    while off < content:
        if n - off < FRAME_HEAD:
            problem = "an incomplete frame header"
        else:
            length, crc, frame_seq = unpack(data, off)
            end = off + FRAME_HEAD + length
            if length > MAX_RECORD_BYTES and end <= n:
                raise _corrupt(name, off, f"frame length {length} is over the limit")
            if end > n:
                problem = f"an incomplete frame ({n - off} of {end - off} bytes)"
            elif crc32(view[off + 8 : end]) != crc:
                problem = "a frame that fails its CRC"
            else:
                if frame_seq != seq + 1:
                    raise _corrupt(
                        name, off, f"sequence number {frame_seq} where {seq + 1} was expected"
                    )
                records.append(_decode(name, data[off + FRAME_HEAD : end], off, frame_seq))
                seq = frame_seq
                off = end
                continue
        later = _find_valid_frame(data, off + 1, content)
        if later is not None:
            raise _corrupt(
                name,
                off,
                f"{problem} (after record {seq}) followed by a valid frame at byte {later}",
            )
        return records, off
    return records, off


def _decode(name: str, payload: bytes, off: int, seq: int) -> dict[str, Any]:
    try:
        value = json.loads(payload.decode("utf-8"))
    except ValueError as exc:  # UnicodeDecodeError and JSONDecodeError are ValueErrors
        raise _corrupt(name, off, f"record {seq} is not valid UTF-8 JSON: {exc}") from exc
    if not isinstance(value, dict):
        raise _corrupt(name, off, f"record {seq} is a JSON {type(value).__name__}, not an object")
    return value


def _corrupt(name: str, offset: int, message: str) -> CatalogCorruptError:
    return CatalogCorruptError(message, file=name, offset=offset)


def _find_valid_frame(data: bytes, start: int, content: int) -> int | None:
    """The offset of the first frame at or after ``start`` whose CRC checks out, if any.

    ``content``: :func:`content_end` of ``data`` (a frame has a non-zero sequence number, so
    none starts in the zeros after it).
    """
    view = memoryview(data)
    n = len(data)
    unpack = FRAME.unpack_from
    crc32 = zlib.crc32
    for off in range(start, min(n - FRAME_HEAD + 1, content)):
        length, crc, seq = unpack(data, off)
        end = off + FRAME_HEAD + length
        if seq and end <= n and length <= MAX_RECORD_BYTES and crc32(view[off + 8 : end]) == crc:
            return off
    return None


def content_end(data: bytes) -> int:
    """The length of ``data`` without its trailing zero bytes."""
    end = len(data)
    while end:
        start = max(0, end - 65536)
        if data.count(0, start, end) != end - start:
            return len(data[start:end].rstrip(b"\0")) + start
        end = start
    return 0
