"""SimMitMotor moves as the AK firmware makes it: impedance torque, inertia, friction.

The firmware (Ben Katz's mini-cheetah ``motorcontrol``, ``foc.c`` ``torque_control``, followed by
the CubeMars AK series) evaluates ``kp (p_des - p) + kd (v_des - v) + t_ff``, clamped to the
motor's torque range, on the measured position and velocity in its current loop; the motor then
accelerates as that torque, its inertia and its friction allow. Its ``unpack_cmd`` maps a field
``u`` back as ``u * span / (2**bits - 1) + min``, and the host's ``float_to_uint`` rounds down,
so a zero command arrives as a small negative torque; the special frame ``... FD`` leaves motor
mode (no current: the motor coasts).
"""

from __future__ import annotations

import itertools
import uuid

import can
import pytest

from temoto.clock import ManualClock
from temoto.drivers.can_motor import mitmode as mm
from temoto.drivers.can_motor.sim import SimMitMotor
from temoto.drivers.can_motor.sim_model import MIT_MECHANICS, MitModel

AK80_9 = mm.MODELS["AK80-9"]


class Wire:
    """A SimMitMotor driven frame by frame in virtual time (no bus, no thread)."""

    def __init__(self, model: MitModel) -> None:
        self.clock = ManualClock()
        link = {"interface": "virtual", "channel": f"mitphys-{uuid.uuid4().hex[:8]}"}
        self.sim = SimMitMotor(link, [model], self.clock)
        self.replies: list[mm.MitReply] = []
        self.sim.send = self._send  # type: ignore[method-assign]
        self.motor = model

    def _send(self, arbitration_id: int, data: bytes, node: int) -> None:
        self.replies.append(mm.decode_reply(data, self.motor.ranges))

    def send(self, data: bytes) -> mm.MitReply:
        msg = can.Message(arbitration_id=self.motor.motor_id, data=data, is_extended_id=False)
        self.sim.on_frame(msg)
        return self.replies[-1]

    def run(self, seconds: float, step: float = 0.001) -> None:
        for _ in range(round(seconds / step)):
            self.clock.advance(step)
            self.sim.on_tick(self.clock.monotonic())


def command(p: float, v: float, kp: float, kd: float, t: float) -> bytes:
    return mm.encode_command(mm.MitCommand(p, v, kp, kd, t), AK80_9)


def test_a_step_accelerates_as_the_torque_limit_and_the_inertia_allow() -> None:
    load = 0.05  # kg·m²: a 0.5 kg mass 0.3 m out on the shaft
    motor = MitModel.of(1, "AK80-9")
    motor.load_inertia = load
    wire = Wire(motor)
    wire.send(mm.CMD_ENTER)
    inertia = MIT_MECHANICS["AK80-9"].inertia + load
    before = wire.send(command(1.0, 0.0, 20.0, 1.0, 0.0))
    samples = []
    for _ in range(100):  # 1 s of 10 ms frames, as a 100 Hz host polls
        wire.run(0.01)
        samples.append((before, wire.send(command(1.0, 0.0, 20.0, 1.0, 0.0))))
        before = samples[-1][1]
    # no faster than 18 N·m can accelerate the inertia in 10 ms (plus a field step of slack)
    bound = AK80_9.t_max / inertia * 0.01 + 0.05
    for a, b in samples:
        assert abs(b.v - a.v) <= bound, (a, b)
    first = samples[0][1]
    assert first.v < 16.0  # not the 16-17 rad/s jump of a model without inertia
    accelerating = [b for a, b in samples if b.v - a.v > 0.1 and b.p < 1.0]
    assert accelerating
    assert all(b.t > 0 for b in accelerating)  # driving torque while it speeds up
    for _, b in samples:  # the torque is the law on the state it reports (field steps apart)
        law = max(-18.0, min(18.0, 20.0 * (1.0 - b.p) + 1.0 * (0.0 - b.v)))
        assert b.t == pytest.approx(law, abs=0.25 + 20 * 0.0004 + 0.05 * abs(b.v))
    wire.run(2.0)
    last = wire.send(command(1.0, 0.0, 20.0, 1.0, 0.0))
    assert last.p == pytest.approx(1.0, abs=0.02)  # settles at the set-point (friction aside)
    assert abs(last.v) < 0.05


def test_the_torque_limit_bounds_the_acceleration_of_a_bare_rotor() -> None:
    motor = MitModel.of(1, "AK80-9")
    motor.enabled = True
    motor.command = mm.MitCommand(5.0, 0.0, 500.0, 0.0, 0.0)  # a hard spring far off: saturated
    motor.step(0.0)
    motor.step(0.0005)  # 2 steps of the integration, barely moving: the back-EMF is no matter
    accel = motor.vel / 0.0005
    limit = AK80_9.t_max / motor.inertia
    assert motor.torque == pytest.approx(18.0, rel=0.05)
    assert 0.9 * limit < accel <= limit


@pytest.mark.parametrize("model", sorted(mm.MODELS))
def test_a_zero_torque_command_leaves_a_motor_at_rest(model: str) -> None:
    ranges = mm.MODELS[model]
    motor = MitModel.of(1, model)
    wire = Wire(motor)
    wire.send(mm.CMD_ENTER)
    zero = mm.encode_command(mm.MitCommand(0.0, 0.0, 0.0, 0.0, 0.0), ranges)
    decoded = mm.decode_command(zero, ranges)
    assert decoded.t < 0  # the firmware really receives a tiny negative torque ...
    assert abs(decoded.t) < 0.01 * ranges.t_max  # ... far below the gearbox's friction
    wire.send(zero)
    wire.run(2.0)
    reply = wire.send(zero)
    assert abs(reply.v) <= 2 * ranges.v_max / 4095  # still: at most a field step
    assert motor.vel == 0.0
    assert abs(motor.pos) < 1e-6


def test_zero_torque_lets_a_turning_motor_coast_to_rest_without_turning_round() -> None:
    motor = MitModel.of(1, "AK80-9")
    motor.load_inertia = 0.02
    wire = Wire(motor)
    wire.send(mm.CMD_ENTER)
    wire.send(command(0.0, 10.0, 0.0, 2.0, 0.0))  # velocity mode: 10 rad/s
    wire.run(1.0)
    assert motor.vel == pytest.approx(10.0, rel=0.05)
    wire.send(command(0.0, 0.0, 0.0, 0.0, 0.0))  # the driver's safe state: zero torque
    speeds = []
    for _ in range(400):
        wire.run(0.01)
        speeds.append(motor.vel)
    assert all(v >= 0.0 for v in speeds)  # never backwards
    assert all(b <= a + 1e-9 for a, b in itertools.pairwise(speeds))  # slows down
    assert speeds[-1] == 0.0  # at rest within 4 s under friction


def test_exit_motor_mode_lets_the_motor_coast_to_rest() -> None:
    motor = MitModel.of(1, "AK80-9")
    motor.load_inertia = 0.02
    wire = Wire(motor)
    wire.send(mm.CMD_ENTER)
    wire.send(command(0.0, -8.0, 0.0, 2.0, 0.0))
    wire.run(1.0)
    assert motor.vel == pytest.approx(-8.0, rel=0.05)
    reply = wire.send(mm.CMD_EXIT)
    assert not motor.enabled
    assert reply.v < -7.0  # the exit frame does not stop it at once: it coasts
    wire.run(4.0)
    assert motor.vel == 0.0
    assert motor.torque == 0.0
    assert wire.send(mm.CMD_EXIT).t == pytest.approx(0.0, abs=18.0 / 4095 * 2)
