"""A pause of the driver's process: no stale set-point goes out, no false fault.

The pause is injected: the simulator runs on a clock of its own, which goes on while the
driver's clock stands still and its receive thread is held at a gate (so frames queue on the bus
as they do in a socket while a process is stopped). The driver's clock then jumps over the pause
and the supervisor wakes *before* the receive thread is let go: the order of a SIGCONT that
schedules the supervisor first. A listener on the bus records the wire.
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
import uuid
from collections.abc import Iterator
from typing import Any

import can
import pytest

from temoto.clock import ManualClock
from temoto.drivers import DriverState, Health
from temoto.drivers.can_motor import cansimple as cs
from temoto.drivers.can_motor import mitmode as mm
from temoto.drivers.can_motor.mit import MitMotorDriver
from temoto.drivers.can_motor.odrive import ODriveDriver
from temoto.drivers.capabilities import ControlMode, JointCommand
from temoto.drivers.sim import Simulator

PAUSE = 0.5  # clock seconds the driver stands still
STEP = 0.005
_SET_POINTS = {cs.Cmd.SET_INPUT_POS, cs.Cmd.SET_INPUT_VEL, cs.Cmd.SET_INPUT_TORQUE}


class Rig:
    """A driver on one clock, its simulator on another, a gate on the driver's receiver."""

    def __init__(
        self, driver: Any, sim: Simulator, ch: str, dclock: ManualClock, sclock: ManualClock
    ):
        self.driver, self.sim, self.ch = driver, sim, ch
        self.dclock, self.sclock = dclock, sclock
        self.gate = threading.Event()
        self.gate.set()
        self.health: list[Health] = []
        driver.add_health_listener(self.health.append)

    def start(self, velocity: float) -> None:
        """Activate, command `velocity` on the left joint, run 0.2 s, then gate the receiver."""
        self.driver.configure()
        self.driver.activate()
        self.driver.command([JointCommand("left", ControlMode.VELOCITY, velocity)])
        self.both(0.2)
        self.gated()

    def pause_with_a_command_held(self, listener: can.BusABC, velocity: float) -> None:
        """The process stops while the application waits for the send lock, its check made.

        The application's command (`velocity` on the left joint) was decided before the pause
        and goes on after SIGCONT; the receiver is let go last.
        """
        with self.driver._send_lock:  # held by another sender when the process stopped
            app = threading.Thread(
                target=self.driver.command,
                args=([JointCommand("left", ControlMode.VELOCITY, velocity)],),
                name="temoto-test-app",
            )
            app.start()
            time.sleep(0.1)  # the application waits for the lock, its check made
            self.pause(listener)
            self.dclock.advance(PAUSE)  # SIGCONT
        app.join(5)
        time.sleep(0.1)
        self.gate.set()

    def gated(self) -> None:
        bus = self.driver._bus
        real = bus.recv

        def recv(timeout: float | None = None) -> can.Message | None:
            self.gate.wait()
            return real(timeout)

        bus.recv = recv

    def both(self, seconds: float) -> None:
        """Both clocks move together (the process runs)."""
        end = self.dclock.monotonic() + seconds
        while self.dclock.monotonic() < end:
            self.sclock.advance(STEP)
            self.dclock.advance(STEP)
            time.sleep(0.003)  # slower than real time: the simulator's threads keep up

    def pause(self, listener: can.BusABC) -> list[can.Message]:
        """The driver's process stops for PAUSE; returns what the wire carried meanwhile."""
        self.gate.clear()
        time.sleep(0.1)  # the receiver finishes its current look and stops at the gate
        end = self.sclock.monotonic() + PAUSE
        while self.sclock.monotonic() < end:  # the devices go on
            self.sclock.advance(STEP)
            time.sleep(0.0005)
        return drain(listener)

    def resume(self, *then: JointCommand) -> None:
        """SIGCONT: the supervisor (and the application) run before the receiver."""
        self.dclock.advance(PAUSE)
        if then:
            self.driver.command(list(then))
        time.sleep(0.1)
        self.gate.set()

    def faults(self) -> list[str]:
        return [str(h.error) for h in self.health if h.state is DriverState.FAULT]


def drain(bus: can.BusABC) -> list[can.Message]:
    out = []
    while (msg := bus.recv(0)) is not None:
        out.append(msg)
    return out


@pytest.fixture
def clocks() -> tuple[ManualClock, ManualClock]:
    return ManualClock(), ManualClock()


def odrive_rig(dclock: ManualClock, sclock: ManualClock) -> tuple[Rig, can.BusABC]:
    ch = f"pause-odrive-{uuid.uuid4().hex[:8]}"
    cfg = {
        "link": {"interface": "virtual", "channel": ch},
        "heartbeat_period": 0.1,
        "encoder_period": 0.01,
        "command_period": 0.05,
        "watchdog_timeout": 1.0,
        "init_timeout": 0.5,
        "nodes": [{"node_id": 1, "joint": "left"}, {"node_id": 2, "joint": "right"}],
    }
    sim, cfg = ODriveDriver.simulate("base", cfg, clock=sclock)
    driver = ODriveDriver.from_profile("base", cfg, clock=dclock, where="devices.base")
    return Rig(driver, sim, ch, dclock, sclock), can.Bus(interface="virtual", channel=ch)


@contextlib.contextmanager
def running(rig: Rig, listener: can.BusABC) -> Iterator[tuple[Rig, can.BusABC]]:
    """The simulator and the listener open, the driver shut down at the end."""
    with rig.sim, listener:
        try:
            yield rig, listener
        finally:
            rig.driver.shutdown()


@pytest.fixture
def odrive(clocks: tuple[ManualClock, ManualClock]) -> Iterator[tuple[Rig, can.BusABC]]:
    with running(*odrive_rig(*clocks)) as rig_listener:
        yield rig_listener


def test_odrive_pause_with_heartbeats_flowing_sends_nothing_stale_and_no_fault(
    odrive: tuple[Rig, can.BusABC],
) -> None:
    rig, listener = odrive
    driver = rig.driver
    rig.start(1.0)
    during = rig.pause(listener)
    beats = [m for m in during if cs.split_id(m.arbitration_id)[1] == cs.Cmd.HEARTBEAT]
    assert len(beats) >= 8  # the heartbeats never stopped on the wire
    rig.resume(JointCommand("left", ControlMode.VELOCITY, 2.0))
    rig.both(0.2)
    after = drain(listener)
    kinds = [cs.split_id(m.arbitration_id)[1] for m in after]
    first_beat = kinds.index(cs.Cmd.HEARTBEAT)
    sent = [i for i, k in enumerate(kinds) if k in _SET_POINTS]
    assert sent, f"the set-points never resumed: {driver.state}, faults {rig.faults()}"
    assert sent[0] > first_beat, "a set-point went out before any feedback after the pause"
    assert rig.faults() == []  # 0.5 s < the 1 s watchdog: the heartbeats show it
    assert driver.state is DriverState.ACTIVE
    left = [m for m in after if m.arbitration_id == cs.arbitration_id(1, cs.Cmd.SET_INPUT_VEL)]
    vel, _ = cs.decode_set_input_vel(bytes(left[-1].data))
    assert math.isclose(vel, 2.0 / (2 * math.pi), rel_tol=1e-6)  # the newest, once judged
    assert driver.gaps >= 1


def mit_rig(dclock: ManualClock, sclock: ManualClock, can_timeout: float) -> tuple[Rig, can.BusABC]:
    ch = f"pause-mit-{uuid.uuid4().hex[:8]}"
    cfg = {
        "link": {"interface": "virtual", "channel": ch},
        "poll_rate": 20.0,
        "init_timeout": 0.5,
        "can_timeout": can_timeout,
        "motors": [
            {"motor_id": 1, "joint": "left", "model": "AK80-9"},
            {"motor_id": 2, "joint": "right", "model": "AK80-9"},
        ],
    }
    sim, cfg = MitMotorDriver.simulate("base", cfg, clock=sclock)
    driver = MitMotorDriver.from_profile("base", cfg, clock=dclock, where="devices.base")
    return Rig(driver, sim, ch, dclock, sclock), can.Bus(interface="virtual", channel=ch)


def set_points(frames: list[can.Message]) -> list[tuple[int, float]]:
    """(index, velocity) of every MIT command frame to motor 1 (rad/s)."""
    out = []
    for i, m in enumerate(frames):
        data = bytes(m.data)
        if m.arbitration_id == 1 and mm.special(data) is None:
            out.append((i, mm.decode_command(data, mm.MODELS["AK80-9"]).v))
    return out


@pytest.mark.parametrize("can_timeout", [0.0, 2.0])
def test_mit_pause_shorter_than_the_can_timeout_resumes_after_fresh_replies(
    clocks: tuple[ManualClock, ManualClock], can_timeout: float
) -> None:
    rig, listener = mit_rig(*clocks, can_timeout=can_timeout)
    with running(rig, listener):
        rig.start(2.99)
        rig.pause(listener)
        rig.resume()
        rig.both(0.5)
        after = drain(listener)
    polls = set_points(after)
    first_reply = next(i for i, m in enumerate(after) if m.arbitration_id == 0)
    stale = [i for i, v in polls if abs(v - 2.99) < 0.05]
    assert stale, "the set-point never resumed"
    assert stale[0] > first_reply, "the held set-point went out before a reply after the pause"
    assert all(abs(v) < 0.05 for i, v in polls if i < first_reply)  # only damping polls
    assert rig.faults() == []


def test_mit_pause_longer_than_the_can_timeout_is_a_fault_and_sends_nothing_stale(
    clocks: tuple[ManualClock, ManualClock],
) -> None:
    rig, listener = mit_rig(*clocks, can_timeout=0.2)
    with running(rig, listener):
        rig.start(2.99)
        rig.pause(listener)
        rig.resume()
        rig.both(0.3)
        after = drain(listener)
    assert [v for _, v in set_points(after) if abs(v - 2.99) < 0.05] == []
    faults = rig.faults()
    assert faults, "the expired CAN timeout was not reported"
    assert "can_timeout (0.2 s)" in faults[0]
    assert "motor 1 (left)" in faults[0]


def test_mit_pause_seen_first_by_the_receiver_is_no_false_stale_fault(
    clocks: tuple[ManualClock, ManualClock],
) -> None:
    # The other order of a SIGCONT: the receiver looks at the link (empty: the motors answer
    # polls only, and none were sent during the pause) before the supervisor runs. The replies'
    # age then says nothing about the motors (issue 25: a false "replies stale" in 3 of 4 runs).
    rig, listener = mit_rig(*clocks, can_timeout=2.0)
    driver = rig.driver
    with running(rig, listener):
        rig.start(2.99)
        rig.pause(listener)
        with driver._cond:  # the supervisor cannot go on while this is held
            rig.dclock.advance(PAUSE)
            rig.gate.set()
            time.sleep(0.2)  # the receiver finds the link empty, after the pause
        rig.both(0.5)
        after = drain(listener)
    assert rig.faults() == []
    assert driver.gaps >= 1
    polls = set_points(after)
    first_reply = next(i for i, m in enumerate(after) if m.arbitration_id == 0)
    assert all(abs(v) < 0.05 for i, v in polls if i < first_reply)  # only damping polls
    assert any(abs(v - 2.99) < 0.05 for _, v in polls), "the set-point never resumed"


def test_odrive_set_point_decided_before_the_pause_waits_for_the_feedback_after_it(
    odrive: tuple[Rig, can.BusABC],
) -> None:
    # The process stops while the application's thread has decided to send (it found no gap)
    # and waits for the send lock; after SIGCONT its set-point must not go out before the
    # devices' feedback was judged (issue 25: a stale command 8 ms after SIGCONT).
    rig, listener = odrive
    driver = rig.driver
    rig.start(1.0)
    rig.pause_with_a_command_held(listener, 2.0)
    rig.both(0.2)
    after = drain(listener)
    kinds = [cs.split_id(m.arbitration_id)[1] for m in after]
    sent = [i for i, k in enumerate(kinds) if k in _SET_POINTS]
    assert sent, f"the set-points never resumed: {driver.state}, faults {rig.faults()}"
    assert cs.Cmd.HEARTBEAT in kinds[: sent[0]], "a set-point went out before any feedback"
    assert rig.faults() == []
    assert driver.state is DriverState.ACTIVE


def test_mit_set_point_decided_before_the_pause_waits_for_the_replies_after_it(
    clocks: tuple[ManualClock, ManualClock],
) -> None:
    # as above, for MIT motors: the held command goes out only after a reply to a damping poll
    rig, listener = mit_rig(*clocks, can_timeout=2.0)
    driver = rig.driver
    with running(rig, listener):
        rig.start(1.0)
        rig.pause_with_a_command_held(listener, 2.99)
        rig.both(0.5)
        after = drain(listener)
    polls = set_points(after)
    replies = [i for i, m in enumerate(after) if m.arbitration_id == 0]
    moving = [i for i, v in polls if abs(v) > 0.05]
    assert moving, f"the set-point never resumed: {driver.state}, faults {rig.faults()}"
    assert replies, "no reply after the pause"
    assert replies[0] < moving[0], "a command went out before a reply after the pause"
    assert rig.faults() == []
