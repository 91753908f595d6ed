"""Protocol 2.0 encoding against the ROBOTIS e-Manual's example packets, and stuffing/CRC laws."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from temoto.drivers.dynamixel import control_table as ct
from temoto.drivers.dynamixel import protocol as p


def hexb(text: str) -> bytes:
    return bytes.fromhex(text)


# (what, built by us, the e-Manual's bytes)
EXAMPLES = [
    ("ping id 1", lambda: p.ping_packet(1), "FF FF FD 00 01 03 00 01 19 4E"),
    (
        "ping status: XM430-W210 (1030), firmware 0x26",
        lambda: p.status_packet(1, 0, bytes([0x06, 0x04, 0x26])),
        "FF FF FD 00 01 07 00 55 00 06 04 26 65 5D",
    ),
    (
        "read present position (132, 4 bytes) of id 1",
        lambda: p.read_packet(1, 132, 4),
        "FF FF FD 00 01 07 00 02 84 00 04 00 1D 15",
    ),
    (
        "read status: 166",
        lambda: p.status_packet(1, 0, p.to_le(166, 4)),
        "FF FF FD 00 01 08 00 55 00 A6 00 00 00 8C C0",
    ),
    (
        "write 512 to goal position (116) of id 1",
        lambda: p.write_packet(1, 116, p.to_le(512, 4)),
        "FF FF FD 00 01 09 00 03 74 00 00 02 00 00 CA 89",
    ),
    ("write status", lambda: p.status_packet(1), "FF FF FD 00 01 04 00 55 00 A1 0C"),
    (
        "sync read present position of ids 1, 2",
        lambda: p.sync_read_packet(132, 4, [1, 2]),
        "FF FF FD 00 FE 09 00 82 84 00 04 00 01 02 CE FA",
    ),
    (
        "sync write goal position 150 to id 1, 170 to id 2",
        lambda: p.sync_write_packet(116, 4, {1: p.to_le(150, 4), 2: p.to_le(170, 4)}),
        "FF FF FD 00 FE 11 00 83 74 00 04 00 01 96 00 00 00 02 AA 00 00 00 82 87",
    ),
    ("reboot id 1", lambda: p.reboot_packet(1), "FF FF FD 00 01 03 00 08 2F 4E"),
]


@pytest.mark.parametrize(("what", "build", "wire"), EXAMPLES, ids=[e[0] for e in EXAMPLES])
def test_e_manual_examples_encode_and_parse(what: str, build: object, wire: str) -> None:
    assert callable(build)
    assert build() == hexb(wire)
    packet = p.parse_packet(hexb(wire))
    assert p.build_packet(packet.id, packet.instruction, _raw_params(packet)) == hexb(wire)


def _raw_params(packet: p.Packet) -> bytes:
    return bytes([packet.error]) + packet.params if packet.is_status else packet.params


def test_ping_status_fields() -> None:
    packet = p.parse_packet(hexb("FF FF FD 00 01 07 00 55 00 06 04 26 65 5D"))
    assert packet.is_status
    assert packet.id == 1
    assert packet.error == 0
    assert p.from_le(packet.params[:2]) == ct.MODELS["XM430-W210"].number == 1030
    assert packet.params[2] == 0x26


def test_crc_matches_the_example_and_catches_a_flip() -> None:
    assert p.crc16(hexb("FF FF FD 00 01 03 00 01")) == 0x4E19
    with pytest.raises(p.PacketError, match="CRC"):
        p.parse_packet(hexb("FF FF FD 00 01 03 00 01 19 4F"))


def test_status_error_byte_alert_and_number() -> None:
    packet = p.parse_packet(p.status_packet(3, p.ALERT_BIT | p.ErrorNumber.ACCESS))
    assert packet.alert
    assert packet.error_number is p.ErrorNumber.ACCESS


def test_hardware_error_bits_decode() -> None:
    assert p.decode_hardware_error(0) == ()
    assert p.decode_hardware_error(0x24) == ("overheating", "overload")
    assert p.decode_hardware_error(0x01 | 0x08 | 0x10) == (
        "input voltage",
        "motor encoder",
        "electrical shock",
    )
    assert p.decode_hardware_error(0x02) == ("bit 1",)


def test_stuffing_example() -> None:
    assert p.stuff(hexb("FF FF FD 01")) == hexb("FF FF FD FD 01")
    assert p.unstuff(hexb("FF FF FD FD 01")) == hexb("FF FF FD 01")
    wire = p.write_packet(1, 116, hexb("FF FF FD 00"))
    assert b"\xff\xff\xfd\xfd" in wire
    assert p.parse_packet(wire).params == p.to_le(116, 2) + hexb("FF FF FD 00")


@given(st.binary(max_size=64))
def test_stuffing_round_trips_and_hides_headers(body: bytes) -> None:
    stuffed = p.stuff(body)
    assert p.unstuff(stuffed) == body
    # a header (FF FF FD followed by anything but FD) never appears inside a stuffed body
    at = stuffed.find(b"\xff\xff\xfd")
    while at >= 0:
        assert stuffed[at + 3 : at + 4] == b"\xfd"
        at = stuffed.find(b"\xff\xff\xfd", at + 4)


@given(
    st.integers(0, 252),
    st.sampled_from(list(p.Instruction)),
    st.binary(max_size=80),
)
def test_build_parse_round_trip(dxl_id: int, inst: int, params: bytes) -> None:
    if inst == p.Instruction.STATUS:
        params = b"\x00" + params
    packet = p.parse_packet(p.build_packet(dxl_id, inst, params))
    assert packet.id == dxl_id
    assert packet.instruction == inst
    assert _raw_params(packet) == params


@given(st.lists(st.binary(max_size=20), min_size=1, max_size=5), st.binary(max_size=8))
def test_reader_splits_a_stream_with_garbage(payloads: list[bytes], junk: bytes) -> None:
    junk = junk.replace(b"\xff", b"")
    stream = junk + b"".join(p.write_packet(7, 200, d or b"\x00") for d in payloads)
    reader = p.PacketReader()
    got: list[p.Packet | p.PacketError] = []
    for i in range(0, len(stream), 3):  # in small pieces
        got.extend(reader.feed(stream[i : i + 3]))
    assert [g.params[2:] for g in got if isinstance(g, p.Packet)] == [
        d or b"\x00" for d in payloads
    ]


def test_reader_reports_a_corrupt_packet_and_goes_on() -> None:
    bad = bytearray(p.ping_packet(1))
    bad[-1] ^= 0xFF
    got = list(p.PacketReader().feed(bytes(bad) + p.ping_packet(2)))
    assert isinstance(got[0], p.PacketError)
    assert isinstance(got[1], p.Packet)
    assert got[1].id == 2


def test_le_values() -> None:
    assert p.to_le(-1, 4) == hexb("FF FF FF FF")
    assert p.from_le(hexb("FF FF FF FF"), signed=True) == -1
    with pytest.raises(ValueError, match="fit"):
        p.to_le(70000, 2)


def test_bad_packets_are_refused() -> None:
    with pytest.raises(ValueError, match="id"):
        p.build_packet(0xFD, p.Instruction.PING)
    with pytest.raises(p.PacketError, match="truncated"):
        p.parse_packet(p.ping_packet(1)[:-1])
    with pytest.raises(ValueError, match="bytes of data"):
        p.sync_write_packet(116, 4, {1: b"\x00"})


def test_control_table_matches_the_e_manual() -> None:
    addresses = {r.name: (r.address, r.size) for r in ct.REGISTERS}
    assert addresses["Model Number"] == (0, 2)
    assert addresses["Operating Mode"] == (11, 1)
    assert addresses["Torque Enable"] == (64, 1)
    assert addresses["Hardware Error Status"] == (70, 1)
    assert addresses["Goal Current"] == (102, 2)
    assert addresses["Goal Velocity"] == (104, 4)
    assert addresses["Goal Position"] == (116, 4)
    assert addresses["Present Current"] == (126, 2)
    assert addresses["Present Velocity"] == (128, 4)
    assert addresses["Present Position"] == (132, 4)
    assert addresses["Present Input Voltage"] == (144, 2)
    assert addresses["Present Temperature"] == (146, 1)
    assert ct.MODELS["XM430-W350"].number == 1020
    assert ct.MODELS["XL430-W250"].number == 1060
    assert len(ct.MODELS_BY_NUMBER) == len(ct.MODELS)
