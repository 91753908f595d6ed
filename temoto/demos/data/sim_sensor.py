"""A simulated range sensor for demonstration 1: sends ``<name> <seq>`` datagrams.

Started by the Component Manager as ``python -S -I sim_sensor.py --output CHANNEL --name NAME
[--rate HZ]``. It imports only ``socket``, ``sys`` and ``time`` so it starts in a few
milliseconds (a failover includes the substitute's start). Channels: ``unix:@NAME`` (abstract
Unix datagram socket) or ``udp:HOST:PORT``. Readings nobody listens to are dropped.
"""

import socket
import sys
import time


def address(channel: str) -> tuple[socket.AddressFamily, str | tuple[str, int]]:
    """The socket family and address of a channel."""
    if channel.startswith("unix:"):
        rest = channel[5:]
        return socket.AF_UNIX, ("\0" + rest[1:]) if rest.startswith("@") else rest
    host, _, port = channel[4:].rpartition(":")
    host = host.strip("[]")
    return (socket.AF_INET6 if ":" in host else socket.AF_INET), (host, int(port))


def main(argv: list[str]) -> None:
    """Send readings until killed."""
    opts = dict(zip(argv[::2], argv[1::2], strict=False))
    family, addr = address(opts["--output"])
    name = opts.get("--name", "sensor").encode()
    period = 1.0 / float(opts.get("--rate", "100"))
    sock = socket.socket(family, socket.SOCK_DGRAM)
    seq = 0
    due = time.monotonic()
    while True:
        try:  # noqa: SIM105 - no contextlib import: this program must start fast
            sock.sendto(name + b" " + str(seq).encode(), addr)
        except OSError:
            pass  # nobody listens (yet)
        seq += 1
        due += period
        delay = due - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        else:
            due = time.monotonic()


if __name__ == "__main__":
    main(sys.argv[1:])
