"""The ODrive CANSimple driver on its simulator: the driver contract, faults and profiles."""

from __future__ import annotations

import math
import threading
import uuid
from collections.abc import Callable, Iterator
from typing import Any

import pytest
from contract import DriverContract, Rig, eventually

from temoto.clock import Clock, ManualClock
from temoto.drivers import DriverState, Health
from temoto.drivers.can_motor import cansimple as cs
from temoto.drivers.can_motor.odrive import ODriveDriver
from temoto.drivers.can_motor.sim import SimODrive
from temoto.drivers.capabilities import Actuator, ControlMode, JointCommand
from temoto.drivers.registry import driver_class
from temoto.errors import (
    DriverInitError,
    DriverOperationError,
    DriverTimeoutError,
    MotorFaultError,
    ProfileError,
    StateError,
)

HB = 0.1  # heartbeat period of the rigs, clock seconds
BOUND = 3 * HB + 2 * HB  # 3 silent periods, plus a period of detection and one of slack


def config(channel: str, **extra: Any) -> dict[str, Any]:
    return {
        "link": {"interface": "virtual", "channel": channel},
        "heartbeat_period": HB,
        "encoder_period": 0.01,
        "init_timeout": 0.5,
        "nodes": [
            {"node_id": 1, "joint": "left", "gear_ratio": 2.0, "velocity_limit": 20.0},
            {"node_id": 2, "joint": "right", "position_min": -3.0, "position_max": 3.0},
        ],
        **extra,
    }


def make(clock: Clock, **extra: Any) -> tuple[ODriveDriver, SimODrive]:
    channel = f"odrive-{uuid.uuid4().hex[:8]}"
    sim, cfg = ODriveDriver.simulate("base", config(channel, **extra), clock=clock)
    assert isinstance(sim, SimODrive)
    driver = ODriveDriver.from_profile("base", cfg, clock=clock, where="devices.base")
    return driver, sim


@pytest.fixture
def clock() -> ManualClock:
    return ManualClock()


@pytest.fixture
def pair(clock: ManualClock) -> Iterator[tuple[ODriveDriver, SimODrive]]:
    driver, sim = make(clock)
    sim.start()
    try:
        yield driver, sim
    finally:
        driver.shutdown()
        sim.close()


def run(
    call: Callable[[], object], clock: ManualClock, timeout: float = 2.0
) -> BaseException | None:
    """Call something that waits on the clock, in a thread, while moving virtual time."""
    errors: list[BaseException] = []

    def target() -> None:
        try:
            call()
        except BaseException as err:
            errors.append(err)

    thread = threading.Thread(target=target)
    thread.start()
    eventually(lambda: not thread.is_alive(), timeout, clock)
    thread.join()
    return errors[0] if errors else None


def position(driver: ODriveDriver, joint: str) -> float:
    return driver.read_state().joints[joint].position


class TestODriveContract(DriverContract):
    @pytest.fixture
    def rig(self, pair: tuple[ODriveDriver, SimODrive], clock: ManualClock) -> Rig:
        driver, sim = pair

        def act() -> None:
            driver.command([JointCommand("left", ControlMode.POSITION, 1.0)])

        return Rig(
            driver=driver,
            sim=sim,
            clock=clock,
            act=act,
            acted=lambda: abs(position(driver, "left") - 1.0) < 0.01,
            stamp=lambda: driver.read_state().stamp,
            fault_bound=BOUND,
            init_timeout=0.5,
        )


# ---- commands and state ----------------------------------------------------------------------


def test_it_is_an_actuator_in_the_registry(pair: tuple[ODriveDriver, SimODrive]) -> None:
    driver, _ = pair
    assert driver_class("odrive_can") is ODriveDriver
    assert isinstance(driver, Actuator)
    assert driver.joint_names == ("left", "right")


def test_units_gear_ratio_and_modes(
    pair: tuple[ODriveDriver, SimODrive], clock: ManualClock
) -> None:
    driver, sim = pair
    driver.configure()
    driver.activate()
    assert sim.axes[1].state == cs.AxisState.CLOSED_LOOP_CONTROL
    driver.command([JointCommand("left", ControlMode.POSITION, math.pi)])  # joint half a turn
    eventually(lambda: abs(position(driver, "left") - math.pi) < 1e-3, 2.0, clock)
    assert sim.axes[1].pos == pytest.approx(1.0, abs=1e-3)  # gear 2: a whole motor turn
    driver.command([JointCommand("right", ControlMode.VELOCITY, 2.0)])
    assert sim.axes[2].control_mode == cs.ControlMode.VELOCITY_CONTROL or eventually(
        lambda: sim.axes[2].control_mode == cs.ControlMode.VELOCITY_CONTROL, 1.0, clock
    )
    eventually(lambda: abs(driver.read_state().joints["right"].velocity - 2.0) < 0.01, 2.0, clock)
    driver.command([JointCommand("left", ControlMode.EFFORT, 0.4)])
    eventually(lambda: sim.axes[1].input_torque == pytest.approx(0.2), 1.0, clock)  # gear 2
    state = driver.read_state()
    assert state.stamp == max(j.stamp for j in state.joints.values())
    driver.deactivate()
    assert sim.axes[1].state == sim.axes[2].state == cs.AxisState.IDLE


def test_bad_commands_are_value_errors(pair: tuple[ODriveDriver, SimODrive]) -> None:
    driver, sim = pair
    driver.configure()
    driver.activate()
    with pytest.raises(ValueError, match="no joint 'middle'"):
        driver.command([JointCommand("middle", ControlMode.POSITION, 0.0)])
    with pytest.raises(ValueError, match="outside"):
        driver.command([JointCommand("right", ControlMode.POSITION, 4.0)])
    with pytest.raises(ValueError, match="velocity"):
        driver.command([JointCommand("left", ControlMode.VELOCITY, -21.0)])
    before = sim.axes[1].commands
    with pytest.raises(
        ValueError, match="outside"
    ):  # all or nothing: the first, valid one is not sent
        driver.command(
            [
                JointCommand("left", ControlMode.POSITION, 1.0),
                JointCommand("right", ControlMode.POSITION, 9.0),
            ]
        )
    assert sim.axes[1].commands == before


def test_read_state_needs_a_configured_driver(pair: tuple[ODriveDriver, SimODrive]) -> None:
    driver, _ = pair
    with pytest.raises(StateError, match="UNCONFIGURED"):
        driver.read_state()
    driver.configure()
    assert set(driver.read_state().joints) == {"left", "right"}
    driver.shutdown()
    with pytest.raises(StateError, match="FINALIZED"):
        driver.read_state()


def test_configure_names_the_silent_node(clock: ManualClock) -> None:
    driver, sim = make(clock)
    with sim:
        sim.inject("silence", node=2)
        error = run(driver.configure, clock, 1.0)
        assert isinstance(error, DriverInitError)
        assert "node 2 (right)" in str(error)
        assert "node 1" not in str(error)
        driver.shutdown()


# ---- faults ----------------------------------------------------------------------------------


def faults(driver: ODriveDriver) -> tuple[list[Health], threading.Event]:
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
        ("overheat", "MOTOR_OVER_TEMP", "overheat"),
        ("overload", "CURRENT_LIMIT_VIOLATION", "overload"),
        ("voltage", "DC_BUS_UNDER_VOLTAGE", "voltage"),
    ],
)
def test_hardware_errors_are_motor_faults_until_cleared(
    pair: tuple[ODriveDriver, SimODrive], clock: ManualClock, kind: str, bit: str, word: str
) -> None:
    driver, sim = pair
    got, seen = faults(driver)
    driver.configure()
    driver.activate()
    sim.inject("hardware_error", kind=kind, node=2)
    eventually(seen.is_set, HB * 2, clock)  # the next heartbeat carries the bits
    error = next(h.error for h in got if h.state is DriverState.FAULT)
    assert isinstance(error, MotorFaultError)
    assert error.node_id == 2
    assert bit in str(error)
    assert word in str(error)
    assert "right" in str(error)
    # still present: recover() clears, but the bit comes back
    assert isinstance(run(driver.recover, clock), MotorFaultError)
    assert driver.state is DriverState.FAULT
    sim.clear("hardware_error")
    eventually(lambda: driver.state is DriverState.FAULT, HB * 5, clock)  # latched
    driver.recover()  # Clear_Errors
    assert driver.state is DriverState.INACTIVE
    driver.activate()
    assert driver.health().ok


def test_corrupt_frames_are_operation_errors_and_recover(
    pair: tuple[ODriveDriver, SimODrive], clock: ManualClock
) -> None:
    driver, sim = pair
    got, seen = faults(driver)
    driver.configure()
    driver.activate()
    sim.inject("corrupt", node=1)
    eventually(seen.is_set, HB, clock)
    error = next(h.error for h in got if h.state is DriverState.FAULT)
    assert type(error) is DriverOperationError
    assert "malformed" in str(error)
    assert "node 1 (left)" in str(error)
    sim.clear("corrupt")
    eventually(lambda: driver.state is DriverState.ACTIVE, HB * 3, clock)


def test_lost_heartbeats_time_out_and_recover(
    pair: tuple[ODriveDriver, SimODrive], clock: ManualClock
) -> None:
    driver, sim = pair
    got, seen = faults(driver)
    driver.configure()
    driver.activate()
    sim.inject("no_heartbeat", node=1)
    took = eventually(seen.is_set, BOUND, clock)
    assert took >= 2 * HB  # not before the heartbeats are really missing
    error = next(h.error for h in got if h.state is DriverState.FAULT)
    assert isinstance(error, DriverTimeoutError)
    assert "node 1 (left)" in str(error)
    sim.clear("no_heartbeat")
    eventually(lambda: driver.state is DriverState.ACTIVE, HB * 3, clock)
    assert got[-1].ok


def test_link_loss_and_recovery(pair: tuple[ODriveDriver, SimODrive], clock: ManualClock) -> None:
    driver, sim = pair
    _, seen = faults(driver)
    driver.configure()
    driver.activate()
    sim.inject("link_loss")
    eventually(seen.is_set, BOUND, clock)
    assert isinstance(driver.health().error, DriverTimeoutError)
    sim.clear("link_loss")
    eventually(lambda: driver.state is DriverState.ACTIVE, HB * 3, clock)
    driver.command([JointCommand("right", ControlMode.POSITION, 0.5)])
    eventually(lambda: abs(position(driver, "right") - 0.5) < 0.01, 2.0, clock)


def test_estop_faults_every_node(pair: tuple[ODriveDriver, SimODrive], clock: ManualClock) -> None:
    driver, sim = pair
    _, seen = faults(driver)
    driver.configure()
    driver.activate()
    driver.estop()
    eventually(seen.is_set, HB * 2, clock)
    assert "ESTOP_REQUESTED" in driver.health().message
    assert sim.axes[1].state == sim.axes[2].state == cs.AxisState.IDLE
    driver.recover()
    driver.activate()
    assert sim.axes[1].state == cs.AxisState.CLOSED_LOOP_CONTROL


def test_simulator_rejects_unknown_faults(pair: tuple[ODriveDriver, SimODrive]) -> None:
    _, sim = pair
    with pytest.raises(ValueError, match="cannot inject"):
        sim.inject("fire")
    with pytest.raises(ValueError, match="kind"):
        sim.inject("hardware_error", kind="rust")


# ---- profiles --------------------------------------------------------------------------------


def bad(cfg: dict[str, Any], path: str, match: str) -> None:
    with pytest.raises(ProfileError, match=match) as info:
        ODriveDriver.from_profile("base", cfg, clock=ManualClock(), where="p.yaml: devices.base")
    assert str(info.value).startswith(f"p.yaml: devices.base.{path}: "), str(info.value)


def test_profile_errors_name_the_key_path() -> None:
    ok = config("c")
    bad({**ok, "speed": 1}, "speed", "unknown key")
    bad({k: v for k, v in ok.items() if k != "link"}, "link", "missing")
    bad({**ok, "link": {"interface": "virtual"}}, "link.channel", "missing")
    bad({**ok, "nodes": []}, "nodes", "non-empty list")
    nodes = ok["nodes"]
    bad({**ok, "nodes": [nodes[0], {**nodes[1], "node_id": 1}]}, "nodes[1].node_id", "duplicate")
    bad({**ok, "nodes": [nodes[0], {**nodes[1], "joint": "left"}]}, "nodes[1].joint", "duplicate")
    bad({**ok, "nodes": [{"node_id": 3}]}, "nodes[0].joint", "missing")
    bad({**ok, "nodes": [{"node_id": 64, "joint": "a"}]}, "nodes[0].node_id", "0..63")
    bad({**ok, "nodes": [{"joint": "a"}]}, "nodes[0].node_id", "missing")
    bad({**ok, "nodes": [{"node_id": 1, "joint": "a", "gear": 2}]}, "nodes[0].gear", "unknown")
    bad(
        {**ok, "nodes": [{"node_id": 1, "joint": "a", "gear_ratio": 0}]},
        "nodes[0].gear_ratio",
        "positive",
    )
    limits = {"node_id": 1, "joint": "a", "position_min": 1.0, "position_max": -1.0}
    bad({**ok, "nodes": [limits]}, "nodes[0].position_min", "below position_max")
    bad(
        {**ok, "nodes": [{"node_id": 1, "joint": "a", "velocity_limit": "x"}]},
        "nodes[0].velocity_limit",
        "number",
    )
    bad({**ok, "heartbeat_period": -1}, "heartbeat_period", "positive")
    bad({**ok, "nodes": ["x"]}, "nodes[0]", "mapping")
