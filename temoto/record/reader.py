"""Reading a recording back: its messages, and the node transitions of its graph runs.

The file is read from its start, record by record, so a recording that was never finished (its
process killed with SIGKILL) still yields every message of the chunks it wrote; reading stops
where the file stops.
"""

from __future__ import annotations

import json
import struct
from pathlib import Path
from typing import Any, NamedTuple

from mcap.exceptions import McapError
from mcap.records import Channel, Footer, Message, Schema
from mcap.stream_reader import StreamReader

from temoto.errors import ConfigError

__all__ = ["RecordedMessage", "Transition", "read_messages", "read_transitions"]


class RecordedMessage(NamedTuple):
    """One message of a recording."""

    topic: str  #: its channel's topic (``/temoto/transitions`` ...)
    schema: str  #: its schema's name (``foxglove.Log`` ...)
    log_time_ns: int  #: when it was recorded, nanoseconds since the epoch
    data: dict[str, Any]  #: the decoded JSON message


class Transition(NamedTuple):
    """A node's state change, as ``Instrument.node_transition`` saw it."""

    time: float  #: when it was recorded, seconds since the epoch
    t: float  #: the engine's clock, seconds
    graph: str  #: the run's name
    node: str  #: ``<Name>_<instance id>``
    old: str  #: the state it left (``NodeState`` value)
    new: str  #: the state it entered
    result: str | None = None  #: the node's result on the change that ends its run


def read_messages(
    path: str | Path, topics: set[str] | None = None
) -> tuple[list[RecordedMessage], bool]:
    """Every message of a recording (or of some topics), in the order they were recorded.

    Args:
        path: An MCAP file written by :class:`~temoto.record.Recorder` (any MCAP file whose
            messages are JSON).
        topics: Only these topics (None: all).

    Returns:
        The messages, and whether the file is complete (it has its footer: the recorder was
        closed). An incomplete file yields what it holds up to where it stops.

    Raises:
        ConfigError: The file cannot be read, or is not an MCAP file (the message names it).
    """
    path = Path(path)
    messages: list[RecordedMessage] = []
    complete = False
    try:
        with path.open("rb") as stream:
            schemas: dict[int, str] = {}
            channels: dict[int, tuple[str, str]] = {}
            try:
                for record in StreamReader(stream, skip_magic=False).records:
                    if isinstance(record, Schema):
                        schemas[record.id] = record.name
                    elif isinstance(record, Channel):
                        channels[record.id] = (record.topic, schemas.get(record.schema_id, ""))
                    elif isinstance(record, Message):
                        topic, schema = channels[record.channel_id]
                        if topics is None or topic in topics:
                            data = json.loads(record.data)
                            messages.append(RecordedMessage(topic, schema, record.log_time, data))
                    elif isinstance(record, Footer):
                        complete = True
            except (McapError, EOFError, struct.error, KeyError) as err:
                if not messages and not channels:
                    raise ConfigError(f"{path}: not an MCAP recording ({err})") from None
            except ValueError as err:  # a JSON message that does not decode, a bad CRC
                if not messages:
                    raise ConfigError(f"{path}: not an MCAP recording ({err})") from None
    except OSError as err:
        raise ConfigError(f"{path}: {err.strerror or err}") from None
    messages.sort(key=lambda m: m.log_time_ns)
    return messages, complete


def read_transitions(path: str | Path) -> list[Transition]:
    """The node transitions of a recording, in order (for a replay of its graph runs).

    Args:
        path: A recording (``--record FILE.mcap``), finished or not.

    Returns:
        One :class:`Transition` per node state change.

    Raises:
        ConfigError: The file cannot be read or is not an MCAP recording.
    """
    messages, _ = read_messages(path, {"/temoto/transitions"})
    return [
        Transition(
            m.log_time_ns / 1e9,
            float(m.data.get("t", 0.0)),
            str(m.data["graph"]),
            str(m.data["node"]),
            str(m.data["old"]),
            str(m.data["new"]),
            str(m.data["result"]) if isinstance(m.data.get("result"), str) else None,
        )
        for m in messages
    ]
