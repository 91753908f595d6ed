"""An ODrive profile asking more than the device is configured for: exit 2, nothing written.

The simulated ODrives run in a process of their own (:mod:`temoto.testing.simhost`, their
``vel_limit`` set to 2 turn/s), the robot command in another one, and the CAN bus (python-can
``udp_multicast`` inside ``unshare -n``) is watched from this one: every frame from before the
robot starts until after it exits. The robot reads each node's limits over CAN (``RxSdo``,
decoded here with the official DBC) and refuses the profile's ``velocity_limit`` of 20 rad/s
(3.2 turn/s) with one line, before any ``Set_Axis_State``, ``Set_Limits``, controller mode or
set-point is sent.

Run as a script (``python tests/safety/test_odrive_limits_on_wire.py DIR``) it is the part that
runs inside the namespace; the test starts it there.
"""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from temoto.testing.exitpaths import in_netns, why_not_netns

pytestmark = pytest.mark.slow

CHANNEL = "239.74.163.10"
LINK = {"interface": "udp_multicast", "channel": CHANNEL, "fd": False}
#: Commands a host sends that write to or move an axis.
WRITES = {0x02, 0x07, 0x0B, 0x0C, 0x0D, 0x0E, 0x0F, 0x11, 0x12, 0x16, 0x18}


def _inside(folder: Path) -> None:
    """In the namespace: simulator process, watcher, robot process; write the result."""
    import can

    device = {
        "driver": "odrive_can",
        "link": LINK,
        "heartbeat_period": 0.1,
        "nodes": [
            {"node_id": 1, "joint": "left_wheel", "velocity_limit": 20.0},
            {"node_id": 2, "joint": "right_wheel", "velocity_limit": 20.0},
        ],
    }
    host = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "temoto.testing.simhost",
            json.dumps(device | {"sim": {"vel_limit": 2.0}}),
        ],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    frames: list[dict[str, Any]] = []
    stop = threading.Event()
    try:
        assert host.stdout is not None
        json.loads(host.stdout.readline())  # the config line: the simulator is up
        watcher = can.Bus(**LINK)

        def watch() -> None:
            while not stop.is_set():
                msg = watcher.recv(0.05)
                if msg is not None:
                    frames.append(
                        {
                            "id": msg.arbitration_id,
                            "data": bytes(msg.data).hex(),
                            "rtr": msg.is_remote_frame,
                        }
                    )

        thread = threading.Thread(target=watch, name="temoto-test-watch")
        thread.start()
        profile = folder / "robot.json"
        features = {
            "navigation": {
                "type": "differential_drive",
                "left_wheel": "left_wheel",
                "right_wheel": "right_wheel",
                "wheel_radius": 0.08,
                "wheel_separation": 0.42,
                "max_speed": 0.5,
                "max_turn_rate": 1.0,
            }
        }
        profile.write_text(
            json.dumps({"robot": "limited", "devices": {"base": device}, "features": features})
        )
        argv = [sys.executable, "-m", "temoto.managers.robot", "--local", "--profile", str(profile)]
        ran = subprocess.run(argv, capture_output=True, text=True, timeout=60, check=False)
        time.sleep(0.3)  # the last frames on their way
        stop.set()
        thread.join()
        watcher.shutdown()
        result = {"rc": ran.returncode, "stderr": ran.stderr, "stdout": ran.stdout}
        (folder / "result.json").write_text(json.dumps(result | {"frames": frames}))
    finally:
        stop.set()
        try:
            host.communicate("quit\n", timeout=10)
        except subprocess.TimeoutExpired:
            host.kill()
            host.communicate()


def test_the_robot_exits_2_with_one_line_before_writing_anything(tmp_path: Path) -> None:
    why = why_not_netns()
    if why:
        pytest.skip(why)
    import cantools
    import odrive_can

    proc = in_netns(
        [sys.executable, __file__, str(tmp_path)], capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads((tmp_path / "result.json").read_text())
    said = result["stdout"] + result["stderr"]
    assert result["rc"] == 2, said
    lines = result["stderr"].strip().splitlines()
    assert len(lines) == 1, said
    line = lines[0]
    assert str(tmp_path / "robot.json") in line, line
    assert "devices.base.nodes[0].velocity_limit: 20 rad/s" in line, line
    assert "node 1 (left_wheel)" in line, line
    assert "devices.base.nodes[1].velocity_limit" in line, line
    assert "Traceback" not in said

    db: Any = cantools.database.load_file(
        str(Path(odrive_can.__file__).parent / "dbc" / "odrive-cansimple-0.6.10.dbc")
    )
    reads: set[tuple[int, int]] = set()
    for frame in result["frames"]:
        node, cmd = frame["id"] >> 5, frame["id"] & 0x1F
        assert frame["rtr"] or cmd not in WRITES, f"node {node}: command {cmd:#x} was sent"
        if cmd == 0x04 and not frame["rtr"]:
            signals = db.decode_message(
                frame["id"], bytes.fromhex(frame["data"]), decode_choices=False
            )
            assert signals["Opcode"] == 0, signals  # reads only
            reads.add((node, int(signals["Endpoint_ID"])))
    assert {(1, 388), (2, 388)} <= reads, reads  # each node's vel_limit was read


if __name__ == "__main__":
    _inside(Path(sys.argv[1]))
