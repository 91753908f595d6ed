"""The recorder on its own: schemas, channels, sampling on virtual time, logs, cut-short files."""

from __future__ import annotations

import itertools
import json
import logging
import math
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader

from temoto.clock import ManualClock
from temoto.core.states import NodeState, Result
from temoto.errors import ConfigError
from temoto.record import Recorder, read_messages, read_transitions
from temoto.record.schemas import SCHEMAS
from temoto.testing.robots import FakeRobot as Robot
from temoto.transport import InProcessTransport
from temoto.transport.auth import FleetAuth
from temoto.transport.link import FleetLink

pytestmark = pytest.mark.timeout(30)


def FakeRobot() -> Robot:  # noqa: N802 - reads like the class it makes
    """A rover with an arm that also flies, moving 0.1 m per pose."""
    return Robot(step=0.1, y=0.5, attitude=(0.0, 0.1, 0.2))


def summary(path: Path) -> dict[str, tuple[str, str, int]]:
    """topic -> (schema name, schema encoding, message count), from the file's summary."""
    with path.open("rb") as stream:
        found = make_reader(stream).get_summary()
    assert found is not None
    assert found.statistics is not None
    counts = found.statistics.channel_message_counts
    return {
        c.topic: (found.schemas[c.schema_id].name, found.schemas[c.schema_id].encoding, counts[i])
        for i, c in found.channels.items()
    }


def test_sampling_on_virtual_time_gives_one_sample_per_period_in_foxglove_schemas(
    tmp_path: Path,
) -> None:
    clock = ManualClock()
    path = tmp_path / "robot.mcap"
    with Recorder(path, clock=clock) as recorder:
        recorder.sample(FakeRobot(), rate_hz=10.0)
        assert recorder.wait_for_samples(1, 5.0)  # the first sample is taken at once
        for tick in range(1, 21):  # 2 s of virtual time
            clock.advance(0.1)
            assert recorder.wait_for_samples(tick + 1, 5.0)
        recorder.stop_sampling()
    assert recorder.samples == 21
    topics = summary(path)
    assert topics == {
        "/bot/pose": ("foxglove.PoseInFrame", "jsonschema", 21),
        "/tf": ("foxglove.FrameTransform", "jsonschema", 21),
        "/bot/joint_states": ("temoto.JointStates", "jsonschema", 21),
        "/bot/location": ("foxglove.LocationFix", "jsonschema", 21),
        "/bot/vehicle": ("temoto.VehicleState", "jsonschema", 21),
        "/bot/health": ("temoto.RobotHealth", "jsonschema", 21),
    }
    messages, complete = read_messages(path)
    assert complete
    for m in messages:  # every field of the schema, and nothing else
        assert set(m.data) == set(SCHEMAS[m.schema]["properties"]), m
    by_topic: dict[str, list[dict[str, Any]]] = {}
    for m in messages:
        by_topic.setdefault(m.topic, []).append(m.data)
    # stamped with the recorder's clock: 0.1 s apart
    stamps = [p["timestamp"]["sec"] + p["timestamp"]["nsec"] / 1e9 for p in by_topic["/bot/pose"]]
    assert [round(b - a, 3) for a, b in itertools.pairwise(stamps)] == [0.1] * 20
    pose = by_topic["/bot/pose"][0]
    assert pose["frame_id"] == "odom"
    assert pose["pose"]["position"] == {"x": pytest.approx(0.1), "y": 0.5, "z": 0.0}
    q = pose["pose"]["orientation"]
    assert (q["z"], q["w"]) == (pytest.approx(math.sqrt(0.5)), pytest.approx(math.sqrt(0.5)))
    tf = by_topic["/tf"][0]
    assert (tf["parent_frame_id"], tf["child_frame_id"]) == ("odom", "bot/base_link")
    fix = by_topic["/bot/location"][0]
    assert (fix["latitude"], fix["longitude"], fix["altitude"]) == (47.39, 8.54, 10.0)
    assert by_topic["/bot/joint_states"][0]["name"] == ["shoulder", "elbow"]
    assert by_topic["/bot/joint_states"][0]["position"] == [0.25, -0.5]
    vehicle = by_topic["/bot/vehicle"][0]
    assert (vehicle["mode"], vehicle["armed"], vehicle["battery_remaining"]) == ("GUIDED", True, 87)


def test_engine_events_become_transitions_graph_events_and_error_logs(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    with Recorder(path, clock=ManualClock(epoch=1_700_000_000.0)) as recorder:
        recorder.graph_started("g", 1.0)
        recorder.node_transition("g", "A_0", NodeState.UNINITIALIZED, NodeState.RUNNING, 1.5)
        recorder.action_failed("g", "A_0", RuntimeError("boom"))
        recorder.node_transition("g", "A_0", NodeState.RUNNING, NodeState.ERROR, 2.0)
        recorder.graph_finished("g", Result.FALSE, 2.5)
    assert [(t.t, t.graph, t.node, t.old, t.new) for t in read_transitions(path)] == [
        (1.5, "g", "A_0", "UNINITIALIZED", "RUNNING"),
        (2.0, "g", "A_0", "RUNNING", "ERROR"),
    ]
    assert read_transitions(path)[0].time == 1_700_000_000.0
    messages, _ = read_messages(path, {"/temoto/graphs", "/temoto/log"})
    assert [(m.topic, m.data.get("event"), m.data.get("result")) for m in messages] == [
        ("/temoto/graphs", "started", ""),
        ("/temoto/log", None, None),
        ("/temoto/graphs", "finished", "on_false"),
    ]
    log = messages[1].data
    assert (log["level"], log["name"]) == (4, "g/A_0")
    assert log["message"] == "A_0 failed: RuntimeError: boom"
    assert summary(path)["/temoto/log"][0] == "foxglove.Log"


def test_action_logs_are_recorded_and_the_console_shows_what_it_showed(tmp_path: Path) -> None:
    shown: list[str] = []

    class Keep(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            shown.append(record.getMessage())

    root = logging.getLogger()
    keep = Keep()
    old_level = root.level
    root.addHandler(keep)
    root.setLevel(logging.WARNING)
    actions = logging.getLogger("temoto.action")
    try:
        path = tmp_path / "logs.mcap"
        with Recorder(path) as recorder:
            recorder.capture_logs()
            node = logging.getLogger("temoto.action.g.Move_0")
            node.info("moving")
            node.warning("slipping")
            logging.getLogger("temoto.drivers.x").warning("bus lost")
            logging.getLogger("temoto.drivers.x").info("not recorded")
        assert (actions.level, actions.propagate, actions.handlers) == (logging.NOTSET, True, [])
    finally:
        root.removeHandler(keep)
        root.setLevel(old_level)
    assert shown == ["slipping", "bus lost"]  # the console's level still applies
    messages, _ = read_messages(path, {"/temoto/log"})
    assert [(m.data["level"], m.data["name"], m.data["message"]) for m in messages] == [
        (2, "temoto.action.g.Move_0", "moving"),
        (3, "temoto.action.g.Move_0", "slipping"),
        (3, "temoto.drivers.x", "bus lost"),
    ]
    assert messages[0].data["file"] == __file__
    assert messages[0].data["line"] > 0


def test_fleet_envelopes_are_recorded_per_channel_with_sender_and_type(tmp_path: Path) -> None:
    path = tmp_path / "fleet.mcap"
    transport = InProcessTransport("record-fleet-test")
    try:
        link = FleetLink(transport, FleetAuth("temoto", "rover", bytes(32)))
        with Recorder(path, flush_period_s=0.0) as recorder:
            recorder.listen(transport)
            link.send("TEMOTO_RIS", "ris_advert_t", b"\x01\x02")
            link.send("TEMOTO_CONTEXT", "context_update_t", b"\x03")
            link.send("NOT_A_FLEET_CHANNEL", "x_t", b"")
            transport.publish("TEMOTO_RIS", b"garbage")
            deadline_ok = _wait(lambda: sum(recorder.counts.values()) == 3)
        assert deadline_ok
    finally:
        transport.close()
    messages, _ = read_messages(path)
    rows = [(m.topic, m.data["sender"], m.data["type"], m.data["signed"]) for m in messages]
    assert rows == [
        ("/fleet/TEMOTO_RIS", "rover", "ris_advert_t", True),
        ("/fleet/TEMOTO_CONTEXT", "rover", "context_update_t", True),
        ("/fleet/TEMOTO_RIS", "", "", False),
    ]
    assert summary(path)["/fleet/TEMOTO_RIS"] == ("temoto.FleetMessage", "jsonschema", 2)


def test_a_fleet_envelopes_stamp_is_its_senders_clock_or_its_session(tmp_path: Path) -> None:
    """A keyed fleet's envelopes carry a session id where an insecure one's carry the clock:
    it is recorded as ``session`` (constant), never as a ``stamp_us``."""
    path = tmp_path / "stamps.mcap"
    transport = InProcessTransport("record-stamps-test")
    try:
        keyed = FleetLink(transport, FleetAuth("temoto", "rover", bytes(32)))
        plain = FleetLink(transport, FleetAuth("temoto", "drone", None, insecure=True))
        with Recorder(path, flush_period_s=0.0) as recorder:
            recorder.listen(transport)
            before_us = int(time.time() * 1e6)
            for _ in range(2):
                keyed.send("TEMOTO_RIS", "ris_advert_t", b"\x01")
                plain.send("TEMOTO_RIS", "ris_advert_t", b"\x02")
            assert _wait(lambda: sum(recorder.counts.values()) == 4)
            after_us = int(time.time() * 1e6)
    finally:
        transport.close()
    messages, _ = read_messages(path)
    keyed_rows = [m.data for m in messages if m.data["sender"] == "rover"]
    plain_rows = [m.data for m in messages if m.data["sender"] == "drone"]
    assert [(m["signed"], m["stamp_us"]) for m in keyed_rows] == [(True, 0), (True, 0)]
    assert keyed_rows[0]["session"] == keyed_rows[1]["session"] != 0
    for m in plain_rows:
        assert (m["signed"], m["session"]) == (False, 0)
        assert before_us - 1_000_000 <= m["stamp_us"] <= after_us + 1_000_000


def test_the_acknowledgement_channels_of_shared_runs_are_recorded(tmp_path: Path) -> None:
    """TEMOTO_ACK_<actor>: the listening actor's own from the start, every other one from the
    first handshake that names it (a handshake comes before the notifications of its run)."""
    from temoto.fleet import FleetActorLink
    from temoto.fleet.actors import ack_channel

    path = tmp_path / "acks.mcap"
    bus = "record-acks-test"
    transports = [InProcessTransport(bus) for _ in range(3)]
    try:
        fleet_links = [
            FleetLink(t, FleetAuth("temoto", name, bytes(32)))
            for t, name in zip(transports[1:], ("A", "B c"), strict=True)
        ]
        links = [
            FleetActorLink(link, name) for link, name in zip(fleet_links, ("A", "B c"), strict=True)
        ]
        with Recorder(path, flush_period_s=0.0) as recorder:
            recorder.listen(transports[0], ["Me"])
            own = FleetLink(transports[0], FleetAuth("temoto", "me", bytes(32)))
            # keys agreed both ways first: nothing "me" sends is re-sent later (docs/security.md)
            assert own.wait_for_peers(["A", "B c"], 5.0)
            assert all(link.wait_for_peers(["me"], 5.0) for link in fleet_links)
            own.send(ack_channel("Me"), "action_ack_t", b"\x01")
            own.send(ack_channel("A"), "action_ack_t", b"\x02")  # A not named yet: not kept
            errors: list[BaseException] = []

            def shake(link: FleetActorLink) -> None:
                try:
                    run = link.handshake("g", "s", ["A", "B c"], 5.0)
                    if link.actor == "A":
                        link.notify("g", run, "Go_0", Result.TRUE, {}, ["B c"], 5.0)
                    else:
                        done: list[Result] = []
                        link.expect("g", run, "Go_0", "A", lambda r, o: done.append(r))
                        assert _wait(lambda: bool(done))
                except BaseException as err:
                    errors.append(err)

            threads = [threading.Thread(target=shake, args=(link,)) for link in links]
            for thread in threads:
                thread.start()
            for thread in threads:
                thread.join(10.0)
            assert errors == []
            assert _wait(lambda: recorder.counts.get("/fleet/TEMOTO_ACK_A", 0) >= 1)
        for link in links:
            link.close()
    finally:
        for transport in transports:
            transport.close()
    topics = summary(path)
    assert topics["/fleet/TEMOTO_ACK_Me"][2] == 1
    assert topics["/fleet/TEMOTO_ACK_A"][2] >= 1  # B c's acknowledgement of Go_0
    acks = [m for m in read_messages(path)[0] if m.topic == "/fleet/TEMOTO_ACK_A"]
    # only after the handshake named A: the acknowledgement "me" sent before is not there
    assert {(m.data["sender"], m.data["type"]) for m in acks} == {("B c", "action_ack_t")}


def _wait(condition: Any, timeout: float = 5.0) -> bool:
    """Poll a condition that a writer thread makes true (no event to wait on from outside)."""
    import time

    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.005)
    return True


def test_a_recording_killed_with_sigkill_reads_up_to_its_last_flush(tmp_path: Path) -> None:
    path = tmp_path / "killed.mcap"
    script = textwrap.dedent(
        f"""
        import sys, time
        from temoto.core.states import NodeState
        from temoto.record import Recorder
        r = Recorder({str(path)!r}, flush_period_s=0.0)
        for i in range(5):
            r.node_transition("g", f"A_{{i}}", NodeState.UNINITIALIZED, NodeState.RUNNING, i)
        while sum(r.counts.values()) < 5:
            time.sleep(0.01)
        time.sleep(0.2)  # the writer flushes after the message it counted
        print("written", flush=True)
        time.sleep(60)
        """
    )
    with subprocess.Popen(
        [sys.executable, "-c", script], stdout=subprocess.PIPE, text=True, env=dict(os.environ)
    ) as proc:
        try:
            assert proc.stdout is not None
            assert proc.stdout.readline() == "written\n"
        finally:
            proc.send_signal(signal.SIGKILL)
            proc.wait(10)
    messages, complete = read_messages(path)
    assert not complete
    assert [t.node for t in read_transitions(path)] == [f"A_{i}" for i in range(5)]
    assert len(messages) == 5


def test_read_errors_name_the_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"missing\.mcap"):
        read_messages(tmp_path / "missing.mcap")
    text = tmp_path / "notes.mcap"
    text.write_text(json.dumps({"not": "mcap"}))
    with pytest.raises(ConfigError, match=r"notes\.mcap: not an MCAP recording"):
        read_transitions(text)
    with pytest.raises(ConfigError, match=r"nowhere.*x\.mcap: cannot record"):
        Recorder(tmp_path / "nowhere" / "x.mcap")
    with Recorder(tmp_path / "ok.mcap") as recorder, pytest.raises(ValueError, match="rate"):
        recorder.sample(FakeRobot(), rate_hz=0.0)
