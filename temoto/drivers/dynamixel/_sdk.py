"""The one place that touches dynamixel-sdk (untyped): narrow, typed wrappers around it.

dynamixel-sdk's ``PortHandler`` opens the serial port (pyserial) and times replies out in
*real* milliseconds (twice its 16 ms latency timer plus 2 ms plus the bytes' transfer time);
its ``PacketHandler`` (Protocol 2.0) builds, sends and parses packets; ``GroupSyncRead`` and
``GroupSyncWrite`` pack one instruction for a whole chain. The SDK reports failures as result
codes; pyserial raises ``SerialException`` (an ``OSError``) when the port breaks. Both come out
of this module as a result code, so the driver has one place to turn them into typed errors.

The SDK measures its timeouts with ``time.time``; here each port reads ``time.monotonic``
instead, so a wall-clock step cannot cut a wait short or stretch it. pyserial's port list (for
discovery) is read here too.

While it waits for a status packet the SDK reads the port without blocking (pyserial's
timeout 0) in a loop: a servo that does not answer keeps a core busy for the whole reply
timeout, every poll. On a loaded onboard computer that spin takes CPU from everything else --
and from a simulator in the same process, whose reply then comes late. Here a read that finds
no bytes waits for some (``select``) until the transaction's timeout instead.

A status packet that comes after its timeout (a USB adapter's latency timer, a busy USB host,
the simulator's ``harsh`` realism) reaches the host during the next transaction. The SDK takes
the first status packet of the right id for the answer, whatever its length, and slices the
bytes it wants out of it: a late answer to another read would give wrong register values, and
one shorter than asked an ``IndexError`` inside the SDK. Here each transaction knows how many
parameter bytes its status packet has (READ: the bytes read; WRITE and REBOOT: none; PING:
three; SYNC_READ: the bytes read of each servo; any of them refused: none) and a packet of
another length is dropped as a late one (counted in :attr:`SdkPort.stray_packets`) while the
SDK reads on until its timeout. A late answer to the same read is indistinguishable from the
new one (Protocol 2.0 has no sequence numbers): it is taken, data one transaction old, as on a
real line.
"""

from __future__ import annotations

import contextlib
import logging
import select
import time
from collections.abc import Iterator, Mapping
from typing import Any, Final, cast

import dynamixel_sdk as _dxl  # type: ignore[import-untyped]  # no type hints: wrapped here
from serial.tools import list_ports as _list_ports  # type: ignore[import-untyped]  # pyserial

logger = logging.getLogger(__name__)

__all__ = [
    "COMM_RX_CORRUPT",
    "COMM_RX_TIMEOUT",
    "COMM_SUCCESS",
    "COMM_TX_FAIL",
    "RESULT_WORDS",
    "SdkPort",
    "SyncReader",
    "SyncWriter",
    "serial_ports",
]

COMM_SUCCESS: Final[int] = cast("int", _dxl.COMM_SUCCESS)
COMM_TX_FAIL: Final[int] = cast("int", _dxl.COMM_TX_FAIL)
COMM_RX_TIMEOUT: Final[int] = cast("int", _dxl.COMM_RX_TIMEOUT)
COMM_RX_CORRUPT: Final[int] = cast("int", _dxl.COMM_RX_CORRUPT)

#: Our words for dynamixel-sdk's result codes (its own read "[TxRxResult] There is no status
#: packet!"); messages put the servo and the register around them.
RESULT_WORDS: Final[Mapping[int, str]] = {
    COMM_SUCCESS: "success",
    cast("int", _dxl.COMM_PORT_BUSY): "the port is busy (another transaction)",
    COMM_TX_FAIL: "could not send the instruction packet",
    cast("int", _dxl.COMM_RX_FAIL): "could not receive the status packet",
    cast("int", _dxl.COMM_TX_ERROR): "bad instruction packet",
    cast("int", _dxl.COMM_RX_WAITING): "status packet incomplete",
    COMM_RX_TIMEOUT: "no status packet",
    COMM_RX_CORRUPT: "corrupt status packet",
    cast("int", _dxl.COMM_NOT_AVAILABLE): "not available",
}


class SdkPort:
    """A serial port and a Protocol 2.0 packet handler (not thread-safe: callers lock).

    Args:
        path: The serial device (``/dev/ttyUSB0``, or a simulator's ``/dev/pts/N``).
        baud: Bits per second.
        reply_timeout: Real seconds a status packet may take beyond its transfer time
            (dynamixel-sdk's own value is 0.034: twice a USB adapter's 16 ms latency timer
            plus 2 ms).
    """

    def __init__(self, path: str, baud: int, reply_timeout: float = 0.034) -> None:
        self.path = path
        self.baud = baud
        self.reply_timeout = reply_timeout
        self._port: Any = _dxl.PortHandler(path)
        self._port.setPacketTimeout = self._set_packet_timeout  # the SDK's, with our margin
        self._port.getCurrentTime = _monotonic_ms  # the SDK's clock, never stepped
        self._port.readPort = self._read_port  # the SDK's, waiting for bytes instead of spinning
        self._ph: Any = _dxl.PacketHandler(2.0)
        #: Status packets dropped because their length fits no transaction at hand (late
        #: answers to an earlier one; see the module docstring).
        self.stray_packets = 0
        self._expect: int | None = None  # parameter bytes of the status packet awaited
        self._sdk_rx = self._ph.rxPacket
        self._ph.rxPacket = self._rx_packet  # the SDK's, dropping late answers

    def _rx_packet(self, port: Any, fast_option: bool) -> tuple[list[int], int]:
        """The SDK's ``rxPacket``, reading on past status packets of the wrong length."""
        while True:
            rxpacket, result = self._sdk_rx(port, fast_option)
            expect = self._expect
            if result != COMM_SUCCESS or fast_option or expect is None:
                return rxpacket, result
            params = len(rxpacket) - _STATUS_OVERHEAD
            if params == expect or (params == 0 and rxpacket[_PKT_ERROR] & 0x7F):
                return rxpacket, result  # an instruction refused answers without data
            self.stray_packets += 1
            logger.debug(
                "%s: a late status packet from id %d (%d parameter bytes, %d awaited): dropped",
                self.path,
                rxpacket[_PKT_ID],
                params,
                expect,
            )

    def _read_port(self, length: int) -> bytes:
        """The SDK's ``readPort``; with nothing to read, it waits for the line, not the CPU.

        dynamixel-sdk opens the port non-blocking and calls ``readPort`` in a loop until its
        packet timeout: a busy loop that holds a core (and, in Python, the interpreter lock)
        for every reply it waits for, e.g. the servos' Return Delay Times of each poll. Here
        an empty read waits (``select``) until bytes arrive or the packet's timeout is due, so
        a reply is taken as soon as it comes and the wait costs no CPU; on a busy onboard
        computer (and for a simulator in this process) that CPU is the other threads'.

        A wait that ends more than :data:`_STALL_MS` after it was due (the thread was not
        scheduled: a loaded machine) moves the packet's timeout on by that much: the timeout
        counts the time this host watched the line. A real line's bytes wait in the kernel's
        buffer meanwhile and are read at once; a simulator in this process stalled with it and
        gets its time to answer.
        """
        port = self._port
        data = cast("bytes", port.ser.read(length))
        if data or length <= 0:
            return data
        now = port.getCurrentTime()
        left = port.packet_timeout - (now - port.packet_start_time)
        if left > 0:
            wait = min(left, _IDLE_WAIT_MS)
            with contextlib.suppress(OSError, ValueError):  # closed meanwhile: the SDK says so
                _wait_readable(port.ser.fileno(), wait / 1000.0)
            overslept = port.getCurrentTime() - now - wait
            if overslept > _STALL_MS:  # this thread did not run: that time is not the reply's
                port.packet_start_time += overslept
            data = cast("bytes", port.ser.read(length))
        return data

    @contextlib.contextmanager
    def _expecting(self, params: int) -> Iterator[None]:
        """Within the block, a status packet must carry ``params`` parameter bytes."""
        self._expect = params
        try:
            yield
        finally:
            self._expect = None

    def _set_packet_timeout(self, packet_length: int) -> None:
        port = self._port
        port.packet_start_time = port.getCurrentTime()
        port.packet_timeout = port.tx_time_per_byte * packet_length + self.reply_timeout * 1000.0

    @property
    def is_open(self) -> bool:
        """Whether the port is open."""
        return bool(self._port.is_open)

    def open(self) -> None:
        """Open the port at the baud rate.

        Raises:
            OSError: The port cannot be opened (pyserial's SerialException).
            ValueError: The SDK refused the baud rate.
        """
        if not self._port.openPort():
            raise OSError(f"cannot open {self.path}")
        if not self._port.setBaudRate(self.baud):
            self._port.closePort()
            raise ValueError(f"baud rate {self.baud} refused")

    def close(self) -> None:
        """Close the port (idempotent)."""
        if self._port.ser is not None and self._port.is_open:
            self._port.closePort()

    def result_text(self, result: int) -> str:
        """Words for a result code (:data:`RESULT_WORDS`; not the SDK's ``[TxRxResult]`` text)."""
        return RESULT_WORDS.get(result, f"dynamixel-sdk result {result}")

    def leftover(self, settle: float) -> bytes:
        """The bytes that arrive within ``settle`` real seconds after a transaction.

        dynamixel-sdk reads exactly one status packet per unicast instruction and flushes the
        input before the next one, so a second status packet for the same id -- two servos
        answering one id -- is never seen by it. This reads what follows the first one.

        Args:
            settle: Real seconds to listen after the last byte received.

        Returns:
            The bytes (empty when nothing followed).
        """
        port = self._port
        got = bytearray()
        quiet_until = time.monotonic() + settle
        while time.monotonic() < quiet_until:
            try:
                chunk = bytes(port.readPort(4096))
            except OSError:
                break
            if chunk:
                got += chunk
                quiet_until = time.monotonic() + settle
            else:
                time.sleep(0.001)
        return bytes(got)

    def _guard(self, call: Any, *args: Any) -> Any:
        try:
            return call(*args)
        except OSError:
            self._port.is_using = False  # the SDK leaves its busy flag set on an exception
            return None

    def ping(self, dxl_id: int) -> tuple[int, int, int]:
        """PING: (model number, result, error byte)."""
        with self._expecting(3):  # model number (2), firmware version
            out = self._guard(self._ph.ping, self._port, dxl_id)
        if out is None:
            return 0, COMM_TX_FAIL, 0
        return int(out[0]), int(out[1]), int(out[2])

    def broadcast_ping(self, wait: float) -> tuple[dict[int, tuple[int, int]], int]:
        """PING to the broadcast id: every servo on the bus answers, in ascending id order.

        The SDK collects status packets until its packet timeout, which it sets to the time
        all 252 ids would take (0.8 s at 1 Mbaud, 4.4 s at 9600 baud); here it listens for
        ``wait`` real seconds instead.

        Args:
            wait: Real seconds to collect status packets after the instruction went out.

        Returns:
            ({id: (model number, firmware version)} of every valid status packet, result):
            COMM_RX_TIMEOUT when nothing answered, COMM_RX_CORRUPT when some bytes were not
            a valid status packet (the valid ones are still there).
        """
        port = self._port

        def listen(_msec: float) -> None:
            port.packet_start_time = port.getCurrentTime()
            port.packet_timeout = wait * 1000.0

        port.setPacketTimeoutMillis = listen  # the only timeout broadcastPing sets
        try:
            out = self._guard(self._ph.broadcastPing, port)
        finally:
            del port.setPacketTimeoutMillis  # the SDK's own again
        if out is None:
            return {}, COMM_TX_FAIL
        found: dict[int, tuple[int, int]] = {
            int(dxl_id): (int(info[0]), int(info[1])) for dxl_id, info in out[0].items()
        }
        return found, int(out[1])

    def read(self, dxl_id: int, address: int, size: int) -> tuple[int, int, int]:
        """READ one register of 1, 2 or 4 bytes: (unsigned value, result, error byte)."""
        call = {
            1: self._ph.read1ByteTxRx,
            2: self._ph.read2ByteTxRx,
            4: self._ph.read4ByteTxRx,
        }[size]
        with self._expecting(size):
            out = self._guard(call, self._port, dxl_id, address)
        if out is None:
            return 0, COMM_TX_FAIL, 0
        return int(out[0]), int(out[1]), int(out[2])

    def write(self, dxl_id: int, address: int, size: int, value: int) -> tuple[int, int]:
        """WRITE one register (``value`` unsigned, two's complement): (result, error byte)."""
        call = {
            1: self._ph.write1ByteTxRx,
            2: self._ph.write2ByteTxRx,
            4: self._ph.write4ByteTxRx,
        }[size]
        with self._expecting(0):
            out = self._guard(call, self._port, dxl_id, address, value & ((1 << (8 * size)) - 1))
        if out is None:
            return COMM_TX_FAIL, 0
        return int(out[0]), int(out[1])

    def reboot(self, dxl_id: int) -> tuple[int, int]:
        """REBOOT: (result, error byte)."""
        with self._expecting(0):
            out = self._guard(self._ph.reboot, self._port, dxl_id)
        if out is None:
            return COMM_TX_FAIL, 0
        return int(out[0]), int(out[1])

    def sync_reader(self, address: int, length: int, ids: list[int]) -> SyncReader:
        """A GroupSyncRead of ``length`` bytes at ``address`` from ``ids``."""
        return SyncReader(self, address, length, ids)

    def sync_writer(self, address: int, length: int) -> SyncWriter:
        """A GroupSyncWrite of ``length`` bytes at ``address``."""
        return SyncWriter(self, address, length)


def serial_ports() -> list[str]:
    """The serial devices pyserial lists (``/dev/ttyUSB0`` ...), sorted.

    Returns:
        Their paths.
    """
    return sorted(str(port.device) for port in _list_ports.comports())


#: Bytes of a status packet besides its parameters: header (3), reserved, id, length (2),
#: instruction, error, CRC (2) -- the e-Manual's Protocol 2.0 status packet.
_STATUS_OVERHEAD: Final = 11
_PKT_ID: Final = 4  # the id's index in a packet
_PKT_ERROR: Final = 8  # the error byte's index in a status packet


#: The longest one wait of :meth:`SdkPort._read_port` for bytes (ms; the timeout is checked
#: after each).
_IDLE_WAIT_MS: Final = 50.0


#: How late (ms) a wait of :meth:`SdkPort._read_port` may end before the time is taken for a
#: stall of this thread, not counted towards the packet's timeout.
_STALL_MS: Final = 20.0


def _wait_readable(fd: int, seconds: float) -> None:
    """Wait until ``fd`` has bytes to read, at most ``seconds``."""
    select.select([fd], [], [], seconds)


def _monotonic_ms() -> float:
    """``time.monotonic`` in milliseconds (the unit of the SDK's ``getCurrentTime``)."""
    return time.monotonic() * 1000.0


class SyncReader:
    """A ``GroupSyncRead`` that also keeps each status packet's error byte (the alert bit).

    The SDK's ``GroupSyncRead.rxPacket`` drops the error bytes, so the replies are read with
    the packet handler's ``readRx`` (what ``rxPacket`` does inside) after the group sends.
    """

    def __init__(self, port: SdkPort, address: int, length: int, ids: list[int]) -> None:
        self._port = port
        self.length = length
        self.ids = list(ids)
        self.address = address
        #: After :meth:`read`: the result code of each servo whose reply failed.
        self.failed: dict[int, int] = {}
        #: After :meth:`read`: how many of its replies were corrupt.
        self.bad_packets = 0
        self._group: Any = _dxl.GroupSyncRead(port._port, port._ph, address, length)
        for dxl_id in self.ids:
            self._group.addParam(dxl_id)

    def read(self) -> tuple[int, dict[int, bytes], dict[int, int]]:
        """Send the SYNC_READ and collect every reply.

        A servo whose reply is missing or corrupt does not stop the others' being read: after
        the call :attr:`failed` holds each failing servo's result code, and :attr:`bad_packets`
        how many replies were corrupt (each one counts, not the read).

        Returns:
            (result, data by id, status error byte by id); the first failing reply's result.
        """
        self.failed = {}
        self.bad_packets = 0
        result = self._port._guard(self._group.txPacket)
        if result is None:
            return COMM_TX_FAIL, {}, {}
        if result != COMM_SUCCESS:
            return int(result), {}, {}
        data: dict[int, bytes] = {}
        errors: dict[int, int] = {}
        first = COMM_SUCCESS
        ph, raw = self._port._ph, self._port._port
        for dxl_id in self.ids:
            with self._port._expecting(self.length):
                out = self._port._guard(ph.readRx, raw, dxl_id, self.length)
            code = COMM_TX_FAIL if out is None else int(out[1])
            if code != COMM_SUCCESS:
                self.failed[dxl_id] = code
                self.bad_packets += code == COMM_RX_CORRUPT
                if first == COMM_SUCCESS:
                    first = code
                if code == COMM_TX_FAIL:  # the port broke: nothing more will come
                    break
                continue
            assert out is not None
            data[dxl_id] = bytes(out[0])
            errors[dxl_id] = int(out[2])
        return first, data, errors


class SyncWriter:
    """A ``GroupSyncWrite``: one packet sets the same register of several servos."""

    def __init__(self, port: SdkPort, address: int, length: int) -> None:
        self._port = port
        self._group: Any = _dxl.GroupSyncWrite(port._port, port._ph, address, length)

    def write(self, data: dict[int, bytes]) -> int:
        """Send one SYNC_WRITE (no replies).

        Args:
            data: The bytes for each servo id.

        Returns:
            The SDK's result code.
        """
        self._group.clearParam()
        for dxl_id, value in data.items():
            self._group.addParam(dxl_id, list(value))
        result = self._port._guard(self._group.txPacket)
        return COMM_TX_FAIL if result is None else int(result)
