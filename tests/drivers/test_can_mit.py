"""MIT-mode motors: frame packing, and the MitMotorDriver on its simulator."""

from __future__ import annotations

import math
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from typing import Any

import can
import pytest
from contract import DriverContract, Rig, eventually
from hypothesis import given
from hypothesis import strategies as st

from temoto.clock import ManualClock
from temoto.drivers import DriverState, Health
from temoto.drivers.can_motor import mitmode as mm
from temoto.drivers.can_motor.mit import MitMotorDriver
from temoto.drivers.can_motor.sim import SimMitMotor
from temoto.drivers.can_motor.sim_model import MIT_MECHANICS
from temoto.drivers.capabilities import Actuator, ControlMode, JointCommand
from temoto.drivers.registry import driver_class
from temoto.errors import (
    DriverInitError,
    DriverOperationError,
    DriverTimeoutError,
    MotorFaultError,
    ProfileError,
)

R = mm.MODELS["AK80-9"]

# ---- packing ---------------------------------------------------------------------------------


def test_special_frames() -> None:
    assert mm.CMD_ENTER.hex() == "fffffffffffffffc"
    assert mm.CMD_EXIT.hex() == "fffffffffffffffd"
    assert mm.CMD_ZERO.hex() == "fffffffffffffffe"
    assert [mm.special(f) for f in (mm.CMD_ENTER, mm.CMD_EXIT, mm.CMD_ZERO)] == [
        "enter",
        "exit",
        "zero",
    ]
    assert mm.special(b"\xff" * 8) is None
    assert mm.special(mm.CMD_ENTER[:7]) is None


def test_command_layout_by_hand() -> None:
    # midpoints: p 0 → 0x7FFF, v 0 → 0x7FF, kp 0 → 0, kd 0 → 0, t 0 → 0x7FF
    assert mm.encode_command(mm.MitCommand(0, 0, 0, 0, 0), R).hex() == "7fff7ff0000007ff"
    top = mm.encode_command(mm.MitCommand(99, 99, 999, 99, 99), R)  # all clamped to the top
    assert top == b"\xff" * 8
    bottom = mm.encode_command(mm.MitCommand(-99, -99, -1, -1, -99), R)
    assert bottom == b"\x00" * 8
    # kp = 500 (0xFFF), everything else at the bottom: the nibbles sit where the manual says
    kp_only = mm.encode_command(mm.MitCommand(-99, -99, 500, 0, -99), R)
    assert kp_only.hex() == "0000000fff000000"


def test_reply_layout_by_hand() -> None:
    data = mm.encode_reply(mm.MitReply(5, 12.5, -50.0, 0.0), R)
    assert data.hex() == "05" + "ffff" + "000" + "7ff"
    assert len(data) == 6
    long = mm.encode_reply(mm.MitReply(5, 12.5, -50.0, 0.0, -5, 2), R)
    assert long[6:] == b"\xfb\x02"
    back = mm.decode_reply(long, R)
    assert (back.motor_id, back.temperature, back.error) == (5, -5, 2)
    assert mm.decode_reply(data, R).temperature is None


finite = st.floats(allow_nan=False, allow_infinity=False)


@given(
    p=st.floats(-R.p_max, R.p_max),
    v=st.floats(-R.v_max, R.v_max),
    kp=st.floats(0, R.kp_max),
    kd=st.floats(0, R.kd_max),
    t=st.floats(-R.t_max, R.t_max),
)
def test_command_round_trips_within_one_step(
    p: float, v: float, kp: float, kd: float, t: float
) -> None:
    back = mm.decode_command(mm.encode_command(mm.MitCommand(p, v, kp, kd, t), R), R)
    step = lambda span, bits: span / ((1 << bits) - 1)  # noqa: E731
    assert abs(back.p - p) <= step(2 * R.p_max, 16) * 1.0001
    assert abs(back.v - v) <= step(2 * R.v_max, 12) * 1.0001
    assert abs(back.kp - kp) <= step(R.kp_max, 12) * 1.0001
    assert abs(back.kd - kd) <= step(R.kd_max, 12) * 1.0001
    assert abs(back.t - t) <= step(2 * R.t_max, 12) * 1.0001


@given(data=st.binary(min_size=8, max_size=8))
def test_every_command_frame_decodes_and_reencodes_to_itself(data: bytes) -> None:
    if mm.special(data) is None:
        assert mm.encode_command(mm.decode_command(data, R), R) == data


@given(data=st.binary(min_size=6, max_size=6))
def test_every_reply_frame_decodes_and_reencodes_to_itself(data: bytes) -> None:
    assert mm.encode_reply(mm.decode_reply(data, R), R) == data


@given(x=st.floats(allow_nan=True), bits=st.sampled_from([12, 16]))
def test_float_to_uint_clamps_everything(x: float, bits: int) -> None:
    u = mm.float_to_uint(x, -1.0, 1.0, bits)
    assert 0 <= u < 1 << bits
    if math.isnan(x) or x <= -1:
        assert u == 0
    if x >= 1:
        assert u == (1 << bits) - 1


def test_bad_lengths_and_ranges() -> None:
    with pytest.raises(ValueError, match="expected 8"):
        mm.decode_command(b"\0" * 6, R)
    with pytest.raises(ValueError, match="6 or 8"):
        mm.decode_reply(b"\0" * 7, R)
    with pytest.raises(ValueError, match="motor id"):
        mm.encode_reply(mm.MitReply(256, 0, 0, 0), R)
    with pytest.raises(ValueError, match="positive"):
        mm.MitRanges(p_max=0)


# ---- the driver ------------------------------------------------------------------------------

RATE = 10.0  # polls per clock second in the rigs (ManualClock: 3 missed polls ≈ 30 ms real)
BOUND = 5 / RATE


def config(channel: str, **extra: Any) -> dict[str, Any]:
    return {
        "link": {"interface": "virtual", "channel": channel},
        "poll_rate": RATE,
        "init_timeout": 0.5,
        "motors": [
            {"motor_id": 1, "joint": "shoulder", "model": "AK80-9", "kp": 30.0, "kd": 1.0},
            {"motor_id": 2, "joint": "elbow", "model": "AK60-6", "gear_ratio": 2.0},
        ],
        **extra,
    }


@pytest.fixture
def clock() -> ManualClock:
    return ManualClock()


@pytest.fixture
def pair(clock: ManualClock) -> Iterator[tuple[MitMotorDriver, SimMitMotor]]:
    channel = f"mit-{uuid.uuid4().hex[:8]}"
    sim, cfg = MitMotorDriver.simulate("arm", config(channel), clock=clock)
    assert isinstance(sim, SimMitMotor)
    driver = MitMotorDriver.from_profile("arm", cfg, clock=clock, where="devices.arm")
    sim.start()
    try:
        yield driver, sim
    finally:
        driver.shutdown()
        sim.close()


def position(driver: MitMotorDriver, joint: str) -> float:
    return driver.read_state().joints[joint].position


def run(
    call: Callable[[], object], clock: ManualClock, timeout: float = 2.0
) -> BaseException | None:
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


class TestMitContract(DriverContract):
    @pytest.fixture
    def rig(self, pair: tuple[MitMotorDriver, SimMitMotor], clock: ManualClock) -> Rig:
        driver, sim = pair
        return Rig(
            driver=driver,
            sim=sim,
            clock=clock,
            act=lambda: driver.command([JointCommand("shoulder", ControlMode.POSITION, 1.0)]),
            acted=lambda: abs(position(driver, "shoulder") - 1.0) < 0.01,
            stamp=lambda: driver.read_state().stamp,
            fault_bound=BOUND,
            init_timeout=0.5,
        )


def test_it_is_an_actuator_in_the_registry(pair: tuple[MitMotorDriver, SimMitMotor]) -> None:
    driver, _ = pair
    assert driver_class("mit_can") is MitMotorDriver
    assert isinstance(driver, Actuator)
    assert driver.joint_names == ("shoulder", "elbow")


def test_modes_units_and_enable(
    pair: tuple[MitMotorDriver, SimMitMotor], clock: ManualClock
) -> None:
    driver, sim = pair
    driver.configure()
    assert not sim.motors[1].enabled
    driver.activate()
    assert sim.motors[1].enabled
    assert sim.motors[2].enabled
    driver.command([JointCommand("elbow", ControlMode.POSITION, 1.5)])  # gear 2: 3 rad motor
    eventually(lambda: abs(position(driver, "elbow") - 1.5) < 0.01, 3.0, clock)
    assert sim.motors[2].pos == pytest.approx(3.0, abs=0.02)
    assert sim.motors[2].command.kp == pytest.approx(20.0, abs=0.2)  # the default kp
    driver.command([JointCommand("shoulder", ControlMode.VELOCITY, 2.0)])
    # velocity mode is kd alone (kp 0): the gearbox's friction leaves a droop, as on a motor
    mech = MIT_MECHANICS["AK80-9"]
    droop = (1.0 * 2.0 - mech.coulomb) / (1.0 + mech.damping)
    eventually(
        lambda: abs(driver.read_state().joints["shoulder"].velocity - droop) < 0.05, 2.0, clock
    )
    driver.command([JointCommand("shoulder", ControlMode.EFFORT, 1.0)])
    eventually(lambda: abs(sim.motors[1].command.t - 1.0) < 0.01, 1.0, clock)
    with pytest.raises(ValueError, match="range"):
        driver.command([JointCommand("shoulder", ControlMode.POSITION, 13.0)])
    with pytest.raises(ValueError, match="no joint"):
        driver.command([JointCommand("wrist", ControlMode.POSITION, 0.0)])
    driver.deactivate()
    assert not sim.motors[1].enabled


def listen(driver: MitMotorDriver) -> tuple[list[Health], threading.Event]:
    got: list[Health] = []
    seen = threading.Event()

    def on(health: Health) -> None:
        got.append(health)
        if health.state is DriverState.FAULT:
            seen.set()

    driver.add_health_listener(on)
    return got, seen


@pytest.mark.parametrize(
    ("kind", "word"), [("overheat", "temperature"), ("overload", "current"), ("voltage", "voltage")]
)
def test_hardware_errors_are_latched_motor_faults(
    pair: tuple[MitMotorDriver, SimMitMotor], clock: ManualClock, kind: str, word: str
) -> None:
    driver, sim = pair
    _, seen = listen(driver)
    driver.configure()
    driver.activate()
    sim.inject("hardware_error", kind=kind, node=2)
    eventually(seen.is_set, 2 / RATE, clock)
    error = driver.health().error
    assert isinstance(error, MotorFaultError)
    assert error.node_id == 2
    assert word in str(error)
    assert kind in str(error)
    assert "elbow" in str(error)
    assert not sim.motors[2].enabled
    sim.clear("hardware_error")
    eventually(lambda: sim.motors[2].error == 0 and sim.motors[1].commands > 3, 0.5, clock)
    assert driver.state is DriverState.FAULT  # latched
    assert run(driver.recover, clock) is None
    driver.activate()
    assert sim.motors[2].enabled


def test_silence_of_one_motor_is_a_timeout_naming_it(
    pair: tuple[MitMotorDriver, SimMitMotor], clock: ManualClock
) -> None:
    driver, sim = pair
    _, seen = listen(driver)
    driver.configure()
    driver.activate()
    sim.inject("silence", node=1)
    took = eventually(seen.is_set, BOUND, clock)
    assert took >= 2 / RATE
    error = driver.health().error
    assert isinstance(error, DriverTimeoutError)
    assert "motor 1 (shoulder)" in str(error)
    sim.clear("silence")
    eventually(lambda: driver.state is DriverState.ACTIVE, BOUND, clock)


def test_corrupt_replies_are_operation_errors(
    pair: tuple[MitMotorDriver, SimMitMotor], clock: ManualClock
) -> None:
    driver, sim = pair
    _, seen = listen(driver)
    driver.configure()
    driver.activate()
    sim.inject("corrupt")
    eventually(seen.is_set, 2 / RATE, clock)
    error = driver.health().error
    assert type(error) is DriverOperationError
    assert "malformed" in str(error)
    sim.clear("corrupt")
    eventually(lambda: driver.state is DriverState.ACTIVE, BOUND, clock)


def test_configure_names_the_silent_motor(clock: ManualClock) -> None:
    channel = f"mit-{uuid.uuid4().hex[:8]}"
    sim, cfg = MitMotorDriver.simulate("arm", config(channel), clock=clock)
    driver = MitMotorDriver.from_profile("arm", cfg, clock=clock, where="arm")
    with sim:
        sim.inject("link_loss")
        error = run(driver.configure, clock)
        assert isinstance(error, DriverInitError)
        assert "motor 1 (shoulder), motor 2 (elbow)" in str(error)
        driver.shutdown()


def bad(cfg: dict[str, Any], path: str, match: str) -> None:
    with pytest.raises(ProfileError, match=match) as info:
        MitMotorDriver.from_profile("arm", cfg, clock=ManualClock(), where="p.yaml: devices.arm")
    assert str(info.value).startswith(f"p.yaml: devices.arm.{path}: "), str(info.value)


def test_profile_errors_name_the_key_path() -> None:
    ok = config("c")
    m = ok["motors"]
    bad({**ok, "rate": 1}, "rate", "unknown key")
    bad({**ok, "motors": [m[0], {**m[1], "motor_id": 1}]}, "motors[1].motor_id", "duplicate")
    bad({**ok, "host_id": 2}, "motors[1].motor_id", "host_id")
    bad({**ok, "motors": [m[0], {**m[1], "joint": "shoulder"}]}, "motors[1].joint", "duplicate")
    bad({**ok, "motors": [{"motor_id": 3}]}, "motors[0].joint", "missing")
    bad({**ok, "motors": [{**m[0], "model": "AK99"}]}, "motors[0].model", "unknown model")
    bad({**ok, "motors": [{**m[0], "kp": 600}]}, "motors[0].kp", "at most 500")
    bad({**ok, "motors": [{**m[0], "kd": -1}]}, "motors[0].kd", "positive")
    inverted = {**m[0], "position_min": 1.0, "position_max": -1.0}
    bad({**ok, "motors": [inverted]}, "motors[0].position_min", "below")
    bad({**ok, "poll_rate": 0}, "poll_rate", "positive")
    bad({**ok, "link": "can0"}, "link", "mapping")


def test_a_late_supervisor_poll_does_not_undo_activation(
    pair: tuple[MitMotorDriver, SimMitMotor], clock: ManualClock, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The supervisor re-sends each motor's held frame every period. A poll sent late by a busy
    # supervisor thread lands after activate's ENTER: it must not be an EXIT (it was, and the
    # motors then ignored every set-point: a CI flake of the contract's fault test).
    driver, sim = pair
    driver.configure()
    real_ping = driver._ping
    late: list[int] = []

    def ping_then_late_poll(frame: bytes) -> None:
        real_ping(frame)
        late.extend(c.replies for c in driver._cache)
        driver._on_period(clock.monotonic())  # what the late poll sends

    monkeypatch.setattr(driver, "_ping", ping_then_late_poll)
    driver.activate()
    eventually(lambda: all(c.replies > n for c, n in zip(driver._cache, late, strict=True)), 1.0)
    assert sim.motors[1].enabled
    assert sim.motors[2].enabled
    driver.command([JointCommand("shoulder", ControlMode.POSITION, 1.0)])
    eventually(lambda: abs(position(driver, "shoulder") - 1.0) < 0.01, 3.0, clock)


def test_a_receive_thread_not_scheduled_is_not_a_silent_motor(
    pair: tuple[MitMotorDriver, SimMitMotor], clock: ManualClock
) -> None:
    # heavy load (seen at 10x the cores): the polls go out, the replies queue, and the receive
    # thread does not run to read them; "no reply to 10 polls" was then a false fault
    driver, _ = pair
    driver.configure()
    driver.activate()
    release, stalled = threading.Event(), threading.Event()
    handle = driver._on_frame

    def starved(msg: can.Message) -> None:
        stalled.set()
        release.wait(30)
        handle(msg)

    driver._on_frame = starved  # type: ignore[method-assign]
    try:
        eventually(stalled.is_set, 1.0, clock)  # the next reply: the thread stops there
        polls = driver.timeout_periods + 5
        for _ in range(polls * 4):  # polls go on meanwhile, unanswered as far as it knows
            clock.advance(0.25 / RATE)
            time.sleep(0.002)
        assert driver.state is DriverState.ACTIVE, driver.health().error
    finally:
        driver._on_frame = handle  # type: ignore[method-assign]
        release.set()
    for _ in range(20):  # the queued replies are read: the motors answer as before
        clock.advance(0.25 / RATE)
        time.sleep(0.002)
    assert driver.state is DriverState.ACTIVE, driver.health().error
