"""The time estimates behind the robot actions' deadlines, against their formulas.

No robot: the controllers get stand-in devices that report a fixed state.
"""

from __future__ import annotations

import math

import pytest

from temoto.config import ArmFeature, DriveFeature, FlightFeature
from temoto.drivers import GeoPoint, JointState, JointStates, MissionItem, VehicleTelemetry
from temoto.managers.robot.features import ArmController, DriveController, FlightController

HOME = GeoPoint(47.397742, 8.545594, 0.0)
METRE_LAT = 1 / 111_194.93  # degrees of latitude per metre (mean Earth radius 6,371 km)


class _Joints:
    """An actuator standing still at the given positions."""

    def __init__(self, positions: dict[str, float]) -> None:
        self.positions = positions

    def read_state(self) -> JointStates:
        joints = {j: JointState(j, p, 0.0, 0.0, 0.0) for j, p in self.positions.items()}
        return JointStates(0.0, joints)


class _Vehicle:
    """A vehicle at ``position``; its parameters answer ``params`` (others: no answer)."""

    name = "quad"

    def __init__(self, position: GeoPoint, params: dict[str, float] | None = None) -> None:
        self.position = position
        self.params = params or {}

    def telemetry(self) -> VehicleTelemetry:
        return VehicleTelemetry(0.0, True, "GUIDED", self.position, (0, 0, 0), 12.0, 90, (), 0.1)

    def get_param(self, name: str) -> float:
        if name not in self.params:
            raise TimeoutError(f"no PARAM_VALUE for {name}")
        return self.params[name]

    def home(self) -> GeoPoint:
        return HOME


def test_the_drive_estimate_is_turn_distance_and_approach() -> None:
    feature = DriveFeature("lw", "rw", 0.08, 0.42, max_speed=1.0, max_turn_rate=2.0)
    wheels = _Joints({"lw": 0.0, "rw": 0.0})
    drive = DriveController(feature, (wheels, wheels))  # type: ignore[arg-type]
    approach = math.log((1.0 / DriveController.K_LINEAR) / 0.05) / DriveController.K_LINEAR
    assert drive.estimate(2.0, 0.0) == pytest.approx(2.0 + approach)
    # behind it: a half turn first; then a quarter turn to the goal's yaw
    assert drive.estimate(-2.0, 0.0, math.pi / 2) == pytest.approx(
        math.pi / 2.0 + 2.0 + approach + (math.pi / 2) / 2.0
    )


def test_the_arm_estimate_is_the_slowest_joints_travel() -> None:
    feature = ArmFeature("arm", ("a", "b"))
    arm = ArmController(feature, _Joints({"a": 0.0, "b": 0.5}), {"b": 0.25})  # type: ignore[arg-type]
    # a: 0.8 rad at the default 1 rad/s; b: 0.5 rad at 0.25 rad/s
    assert arm.estimate({"a": 0.8, "b": 0.0}) == pytest.approx(2.0)


def test_the_flight_estimates_use_the_vehicles_speeds_or_arducopters_defaults() -> None:
    vehicle = _Vehicle(GeoPoint(HOME.lat, HOME.lon, 20.0), {"WPNAV_SPEED": 500.0})
    flight = FlightController(FlightFeature("quad"), vehicle)  # type: ignore[arg-type]
    far = GeoPoint(HOME.lat + 1000 * METRE_LAT, HOME.lon, 20.0)
    assert flight.estimate_fly_to(far) == pytest.approx(1000 / 5.0, rel=1e-3)  # its 5 m/s
    # above LAND_ALT_LOW (10 m) at WPNAV_SPEED_DN 1.5 m/s, then LAND_SPEED 0.5 m/s
    assert flight.estimate_land() == pytest.approx(10 / 1.5 + 10 / 0.5)
    assert flight.estimate_takeoff(30.0) == pytest.approx(10 / 2.5)  # WPNAV_SPEED_UP 2.5 m/s


def test_a_missions_estimate_adds_its_legs_holds_and_landing() -> None:
    vehicle = _Vehicle(HOME)
    flight = FlightController(FlightFeature("quad"), vehicle)  # type: ignore[arg-type]
    mission = [
        MissionItem.takeoff(10.0),
        MissionItem.change_speed(4.0),
        MissionItem.waypoint(HOME.lat + 400 * METRE_LAT, HOME.lon, 10.0, hold=3.0),
        MissionItem.land(),
    ]
    expected = 10 / 2.5 + 400 / 4.0 + 3.0 + 10 / 0.5
    assert flight.estimate_mission(mission) == pytest.approx(expected, rel=1e-3)
