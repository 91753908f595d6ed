"""The robot command with ``sim: true``: its simulators' endpoints, and ``--sim-out`` for a GCS."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from temoto.drivers.mavlink.protocol import Codec

ROOT = Path(__file__).resolve().parents[2]
PROFILES = ROOT / "hw_profiles"
MISSION = ROOT / "examples" / "missions" / "arm_poses.graph.json"


def env() -> dict[str, str]:
    return {k: v for k, v in os.environ.items() if k != "TEMOTO_FLEET_KEY"}


def robot(*args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "temoto.managers.robot", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        env=env(),
        check=False,
    )


def test_a_mission_run_prints_each_simulator_s_endpoint_after_ready() -> None:
    proc = robot("--profile", str(PROFILES / "sim_arm.yaml"), "--mission", str(MISSION), "--local")
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    assert lines[0].startswith("robot 'sim_arm' ready in ")
    assert lines[1].startswith("  simulator arm (dynamixel): link: serial:/dev/pts/")
    assert "PortHandler(" in lines[1]


def test_the_robot_s_own_vehicle_streams_to_sim_out_until_sigterm() -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as gcs:
        gcs.bind(("127.0.0.1", 0))
        port = gcs.getsockname()[1]
        proc = subprocess.Popen(
            [sys.executable, "-m", "temoto.managers.robot", "--profile",
             str(PROFILES / "sim_quad.yaml"), "--local", "--sim-out", f"udp:127.0.0.1:{port}"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env(),
        )  # fmt: skip
        try:
            assert proc.stdout is not None
            ready = proc.stdout.readline()
            assert "ready" in ready, ready
            line = proc.stdout.readline()
            assert line.startswith("  simulator quad (mavlink): link: udpin:127.0.0.1:")
            assert "mavproxy.py --master udpout:127.0.0.1:" in line
            codec = Codec(255, 190)
            deadline = time.monotonic() + 20
            names: set[str] = set()
            while "HEARTBEAT" not in names and time.monotonic() < deadline:
                gcs.settimeout(max(0.01, deadline - time.monotonic()))
                data, _ = gcs.recvfrom(65536)
                names |= {m.name for m in codec.decode_datagram(data)}
            assert "HEARTBEAT" in names  # the ground station sees the robot's vehicle
        finally:
            proc.send_signal(signal.SIGTERM)
            try:
                _, err = proc.communicate(timeout=30)
            except subprocess.TimeoutExpired:  # killed here: no process outlives the test
                proc.kill()
                _, err = proc.communicate()
                pytest.fail(f"no exit within 30 s of SIGTERM; its stderr:\n{err}")
    assert proc.returncode == 0, err
    assert "Traceback" not in err


@pytest.mark.parametrize(
    ("profile", "words"),
    [
        ("sim_arm.yaml", "no MAVLink vehicle"),
        ("real_quad_ardupilot.yaml", "sim: false"),
    ],
)
def test_sim_out_without_a_simulated_vehicle_is_invalid_input(profile: str, words: str) -> None:
    proc = robot("--profile", str(PROFILES / profile), "--local", "--sim-out", "udp:127.0.0.1:1")
    assert proc.returncode == 2
    assert words in proc.stderr
    assert "Traceback" not in proc.stderr


def test_sim_out_must_be_a_loopback_udp_address() -> None:
    proc = robot("--profile", str(PROFILES / "sim_quad.yaml"), "--sim-out", "udp:192.0.2.1:1")
    assert proc.returncode == 2
    assert "loopback" in proc.stderr
