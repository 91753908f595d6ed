"""DynamixelDriver on the simulated chain: the driver contract, faults, recovery, profiles."""

from __future__ import annotations

import linecache
import math
import sys
import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest
from contract import DriverContract, Rig, eventually
from dxl_polled import follow
from dxl_sdk_client import patient_sim_links

from temoto.clock import Clock, ManualClock, MonotonicClock
from temoto.drivers import (
    Actuator,
    ControlMode,
    DriverState,
    Health,
    JointCommand,
    driver_class,
)
from temoto.drivers.dynamixel import _sdk
from temoto.drivers.dynamixel.driver import SIM_REPLY_TIMEOUT, DynamixelDriver, ServoConfig
from temoto.drivers.dynamixel.sim import SimDynamixelChain
from temoto.errors import (
    DriverInitError,
    DriverOperationError,
    DriverTimeoutError,
    DriverUnavailableError,
    DynamixelHardwareError,
    ProfileError,
    StateError,
)

pytest.importorskip("dynamixel_sdk")

# The simulators are threads of this process: their replies wait for them, not for the clock
# (tests/drivers/dxl_sdk_client.py).
pytestmark = pytest.mark.usefixtures(patient_sim_links.__name__)

POLL_RATE = 100.0
# Real seconds: 3 failed polls, each a period plus the reply timeout, and scheduling slack for
# loaded machines.
FAULT_BOUND = 3 * (1 / POLL_RATE + SIM_REPLY_TIMEOUT) + 0.5


def arm_config(n: int = 6, **extra: Any) -> dict[str, Any]:
    servos = [
        {
            "id": i + 1,
            "joint": f"j{i + 1}",
            "model": "XM430-W350",
            "min_position": -2.5,
            "max_position": 2.5,
        }
        for i in range(n)
    ]
    return {
        "driver": "dynamixel",
        "link": "serial:/dev/null",
        "baud": 1_000_000,
        "poll_rate": POLL_RATE,
        "servos": servos,
        **extra,
    }


@pytest.fixture
def chain() -> Iterator[tuple[DynamixelDriver, SimDynamixelChain, Clock]]:
    clock = MonotonicClock()
    sim, config = DynamixelDriver.simulate("arm", arm_config(), clock=clock)
    sim.start()
    driver = DynamixelDriver.from_profile("arm", config, clock=clock, where="devices.arm")
    yield driver, sim, clock
    driver.shutdown()
    sim.close()


class TestDynamixelContract(DriverContract):
    @pytest.fixture
    def rig(self, chain: tuple[DynamixelDriver, SimDynamixelChain, Clock]) -> Rig:
        driver, sim, clock = chain
        target = 0.4

        def act() -> None:
            driver.command([JointCommand("j2", ControlMode.POSITION, target)])

        def acted() -> bool:
            return abs(driver.read_state().joints["j2"].position - target) < 0.01

        return Rig(
            driver=driver,
            sim=sim,
            clock=clock,
            act=act,
            acted=acted,
            stamp=lambda: driver.read_state().stamp,
            fault_bound=FAULT_BOUND,
            init_timeout=3 * SIM_REPLY_TIMEOUT * 3 + 0.5,
        )


def test_it_is_the_registered_actuator(
    chain: tuple[DynamixelDriver, SimDynamixelChain, Clock],
) -> None:
    driver, _, _ = chain
    assert driver_class("dynamixel") is DynamixelDriver
    assert isinstance(driver, Actuator)
    assert driver.joint_names == ("j1", "j2", "j3", "j4", "j5", "j6")
    with pytest.raises(StateError):
        driver.read_state()


def test_state_in_si_units_and_commands(
    chain: tuple[DynamixelDriver, SimDynamixelChain, Clock],
) -> None:
    driver, sim, clock = chain
    driver.configure()
    state = driver.read_state()
    assert state.joints["j1"].position == 0.0
    assert sim.read_register(1, 11) == 3  # position mode
    driver.activate()
    assert sim.read_register(1, 64) == 1
    driver.command(
        [
            JointCommand("j1", ControlMode.POSITION, -1.0),
            JointCommand("j3", ControlMode.POSITION, 1.0, velocity_limit=2.0),
        ]
    )
    eventually(lambda: abs(driver.read_state().joints["j1"].position + 1.0) < 0.01, 3.0, clock)
    assert sim.read_register(3, 112) == round(2.0 / (0.229 * 2 * math.pi / 60))
    with pytest.raises(ValueError, match="outside"):
        driver.command([JointCommand("j1", ControlMode.POSITION, 3.0)])
    with pytest.raises(ValueError, match="no joint"):
        driver.command([JointCommand("elbow", ControlMode.POSITION, 0.0)])
    with pytest.raises(ValueError, match="position mode"):
        driver.command([JointCommand("j1", ControlMode.VELOCITY, 0.1)])
    status = driver.servo_status()
    assert status[1].temperature == 30.0
    assert status[1].voltage == pytest.approx(12.0)
    driver.deactivate()
    assert sim.read_register(1, 64) == 0


def one_servo(mode: str, model: str = "XM430-W350", **extra: Any) -> dict[str, Any]:
    servo = {"id": 7, "joint": "wheel", "model": model, "mode": mode, **extra}
    return {"link": "/dev/null", "poll_rate": 200, "servos": [servo]}


def test_velocity_and_effort_modes_on_a_manual_clock() -> None:
    clock = ManualClock()
    for mode, cmd, check in (
        ("velocity", ControlMode.VELOCITY, lambda s: s.velocity > 1.9),
        ("current", ControlMode.EFFORT, lambda s: s.effort == pytest.approx(0.5, rel=0.02)),
    ):
        sim, config = DynamixelDriver.simulate("w", one_servo(mode, gear=2.0), clock=clock)
        with sim, DynamixelDriver.from_profile("w", config, clock=clock, where="w") as driver:
            driver.configure()
            driver.activate()
            driver.command([JointCommand("wheel", cmd, 2.0 if mode == "velocity" else 0.5)])
            follow(driver, clock, lambda c=check: c(driver.read_state().joints["wheel"]), 30.0)
            with pytest.raises(ValueError, match="too"):
                driver.command([JointCommand("wheel", cmd, 1e3)])


def test_a_starved_simulator_thread_does_not_fail_the_bring_up(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # As on a loaded machine: the simulator's thread runs only after the driver's reply
    # timeout; its replies are late, not missing (patient_sim_links), so nothing fails.
    clock = ManualClock()
    sim, config = DynamixelDriver.simulate("arm", arm_config(1), clock=clock)
    serve = sim._serve_data

    def starved(data: bytes) -> None:
        time.sleep(1.5 * SIM_REPLY_TIMEOUT)
        serve(data)

    monkeypatch.setattr(sim, "_serve_data", starved)
    with sim, DynamixelDriver.from_profile("arm", config, clock=clock, where="a") as driver:
        driver.configure()
        driver.activate()
        assert driver.state is DriverState.ACTIVE
        assert driver.read_state().joints["j1"].position == pytest.approx(0.0, abs=0.01)


def test_model_mismatch_names_the_servo() -> None:
    config = arm_config(2)
    sim, config = DynamixelDriver.simulate("arm", config, clock=MonotonicClock())
    config["servos"][1] = {**config["servos"][1], "model": "XL430-W250"}
    with sim, DynamixelDriver.from_profile("arm", config, clock=MonotonicClock(), where="a") as d:
        with pytest.raises(DriverInitError, match=r"servo 2 \(j2\) is XM430-W350.*XL430-W250"):
            d.configure()
        assert d.state is DriverState.UNCONFIGURED


def test_missing_port_is_unavailable() -> None:
    driver = DynamixelDriver.from_profile(
        "arm", arm_config(1, link="/dev/nonexistent-dxl"), clock=MonotonicClock(), where="a"
    )
    with driver, pytest.raises(DriverUnavailableError, match="nonexistent"):
        driver.configure()


def faults(driver: DynamixelDriver) -> tuple[list[Health], threading.Event]:
    got: list[Health] = []
    seen = threading.Event()

    def listen(health: Health) -> None:
        got.append(health)
        if health.state is DriverState.FAULT:
            seen.set()

    driver.add_health_listener(listen)
    return got, seen


@pytest.mark.parametrize(
    ("kind", "bit", "word"),
    [
        ("overheat", 0x04, "overheating"),
        ("overload", 0x20, "overload"),
        ("voltage", 0x01, "input voltage"),
    ],
)
def test_hardware_error_is_typed_and_recovered_by_reboot(
    chain: tuple[DynamixelDriver, SimDynamixelChain, Clock], kind: str, bit: int, word: str
) -> None:
    driver, sim, clock = chain
    got, seen = faults(driver)
    driver.configure()
    driver.activate()
    sim.inject("hardware_error", kind=kind, device=4)
    took = eventually(seen.is_set, FAULT_BOUND, clock)
    assert took <= FAULT_BOUND
    error = next(h for h in got if h.state is DriverState.FAULT).error
    assert isinstance(error, DynamixelHardwareError)
    assert error.servo_id == 4
    assert error.error == bit
    assert word in str(error)
    assert "j4" in str(error)
    assert driver.servo_status()[4].hardware_error == bit
    sim.clear("hardware_error")
    eventually(lambda: True, 0.1, clock)
    assert driver.state is DriverState.FAULT  # a hardware error does not go away by itself
    reboots = sim.stats["reboots"]
    driver.recover()
    assert sim.stats["reboots"] == reboots + 1  # only the failing servo
    assert driver.state is DriverState.INACTIVE
    driver.activate()
    assert sim.read_register(4, 64) == 1
    driver.command([JointCommand("j4", ControlMode.POSITION, 0.3)])
    eventually(lambda: abs(driver.read_state().joints["j4"].position - 0.3) < 0.01, 3, clock)


def test_recover_fails_while_the_error_persists(
    chain: tuple[DynamixelDriver, SimDynamixelChain, Clock],
) -> None:
    driver, sim, clock = chain
    _, seen = faults(driver)
    driver.configure()
    sim.inject("hardware_error", kind="overload", device=1)
    eventually(seen.is_set, FAULT_BOUND, clock)
    with pytest.raises(DynamixelHardwareError, match="overload"):
        driver.recover()
    assert driver.state is DriverState.FAULT
    sim.clear()
    driver.recover()
    assert driver.state is DriverState.INACTIVE


@pytest.mark.parametrize(
    ("fault", "error"), [("corrupt", DriverOperationError), ("link_loss", DriverTimeoutError)]
)
def test_corrupt_and_link_loss_fault_and_recover(
    chain: tuple[DynamixelDriver, SimDynamixelChain, Clock], fault: str, error: type
) -> None:
    driver, sim, clock = chain
    got, seen = faults(driver)
    driver.configure()
    driver.activate()
    sim.inject(fault)
    assert eventually(seen.is_set, FAULT_BOUND, clock) <= FAULT_BOUND
    reported = next(h for h in got if h.state is DriverState.FAULT).error
    assert isinstance(reported, error)
    sim.clear(fault)
    eventually(lambda: driver.state is DriverState.ACTIVE, FAULT_BOUND, clock)


def test_torque_lost_while_silent_needs_recover(
    chain: tuple[DynamixelDriver, SimDynamixelChain, Clock],
) -> None:
    driver, sim, clock = chain
    _got, seen = faults(driver)
    driver.configure()
    driver.activate()
    sim.inject("silence")
    eventually(seen.is_set, FAULT_BOUND, clock)
    sim.write_register(5, 64, 0)  # as if it power-cycled
    sim.clear("silence")
    eventually(lambda: "lost torque" in driver.health().message, FAULT_BOUND, clock)
    assert driver.state is DriverState.FAULT
    driver.recover()
    driver.activate()
    assert sim.read_register(5, 64) == 1


def test_configure_reboots_a_servo_with_an_old_hardware_error() -> None:
    clock = MonotonicClock()
    sim, config = DynamixelDriver.simulate("arm", arm_config(2), clock=clock)
    with sim, DynamixelDriver.from_profile("arm", config, clock=clock, where="a") as driver:
        sim.inject("hardware_error", kind="overheat", device=2)
        sim.clear()
        driver.configure()
        assert sim.stats["reboots"] == 1
        assert driver.servo_status()[2].hardware_error == 0


def test_poll_period_follows_a_manual_clock() -> None:
    clock = ManualClock()
    sim, config = DynamixelDriver.simulate("arm", arm_config(2, poll_rate=10), clock=clock)
    with sim, DynamixelDriver.from_profile("arm", config, clock=clock, where="a") as driver:
        driver.configure()
        first = driver.read_state().stamp
        packets = sim.stats["packets"]
        threading.Event().wait(0.05)  # real time passes, virtual time does not
        assert driver.read_state().stamp == first
        assert sim.stats["packets"] - packets <= 1
        eventually(lambda: driver.read_state().stamp >= first + 0.3, 30.0, clock)


# ---- profiles ----------------------------------------------------------------------------------


def bad(path: str, **change: Any) -> tuple[str, dict[str, Any]]:
    return path, change


def servo_change(i: int, **change: Any) -> dict[str, Any]:
    config = arm_config(2)
    config["servos"][i] = {**config["servos"][i], **change}
    return config


BAD_PROFILES = [
    ("d.colour", {**arm_config(), "colour": "red"}),
    ("d.link", {k: v for k, v in arm_config().items() if k != "link"}),
    ("d.link", arm_config(link="udp:127.0.0.1:9")),
    ("d.link", arm_config(link="serial:/dev/ttyUSB0?baud=12345")),
    ("d.baud", arm_config(baud=12345)),
    ("d.baud", arm_config(link="serial:/dev/ttyUSB0?baud=57600")),
    ("d.poll_rate", arm_config(poll_rate=0)),
    ("d.timeout_polls", arm_config(timeout_polls=0)),
    ("d.servos", arm_config(servos=[])),
    ("d.servos[1].id", servo_change(1, id=1)),
    ("d.servos[1].joint", servo_change(1, joint="j1")),
    ("d.servos[0].model", servo_change(0, model="AX-12")),
    ("d.servos[0].mode", servo_change(0, mode="torque")),
    ("d.servos[0].mode", servo_change(0, model="XL430-W250", mode="current")),
    ("d.servos[0].max_position", servo_change(0, min_position=1.0, max_position=-1.0)),
    ("d.servos[0].max_position", servo_change(0, max_position=4.0)),
    ("d.servos[0].gear", servo_change(0, gear=0)),
    ("d.servos[0].velocity_limit", servo_change(0, velocity_limit=-1)),
    ("d.servos[0].id", servo_change(0, id=253)),
    ("d.servos[0].colour", servo_change(0, colour="red")),
    ("d.servos[0].min_position", servo_change(0, min_position="low")),
]


@pytest.mark.parametrize(("path", "config"), BAD_PROFILES, ids=[b[0] for b in BAD_PROFILES])
def test_bad_profiles_name_the_key(path: str, config: dict[str, Any]) -> None:
    with pytest.raises(ProfileError) as info:
        DynamixelDriver.from_profile("arm", config, clock=MonotonicClock(), where="d")
    assert str(info.value).startswith(path + ":"), str(info.value)


def test_a_good_profile_and_the_conversions() -> None:
    config = arm_config(1, link="serial:/dev/ttyUSB0?baud=1000000")
    config["servos"][0].update(
        gear=-2.0, offset=0.5, torque_constant=2.0, min_position=-1.0, max_position=1.0
    )
    driver = DynamixelDriver.from_profile("arm", config, clock=MonotonicClock(), where="d")
    servo = driver.servos[0]
    assert driver.port == "/dev/ttyUSB0"
    assert driver.baud == 1_000_000
    assert servo.position(servo.ticks(1.0)) == pytest.approx(1.0, abs=1e-3)
    assert servo.effort(100) == pytest.approx(-100 * 0.00269 * 2.0 * 2.0)
    assert servo.current_units(servo.effort(100)) == 100
    with pytest.raises(ValueError, match="gear"):
        ServoConfig(1, "j", "XM430-W350", gear=0.0)


def _waiting_at_the_bus(thread: threading.Thread, function: str) -> bool:
    """Whether ``thread`` is in the Dynamixel driver's ``function``, stopped at taking the bus."""
    frame = sys._current_frames().get(thread.ident or -1)
    while frame is not None:
        code = frame.f_code
        if code.co_name == function and "dynamixel" in code.co_filename:
            return "self._bus" in linecache.getline(code.co_filename, frame.f_lineno)
        frame = frame.f_back
    return False


def test_a_set_point_goes_before_the_polls_waiting_for_the_bus(
    chain: tuple[DynamixelDriver, SimDynamixelChain, Clock],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A hold waits for the transaction in flight only, not for the polls queued behind it.

    The bus is held (a transaction in flight) until the poll thread waits for it and then a
    command waits too; when it is given back, the next transaction on the wire must be the
    command's SYNC_WRITE (before: the poll thread, waiting first, went first, and a hold
    queued behind its reads and its goal feed).
    """
    driver, _, clock = chain
    driver.configure()
    driver.activate()
    wire: list[tuple[str, str]] = []  # (thread, transaction) in the order they took place
    real_read, real_write = _sdk.SyncReader.read, _sdk.SyncWriter.write

    def read(self: _sdk.SyncReader) -> Any:
        wire.append((threading.current_thread().name, "read"))
        return real_read(self)

    def write(self: _sdk.SyncWriter, data: dict[int, bytes]) -> int:
        wire.append((threading.current_thread().name, "write"))
        return real_write(self, data)

    monkeypatch.setattr(_sdk.SyncReader, "read", read)
    monkeypatch.setattr(_sdk.SyncWriter, "write", write)
    poller = driver._poller
    assert poller is not None
    for target in (0.5, -0.5, 0.3, -0.3, 0.1):  # before: the poll went first in 2 of 4
        hold = threading.Thread(
            target=driver.command,
            args=([JointCommand("j1", ControlMode.POSITION, target)],),
            name="hold",
        )
        with driver._bus:  # the transaction in flight
            eventually(
                lambda: (
                    _waiting_at_the_bus(poller, "_poll_fast")
                    or _waiting_at_the_bus(poller, "_feed_goals")
                ),
                5.0,
            )
            hold.start()
            eventually(lambda: _waiting_at_the_bus(hold, "command"), 5.0)  # noqa: B023
            start = len(wire)
        hold.join(5.0)
        assert not hold.is_alive()
        eventually(lambda: len(wire) > start, 5.0, clock)  # noqa: B023
        assert wire[start] == ("hold", "write"), wire[start:]


def test_a_poll_cannot_take_the_bus_again_while_a_set_point_waits(
    chain: tuple[DynamixelDriver, SimDynamixelChain, Clock],
) -> None:
    """The thread that gives the bus back (a poll between two transactions) must not retake it.

    Before, the chain's bus was a plain re-entrant lock: the poll thread, giving it back after
    a SYNC_READ and taking it again for its goal feed a few microseconds later, got it again
    before the command waiting for it had woken up.
    """
    driver, _, _ = chain
    driver.configure()
    driver.activate()
    driver._stop_polling()  # this thread plays the poll
    hold = threading.Thread(
        target=driver.command,
        args=([JointCommand("j1", ControlMode.POSITION, 0.5)],),
        name="hold",
    )
    driver._bus.acquire()
    hold.start()
    eventually(lambda: _waiting_at_the_bus(hold, "command"), 5.0)
    driver._bus.release()
    again = driver._bus.acquire(blocking=False)  # the poll's next transaction
    if again:
        driver._bus.release()
    hold.join(5.0)
    assert not hold.is_alive()
    assert not again, "the poll took the bus again before the waiting set-point"
