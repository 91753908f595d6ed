"""A component's datagrams decoded as a Foxglove message: a laser scan or a compressed image.

A component display asked for with ``kind`` ``foxglove.LaserScan`` or
``foxglove.CompressedImage`` (:data:`~temoto.managers.visualization.messages.OTHER_KINDS`)
decodes each datagram of the component's output (the default, ``temoto.ComponentData``,
shows it as text):

* ``foxglove.LaserScan``: the datagram is a JSON object with LaserScan's fields: ``ranges``
  (metres, a list of numbers; required), ``start_angle`` and ``end_angle`` (radians; default
  0 and 2π), ``intensities`` (optional, as many as the ranges), ``frame_id`` (default: the
  component's name). The scan's origin is its frame's (pose: identity).
* ``foxglove.CompressedImage``: the datagram is the bytes of one PNG or JPEG image (its format
  from its first bytes); ``frame_id`` is the component's name.

A datagram that is not one of these is dropped (counted, and logged at DEBUG). Field names
and meanings: Foxglove's message schemas (https://docs.foxglove.dev/docs/visualization/
message-schemas/laser-scan and .../compressed-image).
"""

from __future__ import annotations

import base64
import json
import math
from typing import Any, Final

from temoto.record.schemas import SCHEMAS

__all__ = ["DECODED_SCHEMAS", "decode"]

_TIME: Final = SCHEMAS["foxglove.PoseInFrame"]["properties"]["timestamp"]
_POSE: Final = SCHEMAS["foxglove.PoseInFrame"]["properties"]["pose"]
_NUMBERS: Final = {"type": "array", "items": {"type": "number"}}

#: The JSON schemas of the decoded messages.
DECODED_SCHEMAS: Final[dict[str, dict[str, Any]]] = {
    "foxglove.LaserScan": {
        "title": "foxglove.LaserScan",
        "description": "A single scan from a planar laser range-finder",
        "type": "object",
        "properties": {
            "timestamp": _TIME,
            "frame_id": {"type": "string"},
            "pose": _POSE,
            "start_angle": {"type": "number"},
            "end_angle": {"type": "number"},
            "ranges": _NUMBERS,
            "intensities": _NUMBERS,
        },
    },
    "foxglove.CompressedImage": {
        "title": "foxglove.CompressedImage",
        "description": "A compressed image",
        "type": "object",
        "properties": {
            "timestamp": _TIME,
            "frame_id": {"type": "string"},
            "data": {"type": "string", "contentEncoding": "base64"},
            "format": {"type": "string"},
        },
    },
}

_IDENTITY: Final = {
    "position": {"x": 0.0, "y": 0.0, "z": 0.0},
    "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
}


def _numbers(value: Any, what: str) -> list[float]:
    if not isinstance(value, list) or not all(
        isinstance(v, int | float) and not isinstance(v, bool) for v in value
    ):
        raise ValueError(f"{what} must be a list of numbers")
    return [float(v) if math.isfinite(v) else float("inf") for v in value]


def _scan(data: bytes, component: str) -> dict[str, Any]:
    body = json.loads(data)
    if not isinstance(body, dict):
        raise ValueError("a scan is a JSON object")
    ranges = _numbers(body.get("ranges"), "ranges")
    # JSON has no infinity: a range out of reach is sent as null by Foxglove's own encoders;
    # here it is the largest float (the server refuses NaN and infinity)
    ranges = [r if math.isfinite(r) else 1.7976931348623157e308 for r in ranges]
    intensities = _numbers(body.get("intensities", []), "intensities")
    if intensities and len(intensities) != len(ranges):
        raise ValueError("intensities and ranges differ in length")
    start = float(body.get("start_angle", 0.0))
    end = float(body.get("end_angle", 2 * math.pi))
    if not (math.isfinite(start) and math.isfinite(end)):
        raise ValueError("the angles must be finite")
    return {
        "frame_id": str(body.get("frame_id") or component),
        "pose": _IDENTITY,
        "start_angle": start,
        "end_angle": end,
        "ranges": ranges,
        "intensities": intensities,
    }


def _image(data: bytes, component: str) -> dict[str, Any]:
    if data.startswith(b"\x89PNG\r\n\x1a\n"):
        kind = "png"
    elif data.startswith(b"\xff\xd8\xff"):
        kind = "jpeg"
    else:
        raise ValueError("not a PNG or JPEG image")
    return {"frame_id": component, "format": kind, "data": base64.b64encode(data).decode()}


def decode(kind: str, data: bytes, component: str) -> dict[str, Any]:
    """A datagram as a message of ``kind``.

    Args:
        kind: ``foxglove.LaserScan`` or ``foxglove.CompressedImage``.
        data: The datagram.
        component: The component's name (the default frame).

    Returns:
        The message (without its timestamp).

    Raises:
        ValueError: The datagram is not a message of that kind (or the kind is unknown).
    """
    if kind == "foxglove.LaserScan":
        return _scan(data, component)
    if kind == "foxglove.CompressedImage":
        return _image(data, component)
    raise ValueError(f"no decoder for {kind}")
