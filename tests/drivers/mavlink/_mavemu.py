"""A small, independent MAVLink vehicle end for the driver's mission and parameter tests.

Written from the MAVLink mission and parameter protocol documents (mavlink.io services
"Mission Protocol" and "Parameter Protocol") and ArduPilot's documented habits, not from
temoto's simulator: it speaks pymavlink's ``ardupilotmega`` dialect on its own UDP socket,
sends an ArduPilot heartbeat, and answers

* the mission microservice: MISSION_COUNT → MISSION_REQUEST_INT (or the older MISSION_REQUEST)
  per item → MISSION_ACK; MISSION_REQUEST_LIST → MISSION_COUNT, MISSION_REQUEST_INT →
  MISSION_ITEM_INT; MISSION_CLEAR_ALL → MISSION_ACK; an item it did not ask for makes it ask
  again for the one it waits for (ArduPilot re-requests after 1 s without an item; this end at
  once), with MAV_MISSION_INVALID_SEQUENCE first when ``nack_stray`` (as ArduPilot answers a
  stray item);
* the parameter microservice: PARAM_REQUEST_READ (by name or index) and PARAM_SET →
  PARAM_VALUE, integers carried as floats (ArduPilot's "C cast"); an unknown name gets no
  answer, as on ArduPilot;
* COMMAND_LONG: mode changes, arming, MAV_CMD_MISSION_START (AUTO, MISSION_CURRENT 1), and an
  ACCEPTED ack for everything else.

Faults to exercise the retries: drop the first MISSION_REQUEST for an item, send one twice,
ignore the first copy of an item, drop the first MISSION_ITEM_INT of a download or the first
PARAM_VALUE of a parameter; refuse an upload with a given MAV_MISSION_RESULT; stay silent to a
message.
"""

from __future__ import annotations

import socket
import threading
import time
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mav

AUTO = 3
GUIDED = 4
INT_TYPES = {
    mav.MAV_PARAM_TYPE_UINT8,
    mav.MAV_PARAM_TYPE_INT8,
    mav.MAV_PARAM_TYPE_UINT16,
    mav.MAV_PARAM_TYPE_INT16,
    mav.MAV_PARAM_TYPE_UINT32,
    mav.MAV_PARAM_TYPE_INT32,
}


class MavEmu:
    """The vehicle end (system 1, component 1) on ``127.0.0.1:<port>``; use as a context."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.02)
        self.port: int = self.sock.getsockname()[1]
        self.mav = mav.MAVLink(None, 1, 1)
        self.peer: Any = None
        self.lock = threading.Lock()
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._loop, name="mavemu", daemon=True)
        self.received: list[Any] = []  # every message from the GCS, in order
        self.sent: list[Any] = []  # every message to the GCS, heartbeats left out
        # vehicle state
        self.mode = 0
        self.armed = False
        self.home = (47.397742, 8.545594, 488.0)
        self.mission: list[Any] = []  # MISSION_ITEM_INT messages, seq 0 = home
        self.params: dict[str, tuple[float, int]] = {
            "WPNAV_SPEED": (500.0, mav.MAV_PARAM_TYPE_REAL32),
            "RTL_ALT": (1500.0, mav.MAV_PARAM_TYPE_INT32),
            "FS_GCS_ENABLE": (0.0, mav.MAV_PARAM_TYPE_INT8),
            "ARMING_CHECK": (1.0, mav.MAV_PARAM_TYPE_INT32),
        }
        self.param_clamp: dict[str, float] = {}  # name → the most it takes
        # an upload under way
        self._incoming: list[Any] | None = None
        self._expect = 0
        # faults
        self.legacy_requests = False  # ask with MISSION_REQUEST, not MISSION_REQUEST_INT
        self.drop_request: set[int] = set()  # the first request for these items is not sent
        self.double_request: set[int] = set()  # the request for these items goes twice
        self.ignore_item: set[int] = set()  # the first copy of these items is lost
        self.refuse_count: int | None = None  # a MAV_MISSION_RESULT for MISSION_COUNT
        self.refuse_item: tuple[int, int] | None = None  # (seq, MAV_MISSION_RESULT)
        self.drop_download_item: set[int] = set()
        self.drop_param: set[str] = set()
        self.silent: set[str] = set()  # GCS messages never answered
        self.param_errors = False  # unknown names get PARAM_ERROR (newer ArduPilot), not silence
        self.nack_stray = False  # a stray item gets MAV_MISSION_INVALID_SEQUENCE, as ArduPilot
        # flying: with ``item_seconds`` set, AUTO goes to the next item every so many real
        # seconds (not in another mode: LOITER holds), and after a last LAND it disarms
        self.item_seconds: float | None = None
        self.flying_seq = 0  # the item AUTO is at (0: none)
        self._item_due = 0.0

    # ---- running -------------------------------------------------------------------------------

    def __enter__(self) -> MavEmu:
        self.thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        self.thread.join()
        self.sock.close()

    @property
    def link(self) -> str:
        """The driver's link to this vehicle."""
        return f"udpout:127.0.0.1:{self.port}"

    def send(self, msg: Any) -> None:
        with self.lock:
            data = msg.pack(self.mav)
            if msg.get_type() != "HEARTBEAT":
                self.sent.append(msg)
            peer = self.peer
        if peer is not None:
            self.sock.sendto(data, peer)

    def names_received(self) -> list[str]:
        with self.lock:
            return [m.get_type() for m in self.received]

    def names_sent(self) -> list[str]:
        with self.lock:
            return [m.get_type() for m in self.sent]

    def _loop(self) -> None:
        parser = mav.MAVLink(None, 1, 1)
        next_hb = 0.0
        while not self.stop.is_set():
            now = time.monotonic()
            if now >= next_hb and self.peer is not None:
                next_hb = now + 0.1
                self._heartbeat()
            self._fly(now)
            try:
                data, peer = self.sock.recvfrom(65536)
            except (TimeoutError, OSError):
                continue
            self.peer = peer
            for msg in parser.parse_buffer(data) or []:
                if msg.get_type() == "BAD_DATA":
                    continue
                with self.lock:
                    self.received.append(msg)
                if msg.get_type() not in self.silent:
                    self._handle(msg)

    def _heartbeat(self) -> None:
        base = mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if self.armed:
            base |= mav.MAV_MODE_FLAG_SAFETY_ARMED
        self.send(
            self.mav.heartbeat_encode(
                mav.MAV_TYPE_QUADROTOR,
                mav.MAV_AUTOPILOT_ARDUPILOTMEGA,
                base,
                self.mode,
                mav.MAV_STATE_STANDBY,
            )
        )

    # ---- what the GCS says ---------------------------------------------------------------------

    def _handle(self, msg: Any) -> None:
        kind = msg.get_type()
        handler = getattr(self, f"_on_{kind.lower()}", None)
        if handler is not None:
            handler(msg)

    def _ack(self, result: int) -> None:
        self.send(self.mav.mission_ack_encode(255, 190, result, mav.MAV_MISSION_TYPE_MISSION))

    def _request(self, seq: int) -> None:
        if seq in self.drop_request:
            self.drop_request.discard(seq)
            return
        if self.legacy_requests:
            msg = self.mav.mission_request_encode(255, 190, seq, mav.MAV_MISSION_TYPE_MISSION)
        else:
            msg = self.mav.mission_request_int_encode(255, 190, seq, mav.MAV_MISSION_TYPE_MISSION)
        self.send(msg)
        if seq in self.double_request:
            self.double_request.discard(seq)
            self.send(msg)

    def _on_mission_count(self, msg: Any) -> None:
        if self.refuse_count is not None:
            self._ack(self.refuse_count)
            return
        self._incoming = [None] * msg.count
        self._expect = 0
        self._request(0)

    def _on_mission_item_int(self, msg: Any) -> None:
        if self._incoming is None:
            return  # no upload under way: a late copy
        if msg.seq in self.ignore_item:
            self.ignore_item.discard(msg.seq)
            return
        if msg.seq != self._expect:
            if self.nack_stray:
                self._ack(mav.MAV_MISSION_INVALID_SEQUENCE)
            self._request(self._expect)  # ask again for the one it waits for
            return
        if self.refuse_item is not None and self.refuse_item[0] == msg.seq:
            self._incoming = None
            self._ack(self.refuse_item[1])
            return
        self._incoming[msg.seq] = msg
        self._expect += 1
        if self._expect < len(self._incoming):
            self._request(self._expect)
            return
        self.mission = list(self._incoming)
        self._incoming = None
        self._ack(mav.MAV_MISSION_ACCEPTED)

    def _on_mission_request_list(self, msg: Any) -> None:
        self.send(
            self.mav.mission_count_encode(255, 190, len(self.mission), mav.MAV_MISSION_TYPE_MISSION)
        )

    def _on_mission_request_int(self, msg: Any) -> None:
        if msg.seq in self.drop_download_item:
            self.drop_download_item.discard(msg.seq)
            return
        if not 0 <= msg.seq < len(self.mission):
            self._ack(mav.MAV_MISSION_INVALID_SEQUENCE)
            return
        item = self.mission[msg.seq]
        self.send(
            self.mav.mission_item_int_encode(
                255,
                190,
                item.seq,
                item.frame,
                item.command,
                0,
                1,
                item.param1,
                item.param2,
                item.param3,
                item.param4,
                item.x,
                item.y,
                item.z,
                mav.MAV_MISSION_TYPE_MISSION,
            )
        )

    def _on_mission_clear_all(self, msg: Any) -> None:
        self.mission = []
        self._ack(mav.MAV_MISSION_ACCEPTED)

    def _param_value(self, name: str) -> None:
        if name in self.drop_param:
            self.drop_param.discard(name)
            return
        value, kind = self.params[name]
        index = sorted(self.params).index(name)
        self.send(self.mav.param_value_encode(name.encode(), value, kind, len(self.params), index))

    def _on_param_request_read(self, msg: Any) -> None:
        name = msg.param_id
        if msg.param_index >= 0:
            names = sorted(self.params)
            if msg.param_index >= len(names):
                return
            name = names[msg.param_index]
        if name in self.params:
            self._param_value(name)
        else:
            self._param_error(name)

    def _param_error(self, name: str) -> None:
        if self.param_errors:
            self.send(
                self.mav.param_error_encode(
                    255, 190, name.encode(), -1, mav.MAV_PARAM_ERROR_DOES_NOT_EXIST
                )
            )

    def _on_param_set(self, msg: Any) -> None:
        name = msg.param_id
        if name not in self.params:
            self._param_error(name)  # older ArduPilot: unanswered
            return
        kind = self.params[name][1]
        value = float(msg.param_value)
        if kind in INT_TYPES:
            value = float(int(value))  # the float carries the integer (C cast)
        value = min(value, self.param_clamp.get(name, value))
        self.params[name] = (value, kind)
        self._param_value(name)

    def _on_command_long(self, msg: Any) -> None:
        result = mav.MAV_RESULT_ACCEPTED
        if msg.command == mav.MAV_CMD_DO_SET_MODE:
            if self.mode != AUTO and int(msg.param2) == AUTO:  # resumed: this item again
                self._item_due = time.monotonic() + (self.item_seconds or 0.0)
            self.mode = int(msg.param2)
        elif msg.command == mav.MAV_CMD_COMPONENT_ARM_DISARM:
            self.armed = msg.param1 == 1
        elif msg.command == mav.MAV_CMD_MISSION_START:
            if len(self.mission) < 2 or not self.armed:
                result = mav.MAV_RESULT_FAILED
            else:
                self.mode = AUTO
                self.flying_seq = 1
                self._item_due = time.monotonic() + (self.item_seconds or 0.0)
                self.current(1)
        self.send(self.mav.command_ack_encode(msg.command, result, 0, 0, 255, 190))
        self._heartbeat()

    def _fly(self, now: float) -> None:
        if self.item_seconds is None or self.mode != AUTO or not self.flying_seq:
            return
        if now < self._item_due:
            return
        seq = self.flying_seq
        self.reached(seq)
        if seq + 1 < len(self.mission):
            self.flying_seq = seq + 1
            self._item_due = now + self.item_seconds
            self.current(seq + 1)
            return
        self.flying_seq = 0
        if self.mission[seq].command == mav.MAV_CMD_NAV_LAND:
            self.armed = False  # landed: ArduCopter disarms
        self.current(seq, mav.MISSION_STATE_COMPLETE)

    # ---- what the vehicle reports --------------------------------------------------------------

    def load(self, items: int) -> None:
        """Hold a mission of ``items`` waypoints (and home), as if another station uploaded it."""
        self.mission = [
            self.mav.mission_item_int_encode(
                255,
                190,
                seq,
                3,
                mav.MAV_CMD_NAV_WAYPOINT,
                0,
                1,
                0,
                0,
                0,
                0,
                473977420 + seq * 1000,
                85455940,
                10.0,
                0,
            )
            for seq in range(items + 1)
        ]

    def current(self, seq: int, state: int = mav.MISSION_STATE_ACTIVE) -> None:
        """Send MISSION_CURRENT."""
        total = max(len(self.mission) - 1, 0)  # without item 0, home: seq == total on the last
        self.send(self.mav.mission_current_encode(seq, total, state, 0))

    def reached(self, seq: int) -> None:
        """Send MISSION_ITEM_REACHED."""
        self.send(self.mav.mission_item_reached_encode(seq))
