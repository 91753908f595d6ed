"""The Dynamixel simulator at a realism level, and the driver living with it.

Noise on Present Position / Velocity / Current / Temperature (never on the model's state), and
the status packets of a poll (SYNC_READ and the like) lost now and then: a timeout for the
driver, which faults only after ``timeout_polls`` polls in a row fail and asks a one-shot read
again once.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import replace
from typing import Any

import pytest
from dxl_polled import follow

from temoto.clock import ManualClock
from temoto.drivers import DriverState
from temoto.drivers.capabilities import ControlMode, JointCommand
from temoto.drivers.dynamixel import _sdk
from temoto.drivers.dynamixel import control_table as ct
from temoto.drivers.dynamixel._sdk import COMM_RX_TIMEOUT, COMM_SUCCESS, SdkPort
from temoto.drivers.dynamixel.driver import SIM_REPLY_TIMEOUT, DynamixelDriver
from temoto.drivers.dynamixel.sim import SimDynamixelChain
from temoto.drivers.realism import (
    SERIAL_REPLY_TIMING,
    Realism,
    RealismLevel,
    SerialReplyDelay,
    SerialReplyTiming,
)
from temoto.errors import ProfileError


def _address(name: str) -> int:
    for reg in ct.MODELS["XM430-W350"].registers:
        if reg.name == name:
            return reg.address
    raise KeyError(name)


def readings(sim: SimDynamixelChain, clock: ManualClock, name: str, n: int = 200) -> list[int]:
    out = []
    for _ in range(n):
        clock.advance(0.01)
        out.append(sim.read_register(1, _address(name)))
    return out


@pytest.fixture
def sims() -> Iterator[Any]:
    made: list[SimDynamixelChain] = []

    def make(**kwargs: Any) -> tuple[SimDynamixelChain, ManualClock]:
        clock = ManualClock()
        sim = SimDynamixelChain({1: "XM430-W350"}, clock=clock, name="arm", **kwargs)
        made.append(sim)
        return sim, clock

    yield make
    for sim in made:
        sim.close()


def test_at_off_the_present_registers_are_the_model_s(sims: Any) -> None:
    sim, clock = sims()
    for name in ("Present Position", "Present Velocity", "Present Temperature"):
        assert len(set(readings(sim, clock, name))) == 1, name


def test_at_typical_they_are_noisy_and_replay_from_the_seed(sims: Any) -> None:
    sim, clock = sims(realism="typical", seed=9)
    position = readings(sim, clock, "Present Position")
    current = readings(sim, clock, "Present Current")
    temperature = readings(sim, clock, "Present Temperature")
    assert len(set(position)) > 1  # sigma 0.0005 rad is a third of a tick: now and then one
    assert max(abs(v - position[0]) for v in position) <= 4
    assert len(set(current)) > 5  # 0.1 A in 2.69 mA units
    assert {29, 30, 31} & set(temperature)
    assert len(set(temperature)) > 1
    sim2, clock2 = sims(realism="typical", seed=9)
    assert readings(sim2, clock2, "Present Position") == position
    # the model itself is untouched: at rest, still at rest
    assert sim.read_register(1, _address("Moving")) == 0


def config(**extra: Any) -> dict[str, Any]:
    servos = [{"id": i, "joint": f"j{i}", "model": "XM430-W350"} for i in (1, 2)]
    return {"link": "/dev/null", "poll_rate": 100, "servos": servos, **extra}


def test_a_lost_reply_to_the_first_syncread_does_not_fail_configure() -> None:
    # seed 2 on the device "arm" at a 50 % loss: the first poll's replies are lost, the second's
    # come (found by drawing Realism(...).lost() in turn); the driver asks once more
    clock = ManualClock()
    realism = Realism(RealismLevel("lossy", drop=0.5), seed=2, device="arm")
    sim = SimDynamixelChain({1: "XM430-W350", 2: "XM430-W350"}, clock=clock, name="arm")
    sim.realism = realism
    cfg = config(link=f"serial:{sim.path}", reply_timeout=SIM_REPLY_TIMEOUT)
    with sim, DynamixelDriver.from_profile("arm", cfg, clock=clock, where="arm") as driver:
        driver.configure()
        assert sim.replies_lost >= 1
        assert driver.state is DriverState.INACTIVE


@pytest.mark.parametrize("seed", [3, 4])
def test_a_driven_chain_at_typical_does_not_fault(seed: int) -> None:
    clock = ManualClock()
    sim, cfg = DynamixelDriver.simulate(
        "arm", config(sim={"realism": "typical", "seed": seed}), clock=clock
    )
    assert isinstance(sim, SimDynamixelChain)
    assert sim.realism.describe() == f"realism typical, seed {seed}"
    with sim, DynamixelDriver.from_profile("arm", cfg, clock=clock, where="arm") as driver:
        driver.configure()
        driver.activate()
        driver.command([JointCommand("j1", ControlMode.POSITION, 0.5)])
        t0 = clock.monotonic()
        follow(driver, clock, lambda: clock.monotonic() - t0 >= 6.0, 7.0, real_timeout=60.0)
        assert driver.state is DriverState.ACTIVE, driver.health().error
        assert abs(driver.read_state().joints["j1"].position - 0.5) < 0.01


@pytest.mark.parametrize(
    ("sim", "key", "words"),
    [
        ({"realism": "rough"}, "sim.realism", "off, typical, harsh"),
        ({"seed": 1.5}, "sim.seed", "non-negative integer"),
        ({"noise": 1}, "sim.noise", "realism, seed"),
        ("typical", "sim", "mapping"),
    ],
)
def test_bad_sim_keys_are_refused_in_one_line(sim: Any, key: str, words: str) -> None:
    with pytest.raises(ProfileError, match=words) as err:
        DynamixelDriver.from_profile("arm", config(sim=sim), clock=ManualClock(), where="arm")
    assert f"arm.{key}:" in str(err.value)


# ---- late status packets (issue 30, item 3) ------------------------------------------------

SDK_TIMEOUT = 0.034  # dynamixel-sdk's own: twice the 16 ms latency timer plus 2 ms


def test_late_replies_stay_within_the_sdk_timeout_at_typical_and_pass_it_at_harsh() -> None:
    def draws(level: str, seed: int, n: int = 20000) -> list[float]:
        delays = SerialReplyDelay(Realism(level, seed=seed, device="arm"))
        return [delays.delay(poll=True) for _ in range(n)]

    assert set(draws("off", 1, 100)) == {0.0}
    typical = draws("typical", 5)
    assert max(typical) < SDK_TIMEOUT  # never a timeout
    assert sum(d > 0.002 for d in typical) > 100  # about 1 % late (the latency timer at 16 ms)
    harsh = draws("harsh", 5)
    late = [d for d in harsh if d > 0.02]
    assert 0.03 < len(late) / len(harsh) < 0.05  # 4 %
    assert sum(d > SDK_TIMEOUT for d in late) > 0.8 * len(late)
    assert sum(d > SIM_REPLY_TIMEOUT for d in late) > 0.2 * len(late)
    assert draws("harsh", 5, 500) == harsh[:500]  # replayed from the seed
    assert draws("harsh", 6, 500) != harsh[:500]
    # a single READ's or WRITE's status packet gets the jitter only
    single = SerialReplyDelay(Realism("harsh", seed=5, device="arm"))
    assert max(single.delay(poll=False) for _ in range(5000)) < 0.01


def _late_sim(delay: float) -> SimDynamixelChain:
    """A chain of two XM430-W350 whose every poll's status packets come ``delay`` s late."""
    sim = SimDynamixelChain(
        {1: "XM430-W350", 2: "XM430-W350"}, clock=ManualClock(), name="arm", realism="typical"
    )
    sim.reply_delays = SerialReplyDelay(
        sim.realism, SerialReplyTiming("late", late=1.0, late_delay=(delay, delay))
    )
    return sim


def test_the_sim_sends_a_poll_s_status_packets_late() -> None:
    with _late_sim(0.06) as sim:
        port = SdkPort(sim.path, 1_000_000, reply_timeout=0.5)
        port.open()
        try:
            reader = port.sync_reader(*ct.FAST_READ, [1, 2])
            t0 = time.monotonic()
            result, data, _ = reader.read()
            took = time.monotonic() - t0
            assert result == COMM_SUCCESS
            assert set(data) == {1, 2}
            assert took >= 0.06
            assert sim.replies_late == 1
            # a single READ gets the jitter only (never late: the figures make every poll late)
            assert port.read(1, ct.MODEL_NUMBER.address, 2)[:2] == (1020, COMM_SUCCESS)
            assert sim.replies_late == 1
        finally:
            port.close()


def test_waiting_for_a_late_reply_costs_no_cpu() -> None:
    # dynamixel-sdk polls its non-blocking port in a loop until the reply or its timeout: a
    # busy host (or the simulator in this process) loses a core to every wait. The wait is
    # for the line now: the reading thread's CPU time stays far below the time it waited.
    with _late_sim(0.3) as sim:
        port = SdkPort(sim.path, 1_000_000, reply_timeout=0.5)
        port.open()
        try:
            reader = port.sync_reader(*ct.FAST_READ, [1, 2])
            cpu0, t0 = time.thread_time(), time.monotonic()
            for _ in range(2):
                result, data, _ = reader.read()
                assert result == COMM_SUCCESS
                assert set(data) == {1, 2}
            waited, cpu = time.monotonic() - t0, time.thread_time() - cpu0
            assert waited >= 0.6
            assert cpu < 0.03, f"{cpu * 1000:.0f} ms of CPU for {waited * 1000:.0f} ms waited"
        finally:
            port.close()


def test_a_stall_of_the_reading_thread_is_not_counted_as_the_reply_s_lateness(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # A loaded machine stalls the process for 0.3 s during a poll: the simulator in it (or a
    # real line's kernel buffer) could not answer meanwhile. The 0.1 s reply timeout counts
    # the time the host watched the line, so the reply 0.35 s after the instruction is taken.
    waits: list[float] = []
    wait_readable = _sdk._wait_readable

    def stalled(fd: int, seconds: float) -> None:
        if not waits:
            time.sleep(0.3)  # the thread is not scheduled
        waits.append(seconds)
        wait_readable(fd, seconds)

    monkeypatch.setattr(_sdk, "_wait_readable", stalled)
    with _late_sim(0.35) as sim:
        port = SdkPort(sim.path, 1_000_000, reply_timeout=0.1)
        port.open()
        try:
            reader = port.sync_reader(*ct.FAST_READ, [1, 2])
            result, data, _ = reader.read()
            assert result == COMM_SUCCESS, port.result_text(result)
            assert set(data) == {1, 2}
            assert waits
        finally:
            port.close()
    with _late_sim(0.35) as sim:  # without a stall, 0.35 s is late past the timeout
        port = SdkPort(sim.path, 1_000_000, reply_timeout=0.1)
        port.open()
        try:
            assert port.sync_reader(*ct.FAST_READ, [1, 2]).read()[0] == COMM_RX_TIMEOUT
        finally:
            port.close()


def test_a_late_answer_to_another_syncread_is_dropped_not_taken() -> None:
    # the slow read's status packets (3 bytes of data) come 0.3 s late, after the host gave up
    # (0.2 s): they reach the host during the next SYNC_READ (1 byte: Hardware Error Status; 0.1
    # s of slack either side for a loaded machine). Taken for its answer, the voltage's low byte
    # (120: 12.0 V) would read as a hardware error.
    with _late_sim(0.3) as sim:
        port = SdkPort(sim.path, 1_000_000, reply_timeout=0.2)
        port.open()
        try:
            slow = port.sync_reader(*ct.STATUS_READ, [1, 2])
            errors = port.sync_reader(ct.HARDWARE_ERROR_STATUS.address, 1, [1, 2])
            assert slow.read()[0] == COMM_RX_TIMEOUT
            result, data, _ = errors.read()
            assert data == {}, f"a late status packet taken for the answer: {data}"
            assert result == COMM_RX_TIMEOUT  # as if its own answer was lost
            assert port.stray_packets >= 1
        finally:
            port.close()


def test_a_late_poll_answer_is_not_taken_for_a_single_read_s() -> None:
    with _late_sim(0.3) as sim:  # as above: late past the timeout, within the next one
        port = SdkPort(sim.path, 1_000_000, reply_timeout=0.2)
        port.open()
        try:
            torques = port.sync_reader(ct.TORQUE_ENABLE.address, 1, [1, 2])
            assert torques.read()[0] == COMM_RX_TIMEOUT
            # a 1-byte status packet where 4 are awaited: dynamixel-sdk indexes past its end
            value, result, _ = port.read(1, ct.GOAL_POSITION.address, 4)
            assert result == COMM_SUCCESS
            assert value == sim.read_register(1, ct.GOAL_POSITION.address)
            assert port.stray_packets >= 1
        finally:
            port.close()


@pytest.mark.parametrize("seed", [1, 2])
def test_a_driven_chain_at_harsh_faults_clearly_or_not_at_all(
    seed: int, caplog: pytest.LogCaptureFixture
) -> None:
    # every tenth poll reads the status (3 bytes) and the hardware errors (1 byte) after the
    # fast read (10 bytes): late answers cross between them; none may be taken for another
    clock = ManualClock()
    sim, cfg = DynamixelDriver.simulate(
        "arm", config(status_every=2, sim={"realism": "harsh", "seed": seed}), clock=clock
    )
    assert isinstance(sim, SimDynamixelChain)
    sim.reply_delays = SerialReplyDelay(  # harsh's lateness, ten times as often
        sim.realism, replace(SERIAL_REPLY_TIMING["harsh"], late=0.4)
    )
    with sim, DynamixelDriver.from_profile("arm", cfg, clock=clock, where="arm") as driver:
        driver.configure()
        driver.activate()
        driver.command([JointCommand("j1", ControlMode.POSITION, 0.5)])
        t0 = clock.monotonic()
        follow(driver, clock, lambda: clock.monotonic() - t0 >= 0.8, 3.0, real_timeout=60.0)
        assert sim.longest_late > SIM_REPLY_TIMEOUT  # some came after the driver gave up
        if driver.state is DriverState.FAULT:
            error = str(driver.health().error)
            assert error.startswith("arm: "), error
            assert "hardware error" not in error, error
            assert "\n" not in error
    assert "Traceback" not in caplog.text
    assert "poll failed" not in caplog.text
    assert "hardware error" not in caplog.text
