"""The operator console in headless Chromium: a robot mission, its controls, and a replay.

The mission is ``make run``'s (the simulated mobile manipulator driven through
``examples/missions/mobile_manipulation.graph.json``), in-process with its live view: the page
must show the rover moving on the map, the arm's joints and the timeline; its Pause, Resume
and Stop buttons must work with the token the printed address carries and be refused without
it; once the server is gone the page keeps the last state and says "disconnected". The replay
test opens a ``--trace`` file with ``temoto view``'s server and moves the time slider.

Screenshots are saved in each test's ``tmp_path`` and, when ``TEMOTO_TEST_ARTIFACTS`` names a
folder, copied there (``console-*.png``).
"""

from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path
from typing import Any

import pytest
from _cdp import Browser
from _demo import demo_engine, demo_graph
from test_console import record_rover
from test_live_view_browser import require_chromium

from temoto import Result
from temoto.core.documents import dump_graph
from temoto.core.instrument import TraceInstrument
from temoto.web import LiveView
from temoto.web.replay import ReplayView, load_recording

ROOT = Path(__file__).resolve().parents[2]
WAIT = 15.0


def keep(shot: Path) -> None:
    assert shot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    artifacts = os.environ.get("TEMOTO_TEST_ARTIFACTS")
    if artifacts:
        Path(artifacts).mkdir(parents=True, exist_ok=True)
        shutil.copyfile(shot, Path(artifacts) / shot.name)


def click(browser: Browser, selector: str) -> None:
    browser.evaluate(f"document.querySelector({json.dumps(selector)}).click()")


def fetch_status(browser: Browser, path: str, headers: dict[str, str]) -> int:
    """POST from inside the page (same origin) and return the HTTP status."""
    script = (
        f"fetch({json.dumps(path)}, {{method: 'POST', body: '{{}}', "
        f"headers: {json.dumps(headers)}}}).then((r) => r.status)"
    )
    answer = browser.call(
        "Runtime.evaluate", expression=script, awaitPromise=True, returnByValue=True
    )
    return int(answer["result"]["value"])


def rover(browser: Browser) -> tuple[float, float] | None:
    pos = browser.evaluate(
        "(() => { const g = document.getElementById('rover'); return g ?"
        " [Number(g.getAttribute('data-x')), Number(g.getAttribute('data-y'))] : null; })()"
    )
    return (float(pos[0]), float(pos[1])) if pos else None


def wait_engine(condition: Any, timeout: float = WAIT) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, "the engine never got there"
        time.sleep(0.02)


@pytest.mark.slow
def test_the_console_shows_the_robot_mission_and_controls_it(tmp_path: Path) -> None:
    import yaml

    from temoto import ActionEngine, ScaledClock
    from temoto.actions.builtin import ROBOT_ACTIONS
    from temoto.config import parse_profile
    from temoto.core.registrar import Registrar
    from temoto.managers.robot import RobotManager

    binary = require_chromium()
    mission = json.loads((ROOT / "examples/missions/mobile_manipulation.graph.json").read_text())
    clock = ScaledClock(1)  # the mission takes about 11 s: time to pause and stop it
    registrar = Registrar("console-mission")
    doc = yaml.safe_load((ROOT / "hw_profiles/sim_mobile_manipulator.yaml").read_text())
    # a test machine shared with other jobs can stall for a tenth of a second: relax the
    # devices' real-time watchdogs (the console is under test here, not the drivers)
    doc["devices"]["base"]["heartbeat_period"] = 0.25
    doc["devices"]["arm"]["bus_watchdog"] = 1.0
    doc["devices"]["arm"]["poll_rate"] = 5
    doc["devices"]["base"]["watchdog_timeout"] = 2.0
    profile = parse_profile(doc, file="sim_mobile_manipulator.yaml", clock=clock)
    manager = RobotManager(registrar, profile, clock=clock)
    moving = tmp_path / "console-mission.png"
    stopped = tmp_path / "console-stopped.png"
    gone = tmp_path / "console-disconnected.png"
    try:
        with ActionEngine(
            "sim_mobile_manipulator", actions=[ROBOT_ACTIONS], registrar=registrar, clock=clock
        ) as engine:
            view = LiveView(engine, robot_period_s=0.1)
            browser = Browser(binary, view.url, tmp_path / "profile", tmp_path / "chromium.log")
            try:
                browser.wait_for("document.getElementById('conn').textContent === 'live'")
                # the token moved from the address bar into the tab's storage
                assert "token" not in browser.evaluate("location.href")
                assert browser.evaluate("sessionStorage.getItem('temoto-token')") == view.token
                run = engine.start(mission)

                # the rover appears on the map and moves; the arm's six joints are listed
                browser.wait_for("document.getElementById('rover') !== null", timeout=WAIT)
                first = rover(browser)
                assert first is not None
                browser.wait_for(
                    "Number(document.getElementById('rover').getAttribute('data-x')) > "
                    f"{first[0] + 0.3}",
                    timeout=WAIT,
                )
                assert browser.evaluate("document.getElementById('goal') !== null")
                trail = browser.evaluate(
                    "document.querySelector('#map .trail').getAttribute('points')"
                )
                assert len(trail.split()) >= 3
                joints = browser.evaluate(
                    "[...document.querySelectorAll('#joints .joint')]"
                    ".map((j) => j.getAttribute('data-joint'))"
                )
                assert joints == [
                    "shoulder_pan",
                    "shoulder_lift",
                    "elbow",
                    "wrist_pitch",
                    "wrist_roll",
                    "gripper",
                ]
                health = browser.evaluate(
                    "[...document.querySelectorAll('#health li')]"
                    ".map((li) => li.getAttribute('data-device'))"
                )
                assert sorted(health) == ["arm", "base"]
                # the timeline has a bar per action run so far, one of them still open
                browser.wait_for(
                    "document.querySelectorAll('#ganttsvg .bar').length >= 2"
                    " && document.querySelector('#ganttsvg .bar[data-open=\"1\"]') !== null",
                    timeout=WAIT,
                )
                browser.screenshot(moving)

                # without the token the page's buttons are off and the server refuses
                path = f"/api/graphs/{run}/pause"
                assert fetch_status(browser, path, {"Content-Type": "application/json"}) == 403
                assert (
                    fetch_status(
                        browser,
                        path,
                        {"Content-Type": "application/json", "X-TeMoto-Token": "guess"},
                    )
                    == 403
                )
                assert engine.outcome(run).state.value == "RUNNING"
                no_token = browser.evaluate(
                    "(() => { const t = token; token = ''; renderControls();"
                    " const off = document.getElementById('pause').disabled;"
                    " token = t; renderControls(); return off; })()"
                )
                assert no_token is True

                # pause, resume and stop from the page
                browser.wait_for("!document.getElementById('pause').disabled")
                click(browser, "#pause")
                wait_engine(lambda: engine.outcome(run).state.value == "PAUSED")
                browser.wait_for("document.getElementById('runstate').textContent === 'PAUSED'")
                browser.wait_for("!document.getElementById('resume').disabled")
                click(browser, "#resume")
                wait_engine(lambda: engine.outcome(run).state.value == "RUNNING")
                browser.wait_for("document.getElementById('runstate').textContent === 'RUNNING'")
                # the arm's first move ends on_true: its node says so (from node_result)
                browser.wait_for(
                    "document.querySelector('#svg .node[data-node=\"MoveJoints_0\"] .state')"
                    ".textContent === 'FINISHED \\u00b7 on_true'",
                    timeout=WAIT,
                )
                browser.wait_for("!document.getElementById('stop').disabled")
                click(browser, "#stop")
                assert engine.wait(run, timeout=WAIT) is Result.STOPPED
                shown = browser.wait_for(
                    "document.getElementById('runstate').textContent.endsWith('on_stopped')"
                    " && document.getElementById('runstate').textContent"
                )
                assert "RUNNING" not in shown
                browser.wait_for("document.getElementById('stop').disabled")
                browser.screenshot(stopped)

                # the server goes away: the page keeps what it showed and says so
                nodes = browser.evaluate("document.querySelectorAll('#svg .node').length")
                view.close()
                browser.wait_for("document.getElementById('conn').textContent === 'disconnected'")
                assert browser.evaluate("document.querySelectorAll('#svg .node').length") == nodes
                assert browser.evaluate("document.getElementById('runstate').textContent") == (
                    shown
                )
                assert browser.evaluate("document.getElementById('rover') !== null")
                assert browser.evaluate("document.getElementById('pause').disabled")
                browser.screenshot(gone)
            finally:
                browser.close()
                view.close()
    finally:
        manager.shutdown()
        registrar.close()
    for shot in (moving, stopped, gone):
        keep(shot)


@pytest.mark.slow
def test_a_recorded_trace_replays_with_a_time_slider(tmp_path: Path) -> None:
    binary = require_chromium()
    trace = tmp_path / "run.jsonl"
    # the engine ends first (it stops the holder), then the file is closed
    with trace.open("w", encoding="utf-8") as stream, demo_engine() as demo:
        demo.engine.add_instrument(
            TraceInstrument(stream, "live_demo", demo.engine.clock.monotonic())
        )
        run = demo.engine.start(demo_graph(timer_s=0.4))
        assert demo.engine.wait(run, timeout=WAIT) is Result.TRUE
    graph = tmp_path / "live_demo.graph.json"
    graph.write_text(dump_graph(demo_graph(timer_s=0.4)))
    recording = load_recording(trace, graph)
    timer = [e["t"] for e in recording.events if e["node"] == "TaTimer_0"]
    shot = tmp_path / "console-replay.png"
    with ReplayView(recording) as site:
        browser = Browser(binary, site.url, tmp_path / "profile", tmp_path / "chromium.log")
        try:
            # it opens at the end: the run's result, every action finished, one bar each
            browser.wait_for(
                "document.getElementById('runstate').textContent === 'FINISHED \\u00b7 on_true'"
            )
            states = browser.evaluate(
                "[...document.querySelectorAll('#svg .node')].map((g) =>"
                " g.getAttribute('data-state'))"
            )
            assert states == ["FINISHED"] * 4
            assert browser.evaluate("document.querySelectorAll('#svg .edge').length") == 5
            assert browser.evaluate("document.querySelectorAll('#ganttsvg .bar').length") == 4
            # each node shows its result (the trace's node_result), each taken edge its parent's
            shown = browser.evaluate(
                "Object.fromEntries([...document.querySelectorAll('#svg .node')].map((g) =>"
                " [g.getAttribute('data-node'), g.querySelector('.state').textContent]))"
            )
            assert shown == {
                "TaLogger_0": "FINISHED \u00b7 on_true",
                "TaTimer_0": "FINISHED \u00b7 on_true",
                "Holder_0": "FINISHED \u00b7 on_stopped",
                "TaRelayString_0": "FINISHED \u00b7 on_true",
            }
            labels = browser.evaluate(
                "[...document.querySelectorAll('#svg .elabel')].map((t) => t.textContent)"
            )
            assert labels == ["on_true"] * 4  # entry -> TaLogger_0 has none
            assert "run.jsonl" in browser.evaluate("document.getElementById('source').textContent")

            def slide_to(t: float) -> None:
                browser.evaluate(
                    "(() => { const s = document.getElementById('slider');"
                    f" s.value = String(({t} - rec.start) / (rec.end - rec.start) * s.max);"
                    " s.dispatchEvent(new Event('input')); })()"
                )

            def state_of(node: str) -> str:
                return str(
                    browser.evaluate(
                        f"document.querySelector('#svg .node[data-node=\"{node}\"]')"
                        ".getAttribute('data-state')"
                    )
                )

            slide_to(0.0)
            assert state_of("TaTimer_0") == "UNINITIALIZED"
            slide_to((min(timer) + max(timer)) / 2)  # while the timer ran
            assert state_of("TaTimer_0") == "RUNNING"
            assert state_of("TaLogger_0") == "FINISHED"
            assert state_of("TaRelayString_0") == "UNINITIALIZED"
            assert browser.evaluate("document.getElementById('runstate').textContent") == (
                "RUNNING"
            )
            assert browser.evaluate("document.getElementById('clock').textContent").endswith(" s")
            browser.screenshot(shot)
            # the graph is fitted to its panel; the wheel zooms, a drag pans, "fit" refits
            fitted = browser.evaluate("document.getElementById('svg').getAttribute('viewBox')")
            browser.evaluate(
                "document.getElementById('canvas').dispatchEvent(new WheelEvent('wheel',"
                " {deltaY: -100, clientX: 400, clientY: 300, bubbles: true, cancelable: true}))"
            )
            zoomed = browser.evaluate("document.getElementById('svg').getAttribute('viewBox')")
            assert float(zoomed.split()[2]) < float(fitted.split()[2])
            browser.evaluate(
                "(() => { const c = document.getElementById('canvas');"
                " c.dispatchEvent(new PointerEvent('pointerdown', {clientX: 400, clientY: 300,"
                " bubbles: true}));"
                " window.dispatchEvent(new PointerEvent('pointermove', {clientX: 450,"
                " clientY: 320})); window.dispatchEvent(new PointerEvent('pointerup')); })()"
            )
            panned = browser.evaluate("document.getElementById('svg').getAttribute('viewBox')")
            assert float(panned.split()[0]) < float(zoomed.split()[0])
            click(browser, "#zoomfit")
            assert browser.evaluate("document.getElementById('svg').getAttribute('viewBox')") == (
                fitted
            )
            # play runs to the end by itself
            browser.evaluate("document.getElementById('speed').value = '16'")
            click(browser, "#play")
            browser.wait_for(
                "document.getElementById('runstate').textContent === 'FINISHED \\u00b7 on_true'",
                timeout=WAIT,
            )
        finally:
            browser.close()
    keep(shot)


def test_an_mcap_recording_replays_with_the_robot_on_the_map(tmp_path: Path) -> None:
    binary = require_chromium()
    path = tmp_path / "robot.mcap"
    record_rover(path)
    shot = tmp_path / "console-replay-mcap.png"
    with ReplayView(load_recording(path)) as site:
        browser = Browser(binary, site.url, tmp_path / "profile", tmp_path / "chromium.log")
        try:
            # at the end: the run failed, its node shows on_error, the rover at its last pose
            browser.wait_for(
                "document.getElementById('runstate').textContent === 'FINISHED \\u00b7 on_error'"
            )
            assert browser.evaluate(
                "document.querySelector('#svg .node[data-node=\"NavigateTo_0\"] .state')"
                ".textContent"
            ) == ("ERROR \u00b7 on_error")
            assert rover(browser) == (2.0, 1.0)
            assert (
                len(
                    browser.evaluate(
                        "document.querySelector('#map .trail').getAttribute('points')"
                    ).split()
                )
                == 4
            )
            joints = browser.evaluate(
                "[...document.querySelectorAll('#joints .joint')]"
                ".map((j) => j.getAttribute('data-joint'))"
            )
            assert joints == ["shoulder", "elbow"]
            browser.screenshot(shot)
        finally:
            browser.close()
    keep(shot)


@pytest.mark.slow
def test_the_console_shows_a_vehicle(tmp_path: Path) -> None:
    """The simulated quadcopter, loaded outside any graph: the vehicle table and its driver."""
    from temoto import ActionEngine
    from temoto.config import load_profile
    from temoto.core.registrar import Registrar
    from temoto.managers.robot import RobotManager
    from temoto.managers.robot.client import RobotManagerClient

    binary = require_chromium()
    registrar = Registrar("console-quad-page")
    manager = RobotManager(registrar, load_profile(ROOT / "hw_profiles/sim_quad.yaml"))
    shot = tmp_path / "console-vehicle.png"
    try:
        with (
            ActionEngine("quad", registrar=registrar) as engine,
            LiveView(engine, robot_period_s=0.05) as view,
        ):
            RobotManagerClient(registrar).request(client="console-test")
            browser = Browser(binary, view.url, tmp_path / "profile", tmp_path / "chromium.log")
            try:
                rows = browser.wait_for(
                    "document.querySelectorAll('#vehicle tr').length >= 5 &&"
                    " [...document.querySelectorAll('#vehicle tr')].map((tr) =>"
                    " [tr.children[0].textContent, tr.children[1].textContent])"
                )
                table = dict(rows)
                assert table["position"].startswith("47.39")
                assert table["altitude"].endswith(" m")
                assert table["armed"] == "disarmed"
                assert "%" in table["battery"]
                assert table["mode"]
                assert browser.evaluate("document.getElementById('mapbox').hidden") is True
                assert browser.evaluate("document.getElementById('jointsbox').hidden") is True
                assert browser.evaluate(
                    "document.querySelector('#health li').getAttribute('data-device')"
                ) == ("quad")
                browser.screenshot(shot)
            finally:
                browser.close()
    finally:
        manager.shutdown()
        registrar.close()
    keep(shot)
