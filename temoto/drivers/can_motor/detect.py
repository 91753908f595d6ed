"""Finding ODrive axes on CAN buses without a profile (``temoto drivers detect``).

:func:`detect` only listens: it opens each bus, reads the nodes' cyclic CANSimple heartbeats
for a while and closes it again, sending nothing (no RTR request either), so looking never
moves an axis. MIT-mode motors cannot be found this way (they move on every frame), so
``mit_can`` finds nothing.
"""

from __future__ import annotations

import itertools
import logging
import statistics
import time
from collections.abc import Mapping, Sequence
from typing import Any, Final

import can

from temoto.drivers.base import detect_links
from temoto.drivers.can_motor import cansimple as cs
from temoto.drivers.can_motor._common import open_bus, read_link
from temoto.drivers.profile import ProfileReader
from temoto.errors import DriverError, ProfileError

__all__ = ["DETECT_MIN_BEATS", "detect"]

logger = logging.getLogger(__name__)

#: Well-formed heartbeats a node must send while :func:`detect` listens.
DETECT_MIN_BEATS: Final = 2


def detect(kind: str, links: Sequence[Any] | None, timeout: float) -> list[dict[str, Any]]:
    """The ODrive axes heartbeating on CAN buses, as profile device entries.

    See :meth:`~temoto.drivers.can_motor.odrive.ODriveDriver.detect`, which calls this.

    Listens only: each link's bus is opened, read for ``timeout`` real seconds and closed
    again, and no frame is sent (no RTR request either), so nothing moves. A node is an
    ODrive axis when at least :data:`DETECT_MIN_BEATS` well-formed CANSimple heartbeats
    (command 0x01, standard id, 8 data bytes whose axis state, procedure result and flags
    are defined values: :func:`~temoto.drivers.can_motor.cansimple.heartbeat_problem`)
    arrive from it, outnumbering the malformed frames on its id, with a median gap of at
    least 1 ms between their timestamps (cyclic, not a burst); so an
    MIT-mode command frame to motor 0x41 is not node 2. Each listed node's axis state and
    error bits are logged, at WARNING when it has errors (clear them before use), at INFO
    otherwise; an id heard but not listed is logged at INFO with the reason. The entries
    themselves stay as a profile takes them. Only the ODrives' cyclic heartbeats are
    seen: an axis whose ``heartbeat_msg_rate_ms`` is 0, or slower than half of
    ``timeout``, may be missed.

    Args:
        kind: The driver's name (each entry's ``driver``).
        links: python-can ``Bus`` mappings in the form of a profile's ``link``; None: every
            configuration :func:`can.detect_available_configs` reports.
        timeout: Real seconds to listen on each link, one link after the other.

    Returns:
        One entry per link on which at least one node sent a heartbeat, in link order.

    Raises:
        ValueError: A bad timeout, ``links`` not a sequence, or a link that is not a mapping
            with ``interface`` and ``channel`` (named by its index).
    """
    if links is not None and (
        isinstance(links, str | bytes | Mapping) or not isinstance(links, Sequence)
    ):
        raise ValueError(f"{kind} detect: links must be a sequence of link mappings, got {links!r}")
    found = detect_links(links, timeout, _available_links)
    candidates = [_link(kind, i, link) for i, link in enumerate(found)]
    entries: list[dict[str, Any]] = []
    for link in candidates:
        seen = _listen(kind, link, timeout)
        if seen:
            nodes = [{"node_id": n, "joint": f"joint_{n}"} for n in sorted(seen)]
            entries.append({"driver": kind, "link": dict(link), "nodes": nodes})
    return entries


def _link(kind: str, index: int, link: object) -> dict[str, Any]:
    """A link to look at, checked as a profile's ``link`` is checked."""
    try:
        return read_link(ProfileReader(), link, f"links[{index}]")
    except ProfileError as err:
        raise ValueError(
            f"{kind} detect: links[{index}] is not a python-can bus mapping with"
            f" interface and channel (e.g. {{interface: socketcan, channel: can0}}): {link!r}"
        ) from err


def _available_links() -> list[dict[str, Any]]:
    """What python-can can open here (a configuration not in profile form is skipped).

    python-can imports every interface module to ask it, and each one that lacks its vendor
    library logs a WARNING on the ``can`` logger (a dozen on a machine without them); those
    are not shown: that logger is quieted to ERROR for the call.
    """
    quiet = logging.getLogger("can")
    level = quiet.level
    quiet.setLevel(logging.ERROR)
    try:
        configs = can.detect_available_configs()
    finally:
        quiet.setLevel(level)
    links: list[dict[str, Any]] = []
    for index, config in enumerate(configs):
        try:
            links.append(_link("odrive_can", index, config))
        except ValueError as err:
            logger.debug("%s", err)
    return links


def _listen(kind: str, link: dict[str, Any], timeout: float) -> dict[int, cs.Heartbeat]:
    """The newest heartbeat of each ODrive node heard on ``link`` within ``timeout`` s.

    A node counts when at least :data:`DETECT_MIN_BEATS` well-formed heartbeats
    (:func:`~temoto.drivers.can_motor.cansimple.heartbeat_problem`) came from it, more than
    malformed frames on its heartbeat id, with a median gap of 1 ms or more between their
    frame timestamps (a cyclic message, not a burst). What each node tells is logged: INFO
    for a clean axis, WARNING for one with error bits, INFO for an id that was heard but not
    counted, and why.
    """
    what = f"{kind} detect"
    try:
        bus = open_bus(link, what)
    except DriverError as err:
        logger.warning("%s: skipping %s: %s", what, link, err)
        return {}
    beats: dict[int, list[float]] = {}
    newest: dict[int, cs.Heartbeat] = {}
    bad: dict[int, tuple[int, str]] = {}
    try:
        deadline = time.monotonic() + timeout
        while (left := deadline - time.monotonic()) > 0:
            try:
                msg = bus.recv(timeout=left)
            except (can.CanError, OSError) as err:
                logger.warning("%s: receiving on %s failed, stopped listening: %s", what, link, err)
                break
            if msg is None or msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
                continue  # a remote Heartbeat is some host's request, not a node's beat
            if msg.arbitration_id > 0x7FF:
                continue
            node, cmd = cs.split_id(msg.arbitration_id)
            if cmd != cs.Cmd.HEARTBEAT:
                continue
            why = cs.heartbeat_problem(msg.data)
            if why is not None:
                count, _ = bad.get(node, (0, ""))
                bad[node] = (count + 1, why)
                continue
            beats.setdefault(node, []).append(msg.timestamp)
            newest[node] = cs.decode_heartbeat(msg.data)
    finally:
        bus.shutdown()
    seen: dict[int, cs.Heartbeat] = {}
    for node in sorted(set(beats) | set(bad)):
        times = beats.get(node, [])
        malformed, why = bad.get(node, (0, ""))
        gaps = [b - a for a, b in itertools.pairwise(times)]
        reason = None
        if len(times) < DETECT_MIN_BEATS:
            reason = f"{len(times)} well-formed heartbeat(s), {DETECT_MIN_BEATS} needed"
        elif malformed >= len(times):
            reason = f"{malformed} malformed frames on its heartbeat id ({why})"
        elif statistics.median(gaps) < 0.001:
            reason = "heartbeats less than 1 ms apart: not a cyclic heartbeat"
        if reason is not None:
            extra = f" (and {malformed} malformed: {why})" if malformed and times else ""
            logger.info(
                "%s: id 0x%03x on %s not listed: %s%s", what, node << 5 | 1, link, reason, extra
            )
            continue
        seen[node] = beat = newest[node]
        errors = " | ".join(cs.error_names(beat.axis_error)) or "none"
        logger.log(
            logging.WARNING if beat.axis_error else logging.INFO,
            "%s: node %d on %s: axis state %s, axis errors %s, procedure result %d%s",
            what,
            node,
            link,
            cs.state_name(beat.axis_state),
            errors,
            beat.procedure_result,
            " (clear the errors before use: Clear_Errors, or recover())" if beat.axis_error else "",
        )
    return seen
