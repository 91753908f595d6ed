"""DYNAMIXEL Protocol 2.0: packets, CRC-16, byte stuffing and status errors (pure, no I/O).

A packet on the wire is::

    FF FF FD 00 | ID | LEN_L LEN_H | INST | PARAM ... | CRC_L CRC_H

``LEN`` counts the instruction byte, the (stuffed) parameters and the two CRC bytes. A status
packet (the device's reply) has ``INST = 0x55`` and an error byte before its parameters. Inside
the instruction and parameters, every ``FF FF FD`` is sent as ``FF FF FD FD`` (byte stuffing) so
a header never appears in the body. The CRC is CRC-16 with polynomial ``0x8005`` (no reflection,
initial value 0) over everything from the first header byte to the last stuffed parameter byte.

The status error byte: bit 7 is the *alert* bit (the device has a hardware error; its Hardware
Error Status register says which), bits 0 to 6 are the error number of this instruction
(:class:`ErrorNumber`).

Everything here is a function of bytes to values and back, tested against the ROBOTIS e-Manual
examples; the simulator and the tests use it, the driver leaves the wire to dynamixel-sdk (it
only parses here what follows a reply to PING, to find two servos on one id).
"""

from __future__ import annotations

import enum
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from typing import Final

__all__ = [
    "ALERT_BIT",
    "BROADCAST_ID",
    "HEADER",
    "MAX_ID",
    "ErrorNumber",
    "HardwareError",
    "Instruction",
    "Packet",
    "PacketError",
    "PacketReader",
    "build_packet",
    "crc16",
    "decode_hardware_error",
    "from_le",
    "parse_packet",
    "ping_packet",
    "read_packet",
    "reboot_packet",
    "status_packet",
    "stuff",
    "sync_read_packet",
    "sync_write_packet",
    "to_le",
    "unstuff",
    "write_packet",
]

HEADER: Final = b"\xff\xff\xfd\x00"
BROADCAST_ID: Final = 0xFE
MAX_ID: Final = 0xFC  # the largest id a device may have
ALERT_BIT: Final = 0x80
_MIN_PACKET: Final = 10  # header(4) + id + len(2) + inst + crc(2)
_MAX_LENGTH: Final = 1024  # largest LEN accepted (dynamixel-sdk's buffer size)


class Instruction(enum.IntEnum):
    """Instruction codes of Protocol 2.0."""

    PING = 0x01
    READ = 0x02
    WRITE = 0x03
    REG_WRITE = 0x04
    ACTION = 0x05
    FACTORY_RESET = 0x06
    REBOOT = 0x08
    CLEAR = 0x10
    STATUS = 0x55
    SYNC_READ = 0x82
    SYNC_WRITE = 0x83
    FAST_SYNC_READ = 0x8A
    BULK_READ = 0x92
    BULK_WRITE = 0x93
    FAST_BULK_READ = 0x9A


class ErrorNumber(enum.IntEnum):
    """Bits 0 to 6 of a status packet's error byte: why an instruction failed."""

    NONE = 0
    RESULT_FAIL = 1  # failed to process the instruction
    INSTRUCTION = 2  # undefined instruction, or ACTION without REG_WRITE
    CRC = 3  # the instruction packet's CRC did not match
    DATA_RANGE = 4  # data out of range
    DATA_LENGTH = 5  # data shorter than needed
    DATA_LIMIT = 6  # data beyond a limit register
    ACCESS = 7  # write to read-only, read from write-only, EEPROM while torque on


class HardwareError(enum.IntFlag):
    """Bits of the X-series Hardware Error Status register (address 70)."""

    INPUT_VOLTAGE = 0x01
    OVERHEATING = 0x04
    MOTOR_ENCODER = 0x08
    ELECTRICAL_SHOCK = 0x10
    OVERLOAD = 0x20


_HARDWARE_ERROR_TEXT: Final[Mapping[int, str]] = {
    HardwareError.INPUT_VOLTAGE: "input voltage",
    HardwareError.OVERHEATING: "overheating",
    HardwareError.MOTOR_ENCODER: "motor encoder",
    HardwareError.ELECTRICAL_SHOCK: "electrical shock",
    HardwareError.OVERLOAD: "overload",
}


def decode_hardware_error(bits: int) -> tuple[str, ...]:
    """Name the bits of a Hardware Error Status value.

    Args:
        bits: The register's value (0 to 255).

    Returns:
        Names in bit order (``"overheating"``, ``"overload"``, ...); unknown bits as
        ``"bit N"``; empty for 0.
    """
    names: list[str] = []
    for bit in range(8):
        mask = 1 << bit
        if bits & mask:
            names.append(_HARDWARE_ERROR_TEXT.get(mask, f"bit {bit}"))
    return tuple(names)


class PacketError(ValueError):
    """Bytes that are not a valid packet (bad CRC, bad length, truncated)."""


# ---- CRC-16 (polynomial 0x8005, MSB first, initial value 0) ---------------------------------


def _crc_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x8005) if crc & 0x8000 else (crc << 1)
        table.append(crc & 0xFFFF)
    return tuple(table)


_CRC_TABLE: Final = _crc_table()


def crc16(data: bytes | bytearray | memoryview, crc: int = 0) -> int:
    """CRC-16 of Protocol 2.0.

    Args:
        data: The bytes (header to the last parameter, stuffed).
        crc: A running value to continue from.

    Returns:
        The CRC (0 to 0xFFFF); it goes on the wire low byte first.
    """
    table = _CRC_TABLE
    for byte in bytes(data):
        crc = ((crc << 8) ^ table[((crc >> 8) ^ byte) & 0xFF]) & 0xFFFF
    return crc


# ---- byte stuffing ----------------------------------------------------------------------------


def stuff(body: bytes) -> bytes:
    """Insert ``FD`` after every ``FF FF FD`` of a packet body (instruction and parameters).

    Args:
        body: The unstuffed body.

    Returns:
        The stuffed body.
    """
    if b"\xff\xff\xfd" not in body:
        return bytes(body)
    out = bytearray()
    for i, byte in enumerate(body):
        out.append(byte)
        if byte == 0xFD and i >= 2 and body[i - 1] == 0xFF and body[i - 2] == 0xFF:
            out.append(0xFD)
    return bytes(out)


def unstuff(body: bytes) -> bytes:
    """Remove the ``FD`` that :func:`stuff` inserted after every ``FF FF FD``.

    Args:
        body: The stuffed body.

    Returns:
        The original body.
    """
    if b"\xff\xff\xfd\xfd" not in body:
        return bytes(body)
    out = bytearray()
    i = 0
    while i < len(body):
        out.append(body[i])
        header = body[i] == 0xFD and len(out) >= 3 and out[-2] == 0xFF and out[-3] == 0xFF
        if header and i + 1 < len(body) and body[i + 1] == 0xFD:
            i += 1  # skip the stuffing byte
        i += 1
    return bytes(out)


# ---- packets ----------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Packet:
    """One decoded packet.

    Attributes:
        id: The device id (``BROADCAST_ID`` for everyone).
        instruction: The instruction code (``Instruction.STATUS`` for a reply).
        params: The parameters, unstuffed (for a status packet: after the error byte).
        error: A status packet's error byte (0 for an instruction packet).
    """

    id: int
    instruction: int
    params: bytes = b""
    error: int = 0

    @property
    def is_status(self) -> bool:
        """Whether this is a status packet (a device's reply)."""
        return self.instruction == Instruction.STATUS

    @property
    def alert(self) -> bool:
        """Whether a status packet carries the hardware alert bit."""
        return bool(self.error & ALERT_BIT)

    @property
    def error_number(self) -> ErrorNumber | int:
        """A status packet's error number (bits 0 to 6)."""
        number = self.error & 0x7F
        return ErrorNumber(number) if number <= ErrorNumber.ACCESS else number


def build_packet(dxl_id: int, instruction: int, params: bytes = b"") -> bytes:
    """Encode one packet: header, id, length, stuffed body, CRC.

    Args:
        dxl_id: 0 to 253, or ``BROADCAST_ID``.
        instruction: The instruction code (``0x55`` for a status packet, whose ``params`` then
            start with the error byte).
        params: The parameters, unstuffed.

    Returns:
        The bytes for the wire.

    Raises:
        ValueError: An id or instruction out of range, or a packet too long.
    """
    if not 0 <= dxl_id <= 0xFE or dxl_id == 0xFD:
        raise ValueError(f"id must be 0..252 or 254 (broadcast), got {dxl_id}")
    if not 0 <= instruction <= 0xFF:
        raise ValueError(f"instruction must be a byte, got {instruction}")
    body = stuff(bytes([instruction]) + bytes(params))
    length = len(body) + 2
    if length > _MAX_LENGTH:
        raise ValueError(f"packet too long ({length} > {_MAX_LENGTH})")
    head = HEADER + bytes([dxl_id, length & 0xFF, length >> 8]) + body
    crc = crc16(head)
    return head + bytes([crc & 0xFF, crc >> 8])


def parse_packet(data: bytes) -> Packet:
    """Decode exactly one packet.

    Args:
        data: The bytes of one packet, header to CRC.

    Returns:
        The packet.

    Raises:
        PacketError: Not a complete, valid packet (the message says why).
    """
    packet, used = _parse_at(bytes(data), 0)
    if packet is None:
        raise PacketError(f"truncated packet ({len(data)} bytes)")
    if used != len(data):
        raise PacketError(f"{len(data) - used} bytes after the packet")
    return packet


def _parse_at(data: bytes, start: int) -> tuple[Packet | None, int]:
    """Parse a packet whose header starts at ``start``; (None, start) if incomplete."""
    if len(data) - start < 7:
        return None, start
    if data[start : start + 4] != HEADER:
        raise PacketError("no header")
    length = data[start + 5] | (data[start + 6] << 8)
    if length < 3 or length > _MAX_LENGTH:
        raise PacketError(f"bad length {length}")
    end = start + 7 + length
    if len(data) < end:
        return None, start
    crc = data[end - 2] | (data[end - 1] << 8)
    if crc16(data[start : end - 2]) != crc:
        raise PacketError(f"CRC mismatch (got {crc:#06x})")
    body = unstuff(data[start + 7 : end - 2])
    dxl_id, instruction = data[start + 4], body[0]
    if instruction == Instruction.STATUS:
        if len(body) < 2:
            raise PacketError("status packet without an error byte")
        return Packet(dxl_id, instruction, body[2:], body[1]), end
    return Packet(dxl_id, instruction, body[1:]), end


class PacketReader:
    """Splits a byte stream into packets (stateful, but no I/O).

    Garbage before a header is skipped; a packet with a bad CRC or length is reported as a
    :class:`PacketError` in the output and skipped.
    """

    def __init__(self) -> None:
        self._buf = bytearray()

    def feed(self, data: bytes) -> Iterator[Packet | PacketError]:
        """Add received bytes and yield every packet (or error) now complete.

        Args:
            data: The bytes.

        Yields:
            Packets, and PacketErrors for corrupt ones.
        """
        self._buf += data
        while True:
            at = self._buf.find(HEADER[:3])
            if at < 0:
                del self._buf[: max(0, len(self._buf) - 2)]  # keep a possible header start
                return
            del self._buf[:at]
            if len(self._buf) >= 4 and self._buf[3] != 0x00:
                del self._buf[:1]  # "FF FF FD FD" is stuffing, not a header
                continue
            try:
                packet, used = _parse_at(bytes(self._buf), 0)
            except PacketError as err:
                length = self._buf[5] | (self._buf[6] << 8)
                skip = 7 + length if 3 <= length <= _MAX_LENGTH else 1
                del self._buf[: min(skip, len(self._buf))]
                yield err
                continue
            if packet is None:
                return
            del self._buf[:used]
            yield packet

    def pending(self) -> int:
        """How many bytes wait for the rest of a packet."""
        return len(self._buf)


# ---- little-endian values ---------------------------------------------------------------------


def to_le(value: int, size: int) -> bytes:
    """A register value as ``size`` little-endian bytes (negative values in two's complement).

    Args:
        value: The value.
        size: 1, 2 or 4.

    Returns:
        The bytes.

    Raises:
        ValueError: The value does not fit.
    """
    if not -(1 << (8 * size - 1)) <= value < (1 << (8 * size)):
        raise ValueError(f"{value} does not fit in {size} byte(s)")
    return (value & ((1 << (8 * size)) - 1)).to_bytes(size, "little")


def from_le(data: bytes, signed: bool = False) -> int:
    """A little-endian register value.

    Args:
        data: 1, 2 or 4 bytes.
        signed: Two's complement.

    Returns:
        The value.
    """
    return int.from_bytes(data, "little", signed=signed)


# ---- instruction builders ---------------------------------------------------------------------


def ping_packet(dxl_id: int) -> bytes:
    """PING one device (or all, with ``BROADCAST_ID``)."""
    return build_packet(dxl_id, Instruction.PING)


def read_packet(dxl_id: int, address: int, length: int) -> bytes:
    """READ ``length`` bytes from ``address``."""
    return build_packet(dxl_id, Instruction.READ, to_le(address, 2) + to_le(length, 2))


def write_packet(dxl_id: int, address: int, data: bytes) -> bytes:
    """WRITE ``data`` at ``address``."""
    return build_packet(dxl_id, Instruction.WRITE, to_le(address, 2) + bytes(data))


def reboot_packet(dxl_id: int) -> bytes:
    """REBOOT one device."""
    return build_packet(dxl_id, Instruction.REBOOT)


def sync_read_packet(address: int, length: int, ids: Iterable[int]) -> bytes:
    """SYNC_READ the same registers of several devices (they answer in the order given)."""
    return build_packet(
        BROADCAST_ID, Instruction.SYNC_READ, to_le(address, 2) + to_le(length, 2) + bytes(ids)
    )


def sync_write_packet(address: int, length: int, data: Mapping[int, bytes]) -> bytes:
    """SYNC_WRITE the same registers of several devices (no replies).

    Raises:
        ValueError: A device's data is not ``length`` bytes.
    """
    params = bytearray(to_le(address, 2) + to_le(length, 2))
    for dxl_id, value in data.items():
        if len(value) != length:
            raise ValueError(f"id {dxl_id}: {len(value)} bytes of data, expected {length}")
        params.append(dxl_id)
        params += value
    return build_packet(BROADCAST_ID, Instruction.SYNC_WRITE, bytes(params))


def status_packet(dxl_id: int, error: int = 0, params: bytes = b"") -> bytes:
    """A device's reply: error byte and parameters."""
    return build_packet(dxl_id, Instruction.STATUS, bytes([error]) + bytes(params))
