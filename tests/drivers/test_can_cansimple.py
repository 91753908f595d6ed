"""CANSimple frames are byte-exact: checked against cantools and the official ODrive DBC."""

from __future__ import annotations

import math
import struct
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cantools
import odrive_can
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from temoto.drivers.can_motor import cansimple as cs

DBC = Path(odrive_can.__file__).parent / "dbc" / "odrive-cansimple-0.6.10.dbc"


@pytest.fixture(scope="module")
def db() -> Any:
    return cantools.database.load_file(str(DBC))


def f32(x: float) -> float:
    return float(struct.unpack("<f", struct.pack("<f", x))[0])


nodes = st.integers(0, 7)  # the DBC describes axes 0..7
floats = st.floats(-1e6, 1e6, allow_nan=False, width=32)
u32 = st.integers(0, 0xFFFFFFFF)
u8 = st.integers(0, 0xFF)
ff = st.integers(-32768, 32767).map(lambda i: i / 1000.0)

# name → (command, our encoder, our decoder → DBC signal values, strategy of our arguments,
#         DBC signal values of our arguments)
Case = tuple[
    cs.Cmd,
    Callable[..., bytes],
    Callable[[bytes], dict[str, float]],
    Any,
    Callable[..., dict[str, float]],
]
CASES: dict[str, Case] = {
    "Heartbeat": (
        cs.Cmd.HEARTBEAT,
        cs.encode_heartbeat,
        lambda d: dict(
            zip(
                ("Axis_Error", "Axis_State", "Procedure_Result", "Trajectory_Done_Flag"),
                cs.decode_heartbeat(d),
                strict=True,
            )
        ),
        st.tuples(u32, u8, u8, st.booleans()),
        lambda e, s, r, t: {
            "Axis_Error": e,
            "Axis_State": s,
            "Procedure_Result": r,
            "Trajectory_Done_Flag": int(t),
        },
    ),
    "Get_Error": (
        cs.Cmd.GET_ERROR,
        cs.encode_error_status,
        lambda d: dict(
            zip(("Active_Errors", "Disarm_Reason"), cs.decode_error_status(d), strict=True)
        ),
        st.tuples(u32, u32),
        lambda a, r: {"Active_Errors": a, "Disarm_Reason": r},
    ),
    "Set_Axis_State": (
        cs.Cmd.SET_AXIS_STATE,
        cs.encode_set_axis_state,
        lambda d: {"Axis_Requested_State": cs.decode_set_axis_state(d)},
        st.tuples(st.sampled_from(list(cs.AxisState))),
        lambda s: {"Axis_Requested_State": int(s)},
    ),
    "Get_Encoder_Estimates": (
        cs.Cmd.GET_ENCODER_ESTIMATES,
        cs.encode_encoder_estimates,
        lambda d: dict(
            zip(("Pos_Estimate", "Vel_Estimate"), cs.decode_encoder_estimates(d), strict=True)
        ),
        st.tuples(floats, floats),
        lambda p, v: {"Pos_Estimate": f32(p), "Vel_Estimate": f32(v)},
    ),
    "Set_Controller_Mode": (
        cs.Cmd.SET_CONTROLLER_MODE,
        cs.encode_set_controller_mode,
        lambda d: dict(
            zip(("Control_Mode", "Input_Mode"), cs.decode_set_controller_mode(d), strict=True)
        ),
        st.tuples(st.sampled_from(list(cs.ControlMode)), st.sampled_from(list(cs.InputMode))),
        lambda c, i: {"Control_Mode": int(c), "Input_Mode": int(i)},
    ),
    "Set_Input_Pos": (
        cs.Cmd.SET_INPUT_POS,
        cs.encode_set_input_pos,
        lambda d: dict(
            zip(("Input_Pos", "Vel_FF", "Torque_FF"), cs.decode_set_input_pos(d), strict=True)
        ),
        st.tuples(floats, ff, ff),
        lambda p, v, t: {"Input_Pos": f32(p), "Vel_FF": v, "Torque_FF": t},
    ),
    "Set_Input_Vel": (
        cs.Cmd.SET_INPUT_VEL,
        cs.encode_set_input_vel,
        lambda d: dict(
            zip(("Input_Vel", "Input_Torque_FF"), cs.decode_set_input_vel(d), strict=True)
        ),
        st.tuples(floats, floats),
        lambda v, t: {"Input_Vel": f32(v), "Input_Torque_FF": f32(t)},
    ),
    "Set_Input_Torque": (
        cs.Cmd.SET_INPUT_TORQUE,
        cs.encode_set_input_torque,
        lambda d: {"Input_Torque": cs.decode_set_input_torque(d)},
        st.tuples(floats),
        lambda t: {"Input_Torque": f32(t)},
    ),
    "Set_Limits": (
        cs.Cmd.SET_LIMITS,
        cs.encode_set_limits,
        lambda d: dict(
            zip(("Velocity_Limit", "Current_Limit"), cs.decode_set_limits(d), strict=True)
        ),
        st.tuples(floats, floats),
        lambda v, c: {"Velocity_Limit": f32(v), "Current_Limit": f32(c)},
    ),
    "Get_Torques": (
        cs.Cmd.GET_TORQUES,
        cs.encode_torques,
        lambda d: dict(
            zip(("Torque_Target", "Torque_Estimate"), cs.decode_torques(d), strict=True)
        ),
        st.tuples(floats, floats),
        lambda t, e: {"Torque_Target": f32(t), "Torque_Estimate": f32(e)},
    ),
    "Clear_Errors": (
        cs.Cmd.CLEAR_ERRORS,
        cs.encode_clear_errors,
        lambda d: {"Identify": int(cs.decode_clear_errors(d))},
        st.tuples(st.booleans()),
        lambda i: {"Identify": int(i)},
    ),
}


def close(a: dict[str, float], b: dict[str, float]) -> bool:
    return a.keys() == b.keys() and all(
        math.isclose(a[k], b[k], rel_tol=1e-9, abs_tol=1e-9) for k in a
    )


@pytest.mark.parametrize("name", sorted(CASES))
@settings(max_examples=40, deadline=None)
@given(node=nodes, data=st.data())
def test_frames_match_the_official_dbc(db: Any, name: str, node: int, data: Any) -> None:
    cmd, encode, decode, args_strategy, signals = CASES[name]
    args = data.draw(args_strategy)
    message = db.get_message_by_name(f"Axis{node}_{name}")
    frame_id = cs.arbitration_id(node, cmd)
    assert message.frame_id == frame_id
    ours = encode(*args)
    assert len(ours) == message.length
    # ours → cantools
    theirs = db.decode_message(frame_id, ours, decode_choices=False)
    assert close(dict(theirs), signals(*args))
    # cantools → ours, byte for byte
    encoded = db.encode_message(frame_id, signals(*args), padding=False, strict=True)
    assert bytes(encoded) == ours
    assert close(decode(bytes(encoded)), signals(*args))


def test_estop_is_an_empty_frame(db: Any) -> None:
    for node in range(8):
        message = db.get_message_by_name(f"Axis{node}_Estop")
        assert message.frame_id == cs.arbitration_id(node, cs.Cmd.ESTOP)
        assert message.length == len(cs.encode_estop()) == 0


def test_every_dbc_command_id_is_known(db: Any) -> None:
    for message in db.messages:
        node, cmd = cs.split_id(message.frame_id)
        assert message.name.startswith(f"Axis{node}_")
        assert (
            cs.Cmd(cmd).name.replace("_", "").lower()
            == message.name.split("_", 1)[1].replace("_", "").lower()
        )


def test_enum_values_match_the_dbc_choices(db: Any) -> None:
    hb = db.get_message_by_name("Axis0_Heartbeat")
    states = {int(k): str(v) for k, v in hb.get_signal_by_name("Axis_State").choices.items()}
    assert states == {s.value: s.name for s in cs.AxisState}
    errors = {int(k): str(v) for k, v in hb.get_signal_by_name("Axis_Error").choices.items()}
    assert errors == {e.value: e.name for e in cs.AxisError.__members__.values()}
    mode = db.get_message_by_name("Axis0_Set_Controller_Mode")
    controls = {int(k): str(v) for k, v in mode.get_signal_by_name("Control_Mode").choices.items()}
    assert controls == {c.value: c.name for c in cs.ControlMode}
    inputs = {int(k): str(v) for k, v in mode.get_signal_by_name("Input_Mode").choices.items()}
    assert inputs == {i.value: i.name for i in cs.InputMode}


def test_ids_and_names() -> None:
    assert cs.arbitration_id(3, cs.Cmd.SET_INPUT_VEL) == 0x6D
    assert cs.split_id(0x6D) == (3, cs.Cmd.SET_INPUT_VEL)
    assert cs.arbitration_id(63, 31) == 0x7FF
    with pytest.raises(ValueError, match="node id"):
        cs.arbitration_id(64, 1)
    with pytest.raises(ValueError, match="command id"):
        cs.arbitration_id(1, 32)
    bits = cs.AxisError.MOTOR_OVER_TEMP | cs.AxisError.DC_BUS_UNDER_VOLTAGE | 0x800000
    assert cs.error_names(bits) == ["DC_BUS_UNDER_VOLTAGE", "MOTOR_OVER_TEMP", "0x800000"]
    assert cs.error_names(0) == []


@pytest.mark.parametrize(
    ("call", "match"),
    [
        (lambda: cs.encode_set_input_pos(1.0, vel_ff=40.0), "feed-forward"),
        (lambda: cs.encode_set_input_vel(math.nan), "finite"),
        (lambda: cs.encode_set_input_torque(1e39), "finite"),
        (lambda: cs.encode_heartbeat(-1, 1), "32 unsigned"),
        (lambda: cs.encode_heartbeat(0, 256), "single bytes"),
        (lambda: cs.decode_heartbeat(b"\0" * 3), "expected 8"),
        (lambda: cs.decode_encoder_estimates(b"\0" * 7), "expected 8"),
        (lambda: cs.decode_clear_errors(b"\0\0"), "0 or 1"),
    ],
)
def test_values_the_wire_cannot_carry_are_value_errors(call: Callable[[], Any], match: str) -> None:
    with pytest.raises(ValueError, match=match):
        call()


def test_short_forms_are_accepted() -> None:
    assert cs.decode_set_axis_state(b"\x08\0\0\0") == 8
    assert cs.decode_set_input_torque(struct.pack("<f", 1.5)) == 1.5
    assert cs.decode_clear_errors(b"") is False
