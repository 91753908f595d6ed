"""The simulated ArduCopter where it used to differ from ArduPilot, each case from its source.

The vehicle's parts are driven directly on a manual clock (no socket, no threads); the sources
are named per test (ArduPilot master: ``AP_Mission``, ``ArduCopter/mode_auto.cpp``,
``AP_Param::set_float``, ``GCS_MAVLink/MissionItemProtocol*.cpp``, ``AC_Fence``).
"""

from __future__ import annotations

import itertools
import math
from typing import Any

import pytest

from temoto.clock import ManualClock
from temoto.drivers.mavlink import protocol as p
from temoto.drivers.mavlink.protocol import Codec
from temoto.drivers.mavlink.sim import SimVehicle
from temoto.drivers.mavlink.sim_mission import UPLOAD_TIMEOUT, MissionItem, MissionService

GCS = Codec(255, 190)
VEHICLE = Codec(1, 1)
TAKEOFF, WAYPOINT, LAND = p.MAV_CMD_NAV_TAKEOFF, p.MAV_CMD_NAV_WAYPOINT, p.MAV_CMD_NAV_LAND


def _decode(frames: list[bytes]) -> list[Any]:
    return [m for f in frames for m in GCS.decode_datagram(f)]


def _msg(name: str, **fields: Any) -> Any:
    (msg,) = VEHICLE.decode_datagram(GCS.encode(name, **fields))
    return msg


def _item(seq: int, command: int = WAYPOINT, north_m: float = 0.0, alt: float = 10.0) -> Any:
    return _msg(
        "MISSION_ITEM_INT",
        target_system=1,
        target_component=1,
        seq=seq,
        frame=p.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
        command=command,
        current=0,
        autocontinue=1,
        param1=0.0,
        param2=0.0,
        param3=0.0,
        param4=0.0,
        x=p.deg_e7(47.397742 + north_m / 111_320.0),
        y=p.deg_e7(8.545594),
        z=alt,
    )


def _count(n: int, kind: int = p.MAV_MISSION_TYPE_MISSION) -> Any:
    return _msg("MISSION_COUNT", target_system=1, target_component=1, count=n, mission_type=kind)


def _command(cmd: int, *params: float) -> Any:
    values = [*params, *([0.0] * (7 - len(params)))]
    return _msg(
        "COMMAND_LONG",
        target_system=1,
        target_component=1,
        command=cmd,
        confirmation=0,
        **{f"param{i + 1}": v for i, v in enumerate(values)},
    )


def _vehicle(**params: float) -> SimVehicle:
    return SimVehicle("ap", clock=ManualClock(), params=params)


def _handle(vehicle: SimVehicle, msg: Any) -> list[Any]:
    return _decode(vehicle.commands.handle(msg))


def _run(vehicle: SimVehicle, seconds: float) -> None:
    with vehicle.state.lock:
        vehicle.flight.advance(vehicle.state.last + seconds)


def _upload(vehicle: SimVehicle, items: list[tuple[int, float, float]]) -> None:
    """Upload (command, north m, alt) items after home; asserts the final ACK."""
    _handle(vehicle, _count(len(items) + 1))
    replies: list[Any] = []
    for seq, (command, north, alt) in enumerate([(WAYPOINT, 0.0, 0.0), *items]):
        replies = _handle(vehicle, _item(seq, command, north, alt))
    assert replies[-1].name == "MISSION_ACK"
    assert replies[-1].get_int("type") == p.MAV_MISSION_ACCEPTED


def _mode(vehicle: SimVehicle, mode: str) -> None:
    (ack,) = _handle(vehicle, _command(p.MAV_CMD_DO_SET_MODE, 1, p.COPTER_MODES[mode]))[:1]
    assert ack.get_int("result") == p.MAV_RESULT_ACCEPTED, mode


def _arm(vehicle: SimVehicle) -> None:
    (ack,) = _handle(vehicle, _command(p.MAV_CMD_COMPONENT_ARM_DISARM, 1))[:1]
    assert ack.get_int("result") == p.MAV_RESULT_ACCEPTED


MISSION = [(TAKEOFF, 0.0, 10.0), (WAYPOINT, 30.0, 10.0), (WAYPOINT, 60.0, 10.0), (LAND, 60.0, 0.0)]


# ---- AP_Mission::clear: refused while the mission runs


def test_clear_all_during_a_running_mission_is_refused_and_the_mission_goes_on() -> None:
    vehicle = _vehicle()
    _upload(vehicle, MISSION)
    _mode(vehicle, "GUIDED")
    _arm(vehicle)
    _handle(vehicle, _command(p.MAV_CMD_MISSION_START))
    _run(vehicle, 8.0)
    assert vehicle.mission_current == 2  # on the way to the first waypoint
    clear = _msg("MISSION_CLEAR_ALL", target_system=1, target_component=1)
    (ack,) = _handle(vehicle, clear)
    assert (ack.name, ack.get_int("type")) == ("MISSION_ACK", p.MAV_MISSION_ERROR)
    assert len(vehicle.mission()) == 5
    _run(vehicle, 10.0)
    assert vehicle.mission_current >= 3  # flew on
    assert vehicle.state.vel != [0.0, 0.0, 0.0]
    _mode(vehicle, "LOITER")  # the mission stops: now it may be cleared
    (ack,) = _handle(vehicle, clear)
    assert ack.get_int("type") == p.MAV_MISSION_ACCEPTED
    assert vehicle.mission() == []


# ---- ModeAuto::takeoff_run: the takeoff waits for the throttle


@pytest.mark.parametrize(
    ("options", "mission_start", "climbs"),
    [(1, False, False), (3, False, True), (1, True, True)],
    ids=["AUTO_OPTIONS-1-waits", "AUTO_OPTIONS-3-climbs", "MISSION_START-climbs"],
)
def test_an_auto_takeoff_waits_for_the_throttle_unless_told(
    options: int, mission_start: bool, climbs: bool
) -> None:
    vehicle = _vehicle(AUTO_OPTIONS=options)
    _upload(vehicle, MISSION)
    _mode(vehicle, "AUTO")
    _arm(vehicle)  # AUTO_OPTIONS bit 0: arming in AUTO allowed
    if mission_start:
        _handle(vehicle, _command(p.MAV_CMD_MISSION_START))
    _run(vehicle, 3.0)
    assert vehicle.armed
    if climbs:
        assert vehicle.position()[2] > 5.0
    else:  # no RC: nobody raises the throttle
        assert vehicle.position()[2] == 0.0
        assert not vehicle.airborne


# ---- AP_Param::set_float: integers get 0.01 away from zero, then are truncated


@pytest.mark.parametrize(
    ("name", "sent", "stored"),
    [
        ("BATT_CAPACITY", 2500.7, 2500.0),  # INT32
        ("RTL_ALT_FINAL", -3.7, -3.0),  # INT16, negative: truncated toward zero
        ("RTL_ALT_FINAL", 2.995, 3.0),  # the 0.01 lifts it over the integer
        ("FS_GCS_ENABLE", 4.98, 4.0),  # INT8
        ("FS_GCS_ENABLE", 300.0, 127.0),  # clamped to the type
    ],
)
def test_integer_parameters_are_stored_as_ap_param_does(
    name: str, sent: float, stored: float
) -> None:
    vehicle = _vehicle()
    ptype = vehicle.state.ptypes[name]
    (value,) = _handle(
        vehicle,
        _msg(
            "PARAM_SET",
            target_system=1,
            target_component=1,
            param_id=name.encode(),
            param_value=sent,
            param_type=ptype,
        ),
    )
    assert value.get_float("param_value") == stored
    assert vehicle.param(name) == stored


# ---- MissionItemProtocol: uploads and downloads


def _home() -> MissionItem:
    return MissionItem(0, p.MAV_FRAME_GLOBAL, 16, 0, 1, 0, 0, 0, 0, 473977420, 85455940, 488.0)


@pytest.fixture
def service() -> MissionService:
    return MissionService(VEHICLE.encode, _home)


def _names(frames: list[bytes]) -> list[tuple[str, Any]]:
    out = []
    for m in _decode(frames):
        if m.name == "MISSION_ACK":
            out.append((m.name, m.get_int("type")))
        elif m.name == "STATUSTEXT":
            out.append((m.name, m.get_text("text")))
        elif m.name == "MISSION_COUNT":
            out.append((m.name, m.get_int("count")))
        else:
            out.append((m.name, m.get_int("seq")))
    return out


def test_a_stray_item_gets_invalid_sequence_and_the_upload_goes_on(
    service: MissionService,
) -> None:
    service.handle(_count(3), 0.0)
    service.handle(_item(0), 0.1)
    assert _names(service.handle(_item(1), 0.2)) == [("MISSION_REQUEST_INT", 2)]
    stray = service.handle(_item(0), 0.3)  # a copy of an earlier item
    assert _names(stray) == [("MISSION_ACK", p.MAV_MISSION_INVALID_SEQUENCE)]
    ahead = service.handle(_item(5), 0.3)
    assert _names(ahead) == [("MISSION_ACK", p.MAV_MISSION_INVALID_SEQUENCE)]
    assert service.uploading
    # MissionItemProtocol_Waypoints::complete: the text, then the ACK
    assert _names(service.handle(_item(2), 0.4)) == [
        ("STATUSTEXT", "Flight plan received"),
        ("MISSION_ACK", p.MAV_MISSION_ACCEPTED),
    ]
    assert service.count() == 3


def test_a_request_past_the_end_gets_the_count_then_an_error(service: MissionService) -> None:
    service.handle(_count(2), 0.0)
    service.handle(_item(0), 0.0)
    service.handle(_item(1), 0.0)
    request = _msg("MISSION_REQUEST_INT", target_system=1, target_component=1, seq=5)
    assert _names(service.handle(request, 1.0)) == [
        ("MISSION_COUNT", 2),
        ("MISSION_ACK", p.MAV_MISSION_ERROR),
    ]


def test_a_cancelled_upload_leaves_what_it_wrote_over_the_truncated_old_plan(
    service: MissionService,
) -> None:
    service.handle(_count(5), 0.0)
    for seq in range(5):
        service.handle(_item(seq, alt=10.0), 0.0)
    assert service.count() == 5
    service.handle(_count(4), 1.0)  # truncated at once to the new count
    assert service.count() == 4
    service.handle(_item(0, alt=20.0), 1.0)
    service.handle(_item(1, alt=20.0), 1.0)
    frames = service.tick(1.0 + UPLOAD_TIMEOUT + 0.1)
    assert _names(frames) == [
        ("STATUSTEXT", "Mission upload timeout"),
        ("MISSION_ACK", p.MAV_MISSION_OPERATION_CANCELLED),
    ]
    assert [item.z for item in service.items] == [20.0, 20.0, 10.0, 10.0]


# ---- SYS_STATUS: the geofence as AC_Fence reports it


def _sys_status(vehicle: SimVehicle) -> Any:
    with vehicle.state.lock:
        return _decode([vehicle.telemetry.frame("SYS_STATUS", 0.0)])[0]


def test_sys_status_reports_the_fence_present_disabled_and_healthy() -> None:
    fence = p.MAV_SYS_STATUS_GEOFENCE
    status = _sys_status(_vehicle())
    assert status.get_int("onboard_control_sensors_present") & fence
    assert not status.get_int("onboard_control_sensors_enabled") & fence
    assert status.get_int("onboard_control_sensors_health") & fence
    assert _sys_status(_vehicle(FENCE_ENABLE=1)).get_int("onboard_control_sensors_enabled") & fence
    assert (
        not _sys_status(_vehicle(FENCE_TYPE=0)).get_int("onboard_control_sensors_present") & fence
    )


# ---- ArduCopter's defaults


def test_navigation_defaults_are_arducopters() -> None:
    vehicle = SimVehicle("defaults", clock=ManualClock())
    assert vehicle.param("WPNAV_SPEED") == 1000.0
    assert vehicle.param("WPNAV_SPEED_UP") == 250.0
    assert vehicle.param("WPNAV_SPEED_DN") == 150.0
    assert vehicle.param("LAND_SPEED") == 50.0


# ---- ANGLE_MAX: the lean angle limits the attitude and so the acceleration


@pytest.mark.parametrize("angle_max", [1000, 3000])
def test_angle_max_bounds_the_lean_and_the_acceleration(angle_max: int) -> None:
    vehicle = _vehicle(ANGLE_MAX=angle_max)
    lean = math.radians(angle_max / 100.0)
    accel = 9.80665 * math.tan(lean)  # what the lean can give: g·tan(angle)
    _mode(vehicle, "GUIDED")
    _arm(vehicle)
    _handle(vehicle, _command(p.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 10))
    _run(vehicle, 15.0)
    lat, lon, _ = vehicle.position()
    _handle(vehicle, _command(p.MAV_CMD_DO_REPOSITION, -1, 0, 0, 0, lat + 0.001, lon, 498.0))
    speeds, pitches = [], []
    for _ in range(200):  # 20 s in 0.1 s steps: speed up, cruise, brake, arrive
        _run(vehicle, 0.1)
        with vehicle.state.lock:
            speeds.append(math.hypot(*vehicle.state.vel[:2]))
            pitches.append(_decode([vehicle.telemetry.frame("ATTITUDE", 0.0)])[0])
    assert speeds[9] <= accel * 1.0 + 1e-6  # 1 s after the start
    changes = [abs(b - a) / 0.1 for a, b in itertools.pairwise(speeds)]
    assert max(changes) <= accel + 1e-6
    assert max(abs(m.get_float("pitch")) for m in pitches) <= lean + 1e-6
    assert max(abs(m.get_float("pitch")) for m in pitches) > 0.5 * lean  # it does lean
    north = math.radians(vehicle.position()[0] - lat) * 6_378_137.0
    assert north == pytest.approx(111.3, abs=0.5)  # arrived, no overshoot


# ---- wind (ArduPilot SITL's SIM_WIND_SPD, SIM_WIND_DIR: the direction it comes from)


def _hover_in_wind(speed: float, seconds: float, **params: float) -> tuple[float, float, Any]:
    """Take off to 10 m in GUIDED, let ``speed`` m/s blow from the north: the drift north, east
    (m from where it hovered) and the last ATTITUDE."""
    vehicle = _vehicle(**params)
    _mode(vehicle, "GUIDED")
    _arm(vehicle)
    _handle(vehicle, _command(p.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 10))
    _run(vehicle, 15.0)
    start = list(vehicle.pos)
    vehicle.state.params["SIM_WIND_SPD"] = speed
    vehicle.state.params["SIM_WIND_DIR"] = 0.0  # from the north: it pushes south
    _run(vehicle, seconds)
    with vehicle.state.lock:
        attitude = _decode([vehicle.telemetry.frame("ATTITUDE", 0.0)])[0]
    return vehicle.pos[0] - start[0], vehicle.pos[1] - start[1], attitude


def test_wind_params_are_sitls_and_still_by_default() -> None:
    vehicle = SimVehicle("wind", clock=ManualClock())
    assert vehicle.param("SIM_WIND_SPD") == 0.0
    assert vehicle.param("SIM_WIND_DIR") == 180.0  # SITL's default


def test_wind_below_the_lean_limit_is_countered() -> None:
    # 10 m/s needs 0.025·100 = 2.5 m/s² of lean (14°), within ANGLE_MAX 30° (5.66 m/s²)
    north, east, attitude = _hover_in_wind(10.0, 30.0)
    assert math.hypot(north, east) < 1.0  # pushed a little, then held
    assert attitude.get_float("pitch") == pytest.approx(-math.atan(2.5 / 9.80665), abs=0.02)


def test_wind_above_the_lean_limit_drifts_the_vehicle() -> None:
    # 10 m/s with ANGLE_MAX 10° (1.73 m/s²): the wind wins; the drift settles where the
    # airspeed's drag equals the lean: 10 - sqrt(1.73/0.025) = 1.68 m/s downwind (south)
    north, east, attitude = _hover_in_wind(10.0, 30.0, ANGLE_MAX=1000)
    assert north < -30.0
    assert abs(east) < 1e-6
    assert abs(attitude.get_float("pitch")) == pytest.approx(math.radians(10.0), abs=1e-3)
