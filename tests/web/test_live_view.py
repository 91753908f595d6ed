"""The live view's JSON API, event stream and server lifecycle, over plain HTTP (no browser)."""

from __future__ import annotations

import http.client
import json
import socket
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from typing import Any
from urllib.parse import quote

import pytest
from _demo import LOG_LINES, Demo, demo_engine, demo_graph

from temoto import ActionEngine, Result
from temoto.web import LiveView
from temoto.web.events import EventHub
from temoto.web.layout import layered_layout
from temoto.web.view import to_json

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
        assert r.headers["Content-Type"] == "application/json"
        return json.load(r)


class Stream:
    """An open /api/events connection, read event by event."""

    def __init__(self, view: LiveView) -> None:
        self.conn = http.client.HTTPConnection("127.0.0.1", view.port, timeout=WAIT)
        self.conn.request("GET", "/api/events")
        self.response = self.conn.getresponse()
        assert self.response.status == 200
        assert self.response.headers["Content-Type"] == "text/event-stream"

    def next(self) -> dict[str, Any]:
        data = None
        while True:
            line = self.response.readline()
            if not line:
                raise EOFError("stream ended")
            if line.startswith(b"data: "):
                data = json.loads(line[6:])
            elif line == b"\n" and data is not None:
                return dict(data)

    def until(self, predicate: Any) -> list[dict[str, Any]]:
        seen = []
        deadline = time.monotonic() + WAIT
        while time.monotonic() < deadline:
            event = self.next()
            seen.append(event)
            if predicate(event):
                return seen
        raise TimeoutError(seen)

    def close(self) -> None:
        self.response.close()
        self.conn.close()


def test_the_api_lists_runs_and_shows_a_run_with_states_layout_logs_and_resources(
    demo: Demo, view: LiveView
) -> None:
    assert get(view.base_url + "api/graphs") == {"actor": "robot", "graphs": []}
    run = demo.engine.start(demo_graph(timer_s=30))
    assert demo.acquired.wait(WAIT)
    assert get(view.base_url + "api/graphs") == {
        "actor": "robot",
        "graphs": [{"name": run, "state": "RUNNING", "result": None}],
    }
    answer = get(view.base_url + "api/graphs/" + quote(run, safe=""))
    assert (answer["name"], answer["state"], answer["result"]) == (run, "RUNNING", None)
    nodes = {n["id"]: n for n in answer["nodes"]}
    assert list(nodes) == [
        "graph_entry", "Holder_0", "TaLogger_0", "TaRelayString_0", "TaTimer_0", "graph_exit"
    ]  # fmt: skip
    assert nodes["TaLogger_0"]["state"] == "FINISHED"
    assert nodes["TaTimer_0"]["state"] == "RUNNING"
    assert nodes["TaRelayString_0"]["state"] == "UNINITIALIZED"
    assert nodes["graph_entry"]["state"] is None
    assert nodes["graph_entry"]["kind"] == "entry"
    # laid out left to right along the flow
    xs = {k: n["x"] for k, n in nodes.items()}
    assert xs["graph_entry"] < xs["TaLogger_0"] < xs["TaTimer_0"] < xs["TaRelayString_0"]
    assert xs["TaRelayString_0"] < xs["graph_exit"]
    assert xs["Holder_0"] == xs["TaTimer_0"]
    assert nodes["Holder_0"]["y"] != nodes["TaTimer_0"]["y"]
    edges = {(e["from"], e["to"]) for e in answer["edges"]}
    assert edges == {
        ("graph_entry", "TaLogger_0"),
        ("TaLogger_0", "TaTimer_0"),
        ("TaLogger_0", "Holder_0"),
        ("TaTimer_0", "TaRelayString_0"),
        ("TaRelayString_0", "graph_exit"),
    }
    # logs (newest first) and parameters
    assert [m["message"] for m in nodes["TaLogger_0"]["logs"]] == LOG_LINES[::-1]
    assert all(isinstance(m["t"], int) for m in nodes["TaLogger_0"]["logs"])
    assert nodes["TaTimer_0"]["inputs"] == {"count_until": {"type": "number", "value": 30.0}}
    # the resources each action holds
    (held,) = nodes["Holder_0"]["resources"]
    assert held["server"] == "camera"
    assert held["request"] == {"device": "/dev/video0"}
    assert (held["exclusive"], held["suspended"], held["failed"]) == (False, False, False)
    assert nodes["TaTimer_0"]["resources"] == []

    assert demo.engine.stop(run, timeout=WAIT) is Result.STOPPED
    answer = get(view.base_url + "api/graphs/" + quote(run, safe=""))
    assert (answer["state"], answer["result"]) == ("STOPPED", "on_stopped")
    # the engine keeps an action's log once its run returns
    holder = next(n for n in answer["nodes"] if n["id"] == "Holder_0")
    assert [m["message"] for m in holder["logs"]] == ["holding the camera"]


def test_unknown_runs_and_paths_are_404_and_the_page_is_self_contained(view: LiveView) -> None:
    with pytest.raises(urllib.error.HTTPError) as err:
        urllib.request.urlopen(view.base_url + "api/graphs/" + quote("no/such run?", safe=""))
    assert err.value.code == 404
    assert json.load(err.value) == {"error": "no graph run named 'no/such run?'"}
    err.value.close()
    with pytest.raises(urllib.error.HTTPError) as err:
        urllib.request.urlopen(view.base_url + "etc/passwd")
    assert err.value.code == 404
    err.value.close()
    with urllib.request.urlopen(view.base_url) as r:
        html = r.read().decode()
        policy = r.headers["Content-Security-Policy"]
    assert r.headers["Content-Type"] == "text/html; charset=utf-8"
    assert "<svg" in html
    assert "EventSource" in html
    # nothing is fetched from elsewhere, and the policy would refuse it anyway
    for needle in ("http://", "https://", "//cdn", "src="):
        assert needle not in html.replace('xmlns="http://www.w3.org/2000/svg"', "").replace(
            'const SVGNS = "http://www.w3.org/2000/svg"', ""
        ), needle
    assert "default-src 'none'" in policy
    assert "connect-src 'self'" in policy
    assert "innerHTML" not in html


def test_a_foreign_host_header_is_refused(view: LiveView) -> None:
    # what a page on another site would send after re-binding its DNS name to 127.0.0.1
    conn = http.client.HTTPConnection("127.0.0.1", view.port, timeout=WAIT)
    try:
        conn.request("GET", "/api/graphs", headers={"Host": f"evil.example:{view.port}"})
        response = conn.getresponse()
        assert response.status == 421
        response.read()
        conn.request("GET", "/api/graphs", headers={"Host": f"localhost:{view.port}"})
        response = conn.getresponse()
        assert response.status == 200
        response.read()
    finally:
        conn.close()


def test_the_event_stream_reports_node_transitions_as_the_graph_runs(
    demo: Demo, view: LiveView
) -> None:
    stream = Stream(view)
    try:
        assert stream.next() == {"kind": "hello"}
        run = demo.engine.start(demo_graph(timer_s=0.2))
        events = stream.until(lambda e: e["kind"] == "graph" and e["state"] == "ENDED")
    finally:
        stream.close()
    assert events[0] == {"kind": "graph", "graph": run, "state": "RUNNING", "t": events[0]["t"],
                         "seq": events[0]["seq"]}  # fmt: skip
    seqs = [e["seq"] for e in events]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))
    timer = [(e["old"], e["state"]) for e in events if e.get("node") == "TaTimer_0"]
    assert ("UNINITIALIZED", "RUNNING") in timer or ("INITIALIZED", "RUNNING") in timer
    assert timer[-1][1] == "FINISHED"
    assert events[-1]["result"] == "on_true"


def test_streams_are_bounded_and_close_cleanly_with_the_view(demo: Demo) -> None:
    view = LiveView(demo.engine, max_clients=2, heartbeat_s=0.1)
    streams = [Stream(view), Stream(view)]
    try:
        for s in streams:
            assert s.next() == {"kind": "hello"}
        assert view.clients == 2
        with pytest.raises(urllib.error.HTTPError) as err:
            urllib.request.urlopen(view.base_url + "api/events", timeout=WAIT)
        assert err.value.code == 503
        err.value.close()
        # a client that goes away frees its place (noticed at the next keep-alive)
        streams.pop().close()
        deadline = time.monotonic() + WAIT
        while view.clients > 1 and time.monotonic() < deadline:
            time.sleep(0.02)
        assert view.clients == 1
        started = time.monotonic()
        view.close()  # ends the open stream, joins every thread
        assert time.monotonic() - started < 2.0
        with pytest.raises(EOFError):
            streams[0].next()
        view.close()  # idempotent
        assert not [t for t in threading.enumerate() if t.name.startswith("temoto-web")]
        with pytest.raises(ConnectionRefusedError):
            socket.create_connection(("127.0.0.1", view.port), 1).close()
    finally:
        for s in streams:
            s.close()
        view.close()


def test_a_slow_client_gets_a_resync_instead_of_an_unbounded_backlog() -> None:
    from temoto.core.states import NodeState

    hub = EventHub(max_clients=1, queue_size=3)
    sub = hub.subscribe()
    assert sub is not None
    assert hub.subscribe() is None
    for _ in range(5):
        hub.node_transition("g", "A_0", NodeState.RUNNING, NodeState.FINISHED, 0.0)
    batch = sub.get(0)
    assert batch.resync
    assert not batch.closed
    hub.node_transition("g", "A_0", NodeState.FINISHED, NodeState.RUNNING, 0.0)
    batch = sub.get(0)
    assert (len(batch.events), batch.resync) == (1, False)
    hub.close()
    assert sub.get(None).closed
    hub.node_transition("g", "A_0", NodeState.RUNNING, NodeState.FINISHED, 0.0)  # a no-op


def test_the_layout_breaks_cycles_and_orders_layers() -> None:
    layout = layered_layout(
        ["a", "b", "c", "d"], [("a", "b"), ("b", "c"), ("c", "b"), ("a", "d"), ("d", "d")]
    )
    assert layout.layers == {"a": 0, "b": 1, "c": 2, "d": 1}
    assert layout.back_edges == {("c", "b"), ("d", "d")}
    assert layout.positions["b"][0] == layout.positions["d"][0]
    assert layout.positions["b"][1] != layout.positions["d"][1]
    with pytest.raises(ValueError, match="unique"):
        layered_layout(["a", "a"], [])
    empty = layered_layout([], [])
    assert empty.positions == {}
    assert empty.width > 0


def test_answers_are_strict_json_even_for_odd_values() -> None:
    text = to_json({"nan": float("nan"), "inf": [float("inf"), -float("inf")], "x": {1, 2}})
    assert json.loads(text) == {"nan": "NaN", "inf": ["Infinity", "-Infinity"], "x": "{1, 2}"}


def test_a_failed_action_and_its_error_show_without_a_registrar() -> None:
    from _demo import ACTIONS, Holder

    from temoto import ActionCatalog, parse_umrf

    catalog = ActionCatalog([ACTIONS], use_entry_points=False)
    catalog.register(Holder, parse_umrf({"name": "Holder", "type": "sync"}))
    with ActionEngine("robot", actions=catalog) as engine, LiveView(engine) as view:
        run = engine.start(demo_graph(timer_s=0.05, name="no <registrar>"))
        engine.wait(run, timeout=WAIT)
        answer = get(view.base_url + "api/graphs/" + quote(run, safe=""))
    assert answer["name"] == "no <registrar>"
    nodes = {n["id"]: n for n in answer["nodes"]}
    assert nodes["Holder_0"]["state"] == "ERROR"
    assert nodes["Holder_0"]["resources"] == []
    assert any("no resource registrar" in e for e in answer["errors"])


def test_the_event_ending_a_nodes_run_carries_its_result(demo: Demo, view: LiveView) -> None:
    stream = Stream(view)
    try:
        assert stream.next()["kind"] == "hello"
        run = demo.engine.start(demo_graph(timer_s=0.01))
        # Holder_0 is stopped as the graph ends: its change is the last one
        events = stream.until(lambda e: e.get("node") == "Holder_0" and e["state"] == "FINISHED")
        assert demo.engine.wait(run, timeout=WAIT) is Result.TRUE
    finally:
        stream.close()
    nodes = [e for e in events if e["kind"] == "node"]
    ended = {e["node"]: e.get("result") for e in nodes if e["state"] in ("FINISHED", "ERROR")}
    assert ended == {
        "TaLogger_0": "on_true",
        "TaTimer_0": "on_true",
        "TaRelayString_0": "on_true",
        "Holder_0": "on_stopped",
    }
    assert all("result" not in e for e in nodes if e["state"] not in ("FINISHED", "ERROR"))
