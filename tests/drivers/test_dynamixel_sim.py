"""dynamixel-sdk itself as the client of the simulated chain on a pseudo-terminal."""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from typing import Any

import pytest
from dxl_sdk_client import sdk_client

from temoto.clock import ManualClock
from temoto.drivers.dynamixel import _sdk
from temoto.drivers.dynamixel import control_table as ct
from temoto.drivers.dynamixel.sim import SimDynamixelChain

dxl: Any = pytest.importorskip("dynamixel_sdk")

IDS = (1, 2, 3)


@pytest.fixture
def clock() -> ManualClock:
    return ManualClock()


@pytest.fixture
def sim(clock: ManualClock) -> Iterator[SimDynamixelChain]:
    with SimDynamixelChain({1: "XM430-W350", 2: "XM430-W350", 3: "XL430-W250"}, clock=clock) as s:
        yield s


@pytest.fixture
def sdk(sim: SimDynamixelChain) -> Iterator[tuple[Any, Any]]:
    port, ph = sdk_client(sim.path, sim)
    yield port, ph
    port.closePort()


def test_pty_exists_before_start_and_is_released_on_close() -> None:
    sim = SimDynamixelChain({1: "XM430-W350"})
    assert sim.path.startswith("/dev/")
    sim.close()
    sim.close()
    with pytest.raises(RuntimeError, match="closed"):
        sim.start()


def test_ping_and_model_numbers(sdk: tuple[Any, Any]) -> None:
    port, ph = sdk
    assert ph.ping(port, 1) == (1020, dxl.COMM_SUCCESS, 0)
    assert ph.ping(port, 3)[0] == 1060
    assert ph.ping(port, 9)[1] == dxl.COMM_RX_TIMEOUT
    found, result = ph.broadcastPing(port)
    assert result == dxl.COMM_SUCCESS
    assert sorted(found) == list(IDS)


def test_read_write_and_motion_on_the_clock(
    sdk: tuple[Any, Any], clock: ManualClock, sim: SimDynamixelChain
) -> None:
    port, ph = sdk
    assert ph.read1ByteTxRx(port, 1, 11) == (3, dxl.COMM_SUCCESS, 0)
    assert ph.write1ByteTxRx(port, 1, 64, 1) == (dxl.COMM_SUCCESS, 0)
    assert ph.write4ByteTxRx(port, 1, 116, 3072) == (dxl.COMM_SUCCESS, 0)
    assert ph.read4ByteTxRx(port, 1, 132)[0] == 2048  # no time has passed
    clock.advance(0.05)
    moving = ph.read4ByteTxRx(port, 1, 132)[0]
    assert 2048 < moving < 3072
    clock.advance(0.15)  # the controller has caught up with its profile (~80 ms)
    assert ph.read4ByteTxRx(port, 1, 132)[0] < 3072
    speed = ph.read4ByteTxRx(port, 1, 128)[0]
    assert speed == 200  # at the Velocity Limit
    current = ph.read2ByteTxRx(port, 1, 126)[0]
    assert current > 0  # effort while tracking
    clock.advance(2.0)
    assert ph.read4ByteTxRx(port, 1, 132)[0] == 3072
    assert sim.read_register(1, 132) == 3072


def test_write_errors_like_a_servo(sdk: tuple[Any, Any]) -> None:
    port, ph = sdk
    access = 7
    assert ph.write2ByteTxRx(port, 1, 132, 5) == (dxl.COMM_SUCCESS, access)  # read-only
    assert ph.write1ByteTxRx(port, 1, 64, 1)[1] == 0
    assert ph.write1ByteTxRx(port, 1, 11, 1)[1] == access  # EEPROM while torque is on
    assert ph.write4ByteTxRx(port, 1, 116, 5000)[1] == 6  # beyond Max Position Limit
    assert ph.write1ByteTxRx(port, 3, 11, 0)[1] == 4  # XL430 has no current mode
    assert ph.factoryReset(port, 1, 0x02) == (dxl.COMM_SUCCESS, 0)  # and a reboot:
    assert ph.read1ByteTxRx(port, 1, 64)[0] == 0  # torque off


def test_sync_read_and_sync_write(sdk: tuple[Any, Any], clock: ManualClock) -> None:
    port, ph = sdk
    torque = dxl.GroupSyncWrite(port, ph, 64, 1)
    goal = dxl.GroupSyncWrite(port, ph, 116, 4)
    for i, target in zip(IDS, (1000, 2500, 4000), strict=True):
        torque.addParam(i, [1])
        goal.addParam(i, list(target.to_bytes(4, "little")))
    assert torque.txPacket() == dxl.COMM_SUCCESS
    assert goal.txPacket() == dxl.COMM_SUCCESS
    assert ph.ping(port, 1)[1] == dxl.COMM_SUCCESS  # a round trip: the writes were handled
    clock.advance(3.0)
    read = dxl.GroupSyncRead(port, ph, 126, 10)
    for i in IDS:
        read.addParam(i)
    assert read.txRxPacket() == dxl.COMM_SUCCESS
    got = [read.getData(i, 132, 4) for i in IDS]
    assert got == [1000, 2500, 4000]
    bulk = dxl.GroupBulkRead(port, ph)
    assert bulk.addParam(1, 146, 1)
    assert bulk.addParam(2, 144, 2)
    assert bulk.txRxPacket() == dxl.COMM_SUCCESS
    assert bulk.getData(1, 146, 1) == 30
    assert bulk.getData(2, 144, 2) == 120


def test_velocity_and_current_modes(sdk: tuple[Any, Any], clock: ManualClock) -> None:
    port, ph = sdk
    assert ph.write1ByteTxRx(port, 1, 11, 1)[1] == 0
    assert ph.write1ByteTxRx(port, 2, 11, 0)[1] == 0
    for i in (1, 2):
        assert ph.write1ByteTxRx(port, i, 64, 1)[1] == 0
    assert ph.write4ByteTxRx(port, 1, 104, 100)[1] == 0
    assert ph.write2ByteTxRx(port, 2, 102, (-300) & 0xFFFF)[1] == 0
    clock.advance(0.5)
    assert 95 <= ph.read4ByteTxRx(port, 1, 128)[0] <= 100
    velocity = ph.read4ByteTxRx(port, 2, 128)[0]
    assert velocity >= 1 << 31  # negative
    current = ph.read2ByteTxRx(port, 2, 126)[0] - (1 << 16)
    assert current == -300


def test_faults_seen_by_the_sdk(sdk: tuple[Any, Any], sim: SimDynamixelChain) -> None:
    port, ph = sdk
    sim.inject("silence", device=2)
    assert ph.ping(port, 2)[1] == dxl.COMM_RX_TIMEOUT
    assert ph.ping(port, 1)[1] == dxl.COMM_SUCCESS
    sim.clear("silence")
    sim.inject("corrupt")
    assert ph.ping(port, 1)[1] == dxl.COMM_RX_CORRUPT
    sim.clear()
    sim.inject("link_loss")
    assert ph.ping(port, 1)[1] == dxl.COMM_RX_TIMEOUT
    sim.clear("link_loss")
    assert ph.write1ByteTxRx(port, 1, 64, 1) == (dxl.COMM_SUCCESS, 0)
    sim.inject("hardware_error", kind="overheat", device=1)
    _model, result, error = ph.ping(port, 1)
    assert result == dxl.COMM_SUCCESS
    assert error & 0x80
    assert ph.read1ByteTxRx(port, 1, 70)[0] == 0x04
    assert ph.read1ByteTxRx(port, 1, 64)[0] == 0  # torque went off
    assert ph.read1ByteTxRx(port, 1, 146)[0] > 80
    assert ph.write1ByteTxRx(port, 1, 64, 1)[0] == dxl.COMM_SUCCESS
    assert ph.read1ByteTxRx(port, 1, 64)[0] == 0  # stays off with the error
    sim.clear("hardware_error")
    assert ph.read1ByteTxRx(port, 1, 70)[0] == 0x04  # until a reboot
    assert ph.reboot(port, 1)[0] == dxl.COMM_SUCCESS
    assert ph.ping(port, 1) == (1020, dxl.COMM_SUCCESS, 0)
    for kind, bit in (("overload", 0x20), ("voltage", 0x01)):
        sim.inject("hardware_error", kind=kind, device=2)
        assert ph.read1ByteTxRx(port, 2, 70)[0] == bit
        assert ph.reboot(port, 2)[0] == dxl.COMM_SUCCESS
        assert ph.read1ByteTxRx(port, 2, 70)[0] == bit  # still injected: back after reboot
        sim.clear("hardware_error")
        ph.reboot(port, 2)
        assert ph.read1ByteTxRx(port, 2, 70)[0] == 0
    with pytest.raises(ValueError, match="kind"):
        sim.inject("hardware_error", kind="meltdown")
    with pytest.raises(ValueError, match="cannot inject"):
        sim.inject("no_heartbeat")


def test_position_mode_goal_is_reached_in_radians(sdk: tuple[Any, Any], clock: ManualClock) -> None:
    port, ph = sdk
    ph.write1ByteTxRx(port, 1, 64, 1)
    ph.write4ByteTxRx(port, 1, 116, 2048 + 1024)
    clock.advance(1.5)
    ticks = ph.read4ByteTxRx(port, 1, 132)[0]
    assert math.isclose((ticks - 2048) * ct.RAD_PER_TICK, math.pi / 2)


def test_a_starved_simulator_is_not_a_timeout(
    sdk: tuple[Any, Any], sim: SimDynamixelChain, monkeypatch: pytest.MonkeyPatch
) -> None:
    # As on a loaded machine: the serving thread gets no CPU for far longer than the SDK's
    # 34 ms. The reply is late, not missing; a servo that is really silent still times out.
    serve = sim._serve_data

    def starved(data: bytes) -> None:
        time.sleep(0.3)
        serve(data)

    monkeypatch.setattr(sim, "_serve_data", starved)
    port, ph = sdk
    assert ph.ping(port, 1) == (1020, dxl.COMM_SUCCESS, 0)
    assert ph.read1ByteTxRx(port, 2, 11) == (3, dxl.COMM_SUCCESS, 0)
    assert ph.ping(port, 9)[1] == dxl.COMM_RX_TIMEOUT
    assert ph.ping(port, 1)[1] == dxl.COMM_SUCCESS  # the missing reply left nothing behind


def test_our_sdk_port_waits_for_a_reply_without_spinning(sim: SimDynamixelChain) -> None:
    # dynamixel-sdk reads the port without blocking in a loop until its timeout: a missing
    # servo kept a core busy (thousands of reads in 0.3 s) and starved the simulator thread.
    port = _sdk.SdkPort(sim.path, 1_000_000, reply_timeout=0.3)
    port.open()
    try:
        reads = 0
        read = port._port.ser.read

        def counted(size: int) -> bytes:
            nonlocal reads
            reads += 1
            return bytes(read(size))

        port._port.ser.read = counted
        assert port.ping(9)[1] == dxl.COMM_RX_TIMEOUT  # no such servo: the whole 0.3 s
        # two reads per wait of at most _IDLE_WAIT_MS (the timeout is checked after each)
        assert reads <= 2 * math.ceil(300 / _sdk._IDLE_WAIT_MS) + 2, reads
        reads = 0
        assert port.ping(1) == (1020, dxl.COMM_SUCCESS, 0)
        assert reads <= 10, reads
    finally:
        port.close()
