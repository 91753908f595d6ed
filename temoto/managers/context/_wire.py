"""Records to and from ``context_item_t``, and chunking of record lists (private)."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from typing import Any, Final

from temoto.fleet.common import new
from temoto.lcm_types import context_item_t
from temoto.managers.context.pose import Pose
from temoto.managers.context.tree import Item, Record, Removal

__all__ = ["CHUNK_BYTES", "chunks", "from_wire", "to_wire"]

#: A state answer or a large change is cut into messages of about this many bytes (LCM
#: fragments anything over ~64 KB, and each fragment lost loses the message).
CHUNK_BYTES: Final = 48_000

# Fixed part of one encoded context_item_t: 7 doubles, an int64, a boolean, and 4 bytes of
# length plus a NUL per string (7 strings).
_FIXED: Final = 7 * 8 + 8 + 1 + 7 * 5


def to_wire(record: Record) -> Any:
    """A record as a ``context_item_t``."""
    msg = new(context_item_t)
    msg.name, msg.writer, msg.stamp_us = record.name, record.writer, record.stamp_us
    if isinstance(record, Removal):
        msg.removed = True
        msg.qw = 1.0
        msg.attributes = "{}"
        return msg
    msg.type, msg.parent, msg.maintainer = record.type, record.parent, record.maintainer
    p = record.pose
    msg.x, msg.y, msg.z, msg.qx, msg.qy, msg.qz, msg.qw = p.as_tuple()
    msg.attributes = record.attributes_json
    return msg


def from_wire(msg: Any) -> Record:
    """A received ``context_item_t`` as a checked record.

    Raises:
        ValueError: If a field is invalid.
    """
    if msg.removed:
        return Removal(msg.name, msg.stamp_us, msg.writer).check()
    pose = Pose(msg.x, msg.y, msg.z, msg.qx, msg.qy, msg.qz, msg.qw)
    item = Item(
        msg.name,
        msg.type,
        msg.parent,
        pose,
        msg.maintainer,
        msg.stamp_us,
        msg.writer,
        msg.attributes,
    )
    return item.check()


def _size(record: Record) -> int:
    if isinstance(record, Removal):
        return _FIXED + len(record.name.encode()) + len(record.writer.encode()) + 2
    return _FIXED + sum(
        len(s.encode())
        for s in (
            record.name,
            record.type,
            record.parent,
            record.maintainer,
            record.writer,
            record.attributes_json,
        )
    )


def chunks(records: Sequence[Record], limit: int = CHUNK_BYTES) -> Iterator[list[Any]]:
    """Cut records into lists of ``context_item_t`` of at most ``limit`` encoded bytes each.

    Yields at least one (possibly empty) list.
    """
    batch: list[Any] = []
    size = 0
    for record in records:
        n = _size(record)
        if batch and size + n > limit:
            yield batch
            batch, size = [], 0
        batch.append(to_wire(record))
        size += n
    yield batch
