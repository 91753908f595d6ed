"""An independent MAVLink client, MAVSDK (the 4.x wheel embeds the C++ core), flies SimVehicle.

MAVSDK listens (``udpin://127.0.0.1:<port>``, as it does on 14540) and the simulated vehicle
streams to it; arm, takeoff, goto and land go through MAVSDK's Action plugin and positions are
read back through its Telemetry plugin. Real time (MAVSDK's timeouts are real): about 10 s.
"""

from __future__ import annotations

import math
import socket
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest

from temoto.clock import MonotonicClock
from temoto.drivers.mavlink import SimVehicle

mavsdk = pytest.importorskip("mavsdk")
from mavsdk.plugins.action import Action  # noqa: E402
from mavsdk.plugins.telemetry import Telemetry  # noqa: E402

HOME = (47.397742, 8.545594, 488.0)

pytestmark = pytest.mark.slow


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _until(pred: Callable[[], bool], seconds: float, what: str) -> None:
    deadline = time.monotonic() + seconds
    while not pred():
        assert time.monotonic() < deadline, f"{what}: not within {seconds} s"
        time.sleep(0.05)


@pytest.fixture
def flight() -> Iterator[tuple[SimVehicle, Any]]:
    port = _free_port()
    sim = SimVehicle(
        "mavsdk-quad",
        clock=MonotonicClock(),
        gcs=[("127.0.0.1", port)],
        home=HOME,
        speed=10.0,
        climb_rate=5.0,
        descent_rate=4.0,
        tau=0.4,
        params={"LAND_SPEED": 400},  # ArduCopter's 50 cm/s is too slow for a real-time test
    )
    mavsdk.log_subscribe(lambda level, message, file, line: True)  # keep MAVSDK quiet
    client = mavsdk.Mavsdk(
        mavsdk.Configuration.create_with_component_type(mavsdk.ComponentType.GROUND_STATION)
    )
    sim.start()
    try:
        assert client.add_any_connection(f"udpin://127.0.0.1:{port}") == (
            mavsdk.ConnectionResult.SUCCESS
        )
        system = client.first_autopilot(5.0)
        assert system is not None, "MAVSDK did not discover the simulated autopilot"
        yield sim, system
    finally:
        client.destroy()
        mavsdk.log_unsubscribe()
        sim.close()


def test_mavsdk_arms_takes_off_flies_to_a_point_and_lands(
    flight: tuple[SimVehicle, Any],
) -> None:
    sim, system = flight
    action, telemetry = Action(system), Telemetry(system)
    assert system.has_autopilot()
    action.arm()
    _until(telemetry.armed, 3.0, "armed")
    assert sim.armed

    action.set_takeoff_altitude(5.0)
    action.takeoff()
    _until(lambda: telemetry.position().relative_altitude_m > 4.7, 8.0, "takeoff")
    assert sim.mode == "GUIDED"

    lat, lon = HOME[0] + 0.0002, HOME[1] + 0.0002  # ~27 m north-east
    action.goto_location(lat, lon, HOME[2] + 8.0, 0.0)
    _until(lambda: _distance(sim.position(), (lat, lon, 8.0)) < 0.5, 10.0, "goto")

    def seen_there() -> bool:  # MAVSDK's own view of where the vehicle is
        pos = telemetry.position()
        return (
            _distance(
                (pos.latitude_deg, pos.longitude_deg, pos.relative_altitude_m), (lat, lon, 8.0)
            )
            < 0.6
        )

    _until(seen_there, 3.0, "goto seen by MAVSDK")
    assert math.isclose(telemetry.position().absolute_altitude_m, HOME[2] + 8.0, abs_tol=0.6)

    action.land()
    _until(lambda: not telemetry.armed(), 8.0, "landed and disarmed")
    assert sim.position()[2] == 0.0
    assert sim.mode == "LAND"
    for command in (400, 176, 22, 192, 21):  # arm, mode, takeoff, reposition, land: accepted
        assert (command, 0) in sim.acks


def _distance(a: tuple[float, float, float], b: tuple[float, float, float]) -> float:
    north = math.radians(a[0] - b[0]) * 6_378_137.0
    east = math.radians(a[1] - b[1]) * 6_378_137.0 * math.cos(math.radians(b[0]))
    return math.sqrt(north**2 + east**2 + (a[2] - b[2]) ** 2)
