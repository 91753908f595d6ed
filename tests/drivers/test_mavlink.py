"""MavlinkDriver against SimVehicle: the driver contract, every Vehicle verb, faults, profiles."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Iterator

import pytest
from contract import DriverContract, Rig

from temoto.clock import Clock, ManualClock, MonotonicClock, ScaledClock
from temoto.drivers import DriverState, GeoPoint, Health, Vehicle, driver_class
from temoto.drivers.mavlink import MavlinkDriver, SimVehicle
from temoto.drivers.mavlink import protocol as p
from temoto.errors import (
    DriverOperationError,
    DriverTimeoutError,
    MavlinkCommandError,
    ProfileError,
    StateError,
)

HOME = (47.397742, 8.545594, 488.0)


def make(clock: Clock, **sim_kwargs: object) -> tuple[SimVehicle, MavlinkDriver]:
    config = {
        "link": "udpin:127.0.0.1:14550",
        "init_timeout": 2.0,
        "command_timeout": 0.3,
        "command_retries": 1,
        "sim": {
            "home": list(HOME),
            "speed": 8.0,
            "climb_rate": 4.0,
            "descent_rate": 3.0,
            "tau": 0.5,
            **sim_kwargs,
        },
    }
    sim, settings = MavlinkDriver.simulate("quad", config, clock=clock)
    assert isinstance(sim, SimVehicle)
    driver = MavlinkDriver.from_profile("quad", settings, clock=clock, where="devices.quad")
    return sim, driver


@pytest.fixture
def clock() -> ManualClock:
    return ManualClock()


@pytest.fixture
def rig_parts(clock: ManualClock) -> Iterator[tuple[SimVehicle, MavlinkDriver]]:
    sim, driver = make(clock)
    sim.start()
    try:
        yield sim, driver
    finally:
        driver.shutdown()
        sim.close()


def run_until(clock: ManualClock, pred: Callable[[], bool], seconds: float) -> float:
    """Advance virtual time in 20 ms steps until ``pred()``; the virtual seconds it took."""
    start = clock.monotonic()
    real_deadline = time.monotonic() + 15.0
    while not pred():
        assert clock.monotonic() - start <= seconds, f"not within {seconds} virtual s"
        assert time.monotonic() < real_deadline, "no progress in real time"
        clock.advance(0.02)
        time.sleep(0.0007)
    return clock.monotonic() - start


def configure(driver: MavlinkDriver, clock: ManualClock) -> None:
    """Configure while virtual time runs: the vehicle's next heartbeat is a clock tick away."""
    ticking(clock, driver.configure)


def ticking(clock: ManualClock, fn: Callable[[], None]) -> None:
    """Call ``fn`` while a thread advances virtual time (20 ms per real millisecond)."""
    done = threading.Event()

    def tick() -> None:
        while not done.wait(0.001):
            clock.advance(0.02)

    ticker = threading.Thread(target=tick)
    ticker.start()
    try:
        fn()
    finally:
        done.set()
        ticker.join()


@pytest.fixture
def active(
    rig_parts: tuple[SimVehicle, MavlinkDriver], clock: ManualClock
) -> tuple[SimVehicle, MavlinkDriver]:
    sim, driver = rig_parts
    configure(driver, clock)
    driver.activate()
    return sim, driver


class TestMavlinkContract(DriverContract):
    """On a ScaledClock (10x): ``configure`` needs the vehicle's heartbeats to keep coming
    while the contract waits, which a ManualClock nobody advances cannot give."""

    @pytest.fixture
    def rig(self) -> Iterator[Rig]:
        clock = ScaledClock(10.0)
        sim, driver = make(clock)
        driver.command_timeout = 2.0
        sim.start()
        try:
            yield Rig(
                driver=driver,
                sim=sim,
                clock=clock,
                act=driver.arm,
                acted=lambda: driver.telemetry().armed,
                stamp=lambda: driver.telemetry().stamp,
                fault_bound=driver.heartbeat_timeout + 0.5,
                init_timeout=driver.init_timeout,
            )
        finally:
            driver.shutdown()
            sim.close()


# ---- verbs ---------------------------------------------------------------------------------


def test_the_driver_is_a_registered_vehicle() -> None:
    assert driver_class("mavlink") is MavlinkDriver
    driver = MavlinkDriver("quad", link="udpin:127.0.0.1:0")
    assert isinstance(driver, Vehicle)
    with pytest.raises(StateError, match="UNCONFIGURED"):
        driver.telemetry()
    driver.shutdown()


def test_a_full_flight_in_virtual_time(
    active: tuple[SimVehicle, MavlinkDriver], clock: ManualClock
) -> None:
    _, d = active
    tel = d.telemetry
    assert tel().mode == "STABILIZE"
    assert not tel().armed
    assert tel().battery_remaining == 100
    assert tel().battery_voltage == pytest.approx(16.8)
    run_until(clock, lambda: d.home is not None, 5.0)

    d.arm()
    run_until(clock, lambda: tel().armed, 2.0)
    d.takeoff(10.0)
    took = run_until(clock, lambda: tel().position.alt > 9.7, 15.0)
    assert took > 10.0 / 4.0  # climb rate limited
    assert tel().mode == "GUIDED"
    assert math.isclose(tel().position.lat, HOME[0], abs_tol=1e-6)

    target = GeoPoint(HOME[0] + 0.0004, HOME[1] + 0.0003, 15.0)  # ~51 m away
    d.goto(target)
    took = run_until(clock, lambda: _distance(tel().position, target) < 0.5, 40.0)
    assert took > 51.0 / 8.0  # speed limited
    assert abs(tel().position.alt - 15.0) < 0.3

    d.land()
    took = run_until(clock, lambda: not tel().armed, 40.0)
    assert took > 10.0 / 0.5  # the last 10 m (LAND_ALT_LOW) at ArduCopter's LAND_SPEED 0.5 m/s
    assert tel().mode == "LAND"
    assert tel().position.alt == pytest.approx(0.0, abs=0.05)
    assert _distance(tel().position, GeoPoint(target.lat, target.lon, 0.0)) < 0.5
    assert "Disarming motors: landed" in tel().status_texts
    assert tel().battery_remaining < 100  # it drained
    assert tel().heartbeat_age <= 1.1


def test_return_to_launch_flies_home_and_lands(
    active: tuple[SimVehicle, MavlinkDriver], clock: ManualClock
) -> None:
    _, d = active
    tel = d.telemetry
    d.arm()
    d.takeoff(5.0)
    run_until(clock, lambda: tel().position.alt > 4.7, 10.0)
    d.goto(GeoPoint(HOME[0] - 0.0002, HOME[1], 5.0))
    run_until(clock, lambda: tel().position.lat < HOME[0] - 0.00019, 20.0)
    d.return_to_launch()
    run_until(clock, lambda: tel().mode == "RTL", 2.0)
    run_until(clock, lambda: tel().position.alt > 14.0, 10.0)  # RTL altitude first
    run_until(clock, lambda: not tel().armed, 40.0)
    assert _distance(tel().position, GeoPoint(HOME[0], HOME[1], 0.0)) < 1.0


def test_arming_on_a_low_battery_is_refused_with_the_result(clock: ManualClock) -> None:
    sim, d = make(clock, battery=10.0)
    with sim, d:
        configure(d, clock)
        d.activate()
        with pytest.raises(MavlinkCommandError, match="Battery below minimum") as info:
            d.arm()
        assert info.value.command == p.MAV_CMD_COMPONENT_ARM_DISARM == 400
        assert info.value.result == p.MAV_RESULT_FAILED
        assert "MAV_RESULT_FAILED" in str(info.value)
        assert isinstance(info.value, DriverOperationError)
        assert not sim.armed


def test_refusals_and_argument_errors(
    active: tuple[SimVehicle, MavlinkDriver], clock: ManualClock
) -> None:
    _, d = active
    with pytest.raises(MavlinkCommandError) as info:  # not armed
        d.takeoff(5.0)
    assert info.value.command == p.MAV_CMD_NAV_TAKEOFF
    assert info.value.result == p.MAV_RESULT_FAILED
    with pytest.raises(MavlinkCommandError) as info:  # not flying
        d.goto(GeoPoint(HOME[0], HOME[1], 5.0))
    assert info.value.command == p.MAV_CMD_DO_REPOSITION
    with pytest.raises(ValueError, match="unknown ArduCopter flight mode"):
        d.set_mode("HOVER")
    with pytest.raises(ValueError, match="positive"):
        d.takeoff(-1.0)
    with pytest.raises(TypeError):
        d.goto((1.0, 2.0, 3.0))  # type: ignore[arg-type]
    d.set_mode("RTL")
    with pytest.raises(MavlinkCommandError, match="Mode not armable"):
        d.arm()
    d.set_mode("loiter")
    d.arm()
    d.disarm()
    d.deactivate()
    with pytest.raises(StateError, match="INACTIVE"):
        d.arm()
    # telemetry keeps coming in while inactive: the heartbeats catch up with the last mode
    run_until(clock, lambda: d.telemetry().mode == "LOITER", 3.0)


def test_set_mode_shows_in_the_heartbeat(
    active: tuple[SimVehicle, MavlinkDriver], clock: ManualClock
) -> None:
    sim, d = active
    d.set_mode("LOITER")
    run_until(clock, lambda: d.telemetry().mode == "LOITER", 2.0)
    assert sim.mode == "LOITER"


def test_a_command_without_an_ack_times_out(active: tuple[SimVehicle, MavlinkDriver]) -> None:
    sim, d = active
    sim.inject("silence")
    started = time.monotonic()
    with pytest.raises(DriverTimeoutError, match="no COMMAND_ACK for MAV_CMD_COMPONENT_ARM"):
        d.arm()  # nobody advances the ManualClock: the real-time guard ends each try
    assert time.monotonic() - started < 3.0
    sim.clear()


def test_a_command_retries_after_a_lost_ack() -> None:
    real = MonotonicClock()
    sim, d = make(real)
    with sim, d:
        d.configure()
        d.activate()
        d.command_retries = 8  # 0.3 s each: room for a slow CPU
        sim.inject("corrupt")  # the first ack is lost to a bad CRC
        done = threading.Event()
        errors: list[BaseException] = []

        def arm() -> None:
            try:
                d.arm()
            except BaseException as err:
                errors.append(err)
            done.set()

        thread = threading.Thread(target=arm)
        thread.start()
        time.sleep(0.15)
        sim.clear("corrupt")
        thread.join(5.0)
        assert done.is_set()
        assert not errors
        assert sim.acks.count((400, 0)) >= 2  # the resend was acknowledged again
        assert d.bad_frames > 0


# ---- faults --------------------------------------------------------------------------------


def _listen(d: MavlinkDriver) -> list[Health]:
    got: list[Health] = []
    d.add_health_listener(got.append)
    return got


@pytest.mark.parametrize(
    ("fault", "params", "error", "match"),
    [
        ("no_heartbeat", {}, DriverTimeoutError, "no heartbeat within 3 s"),
        ("link_loss", {}, DriverTimeoutError, "no heartbeat within 3 s"),
        ("silence", {}, DriverTimeoutError, "no heartbeat within 3 s"),
        ("corrupt", {}, DriverOperationError, "corrupt frames"),
        ("hardware_error", {"kind": "overheat"}, DriverOperationError, "MOTOR_OUTPUTS"),
        ("hardware_error", {"kind": "overload"}, DriverOperationError, "PROPULSION"),
        ("hardware_error", {"kind": "voltage"}, DriverOperationError, "unhealthy BATTERY"),
    ],
)
def test_faults_become_typed_errors_and_recover(
    active: tuple[SimVehicle, MavlinkDriver],
    clock: ManualClock,
    fault: str,
    params: dict[str, str],
    error: type[Exception],
    match: str,
) -> None:
    sim, d = active
    got = _listen(d)
    sim.inject(fault, **params)
    took = run_until(clock, lambda: d.state is DriverState.FAULT, d.heartbeat_timeout + 3.0)
    assert took <= d.heartbeat_timeout + 1.5  # 3 heartbeat periods (+ slack for a busy CPU)
    fault_health = d.health()
    assert isinstance(fault_health.error, error)
    assert match in str(fault_health.error)
    assert [h.state for h in got] == [DriverState.FAULT]
    with pytest.raises(StateError, match="FAULT"):
        d.arm()
    if fault == "hardware_error":
        run_until(
            clock,
            lambda: any(
                "overheat" in t or "Prop" in t or "Battery" in t for t in d.telemetry().status_texts
            ),
            2.0,
        )
    sim.clear(fault)
    run_until(clock, lambda: d.state is DriverState.ACTIVE, 3.0)
    assert d.health().ok
    d.arm()


def test_a_hardware_error_refuses_arming_in_the_vehicle(
    rig_parts: tuple[SimVehicle, MavlinkDriver], clock: ManualClock
) -> None:
    sim, d = rig_parts
    configure(d, clock)
    d.activate()
    sim.inject("hardware_error", kind="overheat")
    with pytest.raises(MavlinkCommandError, match="PreArm: Motor overheat") as info:
        d.arm()  # before the next SYS_STATUS: the vehicle itself refuses
    assert info.value.result == p.MAV_RESULT_FAILED
    assert sim.fault("hardware_error") == {"kind": "overheat"}
    with pytest.raises(ValueError, match="kind"):
        sim.inject("hardware_error", kind="meltdown")


def test_configure_against_a_non_ardupilot_fails(clock: ManualClock) -> None:
    sim, d = make(clock)
    real_frame = sim.telemetry.frame

    def px4_heartbeat(name: str, now: float) -> bytes:
        if name == "HEARTBEAT":
            return sim.codec.encode(
                "HEARTBEAT",
                type=2,
                autopilot=12,
                base_mode=1,
                custom_mode=0,
                system_status=3,
                mavlink_version=3,
            )
        return real_frame(name, now)

    sim.telemetry.frame = px4_heartbeat  # type: ignore[method-assign]
    with sim, d:
        with pytest.raises(Exception, match="not an ArduPilot") as info:
            configure(d, clock)
        assert type(info.value).__name__ == "DriverInitError"
        assert d.state is DriverState.UNCONFIGURED


def test_recover_after_shutdown_of_threads(
    active: tuple[SimVehicle, MavlinkDriver], clock: ManualClock
) -> None:
    sim, d = active
    sim.inject("silence")
    run_until(clock, lambda: d.state is DriverState.FAULT, 5.0)
    sim.clear()
    ticking(clock, d.recover)  # explicit reconnect (the watch would also recover it by itself)
    assert d.state is DriverState.INACTIVE
    d.activate()
    d.arm()


def test_telemetry_stamps_follow_the_clock(
    active: tuple[SimVehicle, MavlinkDriver], clock: ManualClock
) -> None:
    _, d = active
    first = d.telemetry().stamp
    run_until(clock, lambda: d.telemetry().stamp >= first + 1.0, 3.0)
    assert d.telemetry().heartbeat_age < 1.1


# ---- profiles ------------------------------------------------------------------------------


def test_from_profile_reads_every_key() -> None:
    d = MavlinkDriver.from_profile(
        "quad",
        {
            "link": "udpout:127.0.0.1:14555",
            "system_id": 3,
            "component_id": 1,
            "gcs_system_id": 250,
            "gcs_component_id": 191,
            "heartbeat_period": 0.5,
            "heartbeat_timeout": 2,
            "init_timeout": 4,
            "command_timeout": 0.5,
            "command_retries": 4,
            "stream_rate": 20,
            "status_texts": 5,
            "sim": {"home": [1.0, 2.0, 3.0], "battery": 50, "rates": {"ATTITUDE": 25}},
        },
        clock=MonotonicClock(),
        where="robot.yaml: devices.quad",
    )
    assert (d.system_id, d.heartbeat_timeout, d.command_retries) == (3, 2.0, 4)
    assert str(d.link_spec) == "udpout:127.0.0.1:14555"
    d.shutdown()


@pytest.mark.parametrize(
    ("config", "path"),
    [
        ({}, "devices.quad.link: missing"),
        ({"link": 14550}, "devices.quad.link: must be text"),
        ({"link": "tcp:127.0.0.1:5760"}, "devices.quad.link: unknown link"),
        ({"link": "udpin:127.0.0.1"}, "devices.quad.link: udpin: needs HOST:PORT"),
        ({"link": "udpout:host:99999"}, "devices.quad.link: udpout: port out of range"),
        ({"link": "serial:"}, "devices.quad.link: serial: needs a device"),
        ({"link": "serial:/dev/x?baud=fast"}, "devices.quad.link: serial: baud"),
        ({"link": "udp:127.0.0.1:1", "speed": 3}, "devices.quad.speed: unknown key"),
        (
            {"link": "udp:127.0.0.1:1", "system_id": 0},
            "devices.quad.system_id: must be an integer 1..255",
        ),
        ({"link": "udp:127.0.0.1:1", "system_id": 1.5}, "devices.quad.system_id: must be an int"),
        ({"link": "udp:127.0.0.1:1", "heartbeat_timeout": -1}, "devices.quad.heartbeat_timeout"),
        ({"link": "udp:127.0.0.1:1", "init_timeout": "5"}, "devices.quad.init_timeout: must be"),
        ({"link": "udp:127.0.0.1:1", "command_retries": True}, "devices.quad.command_retries"),
        ({"link": "udp:127.0.0.1:1", "stream_rate": -2}, "devices.quad.stream_rate"),
        ({"link": "udp:127.0.0.1:1", "sim": 3}, "devices.quad.sim: must be a mapping"),
        ({"link": "udp:127.0.0.1:1", "sim": {"wind": 1}}, "devices.quad.sim.wind: unknown"),
        ({"link": "udp:127.0.0.1:1", "sim": {"home": [1, 2]}}, "devices.quad.sim.home: must"),
        ({"link": "udp:127.0.0.1:1", "sim": {"battery": 120}}, "devices.quad.sim.battery"),
        ({"link": "udp:127.0.0.1:1", "sim": {"speed": 0}}, "devices.quad.sim.speed: out of"),
        ({"link": "udp:127.0.0.1:1", "sim": {"rates": {"FOO": 1}}}, "sim.rates.FOO: not a"),
    ],
)
def test_bad_profiles_name_the_key(config: dict[str, object], path: str) -> None:
    with pytest.raises(ProfileError) as info:
        MavlinkDriver.from_profile("quad", config, clock=MonotonicClock(), where="devices.quad")
    assert path in str(info.value)


def test_simulate_points_the_driver_at_the_simulator() -> None:
    sim, settings = MavlinkDriver.simulate(
        "quad", {"link": "serial:/dev/ttyACM0", "sim": {"battery": 55}}, clock=MonotonicClock()
    )
    assert settings["link"].startswith("udpin:127.0.0.1:")
    assert "sim" not in settings
    assert isinstance(sim, SimVehicle)
    assert sim.battery == 55.0
    sim.close()  # never started: closing is still fine


def _distance(a: GeoPoint, b: GeoPoint) -> float:
    north = math.radians(a.lat - b.lat) * 6_378_137.0
    east = math.radians(a.lon - b.lon) * 6_378_137.0 * math.cos(math.radians(b.lat))
    return math.sqrt(north**2 + east**2 + (a.alt - b.alt) ** 2)
