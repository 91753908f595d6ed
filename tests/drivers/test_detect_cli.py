"""``temoto drivers list|detect``: the command around the drivers' detect().

The ODrive case runs the simulator in real time on a virtual CAN channel (detect listens for
real seconds), then builds a profile from what the command printed.
"""

from __future__ import annotations

import json
import uuid
from collections.abc import Iterator
from typing import Any

import pytest
import yaml

from temoto.cli import main
from temoto.clock import MonotonicClock
from temoto.config import parse_profile
from temoto.drivers.can_motor.odrive import ODriveDriver
from temoto.drivers.can_motor.sim import SimODrive
from temoto.errors import ProfileError

LISTEN = "0.3"  # --timeout: several heartbeats of the simulated axes


@pytest.fixture
def bus() -> Iterator[str]:
    """A virtual CAN channel with two ODrive axes (node ids 4 and 2) heartbeating on it."""
    channel = f"cli-{uuid.uuid4().hex[:8]}"
    link = {"interface": "virtual", "channel": channel}
    with SimODrive(link, [4, 2], MonotonicClock(), heartbeat_period=0.05):
        yield channel


def link_arg(channel: str) -> str:
    return f"{{interface: virtual, channel: {channel}}}"


def test_list_names_every_built_in_driver(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["drivers", "list"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert [line.split()[0] for line in lines] == ["dynamixel", "mavlink", "mit_can", "odrive_can"]
    assert all(line.split(None, 1)[1] == "installed" for line in lines)  # the dev extra has all


def test_detect_prints_a_devices_block_that_makes_a_working_profile(
    bus: str, capsys: pytest.CaptureFixture[str]
) -> None:
    args = ["drivers", "detect", "odrive_can", "--link", link_arg(bus), "--timeout", LISTEN]
    assert main(args) == 0
    captured = capsys.readouterr()
    assert "asking odrive_can for devices on the given links" in captured.err
    assert "odrive_can: 1 found" in captured.err
    printed = yaml.safe_load(captured.out)
    entry = printed["devices"]["odrive_can_1"]
    assert entry == {
        "driver": "odrive_can",
        "link": {"interface": "virtual", "channel": bus},
        "nodes": [{"node_id": 2, "joint": "joint_2"}, {"node_id": 4, "joint": "joint_4"}],
    }
    # pasted under devices: it is a valid profile, and the entry builds the driver as it is
    profile = parse_profile({"robot": "found", **printed}, file="found.yaml")
    assert profile.devices["odrive_can_1"].joints == ("joint_2", "joint_4")
    driver = ODriveDriver.from_profile("base", entry, clock=MonotonicClock(), where="d.base")
    assert driver.joint_names == ("joint_2", "joint_4")


def test_detect_json(bus: str, capsys: pytest.CaptureFixture[str]) -> None:
    args = ["drivers", "detect", "odrive_can", "--link", link_arg(bus), "--timeout", LISTEN]
    assert main([*args, "--json"]) == 0
    entries: list[dict[str, Any]] = json.loads(capsys.readouterr().out)
    assert [e["driver"] for e in entries] == ["odrive_can"]
    assert [n["node_id"] for n in entries[0]["nodes"]] == [2, 4]


def test_mit_motors_are_never_detected_and_nothing_found_exits_1(
    bus: str, capsys: pytest.CaptureFixture[str]
) -> None:
    # MIT-mode motors send nothing unasked, and any frame commands them: detect only listens
    args = ["drivers", "detect", "mit_can", "--link", link_arg(bus), "--timeout", "0.1"]
    assert main(args) == 1
    captured = capsys.readouterr()
    assert "mit_can: 0 found" in captured.err
    assert captured.out == ""


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["odrive_can", "--link", "{interface: [", "--timeout", "0.1"], "is not a link value"),
        (["odrive_can", "--timeout", "0"], "--timeout must be positive"),
        (["odrive_can", "--link", "serial:/dev/null", "--timeout", "0.1"], "odrive_can: "),
        (["no_such_driver", "--timeout", "0.1"], "no driver named 'no_such_driver'"),
    ],
)
def test_bad_input_exits_2_with_the_reason(
    args: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["drivers", "detect", *args]) == 2
    err = capsys.readouterr().err
    assert message in err
    assert "Traceback" not in err


def test_an_entry_naming_another_driver_is_refused() -> None:
    entry = {"driver": "mit_can", "link": {"interface": "virtual", "channel": "x"}, "nodes": []}
    with pytest.raises(ProfileError, match=r"d\.base\.driver: must be 'odrive_can'"):
        ODriveDriver.from_profile("base", entry, clock=MonotonicClock(), where="d.base")
