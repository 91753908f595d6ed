"""The live Foxglove server: the recording's channels and the loaded displays, over WebSocket.

``docs/visualization.md``. :class:`FoxgloveServer` wraps the Foxglove SDK's WebSocket server
(``foxglove-sdk``, the optional extra ``temoto[foxglove]``, imported only when a server is
made) with its own SDK context, so two servers in one process never share a channel. Every
channel carries JSON with a JSON schema of :mod:`temoto.record.schemas`, so a live session
shows in Foxglove as a recording of the same process does.

:class:`LiveRecorder` is a :class:`~temoto.record.Recorder` whose messages go to the server
instead of a file: the same hooks, the same sampling, the same topics and messages as
``--record`` (it reuses them all; only the sink differs).

SDK caveats handled here (checked against ``foxglove-sdk`` 0.30): nothing is latched for a
client that subscribes late, so the last message of every channel is kept and logged again
when a client subscribes; two channels of one topic and schema would share one id (closing
either closes both), so there is at most one channel per topic; callbacks run on the SDK's
threads, so the maps are guarded by a lock; there is no authentication, so the default host
is ``127.0.0.1``.
"""

from __future__ import annotations

import json
import logging
import os
import threading
from dataclasses import dataclass
from typing import Any, Final

from temoto.clock import Clock
from temoto.errors import ConfigError
from temoto.managers.visualization.decode import DECODED_SCHEMAS
from temoto.managers.visualization.scene import SCENE_SCHEMA
from temoto.record.recorder import Recorder
from temoto.record.schemas import SCHEMAS, schema_bytes

__all__ = [
    "DEFAULT_HOST",
    "DEFAULT_PORT",
    "DISPLAY_SCHEMAS",
    "FoxgloveServer",
    "LiveRecorder",
    "import_foxglove",
]

logger = logging.getLogger(__name__)

#: Where the server listens unless told otherwise (the protocol has no authentication).
DEFAULT_HOST: Final = "127.0.0.1"
#: Foxglove's usual port (what the app proposes for a "Foxglove WebSocket" connection).
DEFAULT_PORT: Final = 8765
#: What the missing extra's error says.
INSTALL_HINT: Final = "pip install 'temoto[foxglove]'"


_STR: Final = {"type": "string"}
#: The displays' own schemas (the recording's are :data:`temoto.record.schemas.SCHEMAS`).
DISPLAY_SCHEMAS: Final[dict[str, dict[str, Any]]] = {
    "foxglove.SceneUpdate": SCENE_SCHEMA,
    **DECODED_SCHEMAS,
    "foxglove.PosesInFrame": {
        "title": "foxglove.PosesInFrame",
        "description": "An array of timestamped poses in a reference frame",
        "type": "object",
        "properties": {
            "timestamp": SCHEMAS["foxglove.PoseInFrame"]["properties"]["timestamp"],
            "frame_id": _STR,
            "poses": {
                "type": "array",
                "items": SCHEMAS["foxglove.PoseInFrame"]["properties"]["pose"],
            },
        },
    },
    "temoto.ComponentData": {
        "title": "temoto.ComponentData",
        "description": "One datagram of a component's output, as text (size: its bytes)",
        "type": "object",
        "properties": {
            "timestamp": SCHEMAS["temoto.RobotHealth"]["properties"]["timestamp"],
            "type": _STR,
            "component": _STR,
            "robot": _STR,
            "data": _STR,
            "size": {"type": "integer", "minimum": 0},
        },
    },
}


def _schema_data(name: str) -> bytes:
    """A schema of the recording or of the displays, as the channel's schema data."""
    if name in DISPLAY_SCHEMAS:
        return json.dumps(DISPLAY_SCHEMAS[name], separators=(",", ":")).encode()
    return schema_bytes(name)


def import_foxglove() -> Any:
    """The ``foxglove`` module of the SDK.

    Returns:
        The module.

    Raises:
        ConfigError: The SDK is not installed (one line naming the extra).
    """
    try:
        import foxglove
    except ImportError:
        raise ConfigError(
            f"the Foxglove server needs the foxglove-sdk package: {INSTALL_HINT}"
        ) from None
    return foxglove


@dataclass(eq=False)
class _Live:
    """One advertised channel and the last message logged on it (for late subscribers)."""

    channel: Any
    schema: str
    last: bytes | None = None
    last_ns: int | None = None


def _listener(fg: Any, server: FoxgloveServer) -> Any:
    """The SDK's server listener (its protocol's other callbacks do nothing)."""

    class Listener(fg.websocket.ServerListener):  # type: ignore[misc]
        def on_subscribe(self, client: Any, channel: Any) -> None:
            server._replay(int(channel.id))  # a late subscriber gets the last message

    return Listener()


class FoxgloveServer:
    """A Foxglove WebSocket server with one JSON channel per topic.

    Channels are advertised on first :meth:`publish` (or :meth:`advertise`) and unadvertised
    by :meth:`unadvertise`; a client that subscribes gets the channel's last message at once.
    Thread-safe.

    Args:
        host: The address to listen on (default localhost; the protocol has no authentication).
        port: The TCP port (0: any free port; :attr:`port` says which).
        name: The server's name in its ``serverInfo``.
        services: Declare the ``services`` capability (JSON requests), so that
            :meth:`add_services` may advertise some (the operator's commands,
            :mod:`~temoto.managers.visualization.commands`); off: clients can call nothing.

    Raises:
        ConfigError: The SDK is missing, or the server cannot listen there (the message names
            the address).
    """

    def __init__(
        self,
        host: str = DEFAULT_HOST,
        port: int = DEFAULT_PORT,
        *,
        name: str = "temoto",
        services: bool = False,
    ) -> None:
        fg = import_foxglove()
        self._fg = fg
        self._lock = threading.Lock()
        self._topics: dict[str, _Live] = {}
        self._ids: dict[int, _Live] = {}
        self._closed = False
        self._context = fg.Context()
        self.host = host
        try:
            self._server = fg.start_server(
                name=name,
                host=host,
                port=port,
                context=self._context,
                server_listener=_listener(fg, self),
                capabilities=[fg.websocket.Capability.Services] if services else [],
                supported_encodings=["json"] if services else None,
            )
        except Exception as err:
            raise ConfigError(f"foxglove server on {host}:{port}: {err}") from None
        self.port: int = int(self._server.port)

    @property
    def url(self) -> str:
        """The address a Foxglove client opens (``ws://HOST:PORT``)."""
        return f"ws://{self.host}:{self.port}"

    def __enter__(self) -> FoxgloveServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def topics(self) -> dict[str, str]:
        """The advertised topics and their schema names."""
        with self._lock:
            return {topic: live.schema for topic, live in self._topics.items()}

    def advertise(self, topic: str, schema: str) -> None:
        """Advertise ``topic`` with a schema of the recording's or :data:`DISPLAY_SCHEMAS` (once).

        Args:
            topic: The topic.
            schema: The schema's name.

        Raises:
            KeyError: An unknown schema.
            ValueError: The topic is advertised with another schema.
        """
        with self._lock:
            self._advertise(topic, schema)

    def _advertise(self, topic: str, schema: str) -> _Live | None:
        live = self._topics.get(topic)
        if live is not None:
            if live.schema != schema:
                raise ValueError(f"topic {topic} is advertised as {live.schema}, not {schema}")
            return live
        if self._closed:
            return None
        fg = self._fg
        channel = fg.Channel(
            topic,
            schema=fg.Schema(name=schema, encoding="jsonschema", data=_schema_data(schema)),
            message_encoding="json",
            context=self._context,
        )
        live = _Live(channel, schema)
        self._topics[topic] = live
        self._ids[int(channel.id())] = live
        return live

    def publish(
        self, topic: str, schema: str, message: dict[str, Any], log_time_ns: int | None = None
    ) -> None:
        """Log one message (JSON) on ``topic``, advertising it first if needed.

        Args:
            topic: The topic.
            schema: Its schema's name (a key of :data:`~temoto.record.schemas.SCHEMAS`).
            message: The message.
            log_time_ns: Its log time (ns since the epoch), or None for now.

        Raises:
            KeyError: An unknown schema.
            ValueError: A message that is not JSON (NaN, infinity), or a topic advertised with
                another schema.
        """
        data = json.dumps(message, ensure_ascii=False, allow_nan=False, default=str).encode()
        with self._lock:
            live = self._advertise(topic, schema)
            if live is None:
                return
            live.last, live.last_ns = data, log_time_ns
        # Outside the lock: the SDK's threads take it in on_subscribe.
        live.channel.log(data, log_time=log_time_ns)

    def unadvertise(self, topic: str) -> bool:
        """Close ``topic``'s channel (clients get an ``unadvertise``).

        Returns:
            Whether it was advertised.
        """
        with self._lock:
            live = self._topics.pop(topic, None)
            if live is None:
                return False
            self._ids.pop(int(live.channel.id()), None)
        live.channel.close()
        return True

    def add_json_services(
        self,
        services: list[tuple[str, dict[str, Any], dict[str, Any], Any]],
    ) -> None:
        """Advertise services with JSON requests and responses to the clients.

        Args:
            services: ``(name, request schema, response schema, handler)`` each: the schemas
                are JSON schemas (their ``title`` names them), the handler takes the SDK's
                request (its ``payload`` the JSON bytes) and returns the response's bytes, or
                raises (its text goes to the client as the call's failure).

        Raises:
            RuntimeError: The server was made without ``services=True``, or a name is taken.
        """
        fg = self._fg

        def schema(doc: dict[str, Any]) -> Any:
            data = json.dumps(doc, separators=(",", ":")).encode()
            encoded = fg.Schema(name=doc["title"], encoding="jsonschema", data=data)
            return fg.websocket.MessageSchema(encoding="json", schema=encoded)

        made = [
            fg.websocket.Service(
                name,
                schema=fg.websocket.ServiceSchema(
                    name.strip("/").replace("/", "."), request=schema(req), response=schema(resp)
                ),
                handler=handler,
            )
            for name, req, resp, handler in services
        ]
        self._server.add_services(made)

    def _replay(self, channel_id: int) -> None:
        """Log a channel's last message again (a client just subscribed to it)."""
        with self._lock:
            live = self._ids.get(channel_id)
            if live is None or live.last is None:
                return
            data, ns = live.last, live.last_ns
        live.channel.log(data, log_time=ns)

    def close(self) -> None:
        """Unadvertise every channel and stop the server; idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            lives = list(self._topics.values())
            self._topics.clear()
            self._ids.clear()
        for live in lives:
            live.channel.close()
        self._server.stop()


class LiveRecorder(Recorder):
    """The recorder of ``--record`` with a live Foxglove server for its sink.

    Everything a :class:`~temoto.record.Recorder` records (engine hooks, :meth:`capture_logs`,
    :meth:`sample`, :meth:`listen`) is published on the same topic with the same schema and
    message; the recorder's writer thread hands each one to the server instead of writing a
    file (the MCAP writer it still has writes to the null device).

    Args:
        server: Where the messages go.
        clock: Stamps the messages and paces the sampling (default: real time).
    """

    def __init__(self, server: FoxgloveServer, *, clock: Clock | None = None) -> None:
        self.server = server
        super().__init__(os.devnull, clock=clock)

    def _write(self, topic: str, schema: str, ns: int, message: dict[str, Any]) -> None:
        try:
            self.server.publish(topic, schema, message, ns)
        except ValueError as err:  # a NaN or an infinity: that message only
            logger.debug("live: message on %s not sent: %s", topic, err)
        except Exception as err:
            self._fail(err)
        else:
            self._counts[topic] = self._counts.get(topic, 0) + 1
