"""The flight controller tells the modes it commanded from the vehicle's own, whatever the timing.

No robot: the controller gets a vehicle whose HEARTBEAT the test delivers by hand. As on
ArduCopter, a ``MAV_CMD_DO_SET_MODE`` is acknowledged at once and the new mode shows in the
telemetry only with the next HEARTBEAT (up to a second later); the control thread's step reads
the telemetry between its two turns of the controller's lock, so a stop, pause or resume may
come between that reading and its check. The test drives each interleaving by calling
``step`` itself (virtual time: no threads, no sleeps).
"""

from __future__ import annotations

from collections.abc import Callable

import pytest

from temoto.config import FlightFeature
from temoto.drivers import GeoPoint, VehicleTelemetry
from temoto.drivers.mavlink import ModeChange
from temoto.errors import DriverTimeoutError, StateError
from temoto.managers.robot.flight import FlightController
from temoto.managers.robot.motion import Motion

HOME = GeoPoint(47.397742, 8.545594, 5.0)
FAR = GeoPoint(47.397742 + 2000 / 111_195.0, 8.545594, 5.0)
DT = 0.02


class _Vehicle:
    """A flying vehicle: modes asked are acknowledged at once, shown at the next :meth:`beat`."""

    name = "quad"

    def __init__(self) -> None:
        self.shown = "GUIDED"  # what the newest HEARTBEAT said
        self.mode = "GUIDED"  # what the autopilot is in
        self.asked: list[str] = []
        self.lose_acks = False  # the mode changes, its COMMAND_ACK is lost
        self.on_telemetry: Callable[[], None] | None = None  # runs inside step's reading

    def beat(self) -> None:
        """The next HEARTBEAT arrives."""
        self.shown = self.mode

    def switch(self, mode: str) -> None:
        """The vehicle changes mode by itself (a failsafe, the pilot): shown at once."""
        self.mode = self.shown = mode

    def telemetry(self) -> VehicleTelemetry:
        shown = self.shown  # the reading is taken first ...
        hook, self.on_telemetry = self.on_telemetry, None
        if hook is not None:
            hook()  # ... and another thread's stop, pause or resume comes before the check
        return VehicleTelemetry(0.0, True, shown, HOME, (0, 0, 0), 12.0, 90, (), 0.1)

    def set_mode(self, mode: str) -> None:
        self.asked.append(mode)
        self.mode = mode
        if self.lose_acks:
            raise DriverTimeoutError(f"quad: no COMMAND_ACK for DO_SET_MODE {mode}")

    def goto(self, target: GeoPoint) -> None:
        self.mode = "GUIDED"


@pytest.fixture
def flight() -> tuple[FlightController, _Vehicle]:
    vehicle = _Vehicle()
    return FlightController(FlightFeature("quad"), vehicle), vehicle  # type: ignore[arg-type]


def _error(motion: object) -> str:
    return str(getattr(motion, "error", None))


def _goes_on(controller: FlightController, motion: Motion) -> None:
    """One step; the flight goes on."""
    controller.step(DT)
    assert not motion.done, _error(motion)


def _its_own_switch_ends(
    controller: FlightController, vehicle: _Vehicle, motion: Motion, mode: str
) -> None:
    """The vehicle switches to ``mode`` by itself: the next step ends the flight, saying so."""
    vehicle.switch(mode)
    controller.step(DT)
    assert f"quad: the vehicle switched to {mode} (not commanded)" in _error(motion)


@pytest.mark.parametrize("lose_acks", [False, True], ids=["acked", "ack-lost"])
def test_a_pause_and_resume_within_a_heartbeat_is_not_the_vehicles_own_switch(
    flight: tuple[FlightController, _Vehicle], lose_acks: bool
) -> None:
    """The LOITER of a pause shows after the resume was acknowledged: still commanded.

    Also when the pause's acknowledgement was lost (the vehicle switched all the same).

    Before: a step between the pause's acknowledgement and its HEARTBEAT took the old GUIDED
    for the mode it had seen, and once resumed the late LOITER was "not commanded".
    """
    controller, vehicle = flight
    vehicle.lose_acks = lose_acks
    motion = controller.fly_to(FAR)
    controller.step(DT)
    motion.hold()  # the pause: LOITER asked (acknowledged, or its ack lost), not shown yet
    assert vehicle.asked == ["LOITER"]
    controller.step(DT)  # the telemetry still says GUIDED
    vehicle.beat()  # LOITER shows
    vehicle.lose_acks = False
    motion.resume()  # GUIDED asked (acknowledged), not shown yet
    _goes_on(controller, motion)
    vehicle.beat()  # GUIDED shows
    _goes_on(controller, motion)
    # now the vehicle's own: a pilot's switch
    _its_own_switch_ends(controller, vehicle, motion, "LOITER")
    assert motion.done


def test_a_pause_between_the_reading_and_the_check_is_not_the_vehicles_own_switch(
    flight: tuple[FlightController, _Vehicle],
) -> None:
    """A pause lands while a step holds a reading from before it (GUIDED); resumed at once."""
    controller, vehicle = flight
    motion = controller.fly_to(FAR)
    controller.step(DT)
    vehicle.on_telemetry = motion.hold
    controller.step(DT)  # read GUIDED; the pause came; checked after
    assert motion.held
    vehicle.beat()  # LOITER shows
    motion.resume()
    _goes_on(controller, motion)  # LOITER, shown late, before the GUIDED of the resume
    vehicle.beat()
    _goes_on(controller, motion)


def test_a_stop_between_the_reading_and_the_check_ends_the_flight_as_stopped(
    flight: tuple[FlightController, _Vehicle],
) -> None:
    """The LOITER a stop commands is never the vehicle's own switch, read before or after."""
    controller, vehicle = flight
    motion = controller.fly_to(FAR)
    controller.step(DT)

    def stop() -> None:
        motion.cancel("stopped")
        vehicle.beat()  # LOITER shows at once

    vehicle.on_telemetry = stop
    controller.step(DT)
    vehicle.beat()
    controller.step(DT)
    assert motion.done
    assert isinstance(motion.error, StateError)
    assert "stopped" in _error(motion)
    assert "not commanded" not in _error(motion)
    assert vehicle.asked == ["LOITER"]


def test_the_vehicles_own_mode_change_still_ends_the_flight(
    flight: tuple[FlightController, _Vehicle],
) -> None:
    controller, vehicle = flight
    motion = controller.fly_to(FAR)
    controller.step(DT)
    motion.hold()
    vehicle.beat()
    motion.resume()
    vehicle.beat()
    controller.step(DT)
    _its_own_switch_ends(controller, vehicle, motion, "RTL")


def test_a_stops_loiter_shown_after_the_next_flight_started_is_not_its_own_switch(
    flight: tuple[FlightController, _Vehicle],
) -> None:
    """Stopped, then a new FlyTo at once: the stop's LOITER shows late, then GUIDED."""
    controller, vehicle = flight
    first = controller.fly_to(FAR)
    controller.step(DT)
    first.cancel("stopped")
    second = controller.fly_to(FAR)  # GUIDED again (goto), the telemetry still GUIDED
    vehicle.mode = "LOITER"  # as the autopilot saw them: LOITER, then GUIDED
    vehicle.beat()
    _goes_on(controller, second)
    vehicle.mode = "GUIDED"
    vehicle.beat()
    _goes_on(controller, second)
    _its_own_switch_ends(controller, vehicle, second, "LOITER")  # the pilot's, now


def test_a_mode_asked_while_the_vehicle_is_in_it_is_not_owed(
    flight: tuple[FlightController, _Vehicle],
) -> None:
    """Paused while already loitering (no change comes): a later own LOITER still counts."""
    controller, vehicle = flight
    vehicle.switch("LOITER")
    motion = controller.fly_to(FAR)  # seen LOITER; goto: GUIDED
    motion.hold()  # LOITER asked while the telemetry shows LOITER: nothing owed
    motion.resume()
    vehicle.beat()  # GUIDED shows
    _goes_on(controller, motion)
    _its_own_switch_ends(controller, vehicle, motion, "LOITER")


def test_a_stops_loiter_shown_before_the_next_flight_is_used_up(
    flight: tuple[FlightController, _Vehicle],
) -> None:
    """The stop's LOITER showed while nothing was stepped: a later own LOITER still counts."""
    controller, vehicle = flight
    first = controller.fly_to(FAR)
    controller.step(DT)
    first.cancel("stopped")
    vehicle.beat()  # LOITER shows; no motion, no step
    second = controller.fly_to(FAR)
    vehicle.beat()  # GUIDED
    _goes_on(controller, second)
    _its_own_switch_ends(controller, vehicle, second, "LOITER")


def test_a_mode_the_driver_commanded_is_not_called_the_vehicles_own(
    flight: tuple[FlightController, _Vehicle],
) -> None:
    """The driver's safe state (LOITER after a fault) ends the flight, named as the driver's."""
    controller, vehicle = flight
    motion = controller.fly_to(FAR)
    controller.step(DT)
    vehicle.switch("LOITER")
    vehicle.last_mode_change = ModeChange("GUIDED", "LOITER", 1.0, True)  # type: ignore[attr-defined]
    controller.step(DT)
    assert motion.done
    assert "not commanded" not in _error(motion)
    assert "quad: the vehicle was switched to LOITER by its driver (its safe state)" in _error(
        motion
    )
