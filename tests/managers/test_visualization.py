"""The Visualization Manager and the live Foxglove server, seen by an independent client.

The client (:mod:`temoto.testing.foxglove_client`) speaks the Foxglove WebSocket protocol
from its specification on the ``websockets`` package, not through the SDK the server uses.
The robot is the simulated Dynamixel arm (``hw_profiles/sim_arm.yaml``), in-process.
"""

from __future__ import annotations

import builtins
import itertools
import logging
import math
import os
import signal
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from _displays import show_display_graph
from _robots import robot_manager

from temoto import ActionEngine, Result
from temoto.actions.builtin import VISUALIZATION_ACTIONS
from temoto.config import load_profile
from temoto.core.registrar import Registrar, Status, StatusUpdate
from temoto.errors import ConfigError
from temoto.managers.robot import RobotManager, RobotManagerClient
from temoto.managers.visualization import DisplayRequest, VisualizationManager
from temoto.managers.visualization.foxglove import FoxgloveServer, LiveRecorder
from temoto.testing.foxglove_client import FoxgloveClient

pytest.importorskip("foxglove")
pytest.importorskip("websockets")

PROFILES = Path(__file__).resolve().parents[2] / "hw_profiles"
WAIT = 10.0
JOINTS = "/display/robot_joints/joints"


@pytest.fixture
def server() -> Iterator[FoxgloveServer]:
    with FoxgloveServer(port=0) as srv:
        yield srv


@pytest.fixture
def arm() -> Iterator[tuple[Registrar, RobotManager]]:
    with robot_manager("test-viz", load_profile(PROFILES / "sim_arm.yaml")) as pair:
        yield pair


@pytest.fixture
def viz(
    arm: tuple[Registrar, RobotManager], server: FoxgloveServer
) -> Iterator[tuple[Registrar, RobotManager, VisualizationManager]]:
    registrar, robots = arm
    manager = VisualizationManager(registrar, server)
    try:
        yield registrar, robots, manager
    finally:
        for ref in registrar.references():  # displays first (newest first), then the robot
            registrar.release(ref.id)
        manager.shutdown()


def test_a_display_request_is_checked_and_named_from_what_it_shows() -> None:
    request = DisplayRequest("robot", "joints")
    assert (request.name, request.kind, request.topic) == (
        "robot_joints",
        "temoto.JointStates",
        JOINTS,
    )
    # what a restarted registrar rebuilds from the journal is the same request
    assert DisplayRequest(**vars(request)) == request
    assert DisplayRequest("robot", "joints", name="robot_joints") == request
    assert DisplayRequest("log").kind == "foxglove.Log"
    with pytest.raises(ValueError, match="unknown display source 'lidar'"):
        DisplayRequest("lidar")
    with pytest.raises(ValueError, match="no field 'arm'"):
        DisplayRequest("robot", "arm")
    with pytest.raises(ValueError, match=r"shown as temoto\.JointStates, not foxglove\.Grid"):
        DisplayRequest("robot", "joints", kind="foxglove.Grid")
    with pytest.raises(ValueError, match="needs a target"):
        DisplayRequest("component")
    sensor = DisplayRequest("component", target="range_sensor", candidate="lidar_2d")
    assert sensor.topic == "/display/component_range_sensor_lidar_2d_data/data"
    with pytest.raises(ValueError, match="rate_hz must be positive"):
        DisplayRequest("robot", "pose", rate_hz=0)


def test_without_the_sdk_the_server_names_the_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    real_import = builtins.__import__

    def no_foxglove(name: str, *args: Any, **kwargs: Any) -> Any:
        if name == "foxglove" or name.startswith("foxglove."):
            raise ImportError(name)
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_foxglove)
    with pytest.raises(ConfigError, match=r"pip install 'temoto\[foxglove\]'") as err:
        FoxgloveServer(port=0)
    assert "\n" not in str(err.value)


def test_the_live_server_carries_the_recordings_topics_and_values(
    arm: tuple[Registrar, RobotManager], server: FoxgloveServer
) -> None:
    registrar, _ = arm
    robot = RobotManagerClient(registrar).request(client="test")
    assert robot.move_to_pose("reach").wait(WAIT)
    live = LiveRecorder(server)
    try:
        live.graph_started("patrol", 0.0)
        live.log(2, "hello", "patrol/Say_0")
        live.sample(robot, rate_hz=20)
        with FoxgloveClient(server.url) as client:
            wanted = {
                "/temoto/graphs": "temoto.GraphEvent",
                "/temoto/log": "foxglove.Log",
                "/sim_arm/joint_states": "temoto.JointStates",
                "/sim_arm/health": "temoto.RobotHealth",
            }
            client.wait(lambda c: wanted.items() <= c.topics().items())
            assert client.server_info["op"] == "serverInfo"
            assert client.server_info["name"] == "temoto"
            channel = client.channels[client.channel_id("/sim_arm/joint_states")]
            assert (channel["encoding"], channel["schemaEncoding"]) == ("json", "jsonschema")
            sub = client.subscribe("/sim_arm/joint_states")
            joints = client.first_message(sub).payload
            # sampled after the motion reached "reach" (within the profile's tolerance, 0.03 rad)
            reach = {"shoulder_pan": 0.6, "shoulder_lift": 0.8, "elbow": -1.0, "wrist_pitch": 0.4}
            reach |= {"wrist_roll": 0.0, "gripper": 0.8}
            assert joints["name"] == list(robot.joint_positions())
            assert joints["position"] == pytest.approx([reach[n] for n in joints["name"]], abs=0.04)
            assert set(joints["timestamp"]) == {"sec", "nsec"}
            # a late subscriber gets the last value at once (the log was put before it came)
            log = client.first_message(client.subscribe("/temoto/log")).payload
            assert (log["message"], log["level"], log["name"]) == ("hello", 2, "patrol/Say_0")
    finally:
        live.close()
        registrar.release(robot.resource.id)


def test_a_display_is_advertised_while_held_and_shared_by_equal_requests(
    viz: tuple[Registrar, RobotManager, VisualizationManager], server: FoxgloveServer
) -> None:
    registrar, _, manager = viz
    with FoxgloveClient(server.url) as client:
        client.wait(lambda c: bool(c.server_info))
        t0 = time.monotonic()
        first = registrar.call("display", DisplayRequest("robot", "joints"), client="a")
        client.wait(lambda c: JOINTS in c.topics(), timeout=WAIT)
        advertised = next(
            t for t, op, topic in client.events if op == "advertise" and topic == JOINTS
        )
        assert advertised - t0 < WAIT  # the load itself opens the arm's driver
        assert client.topics()[JOINTS] == "temoto.JointStates"
        assert first.response.topics == (JOINTS,)
        assert first.response.source == "robot sim_arm joints"
        # the robot is a dependency of the display
        assert [d.server for d in registrar.dependencies(first.resource_id)] == ["robot"]
        second = registrar.call("display", DisplayRequest("robot", "joints"), client="b")
        assert second.resource_id == first.resource_id
        assert list(manager.displays()) == ["robot_joints"]
        message = client.first_message(client.subscribe(JOINTS)).payload
        assert message["name"][0] == "shoulder_pan"
        assert len(message["position"]) == 6
        # one consumer lets go: still shown; the last one: unadvertised within 1 s
        assert not registrar.release(first.id)
        assert JOINTS in server.topics()
        t1 = time.monotonic()
        assert registrar.release(second.id)
        client.wait(lambda c: JOINTS not in c.topics(), timeout=WAIT)
        gone = next(t for t, op, topic in client.events if op == "unadvertise" and topic == JOINTS)
        assert gone - t1 < 1.0
        assert manager.displays() == {}
        assert registrar.served("robot") == []  # released with the display


def test_a_late_subscriber_gets_the_displays_last_message(server: FoxgloveServer) -> None:
    registrar = Registrar("test-late")
    manager = VisualizationManager(registrar, server)
    try:
        ref = registrar.call("display", DisplayRequest("log", target="late"), client="a")
        # one message, before any client: nothing else comes on this channel
        logging.getLogger("temoto.action.late.Say_0").warning("battery low")
        assert manager.displays()["log_late_log"].count == 1
        with FoxgloveClient(server.url) as client:
            topic = "/display/log_late_log/log"
            client.wait(lambda c: topic in c.topics())
            message = client.first_message(client.subscribe(topic)).payload
            assert (message["message"], message["level"]) == ("battery low", 3)
            assert message["name"] == "temoto.action.late.Say_0"
        registrar.release(ref.id)
    finally:
        manager.shutdown()
        registrar.close()


def test_the_robots_fault_reaches_the_displays_consumers(
    viz: tuple[Registrar, RobotManager, VisualizationManager],
) -> None:
    registrar, robots, _ = viz
    got: list[StatusUpdate] = []
    cond = threading.Condition()

    def on_status(update: StatusUpdate) -> None:
        with cond:
            got.append(update)
            cond.notify_all()

    registrar.call("display", DisplayRequest("robot", "joints"), client="op", on_status=on_status)
    robots.simulator("arm").inject("silence")
    # a WARNING: the arm's recovery runs (FATAL only when nothing brings a device back)
    with cond:
        assert cond.wait_for(lambda: any(u.status is Status.WARNING for u in got), WAIT), got
    fatal = next(u for u in got if u.status is Status.WARNING)
    assert fatal.hops == ("driver", "robot", "display")
    assert "arm" in fatal.message


GRAPH = show_display_graph("show", source="log", display_name="ops", duration=0.5)


def test_show_display_holds_a_display_for_its_node(server: FoxgloveServer) -> None:
    registrar = Registrar("test-show")
    manager = VisualizationManager(registrar, server)
    seen: list[tuple[str, str]] = []
    manager.add_listener(lambda event, response: seen.append((event, response.name)))
    try:
        with ActionEngine("show", actions=[VISUALIZATION_ACTIONS], registrar=registrar) as engine:
            outcome = engine.run(GRAPH, timeout=30)
        assert outcome.result is Result.TRUE, outcome.errors
        assert seen == [("loaded", "ops"), ("released", "ops")]
        assert manager.displays() == {}
        assert "/display/ops/log" not in server.topics()
    finally:
        manager.shutdown()
        registrar.close()


def test_a_failed_sensors_display_is_unadvertised_and_the_next_ones_advertised(
    server: FoxgloveServer,
) -> None:
    # Demonstration 1 as the thesis has it: the operator's display shows one range sensor; when
    # that sensor fails, its display fails with it and is released, and the next one's loaded.
    from temoto.demos.sensor_redundancy import SENSORS
    from temoto.managers import ProcessManager
    from temoto.managers.component import ComponentManager

    registrar = Registrar("test-viz-sensors")
    processes = ProcessManager(registrar)
    components = ComponentManager(registrar, files=[SENSORS])
    manager = VisualizationManager(registrar, server)
    statuses: list[StatusUpdate] = []
    cond = threading.Condition()

    def on_status(update: StatusUpdate) -> None:
        with cond:
            statuses.append(update)
            cond.notify_all()

    try:
        with FoxgloveClient(server.url) as client:
            client.wait(lambda c: bool(c.server_info))
            shown: list[str] = []
            ref = None
            for sensor in ("lidar_3d", "depth_camera"):
                request = DisplayRequest("component", target="range_sensor", candidate=sensor)
                ref = registrar.call("display", request, client="operator", on_status=on_status)
                client.wait(lambda c, t=request.topic: t in c.topics())
                assert client.topics()[request.topic] == "temoto.ComponentData"
                message = client.first_message(client.subscribe(request.topic)).payload
                assert message["component"] == sensor
                assert message["data"].startswith(sensor)
                shown.append(sensor)
                if sensor == "depth_camera":
                    break
                (component,) = registrar.dependencies(ref.resource_id)
                os.kill(component.response.pid, signal.SIGKILL)
                with cond:
                    assert cond.wait_for(
                        lambda: any(u.status is Status.FATAL for u in statuses), WAIT
                    ), statuses
                t_release = time.monotonic()
                registrar.release(ref.id)
                client.wait(lambda c, t=request.topic: t not in c.topics())
                gone = next(
                    t
                    for t, op, topic in client.events
                    if op == "unadvertise" and topic == request.topic
                )
                assert gone - t_release < 1.0
            assert shown == ["lidar_3d", "depth_camera"]
            fatal = next(u for u in statuses if u.status is Status.FATAL)
            assert fatal.hops[-2:] == ("component", "display")
            order = [(op, topic) for _, op, topic in client.events if op != "message"]
            lidar = DisplayRequest("component", target="range_sensor", candidate="lidar_3d").topic
            depth = DisplayRequest("component", target="range_sensor", candidate="depth_camera")
            assert order == [
                ("advertise", lidar),
                ("unadvertise", lidar),
                ("advertise", depth.topic),
            ]
            assert ref is not None
            registrar.release(ref.id)
    finally:
        manager.shutdown()
        components.shutdown()
        processes.shutdown(stop_processes=True)
        registrar.close()


def test_after_a_registrar_restart_a_display_is_fatal_and_loads_afresh(
    server: FoxgloveServer, tmp_path: Path
) -> None:
    catalog = tmp_path / "catalog.journal"
    reg1 = Registrar("test-viz", catalog=catalog)
    viz1 = VisualizationManager(reg1, server)
    request = DisplayRequest("log", target="patrol", name="ops")
    ref = reg1.call("display", request, client="operator")
    viz1.shutdown()  # the process "dies": nothing is released
    reg1.close()
    reg2 = Registrar("test-viz", catalog=catalog, restore=True)
    viz2 = VisualizationManager(reg2, server)
    try:
        info = reg2.info(ref.id)
        assert info.request == request  # rebuilt from the journal's JSON
        assert info.failed
        assert viz2.displays() == {}
        again = reg2.call("display", request, client="operator")
        assert again.resource_id != ref.resource_id  # a fresh display, not the lost one
        assert "/display/ops/log" in server.topics()
        assert list(viz2.displays()) == ["ops"]
        # the lost one's release leaves the fresh one alone
        reg2.release(ref.id)
        assert "/display/ops/log" in server.topics()
        assert list(viz2.displays()) == ["ops"]
        reg2.release(again.id)
        assert "/display/ops/log" not in server.topics()
    finally:
        viz2.shutdown()
        reg2.close()


def test_a_robots_path_display_grows_as_the_rover_drives(server: FoxgloveServer) -> None:
    """``robot`` / ``path``: the path travelled, as ``foxglove.PosesInFrame``."""
    import yaml

    from temoto import ScaledClock
    from temoto.config import parse_profile

    clock = ScaledClock(4)
    doc = yaml.safe_load((PROFILES / "sim_rover.yaml").read_text())
    doc["devices"]["base"]["heartbeat_period"] = 0.25  # lenient on a loaded machine
    profile = parse_profile(doc, file="sim_rover.yaml", clock=clock)
    request = DisplayRequest("robot", "path")
    assert (request.name, request.kind, request.topic) == (
        "robot_path",
        "foxglove.PosesInFrame",
        "/display/robot_path/path",
    )
    with robot_manager("test-viz-path", profile, clock) as (registrar, _robots):
        manager = VisualizationManager(registrar, server, clock=clock)
        try:
            with FoxgloveClient(server.url) as client:
                ref = registrar.call("display", request, client="op")
                client.wait(lambda c: request.topic in c.topics(), timeout=WAIT)
                assert client.topics()[request.topic] == "foxglove.PosesInFrame"
                sub = client.subscribe(request.topic)
                first = client.first_message(sub, timeout=WAIT).payload
                assert first["frame_id"] == "odom"
                assert len(first["poses"]) == 1  # standing still: one pose, no more messages
                driver = RobotManagerClient(registrar).request(client="driver")
                driver.navigate_to(0.6, 0.0).wait(WAIT * 3)

                def far(c: FoxgloveClient) -> bool:
                    mine = [m for m in c.messages if m.subscription == sub]
                    return mine[-1].payload["poses"][-1]["position"]["x"] > 0.5

                client.wait(far, timeout=WAIT)
                path = [m for m in client.messages if m.subscription == sub][-1].payload["poses"]
                xs = [p["position"]["x"] for p in path]
                xy = [(p["position"]["x"], p["position"]["y"]) for p in path]
                assert xs == sorted(xs)  # straight ahead, in order
                assert len(path) >= 10  # a pose per 2 cm of the 0.6 m
                steps = [math.dist(a, b) for a, b in itertools.pairwise(xy)]
                assert min(steps) >= 0.02 - 1e-9
                registrar.release(ref.id)
                client.wait(lambda c: request.topic not in c.topics(), timeout=WAIT)
        finally:
            for ref in registrar.references():
                registrar.release(ref.id)
            manager.shutdown()


def test_a_world_display_shows_the_world_models_items_as_a_scene(
    server: FoxgloveServer,
) -> None:
    """``world``: the Context Manager's tree as ``foxglove.SceneUpdate``."""
    from temoto.errors import ResourceError
    from temoto.managers.context import ContextManager
    from temoto.managers.context.pose import Pose

    registrar = Registrar("test-viz-world")
    manager = VisualizationManager(registrar, server)
    try:
        with pytest.raises(ResourceError, match="needs a Context Manager"):
            registrar.call("display", DisplayRequest("world"), client="op")
        with ContextManager("worker", registrar=registrar) as context:
            context.add("kitchen", "map", pose=Pose(x=10.0))
            context.add("table", "object", parent="kitchen", pose=Pose(x=1.0, y=2.0))
            with pytest.raises(ResourceError, match="no item 'attic'"):
                registrar.call("display", DisplayRequest("world", target="attic"), client="op")
            request = DisplayRequest("world", target="kitchen")
            topic = "/display/world_kitchen_scene/scene"
            assert (request.kind, request.topic) == ("foxglove.SceneUpdate", topic)
            with FoxgloveClient(server.url) as client:
                ref = registrar.call("display", request, client="op")
                client.wait(lambda c: topic in c.topics(), timeout=WAIT)
                assert client.topics()[topic] == "foxglove.SceneUpdate"
                sub = client.subscribe(topic)
                first = client.first_message(sub).payload
                entities = {e["id"]: e for e in first["entities"]}
                assert set(entities) == {"kitchen", "table"}
                assert entities["kitchen"]["cubes"] == []  # a map: its name only
                (cube,) = entities["table"]["cubes"]
                assert cube["pose"]["position"] == {"x": 11.0, "y": 2.0, "z": 0.0}  # in world
                assert entities["table"]["texts"][0]["text"] == "table"
                assert {"key": "parent", "value": "kitchen"} in entities["table"]["metadata"]
                assert first["deletions"] == []

                def mine(c: FoxgloveClient) -> list[dict[str, Any]]:
                    return [m.payload for m in c.messages if m.subscription == sub]

                context.add("cup", "object", parent="table", pose=Pose(z=0.8))
                client.wait(lambda c: any(e["id"] == "cup" for e in mine(c)[-1]["entities"]))
                cup = next(e for e in mine(client)[-1]["entities"] if e["id"] == "cup")
                assert cup["cubes"][0]["pose"]["position"] == {"x": 11.0, "y": 2.0, "z": 0.8}
                context.remove("cup")
                client.wait(lambda c: mine(c)[-1]["deletions"] != [])
                last = mine(client)[-1]
                assert [d["id"] for d in last["deletions"]] == ["cup"]
                assert {e["id"] for e in last["entities"]} == {"kitchen", "table"}
                context.add("elsewhere", "object")  # outside the subtree: not shown
                count = len(mine(client))
                registrar.release(ref.id)
                client.wait(lambda c: topic not in c.topics(), timeout=WAIT)
                assert all(
                    "elsewhere" not in {e["id"] for e in m["entities"]}
                    for m in mine(client)[count - 1 :]
                )
    finally:
        manager.shutdown()
        registrar.close()


def test_a_components_datagrams_are_decoded_as_a_scan_or_an_image(
    server: FoxgloveServer, tmp_path: Path
) -> None:
    """A component display asked as ``foxglove.LaserScan`` or ``foxglove.CompressedImage``."""
    import base64

    from temoto.managers import ProcessManager
    from temoto.managers.component import ComponentManager
    from temoto.testing import sim_scanner

    components_file = sim_scanner.components_file(str(tmp_path))
    registrar = Registrar("test-viz-decode")
    processes = ProcessManager(registrar)
    components = ComponentManager(registrar, files=[components_file])
    manager = VisualizationManager(registrar, server)
    try:
        with FoxgloveClient(server.url) as client:
            scan = DisplayRequest("component", target="scanner", kind="foxglove.LaserScan")
            image = DisplayRequest("component", target="camera", kind="foxglove.CompressedImage")
            refs = [registrar.call("display", r, client="op") for r in (scan, image)]
            client.wait(lambda c: {scan.topic, image.topic} <= set(c.topics()), timeout=WAIT)
            assert client.topics()[scan.topic] == "foxglove.LaserScan"
            assert client.topics()[image.topic] == "foxglove.CompressedImage"
            got = client.first_message(client.subscribe(scan.topic), timeout=WAIT).payload
            assert got["ranges"] == sim_scanner.RANGES
            assert (got["start_angle"], got["end_angle"]) == (0.0, pytest.approx(math.pi))
            assert got["frame_id"] == "lidar"
            assert got["pose"]["orientation"]["w"] == 1.0
            assert "seq" not in got  # only LaserScan's fields
            shot = client.first_message(client.subscribe(image.topic), timeout=WAIT).payload
            assert shot["format"] == "png"
            assert base64.b64decode(shot["data"]).startswith(b"\x89PNG\r\n\x1a\n")
            assert shot["frame_id"] == "cam"
            # the undecodable datagrams between them were dropped, not published
            deadline = time.monotonic() + WAIT
            shown = manager.displays()
            while not (shown[scan.name].dropped and shown[image.name].dropped):
                assert time.monotonic() < deadline, "nothing dropped"
                time.sleep(0.01)
            assert shown[scan.name].count >= 1  # the good ones were published
            for ref in refs:
                registrar.release(ref.id)
            client.wait(lambda c: not {scan.topic, image.topic} & set(c.topics()), timeout=WAIT)
    finally:
        manager.shutdown()
        components.shutdown()
        processes.shutdown(stop_processes=True)
        registrar.close()


def test_a_components_datagrams_are_decoded_as_a_cloud_a_raw_image_or_a_grid(
    server: FoxgloveServer, tmp_path: Path
) -> None:
    """``foxglove.PointCloud``, ``foxglove.RawImage`` (PPM, PGM, JSON bgr8), ``foxglove.Grid``.

    The values are read back from the base64 ``data`` with the message's own fields and
    strides, as a Foxglove panel reads them; each sensor's bad datagrams are dropped, counted.
    """
    import base64
    import struct

    from temoto.managers import ProcessManager
    from temoto.managers.component import ComponentManager
    from temoto.testing import sim_scanner

    components_file = sim_scanner.components_file(str(tmp_path))
    registrar = Registrar("test-viz-decode2")
    processes = ProcessManager(registrar)
    components = ComponentManager(registrar, files=[components_file])
    manager = VisualizationManager(registrar, server)
    requests = {
        target: DisplayRequest("component", target=target, kind=kind)
        for target, kind in (
            ("depth_camera", "foxglove.PointCloud"),
            ("raw_camera", "foxglove.RawImage"),
            ("bgr_camera", "foxglove.RawImage"),
            ("grey_camera", "foxglove.RawImage"),
            ("costmap", "foxglove.Grid"),
        )
    }
    try:
        with FoxgloveClient(server.url) as client:
            refs = [registrar.call("display", r, client="op") for r in requests.values()]
            topics = {r.topic for r in requests.values()}
            client.wait(lambda c: topics <= set(c.topics()), timeout=WAIT)
            got = {}
            for target, request in requests.items():
                assert client.topics()[request.topic] == request.kind
                sub = client.subscribe(request.topic)
                got[target] = client.first_message(sub, timeout=WAIT).payload

            # the cloud: x, y, z FLOAT32 (NumericType 7) at 0, 4, 8; a point per 12 bytes
            cloud = got["depth_camera"]
            assert cloud["frame_id"] == "depth"
            assert cloud["point_stride"] == 12
            assert cloud["fields"] == [
                {"name": axis, "offset": 4 * i, "type": 7} for i, axis in enumerate("xyz")
            ]
            data = base64.b64decode(cloud["data"])
            points = [list(p) for p in struct.iter_unpack("<fff", data)]
            assert points == [[*p, 0.0][:3] for p in sim_scanner.POINTS]

            # the raw images: the same picture as rgb8 (a PPM) and bgr8 (JSON, padded rows)
            def pixels(image: dict[str, Any], order: str) -> list[list[tuple[int, ...]]]:
                raw = base64.b64decode(image["data"])
                assert len(raw) == image["step"] * image["height"]
                rows = [raw[r * image["step"] :][: 3 * image["width"]] for r in range(2)]
                return [
                    [
                        tuple(row[3 * c : 3 * c + 3])[:: 1 if order == "rgb" else -1]
                        for c in range(2)
                    ]
                    for row in rows
                ]

            rgb, bgr = got["raw_camera"], got["bgr_camera"]
            assert (rgb["encoding"], rgb["width"], rgb["height"], rgb["step"]) == ("rgb8", 2, 2, 6)
            assert (bgr["encoding"], bgr["step"]) == ("bgr8", 8)
            assert rgb["frame_id"] == "rawcam"
            assert (
                pixels(rgb, "rgb")
                == pixels(bgr, "bgr")
                == [[tuple(p) for p in row] for row in sim_scanner.PIXELS]
            )
            grey = got["grey_camera"]
            assert (grey["encoding"], grey["step"]) == ("mono8", 2)
            assert list(base64.b64decode(grey["data"])) == [v for r in sim_scanner.GREYS for v in r]

            # the grid: one FLOAT32 field, row-major from its corner; the unknown cell is NaN
            grid = got["costmap"]
            assert grid["column_count"] == 3
            assert grid["cell_size"] == {"x": 0.5, "y": 0.5}
            assert (grid["row_stride"], grid["cell_stride"]) == (12, 4)
            assert grid["fields"] == [{"name": "value", "offset": 0, "type": 7}]
            assert grid["pose"]["position"] == {"x": -1.0, "y": -1.0, "z": 0.0}
            cells = [v for (v,) in struct.iter_unpack("<f", base64.b64decode(grid["data"]))]
            assert cells[:5] == [0.0, 1.0, 2.0, 3.0, 4.0]
            assert math.isnan(cells[5])

            # every sensor's bad datagrams were dropped and counted, the good ones published
            deadline = time.monotonic() + WAIT
            shown = manager.displays()
            while not all(shown[r.name].dropped for r in requests.values()):
                assert time.monotonic() < deadline, "nothing dropped"
                time.sleep(0.01)
            assert all(shown[r.name].count >= 1 for r in requests.values())
            for ref in refs:
                registrar.release(ref.id)
            client.wait(lambda c: not topics & set(c.topics()), timeout=WAIT)
    finally:
        manager.shutdown()
        components.shutdown()
        processes.shutdown(stop_processes=True)
        registrar.close()


def test_a_robots_plan_display_is_the_segment_to_its_goal(server: FoxgloveServer) -> None:
    """``robot`` / ``plan``: no goal, no poses; a goal: from the base to it; reached: none."""
    import yaml

    from temoto import ScaledClock
    from temoto.config import parse_profile

    clock = ScaledClock(4)
    doc = yaml.safe_load((PROFILES / "sim_rover.yaml").read_text())
    doc["devices"]["base"]["heartbeat_period"] = 0.25  # lenient on a loaded machine
    profile = parse_profile(doc, file="sim_rover.yaml", clock=clock)
    request = DisplayRequest("robot", "plan")
    assert (request.name, request.kind, request.topic) == (
        "robot_plan",
        "foxglove.PosesInFrame",
        "/display/robot_plan/plan",
    )
    with robot_manager("test-viz-plan", profile, clock) as (registrar, _robots):
        manager = VisualizationManager(registrar, server, clock=clock)
        try:
            with FoxgloveClient(server.url) as client:
                ref = registrar.call("display", request, client="op")
                client.wait(lambda c: request.topic in c.topics(), timeout=WAIT)
                sub = client.subscribe(request.topic)

                def mine(c: FoxgloveClient) -> list[dict[str, Any]]:
                    return [m.payload for m in c.messages if m.subscription == sub]

                first = client.first_message(sub, timeout=WAIT).payload
                assert (first["frame_id"], first["poses"]) == ("odom", [])  # no goal yet
                driver = RobotManagerClient(registrar).request(client="driver")
                motion = driver.navigate_to(0.6, 0.3, yaw=math.pi / 2)
                client.wait(lambda c: bool(mine(c)[-1]["poses"]), timeout=WAIT)
                start, goal = mine(client)[-1]["poses"]
                assert goal["position"] == {"x": 0.6, "y": 0.3, "z": 0.0}
                assert goal["orientation"]["z"] == pytest.approx(math.sin(math.pi / 4))
                sx, sy = start["position"]["x"], start["position"]["y"]
                heading = 2 * math.atan2(start["orientation"]["z"], start["orientation"]["w"])
                assert heading == pytest.approx(math.atan2(0.3 - sy, 0.6 - sx))
                assert motion.wait(WAIT * 3)
                # on the way, the segment's start followed the base; reached: no plan
                client.wait(lambda c: mine(c)[-1]["poses"] == [], timeout=WAIT)
                starts = [m["poses"][0]["position"]["x"] for m in mine(client) if m["poses"]]
                assert len(starts) >= 3
                assert starts[-1] > starts[0] + 0.3
                registrar.release(ref.id)
                client.wait(lambda c: request.topic not in c.topics(), timeout=WAIT)
        finally:
            for r in registrar.references():
                registrar.release(r.id)
            manager.shutdown()


def test_a_plan_display_of_a_robot_without_navigation_is_refused(
    viz: tuple[Registrar, RobotManager, VisualizationManager],
) -> None:
    from temoto.errors import ResourceError

    registrar, _robots, manager = viz
    with pytest.raises(ResourceError, match="no navigation feature: it has no planned path"):
        registrar.call("display", DisplayRequest("robot", "plan"), client="op")
    assert manager.displays() == {}


@pytest.mark.parametrize(
    ("kind", "datagram", "why"),
    [
        ("foxglove.PointCloud", b'{"points": [[1.0, NaN, 0.0]]}', "finite"),
        ("foxglove.PointCloud", b'{"points": [[1e39, 0.0, 0.0]]}', "too large"),
        ("foxglove.PointCloud", b"[[1.0, 2.0, 3.0]]", "JSON object"),
        ("foxglove.RawImage", b"P6\n2 2\n255\n" + bytes(11), "11 bytes of pixels, 12 needed"),
        ("foxglove.RawImage", b'{"width": 2, "height": 1, "encoding": "jpeg"}', "encoding"),
        (
            "foxglove.RawImage",
            b'{"width": 2, "height": 1, "encoding": "rgb8", "step": 5, "data": ""}',
            "less than a row",
        ),
        (
            "foxglove.RawImage",
            b'{"width": 1, "height": 1, "encoding": "mono8", "data": "%%"}',
            "not base64",
        ),
        ("foxglove.RawImage", b'{"width": 0, "height": 1, "encoding": "mono8"}', "positive"),
        ("foxglove.Grid", b'{"columns": 2, "cells": [1, 2, 3]}', "whole number of rows"),
        ("foxglove.Grid", b'{"columns": 1, "cells": [1], "cell_size": -1}', "positive"),
        ("foxglove.Grid", b'{"columns": 1, "cells": [1], "origin": [0]}', r"origin is \[x, y\]"),
        ("foxglove.Grid", b'{"columns": 1, "cells": ["a"]}', "a number or null"),
        ("foxglove.PointCloud", b'{"points": [[1.0, "2", 0.0]]}', "finite"),
        ("foxglove.RawImage", b'{"width": 1, "height": 1, "encoding": ["mono8"]}', "encoding"),
        # a TypeError inside the decoder (float() of a list) is a refusal too: it would
        # otherwise end the display's reader thread
        ("foxglove.LaserScan", b'{"ranges": [1.0], "start_angle": [0]}', "float"),
        ("foxglove.Grid", b"[" * 200_000, "nested too deeply"),
    ],
)
def test_a_datagram_that_is_not_the_kind_is_refused_naming_why(
    kind: str, datagram: bytes, why: str
) -> None:
    """The reason a dropped datagram is logged with (at DEBUG)."""
    from temoto.managers.visualization.decode import decode

    with pytest.raises(ValueError, match=why):
        decode(kind, datagram, "sensor")


def _protobuf_fields(descriptor_set: bytes) -> dict[str, list[str]]:
    """Each message's field names, in order, from a protobuf ``FileDescriptorSet``.

    The protobuf wire format (varint keys; length-delimited ``file`` = 1, ``package`` = 2,
    ``message_type`` = 4, ``DescriptorProto.name`` = 1 and ``field`` = 2,
    ``FieldDescriptorProto.name`` = 1), read here without the protobuf package.
    """

    def varint(b: bytes, i: int) -> tuple[int, int]:
        value = shift = 0
        while True:
            c = b[i]
            i += 1
            value |= (c & 0x7F) << shift
            shift += 7
            if c < 0x80:
                return value, i

    def records(b: bytes) -> list[tuple[int, Any]]:
        i, out = 0, []
        while i < len(b):
            key, i = varint(b, i)
            wire = key & 7
            value: Any
            if wire == 0:
                value, i = varint(b, i)
            elif wire == 2:
                n, i = varint(b, i)
                value, i = b[i : i + n], i + n
            else:
                size = {1: 8, 5: 4}[wire]
                value, i = b[i : i + size], i + size
            out.append((key >> 3, value))
        return out

    found = {}
    for number, file in records(descriptor_set):
        if number != 1:
            continue
        parts = records(file)
        package = next((v.decode() for n, v in parts if n == 2), "")
        for n, message in parts:
            if n != 4:
                continue
            body = records(message)
            name = next(v.decode() for k, v in body if k == 1)
            found[f"{package}.{name}"] = [
                next(v.decode() for k2, v in records(f) if k2 == 1) for k, f in body if k == 2
            ]
    return found


@pytest.mark.parametrize(
    "kind",
    [
        "foxglove.PointCloud",
        "foxglove.RawImage",
        "foxglove.Grid",
        "foxglove.LaserScan",
        "foxglove.CompressedImage",
        "foxglove.PosesInFrame",
    ],
)
def test_a_display_schemas_fields_are_the_foxglove_sdks(kind: str) -> None:
    """Our JSON schemas name the fields of Foxglove's own (the SDK's protobuf descriptors)."""
    import foxglove.messages

    from temoto.managers.visualization.decode import FLOAT32
    from temoto.managers.visualization.foxglove import DISPLAY_SCHEMAS

    sdk = _protobuf_fields(getattr(foxglove.messages, kind.split(".")[1]).get_schema().data)
    ours = DISPLAY_SCHEMAS[kind]
    assert ours["title"] == kind
    assert list(ours["properties"]) == sdk[kind]
    for prop in ours["properties"].values():
        nested = prop.get("items", prop).get("title", "")
        if nested in sdk:  # PackedElementField, Vector2
            assert list(prop.get("items", prop)["properties"]) == sdk[nested]
    assert foxglove.messages.PackedElementFieldNumericType.Float32.value == FLOAT32
