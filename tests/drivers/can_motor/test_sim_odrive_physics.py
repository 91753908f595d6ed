"""SimODrive's axes as the ODrive firmware drives them, and what they say of themselves.

Written from the ODrive documentation ("Control Structure and Tuning": a position P loop, a
velocity PI loop with ``vel_gain`` / ``vel_integrator_gain``, the torque clamped by the motor's
current limit; ``Set_Limits`` sets ``vel_limit`` and the current limit) and the 0.6.10 DBC
(``Get_Version``'s fields, ``Heartbeat``'s ``Procedure_Result`` values: SUCCESS 0, BUSY 1,
CANCELLED 2, DISARMED 3).
"""

from __future__ import annotations

import math
import re
import uuid
from pathlib import Path

import can
import cantools
import odrive_can
import pytest

from temoto.clock import ManualClock
from temoto.drivers.can_motor import cansimple as cs
from temoto.drivers.can_motor.sim import SimODrive
from temoto.drivers.can_motor.sim_model import AxisModel

DBC = Path(odrive_can.__file__).parent / "dbc" / "odrive-cansimple-0.6.10.dbc"


def spinning(speed: float, *, inertia: float, load: float, damping: float) -> AxisModel:
    """An armed axis in velocity control, settled at ``speed`` turn/s (ample current)."""
    axis = AxisModel(
        1,
        state=cs.AxisState.CLOSED_LOOP_CONTROL,
        control_mode=cs.ControlMode.VELOCITY_CONTROL,
        inertia=inertia,
        load_inertia=load,
        damping=damping,
        current_limit=60.0,
        vel_gain=5.0,  # tuned stiff for the load, as the tuning guide has one do
        vel_integrator_gain=10.0,
    )
    axis.step(0.0)
    axis.input_vel = speed
    for i in range(1, 3001):
        axis.step(i * 0.001)
    assert axis.vel == pytest.approx(speed, rel=1e-3)
    return axis


def stop(axis: AxisModel, current_limit: float) -> tuple[float, list[tuple[float, float]]]:
    """Set the current limit, command 0 turn/s; the seconds to below 0.038 turn/s and a trace."""
    axis.set_limits(axis.vel_limit, current_limit)
    axis.input_vel = 0.0
    start = axis.stamp or 0.0
    trace = []
    for i in range(1, 5001):
        axis.step(start + i * 0.001)
        trace.append((axis.vel, axis.torque))
        if abs(axis.vel) < 0.038:  # 0.24 rad/s
            return i * 0.001, trace
    raise AssertionError("not still within 5 s")


def test_a_stop_decelerates_as_fast_as_the_current_limit_allows() -> None:
    inertia, load, damping = 3e-4, 0.0317, 0.1
    axis = spinning(2.0, inertia=inertia, load=load, damping=damping)
    seconds, trace = stop(axis, current_limit=50.0)  # 50 A x 0.04 N·m/A = 2 N·m
    turning = 2 * math.pi * (inertia + load)  # N·m per turn/s²
    # the velocity loop asks for far more than 2 N·m: the torque sits at the limit
    saturated = [t for v, t in trace if v > 0.5]
    assert saturated
    assert all(t == pytest.approx(-2.0) for t in saturated)
    # no stop is quicker than 2 N·m (helped by the load's friction) decelerating the inertia
    quickest = turning / damping * math.log((2.0 + damping * 2.0) / (2.0 + damping * 0.038))
    assert quickest <= seconds <= quickest + 0.15  # plus the PI loop's tail below the limit
    assert seconds > 0.15  # not the 50 ms lag of a model without inertia


def test_a_lower_current_limit_or_a_heavier_load_stops_later() -> None:
    quick, _ = stop(spinning(2.0, inertia=3e-4, load=0.01, damping=0.1), current_limit=50.0)
    weak, _ = stop(spinning(2.0, inertia=3e-4, load=0.01, damping=0.1), current_limit=25.0)
    heavy, _ = stop(spinning(2.0, inertia=3e-4, load=0.02, damping=0.1), current_limit=50.0)
    assert weak > 1.6 * quick
    assert heavy > 1.6 * quick


def test_the_torque_estimate_and_iq_follow_the_limited_torque() -> None:
    axis = spinning(2.0, inertia=3e-4, load=0.03, damping=0.1)
    axis.set_limits(axis.vel_limit, 50.0)
    axis.input_vel = 0.0
    axis.step((axis.stamp or 0.0) + 0.02)
    payload = cs.encode_torques(axis.torque_target, axis.torque)
    target, estimate = cs.decode_torques(payload)
    assert estimate == pytest.approx(-2.0)  # the current limit's torque
    assert target < -2.0  # the velocity loop wanted more


def test_an_idle_axis_coasts_down_under_its_friction() -> None:
    axis = spinning(2.0, inertia=3e-4, load=0.03, damping=0.1)
    axis.idle()
    start = axis.stamp or 0.0
    axis.step(start + 0.1)
    rate = 0.1 / (2 * math.pi * (3e-4 + 0.03))  # 1/s
    assert axis.vel == pytest.approx(2.0 * math.exp(-rate * 0.1), rel=0.01)
    assert axis.torque == 0.0


# ---- Get_Version and Procedure_Result, decoded with the official DBC -------------------------


class Wire:
    def __init__(self) -> None:
        self.clock = ManualClock()
        link = {"interface": "virtual", "channel": f"odphys-{uuid.uuid4().hex[:8]}"}
        self.sim = SimODrive(link, [3], self.clock, heartbeat_period=0.0, encoder_period=0.0)
        self.frames: list[tuple[int, bytes]] = []
        self.sim.send = self._send  # type: ignore[method-assign]
        self.db = cantools.database.load_file(str(DBC))

    def _send(self, arbitration_id: int, data: bytes, node: int) -> None:
        self.frames.append((arbitration_id, bytes(data)))

    def to(self, cmd: int, data: bytes = b"", *, rtr: bool = False) -> None:
        self.sim.on_frame(
            can.Message(
                arbitration_id=cs.arbitration_id(3, cmd),
                data=data,
                is_extended_id=False,
                is_remote_frame=rtr,
                dlc=8 if rtr else len(data),
            )
        )

    def ask(self, cmd: int, name: str) -> dict[str, float]:
        self.frames.clear()
        self.to(cmd, rtr=True)
        arbitration_id, data = self.frames[-1]
        msg = self.db.get_message_by_frame_id(arbitration_id)
        assert msg.name == f"Axis3_{name}"
        return dict(msg.decode(data, decode_choices=False))

    def result(self) -> int:
        return int(self.ask(cs.Cmd.HEARTBEAT, "Heartbeat")["Procedure_Result"])

    def wait(self, seconds: float) -> None:
        end = self.clock.monotonic() + seconds
        while self.clock.monotonic() < end:
            self.clock.advance(0.01)
            self.sim.on_tick(self.clock.monotonic())


def test_get_version_names_a_real_board_and_the_dbc_firmware() -> None:
    wire = Wire()
    version = wire.ask(cs.Cmd.GET_VERSION, "Get_Version")
    hardware = (
        version["Hw_Version_Major"],
        version["Hw_Version_Minor"],
        version["Hw_Version_Variant"],
    )
    assert hardware != (0, 0, 0)
    assert hardware == (4, 4, 58)  # an ODrive Pro, "v4.4-58V"
    firmware = (
        version["Fw_Version_Major"],
        version["Fw_Version_Minor"],
        version["Fw_Version_Revision"],
    )
    assert firmware == (0, 6, 10)  # the firmware of the DBC
    assert version["Fw_Version_Unreleased"] == 0
    decoded = cs.decode_version(wire.frames[-1][1])
    assert (decoded.hardware, decoded.firmware) == ("4.4-58", "0.6.10")


def test_procedure_result_is_busy_in_closed_loop_and_says_how_it_ended() -> None:
    wire = Wire()
    assert wire.result() == cs.ProcedureResult.SUCCESS  # nothing ran since power-on
    wire.to(cs.Cmd.SET_AXIS_STATE, cs.encode_set_axis_state(cs.AxisState.CLOSED_LOOP_CONTROL))
    assert wire.result() == cs.ProcedureResult.BUSY  # closed-loop control is running
    wire.to(cs.Cmd.SET_AXIS_STATE, cs.encode_set_axis_state(cs.AxisState.IDLE))
    assert wire.result() == cs.ProcedureResult.CANCELLED  # ended by a state request
    wire.to(cs.Cmd.SET_AXIS_STATE, cs.encode_set_axis_state(cs.AxisState.CLOSED_LOOP_CONTROL))
    assert wire.result() == cs.ProcedureResult.BUSY
    wire.to(cs.Cmd.ESTOP)
    beat = wire.ask(cs.Cmd.HEARTBEAT, "Heartbeat")
    assert beat["Procedure_Result"] == cs.ProcedureResult.DISARMED  # ended by an error
    assert beat["Axis_State"] == cs.AxisState.IDLE
    wire.to(cs.Cmd.SET_AXIS_STATE, cs.encode_set_axis_state(cs.AxisState.CLOSED_LOOP_CONTROL))
    beat = wire.ask(cs.Cmd.HEARTBEAT, "Heartbeat")
    assert beat["Axis_State"] == cs.AxisState.IDLE  # an axis with errors does not arm
    assert beat["Procedure_Result"] == cs.ProcedureResult.DISARMED


def test_a_watchdog_expiry_ends_closed_loop_as_disarmed() -> None:
    wire = Wire()
    wire.sim.watchdog_timeout = 0.1
    wire.to(cs.Cmd.SET_AXIS_STATE, cs.encode_set_axis_state(cs.AxisState.CLOSED_LOOP_CONTROL))
    wire.wait(0.3)
    beat = wire.ask(cs.Cmd.HEARTBEAT, "Heartbeat")
    assert beat["Axis_State"] == cs.AxisState.IDLE
    assert beat["Procedure_Result"] == cs.ProcedureResult.DISARMED


# ---- the profile's sim keys give the simulated axes their mechanics --------------------------


def entry(sim: dict[str, object]) -> dict[str, object]:
    return {
        "link": {"interface": "virtual", "channel": f"odphys-{uuid.uuid4().hex[:8]}"},
        "heartbeat_period": 0.1,
        "encoder_period": 0.01,
        "nodes": [{"node_id": 1, "joint": "left"}, {"node_id": 2, "joint": "right"}],
        "sim": sim,
    }


def test_the_profile_sim_keys_set_every_axis_mechanics() -> None:
    from temoto.drivers.can_motor.odrive import ODriveDriver

    keys = {"load_inertia": 0.032, "damping": 0.1, "current_limit": 50.0, "vel_gain": 10.0}
    sim, _ = ODriveDriver.simulate(
        "base", entry({**keys, "torques_msg_rate_ms": 10}), clock=ManualClock()
    )
    assert isinstance(sim, SimODrive)
    for axis in sim.axes.values():
        assert (axis.load_inertia, axis.damping, axis.current_limit, axis.vel_gain) == (
            0.032,
            0.1,
            50.0,
            10.0,
        )
    assert sim.periods["torques_msg_rate_ms"] == pytest.approx(0.01)


@pytest.mark.parametrize(
    ("sim", "key"),
    [
        ({"current_limit": 0}, "sim.current_limit: must be a positive number of A"),
        ({"load_inertia": -1}, "sim.load_inertia: must be a number >= 0"),
    ],
)
def test_a_bad_mechanics_key_is_a_profile_error_naming_it(sim: dict[str, object], key: str) -> None:
    from temoto.drivers.can_motor.odrive import ODriveDriver
    from temoto.errors import ProfileError

    with pytest.raises(ProfileError, match=re.escape(key)):
        ODriveDriver.from_profile("base", entry(sim), clock=ManualClock(), where="devices.base")
