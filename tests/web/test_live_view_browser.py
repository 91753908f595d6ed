"""The live view in headless Chromium: node states on the page change as the graph runs.

Needs the Debian ``chromium`` package (``make sysdeps`` installs it as root). Without it the
test skips, except under ``CI=true``, where it fails. The page is driven over the DevTools
protocol (``_cdp.py``, standard library only): it is opened *before* the graph starts, so
everything it shows afterwards arrived through its event stream. A screenshot is saved in the
test's ``tmp_path`` and, when ``TEMOTO_TEST_ARTIFACTS`` names a folder, copied there as
``live-view.png``.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest
from _cdp import Browser, find_chromium
from _demo import LOG_LINES, demo_engine, demo_graph

from temoto import Result
from temoto.web import LiveView

TIMER_S = 2.5  # how long the timer node runs (real seconds)


def require_chromium() -> str:
    binary = find_chromium()
    if binary is not None:
        return binary
    message = "needs chromium (`make sysdeps` installs the Debian package as root)"
    if os.environ.get("CI", "").lower() in ("true", "1"):
        pytest.fail(f"CI: {message}", pytrace=False)
    pytest.skip(message)


STATES_JS = """JSON.stringify(Object.fromEntries([...document.querySelectorAll('#svg .node')]
  .map((g) => [g.getAttribute('data-node'), g.getAttribute('data-state')])))"""


def states(browser: Browser) -> dict[str, str]:
    return dict(json.loads(browser.evaluate(STATES_JS)))


@pytest.mark.slow
def test_node_states_on_the_page_change_as_the_graph_runs(tmp_path: Path) -> None:
    binary = require_chromium()
    shot = tmp_path / "live-view.png"
    with demo_engine() as demo, LiveView(demo.engine) as view:
        browser = Browser(binary, view.url, tmp_path / "profile", tmp_path / "chromium.log")
        try:
            # the page is up, connected, and shows no run yet
            browser.wait_for("document.getElementById('conn').textContent === 'live'")
            assert browser.evaluate("document.querySelectorAll('#svg .node').length") == 0
            run = demo.engine.start(demo_graph(timer_s=TIMER_S))

            # the new run appears by itself, with the timer running
            browser.wait_for(
                "document.querySelector('#svg .node[data-node=\"TaTimer_0\"]')"
                "?.getAttribute('data-state') === 'RUNNING'"
            )
            first = states(browser)
            assert first["TaTimer_0"] == "RUNNING"
            assert first["TaLogger_0"] == "FINISHED"
            assert first["TaRelayString_0"] == "UNINITIALIZED"
            assert browser.evaluate("document.getElementById('runname').textContent") == run

            # select the logger: its log is shown as text, not markup
            browser.evaluate(
                "document.querySelector('#svg .node[data-node=\"TaLogger_0\"]')"
                ".dispatchEvent(new MouseEvent('click', {bubbles: true}))"
            )
            log = browser.wait_for(
                "[...document.querySelectorAll('#log li')].map((li) => li.textContent).join('\\n')"
            )
            assert all(line in log for line in LOG_LINES)
            assert browser.evaluate("document.getElementById('injected')") is None
            assert browser.evaluate("document.querySelectorAll('#details script').length") == 0

            # select the holder: the resource it holds is listed
            assert demo.acquired.wait(5)
            browser.evaluate(
                "document.querySelector('#svg .node[data-node=\"Holder_0\"]')"
                ".dispatchEvent(new MouseEvent('click', {bubbles: true}))"
            )
            held = browser.wait_for("document.querySelector('#resources li')?.textContent")
            assert "camera" in held
            assert "/dev/video0" in held
            browser.screenshot(shot)

            # the same page, never reloaded, follows the run to its end
            assert demo.engine.wait(run, timeout=TIMER_S + 10) is Result.TRUE
            browser.wait_for(
                "document.getElementById('runstate').textContent === 'FINISHED \\u00b7 on_true'"
            )
            last = states(browser)
            assert last["TaTimer_0"] == "FINISHED"
            assert last["TaRelayString_0"] == "FINISHED"
            assert first != last
            runs_shown = browser.evaluate("document.querySelectorAll('#runs li').length")
            assert runs_shown == 1
        finally:
            browser.close()
    assert shot.stat().st_size > 10_000
    assert shot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    artifacts = os.environ.get("TEMOTO_TEST_ARTIFACTS")
    if artifacts:
        Path(artifacts).mkdir(parents=True, exist_ok=True)
        shutil.copyfile(shot, Path(artifacts) / "live-view.png")


@pytest.mark.slow
def test_the_page_follows_the_mobile_manipulation_mission(tmp_path: Path) -> None:
    """The running demo of ``make run`` (simulators, Robot Manager) seen in the browser."""
    import yaml

    from temoto import ActionEngine, ScaledClock
    from temoto.actions.builtin import ROBOT_ACTIONS
    from temoto.config import parse_profile
    from temoto.core.registrar import Registrar
    from temoto.managers.robot import RobotManager

    binary = require_chromium()
    root = Path(__file__).resolve().parents[2]
    mission = json.loads((root / "examples/missions/mobile_manipulation.graph.json").read_text())
    clock = ScaledClock(3)
    registrar = Registrar("live-view-mission")
    doc = yaml.safe_load((root / "hw_profiles/sim_mobile_manipulator.yaml").read_text())
    doc["devices"]["base"]["heartbeat_period"] = 0.25  # 3 missed beats: 250 ms real at 3x
    doc["devices"]["arm"]["bus_watchdog"] = 1.0  # a loaded test machine can pause 70 ms
    doc["devices"]["arm"]["poll_rate"] = 5  # and miss polls: stale after ~2 s, not 0.36 s
    profile = parse_profile(doc, file="sim_mobile_manipulator.yaml", clock=clock)
    manager = RobotManager(registrar, profile, clock=clock)
    shot = tmp_path / "live-view-mission.png"
    try:
        with (
            ActionEngine(
                "sim_mobile_manipulator", actions=[ROBOT_ACTIONS], registrar=registrar, clock=clock
            ) as engine,
            LiveView(engine) as view,
        ):
            browser = Browser(binary, view.url, tmp_path / "profile", tmp_path / "chromium.log")
            try:
                browser.wait_for("document.getElementById('conn').textContent === 'live'")
                run = engine.start(mission)
                browser.wait_for(
                    "document.querySelector('#svg .node[data-node=\"NavigateTo_0\"]')"
                    "?.getAttribute('data-state') === 'RUNNING'",
                    timeout=20,
                )
                first = states(browser)
                browser.evaluate(
                    "document.querySelector('#svg .node[data-node=\"NavigateTo_0\"]')"
                    ".dispatchEvent(new MouseEvent('click', {bubbles: true}))"
                )
                # the action holds the robot: shown once the snapshot after the acquisition came
                # (the panel may first say "none", before the action acquired it)
                held = browser.wait_for(
                    "[...document.querySelectorAll('#resources li')]"
                    ".map(li => li.textContent).find(t => t.includes('robot'))"
                )
                assert "robot" in held
                browser.screenshot(shot)
                assert engine.wait(run, timeout=60) is Result.TRUE
                browser.wait_for(
                    "document.getElementById('runstate').textContent"
                    " === 'FINISHED \\u00b7 on_true'",
                    timeout=20,
                )
                last = states(browser)
            finally:
                browser.close()
    finally:
        manager.shutdown()
        registrar.close()
    assert first["NavigateTo_0"] == "RUNNING"
    assert first["MoveJoints_2"] == "UNINITIALIZED"
    assert set(last.values()) == {"FINISHED"}
    assert shot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    artifacts = os.environ.get("TEMOTO_TEST_ARTIFACTS")
    if artifacts:
        Path(artifacts).mkdir(parents=True, exist_ok=True)
        shutil.copyfile(shot, Path(artifacts) / "live-view-mission.png")
