"""The live view as a console, over plain HTTP: controls and their guard, timeline, replay.

Writes need the view's token in a header, a same-origin ``Origin`` and a JSON body; these tests
check each refusal, then pause, resume, stop and start through the API. The replay loader is
checked on good and bad trace files (one-line errors naming the file and the line).
"""

from __future__ import annotations

import http.client
import json
import math
import threading
import time
import urllib.request
from argparse import Namespace
from collections.abc import Iterator
from pathlib import Path
from typing import Any
from urllib.parse import quote

import pytest
from _demo import Demo, demo_engine, demo_graph

from temoto import Result
from temoto.cli import main
from temoto.cli.view import main as view_command
from temoto.core.documents import dump_graph
from temoto.errors import ConfigError
from temoto.testing.robots import FakeRobot
from temoto.web import LiveView
from temoto.web.replay import READERS, ReplayView, load_recording, read_trace

WAIT = 10.0


@pytest.fixture
def demo() -> Iterator[Demo]:
    with demo_engine() as d:
        yield d


@pytest.fixture
def view(demo: Demo) -> Iterator[LiveView]:
    with LiveView(demo.engine, heartbeat_s=0.2) as lv:
        yield lv


def get(url: str) -> Any:
    with urllib.request.urlopen(url, timeout=WAIT) as r:
        return json.load(r)


def post(
    view: LiveView,
    path: str,
    body: Any = None,
    *,
    token: str | None = "",
    headers: dict[str, str] | None = None,
) -> tuple[int, dict[str, Any]]:
    """POST as a browser on the page would (token "" means the view's own)."""
    sent = {"Content-Type": "application/json", "Origin": f"http://127.0.0.1:{view.port}"}
    if token is not None:
        sent["X-TeMoto-Token"] = token or view.token
    sent.update(headers or {})
    conn = http.client.HTTPConnection("127.0.0.1", view.port, timeout=WAIT)
    try:
        conn.request("POST", path, body=json.dumps(body or {}), headers=sent)
        reply = conn.getresponse()
        return reply.status, json.loads(reply.read() or b"{}")
    finally:
        conn.close()


def control(run: str, verb: str) -> str:
    return f"/api/graphs/{quote(run, safe='')}/{verb}"


def wait_state(demo: Demo, run: str, node: str, state: str) -> None:
    deadline = time.monotonic() + WAIT
    while demo.engine.node_states(run)[node].value != state:
        assert time.monotonic() < deadline, demo.engine.node_states(run)
        time.sleep(0.01)


def test_the_printed_address_carries_a_random_token(demo: Demo) -> None:
    with LiveView(demo.engine) as a, LiveView(demo.engine) as b:
        assert a.token != b.token
        assert len(a.token) >= 24
        assert a.url == f"{a.base_url}?token={a.token}"
        assert a.base_url == f"http://127.0.0.1:{a.port}/"
    with LiveView(demo.engine, token="") as ro:
        assert ro.url == ro.base_url


def test_writes_are_refused_without_the_token_or_from_elsewhere(demo: Demo, view: LiveView) -> None:
    run = demo.engine.start(demo_graph(timer_s=30))
    wait_state(demo, run, "TaTimer_0", "RUNNING")
    path = control(run, "pause")
    assert post(view, path, token=None)[0] == 403
    assert post(view, path, token="wrong")[0] == 403
    assert post(view, path, token=view.token[:-1])[0] == 403
    status, answer = post(view, path, headers={"Origin": "http://evil.example"})
    assert (status, answer["error"]) == (403, "cross-origin write refused")
    assert post(view, path, headers={"Host": "evil.example"})[0] == 421
    assert post(view, path, headers={"Content-Type": "text/plain"})[0] == 415
    with urllib.request.urlopen(view.base_url + "api/graphs", timeout=WAIT):
        pass  # reads need no token
    assert demo.engine.outcome(run).state.value == "RUNNING"  # nothing was paused
    # a read-only view refuses every write, even with a guessed empty token
    with LiveView(demo.engine, token="") as ro:
        assert post(ro, path, token=None)[0] == 403
        assert post(ro, path, headers={"X-TeMoto-Token": ""})[0] == 403
    demo.engine.stop(run, timeout=WAIT)


def test_pause_resume_and_stop_with_the_token(demo: Demo, view: LiveView) -> None:
    run = demo.engine.start(demo_graph(timer_s=30))
    wait_state(demo, run, "TaTimer_0", "RUNNING")
    assert post(view, control(run, "pause")) == (200, {"run": run, "done": "pause"})
    # PAUSE_REQUESTED until TaTimer_0's on_pause has returned (on a worker), then PAUSED
    assert demo.engine.outcome(run).state.value in ("PAUSE_REQUESTED", "PAUSED")
    status, answer = post(view, control(run, "pause"))  # not RUNNING any more
    assert status == 409
    assert "not RUNNING" in answer["error"]
    assert post(view, control(run, "resume"))[0] == 200
    assert demo.engine.outcome(run).state.value == "RUNNING"
    assert post(view, control(run, "stop"))[0] == 200
    assert demo.engine.wait(run, timeout=WAIT) is Result.STOPPED
    assert post(view, control("no such run", "stop"))[0] == 404
    assert post(view, "/api/graphs/x/explode")[0] == 404


def test_start_an_indexed_graph(demo: Demo, view: LiveView) -> None:
    demo.engine.graphs.add(demo_graph(timer_s=0.05, name="indexed_demo"))
    assert get(view.base_url + "api/indexed") == {"graphs": ["indexed_demo"]}
    status, answer = post(view, "/api/start", {"graph": "indexed_demo"})
    assert (status, answer) == (200, {"run": "indexed_demo"})
    assert demo.engine.wait("indexed_demo", timeout=WAIT) is Result.TRUE
    assert post(view, "/api/start", {"graph": "nope"})[0] == 404
    assert post(view, "/api/start", {})[0] == 400
    assert post(view, "/api/start", ["indexed_demo"])[0] == 400


def test_a_runs_answer_has_its_timeline_and_no_null_for_unset_inputs(
    demo: Demo, view: LiveView
) -> None:
    run = demo.engine.start(demo_graph(timer_s=0.05))
    assert demo.engine.wait(run, timeout=WAIT) is Result.TRUE
    # the graph ends first, then the Holder it no longer needs is stopped: its span ends after
    # the run's end (ask again until it has; the engine does not wait for it)
    deadline = time.monotonic() + WAIT
    while True:
        answer = get(view.base_url + "api/graphs/" + quote(run, safe=""))
        line = answer["timeline"]
        spans = {s["node"]: s for s in line["spans"]}
        if spans.get("Holder_0", {}).get("state") != "STOPPING" or time.monotonic() > deadline:
            break
        time.sleep(0.01)
    assert set(spans) == {"TaLogger_0", "TaTimer_0", "Holder_0", "TaRelayString_0"}
    for span in spans.values():
        assert span["state"] == "FINISHED"
        assert line["start"] <= span["start"] <= span["end"]
        if span["node"] != "Holder_0":  # stopped as the graph ends, so it ends after it
            assert span["end"] <= line["end"]
    assert spans["TaTimer_0"]["end"] - spans["TaTimer_0"]["start"] >= 0.05
    assert spans["Holder_0"]["result"] == "on_stopped"  # stopped when the graph ended
    nodes = {n["id"]: n for n in answer["nodes"]}
    assert nodes["Holder_0"]["result"] == "on_stopped"
    # the engine's node_result hook: the result of every node, on_true included
    for node in ("TaLogger_0", "TaTimer_0", "TaRelayString_0"):
        assert (spans[node]["result"], nodes[node]["result"]) == ("on_true", "on_true")
    assert isinstance(answer["now"], float)
    assert {e["status"] for e in answer["edges"]} == {"taken"}
    # an input with no value carries no "value" (the page says "not set", never null)
    for node in answer["nodes"]:
        for param in node.get("inputs", {}).values():
            assert param.get("value", "absent") is not None


def test_the_robot_answer_is_null_without_a_robot_manager(view: LiveView) -> None:
    assert get(view.base_url + "api/robot") == {"robot": None}


# ---------------------------------------------------------------- replay


def write_trace(path: Path, demo: Demo) -> str:
    """Run the demo graph under ``temoto run --trace``'s instrument."""
    from temoto.core.instrument import TraceInstrument

    stream = path.open("w", encoding="utf-8")
    t0 = demo.engine.clock.monotonic()
    demo.engine.add_instrument(TraceInstrument(stream, "live_demo", t0))
    run = demo.engine.start(demo_graph(timer_s=0.05))
    assert demo.engine.wait(run, timeout=WAIT) is Result.TRUE
    stream.close()
    return run


def test_a_trace_loads_as_a_recording(tmp_path: Path, demo: Demo) -> None:
    trace = tmp_path / "run.trace.jsonl"
    write_trace(trace, demo)
    rec = read_trace(trace)
    assert rec.name == "live_demo"
    assert rec.result == "on_true"
    assert [e["t"] for e in rec.events] == sorted(e["t"] for e in rec.events)
    assert {e["node"] for e in rec.events} == {
        "TaLogger_0",
        "TaTimer_0",
        "Holder_0",
        "TaRelayString_0",
    }
    # the trace's node_result keys: each node's result at the change that ends its run
    ended = {e["node"]: e.get("result") for e in rec.events if e["state"] == "FINISHED"}
    # Holder_0 is stopped as the graph ends: its line may come after the file was closed
    assert ended.pop("Holder_0", "on_stopped") == "on_stopped"
    assert ended == {"TaLogger_0": "on_true", "TaTimer_0": "on_true", "TaRelayString_0": "on_true"}
    page = rec.to_page()
    assert page["end"] >= 0.05
    assert {n["id"] for n in page["graph"]["nodes"]} >= {"TaTimer_0"}
    assert page["graph"]["edges"] == []
    assert any("--graph" in n for n in page["notes"])
    graph_file = tmp_path / "g.json"
    graph_file.write_text(dump_graph(demo_graph(timer_s=0.05)))
    with_edges = load_recording(trace, graph_file).to_page()
    assert len(with_edges["graph"]["edges"]) == 5
    assert with_edges["notes"] == []


@pytest.mark.parametrize(
    ("text", "where"),
    [
        ('{"t": 0, "graph": "g", "node": "A_0", "state": "RUNNING"}\nnot json\n', "line 2"),
        ('{"t": 0, "graph": "g", "node": "A_0", "state": "DANCING"}\n', "line 1"),
        ("[1, 2]\n", "line 1"),
        ("\n", "no trace lines"),
    ],
)
def test_a_bad_trace_is_one_line_naming_the_file_and_line(
    tmp_path: Path, text: str, where: str
) -> None:
    trace = tmp_path / "bad.jsonl"
    trace.write_text(text)
    with pytest.raises(ConfigError) as err:
        load_recording(trace)
    message = str(err.value)
    assert message.startswith(str(trace))
    assert where in message
    assert "\n" not in message


def test_an_mcap_file_that_is_not_a_recording_is_one_line_naming_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    file = tmp_path / "run.mcap"
    file.write_bytes(b"\x89MCAP0\r\n")
    with pytest.raises(ConfigError, match="not an MCAP recording") as err:
        load_recording(file)
    assert str(err.value).startswith(str(file))
    assert "\n" not in str(err.value)
    from temoto.record import Recorder

    empty = tmp_path / "serve.mcap"
    with Recorder(empty) as recorder:  # a recording of no graph run: nothing to replay
        recorder.log(30, "only a warning", "temoto.test")
    with pytest.raises(ConfigError, match="no graph run") as err:
        load_recording(empty)
    assert str(err.value).startswith(str(empty))
    monkeypatch.delitem(READERS, ".mcap")  # a TeMoto without the reader says so
    with pytest.raises(ConfigError, match="no MCAP reader"):
        load_recording(file)


UPSTREAM = (
    Path(__file__).resolve().parents[2].parent / "shared" / "conformance" / "umrf" / "upstream"
)
CONFORMANCE = Path(__file__).resolve().parents[2] / "examples" / "actions" / "conformance"


@pytest.mark.skipif(not UPSTREAM.is_dir(), reason=f"no conformance data at {UPSTREAM}")
def test_an_mcap_recording_of_temoto_run_replays_what_its_trace_shows(tmp_path: Path) -> None:
    graph = UPSTREAM / "actionengine_test_external_changes_test_1.graph.json"
    trace, record = tmp_path / "trace.jsonl", tmp_path / "run.mcap"
    argv = ["run", str(graph), "--actions", str(CONFORMANCE), "--graphs", str(UPSTREAM)]
    assert main([*argv, "--time-scale", "10", "--trace", str(trace), "--record", str(record)]) == 1
    traced = read_trace(trace)
    rec = load_recording(record)
    assert (rec.name, rec.result) == (traced.name, "on_false")
    assert [(e["node"], e["state"]) for e in rec.events] == [
        (e["node"], e["state"]) for e in traced.events
    ]
    times = [e["t"] for e in rec.events]
    assert times == sorted(times)
    assert times[0] >= 0.0
    assert rec.robot == []  # temoto run drives no robot
    assert rec.notes == []  # a finished file, one run
    with ReplayView(rec) as site:
        answer = get(site.url + "api/recording")
    assert (answer["name"], answer["result"], answer["source"]) == (
        rec.name,
        "on_false",
        str(record),
    )
    assert len(answer["events"]) == len(rec.events)


def Rover() -> FakeRobot:  # noqa: N802 - reads like the class it makes
    """A rover with an arm that also flies, moving 0.5 m per pose."""
    return FakeRobot(step=0.5, y=1.0)


def record_rover(path: Path) -> None:
    """Record a run "mission" (and a run "other") and 4 samples of a :class:`Rover`, 0.1 s apart."""
    from temoto.clock import ManualClock
    from temoto.core.states import NodeState as S
    from temoto.record import Recorder

    clock = ManualClock()
    with Recorder(path, clock=clock) as recorder:
        recorder.graph_started("mission", 0.0)
        recorder.node_transition("mission", "NavigateTo_0", S.INITIALIZED, S.RUNNING, 0.0)
        recorder.graph_started("other", 0.0)  # a second run: noted, not replayed
        recorder.node_transition("other", "X_0", S.INITIALIZED, S.RUNNING, 0.0)
        recorder.sample(Rover(), rate_hz=10.0)
        assert recorder.wait_for_samples(1, WAIT)
        for tick in range(1, 4):
            clock.advance(0.1)
            assert recorder.wait_for_samples(tick + 1, WAIT)
        recorder.stop_sampling()
        recorder.node_transition("mission", "NavigateTo_0", S.RUNNING, S.ERROR, 0.3)
        recorder.graph_finished("mission", Result.ERROR, 0.3)


def test_an_mcap_recording_replays_the_robots_samples_on_its_time(tmp_path: Path) -> None:
    path = tmp_path / "robot.mcap"
    record_rover(path)
    rec = load_recording(path)
    assert (rec.name, rec.result) == ("mission", "on_error")
    assert [(e["node"], e["state"]) for e in rec.events] == [
        ("NavigateTo_0", "RUNNING"),
        ("NavigateTo_0", "ERROR"),
    ]
    assert rec.events[-1]["t"] == pytest.approx(0.3)
    assert [round(r["t"], 3) for r in rec.robot] == [0.0, 0.1, 0.2, 0.3]
    assert [r["pose"]["x"] for r in rec.robot] == [0.5, 1.0, 1.5, 2.0]
    first = rec.robot[0]
    assert first["pose"]["yaw"] == pytest.approx(math.pi / 2)
    assert [(j["name"], j["position"]) for j in first["joints"]] == [
        ("shoulder", 0.25),
        ("elbow", -0.5),
    ]
    assert (first["vehicle"]["alt"], first["vehicle"]["mode"]) == (10.0, "GUIDED")
    assert first["healthy"] is True
    assert first["features"] == ["navigation", "manipulation", "flight"]
    assert rec.notes == ["other runs recorded, not replayed: other"]


def test_temoto_view_serves_the_recording_until_stopped(
    tmp_path: Path, demo: Demo, capsys: pytest.CaptureFixture[str]
) -> None:
    trace = tmp_path / "run.jsonl"
    write_trace(trace, demo)
    stop = threading.Event()
    args = Namespace(file=str(trace), graph=None, port=0, host="127.0.0.1")
    code: list[int] = []
    thread = threading.Thread(target=lambda: code.append(view_command(args, stop)))
    thread.start()
    try:
        deadline = time.monotonic() + WAIT
        url = ""
        out = ""
        while not url:
            assert time.monotonic() < deadline
            out += capsys.readouterr().out
            url = next((w for w in out.split() if w.startswith("http://")), "")
            time.sleep(0.02)
        assert "result on_true" in out
        answer = get(url + "api/recording")
        assert answer["name"] == "live_demo"
        assert answer["result"] == "on_true"
        with urllib.request.urlopen(url, timeout=WAIT) as r:
            assert b'data-mode="replay"' in r.read()
    finally:
        stop.set()
        thread.join(WAIT)
    assert code == [0]


def test_temoto_view_reports_a_bad_file_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "bad.jsonl"
    bad.write_text("nope\n")
    assert main(["view", str(bad)]) == 2
    err = capsys.readouterr().err
    assert err.strip().splitlines() == [f"temoto: error: {bad}: line 1: not JSON (Expecting value)"]
    assert main(["view", str(tmp_path / "missing.jsonl")]) == 2


def test_a_replay_view_refuses_writes(tmp_path: Path, demo: Demo) -> None:
    trace = tmp_path / "run.jsonl"
    write_trace(trace, demo)
    with ReplayView(read_trace(trace)) as site:
        assert site.url == site.base_url  # no token: nothing to write
        conn = http.client.HTTPConnection("127.0.0.1", site.port, timeout=WAIT)
        conn.request(
            "POST",
            "/api/start",
            body="{}",
            headers={"Content-Type": "application/json", "X-TeMoto-Token": ""},
        )
        assert conn.getresponse().status == 403
        conn.close()


# ---------------------------------------------------------------- the robot


def test_the_robot_answer_shows_a_vehicle_and_its_drivers() -> None:
    """The simulated quadcopter: position, altitude, mode, armed state, battery, health."""
    from temoto import ActionEngine
    from temoto.config import load_profile
    from temoto.core.registrar import Registrar
    from temoto.managers.robot import RobotManager
    from temoto.managers.robot.client import RobotManagerClient

    root = Path(__file__).resolve().parents[2]
    registrar = Registrar("console-quad")
    manager = RobotManager(registrar, load_profile(root / "hw_profiles/sim_quad.yaml"))
    try:
        with (
            ActionEngine("quad", registrar=registrar) as engine,
            LiveView(engine, robot_period_s=0.05) as view,
        ):
            assert get(view.base_url + "api/robot") == {"robot": None}  # not loaded yet
            handle = RobotManagerClient(registrar).request(client="console-test")
            deadline = time.monotonic() + WAIT
            robot = None
            while robot is None or robot["vehicle"] is None:
                assert time.monotonic() < deadline
                robot = get(view.base_url + "api/robot")["robot"]
                time.sleep(0.02)
            vehicle = robot["vehicle"]
            assert (robot["name"], robot["loaded"], robot["features"]) == (
                "sim_quad",
                True,
                ["flight"],
            )
            assert vehicle["lat"] == pytest.approx(47.397742, abs=1e-4)
            assert vehicle["lon"] == pytest.approx(8.545594, abs=1e-4)
            assert abs(vehicle["alt"]) < 1.0
            assert vehicle["armed"] is False
            assert isinstance(vehicle["mode"], str)
            assert vehicle["mode"]
            assert 0 < vehicle["battery_remaining"] <= 100
            assert robot["pose"] is None
            assert robot["joints"] is None
            assert [h["device"] for h in robot["health"]] == ["quad"]
            assert robot["healthy"] is True
            registrar.release(handle.resource.id)
            while robot["loaded"]:  # released: the last reading stays, marked
                assert time.monotonic() < deadline
                robot = get(view.base_url + "api/robot")["robot"]
                time.sleep(0.02)
            assert robot["vehicle"]["lat"] == vehicle["lat"]
    finally:
        manager.shutdown()
        registrar.close()


def test_the_timeline_has_a_span_per_run_of_an_action() -> None:
    from temoto.core.states import NodeState as S
    from temoto.web.events import EventHub

    hub = EventHub()
    assert hub.timeline("g") is None
    hub.graph_started("g", 10.0)
    steps = [
        ("A_0", S.INITIALIZED, S.RUNNING, 10.0),
        ("A_0", S.RUNNING, S.FINISHED, 11.0),
        ("A_0", S.FINISHED, S.RUNNING, 12.0),  # a loop runs it again: a second span
        ("A_0", S.RUNNING, S.ERROR, 12.5),
        ("B_0", S.UNINITIALIZED, S.BYPASSED, 12.5),
        ("C_0", S.INITIALIZED, S.RUNNING, 12.6),
        ("C_0", S.RUNNING, S.STOPPING, 13.0),
        ("C_0", S.STOPPING, S.FINISHED, 13.2),
        ("D_0", S.INITIALIZED, S.RUNNING, 13.3),
    ]
    for node, old, new, t in steps:
        if (node, t) == (  # the engine gives this run's result (the others: none given)
            "A_0",
            11.0,
        ):
            hub.node_result("g", node, Result.FALSE, t)
        hub.node_transition("g", node, old, new, t)
    line = hub.timeline("g")
    assert line is not None
    assert (line["start"], line["end"]) == (10.0, None)
    assert [(s["node"], s["start"], s["end"], s["state"], s["result"]) for s in line["spans"]] == [
        ("A_0", 10.0, 11.0, "FINISHED", "on_false"),
        ("A_0", 12.0, 12.5, "ERROR", "on_error"),
        ("B_0", 12.5, 12.5, "BYPASSED", None),
        ("C_0", 12.6, 13.2, "FINISHED", "on_stopped"),
        ("D_0", 13.3, None, "RUNNING", None),
    ]
    hub.graph_finished("g", Result.ERROR, 14.0)
    assert hub.timeline("g")["end"] == 14.0  # type: ignore[index]
    hub.graph_started("g", 20.0)  # the name runs again: a fresh timeline
    assert hub.timeline("g") == {"start": 20.0, "end": None, "spans": []}


def test_serve_v_prints_the_traceback_of_an_action_that_raised(tmp_path: Path) -> None:
    """``temoto serve -v``: a graph started from the console fails; its plugin's line is shown."""
    import os
    import signal
    import subprocess
    import sys

    graphs = tmp_path / "graphs"
    graphs.mkdir()
    trigger = {"name": "TaTriggerResult", "instance_id": 0}
    doc = {
        "graph_name": "boom",
        "graph_entry": [trigger],
        "graph_exit": [trigger],
        "actions": [
            {
                **trigger,
                "type": "sync",
                "input_parameters": {"result": {"pvf_type": "string", "pvf_value": "boom"}},
            }
        ],
    }
    (graphs / "boom.graph.json").write_text(json.dumps(doc))
    argv = ["serve", "-v", "--actor", "a", "--insecure", "--fleet-url", "inproc://serve-v"]
    argv += ["--actions", str(CONFORMANCE), "--graphs", str(graphs), "--live-view", "0"]
    proc = subprocess.Popen(
        [sys.executable, "-m", "temoto", *argv],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    assert proc.stderr is not None
    seen: list[str] = []
    killer = threading.Timer(WAIT * 2, proc.kill)  # a missing line fails the test, not hangs
    killer.start()
    try:
        url = ""
        for line in proc.stderr:
            seen.append(line)
            if "live view on " in line:
                url = line.split("live view on ")[1].strip()
                break
        assert url, seen
        base, _, token = url.partition("?token=")
        request = urllib.request.Request(
            base + "api/start",
            data=json.dumps({"graph": "boom"}).encode(),
            headers={
                "Content-Type": "application/json",
                "Origin": base.rstrip("/"),
                "X-TeMoto-Token": token,
            },
        )
        with urllib.request.urlopen(request, timeout=WAIT) as reply:
            assert json.load(reply) == {"run": "boom"}
        for line in proc.stderr:
            seen.append(line)
            if line.strip().startswith("RuntimeError:"):
                break
    finally:
        killer.cancel()
        proc.send_signal(signal.SIGTERM)
        _, rest = proc.communicate(timeout=30)
        seen.append(rest)
    text = "".join(seen)
    assert "temoto: boom/TaTriggerResult_0: TaTriggerResult_0 failed:" in text, text
    assert "ta_trigger_result.py" in text  # the plugin's own file and line
    assert "raise RuntimeError" in text
    assert proc.returncode == 0, text[-3000:]
