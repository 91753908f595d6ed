"""MavlinkDriver's mission and parameter microservices against an independent vehicle end.

The vehicle is :mod:`_mavemu` (pymavlink on its own UDP socket, written from the MAVLink
protocol documents), not temoto's simulator. Timeouts are a tenth of a second of the real
clock, so a retry costs little; no assertion is about timing.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mav

from temoto.clock import MonotonicClock
from temoto.drivers import MissionItem, MissionProgress, MissionVehicle
from temoto.drivers.mavlink import MavlinkDriver
from temoto.errors import (
    DriverOperationError,
    DriverTimeoutError,
    MavlinkCommandError,
    MavlinkMissionError,
    ProfileError,
    StateError,
)

from ._mavemu import AUTO, GUIDED, MavEmu

LAT, LON = 47.397742, 8.545594
NORTH = round(LAT + 0.0003, 7)  # what int32 degrees·1e7 carry back unchanged
EAST = round(LON + 0.0004, 7)
MISSION = [
    MissionItem.takeoff(10.0),
    MissionItem.change_speed(5.0),
    MissionItem.waypoint(NORTH, LON, 10.0, hold=2.0),
    MissionItem.loiter_time(3.0),
    MissionItem.waypoint(NORTH, EAST, 12.5),
    MissionItem.land(),
]


@pytest.fixture
def emu() -> Iterator[MavEmu]:
    with MavEmu() as vehicle:
        yield vehicle


@pytest.fixture
def driver(emu: MavEmu) -> Iterator[MavlinkDriver]:
    drv = MavlinkDriver(
        "quad",
        link=emu.link,
        clock=MonotonicClock(),
        system_id=1,
        init_timeout=3.0,
        command_timeout=0.1,
        command_retries=2,
        mission_timeout=0.1,
        mission_retries=3,
        stream_rate=0,
    )
    drv.configure()
    drv.activate()
    try:
        yield drv
    finally:
        drv.shutdown()


# ---- upload ----------------------------------------------------------------------------------


def test_upload_sends_every_item_as_mission_item_int_after_ardupilots_home_item(
    emu: MavEmu, driver: MavlinkDriver
) -> None:
    driver.upload_mission(MISSION)
    assert len(emu.mission) == len(MISSION) + 1
    home, *items = emu.mission
    assert (home.seq, home.command, home.frame) == (0, mav.MAV_CMD_NAV_WAYPOINT, 0)
    assert [i.command for i in items] == [
        mav.MAV_CMD_NAV_TAKEOFF,
        mav.MAV_CMD_DO_CHANGE_SPEED,
        mav.MAV_CMD_NAV_WAYPOINT,
        mav.MAV_CMD_NAV_LOITER_TIME,
        mav.MAV_CMD_NAV_WAYPOINT,
        mav.MAV_CMD_NAV_LAND,
    ]
    takeoff, speed, wp1, loiter, wp2, land = items
    assert takeoff.frame == mav.MAV_FRAME_GLOBAL_RELATIVE_ALT
    assert takeoff.z == 10.0
    assert (speed.frame, speed.param1, speed.param2) == (mav.MAV_FRAME_MISSION, 1.0, 5.0)
    assert (wp1.x, wp1.y, wp1.z, wp1.param1) == (round(NORTH * 1e7), 85455940, 10.0, 2.0)
    assert (loiter.param1, loiter.x, loiter.y) == (3.0, 0, 0)  # 0, 0: where it is
    assert wp2.z == 12.5
    assert all(i.mission_type == 0 and i.autocontinue == 1 for i in items)
    assert (land.x, land.y) == (0, 0)
    names = emu.names_received()
    assert names.count("MISSION_COUNT") == 1
    assert names.count("MISSION_ITEM_INT") == len(MISSION) + 1
    assert "MISSION_ITEM" not in names  # never the float form


def test_upload_answers_the_legacy_mission_request_with_mission_item_int(
    emu: MavEmu, driver: MavlinkDriver
) -> None:
    emu.legacy_requests = True
    driver.upload_mission(MISSION[:1])
    assert "MISSION_REQUEST" in emu.names_sent()
    assert [m.command for m in emu.mission] == [mav.MAV_CMD_NAV_WAYPOINT, mav.MAV_CMD_NAV_TAKEOFF]


def test_a_lost_request_makes_the_driver_resend_its_last_message(
    emu: MavEmu, driver: MavlinkDriver
) -> None:
    emu.drop_request = {0, 3}  # the first answer to MISSION_COUNT, and a request mid-way
    driver.upload_mission(MISSION)
    names = emu.names_received()
    assert names.count("MISSION_COUNT") == 2  # resent when no request came
    assert names.count("MISSION_ITEM_INT") == len(MISSION) + 2  # item 2 went twice
    assert len(emu.mission) == len(MISSION) + 1


def test_a_lost_item_and_a_duplicated_request_still_upload_the_mission_once(
    emu: MavEmu, driver: MavlinkDriver
) -> None:
    emu.ignore_item = {2}
    emu.double_request = {4}
    emu.nack_stray = True  # ArduPilot acks a stray copy MAV_MISSION_INVALID_SEQUENCE
    driver.upload_mission(MISSION)
    assert [m.seq for m in emu.mission] == list(range(len(MISSION) + 1))
    assert emu.names_received().count("MISSION_ITEM_INT") > len(MISSION) + 1


def test_a_refused_upload_names_the_mission_result(emu: MavEmu, driver: MavlinkDriver) -> None:
    emu.refuse_count = mav.MAV_MISSION_NO_SPACE
    with pytest.raises(MavlinkMissionError, match="MAV_MISSION_NO_SPACE") as err:
        driver.upload_mission(MISSION)
    assert err.value.result == mav.MAV_MISSION_NO_SPACE
    emu.refuse_count = None
    emu.refuse_item = (3, mav.MAV_MISSION_UNSUPPORTED_FRAME)
    with pytest.raises(MavlinkMissionError, match=r"item 3: MAV_MISSION_UNSUPPORTED_FRAME"):
        driver.upload_mission(MISSION)


def test_an_unanswered_step_times_out_naming_it(emu: MavEmu, driver: MavlinkDriver) -> None:
    emu.silent = {"MISSION_COUNT"}
    with pytest.raises(DriverTimeoutError, match=r"MISSION_REQUEST for item 0.*4 tries of 0.1 s"):
        driver.upload_mission(MISSION)
    assert emu.names_received().count("MISSION_COUNT") == 4  # 1 + mission_retries
    emu.silent = {"MISSION_ITEM_INT"}  # it asks for item 0, then hears no item
    with pytest.raises(DriverTimeoutError, match="MISSION_REQUEST for item 1"):
        driver.upload_mission(MISSION)


def test_the_last_step_waits_for_the_ack(emu: MavEmu, driver: MavlinkDriver) -> None:
    original = emu._ack

    def no_accept(result: int) -> None:
        if result != mav.MAV_MISSION_ACCEPTED:
            original(result)

    emu._ack = no_accept  # type: ignore[method-assign]
    with pytest.raises(DriverTimeoutError, match="MISSION_ACK after the last item"):
        driver.upload_mission(MISSION[:2])


def test_bad_missions_are_refused_before_anything_is_sent(
    emu: MavEmu, driver: MavlinkDriver
) -> None:
    with pytest.raises(ValueError, match="at least one item"):
        driver.upload_mission([])
    with pytest.raises(ValueError, match="item 2 is not a MissionItem"):
        driver.upload_mission([MissionItem.takeoff(5), (LAT, LON, 5)])  # type: ignore[list-item]
    assert "MISSION_COUNT" not in emu.names_received()


# ---- download, clear, start, progress ------------------------------------------------------------


def test_download_returns_what_was_uploaded_and_acks_the_transfer(
    emu: MavEmu, driver: MavlinkDriver
) -> None:
    driver.upload_mission(MISSION)
    emu.drop_download_item = {2}  # one answer lost: asked again
    assert driver.download_mission() == MISSION
    _wait_for(lambda: emu.names_received()[-1] == "MISSION_ACK")  # the transfer's end
    assert emu.names_received().count("MISSION_REQUEST_INT") == len(MISSION) + 2


def test_download_of_no_answer_times_out_naming_the_step(
    emu: MavEmu, driver: MavlinkDriver
) -> None:
    emu.silent = {"MISSION_REQUEST_LIST"}
    with pytest.raises(DriverTimeoutError, match="no MISSION_COUNT in 4 tries"):
        driver.download_mission()


def test_clear_deletes_the_mission(emu: MavEmu, driver: MavlinkDriver) -> None:
    driver.upload_mission(MISSION)
    driver.clear_mission()
    assert emu.mission == []
    assert driver.download_mission() == []
    emu.silent = {"MISSION_CLEAR_ALL"}
    with pytest.raises(DriverTimeoutError, match="MISSION_ACK to MISSION_CLEAR_ALL"):
        driver.clear_mission()


def test_start_from_the_ground_arms_in_guided_then_starts_the_mission(
    emu: MavEmu, driver: MavlinkDriver
) -> None:
    driver.upload_mission(MISSION)
    seen: list[MissionProgress] = []
    got = threading.Event()

    def listener(progress: MissionProgress) -> None:
        seen.append(progress)
        got.set()

    driver.add_mission_listener(listener)
    driver.start_mission()
    commands = [m.command for m in emu.received if m.get_type() == "COMMAND_LONG"]
    assert commands[-3:] == [
        mav.MAV_CMD_DO_SET_MODE,
        mav.MAV_CMD_COMPONENT_ARM_DISARM,
        mav.MAV_CMD_MISSION_START,
    ]
    assert [m.param2 for m in emu.received if m.get_type() == "COMMAND_LONG"][-3] == GUIDED
    assert emu.mode == AUTO
    assert emu.armed
    assert got.wait(2.0)
    assert driver.mission_progress == MissionProgress(current=1, total=len(MISSION))
    got.clear()
    emu.reached(1)
    emu.current(2)
    assert got.wait(2.0)
    emu.reached(len(MISSION))
    _wait_for(lambda: driver.mission_progress.finished)
    assert driver.mission_progress.reached == len(MISSION)
    assert seen[-1].finished


def test_start_when_armed_sends_mission_start_alone_and_a_refusal_is_typed(
    emu: MavEmu, driver: MavlinkDriver
) -> None:
    with pytest.raises(MavlinkCommandError, match="MAV_CMD_MISSION_START refused"):
        driver.start_mission()  # no mission on the vehicle: FAILED
    driver.upload_mission(MISSION)
    before = len([m for m in emu.received if m.get_type() == "COMMAND_LONG"])
    driver.start_mission()
    commands = [m.command for m in emu.received if m.get_type() == "COMMAND_LONG"][before:]
    assert commands == [mav.MAV_CMD_MISSION_START]


def test_progress_of_a_mission_another_station_uploaded_takes_its_total_from_the_vehicle(
    emu: MavEmu, driver: MavlinkDriver
) -> None:
    emu.load(3)
    driver.start_mission()
    _wait_for(lambda: driver.mission_progress.current == 1)
    assert driver.mission_progress.total == 3  # MISSION_CURRENT.total leaves home out
    emu.current(3, mav.MISSION_STATE_COMPLETE)
    _wait_for(lambda: driver.mission_progress.finished)


def test_the_driver_is_a_mission_vehicle_and_needs_a_link() -> None:
    drv = MavlinkDriver("quad", link="udpout:127.0.0.1:9", clock=MonotonicClock())
    assert isinstance(drv, MissionVehicle)
    with pytest.raises(StateError, match="upload_mission needs a configured driver"):
        drv.upload_mission(MISSION)
    with pytest.raises(StateError, match="get_param"):
        drv.get_param("RTL_ALT")


# ---- parameters ------------------------------------------------------------------------------


def test_get_param_types_the_value_by_its_param_type(emu: MavEmu, driver: MavlinkDriver) -> None:
    rtl = driver.get_param("RTL_ALT")
    assert rtl == 1500
    assert isinstance(rtl, int)
    speed = driver.get_param("WPNAV_SPEED")
    assert speed == 500.0
    assert isinstance(speed, float)


def test_get_param_retries_and_times_out_naming_the_parameter(
    emu: MavEmu, driver: MavlinkDriver
) -> None:
    emu.drop_param = {"RTL_ALT"}
    assert driver.get_param("RTL_ALT") == 1500
    assert emu.names_received().count("PARAM_REQUEST_READ") == 2
    with pytest.raises(DriverTimeoutError, match=r"no PARAM_VALUE for NO_SUCH_PARAM in 3 tries"):
        driver.get_param("NO_SUCH_PARAM")


def test_a_param_error_answer_ends_the_exchange_naming_it(
    emu: MavEmu, driver: MavlinkDriver
) -> None:
    emu.param_errors = True  # as newer ArduPilot answers a name it does not have
    with pytest.raises(DriverOperationError, match="MAV_PARAM_ERROR_DOES_NOT_EXIST"):
        driver.get_param("NO_SUCH_PARAM")
    time_for_retries = threading.Event()
    time_for_retries.wait(0.3)  # longer than the retries would take (3 x 0.1 s)
    assert emu.names_received().count("PARAM_REQUEST_READ") == 1  # no retries: it answered
    with pytest.raises(DriverOperationError, match=r"reading NO_SUCH_PARAM: .*DOES_NOT_EXIST"):
        driver.set_param("NO_SUCH_PARAM", 2)


def test_set_param_checks_the_echo(emu: MavEmu, driver: MavlinkDriver) -> None:
    assert driver.set_param("WPNAV_SPEED", 750.5) == 750.5
    assert emu.params["WPNAV_SPEED"][0] == 750.5
    emu.drop_param = {"RTL_ALT"}  # the first read goes unanswered: read again
    assert driver.set_param("RTL_ALT", 2500) == 2500
    assert emu.params["RTL_ALT"] == (2500.0, mav.MAV_PARAM_TYPE_INT32)
    emu.drop_param = {"RTL_ALT"}  # known now: the PARAM_SET itself is resent
    assert driver.set_param("RTL_ALT", 3000) == 3000
    assert emu.names_received().count("PARAM_SET") == 4  # 1 + 1 + 2 (one echo lost)
    emu.param_clamp["WPNAV_SPEED"] = 2000.0
    with pytest.raises(DriverOperationError, match="kept WPNAV_SPEED = 2000"):
        driver.set_param("WPNAV_SPEED", 3000.0)


def test_set_param_refuses_values_its_type_cannot_hold(emu: MavEmu, driver: MavlinkDriver) -> None:
    with pytest.raises(ValueError, match="FS_GCS_ENABLE is an integer"):
        driver.set_param("FS_GCS_ENABLE", 1.5)
    with pytest.raises(ValueError, match=r"\(MAV_PARAM_TYPE_INT8\) must be -128..127"):
        driver.set_param("FS_GCS_ENABLE", 300)
    with pytest.raises(ValueError, match="float32 encoding"):
        driver.set_param("ARMING_CHECK", (1 << 24) + 1)
    with pytest.raises(ValueError, match=r"1\.\.16 ASCII characters"):
        driver.set_param("A_NAME_FAR_TOO_LONG", 1)
    with pytest.raises(ValueError, match="must be finite"):
        driver.set_param("WPNAV_SPEED", float("nan"))
    assert "PARAM_SET" not in emu.names_received()
    with pytest.raises(DriverTimeoutError, match="NO_SUCH_PARAM"):
        driver.set_param("NO_SUCH_PARAM", 1)


# ---- profile ---------------------------------------------------------------------------------


def test_mission_timeout_and_retries_come_from_the_profile() -> None:
    drv = MavlinkDriver.from_profile(
        "quad",
        {"link": "udpin:127.0.0.1:14550", "mission_timeout": 2.5, "mission_retries": 2},
        clock=MonotonicClock(),
        where="q.yaml: devices.quad",
    )
    assert (drv.mission_timeout, drv.mission_retries) == (2.5, 2)
    with pytest.raises(ProfileError, match=r"devices.quad.mission_retries: must be an integer"):
        MavlinkDriver.from_profile(
            "quad",
            {"link": "udpin:127.0.0.1:14550", "mission_retries": 1.5},
            clock=MonotonicClock(),
            where="q.yaml: devices.quad",
        )
    with pytest.raises(ProfileError, match=r"devices.quad.mission_timeout: .*positive"):
        MavlinkDriver.from_profile(
            "quad",
            {"link": "udpin:127.0.0.1:14550", "mission_timeout": 0},
            clock=MonotonicClock(),
            where="q.yaml: devices.quad",
        )


# ---- MissionItem -----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("build", "message"),
    [
        (lambda: MissionItem("hover"), "kind must be one of"),
        (lambda: MissionItem.takeoff(0), "takeoff item: alt must be positive"),
        (lambda: MissionItem.waypoint(91, LON, 5), "out of range"),
        (lambda: MissionItem.waypoint(0, 0, 5), "leave lat and lon None"),
        (lambda: MissionItem("waypoint", LAT, None, 5.0), "both lat and lon"),
        (lambda: MissionItem.waypoint(LAT, LON, float("inf")), "alt must be a finite"),
        (lambda: MissionItem.loiter_time(0), "seconds must be positive"),
        (lambda: MissionItem.change_speed(-1), "speed must be positive"),
        (lambda: MissionItem("rtl", alt=5.0), "rtl item: has no position"),
    ],
)
def test_mission_items_refuse_bad_values(build: object, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        build()  # type: ignore[operator]


def _wait_for(pred: object, seconds: float = 2.0) -> None:
    done = threading.Event()
    for _ in range(int(seconds / 0.01)):
        if pred():  # type: ignore[operator]
            return
        done.wait(0.01)
    raise AssertionError("not within the time")
