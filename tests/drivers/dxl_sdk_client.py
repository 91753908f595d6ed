"""dynamixel-sdk clients for in-process servo simulators (a helper of the Dynamixel tests).

dynamixel-sdk gives up on a status packet after a few tens of milliseconds of real time (2 x
LATENCY_TIMER + 2 ms; our driver's ``reply_timeout``). A test's simulator is a thread of the
test's own process: on a loaded machine it may not run at all within that window, and a reply
that is on its way reads as a timeout (whole-suite runs at load 10-16 failed READs, a REBOOT, a
SYNC_READ and driver bring-ups so). A real servo is never starved by its host's load.

:func:`make_patient` changes one ``PortHandler`` so that its timeout also needs the simulator to
have served every byte the port wrote (its ``bytes_served``) and the port to have read every
byte of reply the simulator wrote meanwhile (its ``bytes_sent``; a pseudo-terminal passes bytes
on a moment later, so an empty input alone proves nothing): then nothing more is coming and the
timeout is the true answer, however slowly the simulator ran. A simulator with realism on (late
and lost replies on purpose) keeps the real-time timeout. A deadline (:data:`STUCK`) past the
SDK's own keeps a stuck simulator from hanging a test.

:func:`sdk_client` is a test's own SDK client so; the :func:`patient_sim_links` fixture makes
the driver's ports (:class:`~temoto.drivers.dynamixel._sdk.SdkPort`) so for every simulator
made during the test and every emulator the test registers.
"""

from __future__ import annotations

import os
import select
from typing import Any, Protocol

import pytest

from temoto.drivers.dynamixel import _sdk
from temoto.drivers.dynamixel.sim import SimDynamixelChain

dxl: Any = pytest.importorskip("dynamixel_sdk")

#: Milliseconds past the SDK's timeout after which a busy simulator counts as stuck.
STUCK = 30_000.0


class Peer(Protocol):
    """A simulator's pseudo-terminal and byte counts."""

    @property
    def path(self) -> str:
        """The pseudo-terminal a client opens."""

    @property
    def bytes_served(self) -> int:
        """Bytes read from the host and fully answered."""

    @property
    def bytes_sent(self) -> int:
        """Bytes of status packets written (counted before ``bytes_served``)."""


def make_patient(port: Any, peer: Peer) -> None:
    """Make ``port`` (a ``dxl.PortHandler``) time a reply out only once ``peer`` is done."""
    counts = {"written": 0, "received": 0}
    served0, sent0 = peer.bytes_served, peer.bytes_sent
    write, read, timed_out = port.writePort, port.readPort, port.isPacketTimeout

    def write_port(packet: Any) -> Any:
        sent = write(packet)
        counts["written"] += sent or 0
        return sent

    def read_port(length: int) -> Any:
        data = read(length)
        counts["received"] += len(data)
        if not data and length > 0 and port.getTimeSinceStart() > port.packet_timeout:
            select.select([port.ser.fileno()], [], [], 0.01)  # waiting on: do not spin
        return data

    def clear_port() -> None:
        read_port(port.ser.in_waiting)  # dropped, but counted

    def is_packet_timeout() -> bool:
        realism = getattr(peer, "realism", None)
        if realism is not None and realism.enabled:
            return bool(timed_out())  # late replies on purpose: the real-time timeout
        since = port.getTimeSinceStart()
        if since <= port.packet_timeout:
            return False
        sent = peer.bytes_sent - sent0  # read first: counted before bytes_served
        quiet = peer.bytes_served - served0 >= counts["written"] and counts["received"] >= sent
        if not quiet and since <= port.packet_timeout + STUCK:
            return False
        port.packet_timeout = 0
        return True

    port.writePort, port.readPort, port.clearPort = write_port, read_port, clear_port
    port.isPacketTimeout = is_packet_timeout


def sdk_client(path: str, peer: Peer) -> tuple[Any, Any]:
    """An open dynamixel-sdk port (1 Mbaud) and Protocol 2.0 packet handler on ``path``.

    Args:
        path: The simulator's pseudo-terminal.
        peer: The simulator (its byte counts).

    Returns:
        (port, packet handler); close the port after use.
    """
    port = dxl.PortHandler(path)
    make_patient(port, peer)
    assert port.openPort()
    assert port.setBaudRate(1_000_000)
    return port, dxl.PacketHandler(2.0)


class SimLinks:
    """The simulators of one test by pseudo-terminal (see :func:`patient_sim_links`)."""

    def __init__(self) -> None:
        self.peers: dict[str, Peer] = {}

    def add(self, peer: Peer) -> None:
        """Register a simulator written in a test (ours register themselves)."""
        self.peers[os.path.realpath(peer.path)] = peer


@pytest.fixture
def patient_sim_links(monkeypatch: pytest.MonkeyPatch) -> SimLinks:
    """The driver's ports to this test's simulators time out only once the simulator is done."""
    links = SimLinks()
    sim_init, port_init = SimDynamixelChain.__init__, _sdk.SdkPort.__init__

    def init_sim(self: SimDynamixelChain, *args: Any, **kwargs: Any) -> None:
        sim_init(self, *args, **kwargs)
        links.add(self)

    def init_port(self: _sdk.SdkPort, path: str, *args: Any, **kwargs: Any) -> None:
        port_init(self, path, *args, **kwargs)
        peer = links.peers.get(os.path.realpath(path))
        if peer is not None:
            make_patient(self._port, peer)

    monkeypatch.setattr(SimDynamixelChain, "__init__", init_sim)
    monkeypatch.setattr(_sdk.SdkPort, "__init__", init_port)
    return links
