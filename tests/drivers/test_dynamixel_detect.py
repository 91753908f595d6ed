"""DynamixelDriver.detect: finds a chain by one broadcast PING, and moves nothing.

The simulated chains here model the baud rate (``SimDynamixelChain(..., baud=)``): their servos
hear only packets sent while the pseudo-terminal is set to their rate, so a wrong rate goes
unanswered as on a real bus. Detect waits real seconds, so the simulators run on a real clock.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Iterator
from types import SimpleNamespace
from typing import Any

import pytest
import yaml
from contract import eventually

from temoto.clock import MonotonicClock
from temoto.config import parse_profile
from temoto.drivers import DriverState
from temoto.drivers.dynamixel import control_table as ct
from temoto.drivers.dynamixel import protocol as p
from temoto.drivers.dynamixel.driver import (
    DETECT_BAUD_RATES,
    SIM_REPLY_TIMEOUT,
    DynamixelDriver,
)
from temoto.drivers.dynamixel.sim import SimDynamixelChain

pytest.importorskip("dynamixel_sdk")

CHAIN = {2: "XM430-W350", 5: "XL430-W250", 9: "XM430-W350"}
FOUND = 0.2  # detect's timeout where servos answer: real seconds
MISS = 0.05  # where nothing answers (each baud rate tried costs this much)
SLACK = 1.5  # real seconds of scheduling slack in time bounds (loaded machines)
DRIVER = "temoto.drivers.dynamixel.detect"  # the logger detect reports on


def servos(*ids: int) -> list[dict[str, Any]]:
    return [
        {
            "id": i,
            "joint": f"joint_{i}",
            "model": CHAIN[i],
            "mode": "position",
            "min_position": -3.14,  # the single turn of position mode: ±π is one tick beyond
            "max_position": 3.14,
        }
        for i in ids
    ]


def snapshot(sim: SimDynamixelChain) -> dict[tuple[int, str], int]:
    """Every register of every servo (but Realtime Tick, the servo's millisecond clock)."""
    return {
        (i, r.name): sim.read_register(i, r.address)
        for i in sim.ids
        for r in sim.model_of(i).registers
        if r.name != "Realtime Tick"
    }


@pytest.fixture
def make_chain() -> Iterator[Callable[..., SimDynamixelChain]]:
    made: list[SimDynamixelChain] = []

    def make(baud: int = 1_000_000, chain: dict[int, str] | None = None) -> SimDynamixelChain:
        sim = SimDynamixelChain(
            chain or CHAIN, clock=MonotonicClock(), name=f"detect{len(made)}", baud=baud
        )
        made.append(sim)
        sim.start()
        return sim

    yield make
    for sim in made:
        sim.close()


@pytest.fixture
def sim(make_chain: Callable[..., SimDynamixelChain]) -> SimDynamixelChain:
    return make_chain()


@pytest.fixture
def instructions(sim: SimDynamixelChain, monkeypatch: pytest.MonkeyPatch) -> list[tuple[int, int]]:
    """(id, instruction) of every packet the chain receives (heard at its baud rate or not)."""
    seen: list[tuple[int, int]] = []
    handle = sim._handle

    def record(packet: p.Packet, line: int | None = None) -> list[bytes]:
        seen.append((packet.id, packet.instruction))
        return handle(packet, line)

    monkeypatch.setattr(sim, "_handle", record)
    return seen


def test_a_chain_becomes_an_entry_the_driver_runs(sim: SimDynamixelChain) -> None:
    link = f"serial:{sim.path}?baud=1000000"
    entries = DynamixelDriver.detect([link], timeout=FOUND)
    assert entries == [{"driver": "dynamixel", "link": link, "servos": servos(2, 5, 9)}]
    entry = entries[0]

    # from_profile takes it as it is, and it pastes into a profile (through YAML) as it is
    clock = MonotonicClock()
    as_is = DynamixelDriver.from_profile("arm", entry, clock=clock, where="devices.arm")
    assert as_is.joint_names == ("joint_2", "joint_5", "joint_9")
    assert [s.model for s in as_is.servos] == ["XM430-W350", "XL430-W250", "XM430-W350"]
    assert (as_is.port, as_is.baud) == (sim.path, 1_000_000)
    for servo in as_is.servos:  # the limits span the turn
        assert servo.ticks(servo.min_position) <= 1
        assert servo.ticks(servo.max_position) >= 4094
    pasted = yaml.safe_load(yaml.safe_dump({"robot": "found", "devices": {"arm": entry}}))
    spec = parse_profile(pasted, file="found.yaml").devices["arm"]
    assert spec.driver == "dynamixel"
    assert spec.joints == ("joint_2", "joint_5", "joint_9")

    # and runs on the chain it found (with the simulator's reply margin for loaded machines)
    driver = DynamixelDriver.from_profile(
        "arm", {**entry, "reply_timeout": SIM_REPLY_TIMEOUT}, clock=clock, where="devices.arm"
    )
    try:
        driver.configure()
        driver.activate()
        assert driver.state is DriverState.ACTIVE
        assert sorted(driver.read_state().joints) == ["joint_2", "joint_5", "joint_9"]
        assert all(sim.read_register(i, ct.TORQUE_ENABLE.address) == 1 for i in sim.ids)
    finally:
        driver.shutdown()
    assert driver.state is DriverState.FINALIZED
    assert all(sim.read_register(i, ct.TORQUE_ENABLE.address) == 0 for i in sim.ids)


@pytest.mark.parametrize(("baud", "tried"), [(57600, 1), (1_000_000, 2), (115200, 3)])
def test_without_a_baud_rate_the_common_ones_are_tried_in_order(
    make_chain: Callable[..., SimDynamixelChain], baud: int, tried: int
) -> None:
    assert DETECT_BAUD_RATES[:3] == (57600, 1_000_000, 115200)
    sim = make_chain(baud)
    entries = DynamixelDriver.detect(f"serial:{sim.path}", timeout=FOUND)  # one string: one link
    assert entries == [
        {"driver": "dynamixel", "link": f"serial:{sim.path}?baud={baud}", "servos": servos(2, 5, 9)}
    ]
    # one broadcast PING per rate, up to the first that was answered
    eventually(lambda: sim.stats["packets"] == tried, 1.0)
    assert sim.stats["packets"] == tried


def test_a_bare_device_path_is_a_link_too(sim: SimDynamixelChain) -> None:
    entries = DynamixelDriver.detect([sim.path], timeout=FOUND)
    assert [e["link"] for e in entries] == [f"serial:{sim.path}?baud=1000000"]


def test_detection_only_pings_and_moves_nothing(
    sim: SimDynamixelChain, instructions: list[tuple[int, int]]
) -> None:
    sim.write_register(5, ct.GOAL_POSITION.address, 3000)  # a goal the servo would go to
    before = snapshot(sim)
    assert DynamixelDriver.detect([f"serial:{sim.path}?baud=1000000"], timeout=FOUND)
    assert DynamixelDriver.detect([f"serial:{sim.path}"], timeout=FOUND)
    # over 0.4 real seconds: a servo with torque on would have moved towards its goal meanwhile
    assert snapshot(sim) == before
    assert all(sim.read_register(i, ct.TORQUE_ENABLE.address) == 0 for i in sim.ids)
    assert sim.read_register(5, ct.GOAL_POSITION.address) == 3000
    assert sim.read_register(5, ct.PRESENT_POSITION.address) == ct.POSITION_CENTER
    assert sim.stats["reboots"] == 0
    eventually(lambda: len(instructions) == 3, 1.0)  # 1000000; then 57600, 1000000
    assert instructions == [(p.BROADCAST_ID, p.Instruction.PING)] * 3


def test_a_wrong_baud_rate_finds_nothing_in_time(sim: SimDynamixelChain) -> None:
    start = time.monotonic()
    assert DynamixelDriver.detect([f"serial:{sim.path}?baud=57600"], timeout=MISS) == []
    assert time.monotonic() - start < MISS + SLACK
    eventually(lambda: sim.stats["packets"] == 1, 1.0)  # heard on the wire, not by the servos
    assert sim.stats["replies"] == 0


def test_a_silent_chain_finds_nothing_at_any_baud_rate(sim: SimDynamixelChain) -> None:
    sim.inject("silence")
    start = time.monotonic()
    assert DynamixelDriver.detect([f"serial:{sim.path}"], timeout=MISS) == []
    assert time.monotonic() - start < len(DETECT_BAUD_RATES) * MISS + SLACK
    eventually(lambda: sim.stats["packets"] == len(DETECT_BAUD_RATES), 1.0)
    assert sim.stats["replies"] == 0


def test_links_in_order_and_one_entry_each(make_chain: Callable[..., SimDynamixelChain]) -> None:
    fast = make_chain(1_000_000, {7: "XM540-W270"})
    slow = make_chain(57600, {1: "XL330-M288", 3: "XH430-W350"})
    links = [f"serial:{fast.path}?baud=1000000", f"serial:{slow.path}?baud=115200", slow.path]
    entries = DynamixelDriver.detect(links, timeout=FOUND)
    assert [e["link"] for e in entries] == [links[0], f"serial:{slow.path}?baud=57600"]
    assert [[(s["id"], s["model"]) for s in e["servos"]] for e in entries] == [
        [(7, "XM540-W270")],
        [(1, "XL330-M288"), (3, "XH430-W350")],
    ]


def test_an_unknown_model_is_left_out_with_a_warning(
    sim: SimDynamixelChain, caplog: pytest.LogCaptureFixture
) -> None:
    sim.write_register(5, ct.MODEL_NUMBER.address, 4242)  # PING answers with this register
    link = f"serial:{sim.path}?baud=1000000"
    with caplog.at_level(logging.WARNING, logger=DRIVER):
        entries = DynamixelDriver.detect([link], timeout=FOUND)
    assert entries == [{"driver": "dynamixel", "link": link, "servos": servos(2, 9)}]
    assert any("servo 5" in r.message and "4242" in r.message for r in caplog.records)
    DynamixelDriver.from_profile("arm", entries[0], clock=MonotonicClock(), where="devices.arm")

    for i in (2, 9):
        sim.write_register(i, ct.MODEL_NUMBER.address, 4242)
    assert DynamixelDriver.detect([link], timeout=FOUND) == []  # no valid entry to give


def test_a_port_that_cannot_be_opened_is_skipped(
    sim: SimDynamixelChain, caplog: pytest.LogCaptureFixture
) -> None:
    missing = "serial:/dev/temoto-no-such-port?baud=57600"
    with caplog.at_level(logging.WARNING, logger=DRIVER):
        entries = DynamixelDriver.detect(
            [missing, f"serial:{sim.path}?baud=1000000"], timeout=FOUND
        )
    assert [e["link"] for e in entries] == [f"serial:{sim.path}?baud=1000000"]
    assert any("/dev/temoto-no-such-port" in r.message for r in caplog.records)


def test_without_links_every_listed_serial_port(
    sim: SimDynamixelChain, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr("serial.tools.list_ports.comports", list)
    assert DynamixelDriver.detect(timeout=MISS) == []
    monkeypatch.setattr(
        "serial.tools.list_ports.comports", lambda: [SimpleNamespace(device=sim.path)]
    )
    entries = DynamixelDriver.detect(timeout=FOUND)
    assert [e["link"] for e in entries] == [f"serial:{sim.path}?baud=1000000"]


@pytest.mark.parametrize("timeout", [0, -1.0, math.nan, math.inf])
def test_a_timeout_must_be_positive(sim: SimDynamixelChain, timeout: float) -> None:
    with pytest.raises(ValueError, match="timeout"):
        DynamixelDriver.detect([f"serial:{sim.path}"], timeout=timeout)
    assert sim.stats["packets"] == 0


@pytest.mark.parametrize(
    "bad",
    [
        "udp:1.2.3.4:5",
        "can:can0",
        "ttyUSB0",
        "serial:/dev/ttyUSB0?baud=12345",
        "serial:/dev/ttyUSB0?parity=odd",
        {"interface": "socketcan", "channel": "can0"},
        7,
    ],
)
def test_a_link_that_is_not_serial_is_refused_before_any_port_opens(
    sim: SimDynamixelChain, bad: Any
) -> None:
    with pytest.raises(ValueError, match="link") as raised:
        DynamixelDriver.detect([f"serial:{sim.path}?baud=1000000", bad], timeout=FOUND)
    assert repr(bad) in str(raised.value)
    # had the first link been pinged, detect would have waited FOUND s for its replies
    assert sim.stats["packets"] == 0
