"""Component Manager with real processes: failover, reliability, pipelines, actions, bad input."""

from __future__ import annotations

import os
import signal
from collections.abc import Iterator
from pathlib import Path

import pytest
from _statuses import Statuses

from temoto import ActionEngine, Result
from temoto.core.registrar import Registrar, Status
from temoto.errors import (
    ComponentNotFoundError,
    ConfigError,
    PipelineError,
    ResourceLoadError,
)
from temoto.managers.component import (
    ChannelReader,
    ComponentDescription,
    ComponentManager,
    ComponentManagerClient,
    ComponentRequest,
    PipelineRequest,
)
from temoto.managers.process import ProcessManager

REPO = Path(__file__).resolve().parents[2]
DESCRIPTIONS = REPO / "examples" / "components" / "components.yaml"
ACTIONS = REPO / "temoto" / "actions" / "builtin" / "component"
WAIT = 10.0
RANGE = ("lidar_3d", "depth_camera", "lidar_2d")  # priority order


@pytest.fixture
def setup(
    request: pytest.FixtureRequest,
) -> Iterator[tuple[Registrar, ProcessManager, ComponentManager]]:
    registrar = Registrar("r1")
    processes = ProcessManager(registrar, grace=1.0)
    manager = ComponentManager(
        registrar, files=[DESCRIPTIONS], channel_prefix=f"test-{os.getpid()}"
    )
    try:
        yield registrar, processes, manager
    finally:
        for info in registrar.resources():
            for ref in info.references:
                if not ref.holder:
                    registrar.release(ref.id)
        manager.shutdown()
        processes.shutdown()
        registrar.close()


def consumer(name: str) -> ChannelReader:
    return ChannelReader(f"unix:@test-{os.getpid()}-{name}")


def origin(data: bytes) -> str:
    """The component a datagram came from (the last ``|``-separated part, before the seq)."""
    return data.decode().rsplit("|", 1)[-1].split(" ")[0]


def from_(name: str) -> object:
    return lambda data: origin(data) == name


def test_failover_across_three_candidates(
    setup: tuple[Registrar, ProcessManager, ComponentManager],
) -> None:
    registrar, processes, manager = setup
    client = ComponentManagerClient(registrar)
    statuses = Statuses()
    with consumer("scan") as reader:
        handle = client.request(
            "range_sensor", outputs={"scan": reader.channel}, client="ocs", on_status=statuses
        )
        assert handle.channel() == reader.channel
        for i, name in enumerate(RANGE):
            assert handle.name == name
            assert reader.recv_until(from_(name), WAIT) is not None, name
            # energy conservation: only the active candidate runs
            assert processes.running() == [handle.response.pid]
            assert len(registrar.served("process")) == 1
            os.kill(handle.response.pid, signal.SIGKILL)
            if i < 2:
                assert reader.recv_until(from_(RANGE[i + 1]), WAIT) is not None
                warnings = statuses.wait(Status.WARNING, i + 1)
                assert warnings[-1].message.startswith(f"switched from r1/{name} to r1/")
        fatal = statuses.wait(Status.FATAL)
        assert "no substitute" in fatal[0].message
    assert handle.response.switches == 2
    assert handle.response.failed == ("r1/lidar_3d", "r1/depth_camera")
    assert manager.stats["failovers"] == 2
    assert manager.stats["exhausted"] == 1
    client.release(handle)
    assert registrar.resources() == []
    assert processes.running() == []


def test_reliability_updates(setup: tuple[Registrar, ProcessManager, ComponentManager]) -> None:
    registrar, _, manager = setup
    client = ComponentManagerClient(registrar)
    assert [manager.reliability(n) for n in RANGE] == [0.8, 0.8, 0.8]
    with consumer("rel") as reader:
        handle = client.request("range_sensor", outputs={"scan": reader.channel})
        os.kill(handle.response.pid, signal.SIGKILL)
        assert reader.recv_until(from_("depth_camera"), WAIT) is not None
        # one failure in a window of 100 pre-filled with 0.8
        assert manager.reliability("lidar_3d") == pytest.approx(0.792)
        client.release(handle)
    # served until released: a success
    assert manager.reliability("depth_camera") == pytest.approx(0.802)
    assert manager.reliability("lidar_2d") == 0.8
    # with equal priorities, reliability ranks: make the two cameras' priorities tie
    ranked = manager.candidates("range_sensor")
    assert [c.description.name for c in ranked] == list(RANGE)  # priority still first
    manager.add(
        [
            ComponentDescription("a_sensor", "tie", "/bin/true", priority=1, reliability=0.5),
            ComponentDescription("b_sensor", "tie", "/bin/true", priority=1, reliability=0.9),
        ]
    )
    assert [c.description.name for c in manager.candidates("tie")] == ["b_sensor", "a_sensor"]


def test_no_failover_when_the_request_forbids_it(
    setup: tuple[Registrar, ProcessManager, ComponentManager],
) -> None:
    registrar, processes, _ = setup
    statuses = Statuses()
    res = registrar.call(
        "component", ComponentRequest("range_sensor", failover=False), on_status=statuses
    )
    os.kill(res.response.pid, signal.SIGKILL)
    fatal = statuses.wait(Status.FATAL)
    assert "allows no failover" in fatal[0].message
    assert processes.running() == []
    registrar.release(res.id)


def test_equal_requests_share_one_component(
    setup: tuple[Registrar, ProcessManager, ComponentManager],
) -> None:
    registrar, processes, _ = setup
    one = registrar.call("component", ComponentRequest("camera"), client="a")
    two = registrar.call("component", ComponentRequest("camera"), client="b")
    assert one.resource_id == two.resource_id
    assert len(processes.running()) == 1
    assert one.response.output().startswith("unix:@test-")
    registrar.release(one.id)
    assert len(processes.running()) == 1
    registrar.release(two.id)
    assert processes.running() == []


def test_pipeline_rewired_on_camera_failover(
    setup: tuple[Registrar, ProcessManager, ComponentManager],
) -> None:
    registrar, processes, manager = setup
    client = ComponentManagerClient(registrar)
    statuses = Statuses()
    with consumer("tracks") as reader:
        pipe = client.request_pipeline(
            "tracking", outputs={"tracks": reader.channel}, on_status=statuses
        )
        assert reader.recv_until(from_("camera_front"), WAIT) is not None
        before = pipe.segments()
        assert {s: r.name for s, r in before.items()} == {
            "camera": "camera_front",
            "detector": "blob_detector",
            "tracker": "kalman_tracker",
        }
        assert len(processes.running()) == 3
        os.kill(before["camera"].pid, signal.SIGKILL)
        data = reader.recv_until(from_("camera_rear"), WAIT)
        assert data is not None
        assert data.startswith(b"tracker|detector|camera_rear ")
        after = pipe.segments()
        assert after["camera"].name == "camera_rear"
        # re-wired: the substitute publishes where the detector listens; the rest kept running
        assert after["detector"].pid == before["detector"].pid
        assert after["tracker"].pid == before["tracker"].pid
        assert after["camera"].outputs == before["camera"].outputs
        warning = statuses.wait(Status.WARNING)[0]
        assert warning.hops == ("component", "pipeline")
        assert "camera_rear" in warning.message
        assert len(processes.running()) == 3
    client.release(pipe)
    assert registrar.resources() == []
    assert processes.running() == []
    assert manager.active() == {}


def test_bad_input_is_typed_and_loses_nothing(
    setup: tuple[Registrar, ProcessManager, ComponentManager], tmp_path: Path
) -> None:
    registrar, processes, manager = setup
    client = ComponentManagerClient(registrar)
    held = client.request("camera", client="keeper")
    before = (registrar.resources(), registrar.references(), processes.running())

    with pytest.raises(ComponentNotFoundError, match="no component of type 'sonar'"):
        client.request("sonar")
    with pytest.raises(ResourceLoadError) as caught:
        registrar.call("component", ComponentRequest("sonar"))
    assert isinstance(caught.value.__cause__, ComponentNotFoundError)
    with pytest.raises(ComponentNotFoundError, match="no pipeline template named 'nope'"):
        client.request_pipeline("nope")
    cyclic = tmp_path / "cyclic.yaml"
    cyclic.write_text(
        "templates:\n"
        "  - name: loop\n"
        "    segments:\n"
        "      detector: {type: detector, inputs: {image: tracker.tracks}}\n"
        "      tracker: {type: tracker, inputs: {detections: detector.detections}}\n"
    )
    with pytest.raises(PipelineError, match="cycle: detector -> tracker -> detector"):
        manager.add_file(cyclic)
    unknown = tmp_path / "unknown.yaml"
    unknown.write_text(
        "templates:\n"
        "  - name: sonar_tracking\n"
        "    segments:\n"
        "      sonar: {type: sonar}\n"
        "      tracker: {type: tracker, inputs: {detections: sonar.pings}}\n"
    )
    manager.add_file(unknown)  # types are checked per request: they may come later
    with pytest.raises(ComponentNotFoundError, match="segment 'sonar'"):
        client.request_pipeline("sonar_tracking")
    with pytest.raises(ResourceLoadError) as caught:
        registrar.call("pipeline", PipelineRequest("sonar_tracking"))
    assert isinstance(caught.value.__cause__, ComponentNotFoundError)
    # a candidate that cannot start (program missing): the next one is used
    manager.add(
        [
            ComponentDescription(
                "ghost", "camera", "/nonexistent/cam", outputs=("image",), priority=9
            )
        ]
    )
    statuses = Statuses()
    other = client.request("camera", outputs={"image": "unix:@test-x"}, on_status=statuses)
    assert other.name == "camera_front"
    assert other.response.failed == ("r1/ghost",)
    assert manager.reliability("ghost") == pytest.approx(0.792)
    client.release(other)
    # a malformed description file: nothing of it is added
    bad = tmp_path / "bad.yaml"
    bad.write_text(
        "components:\n"
        "  - {name: ok_one, type: camera, executable: /bin/true}\n"
        "  - {name: bad one, type: camera, executable: /bin/true}\n"
    )
    with pytest.raises(ConfigError, match=r"components\[1\]: name must be an identifier"):
        manager.add_file(bad)
    assert "ok_one" not in [d.name for d in manager.descriptions()]
    with pytest.raises(ConfigError, match="described twice"):
        manager.add_file(DESCRIPTIONS)
    with pytest.raises(ValueError, match="bad channel"):
        ComponentRequest("camera", outputs={"image": "tcp://x"})
    assert (registrar.resources(), registrar.references(), processes.running()) == before
    client.release(held)


def test_action_in_a_graph_requests_a_component(
    setup: tuple[Registrar, ProcessManager, ComponentManager],
) -> None:
    registrar, processes, _ = setup
    graph = {
        "graph_name": "sense",
        "graph_entry": [{"name": "RequestComponent", "instance_id": 0}],
        "graph_exit": [{"name": "WaitForComponentData", "instance_id": 0}],
        "actions": [
            {
                "name": "RequestComponent",
                "instance_id": 0,
                "type": "sync",
                "input_parameters": {
                    "component_type": {"pvf_type": "string", "pvf_value": "range_sensor"}
                },
                "children": [{"name": "WaitForComponentData", "instance_id": 0}],
            },
            {
                "name": "WaitForComponentData",
                "instance_id": 0,
                "type": "sync",
                "parents": [{"name": "RequestComponent", "instance_id": 0}],
                "input_parameters": {
                    "count": {"pvf_type": "number", "pvf_value": 3},
                    "timeout": {"pvf_type": "number", "pvf_value": 10},
                },
            },
        ],
    }
    with ActionEngine("r1", actions=[ACTIONS], registrar=registrar) as engine:
        outcome = engine.run(graph, timeout=30)
        assert outcome.result is Result.TRUE, outcome.errors
        snapshot = engine.graph_json("sense")
    logs = [m for a in snapshot["actions"] for m in a.get("runtime", {}).get("messages", [])]
    assert any("lidar_3d" in str(m) for m in logs), logs
    assert registrar.resources() == []
    assert processes.running() == []
