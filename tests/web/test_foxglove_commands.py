"""Operator commands from Foxglove, called with our own protocol client.

The server's services (``/temoto/start|pause|resume|stop``) go through the live view's own
controls (:func:`temoto.web.server.operator_command`) behind a token; a server made without
them advertises no service at all. The client is :mod:`temoto.testing.foxglove_client` (the
protocol from its specification, on ``websockets``; not the SDK).
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from _demo import Demo, demo_engine, demo_graph

from temoto import Result
from temoto.testing.foxglove_client import FoxgloveClient

pytest.importorskip("foxglove")
pytest.importorskip("websockets")

from temoto.managers.visualization.commands import add_operator_commands
from temoto.managers.visualization.foxglove import FoxgloveServer

WAIT = 15.0
TOKEN = "s3cret-token"


@pytest.fixture
def demo() -> Iterator[Demo]:
    with demo_engine() as demo:
        yield demo


def _state(demo: Demo, run: str) -> str:
    return demo.engine.outcome(run).state.value


def test_start_pause_resume_stop_from_foxglove_with_the_token(demo: Demo) -> None:
    demo.engine.graphs.add(demo_graph(timer_s=30, name="indexed_demo"))
    with FoxgloveServer(port=0, services=True) as server:
        names = add_operator_commands(server, demo.engine, TOKEN)
        assert names == ["/temoto/start", "/temoto/pause", "/temoto/resume", "/temoto/stop"]
        with FoxgloveClient(server.url) as client:
            client.wait(lambda c: len(c.services) == 4)
            assert "services" in client.server_info["capabilities"]
            assert client.services["/temoto/start"]["request"]["encoding"] == "json"

            ok, answer = client.call("/temoto/start", {"token": TOKEN, "graph": "indexed_demo"})
            assert (ok, answer) == (True, {"run": "indexed_demo"})
            run = answer["run"]
            demo.acquired.wait(WAIT)
            assert client.call("/temoto/pause", {"token": TOKEN, "graph": run}) == (
                True,
                {"run": run, "done": "pause"},
            )
            assert _state(demo, run) == "PAUSED"
            # the live view's checks: pausing a paused run is refused with its reason
            ok, why = client.call("/temoto/pause", {"token": TOKEN, "graph": run})
            assert not ok
            assert "not RUNNING" in why
            assert client.call("/temoto/resume", {"token": TOKEN, "graph": run})[0]
            assert _state(demo, run) == "RUNNING"
            ok, why = client.call("/temoto/stop", {"token": TOKEN, "graph": "no such run"})
            assert not ok
            assert "no such run" in why
            ok, why = client.call("/temoto/start", {"token": TOKEN, "graph": ""})
            assert not ok
            assert why.endswith("start: name a graph")
            assert client.call("/temoto/stop", {"token": TOKEN, "graph": run})[0]
            assert demo.engine.wait(run, timeout=WAIT) is Result.STOPPED


def test_a_command_without_the_token_is_refused_and_does_nothing(demo: Demo) -> None:
    run = demo.engine.start(demo_graph(timer_s=30))
    demo.acquired.wait(WAIT)
    with FoxgloveServer(port=0, services=True) as server:
        add_operator_commands(server, demo.engine, TOKEN)
        with FoxgloveClient(server.url) as client:
            for request in (
                {"graph": run},
                {"token": "wrong", "graph": run},
                {"token": TOKEN[:-1], "graph": run},
                {"token": None, "graph": run},
                [TOKEN, run],
            ):
                ok, why = client.call("/temoto/stop", request)
                assert not ok, request
                assert "token" in why or "JSON object" in why
            assert _state(demo, run) == "RUNNING"  # nothing was stopped
    # an empty token refuses every call, even one that carries the empty token
    with FoxgloveServer(port=0, services=True) as server:
        add_operator_commands(server, demo.engine, "")
        with FoxgloveClient(server.url) as client:
            ok, _ = client.call("/temoto/stop", {"token": "", "graph": run})
            assert not ok
    assert _state(demo, run) == "RUNNING"
    demo.engine.stop(run, timeout=WAIT)


def test_without_the_flag_the_server_offers_no_commands(demo: Demo) -> None:
    with FoxgloveServer(port=0) as server:
        with pytest.raises(Exception, match=r"(?i)service"):
            add_operator_commands(server, demo.engine, TOKEN)
        with FoxgloveClient(server.url) as client:
            client.wait(lambda c: bool(c.server_info))
            assert "services" not in client.server_info.get("capabilities", [])
            assert client.services == {}
