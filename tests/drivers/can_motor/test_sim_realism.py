"""The CAN simulators at a realism level: seeded noise on what they report, lost cyclic frames.

The figures are ``temoto.drivers.realism.LEVELS`` (``docs/simulators.md``, "Realism"); ``off``
keeps the exact figures, ``typical`` must not fault a driver that supervises the streams.
"""

from __future__ import annotations

import contextlib
import statistics
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from typing import Any

import can
import pytest

from temoto.clock import ManualClock
from temoto.drivers import DriverState
from temoto.drivers.can_motor import cansimple as cs
from temoto.drivers.can_motor import mitmode as mm
from temoto.drivers.can_motor.mit import MitMotorDriver
from temoto.drivers.can_motor.odrive import ODriveDriver
from temoto.drivers.can_motor.sim import AxisModel, MitModel, SimMitMotor, SimODrive
from temoto.drivers.capabilities import ControlMode, JointCommand
from temoto.drivers.realism import LEVELS
from temoto.errors import ProfileError


def link() -> dict[str, Any]:
    return {"interface": "virtual", "channel": f"realism-{uuid.uuid4().hex[:8]}"}


def odrive_frames(seconds: float, **kwargs: Any) -> tuple[SimODrive, list[tuple[int, bytes]]]:
    """What an ODrive axis at rest streams for ``seconds`` (virtual time, no bus, no thread)."""
    axis = AxisModel(1)
    axis.pos = 1.25
    clock = ManualClock()
    sim = SimODrive(link(), [axis], clock, torque_period=0.01, **kwargs)
    frames: list[tuple[int, bytes]] = []
    sim.send = lambda aid, data, node: frames.append((cs.split_id(aid)[1], bytes(data)))  # type: ignore[method-assign]
    for i in range(round(seconds / 0.001)):
        clock.set(i * 0.001)
        sim.on_tick(i * 0.001)
        sim.send_due(i * 0.001)  # what the realism's jitter held back (test_sim_can_timing.py)
    sim.send_due(seconds + 1.0)
    return sim, frames


def estimates(frames: list[tuple[int, bytes]]) -> list[cs.EncoderEstimates]:
    return [cs.decode_encoder_estimates(d) for c, d in frames if c == cs.Cmd.GET_ENCODER_ESTIMATES]


def test_an_odrive_at_off_streams_the_exact_figures_and_loses_nothing() -> None:
    sim, frames = odrive_frames(10.0)
    assert sim.realism.seed is None
    assert sim.frames_lost == 0
    est = estimates(frames)
    assert len(est) == 1000  # every 10 ms
    assert {(e.pos, e.vel) for e in est} == {(1.25, 0.0)}  # the model's state, exactly
    again = odrive_frames(10.0)[1]
    assert frames == again


def test_an_odrive_at_typical_is_noisy_loses_a_few_frames_and_replays_from_its_seed() -> None:
    sim, frames = odrive_frames(20.0, realism="typical", seed=42)
    exact = odrive_frames(20.0)[1]
    noisy, true = estimates(frames), estimates(exact)
    # the noise: positions differ from the exact stream by about the level's sigma
    sigma_turns = LEVELS["typical"].sigma["joint_position"] / (2 * 3.141592653589793)
    assert {(e.pos, e.vel) for e in true} == {(1.25, 0.0)}
    assert sum(1 for e in noisy if e.pos != 1.25) > 0.99 * len(noisy)
    assert sum(1 for e in noisy if e.vel != 0.0) > 0.99 * len(noisy)
    assert max(abs(e.pos - 1.25) for e in noisy) < 6 * sigma_turns
    assert 0.5 * sigma_turns < statistics.pstdev(e.pos for e in noisy) < 1.5 * sigma_turns
    # lost frames: 0.2 % of about 2200 cyclic frames; a few, not many
    assert 0 < sim.frames_lost < 30
    assert len(frames) == len(exact) - sim.frames_lost
    # the same seed gives the same stream; another seed another
    assert odrive_frames(20.0, realism="typical", seed=42)[1] == frames
    assert odrive_frames(20.0, realism="typical", seed=43)[1] != frames


def move(clock: ManualClock, until: Callable[[], bool], seconds: float) -> bool:
    end = clock.monotonic() + seconds
    while clock.monotonic() < end:
        if until():
            return True
        clock.advance(0.002)
        time.sleep(0.0003)
    return until()


def in_thread(call: Callable[[], object], clock: ManualClock) -> None:
    thread = threading.Thread(target=call)
    thread.start()
    assert move(clock, lambda: not thread.is_alive(), 5.0)
    thread.join()


@contextlib.contextmanager
def driven(
    driver: Any, sim: Any, clock: ManualClock, command: JointCommand, seconds: float
) -> Iterator[None]:
    """The simulator up, the driver activated and given ``command``, then ``seconds`` of the
    clock in which it must stay ACTIVE; the driver shut down at the end."""
    with sim:
        try:
            in_thread(driver.configure, clock)
            in_thread(driver.activate, clock)
            driver.command([command])
            assert not move(clock, lambda: driver.state is not DriverState.ACTIVE, seconds)
            yield
        finally:
            driver.shutdown()


def odrive_config(**extra: Any) -> dict[str, Any]:
    return {
        "link": link(),
        "heartbeat_period": 0.1,
        "encoder_period": 0.01,
        "init_timeout": 0.5,
        "nodes": [{"node_id": 1, "joint": "wheel"}],
        **extra,
    }


@pytest.mark.parametrize("seed", [1, 2])
def test_a_driven_odrive_at_typical_does_not_fault(seed: int) -> None:
    # 8 virtual seconds of streams (about 1 s real): the supervision sees noise and lost frames
    clock = ManualClock()
    sim, cfg = ODriveDriver.simulate(
        "base", odrive_config(sim={"realism": "typical", "seed": seed}), clock=clock
    )
    assert isinstance(sim, SimODrive)
    assert sim.realism.describe() == f"realism typical, seed {seed}"
    driver = ODriveDriver.from_profile("base", cfg, clock=clock, where="devices.base")
    with driven(driver, sim, clock, JointCommand("wheel", ControlMode.VELOCITY, 1.0), 8.0):
        assert abs(driver.read_state().joints["wheel"].velocity - 1.0) < 0.2


@pytest.mark.parametrize(
    ("sim", "key", "words"),
    [
        ({"realism": "wild"}, "sim.realism", "off, typical, harsh"),
        ({"realism": "typical", "seed": -1}, "sim.seed", "non-negative integer"),
        ({"seed": "x"}, "sim.seed", "non-negative integer"),
    ],
)
def test_bad_realism_keys_are_refused_in_one_line(sim: Any, key: str, words: str) -> None:
    with pytest.raises(ProfileError, match=words) as err:
        ODriveDriver.from_profile("base", odrive_config(sim=sim), clock=ManualClock(), where="base")
    assert f"base.{key}:" in str(err.value)
    assert "\n" not in str(err.value)
    mit_cfg = {"link": link(), "motors": [{"motor_id": 1, "joint": "j"}], "sim": sim}
    with pytest.raises(ProfileError, match=words) as err:
        MitMotorDriver.from_profile("arm", mit_cfg, clock=ManualClock(), where="arm")
    assert f"arm.{key}:" in str(err.value)


def test_a_mit_entry_refuses_other_sim_keys() -> None:
    cfg = {"link": link(), "motors": [{"motor_id": 1, "joint": "j"}], "sim": {"rate": 1}}
    with pytest.raises(ProfileError, match="realism, seed") as err:
        MitMotorDriver.from_profile("arm", cfg, clock=ManualClock(), where="arm")
    assert "arm.sim.rate:" in str(err.value)


def mit_replies(n: int, **kwargs: Any) -> list[mm.MitReply]:
    motor = MitModel.of(1, "AK80-9")
    motor.pos = 0.3
    clock = ManualClock()
    sim = SimMitMotor(link(), [motor], clock, **kwargs)
    replies: list[mm.MitReply] = []
    sim.send = lambda aid, data, node: replies.append(mm.decode_reply(data, motor.ranges))  # type: ignore[method-assign]
    frame = mm.encode_command(mm.MitCommand(0.3, 0.0, 0.0, 0.0, 0.0), motor.ranges)
    for i in range(n):
        clock.set(i * 0.01)
        sim.send_due(i * 0.01)  # what the realism's jitter held back (test_sim_can_timing.py)
        sim.on_frame(can.Message(arbitration_id=1, data=frame, is_extended_id=False))
    sim.send_due(n * 0.01 + 1.0)
    return replies


def test_mit_replies_are_exact_at_off_and_noisy_and_replayable_at_typical() -> None:
    exact = mit_replies(200)
    assert len({r.p for r in exact}) == 1  # a motor at rest reports one position
    noisy = mit_replies(200, realism="typical", seed=5)
    assert len(noisy) == 200  # replies are never lost
    assert len({r.p for r in noisy}) > 3
    assert len({r.v for r in noisy}) > 1
    assert all(abs(r.p - exact[0].p) < 0.01 for r in noisy)
    assert mit_replies(200, realism="typical", seed=5) == noisy
    sim, cfg = MitMotorDriver.simulate(
        "arm",
        {"link": link(), "motors": [{"motor_id": 1, "joint": "j"}], "sim": {"realism": "harsh"}},
        clock=ManualClock(),
    )
    assert isinstance(sim, SimMitMotor)
    assert sim.realism.level.name == "harsh"
    assert sim.realism.seed is not None
    assert "sim" not in cfg


def test_a_driven_mit_motor_at_harsh_gets_every_late_reply_and_does_not_fault() -> None:
    # the replies go out on the simulator's tick thread at their (jittered, now and then late)
    # times, woken on the manual clock; 10 polls a clock second as the MIT rigs use
    clock = ManualClock()
    cfg = {
        "link": link(),
        "poll_rate": 10.0,
        "init_timeout": 0.5,
        "motors": [{"motor_id": 1, "joint": "j", "model": "AK80-9"}],
        "sim": {"realism": "harsh", "seed": 2},  # its second reply is late
    }
    sim, cfg = MitMotorDriver.simulate("arm", cfg, clock=clock)
    assert isinstance(sim, SimMitMotor)
    driver = MitMotorDriver.from_profile("arm", cfg, clock=clock, where="devices.arm")
    with driven(driver, sim, clock, JointCommand("j", ControlMode.POSITION, 0.5), 6.0):
        assert abs(driver.read_state().joints["j"].position - 0.5) < 0.05
        assert sim.transmitter.stalls > 0  # some replies were late, and arrived
