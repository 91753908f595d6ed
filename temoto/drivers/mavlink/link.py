"""Byte links for MAVLink: UDP (``udpin:``, ``udpout:``) and serial, opened from a URL.

============================  ================================================================
``udpin:HOST:PORT``           listen on HOST:PORT; replies go only to the address the driver
                              accepted (:meth:`Link.accept_peer`: where the target vehicle's
                              valid frames come from); ``udp:`` is the same, as in pymavlink
``udpout:HOST:PORT``          send to HOST:PORT from an ephemeral port; the vehicle replies
                              there
``serial:DEVICE?baud=57600``  a serial port (needs pyserial: ``pip install 'temoto[dynamixel]'``)
============================  ================================================================

A link does not trust the wire: a UDP link hands over whole datagrams with their sender
(:meth:`Link.receive`, :attr:`Link.datagrams`), so each is parsed on its own, and a ``udpin``
link never learns where to send from whoever happens to send to it; the driver tells it, after
checking the frames (system and component id of the target vehicle).

One table maps schemes to link classes; an unknown scheme is a ``ValueError`` (the driver turns
it into a :class:`~temoto.errors.ProfileError` naming the key).
"""

from __future__ import annotations

import importlib
import select
import socket
import threading
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, ClassVar, Final
from urllib.parse import parse_qs

from temoto.errors import DriverUnavailableError

__all__ = ["Link", "LinkSpec", "SerialLink", "UdpLink", "open_link", "parse_link"]


@dataclass(frozen=True, slots=True)
class LinkSpec:
    """A parsed link URL.

    Attributes:
        scheme: ``udpin``, ``udpout`` or ``serial``.
        host: UDP host (empty for serial).
        port: UDP port (0 for serial).
        device: Serial device (empty for UDP).
        baud: Serial baud rate (0 for UDP).
    """

    scheme: str
    host: str = ""
    port: int = 0
    device: str = ""
    baud: int = 0

    def __str__(self) -> str:
        if self.scheme == "serial":
            return f"serial:{self.device}?baud={self.baud}"
        return f"{self.scheme}:{self.host}:{self.port}"


def _udp(scheme: str, rest: str) -> LinkSpec:
    host, sep, port_text = rest.rpartition(":")
    if not sep or not host:
        raise ValueError(f"{scheme}: needs HOST:PORT, got {rest!r}")
    try:
        port = int(port_text)
    except ValueError:
        raise ValueError(f"{scheme}: the port must be a number, got {port_text!r}") from None
    if not 0 <= port <= 65535 or (scheme == "udpout" and port == 0):
        raise ValueError(f"{scheme}: port out of range: {port}")
    return LinkSpec(scheme, host=host.strip("[]"), port=port)


def _serial(scheme: str, rest: str) -> LinkSpec:
    device, _, query = rest.partition("?")
    if not device:
        raise ValueError("serial: needs a device, e.g. serial:/dev/ttyUSB0?baud=57600")
    params = parse_qs(query)
    unknown = sorted(set(params) - {"baud"})
    if unknown:
        raise ValueError(f"serial: unknown parameter {unknown[0]!r} (known: baud)")
    try:
        baud = int(params.get("baud", ["57600"])[-1])
    except ValueError:
        raise ValueError("serial: baud must be a number") from None
    if baud <= 0:
        raise ValueError(f"serial: baud must be positive, got {baud}")
    return LinkSpec("serial", device=device, baud=baud)


_PARSERS: Final[Mapping[str, Callable[[str, str], LinkSpec]]] = {
    "udpin": _udp,
    "udp": lambda _scheme, rest: _udp("udpin", rest),
    "udpout": _udp,
    "serial": _serial,
}


def parse_link(url: str) -> LinkSpec:
    """Parse a link URL (see the module docstring).

    Args:
        url: ``udpin:127.0.0.1:14550``, ``udpout:10.0.0.2:14550``, ``serial:/dev/ttyACM0``.

    Returns:
        The parsed spec.

    Raises:
        ValueError: An unknown scheme or a malformed address.
    """
    if not isinstance(url, str):
        raise ValueError(f"a link URL must be text, got {url!r}")
    scheme, sep, rest = url.partition(":")
    parser = _PARSERS.get(scheme.lower()) if sep else None
    if parser is None:
        raise ValueError(f"unknown link {url!r} (schemes: {', '.join(_PARSERS)})")
    return parser(scheme.lower(), rest.removeprefix("//"))


class Link(ABC):
    """A byte link: whole datagrams (UDP) or chunks of a stream (serial)."""

    #: Whether each read is one whole datagram, to be parsed on its own.
    datagrams: ClassVar[bool] = False

    def receive(self, timeout: float) -> tuple[bytes, Any]:
        """Wait up to ``timeout`` real seconds for bytes, and say who sent them.

        Args:
            timeout: Real seconds.

        Returns:
            The bytes (empty on timeout) and their sender's address (None where a link has no
            addresses, as a serial port).

        Raises:
            OSError: The link failed.
        """
        return self.read(timeout), None

    def accept_peer(self, peer: Any) -> bool:
        """Send to ``peer`` from now on (a ``udpin`` link; others ignore it).

        Args:
            peer: An address :meth:`receive` returned.

        Returns:
            Whether the address changed.
        """
        return False

    @property
    def peer(self) -> Any:
        """Where writes go (None: nowhere yet, or a link without addresses)."""
        return None

    def pending(self) -> bool:
        """Whether bytes are waiting to be read (never blocks).

        Returns:
            True if a read would return at once.
        """
        return False

    @abstractmethod
    def read(self, timeout: float) -> bytes:
        """Wait up to ``timeout`` real seconds for bytes.

        Returns:
            What arrived (empty on timeout).

        Raises:
            OSError: The link failed.
        """

    @abstractmethod
    def write(self, data: bytes) -> bool:
        """Send bytes (thread-safe).

        Returns:
            False when there is nowhere to send yet (``udpin`` before the first datagram).

        Raises:
            OSError: The link failed.
        """

    @abstractmethod
    def close(self) -> None:
        """Close the link (idempotent)."""


class UdpLink(Link):
    """UDP: listen (``udpin``) or send to a fixed address (``udpout``).

    A ``udpin`` link sends nowhere until :meth:`accept_peer` names the address: receiving from
    an address never makes it the destination (another system on the network must not steal
    the replies).

    Args:
        spec: A ``udpin`` or ``udpout`` spec.

    Raises:
        OSError: The socket cannot be bound.
    """

    datagrams: ClassVar[bool] = True

    def __init__(self, spec: LinkSpec) -> None:
        family = socket.AF_INET6 if ":" in spec.host else socket.AF_INET
        self._sock = socket.socket(family, socket.SOCK_DGRAM)
        self._peer: Any = None
        self._listening = spec.scheme == "udpin"
        try:
            if spec.scheme == "udpin":
                self._sock.bind((spec.host, spec.port))
            else:
                self._sock.bind(("::" if family == socket.AF_INET6 else "0.0.0.0", 0))
                self._peer = (spec.host, spec.port)
        except OSError:
            self._sock.close()
            raise
        self._lock = threading.Lock()
        self.address: tuple[str, int] = self._sock.getsockname()[:2]

    def read(self, timeout: float) -> bytes:
        """See :meth:`Link.read` (one datagram; the sender is dropped: see :meth:`receive`)."""
        return self.receive(timeout)[0]

    def accept_peer(self, peer: Any) -> bool:
        """See :meth:`Link.accept_peer` (a ``udpout`` link keeps its fixed address)."""
        if not self._listening or peer is None:
            return False
        with self._lock:
            changed = bool(self._peer != peer)
            self._peer = peer
        return changed

    @property
    def peer(self) -> Any:
        """See :attr:`Link.peer`."""
        with self._lock:
            return self._peer

    def pending(self) -> bool:
        """See :meth:`Link.pending`."""
        try:
            ready, _, _ = select.select([self._sock], [], [], 0)
        except (OSError, ValueError):  # closed
            return False
        return bool(ready)

    def receive(self, timeout: float) -> tuple[bytes, Any]:
        """Wait up to ``timeout`` real seconds for one datagram.

        Args:
            timeout: Real seconds.

        Returns:
            The datagram and its sender (``b""`` and None on timeout).

        Raises:
            OSError: The socket failed.
        """
        self._sock.settimeout(max(timeout, 1e-3))
        try:
            data, peer = self._sock.recvfrom(65536)
        except (TimeoutError, ConnectionResetError):  # reset: ICMP "port unreachable"
            return b"", None
        return data, peer

    def send_to(self, data: bytes, peer: Any) -> bool:
        """Send one datagram to a given address.

        Args:
            data: The datagram.
            peer: The (host, port) address.

        Returns:
            False if it could not be sent (nobody listens, or the socket is closed).
        """
        try:
            self._sock.sendto(data, peer)
        except OSError:
            return False
        return True

    def write(self, data: bytes) -> bool:
        """See :meth:`Link.write`."""
        with self._lock:
            peer = self._peer
        if peer is None:
            return False
        return self.send_to(data, peer)

    def close(self) -> None:
        """See :meth:`Link.close`."""
        self._sock.close()


class SerialLink(Link):
    """A serial port through pyserial (imported when opened).

    Args:
        spec: A ``serial`` spec.

    Raises:
        DriverUnavailableError: pyserial is not installed.
        OSError: The port cannot be opened.
    """

    def __init__(self, spec: LinkSpec) -> None:
        try:
            serial = importlib.import_module("serial")
        except ImportError as err:
            raise DriverUnavailableError(
                "a serial MAVLink link needs pyserial: pip install pyserial"
            ) from err
        try:
            self._port: Any = serial.Serial(spec.device, spec.baud, timeout=0.05)
        except Exception as err:  # serial.SerialException is an OSError subclass or not
            raise OSError(f"cannot open {spec.device}: {err}") from err
        self._lock = threading.Lock()

    def read(self, timeout: float) -> bytes:
        """See :meth:`Link.read`."""
        self._port.timeout = max(timeout, 1e-3)
        first = self._port.read(1)
        if not first:
            return b""
        return bytes(first) + bytes(self._port.read(self._port.in_waiting or 0))

    def pending(self) -> bool:
        """See :meth:`Link.pending`."""
        try:
            return bool(self._port.in_waiting)
        except Exception:  # a closed or unplugged port: nothing to read
            return False

    def write(self, data: bytes) -> bool:
        """See :meth:`Link.write`."""
        with self._lock:
            self._port.write(data)
        return True

    def close(self) -> None:
        """See :meth:`Link.close`."""
        self._port.close()


def open_link(spec: LinkSpec) -> Link:
    """Open the link a spec names.

    Args:
        spec: From :func:`parse_link`.

    Returns:
        The open link.

    Raises:
        OSError: It cannot be opened.
        DriverUnavailableError: Its library is missing.
    """
    if spec.scheme == "serial":
        return SerialLink(spec)
    return UdpLink(spec)
