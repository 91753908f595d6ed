"""SimVehicle's parameters: the ArduCopter table, the .param file, the protocol with a pymavlink
ground station."""

from __future__ import annotations

import math
import struct
from pathlib import Path

import pytest

from temoto.clock import ManualClock
from temoto.drivers.mavlink import SimVehicle
from temoto.drivers.mavlink import protocol as p
from temoto.drivers.mavlink.sim import PARAMETERS
from temoto.drivers.mavlink.sim_params import load_param_file, save_param_file, stored_value

from .sim_gcs import (
    command,
    ground_station,
    mavlink,
    none_within,
    recv,
    set_mode,
    set_param,
    until,
)

# ---- the table and the file -------------------------------------------------------------------


def test_the_table_has_arducopter_names_defaults_and_types() -> None:
    assert len(PARAMETERS) >= 40
    expected = {
        "WPNAV_SPEED": (1000.0, p.MAV_PARAM_TYPE_REAL32),
        "RTL_ALT": (1500.0, p.MAV_PARAM_TYPE_INT32),
        "LAND_SPEED": (50.0, p.MAV_PARAM_TYPE_INT16),
        "FS_GCS_ENABLE": (0.0, p.MAV_PARAM_TYPE_INT8),
        "SYSID_MYGCS": (255.0, p.MAV_PARAM_TYPE_INT16),
        "ARMING_CHECK": (1.0, p.MAV_PARAM_TYPE_INT32),
        "BATT_LOW_VOLT": (10.5, p.MAV_PARAM_TYPE_REAL32),
    }
    for name, value in expected.items():
        assert PARAMETERS[name] == value, name
    assert all(len(name) <= 16 for name in PARAMETERS)  # PARAM_VALUE's param_id is char[16]


def test_stored_values_follow_the_type() -> None:
    assert stored_value(p.MAV_PARAM_TYPE_INT8, 300.0) == 127.0
    assert stored_value(p.MAV_PARAM_TYPE_INT16, -2.6) == -2.0  # AP_Param::set_float truncates
    assert (
        stored_value(p.MAV_PARAM_TYPE_REAL32, 0.1) == struct.unpack("<f", struct.pack("<f", 0.1))[0]
    )


def test_param_files_in_mavproxy_and_mission_planner_form(tmp_path: Path) -> None:
    path = tmp_path / "quad.param"
    path.write_text(
        "# saved by MAVProxy\nWPNAV_SPEED 800.0\nRTL_ALT,2000\n\n  FS_GCS_ENABLE\t5  # land\n"
        "WPNAV_SPEED 900\n"
    )
    assert load_param_file(path) == {"WPNAV_SPEED": 900.0, "RTL_ALT": 2000.0, "FS_GCS_ENABLE": 5.0}


@pytest.mark.parametrize(
    ("line", "why"),
    [
        ("WPNAV_SPEED", "expected 'NAME VALUE'"),
        ("WPNAV_SPEED fast", "not a number"),
        ("WPNAV_SPEED nan", "finite"),
        ("A B C", "expected 'NAME VALUE'"),
        ("THIS_NAME_IS_FAR_TOO_LONG 1", "bad parameter name"),
    ],
)
def test_a_bad_line_is_named_with_file_and_line(tmp_path: Path, line: str, why: str) -> None:
    path = tmp_path / "bad.param"
    path.write_text(f"RTL_ALT 1500\n{line}\n")
    with pytest.raises(ValueError, match=f"bad.param:2: .*{why}"):
        load_param_file(path)
    with pytest.raises(ValueError, match=r"bad\.param:2"):
        SimVehicle(params_file=path)


def test_saving_is_atomic_and_round_trips(tmp_path: Path) -> None:
    path = tmp_path / "quad.param"
    types = {"RTL_ALT": p.MAV_PARAM_TYPE_INT32, "WPNAV_SPEED": p.MAV_PARAM_TYPE_REAL32}
    save_param_file(path, {"RTL_ALT": 2500.0, "WPNAV_SPEED": 812.5}, types)
    assert "RTL_ALT 2500\n" in path.read_text()
    assert load_param_file(path) == {"RTL_ALT": 2500.0, "WPNAV_SPEED": 812.5}
    assert [f.name for f in tmp_path.iterdir()] == ["quad.param"]  # no temporary left behind


def test_constructor_values_then_params_then_the_file(tmp_path: Path) -> None:
    path = tmp_path / "quad.param"
    path.write_text("WPNAV_SPEED_UP 400\nSIM_SPEEDUP 4\n")
    sim = SimVehicle(speed=7.0, climb_rate=1.0, params={"WPNAV_SPEED_UP": 300}, params_file=path)
    assert sim.param("WPNAV_SPEED") == 700.0  # speed= is the initial WPNAV_SPEED
    assert sim.param("WPNAV_SPEED_UP") == 400.0  # the file (the vehicle's EEPROM) wins
    assert sim.param("SIM_SPEEDUP") == 4.0  # not simulated, but kept and served
    assert SimVehicle(params_file=tmp_path / "missing.param").param("RTL_ALT") == 1500.0
    with pytest.raises(ValueError, match="NO_SUCH_PARAM"):
        SimVehicle(params={"NO_SUCH_PARAM": 1})


# ---- the protocol, with a pymavlink ground station --------------------------------------------


def test_a_ground_station_downloads_the_complete_parameter_list() -> None:
    with ground_station() as (_, gcs):
        gcs.mav.param_request_list_send(gcs.target_system, 0)
        seen: dict[int, tuple[str, float, int]] = {}
        count = None
        while count is None or len(seen) < count:
            msg = recv(gcs, "PARAM_VALUE", 5.0)
            count = msg.param_count
            seen[msg.param_index] = (msg.param_id, msg.param_value, msg.param_type)
        assert set(seen) == set(range(count))
        names = {name: (value, kind) for name, value, kind in seen.values()}
        assert set(names) == set(PARAMETERS)
        assert names["RTL_ALT"] == (1500.0, p.MAV_PARAM_TYPE_INT32)
        assert names["WPNAV_SPEED"] == (1000.0, p.MAV_PARAM_TYPE_REAL32)  # ArduCopter's 10 m/s


def test_read_by_name_and_by_index_as_arducopter_answers() -> None:
    with ground_station() as (_, gcs):
        gcs.mav.param_request_read_send(gcs.target_system, 1, b"RTL_ALT", -1)
        by_name = recv(gcs, "PARAM_VALUE", 5.0, lambda m: m.param_id == "RTL_ALT")
        assert (by_name.param_value, by_name.param_index) == (1500.0, 65535)  # ArduPilot: -1
        index = sorted(PARAMETERS).index("LAND_SPEED")
        gcs.mav.param_request_read_send(gcs.target_system, 1, b"", index)
        by_index = recv(gcs, "PARAM_VALUE", 5.0, lambda m: m.param_id == "LAND_SPEED")
        assert by_index.param_index == index
        assert by_index.param_count == len(PARAMETERS)
        gcs.mav.param_request_read_send(gcs.target_system, 1, b"NO_SUCH_PARAM", -1)
        none_within(gcs, "PARAM_VALUE", 0.5)


def test_set_answers_the_stored_value_and_persists(tmp_path: Path) -> None:
    path = tmp_path / "quad.param"
    with ground_station(params_file=path) as (sim, gcs):
        echo = set_param(gcs, "FS_GCS_ENABLE", 5.4, p.MAV_PARAM_TYPE_INT8)
        assert echo.param_value == 5.0  # an INT8 holds 5
        echo = set_param(gcs, "WPNAV_SPEED", 1234.5, p.MAV_PARAM_TYPE_REAL32)
        assert echo.param_value == 1234.5
        assert sim.param("WPNAV_SPEED") == 1234.5
        gcs.mav.param_set_send(gcs.target_system, 1, b"NO_SUCH_PARAM", 1.0, 9)
        gcs.mav.param_set_send(gcs.target_system, 1, b"RTL_ALT", math.nan, 6)
        none_within(gcs, "PARAM_VALUE", 0.5)  # ArduPilot: no answer to either
        denied = set_param(gcs, "MIS_TOTAL", 7, p.MAV_PARAM_TYPE_INT16)
        assert denied.param_value == 1.0  # read-only: the mission's count (home only)
        assert "Param write denied (MIS_TOTAL)" in recv(gcs, "STATUSTEXT").text
    stored = load_param_file(path)
    assert stored["FS_GCS_ENABLE"] == 5.0
    assert stored["WPNAV_SPEED"] == 1234.5
    assert SimVehicle(params_file=path).param("WPNAV_SPEED") == 1234.5  # a restart keeps it


def test_wpnav_speed_drives_the_flight() -> None:
    with ground_station(tau=0.5) as (_, gcs):
        set_param(gcs, "WPNAV_SPEED", 300, p.MAV_PARAM_TYPE_REAL32)
        assert set_mode(gcs, "GUIDED")[0] == 0
        assert command(gcs, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)[0] == 0
        assert command(gcs, mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 5)[0] == 0
        recv(gcs, "GLOBAL_POSITION_INT", 10.0, lambda m: m.relative_alt > 4500)
        assert command(gcs, mavlink.MAV_CMD_DO_REPOSITION, -1, 0, 0, 0, 47.4, 8.545594, 493)[0] == 0
        fastest = 0.0
        for _ in range(30):
            msg = recv(gcs, "GLOBAL_POSITION_INT")
            fastest = max(fastest, math.hypot(msg.vx, msg.vy) / 100.0)
        assert fastest == pytest.approx(3.0, abs=0.05)  # WPNAV_SPEED 300 cm/s


def test_ftp_is_nacked_so_mavproxy_falls_back_to_the_parameter_list() -> None:
    with ground_station() as (_, gcs):
        name = b"@PARAM/param.pck"
        header = struct.pack("<HBBBBBBI", 7, 0, 4, len(name), 0, 0, 0, 0)  # OpenFileRO
        payload = list(header + name + bytes(251 - 12 - len(name)))
        gcs.mav.file_transfer_protocol_send(0, gcs.target_system, 1, payload)
        reply = bytes(recv(gcs, "FILE_TRANSFER_PROTOCOL").payload)
        seq, _, opcode, size, req_opcode = struct.unpack("<HBBBB", reply[:6])
        assert (seq, opcode, size, req_opcode, reply[12]) == (8, 129, 1, 4, 10)  # NAK FileNotFound
        header = struct.pack("<HBBBBBBI", 8, 0, 1, 0, 0, 0, 0, 0)  # TerminateSession
        gcs.mav.file_transfer_protocol_send(0, gcs.target_system, 1, list(header + bytes(239)))
        reply = bytes(recv(gcs, "FILE_TRANSFER_PROTOCOL").payload)
        assert (reply[3], reply[5]) == (128, 1)  # ACK


def test_a_parameter_file_that_cannot_be_written_is_logged_not_fatal(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "no-such-dir" / "quad.param"
    with ground_station(params_file=path) as (sim, gcs):
        assert set_param(gcs, "RTL_ALT", 2500, p.MAV_PARAM_TYPE_INT32).param_value == 2500.0
        assert sim.param("RTL_ALT") == 2500.0  # the vehicle keeps it in memory
    assert not path.exists()
    assert any("cannot write parameters" in r.getMessage() for r in caplog.records)


def test_the_parameter_list_is_paced_five_per_model_step() -> None:
    clock = ManualClock()
    with ground_station(clock=clock, step_rate=50.0) as (sim, gcs):
        gcs.mav.param_request_list_send(gcs.target_system, 0)
        until(lambda: sim.received.get("PARAM_REQUEST_LIST", 0) == 1, 5.0, "request")
        got: list[int] = []
        while len(got) < len(PARAMETERS):
            before = len(got)
            clock.advance(0.0201)  # one model step (a hair over 1/50 s: float sums)
            expect = min(5, len(PARAMETERS) - before)
            while len(got) < before + expect:
                got.append(recv(gcs, "PARAM_VALUE", 5.0).param_index)
            none_within(gcs, "PARAM_VALUE", 0.05)  # and no more until the next step
        assert got == list(range(len(PARAMETERS)))
