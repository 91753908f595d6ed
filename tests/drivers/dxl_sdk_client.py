"""A dynamixel-sdk client for in-process servo simulators (a helper of the Dynamixel tests).

dynamixel-sdk gives up on a status packet after 2 x LATENCY_TIMER + 2 ms of real time. A test's
simulator is a thread of the test's own process: on a loaded machine it may not run at all
within that window, and a reply that is on its way reads as a timeout (whole-suite runs at
load 10-16 failed a READ, a REBOOT and a SYNC_READ so). :func:`sdk_client` gives a
``PortHandler`` whose timeout also needs the simulator to have served every byte this client
wrote (its ``bytes_served``) and this client to have read every byte of reply the simulator
wrote meanwhile (its ``bytes_sent``; a pseudo-terminal passes bytes on a moment later, so an
empty input alone proves nothing): then nothing more is coming and the timeout is the true
answer, however slowly the simulator ran. A deadline (:data:`STUCK`) past the SDK's own keeps
a stuck simulator from hanging a test.
"""

from __future__ import annotations

from typing import Any, Protocol

import pytest

dxl: Any = pytest.importorskip("dynamixel_sdk")

#: Milliseconds past the SDK's timeout after which a busy simulator counts as stuck.
STUCK = 30_000.0


class Peer(Protocol):
    """The simulator's byte counts."""

    @property
    def bytes_served(self) -> int:
        """Bytes read from the host and fully answered."""

    @property
    def bytes_sent(self) -> int:
        """Bytes of status packets written (counted before ``bytes_served``)."""


class _PatientPort(dxl.PortHandler):  # type: ignore[misc]
    """``PortHandler`` whose reply timeout waits until the simulator has served this client."""

    def __init__(self, path: str, peer: Peer) -> None:
        super().__init__(path)
        self.peer = peer
        self.written = 0
        self.received = 0
        self._served0, self._sent0 = peer.bytes_served, peer.bytes_sent

    def writePort(self, packet: Any) -> Any:  # noqa: N802 (the SDK's name)
        sent = super().writePort(packet)
        self.written += sent or 0
        return sent

    def readPort(self, length: int) -> Any:  # noqa: N802 (the SDK's name)
        data = super().readPort(length)
        self.received += len(data)
        return data

    def clearPort(self) -> None:  # noqa: N802 (the SDK's name)
        self.readPort(self.ser.in_waiting)  # dropped, but counted

    def isPacketTimeout(self) -> bool:  # noqa: N802 (the SDK's name)
        since = self.getTimeSinceStart()
        if since <= self.packet_timeout:
            return False
        peer = self.peer
        sent = peer.bytes_sent - self._sent0  # read first: counted before bytes_served
        quiet = peer.bytes_served - self._served0 >= self.written and self.received >= sent
        if not quiet and since <= self.packet_timeout + STUCK:
            return False
        self.packet_timeout = 0
        return True


def sdk_client(path: str, peer: Peer) -> tuple[Any, Any]:
    """An open dynamixel-sdk port (1 Mbaud) and Protocol 2.0 packet handler on ``path``.

    Args:
        path: The simulator's pseudo-terminal.
        peer: The simulator (its byte counts).

    Returns:
        (port, packet handler); close the port after use.
    """
    port = _PatientPort(path, peer)
    assert port.openPort()
    assert port.setBaudRate(1_000_000)
    return port, dxl.PacketHandler(2.0)
