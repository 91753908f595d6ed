"""The ODrive CANSimple vocabulary (firmware 0.6): ids, commands, states, errors, messages.

What a frame means, apart from how its payload is laid out (:mod:`cansimple`, which re-exports
every name here): the 11-bit arbitration id ``node_id << 5 | cmd_id`` (:func:`arbitration_id`,
:func:`split_id`), the command ids (:class:`Cmd`), the axis states and control modes, the axis
error bits (:class:`AxisError`, :func:`error_names`) and the decoded messages as named tuples.
Names and values follow the official DBC (``odrive-cansimple-0.6.10.dbc``).
"""

from __future__ import annotations

import enum
from typing import Final, NamedTuple

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
    "error_names",
    "split_id",
    "state_name",
]

#: The largest node id (6 bits).
MAX_NODE_ID: Final = 0x3F


class Cmd(enum.IntEnum):
    """CANSimple command ids (the low 5 bits of the arbitration id)."""

    GET_VERSION = 0x00
    HEARTBEAT = 0x01
    ESTOP = 0x02
    GET_ERROR = 0x03
    RXSDO = 0x04
    TXSDO = 0x05
    ADDRESS = 0x06
    SET_AXIS_STATE = 0x07
    GET_ENCODER_ESTIMATES = 0x09
    SET_CONTROLLER_MODE = 0x0B
    SET_INPUT_POS = 0x0C
    SET_INPUT_VEL = 0x0D
    SET_INPUT_TORQUE = 0x0E
    SET_LIMITS = 0x0F
    SET_TRAJ_VEL_LIMIT = 0x11
    SET_TRAJ_ACCEL_LIMITS = 0x12
    SET_TRAJ_INERTIA = 0x13
    GET_IQ = 0x14
    GET_TEMPERATURE = 0x15
    REBOOT = 0x16
    GET_BUS_VOLTAGE_CURRENT = 0x17
    CLEAR_ERRORS = 0x18
    SET_ABSOLUTE_POSITION = 0x19
    SET_POS_GAIN = 0x1A
    SET_VEL_GAINS = 0x1B
    GET_TORQUES = 0x1C
    GET_POWERS = 0x1D
    ENTER_DFU_MODE = 0x1F


class AxisState(enum.IntEnum):
    """``Axis.current_state`` / ``requested_state`` values."""

    UNDEFINED = 0
    IDLE = 1
    STARTUP_SEQUENCE = 2
    FULL_CALIBRATION_SEQUENCE = 3
    MOTOR_CALIBRATION = 4
    SENSORLESS_CONTROL = 5
    ENCODER_INDEX_SEARCH = 6
    ENCODER_OFFSET_CALIBRATION = 7
    CLOSED_LOOP_CONTROL = 8
    LOCKIN_SPIN = 9
    ENCODER_DIR_FIND = 10
    HOMING = 11
    ENCODER_HALL_POLARITY_CALIBRATION = 12
    ENCODER_HALL_PHASE_CALIBRATION = 13
    ANTICOGGING_CALIBRATION = 14


class ControlMode(enum.IntEnum):
    """``Controller.config.control_mode`` values."""

    VOLTAGE_CONTROL = 0
    TORQUE_CONTROL = 1
    VELOCITY_CONTROL = 2
    POSITION_CONTROL = 3


class InputMode(enum.IntEnum):
    """``Controller.config.input_mode`` values."""

    INACTIVE = 0
    PASSTHROUGH = 1
    VEL_RAMP = 2
    POS_FILTER = 3
    MIX_CHANNELS = 4
    TRAP_TRAJ = 5
    TORQUE_RAMP = 6
    MIRROR = 7
    TUNING = 8


class ProcedureResult(enum.IntEnum):
    """``Axis.procedure_result`` (the heartbeat's ``Procedure_Result``), as the DBC names it."""

    SUCCESS = 0
    BUSY = 1
    CANCELLED = 2
    DISARMED = 3
    NO_RESPONSE = 4
    POLE_PAIR_CPR_MISMATCH = 5
    PHASE_RESISTANCE_OUT_OF_RANGE = 6
    PHASE_INDUCTANCE_OUT_OF_RANGE = 7
    UNBALANCED_PHASES = 8
    INVALID_MOTOR_TYPE = 9
    ILLEGAL_HALL_STATE = 10
    TIMEOUT = 11
    HOMING_WITHOUT_ENDSTOP = 12
    INVALID_STATE = 13
    NOT_CALIBRATED = 14
    NOT_CONVERGING = 15


class AxisError(enum.IntFlag):
    """``Axis.active_errors`` / ``disarm_reason`` bits (the heartbeat's ``Axis_Error``)."""

    NONE = 0
    INITIALIZING = 0x1
    SYSTEM_LEVEL = 0x2
    TIMING_ERROR = 0x4
    MISSING_ESTIMATE = 0x8
    BAD_CONFIG = 0x10
    DRV_FAULT = 0x20
    MISSING_INPUT = 0x40
    DC_BUS_OVER_VOLTAGE = 0x100
    DC_BUS_UNDER_VOLTAGE = 0x200
    DC_BUS_OVER_CURRENT = 0x400
    DC_BUS_OVER_REGEN_CURRENT = 0x800
    CURRENT_LIMIT_VIOLATION = 0x1000
    MOTOR_OVER_TEMP = 0x2000
    INVERTER_OVER_TEMP = 0x4000
    VELOCITY_LIMIT_VIOLATION = 0x8000
    POSITION_LIMIT_VIOLATION = 0x10000
    WATCHDOG_TIMER_EXPIRED = 0x1000000
    ESTOP_REQUESTED = 0x2000000
    SPINOUT_DETECTED = 0x4000000
    BRAKE_RESISTOR_DISARMED = 0x8000000
    THERMISTOR_DISCONNECTED = 0x10000000
    CALIBRATION_ERROR = 0x40000000


def state_name(state: int) -> str:
    """The name of an axis state, or the number for one the protocol does not define.

    Args:
        state: An ``Axis_State`` value.

    Returns:
        ``CLOSED_LOOP_CONTROL``, ..., or ``"17"``.
    """
    try:
        return AxisState(state).name
    except ValueError:
        return str(state)


def error_names(bits: int) -> list[str]:
    """The names of the set :class:`AxisError` bits (unknown bits as hex).

    Args:
        bits: ``Axis_Error`` / ``Active_Errors`` / ``Disarm_Reason``.

    Returns:
        Names, lowest bit first (empty for 0).
    """
    names: list[str] = []
    for bit in range(32):
        mask = 1 << bit
        if bits & mask:
            try:
                names.append(AxisError(mask).name or hex(mask))
            except ValueError:
                names.append(hex(mask))
    return names


class Heartbeat(NamedTuple):
    """``Heartbeat`` (0x01, node → host, cyclic)."""

    axis_error: int
    axis_state: int
    procedure_result: int
    trajectory_done: bool


class Version(NamedTuple):
    """``Get_Version`` (0x00, node -> host): one byte each, in the DBC's order."""

    protocol: int
    hw_major: int
    hw_minor: int
    hw_variant: int
    fw_major: int
    fw_minor: int
    fw_revision: int
    fw_unreleased: int

    @property
    def hardware(self) -> str:
        """``major.minor-variant``, as odrivetool prints a board's hardware version."""
        return f"{self.hw_major}.{self.hw_minor}-{self.hw_variant}"

    @property
    def firmware(self) -> str:
        """``major.minor.revision`` (``-dev`` when unreleased)."""
        dev = "-dev" if self.fw_unreleased else ""
        return f"{self.fw_major}.{self.fw_minor}.{self.fw_revision}{dev}"


class EncoderEstimates(NamedTuple):
    """``Get_Encoder_Estimates`` (0x09, node → host): rev and rev/s."""

    pos: float
    vel: float


class ErrorStatus(NamedTuple):
    """``Get_Error`` (0x03, node → host)."""

    active_errors: int
    disarm_reason: int


def arbitration_id(node_id: int, cmd: int) -> int:
    """The arbitration id of a command to or from a node.

    Args:
        node_id: 0..63.
        cmd: 0..31 (a :class:`Cmd`).

    Returns:
        ``node_id << 5 | cmd``.

    Raises:
        ValueError: Either is out of range.
    """
    if not 0 <= node_id <= MAX_NODE_ID:
        raise ValueError(f"node id must be 0..{MAX_NODE_ID}, got {node_id}")
    if not 0 <= cmd <= 0x1F:
        raise ValueError(f"command id must be 0..31, got {cmd}")
    return node_id << 5 | cmd


def split_id(arbitration_id: int) -> tuple[int, int]:
    """The (node id, command id) of an arbitration id.

    Args:
        arbitration_id: An 11-bit id.

    Returns:
        ``(node_id, cmd)``.
    """
    return (arbitration_id >> 5) & MAX_NODE_ID, arbitration_id & 0x1F
