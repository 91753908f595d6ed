"""A Dynamixel chain is checked whole before anything is written (issue 25), across processes.

The simulated chain runs in a process of its own (:mod:`temoto.testing.simhost`), the robot in
another (``python -m temoto.managers.robot``), and the servos' registers are read afterwards by
a third client (dynamixel-sdk) on the chain's pseudo-terminal.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from temoto.testing.exitpaths import FAMILIES

dxl: Any = pytest.importorskip("dynamixel_sdk")

RETURN_DELAY, OPERATING_MODE, MAX_POSITION, MIN_POSITION, TORQUE = 9, 11, 48, 52, 64
FACTORY = {RETURN_DELAY: 250, OPERATING_MODE: 3, MAX_POSITION: 4095, MIN_POSITION: 0, TORQUE: 0}


def chain(last_model: str) -> dict[str, Any]:
    joints = ["shoulder", "elbow", "j3", "j4", "j5", "j6"]
    servos = [
        {"id": i + 1, "joint": joint, "model": "XM430-W350", "min_position": -2.0}
        | {"max_position": 2.0}
        for i, joint in enumerate(joints)
    ]
    servos[5]["model"] = last_model
    return {
        "driver": "dynamixel",
        "link": "serial:/dev/null?baud=1000000",
        "poll_rate": 50,
        "bus_watchdog": 0.5,
        "return_delay_time": 0,
        "servos": servos,
    }


def read(client: tuple[Any, Any], dxl_id: int, address: int, size: int) -> int:
    port, ph = client
    call = {1: ph.read1ByteTxRx, 4: ph.read4ByteTxRx}[size]
    for _ in range(5):
        value, result, _ = call(port, dxl_id, address)
        if result == dxl.COMM_SUCCESS:
            return int(value)
    raise AssertionError(f"servo {dxl_id} did not answer READ {address}")


def test_a_wrong_model_on_servo_6_leaves_servos_1_to_5_as_they_were(tmp_path: Path) -> None:
    # the chain: servo 6 is an XL430-W250; the robot's profile says XM430-W350
    host = subprocess.Popen(
        [sys.executable, "-m", "temoto.testing.simhost", json.dumps(chain("XL430-W250"))],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert host.stdout is not None
        served = json.loads(host.stdout.readline())["config"]
        entry = {**chain("XM430-W350"), "link": served["link"]}
        family = FAMILIES["dynamixel"]
        profile = {"robot": "wrong_model", "devices": {"device": entry}}
        profile["features"] = family["features"]
        mission = {
            "graph_name": "reach",
            "graph_entry": [{"name": "MoveJoints", "instance_id": 0}],
            "graph_exit": [{"name": "MoveJoints", "instance_id": 0}],
            "actions": [
                {
                    "name": "MoveJoints",
                    "instance_id": 0,
                    "type": "sync",
                    "input_parameters": {"pose": {"pvf_type": "string", "pvf_value": "reach"}},
                }
            ],
        }
        (tmp_path / "profile.json").write_text(json.dumps(profile))
        (tmp_path / "mission.json").write_text(json.dumps(mission))
        robot = subprocess.run(
            [
                sys.executable,
                "-m",
                "temoto.managers.robot",
                "--profile",
                str(tmp_path / "profile.json"),
                "--mission",
                str(tmp_path / "mission.json"),
                "--local",
            ],
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
        )
        said = robot.stdout + robot.stderr
        assert robot.returncode == 1, said
        # a third client on the chain: every servo as it came from the factory
        port = dxl.PortHandler(served["link"].removeprefix("serial:"))
        assert port.openPort()
        try:
            assert port.setBaudRate(1_000_000)
            client = (port, dxl.PacketHandler(2.0))
            sizes = {RETURN_DELAY: 1, OPERATING_MODE: 1, MAX_POSITION: 4, MIN_POSITION: 4}
            sizes[TORQUE] = 1
            for dxl_id in range(1, 7):
                found = {a: read(client, dxl_id, a, n) for a, n in sizes.items()}
                assert found == FACTORY, (dxl_id, found)
        finally:
            port.closePort()
        assert "servo 6 (j6) is XL430-W250 (model number 1060)" in said, said
        assert "nothing was written to any servo" in said, said
        assert "TxRxResult" not in said
    finally:
        try:
            host.communicate("quit\n", timeout=10)
        except subprocess.TimeoutExpired:
            host.kill()
            host.communicate()
