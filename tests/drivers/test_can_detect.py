"""ODriveDriver.detect: finds heartbeating axes on a bus, only by listening.

The simulators run on a real-time clock here: detect listens for real seconds, so the axes must
heartbeat in real time while it does.
"""

from __future__ import annotations

import logging
import math
import time
import uuid
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor, wait
from typing import Any

import can
import pytest
from contract import state

from temoto.clock import MonotonicClock
from temoto.config import parse_profile
from temoto.drivers import DriverState
from temoto.drivers.can_motor import cansimple as cs
from temoto.drivers.can_motor.odrive import ODriveDriver
from temoto.drivers.can_motor.sim import SimODrive

HB = 0.05  # the simulated axes' heartbeat period, real seconds
LISTEN = 0.3  # detect's timeout: several heartbeats
ODRIVE = "temoto.drivers.can_motor.detect"  # the logger detect reports on


def link(channel: str) -> dict[str, Any]:
    return {"interface": "virtual", "channel": channel}


def channel() -> str:
    return f"detect-{uuid.uuid4().hex[:8]}"


@pytest.fixture
def axes() -> Iterator[tuple[SimODrive, str]]:
    """Two ODrive axes (node ids 7 and 3) heartbeating on a fresh virtual channel."""
    ch = channel()
    sim = SimODrive(link(ch), [7, 3], MonotonicClock(), heartbeat_period=HB)
    with sim:
        yield sim, ch


def entry_for(ch: str, *ids: int) -> dict[str, Any]:
    nodes = [{"node_id": n, "joint": f"joint_{n}"} for n in ids]
    return {"driver": "odrive_can", "link": link(ch), "nodes": nodes}


def test_two_axes_make_one_entry_that_drives_them(axes: tuple[SimODrive, str]) -> None:
    sim, ch = axes
    entries = ODriveDriver.detect([link(ch)], timeout=LISTEN)
    assert entries == [entry_for(ch, 3, 7)]  # node ids sorted
    entry = entries[0]

    # it pastes into a profile as it is; the profile hands from_profile the entry minus `driver`
    profile = parse_profile({"robot": "found", "devices": {"base": entry}}, file="found.yaml")
    spec = profile.devices["base"]
    assert spec.driver == "odrive_can"
    assert spec.joints == ("joint_3", "joint_7")
    assert spec.config == {k: v for k, v in entry.items() if k != "driver"}

    clock = MonotonicClock()
    driver = ODriveDriver.from_profile("base", spec.config, clock=clock, where="devices.base")
    try:
        assert driver.joint_names == ("joint_3", "joint_7")
        assert [n.node_id for n in driver.nodes] == [3, 7]
        assert driver.link == link(ch)
        driver.configure()
        driver.activate()
        assert state(driver) is DriverState.ACTIVE
        assert set(driver.read_state().joints) == {"joint_3", "joint_7"}
        assert sim.axes[3].state == sim.axes[7].state == cs.AxisState.CLOSED_LOOP_CONTROL
        driver.deactivate()
        assert sim.axes[3].state == sim.axes[7].state == cs.AxisState.IDLE
    finally:
        driver.shutdown()
    assert state(driver) is DriverState.FINALIZED


def test_an_empty_channel_finds_nothing_after_the_timeout() -> None:
    start = time.monotonic()
    assert ODriveDriver.detect([link(channel())], timeout=0.2) == []
    took = time.monotonic() - start
    assert 0.15 <= took < 0.2 + 2.0


def test_detect_sends_nothing(axes: tuple[SimODrive, str]) -> None:
    sim, ch = axes
    with can.Bus(interface="virtual", channel=ch) as listener:
        assert ODriveDriver.detect([link(ch)], timeout=LISTEN) == [entry_for(ch, 3, 7)]
        sim.close()  # no more frames from the axes: what the listener holds is all there was
        heard: list[tuple[int, int]] = []
        while (msg := listener.recv(timeout=0)) is not None:
            assert not msg.is_remote_frame, msg  # no requests, not even an RTR heartbeat
            heard.append(cs.split_id(msg.arbitration_id))
    cyclic = {cs.Cmd.HEARTBEAT, cs.Cmd.GET_ENCODER_ESTIMATES}
    assert heard, "the listener heard nothing: the check below would prove nothing"
    assert {node for node, _ in heard} == {3, 7}
    assert {cmd for _, cmd in heard} <= cyclic  # only what the axes send by themselves
    assert all(axis.commands == 0 for axis in sim.axes.values())
    assert all(axis.state == cs.AxisState.IDLE for axis in sim.axes.values())


def test_only_well_formed_heartbeats_count() -> None:
    ch = channel()
    hb5, hb6 = cs.arbitration_id(5, cs.Cmd.HEARTBEAT), cs.arbitration_id(6, cs.Cmd.HEARTBEAT)
    others = [
        can.Message(arbitration_id=hb5, data=b"\0" * 4, is_extended_id=False),  # truncated
        can.Message(  # a host asking node 6 for its heartbeat: not a node speaking
            arbitration_id=hb6, is_remote_frame=True, dlc=8, is_extended_id=False
        ),
        can.Message(  # another protocol's extended id that ends in 0x01
            arbitration_id=0x1ABCDE01, data=cs.encode_heartbeat(0, 1), is_extended_id=True
        ),
        can.Message(  # node 9 speaks, but not a heartbeat
            arbitration_id=cs.arbitration_id(9, cs.Cmd.GET_ENCODER_ESTIMATES),
            data=cs.encode_encoder_estimates(0.0, 0.0),
            is_extended_id=False,
        ),
    ]
    sim = SimODrive(link(ch), [2], MonotonicClock(), heartbeat_period=HB)
    with (
        sim,
        can.Bus(interface="virtual", channel=ch) as sender,
        ThreadPoolExecutor(1) as pool,
    ):
        found = pool.submit(ODriveDriver.detect, [link(ch)], timeout=LISTEN)
        while not found.done():
            for msg in others:
                sender.send(msg)
            wait([found], timeout=0.02)
        assert found.result() == [entry_for(ch, 2)]


def test_links_are_looked_at_in_order_and_a_bad_bus_is_skipped(
    axes: tuple[SimODrive, str], caplog: pytest.LogCaptureFixture
) -> None:
    _, ch = axes
    other = channel()
    with SimODrive(link(other), [1], MonotonicClock(), heartbeat_period=HB):
        links = [
            link(other),
            {"interface": "no_such_can_interface", "channel": "x"},
            link(channel()),  # empty: no entry
            {**link(ch), "receive_own_messages": False},  # extra Bus arguments are kept
        ]
        with caplog.at_level(logging.WARNING, logger=ODRIVE):
            entries = ODriveDriver.detect(links, timeout=0.2)
    assert entries == [
        entry_for(other, 1),
        {**entry_for(ch, 3, 7), "link": {**link(ch), "receive_own_messages": False}},
    ]
    skipped = [r for r in caplog.records if r.name == ODRIVE and r.levelno == logging.WARNING]
    assert len(skipped) == 1
    assert "no_such_can_interface" in skipped[0].getMessage()


def test_what_the_heartbeats_tell_is_logged_not_added(
    axes: tuple[SimODrive, str], caplog: pytest.LogCaptureFixture
) -> None:
    sim, ch = axes
    sim.inject("hardware_error", kind="overheat", node=7)
    assert sim.axes[7].error  # raised at once: the next heartbeats carry it
    with caplog.at_level(logging.INFO, logger=ODRIVE):
        entries = ODriveDriver.detect([link(ch)], timeout=LISTEN)
    assert entries == [entry_for(ch, 3, 7)]  # a faulted axis is still found, and nothing added
    lines = [r.getMessage() for r in caplog.records if r.name == ODRIVE]
    node3 = next(line for line in lines if "node 3 " in line)
    node7 = next(line for line in lines if "node 7 " in line)
    assert "IDLE" in node3
    assert "errors none" in node3
    assert "MOTOR_OVER_TEMP" in node7


def test_no_links_looks_where_python_can_says(
    axes: tuple[SimODrive, str], monkeypatch: pytest.MonkeyPatch
) -> None:
    _, ch = axes
    configs = [{"interface": "virtual"}, link(ch)]  # the first is not in profile form: skipped
    monkeypatch.setattr(can, "detect_available_configs", lambda *a, **k: configs)
    assert ODriveDriver.detect(timeout=LISTEN) == [entry_for(ch, 3, 7)]
    monkeypatch.setattr(can, "detect_available_configs", lambda *a, **k: [])
    assert ODriveDriver.detect(timeout=LISTEN) == []


@pytest.mark.parametrize("timeout", [0, 0.0, -1.0, math.nan, math.inf])
def test_a_bad_timeout_is_a_value_error(timeout: float) -> None:
    with pytest.raises(ValueError, match="timeout"):
        ODriveDriver.detect([link(channel())], timeout=timeout)


@pytest.mark.parametrize(
    ("links", "named"),
    [
        ("can0", "sequence"),
        (link("can0"), "sequence"),  # one mapping, not a list of them
        (["can0"], r"links\[0\]"),
        ([link("ok"), {"interface": "virtual"}], r"links\[1\]"),
        ([{"channel": "can0"}], r"links\[0\]"),
        ([{"interface": "virtual", "channel": ""}], r"links\[0\]"),
        ([{"interface": "virtual", "channel": "c", "extra": [1]}], r"links\[0\]"),
    ],
)
def test_a_malformed_link_is_a_value_error_naming_it(links: Any, named: str) -> None:
    start = time.monotonic()
    with pytest.raises(ValueError, match=named):
        ODriveDriver.detect(links, timeout=5.0)
    assert time.monotonic() - start < 2.0  # checked before listening anywhere
