"""A Dynamixel chain is checked whole before anything is written, across processes.

The simulated chain runs in a process of its own (:mod:`temoto.testing.simhost`), the robot in
another (``python -m temoto.managers.robot``), and the servos' registers are read afterwards by
a third client (dynamixel-sdk, through ``_sdk``) on the chain's pseudo-terminal.
"""

from __future__ import annotations

import contextlib
import json
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from temoto.drivers.dynamixel import _sdk
from temoto.testing.exitpaths import FAMILIES

dxl: Any = pytest.importorskip("dynamixel_sdk")

RETURN_DELAY, OPERATING_MODE, MAX_POSITION, MIN_POSITION, TORQUE = 9, 11, 48, 52, 64
SIZES = {RETURN_DELAY: 1, OPERATING_MODE: 1, MAX_POSITION: 4, MIN_POSITION: 4, TORQUE: 1}
FACTORY = {RETURN_DELAY: 250, OPERATING_MODE: 3, MAX_POSITION: 4095, MIN_POSITION: 0, TORQUE: 0}
MISSION = {
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


def chain(last_model: str = "XM430-W350") -> dict[str, Any]:
    """Six servos whose profile sets limits and return delay (EEPROM writes at configure)."""
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


@contextlib.contextmanager
def simhost(entry: dict[str, Any]) -> Iterator[tuple[subprocess.Popen[str], str]]:
    """The chain in a process of its own; yields it and its link."""
    host = subprocess.Popen(
        [sys.executable, "-m", "temoto.testing.simhost", json.dumps(entry)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert host.stdout is not None
        yield host, json.loads(host.stdout.readline())["config"]["link"]
    finally:
        try:
            host.communicate("quit\n", timeout=10)
        except subprocess.TimeoutExpired:
            host.kill()
            host.communicate()


def command(host: subprocess.Popen[str], words: str) -> None:
    assert host.stdin is not None
    assert host.stdout is not None
    host.stdin.write(words + "\n")
    host.stdin.flush()
    while True:  # state lines ({"t": ...}) come in between
        line = json.loads(host.stdout.readline())
        if "ok" in line or "error" in line:
            assert "ok" in line, line
            return


def robot(tmp_path: Path, entry: dict[str, Any]) -> subprocess.CompletedProcess[str]:
    """The robot process with a one-motion mission on the device."""
    profile = {"robot": "checked", "devices": {"device": entry}}
    profile["features"] = FAMILIES["dynamixel"]["features"]
    (tmp_path / "profile.json").write_text(json.dumps(profile))
    (tmp_path / "mission.json").write_text(json.dumps(MISSION))
    argv = [sys.executable, "-m", "temoto.managers.robot", "--local"]
    argv += ["--profile", str(tmp_path / "profile.json")]
    argv += ["--mission", str(tmp_path / "mission.json")]
    return subprocess.run(argv, capture_output=True, text=True, timeout=60, check=False)


def registers(link: str) -> dict[int, dict[int, int]]:
    """Every servo's EEPROM settings and torque, read by a third client.

    One SYNC_READ of the whole span (Return Delay Time to Torque Enable), asked again until
    every servo answered: the simulator is a loaded process and a reply may come after the
    SDK's timeout, during the next try -- as that try asks the same, a late reply carries the
    same values (one READ per register would take a late reply for the next register's
    value; status packets of another length are dropped, see ``_sdk``).
    """
    first, last = min(SIZES), max(a + n for a, n in SIZES.items())
    port = _sdk.SdkPort(link.removeprefix("serial:").partition("?")[0], 1_000_000)
    port.open()
    try:
        reader = port.sync_reader(first, last - first, list(range(1, 7)))
        spans: dict[int, bytes] = {}
        for _ in range(20):
            _result, data, _errors = reader.read()
            spans.update(data)
            if len(spans) == 6:
                break
        else:
            raise AssertionError(f"servos {sorted(set(range(1, 7)) - set(spans))} did not answer")
        return {
            dxl_id: {
                address: int.from_bytes(span[address - first : address - first + n], "little")
                for address, n in SIZES.items()
            }
            for dxl_id, span in spans.items()
        }
    finally:
        port.close()


def test_a_wrong_model_on_servo_6_leaves_servos_1_to_5_as_they_were(tmp_path: Path) -> None:
    # the chain: servo 6 is an XL430-W250; the robot's profile says XM430-W350
    with simhost(chain("XL430-W250")) as (_host, link):
        ran = robot(tmp_path, {**chain(), "link": link})
        said = ran.stdout + ran.stderr
        assert ran.returncode == 1, said
        assert registers(link) == dict.fromkeys(range(1, 7), FACTORY), said
        assert "servo 6 (j6) is XL430-W250 (model number 1060)" in said, said
        assert "nothing was written to any servo" in said, said
        assert "TxRxResult" not in said


def test_garbled_replies_to_ping_write_nothing(tmp_path: Path) -> None:
    # what a noisy line, a wrong baud rate or servos answering one id at once look like
    with simhost(chain()) as (host, link):
        command(host, "inject corrupt")
        ran = robot(tmp_path, {**chain(), "link": link})
        command(host, "clear corrupt")
        said = ran.stdout + ran.stderr
        assert ran.returncode == 1, said
        assert registers(link) == dict.fromkeys(range(1, 7), FACTORY), said
        assert "the replies to PING of servos 1, 2, 3, 4, 5, 6 were garbled" in said, said
        assert "(or duplicate servo ids)" in said, said
        assert "TxRxResult" not in said
