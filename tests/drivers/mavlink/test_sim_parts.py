"""The simulated vehicle's parts: each one built and driven alone over a VehicleState.

SimVehicle holds its parts (state, telemetry, mission, flight model, failsafes, commands);
none inherits from another, and each is tested here without the vehicle, its socket or its
threads, on a manual clock.
"""

from __future__ import annotations

import ast
import inspect
import textwrap
from typing import Any

import pytest

from temoto.clock import ManualClock
from temoto.drivers.mavlink import protocol as p
from temoto.drivers.mavlink.protocol import Codec
from temoto.drivers.mavlink.sim import SimVehicle
from temoto.drivers.mavlink.sim_auto import AutoMission
from temoto.drivers.mavlink.sim_commands import CommandHandler
from temoto.drivers.mavlink.sim_failsafe import Failsafes
from temoto.drivers.mavlink.sim_flight import FlightModel
from temoto.drivers.mavlink.sim_state import VehicleState
from temoto.drivers.mavlink.sim_telemetry import VehicleTelemetry

GCS = Codec(255, 190)
VEHICLE = Codec(1, 1)

PARTS: dict[str, type] = {
    "state": VehicleState,
    "telemetry": VehicleTelemetry,
    "auto": AutoMission,
    "flight": FlightModel,
    "failsafes": Failsafes,
    "commands": CommandHandler,
}


def _decode(frames: list[bytes]) -> list[Any]:
    return [m for f in frames for m in GCS.decode_datagram(f)]


def _gcs_msg(name: str, **fields: Any) -> Any:
    (msg,) = VEHICLE.decode_datagram(GCS.encode(name, **fields))
    return msg


def _state(**kwargs: Any) -> VehicleState:
    return VehicleState("alone", clock=ManualClock(), **kwargs)


def _flight(state: VehicleState) -> FlightModel:
    telemetry = VehicleTelemetry(state)
    return FlightModel(state, telemetry, AutoMission(state, telemetry))


def _upload(state: VehicleState, items: list[tuple[int, float]]) -> None:
    """Store a mission through the state's MissionService: (command, relative altitude)."""
    plans = state.plans
    plans.handle(
        _gcs_msg("MISSION_COUNT", target_system=1, target_component=1, count=1 + len(items)), 0.0
    )
    for seq, (command, alt) in enumerate([(16, 0.0), *items]):
        fields = {
            "target_system": 1,
            "target_component": 1,
            "seq": seq,
            "frame": p.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
            "command": command,
            "current": 0,
            "autocontinue": 1,
            "param1": 0.0,
            "param2": 0.0,
            "param3": 0.0,
            "param4": 0.0,
            "x": 0,
            "y": 0,
            "z": alt,
        }
        plans.handle(_gcs_msg("MISSION_ITEM_INT", **fields), 0.0)


# ---- structure --------------------------------------------------------------------------------


def test_the_vehicle_holds_its_parts_and_no_part_inherits_another() -> None:
    vehicle = SimVehicle("held", clock=ManualClock())
    for attr, cls in PARTS.items():
        assert isinstance(getattr(vehicle, attr), cls), attr
        assert cls.__bases__ == (object,), cls
    held = [getattr(vehicle, attr) for attr in PARTS if attr != "state"]
    assert all(part.state is vehicle.state for part in held)  # one state, by reference


@pytest.mark.parametrize("attr", list(PARTS))
def test_a_part_calls_only_its_own_methods_or_the_public_ones_of_the_parts_it_holds(
    attr: str,
) -> None:
    vehicle = SimVehicle("held", clock=ManualClock())
    cls, part = PARTS[attr], getattr(vehicle, attr)
    tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    missing = []
    for node in ast.walk(tree):
        if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)):
            continue
        owner = node.func.value
        if isinstance(owner, ast.Name) and owner.id == "self":
            if not hasattr(part, node.func.attr):
                missing.append(node.func.attr)
        elif (
            isinstance(owner, ast.Attribute)
            and isinstance(owner.value, ast.Name)
            and owner.value.id == "self"
            and owner.attr in PARTS
        ):
            method = node.func.attr
            if method.startswith("_") or not hasattr(getattr(vehicle, owner.attr), method):
                missing.append(f"{owner.attr}.{method}")
    assert missing == []


# ---- each part alone --------------------------------------------------------------------------


def test_state_alone_parameters_geometry_and_prearm() -> None:
    state = _state(battery=10.0, params={"WPNAV_SPEED": 750})
    assert state.param("WPNAV_SPEED") == 750.0
    north, east = state.local(*state.geo([120.0, -40.0, 0.0])[:2])
    assert (north, east) == (pytest.approx(120.0, abs=1e-6), pytest.approx(-40.0, abs=1e-6))
    with state.lock:
        assert state.prearm_failure() == "PreArm: Battery below minimum arming capacity"
        state.battery = 90.0
        assert state.prearm_failure() is None


def test_telemetry_alone_streams_what_is_due_at_its_rate() -> None:
    state = _state()
    telemetry = VehicleTelemetry(state, {"ATTITUDE": 0})
    with state.lock:
        first = {m.name for m in _decode(telemetry.streams(0.0))}
        assert {"HEARTBEAT", "GLOBAL_POSITION_INT", "SYS_STATUS"} <= first
        assert "ATTITUDE" not in first
        again = {m.name for m in _decode(telemetry.streams(0.05))}
    assert "HEARTBEAT" not in again  # 1 Hz: not due after 50 ms
    assert "GLOBAL_POSITION_INT" not in again  # 10 Hz: due at 0.1 s
    telemetry.set_rate("HEARTBEAT", 0)
    assert telemetry.rate("HEARTBEAT") == 0.0


def test_mission_alone_starts_its_first_command_when_armed() -> None:
    state = _state()
    auto = AutoMission(state, VehicleTelemetry(state))
    _upload(state, [(p.MAV_CMD_NAV_TAKEOFF, 12.0), (p.MAV_CMD_NAV_LAND, 0.0)])
    with state.lock:
        auto.check_plan()
        assert (state.mis_index, state.mis_state) == (1, p.MISSION_STATE_NOT_STARTED)
        state.mode, state.armed = "AUTO", True
        auto.start_or_resume()
        auto.update()
        assert state.nav is not None
        assert state.nav["kind"] == "takeoff"
        assert state.nav["target"][2] == pytest.approx(12.0)


def test_flight_model_alone_takes_off_in_guided() -> None:
    state = _state()
    flight = _flight(state)
    with state.lock:
        assert flight.set_mode("GUIDED") == p.MAV_RESULT_ACCEPTED
        assert flight.arm() == p.MAV_RESULT_ACCEPTED
        assert flight.takeoff(10.0) == p.MAV_RESULT_ACCEPTED
        flight.advance(20.0)
        assert state.airborne
        assert state.pos[2] == pytest.approx(10.0, abs=0.1)


def test_failsafes_alone_send_the_vehicle_home_without_gcs_heartbeats() -> None:
    state = _state(params={"FS_GCS_ENABLE": 1})
    flight = _flight(state)
    failsafes = Failsafes(state, flight)
    with state.lock:
        flight.set_mode("GUIDED")
        flight.arm()
        flight.takeoff(5.0)
        flight.advance(10.0)
        failsafes.gcs_heartbeat(10.0)
        failsafes.check(12.0)
        assert state.mode == "GUIDED"
        failsafes.check(15.5)  # FS_GCS_TIMEOUT 5 s
        assert (state.mode, state.gcs_failsafe) == ("RTL", True)


def test_commands_alone_answer_an_arm_command_with_its_ack() -> None:
    state = _state()
    telemetry = VehicleTelemetry(state)
    auto = AutoMission(state, telemetry)
    flight = FlightModel(state, telemetry, auto)
    commands = CommandHandler(state, telemetry, auto, flight, Failsafes(state, flight))
    arm = _gcs_msg(
        "COMMAND_LONG",
        target_system=1,
        target_component=1,
        command=p.MAV_CMD_COMPONENT_ARM_DISARM,
        confirmation=0,
        param1=1.0,
        param2=0.0,
        param3=0.0,
        param4=0.0,
        param5=0.0,
        param6=0.0,
        param7=0.0,
    )
    replies = _decode(commands.handle(arm))  # STABILIZE: armable
    assert replies[0].name == "COMMAND_ACK"
    assert replies[0].get_int("result") == p.MAV_RESULT_ACCEPTED
    assert state.armed
    assert commands.acks == [(p.MAV_CMD_COMPONENT_ARM_DISARM, p.MAV_RESULT_ACCEPTED)]
