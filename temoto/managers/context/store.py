"""The world model on disk: every record the tree took, replayed when the manager starts.

A :class:`WorldStore` is the registrar's :class:`~temoto.core.registrar.journal.Journal` (an
append-only, checksummed file that survives SIGKILL; torn tails are cut, corruption is refused)
holding one JSON object per record the tree took, local changes and records merged from other
robots alike:

* an item: ``{"op": "item", "name", "type", "parent", "pose": [x, y, z, qx, qy, qz, qw],
  "maintainer", "stamp_us", "writer", "attributes"}`` (``attributes`` is the item's compact JSON
  text);
* a removal: ``{"op": "removal", "name", "stamp_us", "writer"}``.

Records merge by version (last writer wins, see ``docs/context-manager.md``), so replaying them
in any order rebuilds the same tree, and a record written twice changes nothing. When the file
holds many more records than the tree (every change of an item appends one), the manager
rewrites it with the tree's current records (:meth:`WorldStore.compact`, atomic).
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any, Final, Literal

from temoto.core.registrar.journal import Journal
from temoto.errors import CatalogCorruptError
from temoto.managers.context.pose import Pose
from temoto.managers.context.tree import Item, Record, Removal

__all__ = ["WorldStore", "record_from_json", "record_to_json"]

logger = logging.getLogger(__name__)

#: Rewrite the file once it holds this many more records than twice the tree's.
COMPACT_SLACK: Final = 1024


def record_to_json(record: Record) -> dict[str, Any]:
    """A record as the JSON object the store writes.

    Args:
        record: An item or a removal.

    Returns:
        The object (see the module docstring).
    """
    if isinstance(record, Removal):
        return {
            "op": "removal",
            "name": record.name,
            "stamp_us": record.stamp_us,
            "writer": record.writer,
        }
    return {
        "op": "item",
        "name": record.name,
        "type": record.type,
        "parent": record.parent,
        "pose": list(record.pose.as_tuple()),
        "maintainer": record.maintainer,
        "stamp_us": record.stamp_us,
        "writer": record.writer,
        "attributes": record.attributes_json,
    }


def record_from_json(value: Mapping[str, Any]) -> Record:
    """A stored object as a checked record.

    Args:
        value: What :func:`record_to_json` made.

    Returns:
        The item or removal.

    Raises:
        ValueError: A field is missing or invalid.
    """
    try:
        op = value["op"]
        if op == "removal":
            return Removal(value["name"], value["stamp_us"], value["writer"]).check()
        if op != "item":
            raise ValueError(f"unknown op {op!r}")
        pose = value["pose"]
        if not isinstance(pose, list) or len(pose) != 7:
            raise ValueError(f"pose must be a list of 7 numbers, got {pose!r}")
        item = Item(
            value["name"],
            value["type"],
            value["parent"],
            Pose(*pose),
            value["maintainer"],
            value["stamp_us"],
            value["writer"],
            value["attributes"],
        )
    except KeyError as err:
        raise ValueError(f"missing field {err}") from None
    except TypeError as err:
        raise ValueError(str(err)) from None
    return item.check()


class WorldStore:
    """The journal of one robot's world model (see the module docstring).

    Args:
        path: The file (created if missing).
        fsync: ``"group"`` (default: synced in the background at most 0.1 s after a write),
            ``"always"`` or ``"never"`` (tests), as for the registrar's journal.
    """

    def __init__(
        self, path: str | Path, *, fsync: Literal["group", "always", "never"] = "group"
    ) -> None:
        self._journal = Journal(path, fsync=fsync)

    @property
    def path(self) -> Path:
        """The file."""
        return self._journal.path

    @property
    def record_count(self) -> int:
        """Records in the file (written since the last compaction, or restored)."""
        return self._journal.record_count

    def open(self) -> list[Record]:
        """Open (or create) the file and read every record in it.

        Returns:
            The records, oldest first.

        Raises:
            CatalogCorruptError: The file is damaged beyond a torn tail, or holds a record
                that is not a valid item or removal (named by its position).
            ResourceBusyError: Another process has the file open.
            OSError: The file cannot be opened or created.
        """
        records: list[Record] = []
        for index, value in enumerate(self._journal.open()):
            try:
                records.append(record_from_json(value))
            except ValueError as err:
                self._journal.close()
                raise CatalogCorruptError(
                    f"{self.path}: record {index + 1} is not an item or a removal: {err}"
                ) from None
        return records

    def append(self, records: Iterable[Record]) -> None:
        """Write records the tree took (one ``write`` each; they survive SIGKILL at once).

        Args:
            records: The records.

        Raises:
            OSError: The file cannot be written (disk full, ...).
        """
        for record in records:
            self._journal.append(record_to_json(record))

    def should_compact(self, live: int) -> bool:
        """Whether the file is worth rewriting for a tree of ``live`` records.

        Args:
            live: Records the tree holds (items and remembered removals).

        Returns:
            True when the file holds many more records than that.
        """
        return self._journal.record_count > 2 * live + COMPACT_SLACK

    def compact(self, records: Iterable[Record]) -> None:
        """Replace the file with these records (atomic: the old or the new file survives).

        Args:
            records: The tree's current records.

        Raises:
            OSError: The new file cannot be written (the old one stays).
        """
        self._journal.rewrite(record_to_json(r) for r in records)

    def close(self) -> None:
        """Sync and close the file. Idempotent; a failed final sync is logged."""
        try:
            self._journal.close()
        except OSError as err:
            logger.warning("%s: the last changes may not be on disk: %s", self.path, err)
