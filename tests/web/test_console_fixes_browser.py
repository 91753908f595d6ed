"""The live view's page as an operator sees it, in headless Chromium: what it keeps, shows, answers.

* the page keeps what the events told it when the server goes away before its next fetch:
  a finished node stays FINISHED, the run's badge shows its result;
* the graph's text is readable at 1400x1000 in the demo_patrol replay, and no edge label is
  under a node's box;
* HEAD and OPTIONS are answered, other methods get 405 as JSON; the Server header is the
  name alone;
* the timeline's ticks of a very short run are all different;
* a re-run keeps the earlier run listed (``<run> #1``) and drawn as it ended;
* a recording cut short says so on the page, under the time slider.

Each test opens its own Chromium (a few seconds each: ``slow``).
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
from _cdp import Browser
from _demo import demo_engine, demo_graph

from temoto import Result
from temoto.core.documents import graph_to_dict, load_graph
from temoto.web import LiveView
from temoto.web.replay import Recording, ReplayView

ROOT = Path(__file__).resolve().parents[2]
WAIT = 15.0


@contextmanager
def _demo_page(open_page: Any) -> Iterator[tuple[Any, Browser]]:
    """The demo engine, its live view and the page showing it, live: (the demo, the page)."""
    with (
        demo_engine() as demo,
        LiveView(demo.engine) as view,
        open_page(view.url, live=True) as browser,
    ):
        yield demo, browser


def _states(browser: Browser) -> dict[str, str]:
    return dict(
        browser.evaluate(
            "Object.fromEntries([...document.querySelectorAll('#svg .node')].map((g) =>"
            " [g.getAttribute('data-node'), g.querySelector('.state').textContent]))"
        )
    )


@pytest.mark.slow
def test_the_page_keeps_what_the_events_said_when_the_server_is_gone(open_page: Any) -> None:
    with _demo_page(open_page) as (demo, browser):
        run = demo.engine.start(demo_graph(timer_s=1.0))
        browser.wait_for(
            "document.querySelector('#svg .node[data-node=\"TaTimer_0\"]')"
            "?.getAttribute('data-state') === 'RUNNING'"
        )
        # from now on every fetch fails, as when the server has just gone away: only the
        # event stream tells the page how the run goes on
        browser.evaluate("window.fetch = () => Promise.reject(new TypeError('server gone')); true")
        assert demo.engine.wait(run, timeout=WAIT) is Result.TRUE
        browser.wait_for(
            "document.querySelector('#svg .node[data-node=\"TaRelayString_0\"]')"
            "?.getAttribute('data-state') === 'FINISHED'"
        )
        # the page's refetches (after each event, and the 1 s tick) fail; then it still
        # shows what the events said, not the older snapshot it fetched last
        browser.call(
            "Runtime.evaluate",
            expression="new Promise((ok) => setTimeout(() => ok(true), 1500))",
            awaitPromise=True,
        )
        shown = _states(browser)
        assert shown["TaTimer_0"] == "FINISHED \u00b7 on_true"
        assert shown["TaRelayString_0"] == "FINISHED \u00b7 on_true"
        assert browser.evaluate("document.getElementById('runstate').textContent") == (
            "FINISHED \u00b7 on_true"
        )
        badge = browser.evaluate("document.querySelector('#runs li .badge').textContent")
        assert badge == "on_true"
        assert browser.evaluate("document.getElementById('stop').disabled")
        # a redraw (a resize) draws the same: the stored snapshot moved with the events
        browser.evaluate("window.dispatchEvent(new Event('resize')); true")
        assert _states(browser) == shown


@pytest.mark.slow
def test_a_re_run_keeps_the_earlier_run_in_the_list(open_page: Any) -> None:
    with _demo_page(open_page) as (demo, browser):
        for k in (1, 2):  # the page draws each run while it runs (half a second)
            run = demo.engine.start(demo_graph(timer_s=0.5))
            assert demo.engine.wait(run, timeout=WAIT) is Result.TRUE
            # the holder is stopped after the run ends: let it finish (camera released)
            deadline = time.monotonic() + WAIT
            while len(demo.camera.unloads) < k:
                assert time.monotonic() < deadline
                time.sleep(0.01)
            browser.wait_for(
                f"document.querySelectorAll('#runs li').length === {k}"
                " && [...document.querySelectorAll('#runs li .badge')]"
                ".every((b) => b.textContent === 'on_true')",
                timeout=WAIT,
            )
        listed = browser.evaluate(
            "[...document.querySelectorAll('#runs li')].map((li) => li.getAttribute('data-run'))"
        )
        assert listed == ["live_demo", "live_demo #1"]  # newest first
        browser.evaluate(
            "document.querySelector('#runs li[data-run=\"live_demo #1\"]').click(); true"
        )
        browser.wait_for(
            "document.getElementById('runname').textContent === 'live_demo #1'"
            " && document.querySelectorAll('#svg .node').length === 4"
        )
        assert set(_states(browser).values()) == {
            "FINISHED \u00b7 on_true",
            "FINISHED \u00b7 on_stopped",
        }
        assert browser.evaluate("document.querySelectorAll('#svg .edge').length") == 5


def _patrol_recording() -> Recording:
    doc = graph_to_dict(load_graph(ROOT / "examples/graphs/demo_patrol.graph.json"))
    events: list[dict[str, Any]] = []
    t = 0.0
    for action in doc["actions"]:
        node = f"{action['name']}_{action.get('instance_id', 0)}"
        events.append({"t": t, "node": node, "state": "RUNNING"})
        t += 1.0
        events.append({"t": t, "node": node, "state": "FINISHED", "result": "on_true"})
    return Recording("patrol.jsonl", doc["graph_name"], events, "on_true", graph=doc)


@pytest.mark.slow
def test_the_graphs_text_is_readable_and_no_edge_label_is_under_a_box(
    tmp_path: Path, open_page: Any
) -> None:
    with ReplayView(_patrol_recording()) as site, open_page(site.url) as browser:
        browser.call(
            "Emulation.setDeviceMetricsOverride",
            width=1400,
            height=1000,
            deviceScaleFactor=1,
            mobile=False,
        )
        browser.evaluate("window.dispatchEvent(new Event('resize')); true")
        browser.wait_for("document.querySelectorAll('#svg .elabel').length >= 5")
        browser.evaluate("window.dispatchEvent(new Event('resize')); true")
        sizes = browser.evaluate(
            "(() => { const k = document.getElementById('svg').getScreenCTM().a;"
            " const px = (sel) => [...document.querySelectorAll(sel)].map((t) =>"
            " parseFloat(getComputedStyle(t).fontSize) * k);"
            " return {name: px('#svg .node text:not(.state)'), state: px('#svg .node .state'),"
            " label: px('#svg .elabel')}; })()"
        )
        assert len(sizes["name"]) == 5
        assert min(sizes["name"]) >= 11.0, sizes
        assert min(sizes["state"]) >= 9.5, sizes
        assert min(sizes["label"]) >= 9.5, sizes
        overlaps = browser.evaluate(
            "(() => { const boxes = [...document.querySelectorAll('#svg .node rect')]"
            ".map((r) => r.getBoundingClientRect()); const out = [];"
            " for (const t of document.querySelectorAll('#svg .elabel')) {"
            " const a = t.getBoundingClientRect();"
            " for (const b of boxes) if (a.left < b.right && b.left < a.right &&"
            " a.top < b.bottom && b.top < a.bottom) out.push(t.textContent); }"
            " return out; })()"
        )
        assert overlaps == []
        # and the labels are drawn over everything else (last in the drawing)
        last = browser.evaluate(
            "document.getElementById('svg').lastElementChild.getAttribute('class')"
        )
        assert last == "elabel"
        browser.screenshot(tmp_path / "console-patrol.png")


def _fetch(browser: Browser, method: str, path: str) -> dict[str, Any]:
    script = (
        f"fetch({json.dumps(path)}, {{method: {json.dumps(method)}}}).then(async (r) =>"
        " ({status: r.status, server: r.headers.get('Server'), allow: r.headers.get('Allow'),"
        " type: r.headers.get('Content-Type'), body: await r.text()}))"
    )
    answer = browser.call(
        "Runtime.evaluate", expression=script, awaitPromise=True, returnByValue=True
    )
    return dict(answer["result"]["value"])


@pytest.mark.slow
def test_head_and_options_are_answered_and_the_server_header_is_clean(open_page: Any) -> None:
    with _demo_page(open_page) as (_, browser):
        head = _fetch(browser, "HEAD", "/")
        assert head["status"] == 200
        assert head["type"].startswith("text/html")
        assert head["body"] == ""
        assert head["server"] == "TeMotoLiveView"  # no trailing space
        head = _fetch(browser, "HEAD", "/api/graphs")
        assert (head["status"], head["body"]) == (200, "")
        options = _fetch(browser, "OPTIONS", "/api/graphs")
        assert options["status"] == 204
        assert options["allow"] == "GET, HEAD, POST, OPTIONS"
        put = _fetch(browser, "PUT", "/api/graphs")
        assert put["status"] == 405
        assert put["type"] == "application/json"
        assert json.loads(put["body"]) == {"error": "PUT is not allowed"}
        assert _fetch(browser, "GET", "/")["server"] == "TeMotoLiveView"


@pytest.mark.slow
def test_a_very_short_runs_timeline_ticks_all_differ(open_page: Any) -> None:
    events = [
        {"t": 0.0, "node": "TaLogger_0", "state": "RUNNING"},
        {"t": 0.004, "node": "TaLogger_0", "state": "FINISHED", "result": "on_true"},
    ]
    doc = graph_to_dict(demo_graph(timer_s=0.0))
    recording = Recording("short.jsonl", "live_demo", events, "on_true", graph=doc)
    with ReplayView(recording) as site, open_page(site.url) as browser:
        ticks = browser.wait_for(
            "document.querySelectorAll('#ganttsvg .gtime').length &&"
            " [...document.querySelectorAll('#ganttsvg text.gtime')]"
            ".map((t) => t.textContent)"
        )
        axis = ticks[:7]  # the seven ticks come first, then each bar's duration
        assert len(set(axis)) == 7, axis


@pytest.mark.slow
def test_a_recording_cut_short_says_so_on_the_page(open_page: Any) -> None:
    recording = _patrol_recording()
    recording.notes.append("the recording was cut short (no footer): replaying what it holds")
    with ReplayView(recording) as site, open_page(site.url) as browser:
        browser.wait_for("document.getElementById('runstate').textContent !== ''")
        shown = browser.evaluate(
            "(() => { const n = document.getElementById('notes');"
            " const r = n.getBoundingClientRect();"
            " return {text: n.textContent, h: r.height,"
            " visible: getComputedStyle(n).display !== 'none'}; })()"
        )
        assert "cut short" in shown["text"]
        assert shown["visible"]
        assert shown["h"] > 5
