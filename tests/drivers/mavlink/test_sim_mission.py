"""SimVehicle's missions: the mission microservice (MissionService alone, then with a pymavlink
GCS), AUTO flight of waypoints on a ScaledClock, and the refusals ArduCopter gives."""

from __future__ import annotations

import math
import time
from typing import Any

import pytest

from temoto.drivers.mavlink import protocol as p
from temoto.drivers.mavlink.protocol import Codec
from temoto.drivers.mavlink.sim_mission import MissionItem, MissionService

from .sim_gcs import HOME, command, ground_station, mavlink, none_within, recv, set_mode

GCS = Codec(255, 190)
VEHICLE = Codec(1, 1)


def _decode(frames: list[bytes]) -> list[Any]:
    return [m for f in frames for m in GCS.decode_datagram(f)]


def _gcs_msg(name: str, sysid: int = 255, **fields: Any) -> Any:
    codec = GCS if sysid == 255 else Codec(sysid, 190)
    (msg,) = VEHICLE.decode_datagram(codec.encode(name, **fields))
    return msg


def _item_fields(
    seq: int, command: int = 16, lat: float = 47.0, lon: float = 8.0, alt: float = 10.0
) -> dict[str, Any]:
    return {
        "target_system": 1,
        "target_component": 1,
        "seq": seq,
        "frame": p.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
        "command": command,
        "current": 0,
        "autocontinue": 1,
        "param1": 0.0,
        "param2": 0.0,
        "param3": 0.0,
        "param4": 0.0,
        "x": p.deg_e7(lat),
        "y": p.deg_e7(lon),
        "z": alt,
    }


def _home() -> MissionItem:
    return MissionItem(0, p.MAV_FRAME_GLOBAL, 16, 0, 1, 0, 0, 0, 0, 470000000, 80000000, 500.0)


@pytest.fixture
def service() -> MissionService:
    return MissionService(VEHICLE.encode, _home)


# ---- MissionService on its own ---------------------------------------------------------------


def test_upload_asks_for_each_item_then_acks(service: MissionService) -> None:
    (req,) = _decode(
        service.handle(_gcs_msg("MISSION_COUNT", target_system=1, target_component=1, count=3), 0.0)
    )
    assert (req.name, req.get_int("seq")) == ("MISSION_REQUEST_INT", 0)
    for seq in range(2):
        (reply,) = _decode(service.handle(_gcs_msg("MISSION_ITEM_INT", **_item_fields(seq)), 0.1))
        assert (reply.name, reply.get_int("seq")) == ("MISSION_REQUEST_INT", seq + 1)
    text, ack = _decode(service.handle(_gcs_msg("MISSION_ITEM_INT", **_item_fields(2)), 0.1))
    assert text.get_text("text") == "Flight plan received"  # ArduPilot's, before the ACK
    assert (ack.name, ack.get_int("type")) == ("MISSION_ACK", p.MAV_MISSION_ACCEPTED)
    assert service.count() == 3
    assert service.version == 1
    assert service.item(0) == _home()  # item 0 is home, whatever was uploaded there
    assert service.item(2) is not None
    assert service.item(2).lat == pytest.approx(47.0)


def test_an_unanswered_request_is_resent_and_a_stalled_upload_cancelled(
    service: MissionService,
) -> None:
    service.handle(_gcs_msg("MISSION_COUNT", target_system=1, target_component=1, count=2), 0.0)
    assert service.tick(0.5) == []
    (again,) = _decode(service.tick(1.1))  # after 1 s without an item
    assert (again.name, again.get_int("seq")) == ("MISSION_REQUEST_INT", 0)
    text, cancel = _decode(service.tick(8.2))  # 8 s without an item
    assert text.get_text("text") == "Mission upload timeout"
    assert (cancel.name, cancel.get_int("type")) == (
        "MISSION_ACK",
        p.MAV_MISSION_OPERATION_CANCELLED,
    )
    assert not service.uploading
    assert service.count() == 1  # nothing arrived: the old (empty) mission is kept


def test_refusals_during_an_upload(service: MissionService) -> None:
    service.handle(_gcs_msg("MISSION_COUNT", target_system=1, target_component=1, count=2), 0.0)
    (other,) = _decode(
        service.handle(
            _gcs_msg("MISSION_COUNT", sysid=254, target_system=1, target_component=1, count=1), 0.1
        )
    )
    assert other.get_int("type") == p.MAV_MISSION_DENIED  # someone else is uploading
    (download,) = _decode(
        service.handle(_gcs_msg("MISSION_REQUEST_LIST", target_system=1, target_component=1), 0.1)
    )
    assert download.get_int("type") == p.MAV_MISSION_DENIED
    (skip,) = _decode(service.handle(_gcs_msg("MISSION_ITEM_INT", **_item_fields(1)), 0.1))
    assert skip.get_int("type") == p.MAV_MISSION_INVALID_SEQUENCE
    (bad,) = _decode(
        service.handle(_gcs_msg("MISSION_ITEM_INT", **_item_fields(0, command=65000)), 0.1)
    )
    assert bad.get_int("type") == p.MAV_MISSION_UNSUPPORTED
    assert not service.uploading


def test_legacy_items_are_asked_for_and_sent_in_kind(service: MissionService) -> None:
    service.handle(_gcs_msg("MISSION_COUNT", target_system=1, target_component=1, count=2), 0.0)
    legacy = {**_item_fields(0), "x": 47.5, "y": 8.25, "frame": p.MAV_FRAME_GLOBAL_RELATIVE_ALT}
    (req,) = _decode(service.handle(_gcs_msg("MISSION_ITEM", **legacy), 0.1))
    assert req.name == "MISSION_REQUEST"  # the GCS speaks the float form
    service.handle(_gcs_msg("MISSION_ITEM", **{**legacy, "seq": 1}), 0.2)
    assert service.item(1) is not None
    assert service.item(1).x == 475000000
    (item,) = _decode(
        service.handle(_gcs_msg("MISSION_REQUEST", target_system=1, target_component=1, seq=1), 0.3)
    )
    assert item.name == "MISSION_ITEM"
    assert item.get_float("x") == pytest.approx(47.5)


def test_clear_all_and_an_empty_upload_clear(service: MissionService) -> None:
    service.handle(_gcs_msg("MISSION_COUNT", target_system=1, target_component=1, count=1), 0.0)
    service.handle(_gcs_msg("MISSION_ITEM_INT", **_item_fields(0)), 0.1)
    assert service.count() == 1
    assert service.items
    (ack,) = _decode(
        service.handle(_gcs_msg("MISSION_CLEAR_ALL", target_system=1, target_component=1), 0.2)
    )
    assert ack.get_int("type") == p.MAV_MISSION_ACCEPTED
    assert service.items == []
    (count,) = _decode(
        service.handle(
            _gcs_msg(
                "MISSION_REQUEST_LIST",
                target_system=1,
                target_component=1,
                mission_type=p.MAV_MISSION_TYPE_FENCE,
            ),
            0.3,
        )
    )
    assert (count.name, count.get_int("count")) == ("MISSION_COUNT", 0)
    _, ack = _decode(
        service.handle(_gcs_msg("MISSION_COUNT", target_system=1, target_component=1, count=0), 0.4)
    )
    assert ack.get_int("type") == p.MAV_MISSION_ACCEPTED


# ---- with a pymavlink ground station ----------------------------------------------------------


def _offset(north: float, east: float) -> tuple[float, float]:
    lat = HOME[0] + math.degrees(north / 6_378_137.0)
    lon = HOME[1] + math.degrees(east / (6_378_137.0 * math.cos(math.radians(HOME[0]))))
    return lat, lon


def _mission(
    square: float = 40.0, alt: float = 10.0, hold: float = 0.0
) -> list[tuple[int, float, float, float, float]]:
    """(command, param1, lat, lon, alt): home, takeoff, 4 waypoints, land."""
    corners = [(square, 0.0), (square, square), (0.0, square), (0.0, 0.0)]
    items = [(16, 0.0, HOME[0], HOME[1], 0.0), (22, 0.0, 0.0, 0.0, alt)]
    items += [(16, hold, *_offset(n, e), alt) for n, e in corners]
    items.append((21, 0.0, *_offset(0.0, 0.0), 0.0))
    return items


def upload(gcs: Any, items: list[tuple[int, float, float, float, float]]) -> int:
    """Upload with MISSION_INT as a GCS does; the MISSION_ACK type."""
    gcs.mav.mission_count_send(gcs.target_system, 1, len(items), 0)
    while True:
        msg = recv(gcs, ["MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_ACK"])
        if msg.get_type() == "MISSION_ACK":
            return int(msg.type)
        assert msg.get_type() == "MISSION_REQUEST_INT"  # the vehicle asks for MISSION_INT
        cmd, param1, lat, lon, alt = items[msg.seq]
        frame = p.MAV_FRAME_GLOBAL if msg.seq == 0 else p.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT
        gcs.mav.mission_item_int_send(
            gcs.target_system, 1, msg.seq, frame, cmd, 0, 1, param1, 0, 0, 0,
            p.deg_e7(lat), p.deg_e7(lon), alt, 0,
        )  # fmt: skip


def download(gcs: Any) -> list[Any]:
    gcs.mav.mission_request_list_send(gcs.target_system, 1, 0)
    count = recv(gcs, "MISSION_COUNT").count
    items = []
    for seq in range(count):
        gcs.mav.mission_request_int_send(gcs.target_system, 1, seq, 0)
        items.append(recv(gcs, "MISSION_ITEM_INT", 5.0, lambda m, s=seq: m.seq == s))
    gcs.mav.mission_ack_send(gcs.target_system, 1, 0, 0)
    return items


def test_mission_round_trip_with_pymavlink() -> None:
    items = _mission()
    with ground_station() as (sim, gcs):
        assert upload(gcs, items) == p.MAV_MISSION_ACCEPTED
        assert len(sim.mission()) == len(items)
        got = download(gcs)
        assert len(got) == len(items)
        assert (got[0].x, got[0].y, got[0].z) == (p.deg_e7(HOME[0]), p.deg_e7(HOME[1]), HOME[2])
        for sent, back in zip(items[1:], got[1:], strict=True):
            assert (back.command, back.x, back.y, back.z) == (
                sent[0], p.deg_e7(sent[2]), p.deg_e7(sent[3]), sent[4],
            )  # fmt: skip
        assert sim.param("MIS_TOTAL") == len(items)
        gcs.mav.mission_clear_all_send(gcs.target_system, 1, 0)
        assert recv(gcs, "MISSION_ACK").type == p.MAV_MISSION_ACCEPTED
        assert recv(gcs, "MISSION_CURRENT", 5.0, lambda m: m.mission_state == 1).total == 65535


def test_auto_flies_four_waypoints_and_lands() -> None:
    params = {"WPNAV_SPEED": 1500, "LAND_SPEED": 300, "WPNAV_RADIUS": 100}
    with ground_station(params=params, tau=0.5, climb_rate=4.0, descent_rate=3.0) as (sim, gcs):
        mission = _mission(hold=1.0)
        assert upload(gcs, mission) == p.MAV_MISSION_ACCEPTED
        assert set_mode(gcs, "GUIDED")[0] == 0
        assert command(gcs, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)[0] == 0
        assert command(gcs, mavlink.MAV_CMD_MISSION_START, 0, 0)[0] == 0
        assert sim.mode == "AUTO"
        reached: list[int] = []
        closest = dict.fromkeys(range(2, 6), math.inf)  # corner → nearest seen by the GCS
        deadline = time.monotonic() + 30.0
        while len(reached) < 6:
            assert time.monotonic() < deadline, f"reached only {reached}"
            msg = recv(gcs, ["MISSION_ITEM_REACHED", "GLOBAL_POSITION_INT"])
            if msg.get_type() == "MISSION_ITEM_REACHED":
                reached.append(msg.seq)
                continue
            here = (msg.lat / 1e7, msg.lon / 1e7, msg.relative_alt / 1000.0)
            for seq in closest:
                closest[seq] = min(closest[seq], _distance(here, mission[seq][2:]))
        assert max(closest.values()) < 1.0  # each corner within WPNAV_RADIUS (1 m)
        assert reached == [1, 2, 3, 4, 5, 6]
        recv(gcs, "HEARTBEAT", 5.0, lambda m: not m.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
        done = recv(gcs, "MISSION_CURRENT", 5.0, lambda m: m.mission_state == 5)  # COMPLETE
        assert (done.seq, done.total) == (6, 6)
        lat, lon, alt = sim.position()
        assert alt == 0.0
        assert _distance((lat, lon, 0.0), (HOME[0], HOME[1], 0.0)) < 1.0


def test_entering_auto_and_arming_in_it_as_arducopter_allows() -> None:
    with ground_station() as (sim, gcs):
        result, texts = set_mode(gcs, "AUTO", texts_for=0.3)
        assert result == mavlink.MAV_RESULT_FAILED  # no mission
        assert "Mode change to AUTO failed: init failed" in texts
        assert (
            command(gcs, mavlink.MAV_CMD_MISSION_START)[0] == mavlink.MAV_RESULT_FAILED
        )  # no AUTO
        assert command(gcs, mavlink.MAV_CMD_MISSION_START, 2, 4)[0] == mavlink.MAV_RESULT_DENIED
        wps = [m for m in _mission() if m[0] != 22]  # no takeoff first
        assert upload(gcs, wps) == p.MAV_MISSION_ACCEPTED
        assert set_mode(gcs, "AUTO")[0] == 0  # disarmed: allowed
        result, texts = command(gcs, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1, texts_for=0.3)
        assert (result, texts) == (mavlink.MAV_RESULT_FAILED, ["Arm: Mode not armable"])
        assert set_mode(gcs, "GUIDED")[0] == 0
        assert command(gcs, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)[0] == 0
        result, texts = set_mode(
            gcs, "AUTO", texts_for=0.3
        )  # armed on the ground, first item not a takeoff
        assert result == mavlink.MAV_RESULT_FAILED
        assert "Auto: Missing Takeoff Cmd" in texts
        assert command(gcs, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0)[0] == 0
        assert upload(gcs, _mission()) == p.MAV_MISSION_ACCEPTED
        gcs.mav.param_set_send(gcs.target_system, 1, b"AUTO_OPTIONS", 1, p.MAV_PARAM_TYPE_INT32)
        recv(gcs, "PARAM_VALUE", 5.0, lambda m: m.param_id == "AUTO_OPTIONS")
        assert set_mode(gcs, "AUTO")[0] == 0
        assert command(gcs, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)[0] == 0  # AUTO_OPTIONS bit 0
        # ModeAuto::takeoff_run: no throttle raised (no RC here), no AUTO_OPTIONS bit 1: waits
        none_within(gcs, "GLOBAL_POSITION_INT", 1.0, lambda m: m.relative_alt > 100)
        assert command(gcs, mavlink.MAV_CMD_MISSION_START)[0] == 0  # stands in for the throttle
        recv(gcs, "MISSION_CURRENT", 10.0, lambda m: m.seq == 2 and m.mission_state == 3)
        assert sim.position()[2] > 9.0  # took off in AUTO to 10 m


def test_set_current_and_the_guided_mission_item() -> None:
    with ground_station(tau=0.5) as (sim, gcs):
        assert upload(gcs, _mission()) == p.MAV_MISSION_ACCEPTED
        gcs.mav.mission_set_current_send(gcs.target_system, 1, 4)
        assert recv(gcs, "MISSION_CURRENT", 5.0, lambda m: m.seq == 4).mission_state == 2
        assert (
            command(gcs, mavlink.MAV_CMD_DO_SET_MISSION_CURRENT, 99)[0] == mavlink.MAV_RESULT_FAILED
        )
        assert set_mode(gcs, "GUIDED")[0] == 0
        assert command(gcs, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)[0] == 0
        assert command(gcs, mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 5)[0] == 0
        recv(gcs, "GLOBAL_POSITION_INT", 10.0, lambda m: m.relative_alt > 4500)
        lat, lon = _offset(20.0, 0.0)
        gcs.mav.mission_item_int_send(
            gcs.target_system, 1, 0, p.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, 16, 2, 1, 0, 0, 0, 0,
            p.deg_e7(lat), p.deg_e7(lon), 8.0, 0,
        )  # fmt: skip  # current=2: the older guided "fly to"
        assert recv(gcs, "MISSION_ACK").type == p.MAV_MISSION_ACCEPTED
        recv(
            gcs,
            "GLOBAL_POSITION_INT",
            15.0,
            lambda m: (
                _distance((m.lat / 1e7, m.lon / 1e7, m.relative_alt / 1000), (lat, lon, 8.0)) < 0.5
            ),
        )
        assert len(sim.mission()) == len(_mission())  # the guided item is not stored
        assert set_mode(gcs, "LOITER")[0] == 0
        gcs.mav.mission_item_int_send(
            gcs.target_system, 1, 0, p.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, 16, 2, 1, 0, 0, 0, 0,
            p.deg_e7(lat), p.deg_e7(lon), 8.0, 0,
        )  # fmt: skip
        assert recv(gcs, "MISSION_ACK").type == p.MAV_MISSION_ERROR  # not in GUIDED
        none_within(gcs, "MISSION_ITEM_REACHED", 0.2)


def _distance(a: tuple[float, float, float], b: tuple[float, ...]) -> float:
    north = math.radians(a[0] - b[0]) * 6_378_137.0
    east = math.radians(a[1] - b[1]) * 6_378_137.0 * math.cos(math.radians(b[0]))
    return math.sqrt(north**2 + east**2 + (a[2] - b[2]) ** 2)


@pytest.mark.parametrize(("params", "mode"), [({"FS_GCS_ENABLE": 2}, "AUTO"),
                                              ({"FS_GCS_ENABLE": 1, "FS_OPTIONS": 2}, "AUTO"),
                                              ({"FS_GCS_ENABLE": 1}, "RTL")])  # fmt: skip
def test_the_gcs_failsafe_in_auto_continues_the_mission_when_told(
    params: dict[str, float], mode: str
) -> None:
    items = [*_mission()[:3], (19, 60.0, *_offset(40.0, 0.0), 10.0)]  # loiter there for 60 s
    with ground_station(params=params, tau=0.5) as (sim, gcs):
        assert upload(gcs, items) == p.MAV_MISSION_ACCEPTED
        assert set_mode(gcs, "GUIDED")[0] == 0
        assert command(gcs, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)[0] == 0
        assert command(gcs, mavlink.MAV_CMD_MISSION_START)[0] == 0
        recv(gcs, "MISSION_CURRENT", 20.0, lambda m: m.seq == 3)
        gcs.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        text = recv(gcs, "STATUSTEXT", 5.0, lambda m: m.text.startswith("GCS Failsafe")).text
        expected = "GCS Failsafe - Continuing Auto Mode" if mode == "AUTO" else "GCS Failsafe"
        assert text == expected
        recv(gcs, "HEARTBEAT", 5.0, lambda m: m.custom_mode == p.COPTER_MODES[mode])
        assert sim.gcs_failsafe


def test_a_mission_changed_in_flight_restarts_the_current_command() -> None:
    first = [*_mission()[:2], (16, 30.0, *_offset(40.0, 0.0), 10.0)]  # hold 30 s up north
    second = [*_mission()[:2], (16, 30.0, *_offset(0.0, 40.0), 10.0)]  # the same, east
    with ground_station(params={"WPNAV_SPEED": 1500}, tau=0.5) as (sim, gcs):
        assert upload(gcs, first) == p.MAV_MISSION_ACCEPTED
        assert set_mode(gcs, "GUIDED")[0] == 0
        assert command(gcs, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)[0] == 0
        assert command(gcs, mavlink.MAV_CMD_MISSION_START)[0] == 0
        recv(gcs, "MISSION_CURRENT", 20.0, lambda m: m.seq == 2)
        assert upload(gcs, second) == p.MAV_MISSION_ACCEPTED
        there = (*second[2][2:4], 10.0)

        def arrived(m: Any) -> bool:
            return _distance((m.lat / 1e7, m.lon / 1e7, m.relative_alt / 1000), there) < 1.0

        recv(gcs, "GLOBAL_POSITION_INT", 20.0, arrived)
        assert sim.mode == "AUTO"
        assert sim.mission_current == 2
    with ground_station() as (sim, gcs):  # uploaded while not flying: not started, from 1
        assert upload(gcs, first) == p.MAV_MISSION_ACCEPTED
        gcs.mav.mission_set_current_send(gcs.target_system, 1, 2)
        recv(gcs, "MISSION_CURRENT", 5.0, lambda m: m.seq == 2)
        assert upload(gcs, second) == p.MAV_MISSION_ACCEPTED
        current = recv(gcs, "MISSION_CURRENT", 5.0, lambda m: m.seq == 1)
        assert current.mission_state == 2  # NOT_STARTED


def test_do_commands_loiter_time_and_rtl_in_a_mission() -> None:
    north = (*_offset(30.0, 0.0), 10.0)
    items = [
        *_mission()[:2],  # home, takeoff to 10 m
        (178, 1.0, 0.0, 0.0, 0.0),  # DO_CHANGE_SPEED: ground speed (param2 below) 3 m/s
        (16, 0.0, *north),  # 3: 30 m north
        (177, 3.0, 0.0, 0.0, 0.0),  # DO_JUMP to 3, once more (param2 below)
        (19, 2.0, *north),  # 5: LOITER_TIME 2 s
        (20, 0.0, 0.0, 0.0, 0.0),  # 6: RETURN_TO_LAUNCH
    ]
    with ground_station(tau=0.5, climb_rate=4.0, descent_rate=3.0) as (sim, gcs):
        gcs.mav.mission_count_send(gcs.target_system, 1, len(items), 0)
        while (
            msg := recv(gcs, ["MISSION_REQUEST_INT", "MISSION_ACK"])
        ).get_type() != "MISSION_ACK":
            cmd, param1, lat, lon, alt = items[msg.seq]
            param2 = {178: 3.0, 177: 1.0}.get(cmd, 0.0)
            gcs.mav.mission_item_int_send(
                gcs.target_system, 1, msg.seq, p.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, cmd, 0, 1,
                param1, param2, 0, 0, p.deg_e7(lat), p.deg_e7(lon), alt, 0,
            )  # fmt: skip
        assert msg.type == p.MAV_MISSION_ACCEPTED
        assert set_mode(gcs, "GUIDED")[0] == 0
        assert command(gcs, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)[0] == 0
        assert command(gcs, mavlink.MAV_CMD_MISSION_START)[0] == 0
        reached, fastest = [], 0.0
        deadline = time.monotonic() + 30.0
        while sim.armed or len(reached) < 5:
            assert time.monotonic() < deadline, f"reached only {reached}"
            msg = recv(gcs, ["MISSION_ITEM_REACHED", "GLOBAL_POSITION_INT"])
            if msg.get_type() == "MISSION_ITEM_REACHED":
                reached.append(msg.seq)
            elif msg.relative_alt > 9000:
                fastest = max(fastest, math.hypot(msg.vx, msg.vy) / 100.0)
        assert reached == [1, 3, 3, 5, 6]  # DO commands are not "reached"; the jump repeats 3
        assert fastest == pytest.approx(3.0, abs=0.05)  # DO_CHANGE_SPEED, not WPNAV_SPEED 5 m/s
        lat, lon, alt = sim.position()
        assert alt == 0.0
        assert _distance((lat, lon, 0.0), (HOME[0], HOME[1], 0.0)) < 1.0
