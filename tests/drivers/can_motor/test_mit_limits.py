"""MIT motors against their model's limits (issue 25, items 5 and 6).

A wheel driven past the ±12.5 rad position field of the MIT protocol: its reported position
saturates (or wraps), so the driver can no longer see it move; that is a fault naming the motor
and the limit, and the motor is told to stop. Profile values beyond the model's table (CubeMars
AK-series manual, MIT mode) and a ``can_timeout`` beyond the firmware's maximum are refused with
one line naming the file and the key.
"""

from __future__ import annotations

import time
import uuid
from collections.abc import Callable
from typing import Any

import can
import pytest

from temoto.clock import ManualClock
from temoto.drivers import DriverState, Health
from temoto.drivers.can_motor import mitmode as mm
from temoto.drivers.can_motor.mit import MitMotorDriver
from temoto.drivers.can_motor.sim import SimMitMotor
from temoto.drivers.capabilities import ControlMode, JointCommand
from temoto.errors import DriverOperationError


def config(ch: str, **extra: Any) -> dict[str, Any]:
    return {
        "link": {"interface": "virtual", "channel": ch},
        "poll_rate": 50.0,
        "init_timeout": 0.5,
        "motors": [
            {"motor_id": 1, "joint": "left_wheel", "model": "AK80-9"},
            {"motor_id": 2, "joint": "right_wheel", "model": "AK80-9"},
        ],
        **extra,
    }


def until(pred: Callable[[], bool], clock: ManualClock, seconds: float) -> None:
    """Move virtual time in 5 ms steps until ``pred()``; fail after ``seconds`` of it."""
    end = clock.monotonic() + seconds
    while not pred():
        assert clock.monotonic() < end, "did not happen in time"
        clock.advance(0.005)
        time.sleep(0.0005)


@pytest.mark.parametrize("past", ["saturate", "wrap"])
def test_a_wheel_past_the_position_field_is_a_fault_and_is_stopped(past: str) -> None:
    clock = ManualClock()
    ch = f"mit-field-{uuid.uuid4().hex[:8]}"
    driver = MitMotorDriver.from_profile("base", config(ch), clock=clock, where="devices.base")
    sim = SimMitMotor(
        {"interface": "virtual", "channel": ch},
        [1, 2],
        clock,
        tick=0.02,
        past_p_max=past,
    )
    got: list[Health] = []
    driver.add_health_listener(got.append)
    with sim, can.Bus(interface="virtual", channel=ch) as wire:
        try:
            sim.motors[1].pos = 11.5  # a wheel that turned for a while
            driver.configure()
            driver.activate()
            driver.command([JointCommand("left_wheel", ControlMode.VELOCITY, 3.0)])
            until(lambda: driver.state is DriverState.FAULT, clock, 2.0)
            while wire.recv(0) is not None:  # what went out up to the fault
                pass
            for _ in range(20):  # 0.1 s more: the polls go on
                clock.advance(0.005)
                time.sleep(0.0005)
            after = []
            while (msg := wire.recv(0)) is not None:
                if msg.arbitration_id == 1 and mm.special(bytes(msg.data)) is None:
                    after.append(mm.decode_command(bytes(msg.data), mm.MODELS["AK80-9"]).v)
        finally:
            driver.shutdown()
    error = next(h.error for h in got if h.state is DriverState.FAULT)
    assert isinstance(error, DriverOperationError)
    text = str(error)
    assert "motor 1 (left_wheel)" in text
    assert "±12.5 rad" in text
    assert "MIT position field" in text
    assert after, "the motor is no longer polled"
    assert all(abs(v) < 0.05 for v in after), f"still driven after the fault: {after[:5]}"
    assert sim.motors[1].pos > 12.5  # the motor itself turned on past the field
