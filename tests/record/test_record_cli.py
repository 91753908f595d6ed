"""``--record FILE.mcap`` on ``temoto run``, ``temoto serve`` and the robot command."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from mcap.reader import make_reader

from temoto.cli import main
from temoto.errors import ConfigError
from temoto.record import TELEMETRY_RATE_HZ, read_messages, read_transitions

ROOT = Path(__file__).resolve().parents[2]
UPSTREAM = ROOT.parent / "shared" / "conformance" / "umrf" / "upstream"
CONFORMANCE = ROOT / "examples" / "actions" / "conformance"
PROFILE = ROOT / "hw_profiles" / "sim_mobile_manipulator.yaml"
MISSION = ROOT / "examples" / "missions" / "mobile_manipulation.graph.json"
ROBOT = "sim_mobile_manipulator"

pytestmark = pytest.mark.timeout(60)


def metadata(path: Path) -> dict[str, str]:
    with path.open("rb") as stream:
        return {m.name: dict(m.metadata) for m in make_reader(stream).iter_metadata()}["temoto"]


def topics(path: Path) -> dict[str, tuple[str, int]]:
    """topic -> (schema name, message count), from the finished file's summary."""
    with path.open("rb") as stream:
        found = make_reader(stream).get_summary()
    assert found is not None
    assert found.statistics is not None
    counts = found.statistics.channel_message_counts
    return {
        c.topic: (found.schemas[c.schema_id].name, counts[i]) for i, c in found.channels.items()
    }


class Command:
    """A command in a child process whose standard output is read line by line."""

    def __init__(self, *argv: str) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, *argv],
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )
        self.lines: list[str] = []

    def wait_for(self, text: str) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.append(line)
            if text in line:
                return
        self.proc.wait(10)
        pytest.fail(f"no {text!r} in {self.lines}; stderr: {self.proc.stderr.read()}")  # type: ignore[union-attr]

    def finish(self, timeout: float = 30.0) -> tuple[int, str, str]:
        out, err = self.proc.communicate(timeout=timeout)
        return self.proc.returncode, "".join(self.lines) + out, err


# ---- temoto run -----------------------------------------------------------------------------


@pytest.mark.skipif(not UPSTREAM.is_dir(), reason=f"no conformance data at {UPSTREAM}")
def test_run_records_the_transitions_its_trace_shows(tmp_path: Path) -> None:
    graph = UPSTREAM / "actionengine_test_external_changes_test_1.graph.json"
    trace, record = tmp_path / "trace.jsonl", tmp_path / "run.mcap"
    argv = ["run", str(graph), "--actions", str(CONFORMANCE), "--graphs", str(UPSTREAM)]
    code = main([*argv, "--time-scale", "10", "--trace", str(trace), "--record", str(record)])
    assert code == 1  # on_false
    lines = [json.loads(line) for line in trace.read_text().splitlines()]
    states = [(r["graph"], r["node"], r["state"]) for r in lines if "state" in r]
    transitions = read_transitions(record)
    assert states
    assert [(t.graph, t.node, t.new) for t in transitions] == states
    # the node results the trace shows are in the recording too, on the same changes
    results = [(r["node"], r["state"], r.get("node_result")) for r in lines if "state" in r]
    assert [(t.node, t.new, t.result) for t in transitions] == results
    assert any(t.result is not None for t in transitions)
    messages, complete = read_messages(record, {"/temoto/graphs"})
    assert complete
    assert [(m.data["event"], m.data["result"]) for m in messages][-1] == ("finished", "on_false")
    assert metadata(record)["command"] == "temoto run"


def test_run_refuses_a_record_file_it_cannot_write(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    graph = ROOT / "examples" / "graphs" / "hello.graph.json"
    if not graph.is_file():
        graph = next((ROOT / "examples").rglob("*.graph.json"))
    target = tmp_path / "no" / "such" / "dir" / "x.mcap"
    assert main(["run", str(graph), "--record", str(target)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert str(target) in err[0]
    assert "cannot record" in err[0]


# ---- the robot command ----------------------------------------------------------------------


def robot(record: Path, *more: str) -> Command:
    return Command(
        "-m",
        "temoto.managers.robot",
        *("--profile", str(PROFILE), "--mission", str(MISSION), "--local"),
        *("--record", str(record), *more),
    )


def test_robot_recording_has_a_channel_per_stream_at_the_documented_rate(tmp_path: Path) -> None:
    record = tmp_path / "robot.mcap"
    status, out, err = robot(record, "--timeout", "2").finish()
    assert status == 1, err  # stopped by --timeout
    found = topics(record)
    assert {topic: schema for topic, (schema, _) in found.items()}.items() >= {
        f"/{ROBOT}/pose": "foxglove.PoseInFrame",
        "/tf": "foxglove.FrameTransform",
        f"/{ROBOT}/joint_states": "temoto.JointStates",
        f"/{ROBOT}/health": "temoto.RobotHealth",
        "/temoto/graphs": "temoto.GraphEvent",
        "/temoto/transitions": "temoto.NodeTransition",
        "/temoto/log": "foxglove.Log",
        "/fleet/TEMOTO_RIS": "temoto.FleetMessage",
    }.items()
    # one sample of each telemetry stream per period, over the time they were sampled
    samples = {found[t][1] for t in (f"/{ROBOT}/pose", "/tf", f"/{ROBOT}/joint_states")}
    assert len(samples) == 1
    poses, _ = read_messages(record, {f"/{ROBOT}/pose"})
    span = (poses[-1].log_time_ns - poses[0].log_time_ns) / 1e9
    assert span > 1.5  # the mission ran 2 s
    expected = span * TELEMETRY_RATE_HZ + 1
    assert 0.8 * expected <= len(poses) <= expected + 1, (len(poses), span)
    assert poses[-1].data["pose"]["position"]["x"] > 0.1  # the rover moved
    assert metadata(record) == {"telemetry_rate_hz": "10", "command": "robot", "actor": ROBOT}
    assert f"recording to {record}" in out
    transitions = [(t.node, t.new) for t in read_transitions(record)]
    assert ("NavigateTo_0", "RUNNING") in transitions
    logs, _ = read_messages(record, {"/temoto/log"})
    assert any("navigating to (2, 0.5)" in m.data["message"] for m in logs)


@pytest.mark.parametrize("signums", [(signal.SIGINT,), (signal.SIGTERM, signal.SIGTERM)])
def test_robot_recording_is_finished_when_a_signal_stops_the_command(
    tmp_path: Path, signums: tuple[int, ...]
) -> None:
    record = tmp_path / "stopped.mcap"
    command = robot(record)
    command.wait_for("NavigateTo_0 RUNNING")
    for signum in signums:
        command.proc.send_signal(signum)
    status, _, err = command.finish()
    assert status == 128 + signums[0], err
    assert "Traceback" not in err
    messages, complete = read_messages(record)
    assert complete  # summary and footer written on the way out
    assert ("NavigateTo_0", "RUNNING") in [(t.node, t.new) for t in read_transitions(record)]
    assert any(m.topic == f"/{ROBOT}/pose" for m in messages)


# ---- temoto serve ---------------------------------------------------------------------------


def test_serve_records_fleet_traffic_until_sigterm(tmp_path: Path) -> None:
    record = tmp_path / "serve.mcap"
    serve = Command(
        *("-m", "temoto", "serve", "--actor", "a", "--insecure"),
        *("--fleet-url", "inproc://record-serve", "--record", str(record)),
    )
    serve.wait_for("ready")
    serve.proc.send_signal(signal.SIGTERM)
    status, _, err = serve.finish()
    assert status == 0, err
    assert f"temoto: recording to {record}" in err
    assert f"to {record}" in err.splitlines()[-1]  # "recorded N message(s) to ..."
    _, complete = read_messages(record)
    assert complete
    assert metadata(record)["command"] == "temoto serve"
    assert topics(record).get("/fleet/TEMOTO_RIS", ("", 0))[1] >= 1  # its own adverts


def test_a_robot_command_killed_with_sigkill_leaves_what_it_flushed(tmp_path: Path) -> None:
    record = tmp_path / "killed.mcap"
    command = robot(record)
    command.wait_for("NavigateTo_0 RUNNING")
    deadline = time.monotonic() + 10.0
    # the recorder flushes at least once a second: the transition reaches the disk on its own
    while ("NavigateTo_0", "RUNNING") not in _transitions_so_far(record):
        assert time.monotonic() < deadline, "nothing flushed within 10 s"
        time.sleep(0.05)
    command.proc.send_signal(signal.SIGKILL)
    command.finish()
    messages, complete = read_messages(record)
    assert not complete
    assert ("NavigateTo_0", "RUNNING") in [(t.node, t.new) for t in read_transitions(record)]
    assert any(m.topic == f"/{ROBOT}/pose" for m in messages)


def _transitions_so_far(path: Path) -> list[tuple[str, str]]:
    """The transitions a file being written holds so far (none while it holds no chunk)."""
    try:
        return [(t.node, t.new) for t in read_transitions(path)]
    except ConfigError:
        return []
