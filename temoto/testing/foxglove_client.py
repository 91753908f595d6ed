"""An independent client of the Foxglove WebSocket protocol (not the SDK), on ``websockets``.

Written from the protocol's specification, ``foxglove/ws-protocol`` ``docs/spec.md``
(https://github.com/foxglove/ws-protocol/blob/main/docs/spec.md): text frames are JSON objects
with an ``op`` (``serverInfo``, ``advertise``, ``unadvertise`` from the server; ``subscribe``
from the client, ``subscriptions: [{id, channelId}]``); a Message Data frame is binary, opcode
``0x01``, then the subscription id (uint32) and the receive timestamp (uint64, ns), little
endian, then the payload in the channel's encoding. Services: the server's ``advertiseServices``
(``services: [{id, name, type, request, response}]``); a Service Call Request is binary,
opcode ``0x02``, then the service id, the call id and the encoding's length (uint32 each),
the encoding, the payload; its answer is a binary Service Call Response (opcode ``0x03``, the
same layout) or a text ``serviceCallFailure`` (``serviceId``, ``callId``, ``message``).

The SDK's server accepts the subprotocol ``foxglove.sdk.v1`` only (``foxglove-sdk`` 0.30; the
spec's ``foxglove.websocket.v1`` alone is refused with 400), so the client offers both.
"""

from __future__ import annotations

import json
import struct
import time
from dataclasses import dataclass
from typing import Any

from websockets.sync.client import ClientConnection, connect

SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]
MESSAGE_DATA = 0x01
SERVICE_CALL_REQUEST = 0x02
SERVICE_CALL_RESPONSE = 0x03


@dataclass
class Message:
    """A Message Data frame: which subscription, when (ns), the decoded JSON payload."""

    subscription: int
    receive_ns: int
    payload: dict[str, Any]
    at: float  # time.monotonic() when read


class FoxgloveClient:
    """A minimal protocol client: reads frames, keeps the server's channels by id and topic."""

    def __init__(self, url: str, timeout: float = 5.0) -> None:
        self._connection = connect(url, subprotocols=SUBPROTOCOLS, open_timeout=timeout)  # type: ignore[arg-type]
        self.ws: ClientConnection = self._connection.__enter__()
        self.server_info: dict[str, Any] = {}
        self.channels: dict[int, dict[str, Any]] = {}
        self.events: list[tuple[float, str, Any]] = []  # (monotonic, op, topic or message)
        self.messages: list[Message] = []
        self._subs: dict[int, int] = {}  # subscription id -> channel id
        self._next_sub = 1
        self.services: dict[str, dict[str, Any]] = {}  # name -> the advertised service
        self.answers: dict[int, tuple[bool, Any]] = {}  # call id -> (ok, JSON | failure text)
        self._next_call = 1

    def close(self) -> None:
        self._connection.__exit__(None, None, None)

    def __enter__(self) -> FoxgloveClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def topics(self) -> dict[str, str]:
        """Advertised (and not unadvertised) topics -> schema names."""
        return {c["topic"]: c["schemaName"] for c in self.channels.values()}

    def channel_id(self, topic: str) -> int:
        return next(i for i, c in self.channels.items() if c["topic"] == topic)

    def subscribe(self, topic: str) -> int:
        """Subscribe to ``topic``'s channel; returns the subscription id."""
        sub = self._next_sub
        self._next_sub += 1
        channel = self.channel_id(topic)
        self._subs[sub] = channel
        self.ws.send(
            json.dumps({"op": "subscribe", "subscriptions": [{"id": sub, "channelId": channel}]})
        )
        return sub

    def read_one(self, timeout: float) -> None:
        frame = self.ws.recv(timeout=timeout)
        now = time.monotonic()
        if isinstance(frame, bytes) and frame[0] == SERVICE_CALL_RESPONSE:
            _service, call, n = struct.unpack_from("<III", frame, 1)
            self.answers[call] = (True, json.loads(frame[13 + n :]))
            return
        if isinstance(frame, bytes):
            assert frame[0] == MESSAGE_DATA, f"unexpected binary opcode {frame[0]}"
            sub, ns = struct.unpack_from("<IQ", frame, 1)
            msg = Message(sub, ns, json.loads(frame[13:]), now)
            self.messages.append(msg)
            self.events.append((now, "message", msg))
            return
        body = json.loads(frame)
        op = body["op"]
        if op == "serverInfo":
            self.server_info = body
        elif op == "advertise":
            for channel in body["channels"]:
                self.channels[channel["id"]] = channel
                self.events.append((now, "advertise", channel["topic"]))
        elif op == "advertiseServices":
            for service in body["services"]:
                self.services[service["name"]] = service
        elif op == "unadvertiseServices":
            gone = set(body["serviceIds"])
            self.services = {k: v for k, v in self.services.items() if v["id"] not in gone}
        elif op == "serviceCallFailure":
            self.answers[body["callId"]] = (False, body["message"])
        elif op == "unadvertise":
            for cid in body["channelIds"]:
                channel = self.channels.pop(cid, None)
                if channel is not None:
                    self.events.append((now, "unadvertise", channel["topic"]))

    def wait(self, predicate: Any, timeout: float = 10.0) -> None:
        """Read frames until ``predicate(self)`` holds."""
        deadline = time.monotonic() + timeout
        while not predicate(self):
            left = deadline - time.monotonic()
            assert left > 0, f"timed out; topics {sorted(self.topics())}"
            try:
                self.read_one(left)
            except TimeoutError:
                continue

    def call(self, service: str, request: Any, timeout: float = 10.0) -> tuple[bool, Any]:
        """Call an advertised service with a JSON request; wait for its answer.

        Returns:
            ``(True, the response's JSON)`` or ``(False, the failure's message)``.
        """
        self.wait(lambda c: service in c.services, timeout)
        call = self._next_call
        self._next_call += 1
        encoding = b"json"
        head = struct.pack("<BIII", SERVICE_CALL_REQUEST, self.services[service]["id"], call, 4)
        self.ws.send(head + encoding + json.dumps(request).encode())
        self.wait(lambda c: call in c.answers, timeout)
        return self.answers[call]

    def first_message(self, sub: int, timeout: float = 10.0) -> Message:
        self.wait(lambda c: any(m.subscription == sub for m in c.messages), timeout)
        return next(m for m in self.messages if m.subscription == sub)
