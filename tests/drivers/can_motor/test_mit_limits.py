"""MIT motors against their model's limits.

A wheel driven past the ±12.5 rad position field of the MIT protocol: its reported position
saturates (or wraps), so the driver can no longer see it move; that is a fault naming the motor
and the limit, and the motor is told to stop. Profile values beyond the model's table (CubeMars
AK-series manual, MIT mode) and a ``can_timeout`` beyond the firmware's maximum are refused with
one line naming the file and the key.
"""

from __future__ import annotations

import subprocess
import sys
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import can
import pytest

from temoto.clock import ManualClock
from temoto.drivers import DriverState, Health
from temoto.drivers.can_motor import mitmode as mm
from temoto.drivers.can_motor.mit import MitMotorDriver
from temoto.drivers.can_motor.sim import SimMitMotor
from temoto.drivers.capabilities import ControlMode, JointCommand
from temoto.errors import DriverOperationError, ProfileError


def config(ch: str, **extra: Any) -> dict[str, Any]:
    return {
        "link": {"interface": "virtual", "channel": ch},
        "poll_rate": 20.0,
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
        time.sleep(0.002)  # the simulator's and the driver's threads keep up on a loaded machine


def field(h: Health) -> bool:
    """A fault report about the position field (not a slow reply on a loaded machine)."""
    return h.state is DriverState.FAULT and "MIT position field" in str(h.error)


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
            until(lambda: any(field(h) for h in got), clock, 2.0)
            while wire.recv(0) is not None:  # what went out up to the fault
                pass
            for _ in range(40):  # 0.2 s more: the polls go on
                clock.advance(0.005)
                time.sleep(0.002)
            after = []
            while (msg := wire.recv(0)) is not None:
                if msg.arbitration_id == 1 and mm.special(bytes(msg.data)) is None:
                    after.append(mm.decode_command(bytes(msg.data), mm.MODELS["AK80-9"]).v)
        finally:
            driver.shutdown()
    error = next(h.error for h in got if field(h))
    assert isinstance(error, DriverOperationError)
    text = str(error)
    assert "motor 1 (left_wheel)" in text
    assert "±12.5 rad" in text
    assert "MIT position field" in text
    assert after, "the motor is no longer polled"
    assert all(abs(v) < 0.05 for v in after), f"still driven after the fault: {after[:5]}"
    assert sim.motors[1].pos > 12.5  # the motor itself turned on past the field


# ---- the profile against the model's table ---------------------------------------------------


def refused(extra: dict[str, Any], motor: dict[str, Any] | None = None) -> str:
    entry = config("c", **extra)
    if motor is not None:
        entry["motors"] = [{"motor_id": 1, "joint": "shoulder", "model": "AK80-9", **motor}]
    with pytest.raises(ProfileError) as info:
        MitMotorDriver.from_profile(
            "arm", entry, clock=ManualClock(), where="arm.yaml: devices.arm"
        )
    return str(info.value)


def test_a_can_timeout_above_the_firmware_maximum_is_refused() -> None:
    text = refused({"can_timeout": 5.0})
    assert text.startswith("arm.yaml: devices.arm.can_timeout: 5 s is above")
    assert "maximum 2.5 s" in text
    assert "\n" not in text


@pytest.mark.parametrize(
    ("motor", "key", "words"),
    [
        (
            {"velocity_limit": 80.0},
            "velocity_limit",
            "80 rad/s is above the AK80-9's velocity range ±50",
        ),
        (
            {"position_min": -20.0, "position_max": 20.0},
            "position_max",
            "20 rad is beyond the AK80-9's position field ±12.5",
        ),
        ({"position_min": -20.0, "position_max": 1.0}, "position_min", "-20 rad is beyond"),
        ({"torque_limit": 40.0}, "torque_limit", "40 N·m is above the AK80-9's torque range ±18"),
        (
            {"velocity_limit": 30.0, "gear_ratio": 2.0},
            "velocity_limit",
            "30 rad/s (gear_ratio 2) is above",
        ),
    ],
)
def test_joint_limits_beyond_the_model_s_fields_are_refused(
    motor: dict[str, Any], key: str, words: str
) -> None:
    text = refused({}, motor)
    assert text.startswith(f"arm.yaml: devices.arm.motors[0].{key}: "), text
    assert words in text
    assert "\n" not in text


def test_limits_within_the_fields_and_a_2_5_s_timeout_are_taken() -> None:
    entry = config("c", can_timeout=2.5)
    entry["motors"] = [
        {
            "motor_id": 1,
            "joint": "shoulder",
            "model": "AK80-9",
            "position_min": -12.5,
            "position_max": 12.5,
            "velocity_limit": 50.0,
            "torque_limit": 18.0,
        }
    ]
    driver = MitMotorDriver.from_profile("arm", entry, clock=ManualClock(), where="arm.yaml")
    driver.shutdown()


def test_the_robot_command_exits_2_with_one_line(tmp_path: Path) -> None:
    ch = f"mit-profile-{uuid.uuid4().hex[:8]}"
    profile = tmp_path / "arm.yaml"
    profile.write_text(
        "robot: arm_mit\n"
        "sim: true\n"
        "devices:\n"
        "  arm:\n"
        "    driver: mit_can\n"
        f"    link: {{interface: virtual, channel: {ch}}}\n"
        "    motors:\n"
        "      - {motor_id: 1, joint: shoulder, model: AK80-9}\n"
        "      - {motor_id: 2, joint: elbow, model: AK80-9, torque_limit: 40}\n"
    )
    proc = subprocess.run(
        [sys.executable, "-m", "temoto.managers.robot", "--profile", str(profile), "--local"],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert proc.returncode == 2, proc.stderr[-2000:]
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert f"{profile}" in lines[0]
    assert "devices.arm.motors[1].torque_limit" in lines[0]
    assert "Traceback" not in proc.stderr
