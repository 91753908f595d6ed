"""MAVLink 2 encode and decode: a thin, typed adapter over pymavlink's ``ardupilotmega`` dialect.

Pure functions and one small stateful codec, no I/O and no threads (docs/development.md §6).
The dialect is imported explicitly (``pymavlink.dialects.v20.ardupilotmega``, which includes
``common``); no ``mavutil`` and none of its module-level state is used.

:class:`Codec` packs messages for one sender (system id, component id, sequence number) and
parses what others send into :class:`Message` values: :meth:`Codec.decode_datagram` parses one
UDP datagram on its own (a fresh parser each time, so a datagram whose header claims more bytes
than it holds cannot swallow the frames of the next one), :meth:`Codec.decode` a chunk of a byte
stream (a serial port: a frame split across reads is completed later). Frames with a bad CRC or
an unknown message id, and a datagram's truncated tail, are counted (:attr:`Codec.bad_frames`)
and dropped; they never come back as "bad data" objects.

The constants below are the MAVLink and ArduCopter numbers the driver and the simulator use;
they are re-exported from the dialect so there is one source of truth.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Final

from pymavlink.dialects.v20 import ardupilotmega as _dialect  # type: ignore[import-untyped]

__all__ = [
    "COPTER_MODES",
    "Codec",
    "Message",
    "command_name",
    "corrupt",
    "enum_name",
    "mode_name",
    "mode_number",
    "result_name",
]

# ---- numbers -------------------------------------------------------------------------------

MAV_TYPE_QUADROTOR: Final[int] = int(_dialect.MAV_TYPE_QUADROTOR)
MAV_TYPE_GCS: Final[int] = int(_dialect.MAV_TYPE_GCS)
MAV_AUTOPILOT_ARDUPILOTMEGA: Final[int] = int(_dialect.MAV_AUTOPILOT_ARDUPILOTMEGA)
MAV_AUTOPILOT_INVALID: Final[int] = int(_dialect.MAV_AUTOPILOT_INVALID)
#: common.xml MAV_COMPONENT: "System flight controller component ("autopilot"). Only one
#: autopilot is expected in a particular system." ArduPilot sends as this component.
MAV_COMP_ID_AUTOPILOT1: Final[int] = int(_dialect.MAV_COMP_ID_AUTOPILOT1)
#: Seconds between ArduPilot's HEARTBEATs: it sends one a second on every link, whatever
#: streams were asked for (the MAVLink heartbeat microservice's recommended 1 Hz).
VEHICLE_HEARTBEAT_PERIOD: Final = 1.0

MAV_MODE_FLAG_CUSTOM_MODE_ENABLED: Final[int] = int(_dialect.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED)
MAV_MODE_FLAG_SAFETY_ARMED: Final[int] = int(_dialect.MAV_MODE_FLAG_SAFETY_ARMED)
MAV_MODE_FLAG_GUIDED_ENABLED: Final[int] = int(_dialect.MAV_MODE_FLAG_GUIDED_ENABLED)
MAV_MODE_FLAG_STABILIZE_ENABLED: Final[int] = int(_dialect.MAV_MODE_FLAG_STABILIZE_ENABLED)

MAV_STATE_STANDBY: Final[int] = int(_dialect.MAV_STATE_STANDBY)
MAV_STATE_ACTIVE: Final[int] = int(_dialect.MAV_STATE_ACTIVE)
MAV_STATE_CRITICAL: Final[int] = int(_dialect.MAV_STATE_CRITICAL)

MAV_CMD_NAV_RETURN_TO_LAUNCH: Final[int] = int(_dialect.MAV_CMD_NAV_RETURN_TO_LAUNCH)  # 20
MAV_CMD_NAV_LAND: Final[int] = int(_dialect.MAV_CMD_NAV_LAND)  # 21
MAV_CMD_NAV_TAKEOFF: Final[int] = int(_dialect.MAV_CMD_NAV_TAKEOFF)  # 22
MAV_CMD_DO_SET_MODE: Final[int] = int(_dialect.MAV_CMD_DO_SET_MODE)  # 176
MAV_CMD_DO_REPOSITION: Final[int] = int(_dialect.MAV_CMD_DO_REPOSITION)  # 192
MAV_CMD_COMPONENT_ARM_DISARM: Final[int] = int(_dialect.MAV_CMD_COMPONENT_ARM_DISARM)  # 400
MAV_CMD_SET_MESSAGE_INTERVAL: Final[int] = int(_dialect.MAV_CMD_SET_MESSAGE_INTERVAL)  # 511
MAV_CMD_REQUEST_MESSAGE: Final[int] = int(_dialect.MAV_CMD_REQUEST_MESSAGE)  # 512
MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES: Final[int] = int(
    _dialect.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES
)  # 520

MAV_PARAM_TYPE_INT8: Final[int] = int(_dialect.MAV_PARAM_TYPE_INT8)
MAV_PARAM_TYPE_INT16: Final[int] = int(_dialect.MAV_PARAM_TYPE_INT16)
MAV_PARAM_TYPE_INT32: Final[int] = int(_dialect.MAV_PARAM_TYPE_INT32)
MAV_PARAM_TYPE_REAL32: Final[int] = int(_dialect.MAV_PARAM_TYPE_REAL32)

MAV_RESULT_ACCEPTED: Final[int] = int(_dialect.MAV_RESULT_ACCEPTED)
MAV_RESULT_TEMPORARILY_REJECTED: Final[int] = int(_dialect.MAV_RESULT_TEMPORARILY_REJECTED)
MAV_RESULT_DENIED: Final[int] = int(_dialect.MAV_RESULT_DENIED)
MAV_RESULT_UNSUPPORTED: Final[int] = int(_dialect.MAV_RESULT_UNSUPPORTED)
MAV_RESULT_FAILED: Final[int] = int(_dialect.MAV_RESULT_FAILED)
MAV_RESULT_IN_PROGRESS: Final[int] = int(_dialect.MAV_RESULT_IN_PROGRESS)

MAV_FRAME_GLOBAL_INT: Final[int] = int(_dialect.MAV_FRAME_GLOBAL_INT)  # altitude AMSL
MAV_FRAME_GLOBAL_RELATIVE_ALT_INT: Final[int] = int(_dialect.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT)
MAV_FRAME_GLOBAL: Final[int] = int(_dialect.MAV_FRAME_GLOBAL)
MAV_FRAME_GLOBAL_RELATIVE_ALT: Final[int] = int(_dialect.MAV_FRAME_GLOBAL_RELATIVE_ALT)

MAV_LANDED_STATE_ON_GROUND: Final[int] = int(_dialect.MAV_LANDED_STATE_ON_GROUND)
MAV_LANDED_STATE_IN_AIR: Final[int] = int(_dialect.MAV_LANDED_STATE_IN_AIR)
MAV_LANDED_STATE_TAKEOFF: Final[int] = int(_dialect.MAV_LANDED_STATE_TAKEOFF)
MAV_LANDED_STATE_LANDING: Final[int] = int(_dialect.MAV_LANDED_STATE_LANDING)

MAV_SEVERITY_CRITICAL: Final[int] = int(_dialect.MAV_SEVERITY_CRITICAL)
MAV_SEVERITY_WARNING: Final[int] = int(_dialect.MAV_SEVERITY_WARNING)
MAV_SEVERITY_INFO: Final[int] = int(_dialect.MAV_SEVERITY_INFO)

MAV_BATTERY_CHARGE_STATE_OK: Final[int] = int(_dialect.MAV_BATTERY_CHARGE_STATE_OK)
MAV_BATTERY_CHARGE_STATE_LOW: Final[int] = int(_dialect.MAV_BATTERY_CHARGE_STATE_LOW)
MAV_BATTERY_CHARGE_STATE_CRITICAL: Final[int] = int(_dialect.MAV_BATTERY_CHARGE_STATE_CRITICAL)

MAV_DO_REPOSITION_FLAGS_CHANGE_MODE: Final[int] = int(_dialect.MAV_DO_REPOSITION_FLAGS_CHANGE_MODE)
MAV_BATTERY_FAULT_OVER_TEMPERATURE: Final[int] = int(_dialect.MAV_BATTERY_FAULT_OVER_TEMPERATURE)
MAV_BATTERY_TYPE_LIPO: Final[int] = int(_dialect.MAV_BATTERY_TYPE_LIPO)

MAV_PROTOCOL_CAPABILITY_MAVLINK2: Final[int] = int(_dialect.MAV_PROTOCOL_CAPABILITY_MAVLINK2)
MAV_PROTOCOL_CAPABILITY_COMMAND_INT: Final[int] = int(_dialect.MAV_PROTOCOL_CAPABILITY_COMMAND_INT)
MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_GLOBAL_INT: Final[int] = int(
    _dialect.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_GLOBAL_INT
)

# ---- used by the simulator's parameter, mission and FTP services ----------------------------

MAV_CMD_NAV_WAYPOINT: Final[int] = int(_dialect.MAV_CMD_NAV_WAYPOINT)  # 16
MAV_CMD_NAV_LOITER_UNLIM: Final[int] = int(_dialect.MAV_CMD_NAV_LOITER_UNLIM)  # 17
MAV_CMD_NAV_LOITER_TIME: Final[int] = int(_dialect.MAV_CMD_NAV_LOITER_TIME)  # 19
MAV_CMD_DO_JUMP: Final[int] = int(_dialect.MAV_CMD_DO_JUMP)  # 177
MAV_CMD_DO_CHANGE_SPEED: Final[int] = int(_dialect.MAV_CMD_DO_CHANGE_SPEED)  # 178
MAV_CMD_DO_SET_HOME: Final[int] = int(_dialect.MAV_CMD_DO_SET_HOME)  # 179
MAV_CMD_DO_SET_MISSION_CURRENT: Final[int] = int(_dialect.MAV_CMD_DO_SET_MISSION_CURRENT)  # 224
MAV_CMD_MISSION_START: Final[int] = int(_dialect.MAV_CMD_MISSION_START)  # 300
MAV_CMD_GET_HOME_POSITION: Final[int] = int(_dialect.MAV_CMD_GET_HOME_POSITION)  # 410

MAV_FRAME_MISSION: Final[int] = int(_dialect.MAV_FRAME_MISSION)
MAV_FRAME_GLOBAL_TERRAIN_ALT: Final[int] = int(_dialect.MAV_FRAME_GLOBAL_TERRAIN_ALT)
MAV_FRAME_GLOBAL_TERRAIN_ALT_INT: Final[int] = int(_dialect.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT)

MAV_MISSION_TYPE_MISSION: Final[int] = int(_dialect.MAV_MISSION_TYPE_MISSION)
MAV_MISSION_TYPE_FENCE: Final[int] = int(_dialect.MAV_MISSION_TYPE_FENCE)
MAV_MISSION_TYPE_RALLY: Final[int] = int(_dialect.MAV_MISSION_TYPE_RALLY)
MAV_MISSION_TYPE_ALL: Final[int] = int(_dialect.MAV_MISSION_TYPE_ALL)

MAV_MISSION_ACCEPTED: Final[int] = int(_dialect.MAV_MISSION_ACCEPTED)
MAV_MISSION_ERROR: Final[int] = int(_dialect.MAV_MISSION_ERROR)
MAV_MISSION_UNSUPPORTED_FRAME: Final[int] = int(_dialect.MAV_MISSION_UNSUPPORTED_FRAME)
MAV_MISSION_UNSUPPORTED: Final[int] = int(_dialect.MAV_MISSION_UNSUPPORTED)
MAV_MISSION_NO_SPACE: Final[int] = int(_dialect.MAV_MISSION_NO_SPACE)
MAV_MISSION_INVALID_SEQUENCE: Final[int] = int(_dialect.MAV_MISSION_INVALID_SEQUENCE)
MAV_MISSION_DENIED: Final[int] = int(_dialect.MAV_MISSION_DENIED)
MAV_MISSION_OPERATION_CANCELLED: Final[int] = int(_dialect.MAV_MISSION_OPERATION_CANCELLED)

MISSION_STATE_NO_MISSION: Final[int] = int(_dialect.MISSION_STATE_NO_MISSION)
MISSION_STATE_NOT_STARTED: Final[int] = int(_dialect.MISSION_STATE_NOT_STARTED)
MISSION_STATE_ACTIVE: Final[int] = int(_dialect.MISSION_STATE_ACTIVE)
MISSION_STATE_PAUSED: Final[int] = int(_dialect.MISSION_STATE_PAUSED)
MISSION_STATE_COMPLETE: Final[int] = int(_dialect.MISSION_STATE_COMPLETE)

MAV_DATA_STREAM_ALL: Final[int] = int(_dialect.MAV_DATA_STREAM_ALL)
MAV_DATA_STREAM_EXTENDED_STATUS: Final[int] = int(_dialect.MAV_DATA_STREAM_EXTENDED_STATUS)
MAV_DATA_STREAM_RC_CHANNELS: Final[int] = int(_dialect.MAV_DATA_STREAM_RC_CHANNELS)
MAV_DATA_STREAM_POSITION: Final[int] = int(_dialect.MAV_DATA_STREAM_POSITION)
MAV_DATA_STREAM_EXTRA1: Final[int] = int(_dialect.MAV_DATA_STREAM_EXTRA1)
MAV_DATA_STREAM_EXTRA2: Final[int] = int(_dialect.MAV_DATA_STREAM_EXTRA2)
MAV_DATA_STREAM_EXTRA3: Final[int] = int(_dialect.MAV_DATA_STREAM_EXTRA3)

MAV_SYS_STATUS_PREARM_CHECK: Final[int] = int(_dialect.MAV_SYS_STATUS_PREARM_CHECK)
MAV_SYS_STATUS_GEOFENCE: Final[int] = int(_dialect.MAV_SYS_STATUS_GEOFENCE)
MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT: Final[int] = int(_dialect.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT)
MAV_PROTOCOL_CAPABILITY_MISSION_INT: Final[int] = int(_dialect.MAV_PROTOCOL_CAPABILITY_MISSION_INT)
MAV_PROTOCOL_CAPABILITY_MISSION_FENCE: Final[int] = int(
    _dialect.MAV_PROTOCOL_CAPABILITY_MISSION_FENCE
)
MAV_PROTOCOL_CAPABILITY_MISSION_RALLY: Final[int] = int(
    _dialect.MAV_PROTOCOL_CAPABILITY_MISSION_RALLY
)
MAV_MODE_FLAG_MANUAL_INPUT_ENABLED: Final[int] = int(_dialect.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED)
MAV_POWER_STATUS_BRICK_VALID: Final[int] = int(_dialect.MAV_POWER_STATUS_BRICK_VALID)

#: MAVLink FTP (FILE_TRANSFER_PROTOCOL payload) opcodes and NAK error codes used by the
#: simulator (https://mavlink.io/en/services/ftp.html).
FTP_OP_TERMINATE_SESSION: Final = 1
FTP_OP_RESET_SESSIONS: Final = 2
FTP_OP_READ_FILE: Final = 5
FTP_OP_WRITE_FILE: Final = 7
FTP_OP_BURST_READ_FILE: Final = 15
FTP_OP_ACK: Final = 128
FTP_OP_NAK: Final = 129
FTP_ERR_INVALID_SESSION: Final = 4
FTP_ERR_FILE_NOT_FOUND: Final = 10

#: The MAV_CMD ids the dialect defines (for checking uploaded mission items).
MAV_CMDS: Final[frozenset[int]] = frozenset(
    int(k) for k, entry in _dialect.enums["MAV_CMD"].items() if not entry.name.endswith("ENUM_END")
)

#: SYS_STATUS sensor bits by name (``MAV_SYS_STATUS_SENSOR_GPS`` → ``GPS``).
SENSOR_BITS: Final[Mapping[str, int]] = {
    name.removeprefix("MAV_SYS_STATUS_SENSOR_"): int(getattr(_dialect, name))
    for name in dir(_dialect)
    if name.startswith("MAV_SYS_STATUS_SENSOR_") and not name.endswith("ENUM_END")
}

#: Message ids by name (only the ones the driver and simulator name explicitly).
MSG_ID: Final[Mapping[str, int]] = {
    name.removeprefix("MAVLINK_MSG_ID_"): int(getattr(_dialect, name))
    for name in dir(_dialect)
    if name.startswith("MAVLINK_MSG_ID_") and isinstance(getattr(_dialect, name), int)
}

#: ArduCopter flight modes: name → ``custom_mode`` (ArduPilot's Copter ``mode.h`` numbers).
COPTER_MODES: Final[Mapping[str, int]] = {
    "STABILIZE": 0,
    "ACRO": 1,
    "ALT_HOLD": 2,
    "AUTO": 3,
    "GUIDED": 4,
    "LOITER": 5,
    "RTL": 6,
    "CIRCLE": 7,
    "LAND": 9,
    "DRIFT": 11,
    "SPORT": 13,
    "FLIP": 14,
    "AUTOTUNE": 15,
    "POSHOLD": 16,
    "BRAKE": 17,
    "THROW": 18,
    "AVOID_ADSB": 19,
    "GUIDED_NOGPS": 20,
    "SMART_RTL": 21,
}
_MODE_NAMES: Final[Mapping[int, str]] = {number: name for name, number in COPTER_MODES.items()}


def mode_name(custom_mode: int) -> str:
    """The ArduCopter mode name of a heartbeat's ``custom_mode``.

    Args:
        custom_mode: The number.

    Returns:
        The name, or ``MODE(<n>)`` for a number ArduCopter does not define.
    """
    return _MODE_NAMES.get(custom_mode, f"MODE({custom_mode})")


def mode_number(name: str) -> int:
    """The ArduCopter ``custom_mode`` of a mode name (case-insensitive).

    Args:
        name: ``GUIDED``, ``LAND``, ...

    Returns:
        The number.

    Raises:
        ValueError: Not an ArduCopter mode.
    """
    try:
        return COPTER_MODES[name.strip().upper()]
    except KeyError:
        known = ", ".join(COPTER_MODES)
        raise ValueError(f"unknown ArduCopter flight mode {name!r} (known: {known})") from None


def enum_name(enum: str, value: int) -> str:
    """The name of ``value`` in a MAVLink enum of the dialect (``ENUM(<n>)`` if unknown).

    Args:
        enum: The enum's name (``MAV_TYPE``, ``MAV_FRAME``, ...).
        value: The number.

    Returns:
        The entry's name.
    """
    entry = _dialect.enums.get(enum, {}).get(value)
    return str(entry.name) if entry is not None else f"{enum}({value})"


def command_name(command: int) -> str:
    """The ``MAV_CMD_*`` name of a command id (``MAV_CMD(<n>)`` if unknown).

    Args:
        command: The id.

    Returns:
        The name.
    """
    return enum_name("MAV_CMD", command)


def result_name(result: int) -> str:
    """The ``MAV_RESULT_*`` name of a command result (``MAV_RESULT(<n>)`` if unknown).

    Args:
        result: The value.

    Returns:
        The name.
    """
    return enum_name("MAV_RESULT", result)


# ---- messages ------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Message:
    """One decoded MAVLink message.

    Attributes:
        name: The message name (``HEARTBEAT``, ``COMMAND_ACK``, ...).
        msg_id: Its numeric id.
        src_system: The sender's system id.
        src_component: The sender's component id.
        fields: Field name → value (ints, floats, ``str`` for char arrays, lists for arrays).
        seq: The frame's sequence number (0..255, counted per sender; -1 when unknown).
    """

    name: str
    msg_id: int
    src_system: int
    src_component: int
    fields: Mapping[str, Any]
    seq: int = -1

    def get_int(self, field: str) -> int:
        """A field as an ``int``.

        Args:
            field: Its name.

        Returns:
            The value.

        Raises:
            KeyError: The message has no such field.
        """
        return int(self.fields[field])

    def get_float(self, field: str) -> float:
        """A field as a ``float``.

        Args:
            field: Its name.

        Returns:
            The value.

        Raises:
            KeyError: The message has no such field.
        """
        return float(self.fields[field])

    def get_text(self, field: str) -> str:
        """A ``char[]`` field as text (trailing NULs removed).

        Args:
            field: Its name.

        Returns:
            The text.

        Raises:
            KeyError: The message has no such field.
        """
        value = self.fields[field]
        if isinstance(value, bytes):
            value = value.decode("utf-8", "replace")
        return str(value).rstrip("\x00")


def _field_value(value: Any) -> Any:
    if isinstance(value, bytes):
        return value.decode("utf-8", "replace").rstrip("\x00")
    return value


class Codec:
    """Packs messages as one MAVLink 2 sender and parses what others send.

    :meth:`encode` may be called from any thread; :meth:`decode` from one thread at a time.

    Args:
        system_id: This end's system id (1..255).
        component_id: This end's component id (0..255).

    Raises:
        ValueError: An id out of range.
    """

    def __init__(self, system_id: int, component_id: int) -> None:
        if not (1 <= system_id <= 255 and 0 <= component_id <= 255):
            raise ValueError(f"bad MAVLink ids: system {system_id}, component {component_id}")
        self.system_id = system_id
        self.component_id = component_id
        self._tx = _dialect.MAVLink(None, system_id, component_id)
        self._rx = _dialect.MAVLink(None, system_id, component_id)
        self._rx.robust_parsing = True  # bad frames come back as objects we count and drop
        self._tx_lock = threading.Lock()
        #: Frames dropped because their CRC was wrong or their id unknown.
        self.bad_frames = 0

    def encode(self, name: str, **fields: Any) -> bytes:
        """Pack one message (the next sequence number of this sender).

        Args:
            name: The message name, any case (``heartbeat``, ``COMMAND_LONG``).
            **fields: Its fields; MAVLink 2 extension fields may be left out (zero).

        Returns:
            The frame's bytes.

        Raises:
            ValueError: An unknown message, a missing or bad field.
        """
        encoder = getattr(self._tx, f"{name.lower()}_encode", None)
        if encoder is None:
            raise ValueError(f"unknown MAVLink message {name!r}")
        try:
            with self._tx_lock:
                msg = encoder(**fields)
                frame = bytes(msg.pack(self._tx))
                # pymavlink's pack() leaves the count alone (its send() advances it): MAVLink's
                # sequence number counts each sender's frames, and receivers rely on it
                self._tx.seq = (self._tx.seq + 1) % 256
                return frame
        except (TypeError, ValueError, OverflowError, _dialect.MAVError) as err:
            raise ValueError(f"cannot encode {name.upper()}: {err}") from err
        except Exception as err:  # struct.error and friends from the generated packers
            raise ValueError(f"cannot encode {name.upper()}: {err}") from err

    def decode(self, data: bytes) -> list[Message]:
        """Parse a chunk of a byte stream (a serial port) into messages.

        Args:
            data: The bytes received; a frame split across calls is completed later.

        Returns:
            The complete, valid messages in it (bad frames are counted and dropped).
        """
        return self._parse(self._rx, data)

    def decode_datagram(self, data: bytes) -> list[Message]:
        """Parse one whole datagram (UDP) into messages, on its own.

        Each call starts from a fresh parser state: bytes left over at the end of the datagram
        (a frame whose header claims more bytes than the datagram holds) are one bad frame, and
        never wait for the next datagram.

        Args:
            data: The datagram.

        Returns:
            The complete, valid messages in it (bad frames are counted and dropped).
        """
        parser = _dialect.MAVLink(None, self.system_id, self.component_id)
        parser.robust_parsing = True
        out = self._parse(parser, data)
        if parser.buf_len() > 0:
            self.bad_frames += 1  # a truncated frame: it never completes
        return out

    def _parse(self, parser: Any, data: bytes) -> list[Message]:
        out: list[Message] = []
        try:
            parsed = parser.parse_buffer(data) or []
        except Exception:  # the legacy parser can still raise on mangled headers
            self.bad_frames += 1
            return out
        for raw in parsed:
            name = raw.get_type()
            if name == "BAD_DATA" or raw.get_msgId() < 0:
                self.bad_frames += 1
                continue
            fields = {f: _field_value(getattr(raw, f)) for f in raw.get_fieldnames()}
            out.append(
                Message(
                    name,
                    int(raw.get_msgId()),
                    raw.get_srcSystem(),
                    raw.get_srcComponent(),
                    fields,
                    int(raw.get_seq()),
                )
            )
        return out


def corrupt(frame: bytes) -> bytes:
    """The same frame with its CRC inverted (what a noisy link delivers).

    Args:
        frame: A packed, unsigned MAVLink frame.

    Returns:
        The frame with both checksum bytes flipped.
    """
    if len(frame) < 3:
        return frame
    return frame[:-2] + bytes(b ^ 0xFF for b in frame[-2:])


def deg_e7(degrees: float) -> int:
    """Degrees as MAVLink's ``int32`` degrees·10⁷.

    Args:
        degrees: Latitude or longitude.

    Returns:
        The scaled, rounded value.
    """
    return round(degrees * 1e7)


def nan_if_none(value: float | None) -> float:
    """NaN for None (MAVLink's "leave unchanged" for float params).

    Args:
        value: A value or None.

    Returns:
        The value, or NaN.
    """
    return math.nan if value is None else float(value)


# ---- the driver's mission and parameter microservices (shared constants are above) ----------

MAV_FRAME_GLOBAL_INT_FRAMES: Final = frozenset(
    {int(_dialect.MAV_FRAME_GLOBAL), int(_dialect.MAV_FRAME_GLOBAL_INT)}
)
MAV_FRAME_RELATIVE_FRAMES: Final = frozenset(
    {int(_dialect.MAV_FRAME_GLOBAL_RELATIVE_ALT), int(_dialect.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT)}
)

MAV_PARAM_TYPE_UINT8: Final[int] = int(_dialect.MAV_PARAM_TYPE_UINT8)
MAV_PARAM_TYPE_UINT16: Final[int] = int(_dialect.MAV_PARAM_TYPE_UINT16)
MAV_PARAM_TYPE_UINT32: Final[int] = int(_dialect.MAV_PARAM_TYPE_UINT32)
MAV_PARAM_TYPE_REAL64: Final[int] = int(_dialect.MAV_PARAM_TYPE_REAL64)

#: Integer MAV_PARAM_TYPEs → the (low, high) range of their values.
PARAM_INT_RANGES: Final[Mapping[int, tuple[int, int]]] = {
    MAV_PARAM_TYPE_UINT8: (0, 0xFF),
    MAV_PARAM_TYPE_INT8: (-0x80, 0x7F),
    MAV_PARAM_TYPE_UINT16: (0, 0xFFFF),
    MAV_PARAM_TYPE_INT16: (-0x8000, 0x7FFF),
    MAV_PARAM_TYPE_UINT32: (0, 0xFFFFFFFF),
    MAV_PARAM_TYPE_INT32: (-0x80000000, 0x7FFFFFFF),
}
#: The largest integer a float32 carries exactly (ArduPilot sends every value as a float).
FLOAT32_EXACT_INT: Final[int] = 1 << 24
#: A parameter name's longest length (PARAM_VALUE's ``param_id`` is char[16]).
PARAM_ID_LEN: Final[int] = 16


def mission_result_name(result: int) -> str:
    """The ``MAV_MISSION_*`` name of a MISSION_ACK type (``MAV_MISSION_RESULT(<n>)`` if unknown).

    Args:
        result: The value.

    Returns:
        The name.
    """
    return enum_name("MAV_MISSION_RESULT", result)


def param_type_name(param_type: int) -> str:
    """The ``MAV_PARAM_TYPE_*`` name of a parameter type.

    Args:
        param_type: The value.

    Returns:
        The name (``MAV_PARAM_TYPE(<n>)`` if unknown).
    """
    return enum_name("MAV_PARAM_TYPE", param_type)
