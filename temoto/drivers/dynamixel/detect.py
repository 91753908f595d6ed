"""Finding DYNAMIXEL chains without a profile (``temoto drivers detect``).

:func:`detect` sends one broadcast PING (which no servo acts on) on each serial port, at each
likely baud rate until servos answer, and lists the servos that answered as a profile entry
that :meth:`~temoto.drivers.dynamixel.driver.DynamixelDriver.from_profile` accepts as it is.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from typing import Any, Final

from temoto.drivers.base import detect_links
from temoto.drivers.dynamixel import _sdk
from temoto.drivers.dynamixel import control_table as ct
from temoto.drivers.dynamixel import protocol as p
from temoto.drivers.dynamixel.settings import read_link
from temoto.drivers.profile import ProfileReader
from temoto.errors import ProfileError

__all__ = ["DETECT_BAUD_RATES", "detect"]

logger = logging.getLogger(__name__)

#: The baud rates :func:`detect` tries on a link without ``?baud=``, most common first: the
#: X series' factory setting, then the usual setting of an arm.
DETECT_BAUD_RATES: Final = (57600, 1_000_000, 115200, 2_000_000, 3_000_000, 4_000_000, 9600)
#: The joint limits (rad) in detect's entries: the single turn of position mode (ticks 0 to
#: 4095, about ±π), rounded inward; ±π itself ends one tick beyond it.
_DETECT_LIMIT: Final = 3.14


def detect(links: Sequence[Any] | None, timeout: float) -> list[dict[str, Any]]:
    """The chains of servos that answer a broadcast PING, as profile device entries.

    See :meth:`~temoto.drivers.dynamixel.driver.DynamixelDriver.detect`, which calls this.

    Args:
        links: Link URLs as in a profile's ``link``; a single string is one link. None: every
            serial port pyserial lists.
        timeout: Real seconds to wait for status packets on each link at each baud rate.

    Returns:
        One entry per link where known servos answered, in the order given.

    Raises:
        ValueError: ``timeout`` is not a positive finite number of seconds, or a link is not
            a serial link (raised before any port is opened; the message names the link).
    """
    urls = detect_links(links, timeout, _serial_links)
    plans = [_detect_plan(url) for url in urls]  # every link checked before any is opened
    entries: list[dict[str, Any]] = []
    for path, bauds in plans:
        entry = _detect_chain(path, bauds, timeout)
        if entry is not None:
            entries.append(entry)
    return entries


def _detect_plan(link: Any) -> tuple[str, tuple[int, ...]]:
    """The serial device of a link to look at, and the baud rates to try there.

    Raises:
        ValueError: Not a serial link (the message names it).
    """
    try:
        path, baud = read_link(ProfileReader(f"link {link!r}"), link, "")
    except ProfileError as err:
        raise ValueError(str(err)) from None
    return path, DETECT_BAUD_RATES if baud is None else (baud,)


def _detect_chain(path: str, bauds: Sequence[int], timeout: float) -> dict[str, Any] | None:
    """Broadcast-PING ``path`` at each baud rate until servos answer; their entry, or None."""
    for baud in bauds:
        port = _sdk.SdkPort(path, baud)
        try:
            port.open()
        except OSError as err:
            logger.warning("dynamixel detect: skipping %s: cannot open it: %s", path, err)
            return None  # at another baud rate neither
        except ValueError as err:
            logger.warning("dynamixel detect: %s: %s", path, err)
            continue
        try:
            found, result = port.broadcast_ping(timeout)
        finally:
            port.close()
        if found:
            return _detected(path, baud, found)
        logger.debug(
            "dynamixel detect: %s at %d baud: no servo answered: %s",
            path,
            baud,
            port.result_text(result),
        )
    return None


def _detected(path: str, baud: int, found: Mapping[int, tuple[int, int]]) -> dict[str, Any] | None:
    """The profile entry of the servos that answered (None if none is a known model)."""
    servos: list[dict[str, Any]] = []
    for dxl_id, (number, firmware) in sorted(found.items()):
        if not 0 <= dxl_id <= p.MAX_ID:
            logger.warning(
                "dynamixel detect: %s: a status packet from id %d: left out", path, dxl_id
            )
            continue
        model = ct.MODELS_BY_NUMBER.get(number)
        if model is None:
            logger.warning(
                "dynamixel detect: %s at %d baud: servo %d has model number %d, which the"
                " driver does not know (known: %s): left out",
                path,
                baud,
                dxl_id,
                number,
                ", ".join(f"{m.name} = {m.number}" for m in ct.MODELS.values()),
            )
            continue
        logger.info(
            "dynamixel detect: %s at %d baud: servo %d is %s (firmware %d)",
            path,
            baud,
            dxl_id,
            model.name,
            firmware,
        )
        servos.append(
            {
                "id": dxl_id,
                "joint": f"joint_{dxl_id}",
                "model": model.name,
                "mode": "position",
                "min_position": -_DETECT_LIMIT,
                "max_position": _DETECT_LIMIT,
            }
        )
    if not servos:
        return None
    return {"driver": "dynamixel", "link": f"serial:{path}?baud={baud}", "servos": servos}


def _serial_links() -> list[Any]:
    """``serial:`` links of every serial port pyserial lists."""
    return [f"serial:{path}" for path in _sdk.serial_ports()]
