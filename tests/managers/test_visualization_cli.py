"""``--foxglove`` on the robot command: the live server seen by an independent client.

A subprocess runs the robot command (or ``temoto serve``); the client of
:mod:`temoto.testing.foxglove_client` (the protocol from its specification, on
``websockets``) connects to the port it prints. Each test starts a process (~2-4 s).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import pytest
from _displays import show_display_graph

from temoto.testing.foxglove_client import FoxgloveClient

pytest.importorskip("foxglove")
pytest.importorskip("websockets")

ROOT = Path(__file__).resolve().parents[2]
ARM = ROOT / "hw_profiles" / "sim_arm.yaml"


#: The robot command on the simulated arm, without a fleet.
ROBOT = ("temoto.managers.robot", "--profile", str(ARM), "--local")

#: A command started with the python_m fixture (tests/managers/conftest.py).
Start = Callable[..., subprocess.Popen[str]]


def _env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k != "TEMOTO_FLEET_KEY"}
    env.update(extra)
    return env


def _run(*args: str, **env: str) -> subprocess.CompletedProcess[str]:
    """``python -m ARGS...`` to its end (60 s at most), its output captured."""
    return subprocess.run(
        [sys.executable, "-m", *args],
        capture_output=True,
        text=True,
        timeout=60,
        env=_env(**env),
        check=False,
    )


def _url(lines: Iterable[str] | None, marker: str, said: list[str] | None = None) -> str:
    """The last word of the first line that holds ``marker`` ("" if none; lines read kept in
    ``said``)."""
    assert lines is not None
    for line in lines:
        if said is not None:
            said.append(line)
        if marker in line:
            return line.split()[-1]
    return ""


def _stopped(proc: subprocess.Popen[str]) -> int:
    """SIGINT, then the exit status (30 s at most)."""
    proc.send_signal(signal.SIGINT)
    return proc.wait(30)


def test_the_robot_command_serves_its_telemetry_live_to_foxglove(python_m: Start) -> None:
    proc = python_m(
        *ROBOT, "--foxglove", "0", stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=_env()
    )
    url = _url(proc.stderr, "temoto: foxglove on ")
    assert url.startswith("ws://127.0.0.1:"), "no foxglove line"
    with FoxgloveClient(url) as client:
        client.wait(lambda c: "/sim_arm/joint_states" in c.topics(), timeout=20)
        assert client.topics()["/sim_arm/health"] == "temoto.RobotHealth"
        sub = client.subscribe("/sim_arm/joint_states")
        joints = client.first_message(sub).payload
        assert joints["name"][:2] == ["shoulder_pan", "shoulder_lift"]
        assert joints["position"] == pytest.approx([0.0] * 6, abs=0.05)  # the sim starts at 0
    assert _stopped(proc) == 0


def test_without_the_sdk_the_robot_command_names_the_extra(tmp_path: Path) -> None:
    (tmp_path / "foxglove.py").write_text("raise ImportError('foxglove-sdk is not installed')\n")
    path = os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")])
    proc = _run(*ROBOT, "--foxglove", PYTHONPATH=path)
    assert proc.returncode == 2, proc.stderr
    lines = [line for line in proc.stderr.splitlines() if "foxglove" in line]
    assert len(lines) == 1, proc.stderr
    assert "pip install 'temoto[foxglove]'" in lines[0]
    assert "Traceback" not in proc.stderr


def test_temoto_serve_serves_its_fleet_traffic_live_to_foxglove(python_m: Start) -> None:
    serve = ("temoto", "serve", "--actor", "a", "--fleet-url", "inproc://viz", "--insecure")
    proc = python_m(
        *serve, "--foxglove", "0", stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=_env()
    )
    url = _url(proc.stderr, "temoto: foxglove on ")
    assert url.startswith("ws://127.0.0.1:"), "no foxglove line"
    with FoxgloveClient(url) as client:
        client.wait(lambda c: "/fleet/TEMOTO_RIS" in c.topics(), timeout=20)
        assert client.server_info["name"] == "temoto a"
        assert client.topics()["/fleet/TEMOTO_RIS"] == "temoto.FleetMessage"
        advert = client.first_message(client.subscribe("/fleet/TEMOTO_RIS")).payload
        assert (advert["channel"], advert["sender"]) == ("TEMOTO_RIS", "a")
    assert _stopped(proc) == 0


def test_demo_1_failover_is_seen_in_foxglove_as_unadvertise_then_advertise(
    python_m: Start,
) -> None:
    proc = python_m(
        "temoto",
        "demo",
        "1",
        "--foxglove",
        "0",
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        env=_env(),
    )
    assert proc.stdout is not None
    url = _url(proc.stdout, "serving the displays on")
    assert url.startswith("ws://127.0.0.1:"), "no foxglove line"
    sensors = ("lidar_3d", "depth_camera", "lidar_2d")
    topics = [f"/display/{sensor}/data" for sensor in sensors]
    with FoxgloveClient(url) as client:
        client.wait(
            lambda c: ("unadvertise", topics[-1]) in [(op, t) for _, op, t in c.events],
            timeout=30,
        )
    changes = [(op, t) for _, op, t in client.events if op != "message"]
    expected = [(op, t) for t in topics for op in ("advertise", "unadvertise")]
    assert changes == expected
    assert client.server_info["name"] == "temoto demo 1"
    rest = proc.stdout.read()
    assert proc.wait(30) == 0, rest
    for sensor in sensors:
        assert f"display: showing {sensor} (/display/{sensor}/data)" in rest


def test_the_robot_command_writes_a_foxglove_layout_for_its_features(tmp_path: Path) -> None:
    layout = tmp_path / "arm.json"
    mission = ROOT / "examples" / "missions" / "arm_poses.graph.json"
    proc = _run(*ROBOT, "--mission", str(mission), "--foxglove-layout", str(layout))
    assert proc.returncode == 0, proc.stderr
    panels: dict[str, dict[str, Any]] = {}

    def walk(node: dict[str, Any]) -> None:
        if node.get("type") == "panel":
            panels[node["panelType"]] = node
        for item in node.get("items", []):
            walk(item["content"])

    walk(json.loads(layout.read_text())["content"])
    assert sorted(panels) == ["Log", "Plot", "RawMessages", "StateTransitions"]  # no 3D, no Map
    series = panels["Plot"]["config"]["paths"]
    assert series[0] == {"label": "shoulder_pan", "value": "/sim_arm/joint_states.position[0]"}
    assert len(series) == 6
    assert panels["RawMessages"]["config"]["topicPath"] == "/sim_arm/health"
    assert panels["Log"]["config"]["topicToRender"] == "/temoto/log"


def test_demo_2_shows_the_escorts_camera_on_the_same_display_in_foxglove(
    python_m: Start,
) -> None:
    demo = ("temoto", "demo", "2", "--speed", "3", "--foxglove", "0")
    proc = python_m(*demo, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, env=_env())
    assert proc.stdout is not None
    url = _url(proc.stdout, "serving the display on")
    assert url.startswith("ws://127.0.0.1:"), "no foxglove line"
    topic = "/display/camera/data"
    with FoxgloveClient(url) as client:
        client.wait(lambda c: topic in c.topics(), timeout=30)
        assert client.topics()[topic] == "temoto.ComponentData"
        sub = client.subscribe(topic)
        client.wait(
            lambda c: any(m.payload["component"] == "escort_camera" for m in c.messages),
            timeout=30,
        )
    cameras = [m.payload["component"] for m in client.messages if m.subscription == sub]
    first = cameras.index("escort_camera")
    assert set(cameras[:first]) == {"worker_camera"}  # one display, its source switched
    escort = next(m.payload for m in client.messages if m.payload["component"] == "escort_camera")
    assert escort["robot"] == "escort"
    rest = proc.stdout.read()
    assert proc.wait(60) == 0, rest
    assert "display: showing escort_camera" in rest


def test_the_robot_commands_foxglove_commands_need_the_flag_and_the_token(
    python_m: Start,
) -> None:
    """``--foxglove-commands``: the services are offered, and a call needs the token."""
    proc = python_m(
        *ROBOT,
        "--foxglove",
        "0",
        "--foxglove-commands",
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        env=_env(TEMOTO_FOXGLOVE_TOKEN="tok-29"),
    )
    said: list[str] = []
    url = _url(proc.stderr, "temoto: foxglove on ", said)
    assert url.startswith("ws://127.0.0.1:"), "no foxglove line"
    assert any("token $TEMOTO_FOXGLOVE_TOKEN" in line for line in said)  # not echoed
    with FoxgloveClient(url) as client:
        client.wait(lambda c: "/temoto/stop" in c.services)
        ok, why = client.call("/temoto/stop", {"token": "nope", "graph": "x"})
        assert not ok
        assert "token" in why
        ok, why = client.call("/temoto/stop", {"token": "tok-29", "graph": "x"})
        assert not ok
        assert "'x'" in why  # past the token: the engine has no run x
    assert _stopped(proc) == 0


def test_foxglove_commands_without_foxglove_is_refused_in_one_line() -> None:
    proc = _run(*ROBOT, "--foxglove-commands")
    assert proc.returncode == 2, proc.stderr
    assert "--foxglove-commands needs --foxglove" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_with_a_live_view_alone_a_graphs_display_is_drawn_by_the_page(
    tmp_path: Path, python_m: Start
) -> None:
    """``--live-view`` without ``--foxglove``: ShowDisplay works, the page lists the display."""
    import time
    import urllib.request

    graph = show_display_graph("show_joints", source="robot", field="joints", duration=4.0)
    mission = tmp_path / "show.graph.json"
    mission.write_text(json.dumps(graph))
    proc = python_m(
        *ROBOT,
        "--live-view",
        "0",
        "--mission",
        str(mission),
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        env=_env(),
    )
    url = _url(proc.stdout, "live view: ").split("?")[0]
    assert url.startswith("http://127.0.0.1:"), "no live view line"
    deadline = time.monotonic() + 20
    shown: list[dict[str, Any]] = []
    while time.monotonic() < deadline:
        with urllib.request.urlopen(url + "api/displays", timeout=5) as answer:
            shown = json.load(answer)["displays"]
        if shown and shown[0]["messages"]:
            break
        time.sleep(0.1)
    assert [d["name"] for d in shown] == ["robot_joints"]
    assert shown[0]["panel"] == "plot"
    assert shown[0]["messages"][-1]["name"][0] == "shoulder_pan"
    assert proc.wait(30) == 0  # the mission ends on_true once the display is released
