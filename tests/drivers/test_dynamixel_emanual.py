"""The simulated chain against the ROBOTIS e-Manual, with dynamixel-sdk as the client.

Every supported model's control table is read register by register at the e-Manual's address
and size and compared with the initial values its e-Manual page lists (the expectations below
are typed from those pages, not taken from ``control_table``); writes are checked against the
Range column, the access rules (read-only, EEPROM and Indirect Address locked while torque is
on) and the limit registers; and the instructions the Protocol 2.0 page describes -- ID and baud
changes, Status Return Level, REG_WRITE/ACTION, REBOOT, FACTORY_RESET, CLEAR, Indirect Data --
do what it says.
"""

from __future__ import annotations

import select
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import pytest
from dxl_polled import follow

from temoto.clock import ManualClock
from temoto.drivers import ControlMode, JointCommand
from temoto.drivers.dynamixel import control_table as ct
from temoto.drivers.dynamixel import protocol as p
from temoto.drivers.dynamixel.driver import DynamixelDriver, ServoConfig
from temoto.drivers.dynamixel.sim import SimDynamixelChain

dxl: Any = pytest.importorskip("dynamixel_sdk")

OK = 0
RESULT_FAIL, INSTRUCTION, DATA_RANGE, DATA_LENGTH, DATA_LIMIT, ACCESS = 1, 2, 4, 5, 6, 7


@dataclass(frozen=True)
class Spec:
    """One model's rows of the e-Manual that differ between models."""

    number: int
    velocity_limit: int
    current_limit: int | None  # None: Present Load, no Current Limit / Goal Current
    voltage: tuple[int, int, int, int] = (160, 95, 95, 160)  # max, min initial; range
    temperature: int = 80
    gains: tuple[int, int, int, int, int] = (1920, 100, 0, 0, 800)  # VI VP PD PI PP
    volts: int = 120  # Present Input Voltage of the simulated supply (the recommended one)
    led: bool = True
    ports: bool = False  # External Port Mode/Data (X540 M/H/D)
    xl330: bool = False  # 20 indirect pairs, PWM Slope, 0..2047 velocity, baud 0..6, ...


def _load(number: int, velocity: int, gains: tuple[int, ...], xl: bool) -> Spec:
    """XL430 / 2XL430 (``xl``) and XC430: Present Load, their voltage and temperature."""
    voltage = (140, 60, 60, 140) if xl else (160, 60, 60, 160)
    return Spec(number, velocity, None, voltage, 72 if xl else 80, _g(gains))


def _xl330(number: int, velocity: int, gains: tuple[int, ...]) -> Spec:
    return Spec(number, velocity, 1750, (70, 35, 31, 70), 70, _g(gains), volts=50, xl330=True)


def _v(number: int, velocity: int, current: int, ports: bool = False) -> Spec:
    """The 24 V XH models."""
    return Spec(number, velocity, current, (300, 110, 110, 300), volts=240, ports=ports)


def _g(gains: tuple[int, ...]) -> tuple[int, int, int, int, int]:
    vi, vp, pd, pi, pp = gains
    return vi, vp, pd, pi, pp


_H = _g((1920, 100, 0, 0, 900))  # the XH430-W, XD430 and XW430 Position P Gain

E_MANUAL: dict[str, Spec] = {
    "XL430-W250": _load(1060, 265, (1000, 100, 4000, 0, 640), xl=True),
    "2XL430-W250": _load(1090, 250, (1800, 100, 2000, 0, 640), xl=True),
    "XC430-W150": _load(1070, 460, (1920, 100, 0, 0, 460), xl=False),
    "XC430-W240": _load(1080, 306, (1920, 100, 0, 0, 700), xl=False),
    "XL330-M077": _xl330(1190, 1620, (400, 40, 0, 400, 400)),
    "XL330-M288": _xl330(1200, 445, (1600, 180, 0, 0, 400)),
    "XM430-W210": Spec(1030, 330, 1193),
    "XM430-W350": Spec(1020, 200, 1193),
    "XH430-W210": Spec(1010, 210, 648, gains=_H),
    "XH430-W350": Spec(1000, 130, 648, gains=_H),
    "XH430-V210": _v(1050, 380, 689),
    "XH430-V350": _v(1040, 285, 689),
    "XD430-T210": Spec(1011, 210, 648, gains=_H),
    "XD430-T350": Spec(1001, 130, 648, gains=_H),
    "XM540-W150": Spec(1130, 230, 2047, ports=True),
    "XM540-W270": Spec(1120, 128, 2047, ports=True),
    "XH540-W150": Spec(1110, 300, 2047, ports=True),
    "XH540-W270": Spec(1100, 167, 2047, ports=True),
    "XH540-V150": _v(1150, 230, 2047, ports=True),
    "XH540-V270": _v(1140, 128, 2047, ports=True),
    "XD540-T150": Spec(1111, 300, 2047, ports=True),
    "XD540-T270": Spec(1101, 167, 2047, ports=True),
    "XW430-T200": Spec(1280, 235, 2047, gains=_H, led=False),
    "XW430-T333": Spec(1270, 139, 2047, gains=_H, led=False),
    "XW540-T140": Spec(1180, 304, 2047, led=False),
    "XW540-T260": Spec(1170, 167, 2047, led=False),
}
MODELS = sorted(E_MANUAL)
IDS = {name: i + 1 for i, name in enumerate(MODELS)}


def expected_rows(name: str) -> list[tuple[str, int, int, int]]:
    """(name, address, size, initial value) for the rows with an initial value."""
    spec = E_MANUAL[name]
    vmax, vmin, _, _ = spec.voltage
    vi, vp, pd, pi, pp = spec.gains
    rows = [
        ("Model Number", 0, 2, spec.number),
        ("ID", 7, 1, IDS[name]),
        ("Baud Rate", 8, 1, 1),
        ("Return Delay Time", 9, 1, 250),
        ("Drive Mode", 10, 1, 0),
        ("Operating Mode", 11, 1, 3),
        ("Secondary ID", 12, 1, 255),
        ("Protocol Type", 13, 1, 2),
        ("Homing Offset", 20, 4, 0),
        ("Moving Threshold", 24, 4, 10),
        ("Temperature Limit", 31, 1, spec.temperature),
        ("Max Voltage Limit", 32, 2, vmax),
        ("Min Voltage Limit", 34, 2, vmin),
        ("PWM Limit", 36, 2, 885),
        ("Velocity Limit", 44, 4, spec.velocity_limit),
        ("Max Position Limit", 48, 4, 4095),
        ("Min Position Limit", 52, 4, 0),
        ("Startup Configuration", 60, 1, 0),
        ("Shutdown", 63, 1, 53 if spec.xl330 else 52),
        ("Torque Enable", 64, 1, 0),
        ("Status Return Level", 68, 1, 2),
        ("Registered Instruction", 69, 1, 0),
        ("Hardware Error Status", 70, 1, 0),
        ("Velocity I Gain", 76, 2, vi),
        ("Velocity P Gain", 78, 2, vp),
        ("Position D Gain", 80, 2, pd),
        ("Position I Gain", 82, 2, pi),
        ("Position P Gain", 84, 2, pp),
        ("Feedforward 2nd Gain", 88, 2, 0),
        ("Feedforward 1st Gain", 90, 2, 0),
        ("Bus Watchdog", 98, 1, 0),
        ("Profile Acceleration", 108, 4, 0),
        ("Profile Velocity", 112, 4, 0),
        ("Moving", 122, 1, 0),
        ("Moving Status", 123, 1, 0),
        ("Present Input Voltage", 144, 2, spec.volts),
        ("Backup Ready", 147, 1, 0),
    ]
    if spec.current_limit is not None:
        rows.append(("Current Limit", 38, 2, spec.current_limit))
    if spec.led:
        rows.append(("LED", 65, 1, 0))
    if spec.ports:
        rows += [(f"External Port Mode {n}", 55 + n, 1, 3) for n in (1, 2, 3)]
    if spec.xl330:
        rows.append(("PWM Slope", 62, 1, 140))
        # 20 pairs: Indirect Address n at 168 + 2(n-1) points at Indirect Data n, 208 + n-1.
        rows += [(f"Indirect Address {n}", 166 + 2 * n, 2, 207 + n) for n in range(1, 21)]
        rows += [(f"Indirect Data {n}", 207 + n, 1, 0) for n in range(1, 21)]
    else:
        rows += [(f"Indirect Address {n}", 166 + 2 * n, 2, 223 + n) for n in range(1, 29)]
        rows += [(f"Indirect Data {n}", 223 + n, 1, 0) for n in range(1, 29)]
        rows += [(f"Indirect Address {n}", 520 + 2 * n, 2, 605 + n) for n in range(29, 57)]
        rows += [(f"Indirect Data {n}", 605 + n, 1, 0) for n in range(29, 57)]
    return rows


# ---- fixtures ------------------------------------------------------------------------------

#: dynamixel-sdk waits 2 x its LATENCY_TIMER + 2 ms (real time) for a reply. A reply that must
#: come is waited for long: that costs nothing and rides out a loaded machine (the simulator
#: shares this process's GIL); one that must not come is waited for briefly
#: (:func:`silence_expected`), which cannot mistake a late reply for none, as there is none.
PATIENT = 1000
BRIEF = 20


@contextmanager
def silence_expected() -> Iterator[None]:
    """Within: the SDK waits only briefly for replies (none is expected)."""
    saved = dxl.port_handler.LATENCY_TIMER
    dxl.port_handler.LATENCY_TIMER = BRIEF
    try:
        yield
    finally:
        dxl.port_handler.LATENCY_TIMER = saved


@pytest.fixture
def clock() -> ManualClock:
    return ManualClock()


def _open(sim: SimDynamixelChain, baud: int = 1_000_000) -> Any:
    port = dxl.PortHandler(sim.path)
    assert port.openPort()
    assert port.setBaudRate(baud)
    return port


@pytest.fixture
def every_model(
    clock: ManualClock, monkeypatch: pytest.MonkeyPatch
) -> Iterator[tuple[SimDynamixelChain, Any, Any]]:
    """All supported models on one chain (ids in name order), and an SDK port on it."""
    monkeypatch.setattr(dxl.port_handler, "LATENCY_TIMER", PATIENT)
    with SimDynamixelChain({i: m for m, i in IDS.items()}, clock=clock) as sim:
        port = _open(sim)
        yield sim, port, dxl.PacketHandler(2.0)
        port.closePort()


@pytest.fixture
def one(
    clock: ManualClock, monkeypatch: pytest.MonkeyPatch
) -> Iterator[tuple[SimDynamixelChain, Any, Any]]:
    """An XM430-W350 (id 1) and an XL330-M288 (id 2), and an SDK port on them."""
    monkeypatch.setattr(dxl.port_handler, "LATENCY_TIMER", PATIENT)
    with SimDynamixelChain({1: "XM430-W350", 2: "XL330-M288"}, clock=clock) as sim:
        port = _open(sim)
        yield sim, port, dxl.PacketHandler(2.0)
        port.closePort()


def raw(port: Any, packet: bytes, timeout: float = 2.0) -> p.Packet | None:
    """Send one instruction packet as bytes; the status packet that answers it, if any."""
    port.ser.reset_input_buffer()
    port.ser.write(packet)
    reader = p.PacketReader()
    deadline = time.monotonic() + timeout
    while (left := deadline - time.monotonic()) > 0:
        ready, _, _ = select.select([port.ser.fileno()], [], [], left)
        if not ready:
            break
        for item in reader.feed(port.ser.read(port.ser.in_waiting or 1)):
            if isinstance(item, p.Packet) and item.is_status:
                return item
    return None


def read(ph: Any, port: Any, dxl_id: int, address: int, size: int) -> tuple[int, int, int]:
    """(value, comm result, error) of a read of ``size`` bytes (unsigned)."""
    data, result, error = ph.readTxRx(port, dxl_id, address, size)
    return int.from_bytes(bytes(data), "little"), result, error


def write(ph: Any, port: Any, dxl_id: int, address: int, size: int, value: int) -> int:
    """The error number a servo answers a write of ``value`` (``size`` bytes) with."""
    data = list((value & ((1 << (8 * size)) - 1)).to_bytes(size, "little"))
    result, error = ph.writeTxRx(port, dxl_id, address, size, data)
    assert result == dxl.COMM_SUCCESS
    return int(error) & 0x7F


# ---- the control table of every model ------------------------------------------------------


def test_every_models_table_reads_as_the_e_manual_lists_it(
    every_model: tuple[SimDynamixelChain, Any, Any],
) -> None:
    _, port, ph = every_model
    assert sorted(ct.MODELS) == MODELS  # no model left out of this test, none unknown
    found, result = ph.broadcastPing(port)
    assert result == dxl.COMM_SUCCESS
    assert {i: found[i][0] for i in found} == {IDS[m]: E_MANUAL[m].number for m in MODELS}
    wrong: list[str] = []
    for name in MODELS:
        dxl_id = IDS[name]
        for row, address, size, initial in expected_rows(name):
            value, result, error = read(ph, port, dxl_id, address, size)
            if (value, result, error) != (initial, dxl.COMM_SUCCESS, 0):
                wrong.append(f"{name} {row}({address}, {size}): {value} {result} {error}")
        # the whole table in one read; one byte past its end is an Access Error, with no data
        end = 228 if E_MANUAL[name].xl330 else 662
        data, result, error = ph.readTxRx(port, dxl_id, 0, end)
        assert (len(data), result, error) == (end, dxl.COMM_SUCCESS, 0), name
        answer = raw(port, p.read_packet(dxl_id, end - 1, 2))
        assert answer is not None
        assert (answer.error_number, answer.params) == (ACCESS, b""), name
    assert not wrong, "\n".join(wrong)


def test_registers_a_model_lacks_refuse_writes(
    every_model: tuple[SimDynamixelChain, Any, Any],
) -> None:
    _, port, ph = every_model
    for name in MODELS:
        dxl_id, spec = IDS[name], E_MANUAL[name]
        if spec.current_limit is None:  # Present Load models: no Current Limit, Goal Current
            assert write(ph, port, dxl_id, 38, 2, 100) == ACCESS, name
            assert write(ph, port, dxl_id, 102, 2, 10) == ACCESS, name
            assert write(ph, port, dxl_id, 11, 1, 0) == DATA_RANGE, name  # no current mode
            assert write(ph, port, dxl_id, 11, 1, 5) == DATA_RANGE, name
        else:
            assert write(ph, port, dxl_id, 11, 1, 0) == OK, name
            assert write(ph, port, dxl_id, 11, 1, 3) == OK, name
        if not spec.led:
            assert write(ph, port, dxl_id, 65, 1, 1) == ACCESS, name
        if not spec.ports:
            assert write(ph, port, dxl_id, 56, 1, 0) == ACCESS, name


@pytest.mark.parametrize("name", MODELS)
def test_write_ranges_of_the_e_manual(
    name: str, clock: ManualClock, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(dxl.port_handler, "LATENCY_TIMER", PATIENT)
    spec = E_MANUAL[name]
    _, _, vlow, vhigh = spec.voltage
    last_data = 227 if spec.xl330 else 661
    # (address, size, largest value accepted, smallest value accepted)
    ranges = [
        (8, 1, 6 if spec.xl330 else 7, 0),  # Baud Rate
        (9, 1, 254, 0),  # Return Delay Time
        (10, 1, 15 if spec.ports else 13, 0),  # Drive Mode: bits 0, (1 dual: X540), 2, 3
        (24, 4, 1023, 0),  # Moving Threshold
        (31, 1, 100, 0),  # Temperature Limit
        (32, 2, vhigh, vlow),  # Max Voltage Limit
        (34, 2, vhigh, vlow),  # Min Voltage Limit
        (36, 2, 885, 0),  # PWM Limit
        (44, 4, 2047 if spec.xl330 else 1023, 0),  # Velocity Limit
        (48, 4, 4095, 0),  # Max Position Limit
        (60, 1, 3, 0),  # Startup Configuration
        (64, 1, 1, 0),  # Torque Enable
        (68, 1, 2, 0),  # Status Return Level
        (76, 2, 16383, 0),  # Velocity I Gain
        (84, 2, 16383, 0),  # Position P Gain
        (90, 2, 16383, 0),  # Feedforward 1st Gain
        (98, 1, 127, 0),  # Bus Watchdog
        (108, 4, 32767, 0),  # Profile Acceleration
        (112, 4, 32767, 0),  # Profile Velocity
        (168, 2, last_data, 64),  # Indirect Address 1
    ]
    if spec.current_limit is not None:
        ranges.append((38, 2, spec.current_limit, 0))
    if spec.xl330:
        ranges.append((62, 1, 255, 1))  # PWM Slope
    with SimDynamixelChain({1: name}, clock=clock) as sim:
        port = _open(sim)
        ph = dxl.PacketHandler(2.0)
        for address, size, high, low in ranges:
            initial = read(ph, port, 1, address, size)[0]
            assert write(ph, port, 1, address, size, high) == OK, (name, address, high)
            assert write(ph, port, 1, address, size, high + 1) == DATA_RANGE, (name, address)
            if low > 0:
                assert write(ph, port, 1, address, size, low - 1) == DATA_RANGE, (name, address)
            if address != 68:  # Status Return Level 0 would silence the rest of the test
                assert write(ph, port, 1, address, size, low) == OK, (name, address, low)
                assert read(ph, port, 1, address, size)[0] == low
            assert write(ph, port, 1, address, size, initial) == OK
        # goals beyond their limit registers: a Data Limit Error
        assert write(ph, port, 1, 44, 4, 100) == OK  # Velocity Limit
        assert write(ph, port, 1, 104, 4, 101) == DATA_LIMIT  # Goal Velocity
        assert write(ph, port, 1, 104, 4, -100) == OK
        assert write(ph, port, 1, 36, 2, 500) == OK  # PWM Limit
        assert write(ph, port, 1, 100, 2, -501) == DATA_LIMIT  # Goal PWM
        assert write(ph, port, 1, 100, 2, 500) == OK
        if spec.current_limit is not None:
            assert write(ph, port, 1, 38, 2, 300) == OK
            assert write(ph, port, 1, 102, 2, 301) == DATA_LIMIT  # Goal Current
        assert write(ph, port, 1, 52, 4, 1000) == OK  # Min Position Limit
        assert write(ph, port, 1, 116, 4, 999) == DATA_LIMIT  # Goal Position, position mode
        assert write(ph, port, 1, 116, 4, 2000) == OK
        # read-only registers: an Access Error, the value unchanged
        for address, size in ((0, 2), (6, 1), (69, 1), (70, 1), (120, 2), (132, 4), (146, 1)):
            before = read(ph, port, 1, address, size)[0]
            assert write(ph, port, 1, address, size, 1) == ACCESS, (name, address)
            assert read(ph, port, 1, address, size)[0] == before
        port.closePort()


# ---- access, length -------------------------------------------------------------------------


def test_eeprom_and_indirect_addresses_are_locked_while_torque_is_on(
    one: tuple[SimDynamixelChain, Any, Any],
) -> None:
    _, port, ph = one
    assert write(ph, port, 1, 64, 1, 1) == OK
    for address, size, value in ((7, 1, 5), (11, 1, 1), (44, 4, 100), (63, 1, 0), (168, 2, 132)):
        assert write(ph, port, 1, address, size, value) == ACCESS, address
    assert write(ph, port, 1, 84, 2, 900) == OK  # RAM: gains change with torque on
    assert write(ph, port, 1, 64, 1, 0) == OK
    assert write(ph, port, 1, 44, 4, 100) == OK
    assert write(ph, port, 1, 168, 2, 132) == OK


def test_data_length_and_unknown_instructions(one: tuple[SimDynamixelChain, Any, Any]) -> None:
    _, port, ph = one
    short_write = raw(port, p.build_packet(1, p.Instruction.WRITE, b"\x41\x00"))
    assert short_write is not None
    assert short_write.error_number == DATA_LENGTH
    short_read = raw(port, p.build_packet(1, p.Instruction.READ, b"\x84\x00\x04"))
    assert short_read is not None
    assert short_read.error_number == DATA_LENGTH
    assert write(ph, port, 1, 116, 2, 100) == DATA_LENGTH  # 2 bytes of Goal Position
    assert write(ph, port, 1, 118, 2, 0) == DATA_LENGTH  # its last 2
    assert write(ph, port, 1, 132, 2, 0) == ACCESS  # a read-only register: Access goes first
    assert write(ph, port, 1, 168, 2, 116) == OK  # Indirect Data 1 → Goal Position's 1st byte
    assert write(ph, port, 1, 224, 1, 0) == DATA_LENGTH
    assert read(ph, port, 1, 116, 4)[0] == 2048
    reset = raw(port, p.build_packet(1, p.Instruction.FACTORY_RESET, b"\x03"))
    assert reset is not None
    assert reset.error_number == DATA_RANGE
    backup = raw(port, p.build_packet(1, 0x20, b"\x01CTRL"))  # Control Table Backup
    assert backup is not None
    assert backup.error_number == INSTRUCTION


# ---- Indirect Address / Data -----------------------------------------------------------------


def test_indirect_data_reads_and_writes_the_register_it_points_at(
    one: tuple[SimDynamixelChain, Any, Any], clock: ManualClock
) -> None:
    sim, port, ph = one
    for dxl_id, data_1 in ((1, 224), (2, 208)):  # XM430: data at 224; XL330: at 208
        for n in range(4):  # Indirect 1..4 → Present Position, 5..8 → Goal Position
            assert write(ph, port, dxl_id, 168 + 2 * n, 2, 132 + n) == OK
            assert write(ph, port, dxl_id, 176 + 2 * n, 2, 116 + n) == OK
        assert write(ph, port, dxl_id, 64, 1, 1) == OK
        assert write(ph, port, dxl_id, data_1 + 4, 4, 3000) == OK  # Goal Position, indirectly
        assert read(ph, port, dxl_id, 116, 4)[0] == 3000
        clock.advance(2.0)
        assert read(ph, port, dxl_id, data_1, 4)[0] == 3000  # Present Position, indirectly
        assert write(ph, port, dxl_id, data_1, 1, 7) == ACCESS  # it stands for a read-only one
        assert write(ph, port, dxl_id, data_1 + 4, 4, 5000) == DATA_LIMIT  # checks apply too
    # the second block (29..56) of the 430/540 models, through a sync read as the SDK does it
    assert write(ph, port, 1, 64, 1, 0) == OK
    for n in range(4):
        assert write(ph, port, 1, 578 + 2 * n, 2, 132 + n) == OK  # Indirect Address 29..32
    group = dxl.GroupSyncRead(port, ph, 634, 4)  # Indirect Data 29..32
    assert group.addParam(1)
    assert group.txRxPacket() == dxl.COMM_SUCCESS
    assert group.getData(1, 634, 4) == sim.read_register(1, 132) == 3000


def test_fast_sync_and_fast_bulk_read(
    every_model: tuple[SimDynamixelChain, Any, Any], clock: ManualClock
) -> None:
    sim, port, ph = every_model
    ids = [IDS[m] for m in ("XM430-W350", "XL330-M288", "XH540-V270", "XC430-W150")]
    for dxl_id, goal in zip(ids, (1000, 3000, 2500, 100), strict=True):
        assert write(ph, port, dxl_id, 64, 1, 1) == OK
        assert write(ph, port, dxl_id, 116, 4, goal) == OK
    clock.advance(5.0)
    group = dxl.GroupSyncRead(port, ph, 132, 4)
    for dxl_id in ids:
        assert group.addParam(dxl_id)
    assert group.fastSyncRead() == dxl.COMM_SUCCESS  # one packet, the CRC checked at its end
    assert [group.getData(i, 132, 4) for i in ids] == [1000, 3000, 2500, 100]
    bulk = dxl.GroupBulkRead(port, ph)
    assert bulk.addParam(ids[0], 132, 4)
    assert bulk.addParam(ids[1], 146, 1)  # Present Temperature
    assert bulk.addParam(ids[2], 144, 2)  # Present Input Voltage: 24 V
    assert bulk.fastBulkRead() == dxl.COMM_SUCCESS
    got = (bulk.getData(ids[0], 132, 4), bulk.getData(ids[1], 146, 1), bulk.getData(ids[2], 144, 2))
    assert got == (1000, 30, 240)
    assert group.addParam(
        IDS["2XL430-W250"]
    )  # "2XL/2XC Not Supported": the packet stays unfinished
    with silence_expected():
        assert group.fastSyncRead() != dxl.COMM_SUCCESS
    assert sim.read_register(ids[0], 132) == 1000


# ---- ID, baud rate, Status Return Level ------------------------------------------------------


def test_writing_the_id_changes_the_id_the_servo_answers_to(
    one: tuple[SimDynamixelChain, Any, Any],
) -> None:
    sim, port, ph = one
    assert ph.write1ByteTxRx(port, 1, 7, 9) == (dxl.COMM_SUCCESS, 0)  # answered by id 1
    assert ph.ping(port, 9) == (1020, dxl.COMM_SUCCESS, 0)
    with silence_expected():
        assert ph.ping(port, 1)[1] == dxl.COMM_RX_TIMEOUT
    assert sorted(ph.broadcastPing(port)[0]) == [2, 9]
    assert sim.ids == (2, 9)
    assert write(ph, port, 9, 7, 1, 253) == DATA_RANGE


def test_a_baud_rate_change_takes_effect(
    clock: ManualClock, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(dxl.port_handler, "LATENCY_TIMER", PATIENT)
    with SimDynamixelChain({1: "XM430-W350", 2: "XL330-M077"}, clock=clock, baud=57600) as sim:
        port = _open(sim, 57600)
        ph = dxl.PacketHandler(2.0)
        assert ph.write1ByteTxRx(port, 1, 8, 3) == (dxl.COMM_SUCCESS, 0)  # → 1 Mbps
        with silence_expected():
            assert ph.ping(port, 1)[1] == dxl.COMM_RX_TIMEOUT  # still at 57600 here
        assert ph.ping(port, 2)[1] == dxl.COMM_SUCCESS
        assert port.setBaudRate(1_000_000)
        assert ph.ping(port, 1)[1] == dxl.COMM_SUCCESS
        with silence_expected():
            assert ph.ping(port, 2)[1] == dxl.COMM_RX_TIMEOUT
        assert write(ph, port, 1, 8, 1, 7) == OK  # 4.5 Mbps: the XM430 has it
        port.closePort()
        port = _open(sim, 57600)
        assert write(ph, port, 2, 8, 1, 7) == DATA_RANGE  # the XL330 stops at 4 Mbps (6)
        port.closePort()


def test_status_return_level(one: tuple[SimDynamixelChain, Any, Any]) -> None:
    sim, port, ph = one
    assert ph.write1ByteTxRx(port, 1, 68, 1) == (dxl.COMM_SUCCESS, 0)  # level 2 answers it
    with silence_expected():
        assert ph.write1ByteTxRx(port, 1, 65, 1)[0] == dxl.COMM_RX_TIMEOUT  # no status for writes
    assert ph.read1ByteTxRx(port, 1, 65) == (1, dxl.COMM_SUCCESS, 0)  # done, and reads answer
    group = dxl.GroupSyncRead(port, ph, 65, 1)
    assert group.addParam(1)
    assert group.txRxPacket() == dxl.COMM_SUCCESS
    with silence_expected():
        assert ph.write1ByteTxRx(port, 1, 68, 0)[0] == dxl.COMM_RX_TIMEOUT
    with silence_expected():
        assert ph.read1ByteTxRx(port, 1, 65)[1] == dxl.COMM_RX_TIMEOUT  # level 0: no reads either
    assert ph.ping(port, 1) == (1020, dxl.COMM_SUCCESS, 0)  # but PING always
    assert sim.read_register(1, 68) == 0
    with silence_expected():
        assert ph.reboot(port, 1)[0] == dxl.COMM_RX_TIMEOUT  # not answered; RAM back to level 2
    assert ph.read1ByteTxRx(port, 1, 68) == (2, dxl.COMM_SUCCESS, 0)


def test_a_secondary_id_groups_servos_for_ram_writes_without_replies(
    one: tuple[SimDynamixelChain, Any, Any],
) -> None:
    sim, port, ph = one
    for dxl_id in (1, 2):
        assert write(ph, port, dxl_id, 12, 1, 2) == OK  # Secondary ID 2; servo 2's own id too
    assert ph.write1ByteTxRx(port, 2, 65, 1) == (dxl.COMM_SUCCESS, 0)  # servo 2 answers
    assert [sim.read_register(i, 65) for i in (1, 2)] == [1, 1]  # and servo 1 acted too
    assert write(ph, port, 1, 12, 1, 100) == OK
    assert write(ph, port, 2, 12, 1, 100) == OK
    with silence_expected():
        assert ph.write1ByteTxRx(port, 100, 65, 0)[0] == dxl.COMM_RX_TIMEOUT  # nobody answers
    assert [sim.read_register(i, 65) for i in (1, 2)] == [0, 0]  # both acted
    with silence_expected():
        assert ph.write1ByteTxRx(port, 100, 9, 0)[0] == dxl.COMM_RX_TIMEOUT
    assert [sim.read_register(i, 9) for i in (1, 2)] == [250, 250]  # no EEPROM through it
    assert write(ph, port, 1, 12, 1, 253) == OK  # 253..255: off
    with silence_expected():
        ph.write1ByteTxRx(port, 100, 65, 1)
    assert [sim.read_register(i, 65) for i in (1, 2)] == [0, 1]


# ---- REG_WRITE / ACTION, REBOOT, FACTORY_RESET, CLEAR ---------------------------------------


def test_reg_write_waits_for_action(
    one: tuple[SimDynamixelChain, Any, Any], clock: ManualClock
) -> None:
    sim, port, ph = one
    nothing = raw(port, p.build_packet(1, p.Instruction.ACTION))
    assert nothing is not None
    assert nothing.error_number == INSTRUCTION
    for dxl_id in (1, 2):
        assert write(ph, port, dxl_id, 64, 1, 1) == OK
        result, error = ph.regWriteTxRx(port, dxl_id, 116, 4, list((2600).to_bytes(4, "little")))
        assert (result, error) == (dxl.COMM_SUCCESS, 0)
        assert read(ph, port, dxl_id, 69, 1)[0] == 1  # Registered Instruction
        assert read(ph, port, dxl_id, 116, 4)[0] == 2048  # not yet
    assert ph.regWriteTxRx(port, 1, 116, 4, list((5000).to_bytes(4, "little")))[1] == DATA_LIMIT
    assert ph.action(port, p.BROADCAST_ID) == dxl.COMM_SUCCESS  # broadcast: no status
    assert ph.ping(port, 2)[1] == dxl.COMM_SUCCESS  # a round trip: the ACTION was handled
    for dxl_id in (1, 2):
        assert read(ph, port, dxl_id, 116, 4)[0] == 2600
        assert read(ph, port, dxl_id, 69, 1)[0] == 0
    clock.advance(2.0)
    assert sim.read_register(1, 132) == sim.read_register(2, 132) == 2600


def test_reboot_resets_the_ram_area_and_keeps_the_eeprom(
    one: tuple[SimDynamixelChain, Any, Any], clock: ManualClock
) -> None:
    sim, port, ph = one
    assert write(ph, port, 1, 11, 1, 4) == OK  # extended position (EEPROM)
    assert write(ph, port, 1, 9, 1, 0) == OK  # Return Delay Time (EEPROM)
    for address, size, value in ((64, 1, 1), (65, 1, 1), (84, 2, 1500), (112, 4, 100)):
        assert write(ph, port, 1, address, size, value) == OK
    assert write(ph, port, 1, 116, 4, 3 * 4096 + 100) == OK
    clock.advance(8.0)  # 10,340 ticks at Profile Velocity 100 (22.9 rev/min): 6.6 s
    assert sim.read_register(1, 132) == 3 * 4096 + 100
    assert ph.reboot(port, 1) == (dxl.COMM_SUCCESS, 0)
    after = {a: read(ph, port, 1, a, s)[0] for a, s in ((64, 1), (65, 1), (84, 2), (112, 4))}
    assert after == {64: 0, 65: 0, 84: 800, 112: 0}
    assert read(ph, port, 1, 132, 4)[0] == 100  # the multi-turn count is gone
    assert (read(ph, port, 1, 11, 1)[0], read(ph, port, 1, 9, 1)[0]) == (4, 0)
    assert write(ph, port, 1, 60, 1, 1) == OK  # Startup Configuration: torque on at boot
    assert ph.reboot(port, 1) == (dxl.COMM_SUCCESS, 0)
    assert read(ph, port, 1, 64, 1)[0] == 1
    assert sim.stats["reboots"] == 2


def test_factory_reset_options(one: tuple[SimDynamixelChain, Any, Any]) -> None:
    sim, port, ph = one
    assert write(ph, port, 1, 9, 1, 0) == OK
    assert write(ph, port, 1, 8, 1, 3) == OK  # not modelled on this chain: still heard
    assert write(ph, port, 1, 7, 1, 5) == OK
    assert ph.factoryReset(port, 5, 0x02) == (dxl.COMM_SUCCESS, 0)
    assert [read(ph, port, 5, a, 1)[0] for a in (7, 8, 9)] == [5, 3, 250]  # ID, baud kept
    assert ph.factoryReset(port, 5, 0x01) == (dxl.COMM_SUCCESS, 0)
    assert [read(ph, port, 5, a, 1)[0] for a in (7, 8)] == [5, 1]  # ID kept, 57600
    everyone = p.build_packet(p.BROADCAST_ID, p.Instruction.FACTORY_RESET, b"\xff")
    assert raw(port, everyone, timeout=0.2) is None
    assert sim.ids == (2, 5)  # the broadcast Reset All is ignored
    assert ph.factoryReset(port, 5, 0xFF) == (dxl.COMM_SUCCESS, 0)  # from id 5, then id 1
    assert sim.ids == (1, 2)
    assert ph.ping(port, 1) == (1020, dxl.COMM_SUCCESS, 0)
    assert sim.stats["factory_resets"] == 3


def test_clear_drops_the_multi_turn_count_when_standing_still(
    one: tuple[SimDynamixelChain, Any, Any], clock: ManualClock
) -> None:
    sim, port, ph = one
    assert write(ph, port, 1, 11, 1, 4) == OK
    assert write(ph, port, 1, 64, 1, 1) == OK
    assert write(ph, port, 1, 116, 4, -2 * 4096 + 300) == OK
    clock.advance(0.05)
    assert ph.clearMultiTurn(port, 1) == (dxl.COMM_SUCCESS, RESULT_FAIL)  # moving
    clock.advance(10.0)
    assert ph.clearMultiTurn(port, 1) == (dxl.COMM_SUCCESS, 0)
    assert read(ph, port, 1, 132, 4)[0] == 300
    assert read(ph, port, 1, 116, 4)[0] == 300  # the goal follows: it stays where it is
    clock.advance(1.0)
    assert sim.read_register(1, 132) == 300
    wrong = raw(port, p.build_packet(1, p.Instruction.CLEAR, b"\x01\x00\x00\x00\x00"))
    assert wrong is not None
    assert wrong.error_number == DATA_RANGE


def test_homing_offset_shifts_the_present_position(
    one: tuple[SimDynamixelChain, Any, Any], clock: ManualClock
) -> None:
    sim, port, ph = one
    assert write(ph, port, 1, 20, 4, 1000) == OK
    assert read(ph, port, 1, 132, 4)[0] == 3048  # actual 2048 + 1000
    assert write(ph, port, 1, 116, 4, 3048) == OK
    assert write(ph, port, 1, 64, 1, 1) == OK
    clock.advance(1.0)
    assert sim.read_register(1, 132) == 3048  # it did not move
    assert write(ph, port, 1, 64, 1, 0) == OK
    assert write(ph, port, 1, 20, 4, -5000) == OK
    assert sim.read_register(1, 132) == 2048 - 5000
    assert ph.reboot(port, 1) == (dxl.COMM_SUCCESS, 0)
    assert sim.read_register(1, 132) == 2048 - 5000  # the actual position is within a turn
    assert ph.factoryReset(port, 1, 0x02) == (dxl.COMM_SUCCESS, 0)
    assert sim.read_register(1, 132) == 2048


def test_torque_on_by_goal_update(one: tuple[SimDynamixelChain, Any, Any]) -> None:
    sim, port, ph = one
    assert write(ph, port, 1, 116, 4, 2100) == OK
    assert sim.read_register(1, 64) == 0  # Drive Mode 0: a goal leaves torque off
    assert write(ph, port, 1, 10, 1, 0x08) == OK
    assert write(ph, port, 1, 116, 4, 2200) == OK
    assert sim.read_register(1, 64) == 1
    assert write(ph, port, 1, 64, 1, 0) == OK
    assert write(ph, port, 1, 116, 4, 9000) == DATA_LIMIT  # a refused goal switches nothing
    assert sim.read_register(1, 64) == 0


def test_a_servo_switched_to_another_protocol_stops_answering_protocol_2(
    one: tuple[SimDynamixelChain, Any, Any],
) -> None:
    sim, port, ph = one
    assert write(ph, port, 1, 13, 1, 1) == OK  # Protocol 1.0 (not simulated)
    with silence_expected():
        assert ph.ping(port, 1)[1] == dxl.COMM_RX_TIMEOUT
    assert write(ph, port, 2, 13, 1, 1) == DATA_RANGE  # the XL330 range is 2..22
    assert sim.ids == (1, 2)


# ---- the driver knows every model and its units ---------------------------------------------


@pytest.mark.parametrize("name", MODELS)
def test_the_driver_accepts_every_model_in_its_units(name: str) -> None:
    spec = E_MANUAL[name]
    modes = ["position", "extended_position", "velocity"]
    if spec.current_limit is not None:
        modes += ["current", "current_based_position"]
    else:
        with pytest.raises(ValueError, match="no current mode"):
            ServoConfig(1, "j", name, mode="current")
    for mode in modes:
        ServoConfig(1, "j", name, mode=mode)
    servo = ServoConfig(1, "j", name)
    model = ct.MODELS[name]
    unit = {1750: 0.001, 689: 0.00134}.get(spec.current_limit or 0, 0.00269)
    if spec.current_limit is None:  # Present Load, 0.1 % of the stall torque
        assert servo.effort(1000) == pytest.approx(model.stall_torque)
    else:
        assert model.current_unit == unit
        assert servo.effort(1000) == pytest.approx(1000 * unit * model.torque_constant)
    assert servo.velocity(100) == pytest.approx(100 * 0.229 * 2 * 3.141592653589793 / 60)


@pytest.mark.parametrize(
    ("model", "mode", "command"),
    [
        ("XL330-M077", "current", 0.05),  # 1 mA units, 5 V
        ("XH430-V350", "current", 1.0),  # 1.34 mA units, 24 V
        ("XC430-W150", "velocity", 2.0),  # no current sensor: Present Load, no Current Limit
        ("2XL430-W250", "extended_position", 7.0),
        ("XW540-T140", "current_based_position", -1.0),
        ("XD540-T270", "position", 1.0),
    ],
)
def test_the_driver_brings_up_new_models_on_the_simulator(
    model: str, mode: str, command: float
) -> None:
    clock = ManualClock()
    servo = {"id": 4, "joint": "j", "model": model, "mode": mode}
    if mode == "extended_position":
        servo |= {"min_position": -20.0, "max_position": 20.0}
    config = {"link": "/dev/null", "poll_rate": 200, "servos": [servo]}
    kind = {"current": ControlMode.EFFORT, "velocity": ControlMode.VELOCITY}.get(
        mode, ControlMode.POSITION
    )
    sim, config = DynamixelDriver.simulate("x", config, clock=clock)
    with sim, DynamixelDriver.from_profile("x", config, clock=clock, where="x") as driver:
        driver.configure()
        driver.activate()
        driver.command([JointCommand("j", kind, command)])
        field = {ControlMode.EFFORT: "effort", ControlMode.VELOCITY: "velocity"}.get(
            kind, "position"
        )

        def reached() -> bool:
            got = getattr(driver.read_state().joints["j"], field)
            return bool(abs(got - command) < 0.02 * max(abs(command), 1.0))

        follow(driver, clock, reached, 30.0)
        status = driver.servo_status()[4]
        assert status.voltage == pytest.approx(ct.MODELS[model].nominal_voltage)
        driver.deactivate()
        assert sim.read_register(4, 64) == 0
