"""A simulated scanner or camera for the display tests: a laser scan or a PNG, and a bad one.

Started by the Component Manager as ``python -S -I sim_scanner.py --output unix:@NAME --mode
scan|image``: every 20 ms it sends one good datagram and one that decodes as neither (``not
json`` / a GIF header). ``scan``: a JSON object with LaserScan's fields, ``ranges`` 1.0, 1.5,
... 4.5 m over ``start_angle`` 0 to ``end_angle`` π, and a ``seq`` that is not one of them.
``image``: a 1x1 PNG (one green pixel), made here with ``zlib`` (the PNG specification's
chunk layout: length, type, data, CRC-32). Standard library only, to start fast.
"""

import json
import math
import socket
import struct
import sys
import time
import zlib

#: The ranges of every scan (metres).
RANGES = [1.0 + 0.5 * i for i in range(8)]


def components_file(directory: str) -> str:
    """Write ``components.yaml`` in ``directory``: ``lidar`` (type ``scanner``, scans) and
    ``cam`` (type ``camera``, images), both this program; returns its path."""
    entries = "".join(
        f'  - name: {name}\n    type: {kind}\n    executable: "{{python}}"\n'
        f'    args: ["-S", "-I", {json.dumps(__file__)}, "--output", "{{output:out}}",'
        f' "--mode", "{mode}"]\n    outputs: [out]\n'
        for name, kind, mode in (("lidar", "scanner", "scan"), ("cam", "camera", "image"))
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


def main(argv: list[str]) -> None:
    """Send until killed."""
    opts = dict(zip(argv[::2], argv[1::2], strict=False))
    rest = opts["--output"][5:]  # unix:@NAME or unix:/path
    addr = "\0" + rest[1:] if rest.startswith("@") else rest
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    image = png()
    seq = 0
    while True:
        if opts.get("--mode") == "image":
            good, bad = image, b"GIF89a"
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
