"""Data channels between components and their consumers: datagram sockets named by a string.

A channel is where a component's output goes and where its consumer (or the next pipeline
segment) listens. The consumer binds it; producers send datagrams to it and drop them while
nobody listens. Because the address is a plain string handed to the component program as an
argument, a substitute started after a failover sends to the same place: the consumer keeps
receiving without re-subscribing. Two forms:

* ``unix:@NAME`` — a Linux abstract Unix datagram socket (no file, no port to allocate, gone
  when the listener closes; one network namespace, i.e. one host). The manager allocates these
  for outputs a request leaves open and for the links inside a pipeline.
* ``udp:HOST:PORT`` — a UDP socket (reachable from other robots; for remote components).

No multicast route is needed, so plain tests work without ``unshare -n``. The simulated
programs in ``examples/components/`` parse the same two forms on their own (they start with
``python -S -I``, so they import nothing from TeMoto).
"""

from __future__ import annotations

import contextlib
import os
import re
import select
import socket
import time
from typing import Any

__all__ = ["ChannelReader", "ChannelSender", "channel_address", "check_channel"]

_UNIX = re.compile(r"unix:(@[^\0]{1,100}|/[^\0]{1,100})\Z")
_UDP = re.compile(r"udp:([A-Za-z0-9_.\-]+|\[[0-9A-Fa-f:.]+\]):(\d{1,5})\Z")

#: Largest datagram :class:`ChannelReader` receives whole.
MAX_DATAGRAM = 65507


def check_channel(channel: object) -> str:
    """Check a channel address.

    Args:
        channel: ``unix:@NAME``, ``unix:/PATH`` or ``udp:HOST:PORT``.

    Returns:
        The channel.

    Raises:
        TypeError: Not a str.
        ValueError: Not one of the forms.
    """
    if not isinstance(channel, str):
        raise TypeError(f"a channel must be a str, not {type(channel).__name__}")
    if _UNIX.match(channel) is None and (
        (m := _UDP.match(channel)) is None or not 0 <= int(m.group(2)) <= 65535
    ):
        raise ValueError(
            f"bad channel {channel!r}: expected unix:@NAME, unix:/PATH or udp:HOST:PORT"
        )
    return channel


def channel_address(channel: str) -> tuple[int, Any]:
    r"""The socket family and address of a channel.

    Args:
        channel: A channel (see :func:`check_channel`).

    Returns:
        ``(AF_UNIX, "\\0NAME" or path)`` or ``(AF_INET/AF_INET6, (host, port))``.

    Raises:
        ValueError: A bad channel.
    """
    check_channel(channel)
    if channel.startswith("unix:"):
        rest = channel[5:]
        return socket.AF_UNIX, ("\0" + rest[1:]) if rest.startswith("@") else rest
    host, _, port = channel[4:].rpartition(":")
    host = host.strip("[]")
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    return family, (host, int(port))


class ChannelReader:
    """The listening end of a channel (bound on creation).

    Args:
        channel: The channel; for ``udp:HOST:0`` the system picks a port (see :attr:`channel`).

    Raises:
        ValueError: A bad channel.
        OSError: It cannot be bound (someone else listens there).
    """

    def __init__(self, channel: str) -> None:
        family, address = channel_address(channel)
        self._sock = socket.socket(family, socket.SOCK_DGRAM)
        try:
            self._sock.bind(address)
        except BaseException:
            self._sock.close()
            raise
        if family == socket.AF_UNIX:
            self.channel = channel
        else:
            host, port = self._sock.getsockname()[:2]
            self.channel = (
                f"udp:{host}:{port}" if family == socket.AF_INET else f"udp:[{host}]:{port}"
            )

    def fileno(self) -> int:
        """The socket's file descriptor (for ``select``)."""
        return self._sock.fileno()

    def recv(self, timeout: float | None = None) -> bytes | None:
        """The next datagram.

        Args:
            timeout: Seconds to wait (None: forever, 0: do not wait).

        Returns:
            The datagram, or None on timeout.

        Raises:
            OSError: The reader is closed.
        """
        if timeout is not None and not select.select([self._sock], [], [], max(0.0, timeout))[0]:
            return None
        return self._sock.recv(MAX_DATAGRAM)

    def recv_until(self, predicate: Any, timeout: float) -> bytes | None:
        """Receive until a datagram satisfies ``predicate(data)``, within ``timeout`` seconds.

        Args:
            predicate: Called with each datagram.
            timeout: Seconds in all.

        Returns:
            The first datagram that satisfied it, or None on timeout.
        """
        deadline = time.monotonic() + timeout
        while True:
            data = self.recv(deadline - time.monotonic())
            if data is None:
                return None
            if predicate(data):
                return data

    def drain(self) -> int:
        """Drop the datagrams already queued; how many."""
        count = 0
        while self.recv(0) is not None:
            count += 1
        return count

    def close(self) -> None:
        """Stop listening (idempotent)."""
        self._sock.close()
        if self.channel.startswith("unix:/"):
            with contextlib.suppress(OSError):
                os.unlink(self.channel[5:])

    def __enter__(self) -> ChannelReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class ChannelSender:
    """The sending end: datagrams to a channel, dropped while nobody listens.

    Args:
        channel: The channel.

    Raises:
        ValueError: A bad channel.
    """

    def __init__(self, channel: str) -> None:
        family, self._address = channel_address(channel)
        self.channel = channel
        self._sock = socket.socket(family, socket.SOCK_DGRAM)

    def send(self, data: bytes) -> bool:
        """Send one datagram; False if nobody listens (or the buffer is full).

        Args:
            data: The datagram.

        Returns:
            Whether it was handed to a listener.
        """
        try:
            self._sock.sendto(data, self._address)
        except OSError:
            return False
        return True

    def close(self) -> None:
        """Close the socket (idempotent)."""
        self._sock.close()

    def __enter__(self) -> ChannelSender:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
