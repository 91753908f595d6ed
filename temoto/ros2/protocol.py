"""The bridge's wire format: JSON objects in length-prefixed frames over a stream socket.

A frame is a 4-byte big-endian length followed by that many bytes of UTF-8 JSON (one object).
The bridge's first frame on a connection is ``{"ready": true, ...}`` (with ``rmw``, ``domain_id``
and ``pid``) or ``{"error": "..."}``. After that, every request ``{"id": N, "op": ...}`` gets
exactly one reply ``{"id": N, "ok": true, "result": ...}`` or ``{"id": N, "ok": false,
"error": "one line"}``; a request may also get events before its reply (``{"id": N,
"event": "feedback", "feedback": {...}}`` for a goal). The operations are listed in
``docs/ros2.md``.
"""

from __future__ import annotations

import json
import socket
import struct
from typing import Any, Final

__all__ = ["MAX_FRAME", "FrameError", "recv_frame", "send_frame"]

#: The largest frame either side accepts (bytes).
MAX_FRAME: Final = 64 * 1024 * 1024
_HEADER = struct.Struct(">I")


class FrameError(ConnectionError):
    """The peer closed the connection or sent something that is not a frame."""


def send_frame(sock: socket.socket, obj: dict[str, Any]) -> None:
    """Send one object as a frame.

    Args:
        sock: A connected stream socket.
        obj: A JSON-serialisable object.

    Raises:
        FrameError: The frame is too large.
        OSError: The socket failed.
    """
    data = json.dumps(obj, separators=(",", ":")).encode()
    if len(data) > MAX_FRAME:
        raise FrameError(f"a frame of {len(data)} bytes is over the {MAX_FRAME}-byte limit")
    sock.sendall(_HEADER.pack(len(data)) + data)


def _recv_exact(sock: socket.socket, size: int) -> bytes:
    chunks: list[bytes] = []
    left = size
    while left:
        chunk = sock.recv(min(left, 1 << 20))
        if not chunk:
            raise FrameError("the connection was closed")
        chunks.append(chunk)
        left -= len(chunk)
    return b"".join(chunks)


def recv_frame(sock: socket.socket) -> dict[str, Any]:
    """Receive one frame.

    Args:
        sock: A connected stream socket.

    Returns:
        The object.

    Raises:
        FrameError: The connection was closed, or the frame is not a JSON object.
        OSError: The socket failed (``TimeoutError`` on its timeout).
    """
    (size,) = _HEADER.unpack(_recv_exact(sock, _HEADER.size))
    if size > MAX_FRAME:
        raise FrameError(f"a frame of {size} bytes is over the {MAX_FRAME}-byte limit")
    try:
        obj = json.loads(_recv_exact(sock, size))
    except ValueError as exc:
        raise FrameError(f"a frame is not JSON: {exc}") from None
    if not isinstance(obj, dict):
        raise FrameError(f"a frame is a JSON {type(obj).__name__}, not an object")
    return obj
