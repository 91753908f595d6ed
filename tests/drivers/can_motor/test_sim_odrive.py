"""SimODrive as ODrive 0.6 documents it: cyclic message rates (0 = off) and Set_Limits."""

from __future__ import annotations

import math
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import can
import cantools
import odrive_can
import pytest

from temoto.clock import ManualClock
from temoto.drivers import DriverState
from temoto.drivers.can_motor import cansimple as cs
from temoto.drivers.can_motor.odrive import ODriveDriver
from temoto.drivers.can_motor.sim import (
    CYCLIC_RATES,
    TORQUE_CONSTANT,
    AxisModel,
    SimODrive,
)
from temoto.drivers.capabilities import ControlMode, JointCommand
from temoto.errors import DriverTimeoutError, ProfileError

DBC = Path(odrive_can.__file__).parent / "dbc" / "odrive-cansimple-0.6.10.dbc"
NAMES = {
    cs.Cmd.GET_VERSION: "Get_Version",
    cs.Cmd.HEARTBEAT: "Heartbeat",
    cs.Cmd.GET_ERROR: "Get_Error",
    cs.Cmd.GET_ENCODER_ESTIMATES: "Get_Encoder_Estimates",
    cs.Cmd.GET_IQ: "Get_Iq",
    cs.Cmd.GET_TEMPERATURE: "Get_Temperature",
    cs.Cmd.GET_BUS_VOLTAGE_CURRENT: "Get_Bus_Voltage_Current",
    cs.Cmd.GET_TORQUES: "Get_Torques",
    cs.Cmd.GET_POWERS: "Get_Powers",
}


def link() -> dict[str, Any]:
    return {"interface": "virtual", "channel": f"simodrive-{uuid.uuid4().hex[:8]}"}


class Recorder:
    """Stands in for the bus: what the simulator sends, by (node, command)."""

    def __init__(self, sim: SimODrive) -> None:
        self.frames: list[tuple[int, int, bytes]] = []
        sim.send = self.send  # type: ignore[method-assign]

    def send(self, arbitration_id: int, data: bytes, node: int) -> None:
        self.frames.append((*cs.split_id(arbitration_id), bytes(data)))

    def count(self, cmd: int, node: int | None = None) -> int:
        return sum(1 for n, c, _ in self.frames if c == cmd and node in (None, n))


def tick_for(sim: SimODrive, seconds: float, step: float = 0.001) -> None:
    """Drive the simulator's tick as its thread would, in virtual time (no thread, no bus)."""
    for i in range(round(seconds / step)):
        sim.on_tick(i * step)


def frame(node: int, cmd: int, data: bytes = b"", *, rtr: bool = False) -> can.Message:
    return can.Message(
        arbitration_id=cs.arbitration_id(node, cmd),
        data=data,
        is_extended_id=False,
        is_remote_frame=rtr,
        dlc=8 if rtr else len(data),
    )


# ---- cyclic rates ----------------------------------------------------------------------------


def test_the_defaults_are_the_firmware_s_heartbeat_100_ms_and_estimates_10_ms() -> None:
    sim = SimODrive(link(), [1, 2], ManualClock())
    out = Recorder(sim)
    tick_for(sim, 1.0)
    for node in (1, 2):
        assert out.count(cs.Cmd.HEARTBEAT, node) == 10
        assert out.count(cs.Cmd.GET_ENCODER_ESTIMATES, node) == 100
    sent = {c for _, c, _ in out.frames}
    assert sent == {cs.Cmd.HEARTBEAT, cs.Cmd.GET_ENCODER_ESTIMATES}  # the others are off


def test_every_rate_is_set_by_the_odrive_s_name_and_0_turns_one_off() -> None:
    rates = dict.fromkeys(CYCLIC_RATES, 50)
    rates["heartbeat_msg_rate_ms"] = 0
    rates["encoder_msg_rate_ms"] = 0
    rates["powers_msg_rate_ms"] = 250
    sim = SimODrive(link(), [3], ManualClock(), rates_ms=rates)
    out = Recorder(sim)
    tick_for(sim, 1.0)
    assert out.count(cs.Cmd.HEARTBEAT) == 0
    assert out.count(cs.Cmd.GET_ENCODER_ESTIMATES) == 0
    assert out.count(cs.Cmd.GET_POWERS) == 4
    for name, (cmd, _) in CYCLIC_RATES.items():
        if rates[name] == 50:
            assert out.count(cmd) == 20, name


def test_a_message_that_is_off_is_still_answered_on_request() -> None:
    sim = SimODrive(link(), [3], ManualClock(), rates_ms=dict.fromkeys(CYCLIC_RATES, 0))
    out = Recorder(sim)
    tick_for(sim, 0.5)
    assert out.frames == []
    for cmd in CYCLIC_RATES.values():
        sim.on_frame(frame(3, cmd[0], rtr=True))
    assert sorted(c for _, c, _ in out.frames) == sorted(c for c, _ in CYCLIC_RATES.values())
    assert sim.frames_received == len(CYCLIC_RATES)


def test_every_cyclic_payload_decodes_with_the_official_dbc() -> None:
    db = cantools.database.load_file(str(DBC))
    axis = AxisModel(2, state=cs.AxisState.CLOSED_LOOP_CONTROL, damping=0.1)
    axis.control_mode = cs.ControlMode.TORQUE_CONTROL
    axis.input_torque = 0.2
    axis.step(0.0)
    axis.step(1.0)  # up to speed: 0.2 N·m against 0.1 N·m per rev/s → 2 rev/s
    sim = SimODrive(link(), [axis], ManualClock(), rates_ms=dict.fromkeys(CYCLIC_RATES, 10))
    out = Recorder(sim)
    sim.on_tick(1.0)
    decoded = {}
    for node, cmd, data in out.frames:
        msg = db.get_message_by_frame_id(cs.arbitration_id(node, cmd))
        assert msg.name == f"Axis2_{NAMES[cs.Cmd(cmd)]}"
        assert len(data) == msg.length
        decoded[NAMES[cs.Cmd(cmd)]] = msg.decode(data, decode_choices=False)
    assert set(decoded) == set(NAMES.values())
    assert decoded["Get_Torques"]["Torque_Target"] == pytest.approx(0.2)
    assert decoded["Get_Iq"]["Iq_Setpoint"] == pytest.approx(0.2 / TORQUE_CONSTANT)
    assert decoded["Get_Encoder_Estimates"]["Vel_Estimate"] == pytest.approx(2.0, rel=1e-3)
    mechanical = decoded["Get_Powers"]["Mechanical_Power"]
    assert mechanical == pytest.approx(0.2 * 2.0 * 2 * math.pi, rel=1e-3)
    assert decoded["Get_Powers"]["Electrical_Power"] > mechanical  # plus the copper losses
    assert decoded["Get_Bus_Voltage_Current"]["Bus_Voltage"] == pytest.approx(24.0)
    assert decoded["Get_Version"]["Fw_Version_Minor"] == 6


@pytest.mark.parametrize(
    ("rates", "why"),
    [
        ({"heartbeat_msg_rate_ms": -1}, "heartbeat_msg_rate_ms"),
        ({"encoder_msg_rate_ms": math.nan}, "encoder_msg_rate_ms"),
        ({"beacon_msg_rate_ms": 10}, "unknown rate 'beacon_msg_rate_ms'"),
    ],
)
def test_a_bad_rate_is_refused_by_name(rates: dict[str, float], why: str) -> None:
    with pytest.raises(ValueError, match=why):
        SimODrive(link(), [1], ManualClock(), rates_ms=rates)


# ---- Set_Limits ------------------------------------------------------------------------------


def armed(mode: cs.ControlMode, **extra: Any) -> AxisModel:
    axis = AxisModel(1, state=cs.AxisState.CLOSED_LOOP_CONTROL, control_mode=mode, **extra)
    axis.step(0.0)
    return axis


def settle(axis: AxisModel, seconds: float = 2.0, step: float = 0.005) -> None:
    t = axis.stamp or 0.0
    for i in range(1, round(seconds / step) + 1):
        axis.step(t + i * step)


def test_set_limits_over_the_wire_sets_both_limits() -> None:
    sim = SimODrive(link(), [1], ManualClock())
    Recorder(sim)
    sim.on_frame(frame(1, cs.Cmd.SET_LIMITS, cs.encode_set_limits(3.0, 5.0)))
    assert sim.axes[1].vel_limit == 3.0
    assert sim.axes[1].current_limit == 5.0


def test_the_velocity_limit_clamps_a_velocity_set_point() -> None:
    axis = armed(cs.ControlMode.VELOCITY_CONTROL)
    axis.set_limits(4.0, 60.0)
    axis.input_vel = 10.0
    settle(axis)
    assert axis.vel == pytest.approx(4.0, rel=1e-3)


def test_the_velocity_limit_bounds_a_position_move() -> None:
    axis = armed(cs.ControlMode.POSITION_CONTROL)
    axis.set_limits(2.0, 60.0)
    axis.input_pos = 100.0
    t = axis.stamp or 0.0
    speeds = []
    for i in range(1, 200):
        axis.step(t + i * 0.005)
        speeds.append(axis.vel)
    # the position loop asks for far more; the clamped set-point is 2 turn/s (the PI loop's
    # overshoot on reaching it is small)
    assert max(speeds) == pytest.approx(2.0, rel=0.05)
    assert speeds[-1] == pytest.approx(2.0, rel=0.01)  # the integrator's slow tail
    assert axis.pos == pytest.approx(2.0 * 199 * 0.005, rel=0.05)


def test_the_current_limit_clamps_the_torque_and_the_speed_it_holds() -> None:
    axis = armed(cs.ControlMode.TORQUE_CONTROL, damping=0.1)
    axis.set_limits(50.0, 2.5)  # 2.5 A x 0.04 N·m/A = 0.1 N·m
    axis.input_torque = 1.0
    settle(axis)
    assert axis.torque == pytest.approx(0.1)
    assert axis.vel == pytest.approx(0.1 / axis.damping, rel=1e-3)
    velocity = armed(cs.ControlMode.VELOCITY_CONTROL, damping=0.1)
    velocity.set_limits(50.0, 2.5)  # holding 5 rev/s would take 0.5 N·m
    velocity.input_vel = 5.0
    settle(velocity)
    assert velocity.vel == pytest.approx(1.0, rel=1e-3)
    assert velocity.torque == pytest.approx(0.1, rel=1e-3)


def test_a_limit_lowered_below_the_speed_disarms_the_axis_for_overspeed() -> None:
    axis = armed(cs.ControlMode.VELOCITY_CONTROL)
    axis.input_vel = 10.0
    settle(axis)
    assert axis.vel == pytest.approx(10.0, rel=0.01)
    axis.set_limits(5.0, math.inf)  # 10 rev/s > 1.2 x 5 rev/s
    settle(axis, 0.01)
    assert axis.state == cs.AxisState.IDLE
    assert axis.error & cs.AxisError.VELOCITY_LIMIT_VIOLATION


def test_a_limit_that_is_not_finite_and_positive_is_ignored() -> None:
    axis = AxisModel(1)
    axis.set_limits(0.0, -1.0)
    axis.set_limits(math.nan, math.inf)
    assert (axis.vel_limit, axis.current_limit) == (50.0, 10.0)  # the firmware's current_lim


# ---- with the driver, and the profile's sim settings -----------------------------------------


def config(**extra: Any) -> dict[str, Any]:
    return {
        "link": link(),
        "heartbeat_period": 0.1,
        "encoder_period": 0.01,
        "init_timeout": 0.5,
        "nodes": [{"node_id": 1, "joint": "wheel"}],
        **extra,
    }


def move(clock: ManualClock, until: Callable[[], bool], seconds: float = 3.0) -> bool:
    """Advance virtual time in small steps (real pauses for the threads) until ``until()``."""
    end = clock.monotonic() + seconds
    while clock.monotonic() < end:
        if until():
            return True
        clock.advance(0.002)
        time.sleep(0.0005)
    return until()


def in_thread(call: Callable[[], object], clock: ManualClock) -> None:
    errors: list[BaseException] = []

    def target() -> None:
        try:
            call()
        except BaseException as err:
            errors.append(err)

    thread = threading.Thread(target=target)
    thread.start()
    assert move(clock, lambda: not thread.is_alive())
    thread.join()
    if errors:
        raise errors[0]


@pytest.fixture
def clock() -> ManualClock:
    return ManualClock()


@pytest.fixture
def driven(clock: ManualClock) -> Iterator[tuple[ODriveDriver, SimODrive]]:
    sim, cfg = ODriveDriver.simulate("base", config(sim={"torques_msg_rate_ms": 10}), clock=clock)
    assert isinstance(sim, SimODrive)
    assert "sim" not in cfg
    driver = ODriveDriver.from_profile("base", cfg, clock=clock, where="devices.base")
    with sim:
        try:
            yield driver, sim
        finally:
            driver.shutdown()


def test_the_profile_s_torque_rate_gives_the_driver_efforts(
    driven: tuple[ODriveDriver, SimODrive], clock: ManualClock
) -> None:
    driver, sim = driven
    assert sim.periods["torques_msg_rate_ms"] == pytest.approx(0.01)
    in_thread(driver.configure, clock)
    in_thread(driver.activate, clock)
    driver.command([JointCommand("wheel", ControlMode.EFFORT, 0.3)])
    assert move(clock, lambda: driver.read_state().joints["wheel"].effort == pytest.approx(0.3))


def test_the_driver_finds_an_odrive_without_heartbeats_dead() -> None:
    # What the profile check below guards against: the driver supervises the heartbeats.
    # configure() gets its answers (RTR requests are answered), then the silence is a fault.
    clock = ManualClock()
    cfg = config()
    rates = {"heartbeat_msg_rate_ms": 0}
    with SimODrive(cfg["link"], [1], clock, rates_ms=rates):
        driver = ODriveDriver.from_profile("base", cfg, clock=clock, where="devices.base")
        try:
            in_thread(driver.configure, clock)
            assert move(clock, lambda: driver.state is DriverState.FAULT, 1.0)
            error = driver.health().error
            assert isinstance(error, DriverTimeoutError)
            assert "no heartbeat" in str(error)
        finally:
            driver.shutdown()


@pytest.mark.parametrize(
    ("sim", "key", "words"),
    [
        ({"heartbeat_msg_rate_ms": 0}, "sim.heartbeat_msg_rate_ms", "the driver supervises"),
        ({"encoder_msg_rate_ms": 0}, "sim.encoder_msg_rate_ms", "the driver supervises"),
        ({"encoder_msg_rate_ms": 20}, "sim.encoder_msg_rate_ms", "differs from encoder_period"),
        ({"torques_msg_rate_ms": -5}, "sim.torques_msg_rate_ms", r"0 \(off\)"),
        ({"torque_msg_rate_ms": 5}, "sim.torque_msg_rate_ms", "torques_msg_rate_ms"),
        ("fast", "sim", "mapping"),
    ],
)
def test_a_profile_whose_sim_settings_would_fault_the_driver_is_refused(
    sim: Any, key: str, words: str
) -> None:
    with pytest.raises(ProfileError, match=words) as err:
        ODriveDriver.from_profile("base", config(sim=sim), clock=ManualClock(), where="base")
    assert f"base.{key}:" in str(err.value)


def test_the_profile_may_restate_the_supervised_rates() -> None:
    sim, _ = ODriveDriver.simulate(
        "base",
        config(sim={"heartbeat_msg_rate_ms": 100, "encoder_msg_rate_ms": 10, "iq_msg_rate_ms": 0}),
        clock=ManualClock(),
    )
    assert isinstance(sim, SimODrive)
    assert sim.periods["heartbeat_msg_rate_ms"] == pytest.approx(0.1)
    assert sim.periods["iq_msg_rate_ms"] == 0
