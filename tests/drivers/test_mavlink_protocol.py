"""The MAVLink adapter and links: byte round trips, bad CRCs, streams, names, URLs."""

from __future__ import annotations

import math
import socket
import time

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from temoto.clock import ManualClock
from temoto.drivers.mavlink import protocol as p
from temoto.drivers.mavlink.link import LinkSpec, UdpLink, parse_link
from temoto.drivers.mavlink.sim import SimVehicle


def test_a_heartbeat_round_trips_as_mavlink2() -> None:
    vehicle, gcs = p.Codec(1, 1), p.Codec(255, 190)
    frame = vehicle.encode(
        "HEARTBEAT",
        type=2,
        autopilot=3,
        base_mode=129,
        custom_mode=4,
        system_status=4,
        mavlink_version=3,
    )
    assert frame[0] == 0xFD  # MAVLink 2 magic
    (msg,) = gcs.decode(frame)
    assert (msg.name, msg.msg_id, msg.src_system, msg.src_component) == ("HEARTBEAT", 0, 1, 1)
    assert msg.get_int("custom_mode") == 4
    assert p.mode_name(msg.get_int("custom_mode")) == "GUIDED"


def test_command_long_round_trips_with_nan_params() -> None:
    a, b = p.Codec(255, 190), p.Codec(1, 1)
    frame = a.encode(
        "COMMAND_LONG",
        target_system=1,
        target_component=1,
        command=22,
        confirmation=0,
        param1=0,
        param2=0,
        param3=0,
        param4=math.nan,
        param5=math.nan,
        param6=math.nan,
        param7=12.5,
    )
    (msg,) = b.decode(frame)
    assert msg.get_int("command") == p.MAV_CMD_NAV_TAKEOFF == 22
    assert math.isnan(msg.get_float("param4"))
    assert msg.get_float("param7") == 12.5


def test_statustext_is_text_and_positions_are_scaled() -> None:
    a, b = p.Codec(1, 1), p.Codec(255, 190)
    frames = a.encode("STATUSTEXT", severity=2, text=b"PreArm: Battery low", id=0)
    frames += a.encode(
        "GLOBAL_POSITION_INT",
        time_boot_ms=1,
        lat=p.deg_e7(47.3977421),
        lon=p.deg_e7(-8.5),
        alt=488000,
        relative_alt=-1500,
        vx=0,
        vy=0,
        vz=0,
        hdg=65535,
    )
    text, pos = b.decode(frames)
    assert text.get_text("text") == "PreArm: Battery low"
    assert pos.get_int("lat") == 473977421
    assert pos.get_int("lon") == -85000000
    assert pos.get_int("relative_alt") == -1500


def test_a_corrupt_frame_is_counted_and_dropped_and_the_next_one_parses() -> None:
    a, b = p.Codec(1, 1), p.Codec(255, 190)
    good = a.encode(
        "ATTITUDE",
        time_boot_ms=5,
        roll=0.1,
        pitch=0.2,
        yaw=0.3,
        rollspeed=0,
        pitchspeed=0,
        yawspeed=0,
    )
    bad = p.corrupt(good)
    assert bad != good
    assert len(bad) == len(good)
    assert b.decode(bad) == []
    assert b.bad_frames == 1
    (msg,) = b.decode(good)
    assert msg.get_float("yaw") == pytest.approx(0.3)


def test_a_frame_split_across_reads_is_completed() -> None:
    a, b = p.Codec(1, 1), p.Codec(255, 190)
    frame = a.encode(
        "COMMAND_ACK",
        command=400,
        result=2,
        progress=0,
        result_param2=0,
        target_system=255,
        target_component=190,
    )
    assert b.decode(frame[:5]) == []
    (ack,) = b.decode(frame[5:])
    assert (ack.get_int("command"), ack.get_int("result")) == (400, p.MAV_RESULT_DENIED)
    assert ack.get_int("target_system") == 255


def test_encode_errors_are_value_errors() -> None:
    codec = p.Codec(1, 1)
    with pytest.raises(ValueError, match="unknown MAVLink message"):
        codec.encode("NOT_A_MESSAGE")
    with pytest.raises(ValueError, match="cannot encode HEARTBEAT"):
        codec.encode("HEARTBEAT", type=2)
    with pytest.raises(ValueError, match="bad MAVLink ids"):
        p.Codec(0, 1)


def test_names() -> None:
    assert p.command_name(400) == "MAV_CMD_COMPONENT_ARM_DISARM"
    assert p.result_name(p.MAV_RESULT_TEMPORARILY_REJECTED) == "MAV_RESULT_TEMPORARILY_REJECTED"
    assert p.result_name(99) == "MAV_RESULT(99)"
    assert p.mode_number("rtl") == 6
    assert p.mode_name(123) == "MODE(123)"
    with pytest.raises(ValueError, match="known: STABILIZE"):
        p.mode_number("HOVER")
    assert p.SENSOR_BITS["BATTERY"] == 1 << 25


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=300))
def test_decoding_garbage_never_raises(data: bytes) -> None:
    codec = p.Codec(255, 190)
    for msg in codec.decode(data):
        assert msg.name


@settings(max_examples=50, deadline=None)
@given(
    lat=st.floats(-90, 90),
    lon=st.floats(-180, 180),
    alt=st.floats(-1000, 10000),
    command=st.integers(0, 65535),
)
def test_command_int_round_trips(lat: float, lon: float, alt: float, command: int) -> None:
    a, b = p.Codec(255, 190), p.Codec(1, 1)
    frame = a.encode(
        "COMMAND_INT",
        target_system=1,
        target_component=1,
        frame=6,
        command=command,
        current=0,
        autocontinue=0,
        param1=-1,
        param2=1,
        param3=0,
        param4=math.nan,
        x=p.deg_e7(lat),
        y=p.deg_e7(lon),
        z=alt,
    )
    (msg,) = b.decode(frame)
    assert msg.get_int("command") == command
    assert abs(msg.get_int("x") / 1e7 - lat) <= 1e-7
    assert msg.get_float("z") == pytest.approx(alt, rel=1e-6, abs=1e-3)


@pytest.mark.parametrize(
    ("url", "spec"),
    [
        ("udpin:127.0.0.1:14550", LinkSpec("udpin", "127.0.0.1", 14550)),
        ("udp:0.0.0.0:14550", LinkSpec("udpin", "0.0.0.0", 14550)),
        ("udpout://10.0.0.2:14555", LinkSpec("udpout", "10.0.0.2", 14555)),
        ("serial:/dev/ttyACM0", LinkSpec("serial", device="/dev/ttyACM0", baud=57600)),
        ("serial:/dev/ttyUSB0?baud=921600", LinkSpec("serial", device="/dev/ttyUSB0", baud=921600)),
    ],
)
def test_link_urls(url: str, spec: LinkSpec) -> None:
    assert parse_link(url) == spec


@pytest.mark.parametrize(
    "url",
    [
        "tcp:1.2.3.4:5",
        "udpin:1.2.3.4",
        "udpin:host:x",
        "udpout:h:0",
        "serial:",
        "x",
        "serial:/dev/x?parity=N",
        "serial:/dev/x?baud=-1",
    ],
)
def test_bad_link_urls(url: str) -> None:
    with pytest.raises(ValueError, match=r"link|needs|port|baud|parameter"):
        parse_link(url)


def test_the_sim_follows_set_position_target_global_int() -> None:
    """GUIDED position targets (the classic ArduPilot way) move the simulated vehicle."""
    clock = ManualClock()
    sim = SimVehicle("raw", clock=clock, home=(10.0, 20.0, 100.0), speed=10.0, climb_rate=5.0)
    gcs = p.Codec(255, 190)
    with sim, socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.settimeout(2.0)

        def command(cmd: int, *params: float) -> int:
            values = [*params, *[0.0] * (7 - len(params))]
            sock.sendto(
                gcs.encode(
                    "COMMAND_LONG",
                    target_system=1,
                    target_component=1,
                    command=cmd,
                    confirmation=0,
                    **{f"param{i + 1}": v for i, v in enumerate(values)},
                ),
                sim.address,
            )
            while True:
                for msg in gcs.decode(sock.recv(2048)):
                    if msg.name == "COMMAND_ACK" and msg.get_int("command") == cmd:
                        return msg.get_int("result")

        assert command(p.MAV_CMD_DO_SET_MODE, 1, p.mode_number("GUIDED")) == 0
        assert command(p.MAV_CMD_COMPONENT_ARM_DISARM, 1) == 0
        assert command(p.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 5.0) == 0
        assert command(999) == p.MAV_RESULT_UNSUPPORTED
        clock.advance(10.0)
        target = (10.0001, 20.0001)
        sock.sendto(
            gcs.encode(
                "SET_POSITION_TARGET_GLOBAL_INT",
                time_boot_ms=0,
                target_system=1,
                target_component=1,
                coordinate_frame=p.MAV_FRAME_GLOBAL_INT,
                type_mask=0b110111111000,
                lat_int=p.deg_e7(target[0]),
                lon_int=p.deg_e7(target[1]),
                alt=110.0,
                vx=0,
                vy=0,
                vz=0,
                afx=0,
                afy=0,
                afz=0,
                yaw=0,
                yaw_rate=0,
            ),
            sim.address,
        )
        deadline = time.monotonic() + 5.0
        while not sim.received.get("SET_POSITION_TARGET_GLOBAL_INT"):
            assert time.monotonic() < deadline
            time.sleep(0.005)
        # step virtual time until it arrives (the model thread may skip steps when the machine
        # is busy, so the clock keeps moving until the position is reached, 60 s of it at most)
        deadline = time.monotonic() + 10.0
        steps = 0
        while abs(sim.position()[2] - 10.0) > 0.05 or sim.position()[0] != pytest.approx(
            target[0], abs=1e-7
        ):
            assert time.monotonic() < deadline
            assert steps < 6000, "not there after 60 virtual seconds"
            clock.advance(0.01)
            steps += 1
            time.sleep(0.0005)
        lat, lon, alt = sim.position()
        assert lat == pytest.approx(target[0], abs=1e-7)
        assert lon == pytest.approx(target[1], abs=1e-7)
        assert alt == pytest.approx(10.0, abs=0.05)  # 110 m AMSL over a 100 m home


def test_udp_link_needs_a_peer_before_it_can_write() -> None:
    link = UdpLink(LinkSpec("udpin", "127.0.0.1", 0))
    try:
        assert link.write(b"x") is False
        assert link.read(0.01) == b""
    finally:
        link.close()
