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
from pathlib import Path
from typing import Any

import pytest

from temoto.testing.foxglove_client import FoxgloveClient

pytest.importorskip("foxglove")
pytest.importorskip("websockets")

ROOT = Path(__file__).resolve().parents[2]
ARM = ROOT / "hw_profiles" / "sim_arm.yaml"


def _env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k != "TEMOTO_FLEET_KEY"}
    env.update(extra)
    return env


def test_the_robot_command_serves_its_telemetry_live_to_foxglove() -> None:
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "temoto.managers.robot",
            "--profile",
            str(ARM),
            "--local",
            "--foxglove",
            "0",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        env=_env(),
    )
    try:
        assert proc.stderr is not None
        url = ""
        for line in proc.stderr:
            if line.startswith("temoto: foxglove on "):
                url = line.split()[-1]
                break
        assert url.startswith("ws://127.0.0.1:"), "no foxglove line"
        with FoxgloveClient(url) as client:
            client.wait(lambda c: "/sim_arm/joint_states" in c.topics(), timeout=20)
            assert client.topics()["/sim_arm/health"] == "temoto.RobotHealth"
            sub = client.subscribe("/sim_arm/joint_states")
            joints = client.first_message(sub).payload
            assert joints["name"][:2] == ["shoulder_pan", "shoulder_lift"]
            assert joints["position"] == pytest.approx([0.0] * 6, abs=0.05)  # the sim starts at 0
        proc.send_signal(signal.SIGINT)
        assert proc.wait(30) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        if proc.stderr is not None:
            proc.stderr.close()


def test_without_the_sdk_the_robot_command_names_the_extra(tmp_path: Path) -> None:
    (tmp_path / "foxglove.py").write_text("raise ImportError('foxglove-sdk is not installed')\n")
    path = os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")])
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "temoto.managers.robot",
            "--profile",
            str(ARM),
            "--local",
            "--foxglove",
        ],
        capture_output=True,
        text=True,
        timeout=60,
        env=_env(PYTHONPATH=path),
        check=False,
    )
    assert proc.returncode == 2, proc.stderr
    lines = [line for line in proc.stderr.splitlines() if "foxglove" in line]
    assert len(lines) == 1, proc.stderr
    assert "pip install 'temoto[foxglove]'" in lines[0]
    assert "Traceback" not in proc.stderr


def test_temoto_serve_serves_its_fleet_traffic_live_to_foxglove() -> None:
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "temoto",
            "serve",
            "--actor",
            "a",
            "--fleet-url",
            "inproc://viz",
            "--insecure",
            "--foxglove",
            "0",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        env=_env(),
    )
    try:
        assert proc.stderr is not None
        url = next(
            (ln.split()[-1] for ln in proc.stderr if ln.startswith("temoto: foxglove on ")), ""
        )
        assert url.startswith("ws://127.0.0.1:"), "no foxglove line"
        with FoxgloveClient(url) as client:
            client.wait(lambda c: "/fleet/TEMOTO_RIS" in c.topics(), timeout=20)
            assert client.server_info["name"] == "temoto a"
            assert client.topics()["/fleet/TEMOTO_RIS"] == "temoto.FleetMessage"
            advert = client.first_message(client.subscribe("/fleet/TEMOTO_RIS")).payload
            assert (advert["channel"], advert["sender"]) == ("TEMOTO_RIS", "a")
        proc.send_signal(signal.SIGINT)
        assert proc.wait(30) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        if proc.stderr is not None:
            proc.stderr.close()


def test_demo_1_failover_is_seen_in_foxglove_as_unadvertise_then_advertise() -> None:
    proc = subprocess.Popen(
        [sys.executable, "-m", "temoto", "demo", "1", "--foxglove", "0"],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
        env=_env(),
    )
    try:
        assert proc.stdout is not None
        url = next((ln.split()[-1] for ln in proc.stdout if "serving the displays on" in ln), "")
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
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        if proc.stdout is not None:
            proc.stdout.close()


def test_the_robot_command_writes_a_foxglove_layout_for_its_features(tmp_path: Path) -> None:
    layout = tmp_path / "arm.json"
    mission = ROOT / "examples" / "missions" / "arm_poses.graph.json"
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "temoto.managers.robot",
            "--profile",
            str(ARM),
            "--local",
            "--mission",
            str(mission),
            "--foxglove-layout",
            str(layout),
        ],
        capture_output=True,
        text=True,
        timeout=60,
        env=_env(),
        check=False,
    )
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


def test_demo_2_shows_the_escorts_camera_on_the_same_display_in_foxglove() -> None:
    proc = subprocess.Popen(
        [sys.executable, "-m", "temoto", "demo", "2", "--speed", "3", "--foxglove", "0"],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
        env=_env(),
    )
    try:
        assert proc.stdout is not None
        url = next((ln.split()[-1] for ln in proc.stdout if "serving the display on" in ln), "")
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
        escort = next(
            m.payload for m in client.messages if m.payload["component"] == "escort_camera"
        )
        assert escort["robot"] == "escort"
        rest = proc.stdout.read()
        assert proc.wait(60) == 0, rest
        assert "display: showing escort_camera" in rest
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        if proc.stdout is not None:
            proc.stdout.close()


def test_the_robot_commands_foxglove_commands_need_the_flag_and_the_token() -> None:
    """``--foxglove-commands``: the services are offered, and a call needs the token."""
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "temoto.managers.robot",
            "--profile",
            str(ARM),
            "--local",
            "--foxglove",
            "0",
            "--foxglove-commands",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        env=_env(TEMOTO_FOXGLOVE_TOKEN="tok-29"),
    )
    try:
        assert proc.stderr is not None
        url, said = "", []
        for line in proc.stderr:
            said.append(line)
            if line.startswith("temoto: foxglove on "):
                url = line.split()[-1]
                break
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
        proc.send_signal(signal.SIGINT)
        assert proc.wait(30) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        if proc.stderr is not None:
            proc.stderr.close()


def test_foxglove_commands_without_foxglove_is_refused_in_one_line() -> None:
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "temoto.managers.robot",
            "--profile",
            str(ARM),
            "--local",
            "--foxglove-commands",
        ],
        capture_output=True,
        text=True,
        timeout=60,
        env=_env(),
        check=False,
    )
    assert proc.returncode == 2, proc.stderr
    assert "--foxglove-commands needs --foxglove" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_with_a_live_view_alone_a_graphs_display_is_drawn_by_the_page(tmp_path: Path) -> None:
    """``--live-view`` without ``--foxglove``: ShowDisplay works, the page lists the display."""
    import time
    import urllib.request

    graph = {
        "graph_name": "show_joints",
        "graph_entry": [{"name": "ShowDisplay", "instance_id": 0}],
        "graph_exit": [{"name": "ShowDisplay", "instance_id": 0}],
        "actions": [
            {
                "name": "ShowDisplay",
                "instance_id": 0,
                "type": "sync",
                "input_parameters": {
                    "source": {"pvf_type": "string", "pvf_value": "robot"},
                    "field": {"pvf_type": "string", "pvf_value": "joints"},
                    "duration": {"pvf_type": "number", "pvf_value": 4.0},
                },
            }
        ],
    }
    mission = tmp_path / "show.graph.json"
    mission.write_text(json.dumps(graph))
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "temoto.managers.robot",
            "--profile",
            str(ARM),
            "--local",
            "--live-view",
            "0",
            "--mission",
            str(mission),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
        env=_env(),
    )
    try:
        assert proc.stdout is not None
        url = ""
        for line in proc.stdout:
            if line.startswith("live view: "):
                url = line.split()[-1].split("?")[0]
                break
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
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        if proc.stdout is not None:
            proc.stdout.close()
