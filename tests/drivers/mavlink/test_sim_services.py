"""SimVehicle's other ground-station services, with a pymavlink GCS: component targeting, home,
TIMESYNC, the streams and REQUEST_DATA_STREAM, AUTOPILOT_VERSION, the pre-arm bit, the battery
failsafe."""

from __future__ import annotations

import time

import pytest

from temoto.drivers.mavlink import protocol as p
from temoto.drivers.mavlink.sim import DEFAULT_RATES, STREAM_GROUPS

from .sim_gcs import HOME, command, ground_station, mavlink, none_within, recv, set_mode, set_param


def test_commands_for_another_component_are_not_acted_on() -> None:
    with ground_station() as (sim, gcs):
        assert set_mode(gcs, "GUIDED")[0] == 0
        gcs.mav.command_long_send(gcs.target_system, 100, 400, 0, 1, 0, 0, 0, 0, 0, 0)  # camera
        none_within(gcs, "COMMAND_ACK", 0.5)
        assert not sim.armed
        assert command(gcs, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1, component=0)[0] == 0
        assert sim.armed  # broadcast (component 0) reaches the autopilot
        gcs.mav.param_set_send(gcs.target_system, 100, b"RTL_ALT", 3000, 6)
        none_within(gcs, "PARAM_VALUE", 0.3)
        assert sim.param("RTL_ALT") == 1500.0


def test_home_position_on_request_and_set_home() -> None:
    with ground_station() as (sim, gcs):
        assert command(gcs, mavlink.MAV_CMD_GET_HOME_POSITION)[0] == 0
        home = recv(gcs, "HOME_POSITION")
        assert (home.latitude, home.longitude) == (p.deg_e7(HOME[0]), p.deg_e7(HOME[1]))
        gcs.mav.command_long_send(gcs.target_system, 1, 512, 0, 242, 0, 0, 0, 0, 0, 0)
        assert recv(gcs, "COMMAND_ACK", 5.0, lambda m: m.command == 512).result == 0
        recv(gcs, "HOME_POSITION")
        new = (HOME[0] + 0.001, HOME[1] + 0.001, HOME[2] + 2.0)
        result, _ = command(gcs, mavlink.MAV_CMD_DO_SET_HOME, 0, 0, 0, 0, *new)
        assert result == 0
        # COMMAND_LONG carries float32 degrees (~0.1 m steps here): close, not exact
        home = recv(gcs, "HOME_POSITION", 5.0, lambda m: abs(m.latitude - p.deg_e7(new[0])) < 20)
        assert home.altitude == round(new[2] * 1000)
        far = (HOME[0] + 1.0, HOME[1], HOME[2])  # 111 km from the origin
        assert command(gcs, mavlink.MAV_CMD_DO_SET_HOME, 0, 0, 0, 0, *far)[0] == 4  # FAILED
        # GLOBAL_POSITION_INT's relative altitude is now above the new home (2 m higher)
        recv(gcs, "GLOBAL_POSITION_INT", 5.0, lambda m: m.relative_alt == -2000)
        assert sim.position()[2] == pytest.approx(-2.0)
        assert command(gcs, mavlink.MAV_CMD_DO_SET_HOME, 2)[0] == 4  # param1 is 0 or 1
        assert command(gcs, mavlink.MAV_CMD_DO_SET_HOME, 1)[0] == 0  # here
        recv(gcs, "HOME_POSITION", 5.0, lambda m: m.latitude == p.deg_e7(HOME[0]))
        assert sim.position()[2] == pytest.approx(0.0)


def test_timesync_is_answered() -> None:
    with ground_station() as (_, gcs):
        gcs.mav.timesync_send(0, 123456789)
        reply = recv(gcs, "TIMESYNC", 5.0, lambda m: m.ts1 == 123456789)
        assert reply.tc1 > 0


def test_arducopter_streams_arrive_and_request_data_stream_sets_a_group() -> None:
    with ground_station() as (sim, gcs):
        seen: set[str] = set()
        deadline = time.monotonic() + 5.0
        while seen != set(DEFAULT_RATES) and time.monotonic() < deadline:
            msg = gcs.recv_match(blocking=True, timeout=0.5)
            if msg is not None:
                seen.add(msg.get_type())
        assert set(DEFAULT_RATES) <= seen
        gcs.mav.request_data_stream_send(gcs.target_system, 1, mavlink.MAV_DATA_STREAM_EXTRA3, 7, 1)
        for name in STREAM_GROUPS[p.MAV_DATA_STREAM_EXTRA3]:
            recv(gcs, "HEARTBEAT")  # one more round trip: the request was handled
            assert sim.rate(name) == pytest.approx(7.0), name
        assert sim.rate("ATTITUDE") == DEFAULT_RATES["ATTITUDE"]
        gcs.mav.request_data_stream_send(gcs.target_system, 1, mavlink.MAV_DATA_STREAM_ALL, 0, 0)
        recv(gcs, "HEARTBEAT")
        assert sim.rate("ATTITUDE") == 0.0
        assert sim.rate("HEARTBEAT") == 1.0  # not in a group
        none_within(gcs, "ATTITUDE", 0.5)


def test_autopilot_version_has_the_capabilities_ground_stations_check() -> None:
    with ground_station() as (_, gcs):
        gcs.mav.command_long_send(gcs.target_system, 1, 520, 0, 1, 0, 0, 0, 0, 0, 0)
        caps = recv(gcs, "AUTOPILOT_VERSION").capabilities
        for cap in ("MISSION_INT", "PARAM_FLOAT", "MAVLINK2", "COMMAND_INT", "MISSION_FENCE"):
            assert caps & getattr(mavlink, f"MAV_PROTOCOL_CAPABILITY_{cap}"), cap
        assert not caps & mavlink.MAV_PROTOCOL_CAPABILITY_FTP  # FTP requests are NAKed


def test_the_prearm_check_bit_as_arducopter_sets_it() -> None:
    bit = mavlink.MAV_SYS_STATUS_PREARM_CHECK
    with ground_station(battery=15.0) as (sim, gcs):
        status = recv(gcs, "SYS_STATUS")
        assert status.onboard_control_sensors_present & bit
        assert status.onboard_control_sensors_enabled & bit
        assert not status.onboard_control_sensors_health & bit  # 15 % < min_arm_battery
        result, texts = command(gcs, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1, texts_for=0.3)
        assert result == mavlink.MAV_RESULT_FAILED
        assert texts == ["PreArm: Battery below minimum arming capacity"]
        set_param(gcs, "ARMING_CHECK", 0, p.MAV_PARAM_TYPE_INT32)
        status = recv(gcs, "SYS_STATUS", 5.0, lambda m: not m.onboard_control_sensors_enabled & bit)
        assert status.onboard_control_sensors_health & bit
        assert command(gcs, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)[0] == 0  # checks off
        assert sim.armed


def test_the_battery_failsafe_returns_home() -> None:
    params = {"BATT_CAPACITY": 1000, "BATT_LOW_MAH": 700, "BATT_FS_LOW_ACT": 2}
    with ground_station(params=params, drain_flight=10.0, tau=0.5) as (sim, gcs):
        assert set_mode(gcs, "GUIDED")[0] == 0
        assert command(gcs, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)[0] == 0
        assert command(gcs, mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 5)[0] == 0
        text = recv(gcs, "STATUSTEXT", 20.0, lambda m: m.text.startswith("Battery 1 is low"))
        assert "used" in text.text
        recv(gcs, "HEARTBEAT", 5.0, lambda m: m.custom_mode == p.COPTER_MODES["RTL"])
        assert sim.battery_failsafe == 1
        assert recv(gcs, "HEARTBEAT").system_status == mavlink.MAV_STATE_CRITICAL
