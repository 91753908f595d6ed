"""A simulated scanner, camera, depth sensor or map for the display tests, with bad datagrams.

Started by the Component Manager as ``python -S -I sim_scanner.py --output unix:@NAME --mode
MODE``: every 20 ms it sends one good datagram and one that does not decode (``not json`` /
a GIF header / ...). The modes:

* ``scan``: a JSON object with LaserScan's fields, ``ranges`` 1.0, 1.5, ... 4.5 m over
  ``start_angle`` 0 to ``end_angle`` π, and a ``seq`` that is not one of them.
* ``image``: a 1x1 PNG (one green pixel), made here with ``zlib`` (the PNG specification's
  chunk layout: length, type, data, CRC-32).
* ``cloud``: a JSON object, ``points`` :data:`POINTS` (bad: a point of one coordinate).
* ``raw-rgb``: a binary PPM (``P6``, maxval 255) of :data:`PIXELS` (bad: maxval 65535).
* ``raw-bgr``: a JSON RawImage of :data:`PIXELS`, ``encoding`` ``bgr8``, ``step`` 8 (two
  bytes of padding per row; bad: ``data`` one byte short).
* ``raw-mono``: a binary PGM (``P5``) of :data:`GREYS` (bad: ``P5`` with no size).
* ``grid``: a JSON object, :data:`GRID` (bad: cells that are no whole number of rows).

Standard library only, to start fast.
"""

import base64
import json
import math
import socket
import struct
import sys
import time
import zlib

#: The ranges of every scan (metres).
RANGES = [1.0 + 0.5 * i for i in range(8)]
#: The points of every cloud (metres; the second has no z: 0).
POINTS = [[1.0, 0.0, 0.0], [0.0, 2.0], [-1.5, -1.0, 1.0]]
#: The raw colour images' 2x2 pixels, rows top first: red, green / blue, white.
PIXELS = [[(255, 0, 0), (0, 255, 0)], [(0, 0, 255), (255, 255, 255)]]
#: The grey image's 2x2 pixels.
GREYS = [[0, 85], [170, 255]]
#: The grid: 3 columns, 2 rows from the corner at (-1, -1), 0.5 m cells; one unknown cell.
GRID = {"columns": 3, "cells": [0, 1, 2, 3, 4, None], "cell_size": 0.5, "origin": [-1.0, -1.0]}

#: name, type, mode of each simulated component of :func:`components_file`.
COMPONENTS = (
    ("lidar", "scanner", "scan"),
    ("cam", "camera", "image"),
    ("depth", "depth_camera", "cloud"),
    ("rawcam", "raw_camera", "raw-rgb"),
    ("bgrcam", "bgr_camera", "raw-bgr"),
    ("greycam", "grey_camera", "raw-mono"),
    ("costmap", "costmap", "grid"),
)


def components_file(directory: str) -> str:
    """Write ``components.yaml`` in ``directory``: one component per :data:`COMPONENTS` entry
    (``lidar``, type ``scanner``, scans; ``cam``, type ``camera``, PNGs; ...), all this
    program; returns its path."""
    entries = "".join(
        f'  - name: {name}\n    type: {kind}\n    executable: "{{python}}"\n'
        f'    args: ["-S", "-I", {json.dumps(__file__)}, "--output", "{{output:out}}",'
        f' "--mode", "{mode}"]\n    outputs: [out]\n'
        for name, kind, mode in COMPONENTS
    )
    path = directory.rstrip("/") + "/components.yaml"
    with open(path, "w", encoding="utf-8") as out:
        out.write("components:\n" + entries)
    return path


def _chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def png() -> bytes:
    """A 1x1 8-bit RGB PNG of one green pixel."""
    header = struct.pack(">IIBBBBB", 1, 1, 8, 2, 0, 0, 0)
    pixels = zlib.compress(b"\x00\x00\xff\x00")  # filter 0, then R G B
    return (
        b"\x89PNG\r\n\x1a\n"
        + _chunk(b"IHDR", header)
        + _chunk(b"IDAT", pixels)
        + _chunk(b"IEND", b"")
    )


def datagrams(mode: str) -> tuple[bytes, bytes]:
    """The good and the bad datagram of a mode other than ``scan`` (see the module's doc)."""
    rgb = b"".join(bytes(p) for row in PIXELS for p in row)
    if mode == "image":
        return png(), b"GIF89a"
    if mode == "cloud":
        return json.dumps({"points": POINTS}).encode(), b'{"points": [[1.0]]}'
    if mode == "raw-rgb":
        return b"P6\n# sim\n2 2\n255\n" + rgb, b"P6\n2 2\n65535\n" + rgb + rgb
    if mode == "raw-bgr":
        rows = [b"".join(bytes(p[::-1]) for p in row) + b"\0\0" for row in PIXELS]
        body = {"width": 2, "height": 2, "encoding": "bgr8", "step": 8}
        good = {**body, "data": base64.b64encode(b"".join(rows)).decode()}
        bad = {**body, "data": base64.b64encode(b"".join(rows)[:-1]).decode()}
        return json.dumps(good).encode(), json.dumps(bad).encode()
    if mode == "raw-mono":
        return b"P5 2 2 255\n" + bytes(v for row in GREYS for v in row), b"P5\n"
    if mode == "grid":
        return json.dumps(GRID).encode(), json.dumps({**GRID, "columns": 4}).encode()
    raise ValueError(f"unknown mode {mode!r}")


def main(argv: list[str]) -> None:
    """Send until killed."""
    opts = dict(zip(argv[::2], argv[1::2], strict=False))
    rest = opts["--output"][5:]  # unix:@NAME or unix:/path
    addr = "\0" + rest[1:] if rest.startswith("@") else rest
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    mode = opts.get("--mode", "scan")
    fixed = None if mode == "scan" else datagrams(mode)
    seq = 0
    while True:
        if fixed is not None:
            good, bad = fixed
        else:
            scan = {"ranges": RANGES, "start_angle": 0.0, "end_angle": math.pi, "seq": seq}
            good, bad = json.dumps(scan).encode(), b"not json"
        for data in (good, bad):
            try:  # noqa: SIM105 - no contextlib import: this program must start fast
                sock.sendto(data, addr)
            except OSError:
                pass  # nobody listens (yet)
        seq += 1
        time.sleep(0.02)


if __name__ == "__main__":
    main(sys.argv[1:])
