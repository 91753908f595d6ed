"""A run's name used again: the earlier run stays in "Graph runs".

The engine forgets an ended run when a new run takes its name; the live view keeps it as
``<run> #<k>`` with its result and its timeline, drawn as it ended (with its edges when a
page had seen it end, else from its timeline alone).
"""

from __future__ import annotations

import json
import time
import urllib.request
from collections.abc import Iterator
from typing import Any
from urllib.parse import quote

import pytest
from _demo import Demo, demo_engine, demo_graph

from temoto import Result
from temoto.web import LiveView

WAIT = 10.0


@pytest.fixture
def demo() -> Iterator[Demo]:
    with demo_engine() as d:
        yield d


def get(url: str) -> Any:
    with urllib.request.urlopen(url, timeout=WAIT) as r:
        return json.load(r)


def _run_twice(demo: Demo, view: LiveView, *, look_between: bool) -> list[dict[str, Any]]:
    for k in (1, 2):
        run = demo.engine.start(demo_graph(timer_s=0.01))
        assert demo.engine.wait(run, timeout=WAIT) is Result.TRUE
        # the holder is stopped after the run ends: let it finish (its camera released)
        deadline = time.monotonic() + WAIT
        while len(demo.camera.unloads) < k:
            assert time.monotonic() < deadline
            time.sleep(0.01)
        if look_between:  # a page lists the runs after each run's end
            get(view.base_url + "api/graphs")
    return list(get(view.base_url + "api/graphs")["graphs"])


@pytest.mark.parametrize("look_between", [True, False])
def test_a_re_run_keeps_the_earlier_run_listed(demo: Demo, look_between: bool) -> None:
    with LiveView(demo.engine) as view:
        listed = _run_twice(demo, view, look_between=look_between)
        assert [(r["name"], r["state"], r["result"]) for r in listed] == [
            ("live_demo #1", "FINISHED", "on_true"),
            ("live_demo", "FINISHED", "on_true"),
        ]
        earlier = get(view.base_url + "api/graphs/" + quote("live_demo #1", safe=""))
        newer = get(view.base_url + "api/graphs/live_demo")
        assert earlier["name"] == "live_demo #1"
        assert earlier["earlier"] is True
        assert (earlier["state"], earlier["result"]) == ("FINISHED", "on_true")
        nodes = {n["id"]: n["state"] for n in earlier["nodes"] if n["kind"] == "action"}
        assert nodes == dict.fromkeys(
            ["TaLogger_0", "TaTimer_0", "Holder_0", "TaRelayString_0"], "FINISHED"
        )
        # its own timeline, which ended before the newer run started
        assert earlier["timeline"]["end"] <= newer["timeline"]["start"]
        assert len(earlier["timeline"]["spans"]) == 4
        if look_between:  # a page saw it end: drawn with its edges
            assert len(earlier["edges"]) == len(newer["edges"]) == 5
        # a third run: two earlier ones, numbered in order
        run = demo.engine.start(demo_graph(timer_s=0.01))
        assert demo.engine.wait(run, timeout=WAIT) is Result.TRUE
        names = [r["name"] for r in get(view.base_url + "api/graphs")["graphs"]]
        assert names == ["live_demo #1", "live_demo #2", "live_demo"]
