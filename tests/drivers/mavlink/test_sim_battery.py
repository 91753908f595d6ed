"""The simulated ArduCopter's battery: a current that grows with thrust, the voltage's sag
under it, and the BATT_* failsafes it leads to (ArduPilot's AP_BattMonitor: the low/critical
voltage held for BATT_LOW_TIMER s, raw or sag-compensated by BATT_FS_VOLTSRC; ArduCopter's
``handle_battery_failsafe`` actions), on a manual clock."""

from __future__ import annotations

from typing import Any

import pytest

from temoto.clock import ManualClock
from temoto.drivers.mavlink import protocol as p
from temoto.drivers.mavlink.protocol import Codec
from temoto.drivers.mavlink.sim import SimVehicle

GCS = Codec(255, 190)
VEHICLE = Codec(1, 1)


def _decode(frames: list[bytes]) -> list[Any]:
    return [m for f in frames for m in GCS.decode_datagram(f)]


def _command(cmd: int, *params: float) -> Any:
    values = [*params, *([0.0] * (7 - len(params)))]
    fields = {f"param{i + 1}": v for i, v in enumerate(values)}
    frame = GCS.encode(
        "COMMAND_LONG", target_system=1, target_component=1, command=cmd, confirmation=0, **fields
    )
    (msg,) = VEHICLE.decode_datagram(frame)
    return msg


def _handle(vehicle: SimVehicle, cmd: int, *params: float) -> int:
    (ack,) = _decode(vehicle.commands.handle(_command(cmd, *params)))[:1]
    return int(ack.get_int("result"))


def _run(vehicle: SimVehicle, seconds: float) -> None:
    """Step the model and the failsafes as the step thread does, ``seconds`` of clock."""
    with vehicle.state.lock:
        end = vehicle.state.last + seconds
        while vehicle.state.last < end - 1e-9:
            now = min(vehicle.state.last + vehicle.state.dt, end)
            vehicle.flight.advance(now)
            vehicle.failsafes.check(now)


def _texts(vehicle: SimVehicle) -> list[str]:
    return [text for _severity, text in vehicle.state.texts]


def _frame(vehicle: SimVehicle, name: str) -> Any:
    with vehicle.state.lock:
        return _decode([vehicle.telemetry.frame(name, vehicle.state.last)])[0]


def _fly(battery: float = 100.0, **params: float) -> SimVehicle:
    """A vehicle in GUIDED, armed, taking off to 10 m (not yet there)."""
    vehicle = SimVehicle("batt", clock=ManualClock(), battery=battery, params=params)
    cmds = [
        (p.MAV_CMD_DO_SET_MODE, 1, p.COPTER_MODES["GUIDED"]),
        (p.MAV_CMD_COMPONENT_ARM_DISARM, 1),
        (p.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 10),
    ]
    for cmd, *args in cmds:
        assert _handle(vehicle, cmd, *args) == p.MAV_RESULT_ACCEPTED
    return vehicle


HOVER_AMPS = 0.11 / 100 * 3300 * 3.6  # drain_idle + drain_flight %/s of BATT_CAPACITY, in A


def test_the_current_is_idle_on_the_ground_and_grows_with_climb_and_hover() -> None:
    vehicle = SimVehicle("batt", clock=ManualClock())
    _run(vehicle, 1.0)
    status = _frame(vehicle, "SYS_STATUS")
    assert status.get_int("current_battery") == 0  # disarmed: nothing drawn
    assert status.get_int("voltage_battery") == 16800  # full 4S, no sag
    assert _handle(vehicle, p.MAV_CMD_DO_SET_MODE, 1, p.COPTER_MODES["GUIDED"]) == 0
    assert _handle(vehicle, p.MAV_CMD_COMPONENT_ARM_DISARM, 1) == 0
    _run(vehicle, 1.0)
    idle = vehicle.state.current
    assert idle == pytest.approx(0.01 / 100 * 3300 * 3.6)  # the motors' idle spin
    assert _handle(vehicle, p.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 10) == 0
    _run(vehicle, 2.0)
    climbing = vehicle.state.current  # 2.5 m/s up: momentum theory's extra power
    _run(vehicle, 20.0)
    hover = vehicle.state.current
    assert hover == pytest.approx(HOVER_AMPS, rel=1e-6)
    assert climbing > 1.2 * hover
    status, battery = _frame(vehicle, "SYS_STATUS"), _frame(vehicle, "BATTERY_STATUS")
    assert status.get_int("current_battery") == round(HOVER_AMPS * 100)  # cA
    assert battery.get_int("current_battery") == round(HOVER_AMPS * 100)
    sag = HOVER_AMPS * 4 * 0.01
    assert vehicle.state.voltage() == pytest.approx(vehicle.state.resting_voltage() - sag)
    assert status.get_int("voltage_battery") == round(vehicle.state.voltage() * 1000)
    # the charge used at hover: the current's integral
    before = vehicle.state.consumed_mah()
    _run(vehicle, 60.0)
    assert vehicle.state.consumed_mah() - before == pytest.approx(HOVER_AMPS * 60 / 3.6, rel=1e-6)
    consumed = _frame(vehicle, "BATTERY_STATUS").get_int("current_consumed")
    assert consumed == round(vehicle.state.consumed_mah())


def _below_low_volt(vehicle: SimVehicle, threshold: float, limit: float = 30.0) -> None:
    """Run until the measured voltage drops below ``threshold`` (at most ``limit`` s)."""
    for _ in range(round(limit / 0.02)):
        _run(vehicle, 0.02)
        if vehicle.state.voltage() < threshold:
            return
    raise AssertionError(f"the voltage stayed at {vehicle.state.voltage():.2f} V")


def test_the_low_voltage_failsafe_acts_after_batt_low_timer_under_load() -> None:
    # 30 %: 14.28 V resting, 13.76 V sagging at hover: below BATT_LOW_VOLT 14.0 only in flight
    params = {"BATT_LOW_VOLT": 14.0, "BATT_FS_LOW_ACT": 2, "BATT_LOW_TIMER": 10}
    vehicle = _fly(30.0, **params)
    _below_low_volt(vehicle, 14.0)
    assert vehicle.state.resting_voltage() > 14.0
    _run(vehicle, 9.5)
    assert vehicle.battery_failsafe == 0
    assert vehicle.mode == "GUIDED"
    _run(vehicle, 1.0)
    assert vehicle.battery_failsafe == 1
    assert vehicle.mode == "RTL"  # BATT_FS_LOW_ACT 2
    low = [t for t in _texts(vehicle) if t.startswith("Battery 1 is low ")]
    assert len(low) == 1
    assert low[0].endswith(" mAh")
    assert " used " in low[0]
    charge = _frame(vehicle, "BATTERY_STATUS").get_int("charge_state")
    assert charge == p.MAV_BATTERY_CHARGE_STATE_LOW


def test_sag_compensated_voltage_source_ignores_the_load() -> None:
    params = {"BATT_LOW_VOLT": 14.0, "BATT_FS_LOW_ACT": 2, "BATT_FS_VOLTSRC": 1}
    vehicle = _fly(30.0, **params)
    _below_low_volt(vehicle, 14.0)
    _run(vehicle, 15.0)
    assert vehicle.battery_failsafe == 0
    assert vehicle.mode == "GUIDED"


def test_the_critical_failsafe_follows_the_low_and_lands() -> None:
    params = {
        "BATT_LOW_VOLT": 14.0,
        "BATT_FS_LOW_ACT": 2,  # RTL
        "BATT_CRT_VOLT": 13.7,
        "BATT_FS_CRT_ACT": 1,  # LAND
        "BATT_LOW_TIMER": 5,
    }
    vehicle = _fly(30.0, **params)
    _below_low_volt(vehicle, 14.0)
    _run(vehicle, 6.0)
    assert (vehicle.battery_failsafe, vehicle.mode) == (1, "RTL")
    _below_low_volt(vehicle, 13.7, limit=60.0)  # RTL's climb and the drain take it lower
    _run(vehicle, 4.5)
    assert vehicle.battery_failsafe == 1
    _run(vehicle, 1.0)
    assert (vehicle.battery_failsafe, vehicle.mode) == (2, "LAND")
    assert any(t.startswith("Battery 1 is critical ") for t in _texts(vehicle))
    charge = _frame(vehicle, "BATTERY_STATUS").get_int("charge_state")
    assert charge == p.MAV_BATTERY_CHARGE_STATE_CRITICAL
    _run(vehicle, 60.0)
    assert not vehicle.armed  # landed and disarmed
