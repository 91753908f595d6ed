"""The simulated vehicle's side of the MAVLink mission microservice (https://mavlink.io/en/services/mission.html).

:class:`MissionService` keeps the stored plans (mission, geofence and rally points, each a list
of :class:`MissionItem`) and runs the transfers as ArduPilot does: an upload starts with
MISSION_COUNT and the vehicle asks for each item (MISSION_REQUEST_INT, resent after 1 s
without an answer; the upload is cancelled with ``MAV_MISSION_OPERATION_CANCELLED`` after 8 s
without an item) and ends with a MISSION_ACK; a download starts with MISSION_REQUEST_LIST (the
vehicle answers MISSION_COUNT) and the ground station asks for each item. Legacy
MISSION_ITEM / MISSION_REQUEST (float coordinates) are accepted and answered in kind. Item 0 of
the mission is home, as in ArduPilot: a download reports the current home there. While an
upload runs, another system's upload and any download are DENIED. As in ArduPilot
(``MissionItemProtocol``, ``MissionItemProtocol_Waypoints``/``_Rally``/``_Fence``): an item
other than the one asked for gets ``MAV_MISSION_INVALID_SEQUENCE`` and the upload goes on;
mission and rally items are written as they arrive over a plan first truncated to the new
count, so a cancelled or refused upload leaves the items received so far over the rest of the
old plan (fence items are kept apart and stored only when the upload completes); "Flight plan
received" / "Rally points received" before the final ACK, "Mission upload timeout" (rally,
fence: "Rally"/"Fence upload timeout") before ``MAV_MISSION_OPERATION_CANCELLED``;
MISSION_CLEAR_ALL of the mission while it is flown is refused (``AP_Mission::clear``:
``MAV_MISSION_ERROR``, the mission goes on); a request for a mission item past the end gets
MISSION_COUNT with the real count, then ``MAV_MISSION_ERROR``.

No I/O and no threads: the owner passes each received message to :meth:`MissionService.handle`
and calls :meth:`MissionService.tick` regularly, and sends the frames they return. Not
thread-safe: the owner serialises calls (the simulator holds its lock).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any, Final

from temoto.drivers.mavlink import protocol as p
from temoto.drivers.mavlink.protocol import Message

__all__ = ["MAX_ITEMS", "MissionItem", "MissionService"]

#: Items a plan may hold (ArduPilot's limit depends on the board's storage; 700 is SITL's).
MAX_ITEMS: Final = 700
REQUEST_RESEND: Final = 1.0  # s without an item before the request is sent again
UPLOAD_TIMEOUT: Final = 8.0  # s without an item before the upload is cancelled

_TYPES: Final = (p.MAV_MISSION_TYPE_MISSION, p.MAV_MISSION_TYPE_FENCE, p.MAV_MISSION_TYPE_RALLY)
_GLOBAL_FRAMES: Final = frozenset(
    {
        p.MAV_FRAME_GLOBAL,
        p.MAV_FRAME_GLOBAL_RELATIVE_ALT,
        p.MAV_FRAME_GLOBAL_INT,
        p.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
        p.MAV_FRAME_GLOBAL_TERRAIN_ALT,
        p.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT,
    }
)
_FRAMES: Final = _GLOBAL_FRAMES | {p.MAV_FRAME_MISSION}

# ArduPilot's MissionItemProtocol_Waypoints/_Rally/_Fence ``timeout()`` and ``complete()`` texts
_NOUN: Final = {
    p.MAV_MISSION_TYPE_MISSION: "Mission",
    p.MAV_MISSION_TYPE_FENCE: "Fence",
    p.MAV_MISSION_TYPE_RALLY: "Rally",
}
_RECEIVED: Final = {
    p.MAV_MISSION_TYPE_MISSION: "Flight plan received",
    p.MAV_MISSION_TYPE_RALLY: "Rally points received",
}


@dataclass(frozen=True, slots=True)
class MissionItem:
    """One stored plan item, as MISSION_ITEM_INT carries it.

    Attributes:
        seq: Its index in the plan.
        frame: ``MAV_FRAME`` of the coordinates.
        command: ``MAV_CMD``.
        current: The field as uploaded (ArduPilot ignores it in a plan).
        autocontinue: Go on to the next item when this one is done.
        param1: Command parameter 1 (e.g. a waypoint's hold time, s).
        param2: Command parameter 2 (e.g. a waypoint's acceptance radius, m).
        param3: Command parameter 3.
        param4: Command parameter 4 (e.g. yaw, deg).
        x: Latitude, degrees·10⁷ (or a local x).
        y: Longitude, degrees·10⁷.
        z: Altitude, m, in ``frame``.
        mission_type: ``MAV_MISSION_TYPE``.
    """

    seq: int
    frame: int
    command: int
    current: int
    autocontinue: int
    param1: float
    param2: float
    param3: float
    param4: float
    x: int
    y: int
    z: float
    mission_type: int = 0

    @property
    def lat(self) -> float:
        """Latitude, degrees."""
        return self.x / 1e7

    @property
    def lon(self) -> float:
        """Longitude, degrees."""
        return self.y / 1e7

    @property
    def relative(self) -> bool:
        """Whether ``z`` is above home (relative and terrain frames; terrain is flat here)."""
        return self.frame not in (p.MAV_FRAME_GLOBAL, p.MAV_FRAME_GLOBAL_INT)

    @classmethod
    def from_message(cls, msg: Message) -> MissionItem:
        """The item of a MISSION_ITEM_INT, or of a legacy MISSION_ITEM (float degrees).

        Args:
            msg: The message.

        Returns:
            The item.
        """
        frame = msg.get_int("frame")
        x, y = msg.fields["x"], msg.fields["y"]
        if msg.name == "MISSION_ITEM":
            if frame in _GLOBAL_FRAMES:
                x, y = round(float(x) * 1e7), round(float(y) * 1e7)
            else:
                x, y = round(float(x)), round(float(y))
        return cls(
            seq=msg.get_int("seq"),
            frame=frame,
            command=msg.get_int("command"),
            current=msg.get_int("current"),
            autocontinue=msg.get_int("autocontinue"),
            param1=msg.get_float("param1"),
            param2=msg.get_float("param2"),
            param3=msg.get_float("param3"),
            param4=msg.get_float("param4"),
            x=int(x),
            y=int(y),
            z=msg.get_float("z"),
            mission_type=int(msg.fields.get("mission_type", 0)),
        )

    def check(self) -> int:
        """ArduPilot's verdict on storing this item: a ``MAV_MISSION_RESULT``."""
        if self.mission_type == p.MAV_MISSION_TYPE_MISSION:
            if self.command not in p.MAV_CMDS:
                return p.MAV_MISSION_UNSUPPORTED
            if self.frame not in _FRAMES:
                return p.MAV_MISSION_UNSUPPORTED_FRAME
        if not math.isfinite(self.z):  # NaN params mean "default" (MAVLink); z must be a number
            return p.MAV_MISSION_ERROR
        return p.MAV_MISSION_ACCEPTED


@dataclass(slots=True)
class _Upload:
    mission_type: int
    count: int
    sysid: int
    compid: int
    legacy: bool  # the GCS sent MISSION_ITEM: ask with MISSION_REQUEST
    items: list[MissionItem]  # fence items, stored when the upload completes
    next: int  # the item asked for
    last_item: float
    last_request: float


Encode = Callable[..., bytes]


class MissionService:
    """Stored plans and the transfers that change them (see the module docstring).

    Args:
        encode: Packs one message as the vehicle (``Codec.encode``).
        home_item: Item 0 of a downloaded mission: the current home.
        flying: Whether the stored mission is being flown (MISSION_CLEAR_ALL is then refused).
    """

    def __init__(
        self,
        encode: Encode,
        home_item: Callable[[], MissionItem],
        flying: Callable[[], bool] = lambda: False,
    ) -> None:
        self._encode = encode
        self._home_item = home_item
        self._flying = flying
        self._plans: dict[int, list[MissionItem]] = {t: [] for t in _TYPES}
        self._upload: _Upload | None = None
        #: Bumped whenever the stored mission (type MISSION) changes.
        self.version = 0

    # ---- the stored mission -------------------------------------------------------------------

    @property
    def items(self) -> list[MissionItem]:
        """The stored mission, item 0 (home) included; empty when only home is stored."""
        return list(self._plans[p.MAV_MISSION_TYPE_MISSION])

    def count(self, mission_type: int = p.MAV_MISSION_TYPE_MISSION) -> int:
        """Items of a plan as a download reports them (the mission always has home, item 0).

        Args:
            mission_type: ``MAV_MISSION_TYPE``.

        Returns:
            The count.
        """
        stored = len(self._plans.get(mission_type, []))
        if mission_type == p.MAV_MISSION_TYPE_MISSION:
            return max(stored, 1)
        return stored

    def item(self, seq: int) -> MissionItem | None:
        """Mission item ``seq`` (0 is home), or None past the end.

        Args:
            seq: The index.

        Returns:
            The item.
        """
        if seq == 0:
            return self._home_item()
        items = self._plans[p.MAV_MISSION_TYPE_MISSION]
        return items[seq] if 0 < seq < len(items) else None

    def clear(self, mission_type: int = p.MAV_MISSION_TYPE_MISSION) -> None:
        """Forget a plan (``MAV_MISSION_TYPE_ALL``: every plan).

        Args:
            mission_type: Which.
        """
        for kind in _TYPES if mission_type == p.MAV_MISSION_TYPE_ALL else (mission_type,):
            self._plans[kind] = []
            if kind == p.MAV_MISSION_TYPE_MISSION:
                self.version += 1

    @property
    def uploading(self) -> bool:
        """Whether an upload is in progress."""
        return self._upload is not None

    # ---- protocol -----------------------------------------------------------------------------

    def handle(self, msg: Message, now: float) -> list[bytes]:
        """Answer one mission-protocol message.

        Args:
            msg: MISSION_COUNT, MISSION_ITEM(_INT), MISSION_REQUEST(_INT), MISSION_REQUEST_LIST,
                MISSION_CLEAR_ALL or MISSION_ACK (others are ignored).
            now: The simulator's clock.

        Returns:
            The frames to send.
        """
        kind = int(msg.fields.get("mission_type", 0))
        name = msg.name
        if name == "MISSION_ACK":
            return []  # the end of a download; nothing to do
        if name == "MISSION_CLEAR_ALL":
            if self._upload is not None or kind not in (*_TYPES, p.MAV_MISSION_TYPE_ALL):
                return [self._ack(msg, p.MAV_MISSION_ERROR, kind)]
            if kind in (p.MAV_MISSION_TYPE_MISSION, p.MAV_MISSION_TYPE_ALL) and self._flying():
                return [self._ack(msg, p.MAV_MISSION_ERROR, kind)]  # AP_Mission::clear refuses
            self.clear(kind)
            return [self._ack(msg, p.MAV_MISSION_ACCEPTED, kind)]
        if kind not in _TYPES:
            return [self._ack(msg, p.MAV_MISSION_UNSUPPORTED, kind)]
        if name == "MISSION_COUNT":
            return self._count(msg, kind, now)
        if name in ("MISSION_ITEM_INT", "MISSION_ITEM"):
            return self._item(msg, now)
        if name == "MISSION_REQUEST_LIST":
            if self._upload is not None:
                return [self._ack(msg, p.MAV_MISSION_DENIED, kind)]
            return [
                self._encode(
                    "MISSION_COUNT",
                    target_system=msg.src_system,
                    target_component=msg.src_component,
                    count=self.count(kind),
                    mission_type=kind,
                )
            ]
        if name in ("MISSION_REQUEST_INT", "MISSION_REQUEST"):
            return self._send_item(msg, kind)
        return []

    def tick(self, now: float) -> list[bytes]:
        """Resend a request that got no item, cancel an upload that stalled.

        Args:
            now: The simulator's clock.

        Returns:
            The frames to send.
        """
        up = self._upload
        if up is None:
            return []
        if now - up.last_item > UPLOAD_TIMEOUT:
            self._upload = None
            self._changed(up.mission_type)
            return [
                self._text(p.MAV_SEVERITY_WARNING, f"{_NOUN[up.mission_type]} upload timeout"),
                self._encode(
                    "MISSION_ACK",
                    target_system=up.sysid,
                    target_component=up.compid,
                    type=p.MAV_MISSION_OPERATION_CANCELLED,
                    mission_type=up.mission_type,
                ),
            ]
        if now - up.last_request > REQUEST_RESEND:
            return [self._request(up, now)]
        return []

    def _count(self, msg: Message, kind: int, now: float) -> list[bytes]:
        count = msg.get_int("count")
        up = self._upload
        if up is not None and (msg.src_system, msg.src_component) != (up.sysid, up.compid):
            return [self._ack(msg, p.MAV_MISSION_DENIED, kind)]  # someone else is uploading
        if count > MAX_ITEMS:
            return [self._ack(msg, p.MAV_MISSION_NO_SPACE, kind)]
        self._upload = None
        if kind != p.MAV_MISSION_TYPE_FENCE and len(self._plans[kind]) > count:
            del self._plans[kind][count:]  # ArduPilot truncates the stored plan at once
            self._changed(kind)
        if count == 0:
            if kind == p.MAV_MISSION_TYPE_FENCE:
                self._plans[kind] = []
            return [*self._received(kind), self._ack(msg, p.MAV_MISSION_ACCEPTED, kind)]
        self._upload = _Upload(
            kind, count, msg.src_system, msg.src_component, False, [], 0, now, now
        )
        return [self._request(self._upload, now)]

    def _item(self, msg: Message, now: float) -> list[bytes]:
        up = self._upload
        if up is None:
            return []  # not uploading (a guided item is the simulator's business)
        item = MissionItem.from_message(msg)
        if item.mission_type != up.mission_type or item.seq != up.next:
            # ArduPilot: any item but the one asked for (a stray copy after a resent request
            # too); the upload goes on
            return [self._ack(msg, p.MAV_MISSION_INVALID_SEQUENCE, up.mission_type)]
        if (msg.src_system, msg.src_component) != (up.sysid, up.compid):
            return [self._ack(msg, p.MAV_MISSION_DENIED, up.mission_type)]
        verdict = item.check()
        if verdict != p.MAV_MISSION_ACCEPTED:
            self._upload = None
            self._changed(up.mission_type)
            return [self._ack(msg, verdict, up.mission_type)]
        item = replace(item, current=0)
        if up.mission_type == p.MAV_MISSION_TYPE_FENCE:
            up.items.append(item)
        else:  # written as it arrives: replaces the old item there, or appends
            plan = self._plans[up.mission_type]
            if item.seq < len(plan):
                plan[item.seq] = item
            else:
                plan.append(item)
        up.next += 1
        up.legacy = msg.name == "MISSION_ITEM"
        up.last_item = now
        if up.next < up.count:
            return [self._request(up, now)]
        self._upload = None
        if up.mission_type == p.MAV_MISSION_TYPE_FENCE:
            self._plans[up.mission_type] = up.items
        self._changed(up.mission_type)
        return [
            *self._received(up.mission_type),
            self._ack(msg, p.MAV_MISSION_ACCEPTED, up.mission_type),
        ]

    def _changed(self, kind: int) -> None:
        if kind == p.MAV_MISSION_TYPE_MISSION:
            self.version += 1

    def _received(self, kind: int) -> list[bytes]:
        """The STATUSTEXT ArduPilot sends when an upload completes (none for a fence)."""
        text = _RECEIVED.get(kind)
        return [] if text is None else [self._text(p.MAV_SEVERITY_INFO, text)]

    def _text(self, severity: int, text: str) -> bytes:
        return self._encode("STATUSTEXT", severity=severity, text=text.encode(), id=0)

    def _send_item(self, msg: Message, kind: int) -> list[bytes]:
        if self._upload is not None:
            return [self._ack(msg, p.MAV_MISSION_DENIED, kind)]
        seq = msg.get_int("seq")
        if kind == p.MAV_MISSION_TYPE_MISSION:
            item = self.item(seq)
        else:
            plan = self._plans[kind]
            item = plan[seq] if 0 <= seq < len(plan) else None
        if item is None and kind == p.MAV_MISSION_TYPE_MISSION:
            # MissionItemProtocol_Waypoints::get_item: tell the GCS the real count, then ERROR
            count = self._encode(
                "MISSION_COUNT",
                target_system=msg.src_system,
                target_component=msg.src_component,
                count=self.count(kind),
                mission_type=kind,
            )
            return [count, self._ack(msg, p.MAV_MISSION_ERROR, kind)]
        if item is None:
            return [self._ack(msg, p.MAV_MISSION_INVALID_SEQUENCE, kind)]
        fields: dict[str, Any] = {
            "target_system": msg.src_system,
            "target_component": msg.src_component,
            "seq": seq,
            "frame": item.frame,
            "command": item.command,
            "current": 0,
            "autocontinue": item.autocontinue,
            "param1": item.param1,
            "param2": item.param2,
            "param3": item.param3,
            "param4": item.param4,
            "x": item.x,
            "y": item.y,
            "z": item.z,
            "mission_type": kind,
        }
        if msg.name == "MISSION_REQUEST":
            if item.frame in _GLOBAL_FRAMES:
                fields["x"], fields["y"] = item.x / 1e7, item.y / 1e7
            else:
                fields["x"], fields["y"] = float(item.x), float(item.y)
            return [self._encode("MISSION_ITEM", **fields)]
        return [self._encode("MISSION_ITEM_INT", **fields)]

    def _request(self, up: _Upload, now: float) -> bytes:
        up.last_request = now
        return self._encode(
            "MISSION_REQUEST" if up.legacy else "MISSION_REQUEST_INT",
            target_system=up.sysid,
            target_component=up.compid,
            seq=up.next,
            mission_type=up.mission_type,
        )

    def _ack(self, msg: Message, result: int, kind: int) -> bytes:
        return self._encode(
            "MISSION_ACK",
            target_system=msg.src_system,
            target_component=msg.src_component,
            type=result,
            mission_type=kind,
        )
