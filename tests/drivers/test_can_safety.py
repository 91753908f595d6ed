"""Safe states, device watchdogs and stream supervision of the CAN motor drivers.

Most tests run a driver on its simulator in virtual time (:class:`ManualClock`). The safe state
and the watchdog of the ODrive driver are also tested against :class:`DocODrive`, a small
emulator written here from the ODrive CANSimple documentation (frame ids ``node_id << 5 |
cmd_id``, little-endian payloads, the heartbeat ``u32 Axis_Error | u8 Axis_State | u8
Procedure_Result | u8 Trajectory_Done_Flag``, ``WATCHDOG_TIMER_EXPIRED`` = 0x01000000 and the
axis disarming to IDLE on expiry), not from our protocol module or simulator.
"""

from __future__ import annotations

import logging
import math
import struct
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from typing import Any

import can
import pytest
from contract import eventually, state

from temoto.clock import ManualClock, MonotonicClock
from temoto.drivers import DriverState, Health
from temoto.drivers.can_motor import cansimple as cs
from temoto.drivers.can_motor import mitmode as mm
from temoto.drivers.can_motor.mit import MitMotorDriver
from temoto.drivers.can_motor.odrive import ODriveDriver
from temoto.drivers.can_motor.sim import SimMitMotor, SimODrive
from temoto.drivers.capabilities import ControlMode, JointCommand
from temoto.errors import DriverOperationError, DriverTimeoutError, ProfileError

HB = 0.1  # heartbeat period, clock seconds
ENC = 0.01  # encoder estimate period
CMD = 0.05  # the driver's command_period
WATCHDOG = 0.2  # the devices' watchdog timeout
RATE = 10.0  # MIT polls per clock second
ODRIVE_LOG = "temoto.drivers.can_motor.detect"
CAN_LOG = "temoto.drivers.can_motor"


def channel(kind: str) -> str:
    return f"{kind}-{uuid.uuid4().hex[:8]}"


def odrive_config(ch: str, **extra: Any) -> dict[str, Any]:
    return {
        "link": {"interface": "virtual", "channel": ch},
        "heartbeat_period": HB,
        "encoder_period": ENC,
        "command_period": CMD,
        "init_timeout": 0.5,
        "nodes": [
            {"node_id": 1, "joint": "left"},
            {"node_id": 2, "joint": "right"},
        ],
        **extra,
    }


def mit_config(ch: str, **extra: Any) -> dict[str, Any]:
    return {
        "link": {"interface": "virtual", "channel": ch},
        "poll_rate": RATE,
        "init_timeout": 0.5,
        "motors": [
            {"motor_id": 1, "joint": "shoulder", "model": "AK80-9"},
            {"motor_id": 2, "joint": "elbow", "model": "AK60-6"},
        ],
        **extra,
    }


@pytest.fixture
def clock() -> ManualClock:
    return ManualClock()


def odrive_rig(clock: ManualClock, **extra: Any) -> tuple[ODriveDriver, SimODrive, str]:
    ch = channel("odrive")
    sim, cfg = ODriveDriver.simulate("base", odrive_config(ch, **extra), clock=clock)
    assert isinstance(sim, SimODrive)
    driver = ODriveDriver.from_profile("base", cfg, clock=clock, where="devices.base")
    return driver, sim, ch


@pytest.fixture
def odrive(clock: ManualClock) -> Iterator[tuple[ODriveDriver, SimODrive, str]]:
    driver, sim, ch = odrive_rig(clock)
    with sim:
        try:
            yield driver, sim, ch
        finally:
            driver.shutdown()


@pytest.fixture
def mit(clock: ManualClock) -> Iterator[tuple[MitMotorDriver, SimMitMotor, str]]:
    ch = channel("mit")
    sim, cfg = MitMotorDriver.simulate("arm", mit_config(ch), clock=clock)
    assert isinstance(sim, SimMitMotor)
    driver = MitMotorDriver.from_profile("arm", cfg, clock=clock, where="devices.arm")
    with sim:
        try:
            yield driver, sim, ch
        finally:
            driver.shutdown()


def faults(driver: ODriveDriver | MitMotorDriver) -> list[Health]:
    """Every FAULT report the driver makes from now on."""
    got: list[Health] = []
    driver.add_health_listener(lambda h: got.append(h) if h.state is DriverState.FAULT else None)
    return got


def let_time_pass(clock: ManualClock, seconds: float, step: float = 0.005) -> None:
    """Move virtual time in small steps, letting the threads run between them."""
    end = clock.monotonic() + seconds
    while clock.monotonic() < end:
        clock.advance(step)
        time.sleep(0.0005)


def send_raw(ch: str, arbitration_id: int, data: bytes, count: int = 1) -> None:
    with can.Bus(interface="virtual", channel=ch) as bus:
        for _ in range(count):
            bus.send(can.Message(arbitration_id=arbitration_id, data=data, is_extended_id=False))


def active(driver: ODriveDriver | MitMotorDriver) -> None:
    driver.configure()
    driver.activate()
    assert state(driver) is DriverState.ACTIVE


# ---- ODrive: safe states ---------------------------------------------------------------------


def test_odrive_idle_from_active(odrive: tuple[ODriveDriver, SimODrive, str]) -> None:
    driver, sim, _ = odrive
    assert driver.safe_state == "idle"  # the default
    active(driver)
    driver.command([JointCommand("left", ControlMode.VELOCITY, 3.0)])
    done = driver.make_safe("test")
    assert done == "left IDLE, right IDLE"
    assert sim.axes[1].state == sim.axes[2].state == cs.AxisState.IDLE
    assert state(driver) is DriverState.INACTIVE
    assert driver.health().ok  # going IDLE on purpose is no fault


def test_odrive_idle_from_fault_is_sent_anyway(
    odrive: tuple[ODriveDriver, SimODrive, str], clock: ManualClock
) -> None:
    driver, sim, _ = odrive
    active(driver)
    sim.inject("no_encoder", node=2)
    limit = driver._axes[1].enc_age.max_age  # at least 0.2 s for a simulator in this process
    eventually(lambda: state(driver) is DriverState.FAULT, limit + 5 * ENC, clock)
    assert driver.make_safe("fault") == "left IDLE, right IDLE"
    assert sim.axes[1].state == sim.axes[2].state == cs.AxisState.IDLE
    seen: set[DriverState] = set()
    for _ in range(40):  # the estimate asked for in make_safe may clear the fault for a while
        let_time_pass(clock, ENC)
        seen.add(state(driver))
    assert DriverState.ACTIVE not in seen  # made safe: never back to ACTIVE by itself
    assert state(driver) is DriverState.FAULT  # the estimates are still missing


def test_odrive_make_safe_does_not_wait_for_a_dead_device(
    odrive: tuple[ODriveDriver, SimODrive, str], clock: ManualClock
) -> None:
    driver, sim, _ = odrive
    active(driver)
    sim.inject("link_loss")
    eventually(lambda: state(driver) is DriverState.FAULT, 5 * HB, clock)
    start = time.monotonic()
    done = driver.make_safe("fault")
    assert time.monotonic() - start < 1.0  # a short, bounded wait (0.1 s), then on
    assert done == "left IDLE sent (unconfirmed), right IDLE sent (unconfirmed)"


def test_odrive_hold_commands_zero_velocity_and_stays_armed(clock: ManualClock) -> None:
    driver, sim, _ = odrive_rig(clock, safe_state="hold", watchdog_timeout=WATCHDOG)
    with sim:
        try:
            active(driver)
            driver.command([JointCommand("left", ControlMode.VELOCITY, 5.0)])
            eventually(lambda: abs(sim.axes[1].vel) > 0.5, 1.0, clock)
            done = driver.make_safe("test")
            assert done == (
                "left hold 0 rev/s (CLOSED_LOOP_CONTROL), right hold 0 rev/s (CLOSED_LOOP_CONTROL)"
            )
            axis = sim.axes[1]
            assert axis.control_mode == cs.ControlMode.VELOCITY_CONTROL
            assert axis.input_vel == 0.0
            sent = axis.commands
            let_time_pass(clock, 0.5)
            assert axis.state == cs.AxisState.CLOSED_LOOP_CONTROL
            assert abs(axis.vel) < 0.01
            assert axis.commands >= sent + 5  # the zero set-point keeps being sent
            assert state(driver) is DriverState.INACTIVE
        finally:
            driver.shutdown()
    assert sim.axes[1].state == cs.AxisState.CLOSED_LOOP_CONTROL  # hold, also at shutdown


def test_odrive_shutdown_leaves_the_axes_idle(odrive: tuple[ODriveDriver, SimODrive, str]) -> None:
    driver, sim, _ = odrive
    active(driver)
    driver.shutdown()
    assert sim.axes[1].state == sim.axes[2].state == cs.AxisState.IDLE


# ---- ODrive: steady set-points and the axis watchdog -----------------------------------------


def test_set_points_are_re_sent_while_active_only(
    odrive: tuple[ODriveDriver, SimODrive, str], clock: ManualClock
) -> None:
    driver, sim, _ = odrive
    active(driver)
    driver.command([JointCommand("right", ControlMode.VELOCITY, 1.0)])
    sent = sim.axes[2].commands
    let_time_pass(clock, 10 * CMD)
    assert sim.axes[2].commands >= sent + 8  # one every command_period, none changed
    assert sim.axes[2].input_vel == pytest.approx(1.0 / (2 * math.pi))
    driver.deactivate()
    sent = sim.axes[2].commands
    let_time_pass(clock, 5 * CMD)
    assert sim.axes[2].commands == sent


def test_watchdog_disarms_the_axes_when_the_driver_stops_feeding(clock: ManualClock) -> None:
    driver, sim, ch = odrive_rig(clock, watchdog_timeout=WATCHDOG)
    assert sim.watchdog_timeout == WATCHDOG  # configured from the profile
    with sim, can.Bus(interface="virtual", channel=ch) as wire:
        try:
            active(driver)
            driver.command([JointCommand("left", ControlMode.VELOCITY, 4.0)])
            let_time_pass(clock, 5 * WATCHDOG)  # fed all along: still armed
            assert sim.axes[1].state == cs.AxisState.CLOSED_LOOP_CONTROL
            assert state(driver) is DriverState.ACTIVE
            driver.on_shutdown()  # the process dies: threads stop, nothing more is sent
            fed = max(a.fed for a in sim.axes.values())
            eventually(
                lambda: all(a.state == cs.AxisState.IDLE for a in sim.axes.values()), 1.0, clock
            )
            took = clock.monotonic() - fed
            assert WATCHDOG < took <= WATCHDOG + sim.tick + 0.005  # + one period (+ a test step)
            bit = cs.AxisError.WATCHDOG_TIMER_EXPIRED
            assert all(a.error & bit for a in sim.axes.values())
            # seen on the wire by anyone: a heartbeat with IDLE and the watchdog bit
            hb_id = cs.arbitration_id(1, cs.Cmd.HEARTBEAT)
            let_time_pass(clock, 2 * HB)
            beats = []
            while (msg := wire.recv(0)) is not None:
                if msg.arbitration_id == hb_id and not msg.is_remote_frame:
                    beats.append(cs.decode_heartbeat(msg.data))
            assert beats[-1].axis_state == cs.AxisState.IDLE
            assert beats[-1].axis_error & bit
        finally:
            driver.shutdown()


# ---- ODrive: supervision -------------------------------------------------------------------


def test_stale_encoder_estimates_with_heartbeats_going_on(
    odrive: tuple[ODriveDriver, SimODrive, str], clock: ManualClock
) -> None:
    driver, sim, _ = odrive
    got = faults(driver)
    active(driver)
    sim.inject("no_encoder", node=1)
    # 3 periods (at least 0.2 s for a simulator in this process), then a second look
    limit = driver._axes[0].enc_age.max_age
    took = eventually(lambda: bool(got), limit + 3 * driver.supervise_period, clock)
    assert took > 2 * ENC
    error = got[0].error
    assert isinstance(error, DriverTimeoutError)
    assert "node 1 (left) encoder estimates stale" in str(error)
    assert "heartbeat" not in str(error)
    sim.clear("no_encoder")
    eventually(lambda: state(driver) is DriverState.ACTIVE, 3 * HB, clock)


def test_an_axis_dropping_to_idle_is_a_fault_until_recovered(
    odrive: tuple[ODriveDriver, SimODrive, str], clock: ManualClock
) -> None:
    driver, sim, _ = odrive
    got = faults(driver)
    active(driver)
    sim.axes[2].state = cs.AxisState.IDLE  # no error bit: e.g. someone else sent IDLE
    eventually(lambda: bool(got), 3 * HB, clock)  # two heartbeats: not a second device's one
    error = got[0].error
    assert isinstance(error, DriverOperationError)
    assert "node 2 (right)" in str(error)
    assert "left CLOSED_LOOP_CONTROL (now IDLE)" in str(error)
    let_time_pass(clock, 3 * HB)
    assert state(driver) is DriverState.FAULT  # not cleared by itself
    driver.recover()
    driver.activate()
    assert sim.axes[2].state == cs.AxisState.CLOSED_LOOP_CONTROL


def test_one_malformed_frame_is_counted_not_a_fault(
    odrive: tuple[ODriveDriver, SimODrive, str],
    clock: ManualClock,
    caplog: pytest.LogCaptureFixture,
) -> None:
    driver, _, ch = odrive
    got = faults(driver)
    active(driver)
    with caplog.at_level(logging.WARNING, logger=CAN_LOG):
        send_raw(ch, cs.arbitration_id(1, cs.Cmd.HEARTBEAT), b"\x00\x00\x00")
        eventually(lambda: driver.bad_frames == 1, 0.1, clock)
        let_time_pass(clock, 3 * HB)
    assert not got
    assert state(driver) is DriverState.ACTIVE
    logged = [r.getMessage() for r in caplog.records if r.name.startswith(CAN_LOG)]
    assert any("malformed HEARTBEAT frame (3 data bytes" in line for line in logged)


def test_a_burst_of_malformed_frames_is_a_fault_until_a_good_heartbeat(
    odrive: tuple[ODriveDriver, SimODrive, str], clock: ManualClock
) -> None:
    driver, _, ch = odrive
    got = faults(driver)
    active(driver)
    # an 8-byte frame with an undefined axis state counts as malformed too
    send_raw(ch, cs.arbitration_id(1, cs.Cmd.HEARTBEAT), bytes(4) + b"\xc8\0\0\0", 2)
    send_raw(ch, cs.arbitration_id(1, cs.Cmd.GET_ENCODER_ESTIMATES), b"\x01", 3)
    eventually(lambda: bool(got), 0.1, clock)
    assert driver.bad_frames == 5
    error = got[0].error
    assert isinstance(error, DriverOperationError)
    assert "5 malformed frames within 1 s" in str(error)
    assert "node 1 (left)" in str(error)
    eventually(lambda: state(driver) is DriverState.ACTIVE, 2 * HB, clock)


def test_two_devices_on_one_node_id_are_reported(clock: ManualClock) -> None:
    driver, sim, ch = odrive_rig(clock)
    impostor = SimODrive(
        {"interface": "virtual", "channel": ch}, [1], clock, heartbeat_period=HB, encoder_period=ENC
    )
    got = faults(driver)
    with sim:
        try:
            active(driver)  # the second device comes after arming (before: see test_duplicates)
            with impostor:
                eventually(lambda: bool(got), 2 * HB * 20, clock)
        finally:
            driver.shutdown()
    error = got[0].error
    assert isinstance(error, DriverOperationError)
    assert "two devices answer as node 1" in str(error)
    assert "duplicate ODrive node 1" in str(error)  # not "the axis left CLOSED_LOOP_CONTROL"


# ---- ODrive: detect --------------------------------------------------------------------------


def mit_frames() -> list[bytes]:
    """MIT-mode frames a host sends to motor 0x41, i.e. on node 2's heartbeat id."""
    ranges = mm.MODELS["AK80-9"]
    return [
        mm.encode_command(mm.MitCommand(0.5, 0.0, 20.0, 1.0, 0.0), ranges),
        mm.encode_command(mm.MitCommand(0.0, 2.0, 0.0, 1.0, 0.0), ranges),
        mm.encode_command(mm.MitCommand(0.0, 0.0, 0.0, 0.0, 0.0), ranges),
        mm.CMD_ENTER,
        mm.CMD_EXIT,
    ]


@pytest.mark.parametrize("data", mit_frames())
def test_mit_frames_are_not_heartbeats(data: bytes) -> None:
    assert cs.heartbeat_problem(data) is not None


def test_detect_skips_a_foreign_frame_and_shows_an_errored_axis(
    caplog: pytest.LogCaptureFixture,
) -> None:
    ch = channel("detect")
    link = {"interface": "virtual", "channel": ch}
    sim = SimODrive(link, [3], MonotonicClock(), heartbeat_period=0.05)
    stop = threading.Event()

    def mit_host() -> None:
        with can.Bus(interface="virtual", channel=ch) as bus:
            while not stop.is_set():
                for data in mit_frames():
                    bus.send(can.Message(arbitration_id=0x41, data=data, is_extended_id=False))
                stop.wait(0.01)

    host = threading.Thread(target=mit_host)
    with sim, caplog.at_level(logging.INFO, logger=ODRIVE_LOG):
        sim.inject("hardware_error", kind="overheat", node=3)
        host.start()
        try:
            entries = ODriveDriver.detect([link], timeout=0.3)
        finally:
            stop.set()
            host.join()
    assert entries == [
        {"driver": "odrive_can", "link": link, "nodes": [{"node_id": 3, "joint": "joint_3"}]}
    ]
    records = [r for r in caplog.records if r.name == ODRIVE_LOG]
    node3 = next(r for r in records if "node 3 " in r.getMessage())
    assert node3.levelno == logging.WARNING
    assert "MOTOR_OVER_TEMP" in node3.getMessage()
    assert any("id 0x041" in r.getMessage() and "not listed" in r.getMessage() for r in records)


# ---- ODrive: profile keys --------------------------------------------------------------------


def odrive_bad(extra: dict[str, Any], path: str, match: str) -> None:
    with pytest.raises(ProfileError, match=match) as info:
        ODriveDriver.from_profile(
            "base", odrive_config("c", **extra), clock=ManualClock(), where="p.yaml: devices.base"
        )
    assert str(info.value).startswith(f"p.yaml: devices.base.{path}: "), str(info.value)


def test_odrive_profile_keys_are_checked() -> None:
    odrive_bad({"safe_state": "coast"}, "safe_state", "idle, hold")
    odrive_bad({"watchdog_timeout": -1}, "watchdog_timeout", "0 .not used. or positive")
    odrive_bad({"watchdog_timeout": 0.08}, "command_period", "half the watchdog_timeout")
    odrive_bad({"command_period": 0}, "command_period", "positive")
    driver = ODriveDriver.from_profile(
        "base",
        odrive_config("c", safe_state="hold", watchdog_timeout=0.5),
        clock=ManualClock(),
        where="x",
    )
    assert (driver.safe_state, driver.watchdog_timeout, driver.command_period) == ("hold", 0.5, CMD)


# ---- MIT motors ------------------------------------------------------------------------------


def test_mit_safe_state_is_zero_torque_then_exit(
    mit: tuple[MitMotorDriver, SimMitMotor, str], clock: ManualClock
) -> None:
    driver, sim, ch = mit
    assert driver.safe_state == "zero_torque"
    sim.motors[1].damping = 1.0  # a load: 3 N·m holds ~3 rad/s, not a free run to v_max
    active(driver)
    driver.command([JointCommand("shoulder", ControlMode.EFFORT, 3.0)])
    eventually(lambda: sim.motors[1].torque > 2.0, 1.0, clock)
    with can.Bus(interface="virtual", channel=ch) as wire:
        done = driver.make_safe("test")
        frames = []
        while (msg := wire.recv(0)) is not None:
            if msg.arbitration_id == 1:
                frames.append(bytes(msg.data))
    assert done == (
        "shoulder off (zero torque, exit motor mode), elbow off (zero torque, exit motor mode)"
    )
    zero = frames.index(mm.encode_command(mm.MitCommand(0, 0, 0, 0, 0), mm.MODELS["AK80-9"]))
    assert frames[zero + 1] == mm.CMD_EXIT  # zero torque first, then exit
    command = mm.decode_command(frames[zero], mm.MODELS["AK80-9"])
    assert command.kp == command.kd == 0.0
    assert abs(command.t) < 0.01  # the wire's nearest to 0 N·m
    assert not sim.motors[1].enabled
    assert not sim.motors[2].enabled
    assert state(driver) is DriverState.INACTIVE


def test_mit_make_safe_in_fault_is_bounded(
    mit: tuple[MitMotorDriver, SimMitMotor, str], clock: ManualClock
) -> None:
    driver, sim, _ = mit
    active(driver)
    sim.inject("silence", node=2)
    eventually(lambda: state(driver) is DriverState.FAULT, 6 / RATE, clock)
    start = time.monotonic()
    done = driver.make_safe("fault")
    assert time.monotonic() - start < 1.0
    assert done == "shoulder off (zero torque, exit motor mode), elbow off (sent, unconfirmed)"
    assert not sim.motors[1].enabled


def test_mit_can_timeout_zeroes_the_command_when_the_host_dies(clock: ManualClock) -> None:
    ch = channel("mit")
    timeout = 0.3
    sim, cfg = MitMotorDriver.simulate("arm", mit_config(ch, can_timeout=timeout), clock=clock)
    assert isinstance(sim, SimMitMotor)
    assert sim.can_timeout == timeout
    sim.motors[1].damping = 1.0  # 3 N·m: 3 rad/s, not a free run past the ±12.5 rad field
    driver = MitMotorDriver.from_profile("arm", cfg, clock=clock, where="devices.arm")
    with sim:
        try:
            active(driver)
            driver.command([JointCommand("shoulder", ControlMode.EFFORT, 3.0)])
            let_time_pass(clock, 3 * timeout)  # polled all along: the command holds
            assert sim.motors[1].command.t == pytest.approx(3.0, abs=0.01)
            assert sim.motors[1].timeouts == 0
            driver.on_shutdown()  # the host dies: no frame after this one
            fed = sim.motors[1].fed
            eventually(lambda: sim.motors[1].timeouts == 1, 1.0, clock)
            assert timeout < clock.monotonic() - fed <= timeout + sim.tick + 0.005
            assert sim.motors[1].command == mm.MitCommand(0, 0, 0, 0, 0)
            assert sim.motors[1].enabled  # the firmware stays in motor mode, at zero torque
            let_time_pass(clock, 0.05)
            assert sim.motors[1].torque == 0.0
        finally:
            driver.shutdown()


def test_mit_one_malformed_reply_is_counted_a_second_is_a_fault(
    mit: tuple[MitMotorDriver, SimMitMotor, str], clock: ManualClock
) -> None:
    driver, _, ch = mit
    got = faults(driver)
    active(driver)
    send_raw(ch, 0, b"\x01\x00\x00")  # on the host id, from "motor 1", 3 bytes
    eventually(lambda: driver.bad_frames == 1, 0.1, clock)
    let_time_pass(clock, 5 / RATE)
    assert not got
    send_raw(ch, 0, b"\x07\x00\x00\x00\x00\x00")  # a reply from a motor not in the profile
    eventually(lambda: bool(got), 0.1, clock)
    error = got[0].error
    assert isinstance(error, DriverOperationError)
    assert "2 malformed replies" in str(error)
    eventually(lambda: state(driver) is DriverState.ACTIVE, 3 / RATE, clock)


def test_mit_stale_replies_are_a_fault_naming_the_stream(
    mit: tuple[MitMotorDriver, SimMitMotor, str], clock: ManualClock
) -> None:
    driver, _, _ = mit
    active(driver)
    cache = driver._by_joint["elbow"]  # replies stopped while polls were not counted
    last = clock.monotonic()
    cache.age.last = last - 10.0
    problem = driver._problem(last)
    assert isinstance(problem, DriverTimeoutError)
    assert "motor 2 (elbow) replies stale" in str(problem)


def test_two_mit_motors_on_one_id_are_reported(clock: ManualClock) -> None:
    ch = channel("mit")
    sim, cfg = MitMotorDriver.simulate("arm", mit_config(ch), clock=clock)
    impostor = SimMitMotor({"interface": "virtual", "channel": ch}, [1], clock)
    driver = MitMotorDriver.from_profile("arm", cfg, clock=clock, where="devices.arm")
    got = faults(driver)
    with sim:
        try:
            active(driver)  # the second motor comes after (before: see test_duplicates)
            with impostor:
                eventually(lambda: bool(got), 2.0, clock)
        finally:
            driver.shutdown()
    error = got[0].error
    assert isinstance(error, DriverOperationError)
    assert "two motors answer as id 1" in str(error)


def test_mit_profile_keys_are_checked() -> None:
    def bad(extra: dict[str, Any], path: str, match: str) -> None:
        with pytest.raises(ProfileError, match=match) as info:
            MitMotorDriver.from_profile(
                "arm", mit_config("c", **extra), clock=ManualClock(), where="p.yaml: devices.arm"
            )
        assert str(info.value).startswith(f"p.yaml: devices.arm.{path}: "), str(info.value)

    bad({"safe_state": "idle"}, "safe_state", "zero_torque")
    bad({"can_timeout": -0.1}, "can_timeout", "0 .not used. or positive")
    bad({"can_timeout": 0.15}, "can_timeout", "two poll periods")


# ---- an ODrive emulated from the documentation ------------------------------------------------


class DocODrive:
    """One ODrive axis as the CANSimple documentation describes it (not our simulator).

    Heartbeat (0x01) every ``hb`` s and encoder estimates (0x09) every ``enc`` s, RTR requests
    answered; Set_Axis_State (0x07), Set_Controller_Mode (0x0B), Set_Input_Pos/Vel/Torque
    (0x0C/0x0D/0x0E) applied; with ``watchdog`` > 0 the axis watchdog: an armed axis whose
    watchdog is not fed (by those commands) for that long goes IDLE with
    WATCHDOG_TIMER_EXPIRED. A requested state is taken a moment later (by the axis's own
    state machine): a heartbeat asked for at once still shows the old state. Stepped by the
    test with :meth:`tick`.
    """

    IDLE, CLOSED_LOOP = 1, 8
    WATCHDOG_TIMER_EXPIRED = 0x01000000

    def __init__(self, ch: str, node: int, clock: ManualClock, watchdog: float = 0.0) -> None:
        self.node, self.clock, self.watchdog = node, clock, watchdog
        self.state, self.error = self.IDLE, 0
        self.pending: int | None = None
        self.control_mode, self.input_vel, self.input_pos = 3, 0.0, 0.0
        self.fed = -math.inf
        self.due_hb = self.due_enc = -math.inf
        self.bus = can.Bus(interface="virtual", channel=ch)
        self.lock = threading.Lock()
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self.listen)
        self.thread.start()

    def close(self) -> None:
        self.stop.set()
        self.thread.join()
        self.bus.shutdown()

    def out(self, cmd: int, data: bytes) -> None:
        self.bus.send(
            can.Message(arbitration_id=self.node << 5 | cmd, data=data, is_extended_id=False)
        )

    def heartbeat(self) -> bytes:
        return struct.pack("<IBBBB", self.error, self.state, 0, 0, 0)

    def listen(self) -> None:
        while not self.stop.is_set():
            msg = self.bus.recv(0.02)
            if msg is None or msg.arbitration_id >> 5 != self.node:
                continue
            cmd = msg.arbitration_id & 0x1F
            with self.lock:
                now = self.clock.monotonic()
                if msg.is_remote_frame:
                    if cmd == 0x01:
                        self.out(0x01, self.heartbeat())
                        self.switch()
                    elif cmd == 0x09:
                        self.out(0x09, struct.pack("<ff", 0.0, 0.0))
                    continue
                data = bytes(msg.data)
                if cmd == 0x07:
                    self.fed = now
                    (wanted,) = struct.unpack_from("<I", data)
                    if wanted in (self.IDLE, self.CLOSED_LOOP):
                        self.pending = wanted
                elif cmd == 0x0B:
                    self.control_mode, _ = struct.unpack("<II", data)
                elif cmd == 0x0C:
                    self.fed = now
                    self.input_pos = struct.unpack_from("<f", data)[0]
                elif cmd == 0x0D:
                    self.fed = now
                    self.input_vel = struct.unpack_from("<f", data)[0]
                elif cmd == 0x0E:
                    self.fed = now

    def switch(self) -> None:
        if self.pending is not None:
            self.state, self.pending = self.pending, None

    def tick(self, hb: float = HB, enc: float = ENC) -> None:
        with self.lock:
            self.switch()
            now = self.clock.monotonic()
            if (
                self.watchdog > 0
                and self.state == self.CLOSED_LOOP
                and now - self.fed > self.watchdog
            ):
                self.state = self.IDLE
                self.error |= self.WATCHDOG_TIMER_EXPIRED
            if now >= self.due_hb:
                self.due_hb = max(self.due_hb + hb, now)
                self.out(0x01, self.heartbeat())
            if now >= self.due_enc:
                self.due_enc = max(self.due_enc + enc, now)
                self.out(0x09, struct.pack("<ff", 0.0, 0.0))


def spin(
    clock: ManualClock, emus: list[DocODrive], pred: Callable[[], bool], timeout: float
) -> float:
    """Advance virtual time (stepping the emulators) until ``pred``; the time it took."""
    start = clock.monotonic()
    real_end = time.monotonic() + 10.0
    while not pred():
        assert clock.monotonic() - start <= timeout, f"not within {timeout} s"
        assert time.monotonic() < real_end, "no progress in real time"
        clock.advance(0.005)
        for emu in emus:
            emu.tick()
        time.sleep(0.0005)
    return clock.monotonic() - start


def in_thread(call: Callable[[], object], clock: ManualClock, emus: list[DocODrive]) -> None:
    errors: list[BaseException] = []

    def target() -> None:
        try:
            call()
        except BaseException as err:
            errors.append(err)

    thread = threading.Thread(target=target)
    thread.start()
    spin(clock, emus, lambda: not thread.is_alive(), 5.0)
    thread.join()
    if errors:
        raise errors[0]


@pytest.fixture
def doc_rig(clock: ManualClock) -> Iterator[tuple[ODriveDriver, list[DocODrive]]]:
    ch = channel("doc")
    emus = [DocODrive(ch, 1, clock, WATCHDOG), DocODrive(ch, 2, clock, WATCHDOG)]
    cfg = odrive_config(ch, watchdog_timeout=WATCHDOG)
    driver = ODriveDriver.from_profile("base", cfg, clock=clock, where="devices.base")
    try:
        in_thread(driver.configure, clock, emus)
        in_thread(driver.activate, clock, emus)
        assert all(e.state == DocODrive.CLOSED_LOOP for e in emus)
        yield driver, emus
    finally:
        driver.shutdown()
        for emu in emus:
            emu.close()


def test_doc_odrive_safe_state_idle(doc_rig: tuple[ODriveDriver, list[DocODrive]]) -> None:
    driver, emus = doc_rig
    driver.command([JointCommand("left", ControlMode.VELOCITY, 2.0)])
    assert driver.make_safe("test") == "left IDLE, right IDLE"
    assert all(e.state == DocODrive.IDLE and e.error == 0 for e in emus)


def test_doc_odrive_hold(doc_rig: tuple[ODriveDriver, list[DocODrive]], clock: ManualClock) -> None:
    driver, emus = doc_rig
    driver.safe_state = "hold"
    driver.command([JointCommand("left", ControlMode.VELOCITY, 2.0)])
    driver.make_safe("test")
    assert emus[0].control_mode == 2  # VELOCITY_CONTROL
    assert emus[0].input_vel == 0.0
    start = clock.monotonic()
    spin(clock, emus, lambda: clock.monotonic() - start >= 3 * WATCHDOG, 1.0)
    assert all(e.state == DocODrive.CLOSED_LOOP and e.error == 0 for e in emus)  # still fed


def test_doc_odrive_watchdog(
    doc_rig: tuple[ODriveDriver, list[DocODrive]], clock: ManualClock
) -> None:
    driver, emus = doc_rig
    driver.command([JointCommand("right", ControlMode.VELOCITY, 2.0)])
    start = clock.monotonic()
    spin(clock, emus, lambda: clock.monotonic() - start >= 5 * WATCHDOG, 2.0)
    assert all(e.state == DocODrive.CLOSED_LOOP and e.error == 0 for e in emus)  # fed steadily
    assert state(driver) is DriverState.ACTIVE
    driver.on_shutdown()  # the process dies
    fed = max(e.fed for e in emus)
    spin(clock, emus, lambda: all(e.state == DocODrive.IDLE for e in emus), 1.0)
    assert clock.monotonic() - fed <= WATCHDOG + 0.005 + 0.005  # one emulator step, one slack
    assert all(e.error == DocODrive.WATCHDOG_TIMER_EXPIRED for e in emus)
