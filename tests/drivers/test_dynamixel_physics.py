"""The simulated X-series servo moves, draws current and heats as the ROBOTIS e-Manual describes.

From the X-series e-Manual (XM430-W350 page): Profile Acceleration (108, 214.577 rev/min² per
unit) and Profile Velocity (112, 0.229 rev/min per unit) shape a velocity-based trapezoidal
profile in the position modes, Profile Acceleration alone the velocity ramp in Velocity mode,
and Velocity Trajectory (136) / Position Trajectory (140) report the profile; the Current Limit
(38) bounds the current (Present Current, 126, in 2.69 mA units); the stall figures (4.1 N·m at
2.3 A, 12 V) give the torque per ampere; Present Temperature (146) rises with the load; past the
Temperature Limit (31) the Overheating bit (2) of Hardware Error Status (70) is set, Torque
Enable is cleared (Shutdown, 63, has bit 2 set from the factory) and every status packet carries
the Alert bit, until a REBOOT; Shutdown without bit 2 does not detect it.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterator
from typing import Any

import pytest
from dxl_sdk_client import sdk_client

from temoto.clock import ManualClock
from temoto.drivers.dynamixel import control_table as ct
from temoto.drivers.dynamixel import protocol as p
from temoto.drivers.dynamixel.sim import SimDynamixelChain
from temoto.drivers.dynamixel.sim_servo import Servo, move

dxl: Any = pytest.importorskip("dynamixel_sdk")

XM430 = ct.MODELS["XM430-W350"]
TICKS_PER_UNIT_S = 0.229 * 4096 / 60  # Profile/Goal Velocity unit in ticks/s
TICKS_PER_ACCEL_UNIT = 214.577 * 4096 / 3600  # Profile Acceleration unit in ticks/s²


def servo(**registers: int) -> Servo:
    s = Servo(1, XM430)
    for name, value in registers.items():
        s.set(name.replace("_", " "), value)
    s.set("Torque Enable", 1)
    return s


def run(s: Servo, seconds: float, step: float = 0.01) -> list[dict[str, int]]:
    """Step the servo; its registers after every step."""
    out = []
    for _ in range(round(seconds / step)):
        move(s, step)
        out.append(
            {
                name: s.value(name)
                for name in (
                    "Present Position",
                    "Present Velocity",
                    "Present Current",
                    "Velocity Trajectory",
                    "Moving Status",
                    "Present Temperature",
                )
            }
        )
    return out


def test_position_moves_follow_the_trapezoidal_profile() -> None:
    s = servo(Profile_Acceleration=10, Profile_Velocity=50)
    s.set("Goal Position", 3048)  # 1000 ticks from 2048
    trace = run(s, 2.5)
    accel = 10 * TICKS_PER_ACCEL_UNIT  # 2441 ticks/s²
    cruise = 50 * TICKS_PER_UNIT_S  # 781.5 ticks/s
    # the profile's velocity ramps at the acceleration, then cruises at the profile velocity
    assert trace[9]["Velocity Trajectory"] == pytest.approx(accel * 0.1 / TICKS_PER_UNIT_S, abs=1)
    assert trace[49]["Velocity Trajectory"] == 50
    assert max(r["Velocity Trajectory"] for r in trace) == 50
    # a trapezoid takes distance / cruise + cruise / acceleration (1.6 s here)
    planned = 1000 / cruise + cruise / accel
    arrived = next(i for i, r in enumerate(trace) if r["Present Position"] == 3048) * 0.01
    assert planned - 0.05 <= arrived <= planned + 0.2
    assert all(r["Moving Status"] & 2 for r in trace[: int(planned * 100) - 5])  # profile on
    assert trace[-1]["Moving Status"] & 1  # in position
    assert abs(trace[-1]["Present Velocity"]) <= 1


def test_velocity_mode_ramps_at_the_profile_acceleration() -> None:
    s = Servo(1, XM430)
    s.set("Operating Mode", int(ct.OperatingMode.VELOCITY))
    s.set("Profile Acceleration", 20)
    s.set("Torque Enable", 1)
    s.set("Goal Velocity", 100)
    trace = run(s, 1.0)
    ramp = 100 * TICKS_PER_UNIT_S / (20 * TICKS_PER_ACCEL_UNIT)  # 0.32 s
    halfway = trace[round(ramp * 50) - 1]["Velocity Trajectory"]
    assert halfway == pytest.approx(50, abs=3)
    assert trace[round(ramp * 50) - 1]["Present Velocity"] < 60
    assert trace[-1]["Present Velocity"] == 100


def test_the_current_limit_bounds_current_and_acceleration() -> None:
    def reach(current_limit: int) -> tuple[float, int]:
        s = servo(Current_Limit=current_limit)
        s.load_inertia = 0.05  # kg·m²: a 0.5 kg payload 0.3 m out
        s.set("Goal Position", 3072)  # a quarter turn
        trace = run(s, 3.0, 0.005)
        arrived = next(i for i, r in enumerate(trace) if r["Present Position"] >= 3070)
        return arrived * 0.005, max(abs(r["Present Current"]) for r in trace)

    weak_time, weak_current = reach(100)  # 0.269 A: 0.48 N·m
    strong_time, strong_current = reach(1193)  # the initial value: the stall torque
    assert weak_current <= 100
    assert weak_current >= 95  # it pushes at its limit while it accelerates
    assert strong_current > 500
    # 0.48 N·m on 0.05 kg·m²: not there before sqrt(2 d / a) (accelerating all the way)
    quickest = math.sqrt(2 * (math.pi / 2) / (100 * 0.00269 * XM430.torque_constant / 0.05))
    assert weak_time >= quickest
    assert strong_time < weak_time - 0.15  # full current: there much sooner


def test_a_servo_heats_with_its_load_and_cools_without() -> None:
    light = servo()
    run(light, 60.0, 0.1)
    assert light.value("Present Temperature") <= 32  # a servo holding nothing stays cool
    held = servo()
    held.load_torque = 2.0  # N·m held at standstill: ~1.1 A
    trace = run(held, 30.0, 0.1)
    temps = [r["Present Temperature"] for r in trace]
    assert temps[-1] > temps[0] + 10  # warms under load
    assert all(b >= a for a, b in itertools.pairwise(temps))
    held.load_torque = 0.0
    run(held, 300.0, 0.5)
    assert held.value("Present Temperature") < temps[-1] - 5  # and cools again


def test_overheating_sets_bit_2_and_turns_torque_off() -> None:
    s = servo()
    s.load_torque = 4.0  # about the stall torque: 2.2 A
    trace = run(s, 120.0, 0.1)
    hot = next(i for i, r in enumerate(trace) if r["Present Temperature"] >= 80)
    assert 5.0 < hot * 0.1 < 100.0
    assert s.hardware_error & p.HardwareError.OVERHEATING
    assert s.value("Torque Enable") == 0
    assert s.value("Present Current") == 0  # output 0 %


def test_without_bit_2_in_shutdown_overheating_is_not_detected() -> None:
    s = servo(Shutdown=0x34 & ~0x04)
    s.load_torque = 4.0
    run(s, 120.0, 0.1)
    assert s.value("Present Temperature") > 85
    assert s.hardware_error == 0
    assert s.value("Torque Enable") == 1


@pytest.fixture
def chain() -> Iterator[tuple[SimDynamixelChain, ManualClock, Any, Any]]:
    clock = ManualClock()
    with SimDynamixelChain({1: "XM430-W350"}, clock=clock) as sim:
        port, ph = sdk_client(sim.path, sim)
        yield sim, clock, port, ph
        port.closePort()


def test_an_overheated_servo_answers_with_the_alert_bit_until_it_cooled_and_rebooted(
    chain: tuple[SimDynamixelChain, ManualClock, Any, Any],
) -> None:
    sim, clock, port, ph = chain
    assert ph.write1ByteTxRx(port, 1, 64, 1) == (dxl.COMM_SUCCESS, 0)
    sim.set_load(1, torque=4.0)
    for _ in range(120):
        clock.advance(1.0)
        temperature, result, error = ph.read1ByteTxRx(port, 1, 146)
        assert result == dxl.COMM_SUCCESS
        if error & p.ALERT_BIT:
            break
    assert error & p.ALERT_BIT
    assert temperature >= 80
    assert ph.read1ByteTxRx(port, 1, 70)[0] & p.HardwareError.OVERHEATING
    assert ph.read1ByteTxRx(port, 1, 64)[0] == 0
    sim.set_load(1)
    assert ph.reboot(port, 1) == (dxl.COMM_SUCCESS, 0)  # still hot: it trips again
    clock.advance(0.1)
    assert ph.read1ByteTxRx(port, 1, 70)[0] & p.HardwareError.OVERHEATING
    clock.advance(600.0)  # torque off: it cools
    assert ph.read1ByteTxRx(port, 1, 146)[0] < 50
    assert ph.reboot(port, 1) == (dxl.COMM_SUCCESS, 0)
    value, result, error = ph.read1ByteTxRx(port, 1, 70)
    assert (value, result, error) == (0, dxl.COMM_SUCCESS, 0)
