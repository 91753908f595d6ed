"""The ODrive CANSimple protocol (firmware 0.6): frame ids and payloads, pure functions.

Every frame's 11-bit arbitration id is ``node_id << 5 | cmd_id`` (node ids 0..63, command ids
0..31). Payloads are little-endian; the layouts below follow the official DBC
(``odrive-cansimple-0.6.10.dbc``, shipped in the ``odrive-can`` package), which the tests use as
the independent reference. Units are the ODrive's own: turns (rev), rev/s and N·m on the motor
side; the driver converts to SI joint units.

No I/O and no threads here: a frame is ``(arbitration_id, data)``. Encoders raise ``ValueError``
for values the wire cannot carry; decoders raise ``ValueError`` for a payload of the wrong
length (a mangled frame). The ids, commands, states and error bits live in
:mod:`~temoto.drivers.can_motor.cansimple_types` and are importable from here too.
"""

from __future__ import annotations

import struct
from typing import Final

from temoto.drivers.can_motor.cansimple_types import (
    MAX_NODE_ID,
    AxisError,
    AxisState,
    Cmd,
    ControlMode,
    EncoderEstimates,
    ErrorStatus,
    Heartbeat,
    InputMode,
    ProcedureResult,
    Version,
    arbitration_id,
    error_names,
    split_id,
    state_name,
)

__all__ = [
    "MAX_NODE_ID",
    "AxisError",
    "AxisState",
    "Cmd",
    "ControlMode",
    "EncoderEstimates",
    "ErrorStatus",
    "Heartbeat",
    "InputMode",
    "ProcedureResult",
    "Version",
    "arbitration_id",
    "decode_clear_errors",
    "decode_encoder_estimates",
    "decode_error_status",
    "decode_float_pair",
    "decode_heartbeat",
    "decode_set_axis_state",
    "decode_set_controller_mode",
    "decode_set_input_pos",
    "decode_set_input_torque",
    "decode_set_input_vel",
    "decode_set_limits",
    "decode_torques",
    "decode_version",
    "encode_bus_voltage_current",
    "encode_clear_errors",
    "encode_encoder_estimates",
    "encode_error_status",
    "encode_estop",
    "encode_heartbeat",
    "encode_iq",
    "encode_powers",
    "encode_set_axis_state",
    "encode_set_controller_mode",
    "encode_set_input_pos",
    "encode_set_input_torque",
    "encode_set_input_vel",
    "encode_set_limits",
    "encode_temperature",
    "encode_torques",
    "error_names",
    "heartbeat_problem",
    "split_id",
    "state_name",
]

# ---- layouts (precompiled; the hot path encodes and decodes with these directly) ---------------

HEARTBEAT: Final = struct.Struct("<IBBBx")  # error, state, procedure result, flags, reserved
U32_PAD: Final = struct.Struct("<I4x")  # one u32, padded to 8 bytes
U32X2: Final = struct.Struct("<II")
F32_PAD: Final = struct.Struct("<f4x")
F32X2: Final = struct.Struct("<ff")
INPUT_POS: Final = struct.Struct("<fhh")  # pos (rev), vel_ff, torque_ff (0.001 units)

_I16_MIN, _I16_MAX = -32768, 32767


def _u32(name: str, value: int) -> int:
    if not 0 <= value <= 0xFFFFFFFF:
        raise ValueError(f"{name} must fit in 32 unsigned bits, got {value}")
    return value


def _f32(name: str, value: float) -> float:
    if value != value or abs(value) > 3.4028234663852886e38:  # NaN or beyond float32
        raise ValueError(f"{name} must be a finite float32, got {value}")
    return value


def _check_len(what: str, data: bytes | bytearray, size: int) -> None:
    if len(data) != size:
        raise ValueError(f"{what}: expected {size} data bytes, got {len(data)}")


def encode_heartbeat(
    axis_error: int, axis_state: int, procedure_result: int = 0, trajectory_done: bool = False
) -> bytes:
    """``Heartbeat`` payload (8 bytes).

    Args:
        axis_error: :class:`AxisError` bits.
        axis_state: An :class:`AxisState`.
        procedure_result: The last procedure's result (0 = SUCCESS).
        trajectory_done: The trajectory-done flag.

    Returns:
        The payload.

    Raises:
        ValueError: A value does not fit.
    """
    if not (0 <= axis_state <= 0xFF and 0 <= procedure_result <= 0xFF):
        raise ValueError("axis state and procedure result are single bytes")
    return HEARTBEAT.pack(
        _u32("axis_error", axis_error), axis_state, procedure_result, int(trajectory_done)
    )


def decode_heartbeat(data: bytes | bytearray) -> Heartbeat:
    """Parse a ``Heartbeat`` payload.

    Args:
        data: 8 bytes.

    Returns:
        The heartbeat.

    Raises:
        ValueError: Wrong length.
    """
    _check_len("Heartbeat", data, 8)
    error, state, result, flags = HEARTBEAT.unpack(data)
    return Heartbeat(error, state, result, bool(flags & 1))


#: The largest ``Procedure_Result`` the 0.6.10 DBC names (15: NOT_CONVERGING); a little room
#: is left for newer firmware.
MAX_PROCEDURE_RESULT: Final = 31
_STATES: Final = frozenset(int(s) for s in AxisState)


def heartbeat_problem(data: bytes | bytearray) -> str | None:
    """Why ``data`` is not a well-formed ``Heartbeat`` payload, or None when it is one.

    Beyond the length, the fields are checked against the 0.6.10 DBC: the axis state must be
    a known :class:`AxisState`, the procedure result at most :data:`MAX_PROCEDURE_RESULT`, and
    of the flags byte only bit 0 (``Trajectory_Done_Flag``) may be set. Byte 7 is not defined
    by the DBC and is not checked (0.5 firmware puts its trajectory flag there). An 8-byte
    frame of another protocol on a heartbeat id (an MIT-mode command to motor 0x41 looks like
    node 2's heartbeat) fails these checks in all but rare cases.

    Args:
        data: A frame's payload.

    Returns:
        A short reason, or None.
    """
    if len(data) != 8:
        return f"{len(data)} data bytes instead of 8"
    state, result, flags = data[4], data[5], data[6]
    if state not in _STATES:
        return f"unknown axis state {state}"
    if result > MAX_PROCEDURE_RESULT:
        return f"unknown procedure result {result}"
    if flags & 0xFE:
        return f"undefined flag bits 0x{flags & 0xFE:02x}"
    return None


def decode_version(data: bytes | bytearray) -> Version:
    """Parse a ``Get_Version`` payload.

    Args:
        data: 8 bytes.

    Returns:
        The versions.

    Raises:
        ValueError: Wrong length.
    """
    _check_len("Get_Version", data, 8)
    return Version(*data)


def encode_set_axis_state(state: int) -> bytes:
    """``Set_Axis_State`` payload (8 bytes: u32 requested state, 4 reserved).

    Args:
        state: An :class:`AxisState`.

    Returns:
        The payload.

    Raises:
        ValueError: Out of range.
    """
    return U32_PAD.pack(_u32("axis state", state))


def decode_set_axis_state(data: bytes | bytearray) -> int:
    """Parse ``Set_Axis_State``.

    Args:
        data: 8 bytes (4 accepted: the requested state alone).

    Returns:
        The requested state.

    Raises:
        ValueError: Wrong length.
    """
    if len(data) == 4:
        return int.from_bytes(data, "little")
    _check_len("Set_Axis_State", data, 8)
    return int(U32_PAD.unpack(data)[0])


def encode_set_controller_mode(control_mode: int, input_mode: int) -> bytes:
    """``Set_Controller_Mode`` payload (u32 control mode, u32 input mode).

    Args:
        control_mode: A :class:`ControlMode`.
        input_mode: An :class:`InputMode`.

    Returns:
        The payload.

    Raises:
        ValueError: Out of range.
    """
    return U32X2.pack(_u32("control mode", control_mode), _u32("input mode", input_mode))


def decode_set_controller_mode(data: bytes | bytearray) -> tuple[int, int]:
    """Parse ``Set_Controller_Mode``.

    Args:
        data: 8 bytes.

    Returns:
        ``(control_mode, input_mode)``.

    Raises:
        ValueError: Wrong length.
    """
    _check_len("Set_Controller_Mode", data, 8)
    control, inp = U32X2.unpack(data)
    return int(control), int(inp)


def encode_set_input_pos(pos: float, vel_ff: float = 0.0, torque_ff: float = 0.0) -> bytes:
    """``Set_Input_Pos`` payload: float32 rev, int16 vel_ff (0.001 rev/s), int16 torque_ff (mN·m).

    Args:
        pos: Position set-point, rev.
        vel_ff: Velocity feed-forward, rev/s (±32.767).
        torque_ff: Torque feed-forward, N·m (±32.767).

    Returns:
        The payload.

    Raises:
        ValueError: A value does not fit.
    """
    v = round(vel_ff * 1000.0)
    t = round(torque_ff * 1000.0)
    if not (_I16_MIN <= v <= _I16_MAX and _I16_MIN <= t <= _I16_MAX):
        raise ValueError(f"feed-forwards must be within ±32.767, got {vel_ff}, {torque_ff}")
    return INPUT_POS.pack(_f32("pos", pos), v, t)


def decode_set_input_pos(data: bytes | bytearray) -> tuple[float, float, float]:
    """Parse ``Set_Input_Pos``.

    Args:
        data: 8 bytes.

    Returns:
        ``(pos, vel_ff, torque_ff)`` in rev, rev/s, N·m.

    Raises:
        ValueError: Wrong length.
    """
    _check_len("Set_Input_Pos", data, 8)
    pos, v, t = INPUT_POS.unpack(data)
    return pos, v * 0.001, t * 0.001


def encode_set_input_vel(vel: float, torque_ff: float = 0.0) -> bytes:
    """``Set_Input_Vel`` payload: float32 rev/s, float32 torque feed-forward N·m.

    Args:
        vel: Velocity set-point, rev/s.
        torque_ff: Torque feed-forward, N·m.

    Returns:
        The payload.

    Raises:
        ValueError: Not a finite float32.
    """
    return F32X2.pack(_f32("vel", vel), _f32("torque_ff", torque_ff))


def decode_set_input_vel(data: bytes | bytearray) -> tuple[float, float]:
    """Parse ``Set_Input_Vel``.

    Args:
        data: 8 bytes.

    Returns:
        ``(vel, torque_ff)``.

    Raises:
        ValueError: Wrong length.
    """
    _check_len("Set_Input_Vel", data, 8)
    vel, tff = F32X2.unpack(data)
    return vel, tff


def encode_set_input_torque(torque: float) -> bytes:
    """``Set_Input_Torque`` payload: float32 N·m, 4 reserved bytes.

    Args:
        torque: N·m (motor side).

    Returns:
        The payload.

    Raises:
        ValueError: Not a finite float32.
    """
    return F32_PAD.pack(_f32("torque", torque))


def decode_set_input_torque(data: bytes | bytearray) -> float:
    """Parse ``Set_Input_Torque``.

    Args:
        data: 8 bytes (4 accepted).

    Returns:
        N·m.

    Raises:
        ValueError: Wrong length.
    """
    if len(data) == 4:
        return float(struct.unpack("<f", data)[0])
    _check_len("Set_Input_Torque", data, 8)
    return float(F32_PAD.unpack(data)[0])


def encode_set_limits(velocity_limit: float, current_limit: float) -> bytes:
    """``Set_Limits`` payload: float32 rev/s, float32 A.

    Args:
        velocity_limit: rev/s.
        current_limit: A.

    Returns:
        The payload.

    Raises:
        ValueError: Not a finite float32.
    """
    return F32X2.pack(_f32("velocity_limit", velocity_limit), _f32("current_limit", current_limit))


def decode_set_limits(data: bytes | bytearray) -> tuple[float, float]:
    """Parse ``Set_Limits``.

    Args:
        data: 8 bytes.

    Returns:
        ``(velocity_limit, current_limit)``.

    Raises:
        ValueError: Wrong length.
    """
    _check_len("Set_Limits", data, 8)
    vel, cur = F32X2.unpack(data)
    return vel, cur


def encode_encoder_estimates(pos: float, vel: float) -> bytes:
    """``Get_Encoder_Estimates`` reply payload: float32 rev, float32 rev/s.

    Args:
        pos: rev.
        vel: rev/s.

    Returns:
        The payload.

    Raises:
        ValueError: Not a finite float32.
    """
    return F32X2.pack(_f32("pos", pos), _f32("vel", vel))


def decode_encoder_estimates(data: bytes | bytearray) -> EncoderEstimates:
    """Parse ``Get_Encoder_Estimates``.

    Args:
        data: 8 bytes.

    Returns:
        The estimates.

    Raises:
        ValueError: Wrong length.
    """
    _check_len("Get_Encoder_Estimates", data, 8)
    pos, vel = F32X2.unpack(data)
    return EncoderEstimates(pos, vel)


def encode_torques(target: float, estimate: float) -> bytes:
    """``Get_Torques`` reply payload: float32 torque target, float32 torque estimate (N·m).

    Args:
        target: N·m.
        estimate: N·m.

    Returns:
        The payload.

    Raises:
        ValueError: Not a finite float32.
    """
    return F32X2.pack(_f32("target", target), _f32("estimate", estimate))


def decode_torques(data: bytes | bytearray) -> tuple[float, float]:
    """Parse ``Get_Torques``.

    Args:
        data: 8 bytes.

    Returns:
        ``(target, estimate)`` in N·m.

    Raises:
        ValueError: Wrong length.
    """
    _check_len("Get_Torques", data, 8)
    target, estimate = F32X2.unpack(data)
    return target, estimate


def encode_error_status(active_errors: int, disarm_reason: int) -> bytes:
    """``Get_Error`` reply payload: u32 active errors, u32 disarm reason.

    Args:
        active_errors: :class:`AxisError` bits.
        disarm_reason: :class:`AxisError` bits.

    Returns:
        The payload.

    Raises:
        ValueError: Out of range.
    """
    return U32X2.pack(_u32("active_errors", active_errors), _u32("disarm_reason", disarm_reason))


def decode_error_status(data: bytes | bytearray) -> ErrorStatus:
    """Parse ``Get_Error``.

    Args:
        data: 8 bytes.

    Returns:
        The status.

    Raises:
        ValueError: Wrong length.
    """
    _check_len("Get_Error", data, 8)
    active, reason = U32X2.unpack(data)
    return ErrorStatus(active, reason)


def encode_estop() -> bytes:
    """``Estop`` payload: empty (DLC 0).

    Returns:
        ``b""``.
    """
    return b""


def encode_clear_errors(identify: bool = False) -> bytes:
    """``Clear_Errors`` payload: one byte, 1 to also blink the LED (identify).

    Args:
        identify: Whether to identify the device.

    Returns:
        The payload.
    """
    return b"\x01" if identify else b"\x00"


def decode_clear_errors(data: bytes | bytearray) -> bool:
    """Parse ``Clear_Errors`` (an empty payload is accepted, as older firmware sends it).

    Args:
        data: 0 or 1 byte.

    Returns:
        The identify flag.

    Raises:
        ValueError: Wrong length.
    """
    if len(data) > 1:
        raise ValueError(f"Clear_Errors: expected 0 or 1 data bytes, got {len(data)}")
    return bool(data and data[0])


def _float_pair(first: str, second: str, a: float, b: float) -> bytes:
    return F32X2.pack(_f32(first, a), _f32(second, b))


def encode_iq(setpoint: float, measured: float) -> bytes:
    """``Get_Iq`` reply payload: float32 Iq set-point, float32 Iq measured (A).

    Args:
        setpoint: A.
        measured: A.

    Returns:
        The payload.

    Raises:
        ValueError: Not a finite float32.
    """
    return _float_pair("Iq_Setpoint", "Iq_Measured", setpoint, measured)


def encode_temperature(fet: float, motor: float) -> bytes:
    """``Get_Temperature`` reply payload: float32 FET, float32 motor temperature (°C).

    Args:
        fet: °C.
        motor: °C.

    Returns:
        The payload.

    Raises:
        ValueError: Not a finite float32.
    """
    return _float_pair("FET_Temperature", "Motor_Temperature", fet, motor)


def encode_bus_voltage_current(voltage: float, current: float) -> bytes:
    """``Get_Bus_Voltage_Current`` reply payload: float32 V, float32 A.

    Args:
        voltage: The DC bus voltage, V.
        current: The DC bus current, A.

    Returns:
        The payload.

    Raises:
        ValueError: Not a finite float32.
    """
    return _float_pair("Bus_Voltage", "Bus_Current", voltage, current)


def encode_powers(electrical: float, mechanical: float) -> bytes:
    """``Get_Powers`` reply payload: float32 electrical, float32 mechanical power (W).

    Args:
        electrical: W.
        mechanical: W.

    Returns:
        The payload.

    Raises:
        ValueError: Not a finite float32.
    """
    return _float_pair("Electrical_Power", "Mechanical_Power", electrical, mechanical)


def decode_float_pair(data: bytes | bytearray) -> tuple[float, float]:
    """Parse a payload of two float32, in the DBC's signal order.

    ``Get_Iq``, ``Get_Temperature``, ``Get_Bus_Voltage_Current`` and ``Get_Powers`` carry two.

    Args:
        data: 8 bytes.

    Returns:
        The two values.

    Raises:
        ValueError: Wrong length.
    """
    _check_len("two float32", data, 8)
    a, b = F32X2.unpack(data)
    return a, b
