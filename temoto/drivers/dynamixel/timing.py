"""Timing of a DYNAMIXEL chain: poll cycles on the wire, watchdog and delay registers.

The wire time of a poll cycle, the Bus Watchdog and Return Delay Time registers, and the USB
serial adapter's latency timer: the numbers behind the driver's checks of a profile
(a ``poll_rate`` the wire cannot carry, a ``bus_watchdog`` shorter than two polls) and its
warning at ``configure`` (an adapter whose latency timer delays every reply);
``docs/driver-dynamixel.md`` says how to set them.
"""

from __future__ import annotations

import math
import os
from typing import Final

from temoto.drivers.dynamixel import control_table as ct

__all__ = [
    "DEFAULT_BUS_WATCHDOG",
    "FACTORY_RETURN_DELAY",
    "USB_SERIAL_SYSFS",
    "latency_timer",
    "poll_cycle_time",
    "return_delay_units",
    "watchdog_units",
]

#: The Bus Watchdog time (s) when the profile sets none: this, or three poll periods rounded up
#: to the watchdog's 20 ms unit when that is longer (off when that exceeds its 2.54 s).
DEFAULT_BUS_WATCHDOG: Final = 0.5
#: The Return Delay Time (s) of a servo as it leaves the factory (register 9 = 250 x 2 µs): what
#: the poll-rate estimate assumes when the profile sets no ``return_delay_time``.
FACTORY_RETURN_DELAY: Final = 250 * ct.RETURN_DELAY_UNIT
#: Where Linux lists USB serial adapters; each has a ``latency_timer`` file (ms).
USB_SERIAL_SYSFS: Final = "/sys/bus/usb-serial/devices"
_BITS_PER_BYTE: Final = 10  # start bit, 8 data bits, stop bit
_INSTRUCTION_BYTES: Final = 10  # header 4, id, length 2, instruction, CRC 2
_STATUS_BYTES: Final = 11  # header 4, id, length 2, instruction 0x55, error, CRC 2


def poll_cycle_time(
    servos: int,
    baud: int,
    return_delay: float = FACTORY_RETURN_DELAY,
    status_every: int = 10,
    bus_watchdog: bool = True,
) -> float:
    """Seconds one poll cycle of the driver takes on the wire (an estimate, a lower bound).

    Each byte is 10 bits (start, 8 data, stop); an instruction packet is 10 bytes plus its
    parameters, a status packet 11 plus its data (byte stuffing ignored). Per cycle the driver
    sends one SYNC_READ of 10 bytes (``14 + n`` bytes out, ``n`` replies of 21 bytes, each after
    the servo's Return Delay Time) and one SYNC_WRITE of the goals (``14 + 5 n`` bytes; 4-byte
    goals), and every ``status_every`` cycles SYNC_READs of 3 bytes (voltage, temperature),
    1 byte (hardware error) and, with the Bus Watchdog on, 1 byte (its register)::

        bytes  = (14 + n + 21 n) + (14 + 5 n)
                 + [(14 + n + 14 n) + (14 + n + 12 n) (+ (14 + n + 12 n))] / status_every
        reads  = n + [2 n (+ n)] / status_every
        time   = 10 * bytes / baud + reads * return_delay

    A USB adapter adds its latency (the FTDI latency timer: 16 ms by default, 1 ms when set;
    see ``docs/driver-dynamixel.md``) to every read, which this leaves out.

    Args:
        servos: Servos on the chain.
        baud: Bits per second.
        return_delay: The servos' Return Delay Time (s).
        status_every: Polls per status read.
        bus_watchdog: Whether the status read includes the Bus Watchdog register.

    Returns:
        Seconds.
    """
    n = servos
    fast = (_INSTRUCTION_BYTES + 4 + n) + n * (_STATUS_BYTES + 10)
    goals = _INSTRUCTION_BYTES + 4 + 5 * n
    status_reads = [3, 1, 1] if bus_watchdog else [3, 1]
    status = sum((_INSTRUCTION_BYTES + 4 + n) + n * (_STATUS_BYTES + size) for size in status_reads)
    wire = fast + goals + status / status_every
    replies = n + len(status_reads) * n / status_every
    return _BITS_PER_BYTE * wire / baud + replies * return_delay


def latency_timer(port: str) -> int | None:
    """The USB serial adapter's latency timer (ms) of a serial device, where Linux lists it.

    Args:
        port: The serial device (``/dev/ttyUSB0``; a symlink such as ``/dev/serial/by-id/...``
            is followed).

    Returns:
        The value of ``/sys/bus/usb-serial/devices/<tty>/latency_timer``, or None when there is
        no such file (not Linux, not a USB serial adapter, a pseudo-terminal) or it is unreadable.
    """
    tty = os.path.basename(os.path.realpath(port))
    try:
        with open(os.path.join(USB_SERIAL_SYSFS, tty, "latency_timer"), encoding="ascii") as f:
            return int(f.read().strip())
    except (OSError, ValueError):
        return None


def watchdog_units(seconds: float | None, period: float) -> int:
    """Bus Watchdog register units (20 ms) for a time in seconds (None: the default).

    Args:
        seconds: The Bus Watchdog time, 0 for off, or None for :data:`DEFAULT_BUS_WATCHDOG`
            (or three poll periods when that is longer).
        period: The poll period (s).

    Returns:
        The register value (0: off).

    Raises:
        ValueError: Not 0 and not within 0.02..2.54 s, or shorter than two poll periods.
    """
    unit = ct.BUS_WATCHDOG_UNIT
    if seconds is None:
        units = math.ceil(max(DEFAULT_BUS_WATCHDOG, 3 * period) / unit - 1e-9)
        return units if units <= ct.BUS_WATCHDOG_MAX else 0
    if not math.isfinite(seconds) or seconds < 0:
        raise ValueError(f"bus_watchdog must be 0 (off) or 0.02..2.54 s, got {seconds}")
    if seconds == 0:
        return 0
    units = math.ceil(seconds / unit - 1e-9)
    if not 1 <= units <= ct.BUS_WATCHDOG_MAX:
        raise ValueError(f"bus_watchdog must be 0 (off) or 0.02..2.54 s, got {seconds}")
    if units * unit < 2 * period:
        raise ValueError(
            f"bus_watchdog {units * unit:g} s is shorter than two poll periods"
            f" ({2 * period:g} s): the servos would stop between two polls"
        )
    return units


def return_delay_units(seconds: float | None) -> int | None:
    """Return Delay Time register units (2 µs) for a time in seconds (None: not written).

    Args:
        seconds: The Return Delay Time, or None.

    Returns:
        The register value, or None.

    Raises:
        ValueError: Not within 0..508 µs.
    """
    if seconds is None:
        return None
    units = round(seconds / ct.RETURN_DELAY_UNIT) if math.isfinite(seconds) else -1
    if not 0 <= units <= ct.RETURN_DELAY_MAX or seconds < 0:
        raise ValueError(f"return_delay_time must be 0 to 0.000508 s, got {seconds}")
    return units
