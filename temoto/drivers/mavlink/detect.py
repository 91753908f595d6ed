"""Finding MAVLink vehicles without a profile (``temoto drivers detect``), by listening only.

:func:`detect` opens each link with :mod:`~temoto.drivers.mavlink.link`, parses its bytes with
:class:`~temoto.drivers.mavlink.protocol.Codec` and lists the vehicles whose HEARTBEATs it
hears as profile entries. Nothing is sent.
"""

from __future__ import annotations

import importlib
import logging
import time
from collections.abc import Sequence
from typing import Any, Final
from urllib.parse import parse_qs

from temoto.drivers.base import detect_links
from temoto.drivers.mavlink import protocol as p
from temoto.drivers.mavlink.link import LinkSpec, open_link, parse_link
from temoto.drivers.mavlink.protocol import Codec

__all__ = ["detect"]

logger = logging.getLogger(__name__)

#: Baud rates :func:`detect` tries on a serial link without ``?baud=``, in order.
_DETECT_BAUDS: Final = (57600, 115200, 921600)
#: Where a ground station listens (autopilots and telemetry radios send there): detect's UDP
#: candidate when no links are given.
_DETECT_UDP: Final = "udpin:0.0.0.0:14550"
_AUTOPILOT_COMPONENT: Final = 1  # MAV_COMP_ID_AUTOPILOT1, the driver's default component_id

#: (system id, component id) → (MAV_TYPE, MAV_AUTOPILOT) of each vehicle heard, first first.
_Heard = dict[tuple[int, int], tuple[int, int]]


def detect(kind: str, links: Sequence[Any] | None, timeout: float) -> list[dict[str, Any]]:
    """The vehicles heard on MAVLink links, as profile device entries (listening only).

    See :meth:`~temoto.drivers.mavlink.driver.MavlinkDriver.detect`, which calls this.

    Args:
        kind: The driver's name (each entry's ``driver``).
        links: Link URLs as in a profile's ``link``; None: every serial port, then
            ``udpin:0.0.0.0:14550``.
        timeout: Real seconds to listen on each link (and on each baud rate tried).

    Returns:
        One entry per vehicle heard, link by link.

    Raises:
        ValueError: A bad timeout, or a link that is not a URL the link module knows.
        DriverUnavailableError: A serial link, but pyserial is not installed.
    """
    urls = detect_links(links, timeout, lambda: [*_serial_candidates(), _DETECT_UDP])
    plans = [_detect_plan(url) for url in urls]  # every link checked before any is opened
    entries: list[dict[str, Any]] = []
    for plan in plans:
        entries.extend(_detected(kind, *_sweep(plan, timeout)))
    return entries


def _serial_candidates() -> list[str]:
    """``serial:<device>`` for every port pyserial lists (none without pyserial)."""
    try:
        list_ports = importlib.import_module("serial.tools.list_ports")
    except ImportError:
        logger.info("mavlink detect: pyserial is not installed: no serial ports to look at")
        return []
    return [f"serial:{port.device}" for port in sorted(list_ports.comports(), key=_device)]


def _device(port: Any) -> str:
    return str(port.device)


def _detect_plan(url: Any) -> list[tuple[LinkSpec, str]]:
    """The links to listen on for one URL (one per baud rate to try) and how each is shown.

    Raises:
        ValueError: Not a link URL (the message names it).
    """
    spec = parse_link(url)  # ValueError names the URL
    if spec.scheme != "serial" or "baud" in parse_qs(url.partition("?")[2]):
        return [(spec, url)]
    tries = [LinkSpec("serial", device=spec.device, baud=baud) for baud in _DETECT_BAUDS]
    return [(each, str(each)) for each in tries]


def _sweep(plan: list[tuple[LinkSpec, str]], timeout: float) -> tuple[str, _Heard]:
    """Listen on each try of one link until a valid HEARTBEAT arrives.

    Returns:
        How the link that heard it is shown, and the vehicles heard ("" and none if no try
        heard a heartbeat).
    """
    for spec, shown in plan:
        heard = _listen(spec, timeout)
        if heard is None:
            break  # it cannot be opened: at another baud rate neither
        valid, vehicles = heard
        if valid:
            return shown, vehicles
    return "", {}


def _listen(spec: LinkSpec, timeout: float) -> tuple[bool, _Heard] | None:
    """Listen on one link for ``timeout`` real seconds, sending nothing.

    Returns:
        None if the link cannot be opened; else whether any valid HEARTBEAT arrived, and the
        vehicles heard.
    """
    try:
        link = open_link(spec)
    except OSError as err:
        logger.warning("mavlink detect: skipping %s: cannot open it: %s", spec, err)
        return None
    codec = Codec(255, 190)  # only its parser is used: detect never encodes or sends
    valid = False
    vehicles: _Heard = {}
    others: set[tuple[int, int]] = set()
    senders: dict[tuple[int, int], Any] = {}  # a vehicle's ids → the first address heard
    twins: set[tuple[int, int]] = set()
    deadline = time.monotonic() + timeout
    try:
        while (remaining := deadline - time.monotonic()) > 0:
            try:
                data, sender = link.receive(remaining)
            except OSError as err:
                logger.warning("mavlink detect: %s failed while listening: %s", spec, err)
                break
            messages = codec.decode_datagram(data) if link.datagrams else codec.decode(data)
            for msg in messages if data else []:
                if msg.name != "HEARTBEAT":
                    continue
                valid = True
                ids = (msg.src_system, msg.src_component)
                kind, autopilot = msg.get_int("type"), msg.get_int("autopilot")
                vehicle = kind != p.MAV_TYPE_GCS and autopilot != p.MAV_AUTOPILOT_INVALID
                if vehicle and msg.src_system >= 1:
                    vehicles.setdefault(ids, (kind, autopilot))
                    first = senders.setdefault(ids, sender)
                    if sender != first and ids not in twins:
                        twins.add(ids)
                        logger.warning(
                            "mavlink detect: %s: duplicate system id %d: component %d"
                            " heartbeats from %s and from %s (two vehicles with one id;"
                            " configure will refuse it)",
                            spec,
                            *ids,
                            _address(first),
                            _address(sender),
                        )
                elif ids not in others:
                    others.add(ids)
                    logger.debug(
                        "mavlink detect: %s: system %d component %d is not a vehicle: %s, %s",
                        spec,
                        *ids,
                        _type_name(kind),
                        _autopilot_name(autopilot),
                    )
    finally:
        link.close()
    if not valid:
        logger.debug(
            "mavlink detect: %s: no valid heartbeat in %g s (%d bad frames)",
            spec,
            timeout,
            codec.bad_frames,
        )
    return valid, vehicles


def _detected(kind: str, link: str, vehicles: _Heard) -> list[dict[str, Any]]:
    """One profile entry per system heard on ``link`` (logged)."""
    systems: dict[int, list[int]] = {}
    for (system, component), (mav_type, autopilot) in vehicles.items():
        logger.info(
            "mavlink detect: %s: system %d component %d: %s, %s",
            link,
            system,
            component,
            _type_name(mav_type),
            _autopilot_name(autopilot),
        )
        if autopilot != p.MAV_AUTOPILOT_ARDUPILOTMEGA and system not in systems:
            logger.warning(
                "mavlink detect: %s: system %d is not an ArduPilot (%s); the driver flies"
                " ArduPilot only and configure will refuse it",
                link,
                system,
                _autopilot_name(autopilot),
            )
        systems.setdefault(system, []).append(component)
    return [
        {
            "driver": kind,
            "link": link,
            "system_id": system,
            "component_id": (
                _AUTOPILOT_COMPONENT if _AUTOPILOT_COMPONENT in components else components[0]
            ),
        }
        for system, components in systems.items()
    ]


def _type_name(mav_type: int) -> str:
    return p.enum_name("MAV_TYPE", mav_type)


def _autopilot_name(autopilot: int) -> str:
    return p.enum_name("MAV_AUTOPILOT", autopilot)


def _address(addr: Any) -> str:
    """``127.0.0.1:14550`` for a (host, port) address."""
    if isinstance(addr, tuple) and len(addr) >= 2:
        return f"{addr[0]}:{addr[1]}"
    return str(addr)
