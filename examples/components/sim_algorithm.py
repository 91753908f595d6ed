"""A simulated algorithm (detector, tracker): reads datagrams, sends ``<name>|<datagram>``.

Started as ``python -S -I sim_algorithm.py --input CHANNEL --output CHANNEL --name NAME``. It
binds its input channel (it is that channel's listener) and forwards every datagram, prefixed
with its name, to its output: a consumer of a camera -> detector -> tracker pipeline receives
``tracker|detector|camera_a 17``, so it can tell which camera the data came from.
"""

import socket
import sys


def address(channel):
    if channel.startswith("unix:"):
        rest = channel[5:]
        return socket.AF_UNIX, ("\0" + rest[1:]) if rest.startswith("@") else rest
    host, _, port = channel[4:].rpartition(":")
    host = host.strip("[]")
    return (socket.AF_INET6 if ":" in host else socket.AF_INET), (host, int(port))


def main(argv):
    opts = dict(zip(argv[::2], argv[1::2], strict=False))
    in_family, in_addr = address(opts["--input"])
    out_family, out_addr = address(opts["--output"])
    prefix = opts.get("--name", "algorithm").encode() + b"|"
    source = socket.socket(in_family, socket.SOCK_DGRAM)
    source.bind(in_addr)
    sink = socket.socket(out_family, socket.SOCK_DGRAM)
    while True:
        data = source.recv(65507)
        try:  # noqa: SIM105 - no contextlib import: this program must start fast
            sink.sendto(prefix + data, out_addr)
        except OSError:
            pass  # nobody listens (yet)


if __name__ == "__main__":
    main(sys.argv[1:])
