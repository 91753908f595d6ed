"""Component Manager across robots: a candidate on robot B, found through the RIS, used by A."""

from __future__ import annotations

import itertools
import os
import signal
import sys
import threading
from collections.abc import Iterator
from contextlib import ExitStack
from pathlib import Path

import pytest
from _statuses import Statuses

from temoto.core.registrar import Registrar, Status
from temoto.errors import ComponentNotFoundError
from temoto.fleet.resources import RemoteResources
from temoto.fleet.ris import ResourceInfoSync, RobotInfo
from temoto.managers.component import (
    ChannelReader,
    ComponentDescription,
    ComponentManager,
    ComponentManagerClient,
)
from temoto.managers.process import ProcessManager
from temoto.transport import FleetAuth, FleetLink, InProcessTransport
from temoto.transport.inprocess import live_buses

SENSOR = str(Path(__file__).resolve().parents[2] / "examples" / "components" / "sim_sensor.py")
KEY = bytes(range(32))
WAIT = 10.0
_buses = itertools.count()


def camera(name: str, robot: str, priority: int) -> ComponentDescription:
    return ComponentDescription(
        name,
        "camera",
        sys.executable,
        ("-S", "-I", SENSOR, "--output", "{output:image}", "--name", "{name}", "--rate", "200"),
        outputs=("image",),
        priority=priority,
        robot=robot,
    )


#: Every robot reads the same descriptions; each runs its own and reaches the others' remotely.
CAMERAS = [camera("cam_a", "A", 2), camera("cam_b", "B", 1)]


class Robot:
    def __init__(self, name: str, bus: str, stack: ExitStack) -> None:
        transport = stack.enter_context(InProcessTransport(bus))
        link = FleetLink(transport, FleetAuth("component-fleet", name, KEY))
        self.registrar = Registrar(name)
        stack.callback(self.registrar.close)
        self.processes = ProcessManager(self.registrar, grace=1.0)
        stack.callback(self.processes.shutdown)
        self.ris = stack.enter_context(ResourceInfoSync(link, self.registrar, name, period_s=0.1))
        stack.enter_context(RemoteResources(link, self.registrar, self.ris))
        self.components = ComponentManager(
            self.registrar, ris=self.ris, channel_prefix=f"test-{os.getpid()}-{name}"
        )
        stack.callback(self.components.shutdown)
        self.components.add(CAMERAS)
        stack.callback(self.release_all)

    def release_all(self) -> None:
        for info in self.registrar.resources():
            for ref in info.references:
                if not ref.holder and not ref.client.startswith(f"{self.registrar.name}/"):
                    self.registrar.release(ref.id)


@pytest.fixture
def fleet(request: pytest.FixtureRequest) -> Iterator[tuple[Robot, Robot]]:
    bus = f"component-{request.node.name}-{next(_buses)}"
    with ExitStack() as stack:
        b = Robot("B", bus, stack)
        a = Robot("A", bus, stack)
        hears(a, "B")
        hears(b, "A")
        yield a, b
    assert bus not in live_buses()


def hears(robot: Robot, other: str) -> None:
    """Wait until ``robot`` hears ``other`` offering ``"component"`` (on the RIS's callbacks)."""
    heard = threading.Event()

    def seen(info: RobotInfo) -> None:
        if info.robot == other and "component" in info.servers:
            heard.set()

    cancel = robot.ris.subscribe(on_joined=seen, on_changed=seen)
    try:
        if other not in robot.ris.providers("component"):
            assert heard.wait(WAIT), f"{robot.registrar.name} never heard {other}"
    finally:
        cancel()


def test_failover_to_a_camera_on_another_robot(fleet: tuple[Robot, Robot]) -> None:
    a, b = fleet
    ranked = a.components.candidates("camera")
    assert [(c.key, c.local) for c in ranked] == [("A/cam_a", True), ("B/cam_b", False)]
    assert [c.key for c in a.components.candidates("camera", local_only=True)] == ["A/cam_a"]
    client = ComponentManagerClient(a.registrar)
    statuses = Statuses()
    with ChannelReader(f"unix:@test-{os.getpid()}-remote-view") as reader:
        handle = client.request(
            "camera", outputs={"image": reader.channel}, client="ocs", on_status=statuses
        )
        assert handle.response.robot == "A"
        assert reader.recv_until(lambda d: d.startswith(b"cam_a "), WAIT) is not None
        assert b.processes.running() == []  # the remote one is not started while not needed
        os.kill(handle.response.pid, signal.SIGKILL)
        # the escort's camera now feeds A's consumer, on the same channel
        assert reader.recv_until(lambda d: d.startswith(b"cam_b "), WAIT) is not None
        assert statuses.first(Status.WARNING).message.startswith("switched from A/cam_a to B/cam_b")
        assert handle.response.robot == "B"
        assert a.processes.running() == []
        assert b.processes.running() == [handle.response.pid]
        # the remote candidate fails too: nothing is left, A's consumer is told
        os.kill(handle.response.pid, signal.SIGKILL)
        assert "no substitute" in statuses.first(Status.FATAL).message
    assert a.components.reliability("cam_b", "B") == pytest.approx(0.792)
    client.release(handle)
    assert a.registrar.resources() == []


def test_local_wins_a_tie_and_remote_needs_the_ris(fleet: tuple[Robot, Robot]) -> None:
    a, b = fleet
    a.components.add([camera("twin", "A", 5), camera("twin", "B", 5)])
    b.components.add([camera("twin", "A", 5), camera("twin", "B", 5)])
    assert [c.key for c in a.components.candidates("camera")][:2] == ["A/twin", "B/twin"]
    # a type offered only by a robot nobody hears: a clear error
    a.components.add([ComponentDescription("far_cam", "thermal", "/bin/true", robot="C")])
    with pytest.raises(ComponentNotFoundError, match="robot\\(s\\) C not heard"):
        ComponentManagerClient(a.registrar).request("thermal")
    # B asks for A's camera explicitly, by name
    handle = ComponentManagerClient(b.registrar).request("camera", name="cam_a")
    assert handle.response.robot == "A"
    assert len(a.processes.running()) == 1
    assert b.processes.running() == []
    ComponentManagerClient(b.registrar).release(handle)
