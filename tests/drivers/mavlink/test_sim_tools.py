"""Real ground-station tools against SimVehicle: MAVSDK (missions, parameters) and MAVProxy,
headless (``param fetch``, ``wp load``, ``mode auto``, a 4-waypoint flight that lands).

Both run in real time with the simulator on a ScaledClock (5x), so a flight of about 40 s of
vehicle time takes a few seconds; each test polls state with deadlines, never fixed sleeps.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from temoto.clock import ScaledClock
from temoto.drivers.mavlink import SimVehicle
from temoto.testing.tools import require_tool

from .sim_gcs import HOME, free_port, until

pytestmark = pytest.mark.slow

FAST = {"WPNAV_SPEED": 1200, "LAND_SPEED": 300, "WPNAV_RADIUS": 150}


def _offset(north: float, east: float) -> tuple[float, float]:
    lat = HOME[0] + math.degrees(north / 6_378_137.0)
    lon = HOME[1] + math.degrees(east / (6_378_137.0 * math.cos(math.radians(HOME[0]))))
    return lat, lon


CORNERS = [_offset(n, e) for n, e in [(30.0, 0.0), (30.0, 30.0), (0.0, 30.0), (0.0, 0.0)]]


# ---- MAVSDK ---------------------------------------------------------------------------------


@pytest.fixture
def mavsdk_system() -> Iterator[tuple[SimVehicle, Any]]:
    mavsdk = pytest.importorskip("mavsdk")
    port = free_port()
    sim = SimVehicle(
        "mavsdk-quad",
        clock=ScaledClock(5.0),
        gcs=[("127.0.0.1", port)],
        home=HOME,
        tau=0.5,
        climb_rate=4.0,
        descent_rate=3.0,
        params=FAST,
    )
    mavsdk.log_subscribe(lambda level, message, file, line: True)  # keep MAVSDK quiet
    client = mavsdk.Mavsdk(
        mavsdk.Configuration.create_with_component_type(mavsdk.ComponentType.GROUND_STATION)
    )
    sim.start()
    try:
        assert client.add_any_connection(f"udpin://127.0.0.1:{port}") == (
            mavsdk.ConnectionResult.SUCCESS
        )
        system = client.first_autopilot(5.0)
        assert system is not None, "MAVSDK did not discover the simulated autopilot"
        yield sim, system
    finally:
        client.destroy()
        mavsdk.log_unsubscribe()
        sim.close()


def test_mavsdk_gets_and_sets_parameters(mavsdk_system: tuple[SimVehicle, Any]) -> None:
    from mavsdk.plugins.param import Param

    sim, system = mavsdk_system
    params = Param(system)
    assert params.get_param_float("WPNAV_SPEED") == 1200.0
    params.set_param_float("WPNAV_SPEED", 850.0)
    assert sim.param("WPNAV_SPEED") == 850.0
    assert params.get_param_int("RTL_ALT") == 1500
    params.set_param_int("FS_GCS_ENABLE", 5)
    assert sim.param("FS_GCS_ENABLE") == 5.0
    everything = params.get_all_params()
    names = {p.name for p in everything.int_params} | {p.name for p in everything.float_params}
    assert {"WPNAV_SPEED", "RTL_ALT", "FS_GCS_ENABLE", "BATT_LOW_VOLT"} <= names


def test_mavsdk_uploads_and_starts_a_mission(mavsdk_system: tuple[SimVehicle, Any]) -> None:
    """MissionRaw, the MAVSDK plugin for ArduPilot missions (item 0 is home there; the Mission
    plugin writes its first item at seq 0, which ArduPilot, and this simulator, keep as home)."""
    from mavsdk.plugins.action import Action
    from mavsdk.plugins.mission_raw import MissionItem, MissionRaw

    sim, system = mavsdk_system
    rel = 6  # MAV_FRAME_GLOBAL_RELATIVE_ALT_INT

    def item(seq: int, cmd: int, lat: float, lon: float, alt: float, frame: int = rel) -> Any:
        return MissionItem(
            seq,
            frame,
            cmd,
            int(seq == 0),
            1,
            0.0,
            0.0,
            0.0,
            0.0,
            round(lat * 1e7),
            round(lon * 1e7),
            alt,
            0,
        )

    items = [item(0, 16, HOME[0], HOME[1], HOME[2], frame=0), item(1, 22, 0.0, 0.0, 8.0)]
    items += [item(2 + i, 16, lat, lon, 8.0) for i, (lat, lon) in enumerate(CORNERS)]
    items.append(item(6, 21, *CORNERS[-1], 0.0))
    mission, action = MissionRaw(system), Action(system)
    mission.upload_mission(items)
    assert [i.command for i in sim.mission()] == [16, 22, 16, 16, 16, 16, 21]
    downloaded = mission.download_mission()
    assert [(i.seq, i.command, i.x, i.y) for i in downloaded[1:]] == [
        (i.seq, i.command, i.x, i.y) for i in items[1:]
    ]
    action.arm()
    until(lambda: sim.armed, 5.0, "armed")
    mission.start_mission()
    until(lambda: sim.mode == "AUTO" and sim.position()[2] > 1.0, 10.0, "AUTO takeoff")
    until(lambda: not sim.armed, 45.0, "mission flown, landed and disarmed")
    lat, lon, alt = sim.position()
    assert alt == 0.0
    assert math.dist(_local(lat, lon), (0.0, 0.0)) < 1.5
    until(mission.is_mission_finished, 5.0, "MAVSDK sees the mission finished")


def _local(lat: float, lon: float) -> tuple[float, float]:
    north = math.radians(lat - HOME[0]) * 6_378_137.0
    east = math.radians(lon - HOME[1]) * 6_378_137.0 * math.cos(math.radians(HOME[0]))
    return north, east


# ---- MAVProxy -------------------------------------------------------------------------------


def _mavproxy() -> list[str]:
    return [sys.executable, require_tool("mavproxy.py", hint="pip install MAVProxy")]


def _waypoints(path: Path) -> None:
    """A QGC WPL 110 file (MAVProxy's ``wp save`` format): home, takeoff, 4 corners, land."""
    rows = [(0, 0, 16, 0, HOME[0], HOME[1], HOME[2]), (0, 3, 22, 0, 0.0, 0.0, 10.0)]
    rows += [(0, 3, 16, 0, lat, lon, 10.0) for lat, lon in CORNERS]
    rows.append((0, 3, 21, 0, *CORNERS[-1], 0.0))
    lines = ["QGC WPL 110"]
    for seq, (current, frame, cmd, p1, lat, lon, alt) in enumerate(rows):
        lines.append(
            f"{seq}\t{current}\t{frame}\t{cmd}\t{p1}\t0\t0\t0\t{lat:.8f}\t{lon:.8f}\t{alt}\t1"
        )
    path.write_text("\n".join(lines) + "\n")


def test_mavproxy_fetches_params_loads_waypoints_and_flies_auto(tmp_path: Path) -> None:
    command = _mavproxy()
    port = free_port()
    waypoints = tmp_path / "square.txt"
    _waypoints(waypoints)
    sim = SimVehicle(
        "mavproxy-quad",
        clock=ScaledClock(5.0),
        gcs=[("127.0.0.1", port)],
        home=HOME,
        tau=0.5,
        climb_rate=4.0,
        descent_rate=3.0,
        params=FAST,
        params_file=tmp_path / "eeprom.param",
    )
    env = {**os.environ, "HOME": str(tmp_path), "MPLBACKEND": "Agg"}
    with sim:
        proc = subprocess.Popen(
            [
                *command,
                "--master",
                f"udpin:127.0.0.1:{port}",
                "--default-modules",
                "param,wp,mode,arm,cmdlong,ftp",
                "--state-basedir",
                str(tmp_path),
                "--aircraft",
                "quad",
            ],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            cwd=tmp_path,
            env=env,
        )
        out: list[str] = []
        try:
            assert proc.stdin is not None
            assert proc.stdout is not None
            os.set_blocking(proc.stdout.fileno(), False)

            def send(line: str) -> None:
                assert proc.stdin is not None
                proc.stdin.write(line.encode() + b"\n")
                proc.stdin.flush()

            def seen(text: str, seconds: float) -> None:
                deadline = time.monotonic() + seconds
                while not any(text in line for line in out):
                    assert proc.poll() is None, "MAVProxy exited:\n" + "".join(out[-40:])
                    assert time.monotonic() < deadline, (
                        f"MAVProxy never printed {text!r}:\n" + "".join(out[-40:])
                    )
                    assert proc.stdout is not None
                    try:
                        chunk = os.read(proc.stdout.fileno(), 65536)
                    except BlockingIOError:
                        chunk = b""
                    if chunk:
                        out.extend(chunk.decode(errors="replace").splitlines(keepends=True))
                    else:
                        time.sleep(0.05)

            seen("Received", 20.0)  # the parameters MAVProxy fetches by itself on connect
            send("param set RTL_ALT 2000")
            until(lambda: sim.param("RTL_ALT") == 2000.0, 10.0, "param set")
            send("param fetch")
            seen("Requested parameter list", 10.0)
            # the recipe of docs/simulators.md: AUTO_OPTIONS 3 = arming in AUTO (bit 0) and
            # its takeoff without a raised throttle (bit 1), as SITL and a real copter need
            send("param set AUTO_OPTIONS 3")
            until(lambda: sim.param("AUTO_OPTIONS") == 3.0, 10.0, "param set AUTO_OPTIONS")
            send(f"wp load {waypoints}")
            until(lambda: len(sim.mission()) == 7, 15.0, "wp load")
            send("mode auto")
            until(lambda: sim.mode == "AUTO", 10.0, "mode auto")
            send("arm throttle")
            until(lambda: sim.armed, 10.0, "armed in AUTO (AUTO_OPTIONS bit 0)")
            until(lambda: sim.position()[2] > 9.0, 20.0, "AUTO takeoff")
            until(lambda: sim.mission_current >= 6, 40.0, "the 4 waypoints")
            until(lambda: not sim.armed, 30.0, "landed and disarmed")
            lat, lon, alt = sim.position()
            assert alt == 0.0
            assert math.dist(_local(lat, lon), (0.0, 0.0)) < 1.5
            assert "RTL_ALT 2000\n" in (tmp_path / "eeprom.param").read_text()
            assert sim.received.get("FILE_TRANSFER_PROTOCOL", 0) >= 1  # tried FTP, got a NAK
            assert sim.received.get("PARAM_REQUEST_LIST", 0) >= 1  # and fell back
        finally:
            if proc.poll() is None:
                proc.terminate()
                try:
                    proc.wait(10.0)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
            for pipe in (proc.stdin, proc.stdout):
                if pipe is not None:
                    pipe.close()
