"""The MIT-mode CAN protocol of CubeMars/T-Motor AK motors (and Mini-Cheetah-style drives), pure.

A motor listens on the standard arbitration id equal to its motor id. Three special 8-byte
frames switch it: ``FF FF FF FF FF FF FF FC`` enters motor mode, ``… FD`` exits it and
``… FE`` sets the current position as zero. Every other 8-byte frame is a command, packed as
big-endian bit fields::

    p (16 bits) | v (12) | kp (12) | kd (12) | t_ff (12)

Each field is the value clamped to its range and mapped linearly onto ``0 .. 2**bits - 1``.
The motor answers every frame with a reply on the host id (0 by default)::

    motor id (8) | p (16) | v (12) | t (12) [| temperature (8) | error code (8)]

Six bytes is the classic reply; newer CubeMars firmware appends the driver temperature (°C)
and an error code (:data:`ERROR_CODES`). The ranges of position, velocity and torque depend on
the model (:data:`MODELS`); kp is 0..500 N·m/rad and kd 0..5 N·m·s/rad for all of them.
Units are the motor's output side: rad, rad/s, N·m.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final, NamedTuple

__all__ = [
    "CMD_ENTER",
    "CMD_EXIT",
    "CMD_ZERO",
    "ERROR_CODES",
    "MODELS",
    "MitCommand",
    "MitRanges",
    "MitReply",
    "decode_command",
    "decode_reply",
    "encode_command",
    "encode_reply",
    "float_to_uint",
    "special",
    "uint_to_float",
]

CMD_ENTER: Final = b"\xff\xff\xff\xff\xff\xff\xff\xfc"
CMD_EXIT: Final = b"\xff\xff\xff\xff\xff\xff\xff\xfd"
CMD_ZERO: Final = b"\xff\xff\xff\xff\xff\xff\xff\xfe"

#: Error codes in byte 7 of an 8-byte reply (CubeMars AK firmware).
ERROR_CODES: Final = {
    0: "none",
    1: "motor over-temperature",
    2: "over-current",
    3: "over-voltage",
    4: "under-voltage",
    5: "encoder fault",
    6: "phase current unbalance",
}

KP_MAX: Final = 500.0
KD_MAX: Final = 5.0


@dataclass(frozen=True, slots=True)
class MitRanges:
    """The symmetric ranges a motor maps its fields onto.

    Attributes:
        p_max: Position range ±p_max, rad.
        v_max: Velocity range ±v_max, rad/s.
        t_max: Torque range ±t_max, N·m.
        kp_max: kp range 0..kp_max.
        kd_max: kd range 0..kd_max.

    Raises:
        ValueError: A range is not positive.
    """

    p_max: float = 12.5
    v_max: float = 50.0
    t_max: float = 18.0
    kp_max: float = KP_MAX
    kd_max: float = KD_MAX

    def __post_init__(self) -> None:
        for name in ("p_max", "v_max", "t_max", "kp_max", "kd_max"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and 0 < value < float("inf")):
                raise ValueError(f"{name} must be a positive number, got {value!r}")


#: MIT-mode ranges of common AK models (CubeMars AK-series manual; check your firmware).
MODELS: Final = {
    "AK10-9": MitRanges(12.5, 50.0, 65.0),
    "AK60-6": MitRanges(12.5, 45.0, 15.0),
    "AK70-10": MitRanges(12.5, 50.0, 25.0),
    "AK80-6": MitRanges(12.5, 76.0, 12.0),
    "AK80-9": MitRanges(12.5, 50.0, 18.0),
}


class MitCommand(NamedTuple):
    """One command frame's fields (rad, rad/s, N·m/rad, N·m·s/rad, N·m)."""

    p: float
    v: float
    kp: float
    kd: float
    t: float


class MitReply(NamedTuple):
    """One reply frame's fields; ``temperature`` and ``error`` are None in a 6-byte reply."""

    motor_id: int
    p: float
    v: float
    t: float
    temperature: int | None = None
    error: int | None = None


def float_to_uint(x: float, lo: float, hi: float, bits: int) -> int:
    """Clamp ``x`` to ``[lo, hi]`` and map it onto ``0 .. 2**bits - 1`` (rounded down).

    Rounding down is what the manufacturer's reference code does; a millionth of a step is
    added first so that a decoded value encodes to the same field despite float rounding.

    Args:
        x: The value (NaN maps to ``lo``).
        lo: The range's low end.
        hi: The range's high end (> lo).
        bits: The field width.

    Returns:
        The field value.
    """
    top = (1 << bits) - 1
    if not x > lo:  # also NaN
        return 0
    if x >= hi:
        return top
    return min(int((x - lo) * top / (hi - lo) + 1e-6), top)


def uint_to_float(u: int, lo: float, hi: float, bits: int) -> float:
    """Map a field value back onto ``[lo, hi]``.

    Args:
        u: The field value.
        lo: The range's low end.
        hi: The range's high end.
        bits: The field width.

    Returns:
        The value.
    """
    return u * (hi - lo) / ((1 << bits) - 1) + lo


def special(data: bytes | bytearray) -> str | None:
    """Which special frame ``data`` is: ``"enter"``, ``"exit"``, ``"zero"``, or None.

    Args:
        data: A frame's payload.

    Returns:
        The name, or None for a command.
    """
    if len(data) == 8 and data[:7] == b"\xff" * 7:
        return {0xFC: "enter", 0xFD: "exit", 0xFE: "zero"}.get(data[7])
    return None


def encode_command(cmd: MitCommand, ranges: MitRanges) -> bytes:
    """Pack a command frame (values beyond their range are clamped).

    Args:
        cmd: The fields.
        ranges: The motor's ranges.

    Returns:
        8 bytes.
    """
    p = float_to_uint(cmd.p, -ranges.p_max, ranges.p_max, 16)
    v = float_to_uint(cmd.v, -ranges.v_max, ranges.v_max, 12)
    kp = float_to_uint(cmd.kp, 0.0, ranges.kp_max, 12)
    kd = float_to_uint(cmd.kd, 0.0, ranges.kd_max, 12)
    t = float_to_uint(cmd.t, -ranges.t_max, ranges.t_max, 12)
    return bytes(
        (
            p >> 8,
            p & 0xFF,
            v >> 4,
            (v & 0xF) << 4 | kp >> 8,
            kp & 0xFF,
            kd >> 4,
            (kd & 0xF) << 4 | t >> 8,
            t & 0xFF,
        )
    )


def decode_command(data: bytes | bytearray, ranges: MitRanges) -> MitCommand:
    """Unpack a command frame.

    Args:
        data: 8 bytes (not a special frame).
        ranges: The motor's ranges.

    Returns:
        The fields.

    Raises:
        ValueError: Wrong length.
    """
    if len(data) != 8:
        raise ValueError(f"MIT command: expected 8 data bytes, got {len(data)}")
    p = data[0] << 8 | data[1]
    v = data[2] << 4 | data[3] >> 4
    kp = (data[3] & 0xF) << 8 | data[4]
    kd = data[5] << 4 | data[6] >> 4
    t = (data[6] & 0xF) << 8 | data[7]
    return MitCommand(
        uint_to_float(p, -ranges.p_max, ranges.p_max, 16),
        uint_to_float(v, -ranges.v_max, ranges.v_max, 12),
        uint_to_float(kp, 0.0, ranges.kp_max, 12),
        uint_to_float(kd, 0.0, ranges.kd_max, 12),
        uint_to_float(t, -ranges.t_max, ranges.t_max, 12),
    )


def encode_reply(reply: MitReply, ranges: MitRanges) -> bytes:
    """Pack a reply frame (6 bytes, or 8 with temperature and error code).

    Args:
        reply: The fields (temperature and error both set, or both None).
        ranges: The motor's ranges.

    Returns:
        The payload.

    Raises:
        ValueError: A motor id, temperature or error code does not fit a byte.
    """
    if not 0 <= reply.motor_id <= 0xFF:
        raise ValueError(f"motor id must be 0..255, got {reply.motor_id}")
    p = float_to_uint(reply.p, -ranges.p_max, ranges.p_max, 16)
    v = float_to_uint(reply.v, -ranges.v_max, ranges.v_max, 12)
    t = float_to_uint(reply.t, -ranges.t_max, ranges.t_max, 12)
    out = bytes((reply.motor_id, p >> 8, p & 0xFF, v >> 4, (v & 0xF) << 4 | t >> 8, t & 0xFF))
    if reply.temperature is None and reply.error is None:
        return out
    temperature = reply.temperature if reply.temperature is not None else 0
    error = reply.error if reply.error is not None else 0
    if not (-128 <= temperature <= 127 and 0 <= error <= 0xFF):
        raise ValueError(f"temperature/error out of range: {temperature}, {error}")
    return out + bytes((temperature & 0xFF, error))


def decode_reply(data: bytes | bytearray, ranges: MitRanges) -> MitReply:
    """Unpack a reply frame.

    Args:
        data: 6 or 8 bytes.
        ranges: The motor's ranges.

    Returns:
        The fields.

    Raises:
        ValueError: Wrong length.
    """
    n = len(data)
    if n not in (6, 8):
        raise ValueError(f"MIT reply: expected 6 or 8 data bytes, got {n}")
    p = data[1] << 8 | data[2]
    v = data[3] << 4 | data[4] >> 4
    t = (data[4] & 0xF) << 8 | data[5]
    temperature = error = None
    if n == 8:
        temperature = data[6] - 256 if data[6] > 127 else data[6]
        error = data[7]
    return MitReply(
        data[0],
        uint_to_float(p, -ranges.p_max, ranges.p_max, 16),
        uint_to_float(v, -ranges.v_max, ranges.v_max, 12),
        uint_to_float(t, -ranges.t_max, ranges.t_max, 12),
        temperature,
        error,
    )
