"""A component's datagrams decoded as a Foxglove message: a scan, an image, a cloud, a grid.

A component display asked for with ``kind`` ``foxglove.LaserScan``, ``foxglove.CompressedImage``,
``foxglove.PointCloud``, ``foxglove.RawImage`` or ``foxglove.Grid``
(:data:`~temoto.managers.visualization.messages.OTHER_KINDS`) decodes each datagram of the
component's output (the default, ``temoto.ComponentData``, shows it as text):

* ``foxglove.LaserScan``: the datagram is a JSON object with LaserScan's fields: ``ranges``
  (metres, a list of numbers; required), ``start_angle`` and ``end_angle`` (radians; default
  0 and 2π), ``intensities`` (optional, as many as the ranges), ``frame_id`` (default: the
  component's name). The scan's origin is its frame's (pose: identity).
* ``foxglove.CompressedImage``: the datagram is the bytes of one PNG or JPEG image (its format
  from its first bytes); ``frame_id`` is the component's name.
* ``foxglove.PointCloud``: the datagram is a JSON object: ``points`` (a list of ``[x, y, z]`` or
  ``[x, y]``, metres; required), ``frame_id`` (default: the component's name). The cloud has
  the fields ``x``, ``y``, ``z`` (FLOAT32 at offsets 0, 4, 8; ``point_stride`` 12).
* ``foxglove.RawImage``: the datagram is a binary Netpbm image, ``P5`` (grey: ``mono8``) or
  ``P6`` (colour: ``rgb8``) with a maxval of 255 (the header's tokens as netpbm.sourceforge.net
  defines them: magic, width, height, maxval, then one whitespace byte and the pixels, rows
  top first); or a JSON object with RawImage's own fields: ``width``, ``height``,
  ``encoding`` (one of Foxglove's: :data:`RAW_ENCODINGS`), ``step`` (bytes per row; default
  the width times the pixel's bytes), ``data`` (base64), ``frame_id``.
* ``foxglove.Grid``: the datagram is a JSON object: ``columns`` (cells per row), ``cells``
  (numbers or null, row after row from the grid's corner, ``+x`` along a row, ``+y`` from row
  to row: Foxglove's row-major order; a whole number of rows), ``cell_size`` (metres, a number
  or ``[x, y]``; default 0.1), ``origin`` (``[x, y]``, metres: the corner of the first cell;
  default ``[0, 0]``), ``frame_id``. The grid has one field, ``value`` (FLOAT32; a null cell is
  NaN).

Bytes (``data``) are base64 text, as the Foxglove WebSocket protocol's JSON encoding has them.
A datagram that is not one of these is dropped (counted, and logged at DEBUG). Field names
and meanings: Foxglove's message schemas (https://docs.foxglove.dev/docs/visualization/
message-schemas/laser-scan, .../compressed-image, .../point-cloud, .../raw-image, .../grid,
.../packed-element-field; the NumericType values are the SDK's ``PackedElementFieldNumericType``).
"""

from __future__ import annotations

import base64
import json
import math
import re
import struct
from typing import Any, Final

from temoto.record.schemas import SCHEMAS

__all__ = ["DECODED_SCHEMAS", "FLOAT32", "RAW_ENCODINGS", "decode"]

_TIME: Final = SCHEMAS["foxglove.PoseInFrame"]["properties"]["timestamp"]
_POSE: Final = SCHEMAS["foxglove.PoseInFrame"]["properties"]["pose"]
_NUMBERS: Final = {"type": "array", "items": {"type": "number"}}
_UINT: Final = {"type": "integer", "minimum": 0}
_BYTES: Final = {"type": "string", "contentEncoding": "base64"}
_FIELDS: Final = {
    "type": "array",
    "items": {
        "title": "foxglove.PackedElementField",
        "type": "object",
        "properties": {"name": {"type": "string"}, "offset": _UINT, "type": _UINT},
    },
}

#: Foxglove's NumericType of a 32-bit float (PackedElementField ``type``).
FLOAT32: Final = 7

#: RawImage's encodings (Foxglove's supported values) and the bytes of one pixel.
RAW_ENCODINGS: Final[dict[str, int]] = {
    "mono8": 1,
    "8UC1": 1,
    "mono16": 2,
    "16UC1": 2,
    "32FC1": 4,
    "rgb8": 3,
    "bgr8": 3,
    "8UC3": 3,
    "rgba8": 4,
    "bgra8": 4,
    "bayer_bggr8": 1,
    "bayer_gbrg8": 1,
    "bayer_grbg8": 1,
    "bayer_rggb8": 1,
    "uyvy": 2,
    "yuv422": 2,
    "yuyv": 2,
    "yuv422_yuy2": 2,
}

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
            "data": _BYTES,
            "format": {"type": "string"},
        },
    },
    "foxglove.PointCloud": {
        "title": "foxglove.PointCloud",
        "description": "A collection of N-dimensional points",
        "type": "object",
        "properties": {
            "timestamp": _TIME,
            "frame_id": {"type": "string"},
            "pose": _POSE,
            "point_stride": _UINT,
            "fields": _FIELDS,
            "data": _BYTES,
        },
    },
    "foxglove.RawImage": {
        "title": "foxglove.RawImage",
        "description": "A raw image",
        "type": "object",
        "properties": {
            "timestamp": _TIME,
            "frame_id": {"type": "string"},
            "width": _UINT,
            "height": _UINT,
            "encoding": {"type": "string"},
            "step": _UINT,
            "data": _BYTES,
        },
    },
    "foxglove.Grid": {
        "title": "foxglove.Grid",
        "description": "A 2D grid of data",
        "type": "object",
        "properties": {
            "timestamp": _TIME,
            "frame_id": {"type": "string"},
            "pose": _POSE,
            "column_count": _UINT,
            "cell_size": {
                "title": "foxglove.Vector2",
                "type": "object",
                "properties": {"x": {"type": "number"}, "y": {"type": "number"}},
            },
            "row_stride": _UINT,
            "cell_stride": _UINT,
            "fields": _FIELDS,
            "data": _BYTES,
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


def _object(data: bytes, what: str) -> dict[str, Any]:
    body = json.loads(data)
    if not isinstance(body, dict):
        raise ValueError(f"a {what} is a JSON object")
    return body


def _finite(value: Any, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ValueError(f"{what} must be a finite number")
    return float(value)


def _count(value: Any, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
        raise ValueError(f"{what} must be a positive integer")
    return value


def _b64(data: bytes) -> str:
    return base64.b64encode(data).decode()


def _cloud(data: bytes, component: str) -> dict[str, Any]:
    body = _object(data, "point cloud")
    points = body.get("points")
    if not isinstance(points, list):
        raise ValueError("points must be a list of [x, y, z]")
    flat: list[float] = []
    for point in points:
        if not isinstance(point, list) or len(point) not in (2, 3):
            raise ValueError("a point is [x, y, z] or [x, y]")
        flat += point
        if len(point) == 2:
            flat.append(0.0)
    try:  # one pack for the lot (a string or null: struct.error; beyond a float32: overflow)
        packed = struct.pack(f"<{len(flat)}f", *flat)
    except (struct.error, OverflowError) as err:
        raise ValueError(f"a coordinate must be a finite number: {err}") from err
    if not math.isfinite(math.fsum(flat)):  # NaN or infinity among them (each < 3.5e38)
        raise ValueError("a coordinate must be a finite number")
    return {
        "frame_id": str(body.get("frame_id") or component),
        "pose": _IDENTITY,
        "point_stride": 12,
        "fields": [
            {"name": axis, "offset": 4 * i, "type": FLOAT32} for i, axis in enumerate("xyz")
        ],
        "data": _b64(packed),
    }


_PNM: Final = re.compile(
    rb"(P[56])(?:\s|#[^\n]*\n)+(\d+)(?:\s|#[^\n]*\n)+(\d+)"
    rb"(?:\s|#[^\n]*\n)+(\d+)\s"
)


def _raw(data: bytes, component: str) -> dict[str, Any]:
    if data[:2] in (b"P5", b"P6"):  # a binary Netpbm image
        head = _PNM.match(data)
        if head is None:
            raise ValueError("a bad Netpbm header")
        width, height, maxval = (int(g) for g in head.group(2, 3, 4))
        if maxval != 255:
            raise ValueError(f"a Netpbm maxval of {maxval} (255 only)")
        encoding = "mono8" if head.group(1) == b"P5" else "rgb8"
        pixels, step, frame = data[head.end() :], width * RAW_ENCODINGS[encoding], component
    else:
        body = _object(data, "raw image")
        width = _count(body.get("width"), "width")
        height = _count(body.get("height"), "height")
        named = body.get("encoding")
        if not isinstance(named, str) or named not in RAW_ENCODINGS:
            raise ValueError(f"unknown encoding {named!r}")
        encoding = named
        step = body.get("step", width * RAW_ENCODINGS[encoding])
        if _count(step, "step") < width * RAW_ENCODINGS[encoding]:
            raise ValueError(f"a step of {step} is less than a row")
        try:
            pixels = base64.b64decode(str(body.get("data", "")), validate=True)
        except ValueError as err:
            raise ValueError("data is not base64") from err
        frame = str(body.get("frame_id") or component)
    if width <= 0 or height <= 0:
        raise ValueError("an empty image")
    if len(pixels) < step * height:
        raise ValueError(f"{len(pixels)} bytes of pixels, {step * height} needed")
    return {
        "frame_id": frame,
        "width": width,
        "height": height,
        "encoding": encoding,
        "step": step,
        "data": _b64(pixels[: step * height]),
    }


def _grid(data: bytes, component: str) -> dict[str, Any]:
    body = _object(data, "grid")
    columns = _count(body.get("columns"), "columns")
    cells = body.get("cells")
    if not isinstance(cells, list) or not cells or len(cells) % columns:
        raise ValueError("cells must be a whole number of rows of numbers")
    values = [math.nan if v is None else v for v in cells]
    size = body.get("cell_size", 0.1)
    sx, sy = (size, size) if not isinstance(size, list) or len(size) != 2 else size
    sx, sy = _finite(sx, "cell_size"), _finite(sy, "cell_size")
    if sx <= 0 or sy <= 0:
        raise ValueError("cell_size must be positive")
    origin = body.get("origin", [0.0, 0.0])
    if not isinstance(origin, list) or len(origin) != 2:
        raise ValueError("origin is [x, y]")
    ox, oy = (_finite(v, "origin") for v in origin)
    return {
        "frame_id": str(body.get("frame_id") or component),
        "pose": {
            "position": {"x": ox, "y": oy, "z": 0.0},
            "orientation": _IDENTITY["orientation"],
        },
        "column_count": columns,
        "cell_size": {"x": sx, "y": sy},
        "row_stride": 4 * columns,
        "cell_stride": 4,
        "fields": [{"name": "value", "offset": 0, "type": FLOAT32}],
        "data": _b64(_pack_cells(values)),
    }


def _pack_cells(values: list[Any]) -> bytes:
    try:
        return struct.pack(f"<{len(values)}f", *values)
    except (struct.error, OverflowError) as err:
        raise ValueError(f"a cell must be a number or null: {err}") from err


_DECODERS: Final = {
    "foxglove.LaserScan": _scan,
    "foxglove.CompressedImage": _image,
    "foxglove.PointCloud": _cloud,
    "foxglove.RawImage": _raw,
    "foxglove.Grid": _grid,
}


def decode(kind: str, data: bytes, component: str) -> dict[str, Any]:
    """A datagram as a message of ``kind``.

    Args:
        kind: ``foxglove.LaserScan``, ``foxglove.CompressedImage``, ``foxglove.PointCloud``,
            ``foxglove.RawImage`` or ``foxglove.Grid``.
        data: The datagram.
        component: The component's name (the default frame).

    Returns:
        The message (without its timestamp).

    Raises:
        ValueError: The datagram is not a message of that kind (or the kind is unknown).
    """
    decoder = _DECODERS.get(kind)
    if decoder is None:
        raise ValueError(f"no decoder for {kind}")
    try:
        return decoder(data, component)
    except (TypeError, struct.error, OverflowError) as err:  # JSONDecodeError is a ValueError
        raise ValueError(str(err)) from err  # (a TypeError: float([1]) of a field)
    except RecursionError as err:  # json.loads of [[[[...
        raise ValueError("JSON nested too deeply") from err
