"""The Visualization Manager's displays in the live view, in headless Chromium.

The page is opened first; then displays are loaded and released on the engine's registrar:
a panel appears for each loaded display, drawn as its kind asks (the simulated arm's joints
as a plot of each joint's position, an action log as its lines), and goes when the display is
released. The robot is the simulated Dynamixel arm (``hw_profiles/sim_arm.yaml``), in-process.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
from _cdp import Browser

from temoto import ActionEngine, ScaledClock
from temoto.clock import Clock
from temoto.config import load_profile
from temoto.managers.robot import RobotManager, RobotManagerClient
from temoto.managers.visualization import DisplayRequest, VisualizationManager
from temoto.web import LiveView

ROOT = Path(__file__).resolve().parents[2]
WAIT = 15.0


def _panel(name: str) -> str:
    return f"document.querySelector('#displaylist .display[data-display={json.dumps(name)}]')"


@contextmanager
def _page(
    open_page: Any, managers: Any, actor: str, clock: Clock | None = None, **view: Any
) -> Iterator[Browser]:
    """An engine on the test's registrar, its live view (``view``: its options) and the page
    showing it, live."""
    with (
        ActionEngine(actor, registrar=managers.registrar, clock=clock) as engine,
        LiveView(engine, **view) as live,
        open_page(live.url, live=True) as browser,
    ):
        yield browser


def _rover(managers: Any) -> ScaledClock:
    """The simulated rover at 4x, and a Visualization Manager on its clock; returns the clock."""
    import yaml

    from temoto.config import parse_profile

    clock = ScaledClock(4)
    doc = yaml.safe_load((ROOT / "hw_profiles" / "sim_rover.yaml").read_text())
    doc["devices"]["base"]["heartbeat_period"] = 0.25  # lenient on a loaded machine
    profile = parse_profile(doc, file="sim_rover.yaml", clock=clock)
    managers.add(RobotManager(managers.registrar, profile))
    managers.add(VisualizationManager(managers.registrar, clock=clock))
    return clock


def _sensors(managers: Any, tmp_path: Path) -> None:
    """The simulated sensors (``sim_scanner``'s components) and a Visualization Manager."""
    from temoto.managers import ProcessManager
    from temoto.managers.component import ComponentManager
    from temoto.testing import sim_scanner

    processes = ProcessManager(managers.registrar)
    managers.add(processes, lambda: processes.shutdown(stop_processes=True))
    files = [sim_scanner.components_file(str(tmp_path))]
    managers.add(ComponentManager(managers.registrar, files=files))
    managers.add(VisualizationManager(managers.registrar))


@pytest.mark.slow
def test_a_panel_per_loaded_display_appears_and_goes_with_it(
    tmp_path: Path, open_page: Any, managers: Any
) -> None:
    registrar = managers.registrar
    managers.add(RobotManager(registrar, load_profile(ROOT / "hw_profiles" / "sim_arm.yaml")))
    managers.add(VisualizationManager(registrar))  # no Foxglove server: the page only
    shot = tmp_path / "console-displays.png"
    with _page(open_page, managers, "sim_arm") as browser:
        assert browser.evaluate("document.getElementById('displays').hidden")

        joints = registrar.call("display", DisplayRequest("robot", "joints"), client="op")
        log = registrar.call(
            "display",
            DisplayRequest("log", target="patrol", name="patrol_log"),
            client="op",
        )
        # the joints: a plot with one line per joint, with points, and a legend
        browser.wait_for(
            f"{_panel('robot_joints')}?.querySelectorAll('polyline.series').length === 6"
            f" && {_panel('robot_joints')}.querySelector('polyline.series')"
            ".getAttribute('points').split(' ').length >= 3",
            timeout=WAIT,
        )
        assert browser.evaluate(f"{_panel('robot_joints')}.getAttribute('data-panel')") == "plot"
        series = browser.evaluate(
            f"[...{_panel('robot_joints')}.querySelectorAll('.legend span')]"
            ".map((s) => s.getAttribute('data-series'))"
        )
        assert series[:2] == ["shoulder_pan", "shoulder_lift"]
        assert len(series) == 6
        assert not browser.evaluate("document.getElementById('displays').hidden")

        # the log: an action's records, as text (never markup)
        logging.getLogger("temoto.action.patrol.Navigate_3").warning(
            "<b id='injected'>reached</b> waypoint 2"
        )
        line = browser.wait_for(
            f"{_panel('patrol_log')}?.querySelector('li')?.textContent", timeout=WAIT
        )
        assert "WARNING" in line
        assert "<b id='injected'>reached</b> waypoint 2" in line
        assert browser.evaluate("document.getElementById('injected')") is None
        assert browser.evaluate(f"{_panel('patrol_log')}.getAttribute('data-panel')") == "log"
        browser.screenshot(shot)

        # released: its panel goes, the other stays
        registrar.release(joints.id)
        browser.wait_for(f"{_panel('robot_joints')} === null", timeout=WAIT)
        assert browser.evaluate(f"{_panel('patrol_log')} !== null")
        registrar.release(log.id)
        browser.wait_for("document.getElementById('displays').hidden", timeout=WAIT)
        assert browser.evaluate("document.querySelectorAll('#displaylist .display').length") == 0
    assert shot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.slow
def test_a_path_display_is_a_track_and_an_overlay_on_the_map(open_page: Any, managers: Any) -> None:
    registrar = managers.registrar
    clock = _rover(managers)
    with _page(open_page, managers, "sim_rover", clock, robot_period_s=0.1) as browser:
        ref = registrar.call("display", DisplayRequest("robot", "path"), client="op")
        driver = RobotManagerClient(registrar).request(client="driver")
        assert driver.navigate_to(0.6, 0.0).wait(WAIT * 3)
        track = browser.wait_for(
            f"{_panel('robot_path')}?.querySelector('polyline.track')"
            "?.getAttribute('points').split(' ').length >= 10"
            f" && {_panel('robot_path')}.getAttribute('data-panel')",
            timeout=WAIT,
        )
        assert track == "map"
        mark = browser.evaluate(
            f"Number({_panel('robot_path')}.querySelector('.dmark').getAttribute('data-x'))"
        )
        assert mark > 0.5
        # over the robot's own map: the path and a dot at its newest pose
        browser.wait_for(
            "document.querySelector('#map .overlay[data-display=\"robot_path\"]')"
            " !== null && document.querySelector('#map .overlay-path') !== null",
            timeout=WAIT,
        )
        registrar.release(ref.id)
        browser.wait_for(f"{_panel('robot_path')} === null", timeout=WAIT)
        browser.wait_for("document.querySelector('#map .overlay') === null")


@pytest.mark.slow
def test_a_world_display_shows_the_world_models_items(open_page: Any, managers: Any) -> None:
    from temoto.managers.context import ContextManager
    from temoto.managers.context.pose import Pose

    registrar = managers.registrar
    managers.add(VisualizationManager(registrar))
    with (
        ContextManager("worker", registrar=registrar) as context,
        ActionEngine("worker", registrar=registrar) as engine,
        LiveView(engine) as view,
    ):
        context.add("kitchen", "map")
        context.add("table", "object", parent="kitchen", pose=Pose(x=1.0, y=2.0))
        with open_page(view.url, live=True) as browser:
            ref = registrar.call("display", DisplayRequest("world"), client="op")
            entities = (
                f"[...({_panel('world_scene')}?.querySelectorAll('.entity') || [])]"
                ".map((g) => g.getAttribute('data-entity')).sort().join(',')"
            )
            browser.wait_for(f"{entities} === 'kitchen,table'", timeout=WAIT)
            assert browser.evaluate(f"{_panel('world_scene')}.getAttribute('data-panel')") == (
                "scene"
            )
            table = browser.evaluate(
                f"{_panel('world_scene')}.querySelector('.entity[data-entity=\"table\"]')"
                ".getAttribute('data-x')"
            )
            assert float(table) == 1.0
            context.add("cup", "object", parent="table")
            browser.wait_for(f"{entities} === 'cup,kitchen,table'", timeout=WAIT)
            context.remove("cup")
            browser.wait_for(f"{entities} === 'kitchen,table'", timeout=WAIT)
            registrar.release(ref.id)
            browser.wait_for(f"{_panel('world_scene')} === null", timeout=WAIT)


@pytest.mark.slow
def test_a_scan_and_an_image_display_are_drawn(
    tmp_path: Path, open_page: Any, managers: Any
) -> None:
    from temoto.testing import sim_scanner

    registrar = managers.registrar
    _sensors(managers, tmp_path)
    with _page(open_page, managers, "worker") as browser:
        scan = DisplayRequest("component", target="scanner", kind="foxglove.LaserScan")
        image = DisplayRequest("component", target="camera", kind="foxglove.CompressedImage")
        refs = [registrar.call("display", r, client="op") for r in (scan, image)]
        ranges = browser.wait_for(
            f"[...({_panel(scan.name)}?.querySelectorAll('.ray') || [])]"
            ".map((c) => Number(c.getAttribute('data-range')))",
            timeout=WAIT,
        )
        assert ranges == sim_scanner.RANGES
        assert browser.evaluate(f"{_panel(scan.name)}.getAttribute('data-panel')") == ("scan")
        # the first range is straight ahead (angle 0: right of the sensor), the last
        # behind (angle pi: left of it)
        xs = browser.evaluate(
            f"[...{_panel(scan.name)}.querySelectorAll('.ray')]"
            ".map((c) => Number(c.getAttribute('cx')))"
        )
        assert xs[0] > 0 > xs[-1]
        # the image: the camera's PNG, decoded by the browser (1x1)
        size = browser.wait_for(
            f"(() => {{ const i = {_panel(image.name)}?.querySelector('img.dimage');"
            " return i && i.complete && i.naturalWidth ?"
            " [i.naturalWidth, i.naturalHeight] : null; })()",
            timeout=WAIT,
        )
        assert size == [1, 1]
        browser.screenshot(tmp_path / "console-scan.png")
        for ref in refs:
            registrar.release(ref.id)
        browser.wait_for("document.getElementById('displays').hidden", timeout=WAIT)


def _pixels(panel: str) -> str:
    """JS: the panel's canvas's pixels, ``[[r, g, b, a], ...]`` row by row (top first)."""
    return (
        f"(() => {{ const c = {panel}?.querySelector('canvas.draw'); if (!c) return null;"
        " const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;"
        " const out = []; for (let i = 0; i < d.length; i += 4) out.push([...d.slice(i, i + 4)]);"
        " return out; })()"
    )


@pytest.mark.slow
def test_a_cloud_a_raw_image_and_a_grid_display_are_drawn(
    tmp_path: Path, open_page: Any, managers: Any
) -> None:
    """A point cloud from above, raw images (rgb8, bgr8, mono8) on a canvas, a grid's heat map."""
    from temoto.testing import sim_scanner

    registrar = managers.registrar
    _sensors(managers, tmp_path)
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
    with _page(open_page, managers, "worker") as browser:
        refs = [registrar.call("display", r, client="op") for r in requests.values()]
        # the cloud from above: a dot per point at its x, y
        cloud = _panel(requests["depth_camera"].name)
        points = browser.wait_for(
            f"(() => {{ const ps = [...({cloud}?.querySelectorAll('.pt') || [])];"
            " return ps.length ? ps.map((c) => ['data-x', 'data-y', 'cx', 'cy']"
            ".map((a) => Number(c.getAttribute(a)))) : null; })()",
            timeout=WAIT,
        )
        assert [p[:2] for p in points] == [p[:2] for p in sim_scanner.POINTS]
        assert browser.evaluate(f"{cloud}.getAttribute('data-panel')") == "cloud"
        # seen from above: +x is to the right, +y is up (a smaller SVG y)
        (_x1, _y1, cx1, cy1), (_x2, _y2, cx2, cy2) = points[0], points[1]
        assert cx1 > cx2
        assert cy2 < cy1
        # the raw images: the same 2x2 picture from the rgb8 PPM and the padded bgr8
        want = [[*p, 255] for row in sim_scanner.PIXELS for p in row]
        for target in ("raw_camera", "bgr_camera"):
            panel = _panel(requests[target].name)
            got = browser.wait_for(_pixels(panel), timeout=WAIT)
            assert got == want, target
            assert browser.evaluate(f"{panel}.getAttribute('data-panel')") == "rawimage"
        grey = browser.wait_for(_pixels(_panel(requests["grey_camera"].name)), timeout=WAIT)
        assert grey == [[v, v, v, 255] for row in sim_scanner.GREYS for v in row]
        # the grid: 3x2 cells, row 0 (the corner) at the bottom; lowest blue, highest
        # red, the unknown cell grey
        grid = _panel(requests["costmap"].name)
        cells = browser.wait_for(_pixels(grid), timeout=WAIT)
        assert browser.evaluate(f"{grid}.getAttribute('data-panel')") == "grid"
        assert len(cells) == 6
        top, bottom = cells[:3], cells[3:]  # top: the grid's row 1 (3, 4, unknown)
        assert bottom[0][:3] == [47, 125, 225]  # 0: the lowest
        assert top[1][:3] == [214, 59, 59]  # 4: the highest
        assert top[2][:3] == [229, 231, 235]  # unknown
        assert bottom[2][:3] == [245, 158, 11]  # 2: the middle
        browser.screenshot(tmp_path / "console-raw.png")
        for ref in refs:
            registrar.release(ref.id)
        browser.wait_for("document.getElementById('displays').hidden", timeout=WAIT)


@pytest.mark.slow
def test_a_plan_display_is_the_segment_to_the_goal_on_the_map(
    open_page: Any, managers: Any
) -> None:
    registrar = managers.registrar
    clock = _rover(managers)
    plan = _panel("robot_plan")
    with _page(open_page, managers, "sim_rover", clock, robot_period_s=0.1) as browser:
        ref = registrar.call("display", DisplayRequest("robot", "plan"), client="op")
        text = browser.wait_for(f"{plan}?.querySelector('pre.dplan')?.textContent")
        assert text == "no goal"
        driver = RobotManagerClient(registrar).request(client="driver")
        motion = driver.navigate_to(1.5, 0.0)
        text = browser.wait_for(
            f"{plan}?.querySelector('polyline.track.plan') &&"
            f" {plan}.querySelector('pre.dplan').textContent",
            timeout=WAIT,
        )
        assert text.startswith("to x 1.50 m  y 0.00 m")
        mark = browser.evaluate(f"Number({plan}.querySelector('.dmark').getAttribute('data-x'))")
        assert mark == 1.5  # the segment ends at the goal
        browser.wait_for(
            "document.querySelector('#map .overlay-plan[data-display=\"robot_plan\"]') !== null",
            timeout=WAIT,
        )
        assert motion.wait(WAIT * 3)
        browser.wait_for(
            f"{plan}.querySelector('pre.dplan').textContent === 'no goal'", timeout=WAIT
        )
        registrar.release(ref.id)
        browser.wait_for(f"{plan} === null", timeout=WAIT)
