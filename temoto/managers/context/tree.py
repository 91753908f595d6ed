"""The world-model tree of the Context Manager: items, their versions, and the merge rule.

:class:`ContextTree` is the pure data structure (no threads, no locks, no I/O); the
:class:`~temoto.managers.context.manager.ContextManager` wraps it with a lock and the fleet
sync. The tree is a map from item name to its newest *record*: an :class:`Item`, or a
:class:`Removal` (a tombstone). A record's version is ``(stamp_us, writer)``; a record
replaces the one held only if its version is greater (the newest wins; equal stamps are
ordered by the writer's name). That makes the map a last-writer-wins register per name: every
robot that has merged the same records holds the same map, whatever the order of arrival.

What the robots see is a deterministic function of that map, so it converges too:

* The local operations keep the invariants (a parent exists, no cycle, removing a parent is
  refused unless it cascades), but concurrent changes on two robots can still break them once
  merged: a child added under an item another robot removed, or two re-parents that close a
  cycle. Such items are *detached*: an item whose parent is not in the tree, or the oldest
  member (by version) of a cycle, whose parent link is ignored so the cycle is cut there.
  Nothing is dropped: detached items stay, keep their recorded parent (they re-attach when it
  appears), are listed by :meth:`ContextTree.detached`, and have no world pose.
* Queries (:meth:`~ContextTree.children`, :meth:`~ContextTree.subtree`) follow the attached
  links only.
"""

from __future__ import annotations

import collections
import hashlib
import json
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any, Final

from temoto.errors import ContextCycleError, ContextError, ContextItemNotFoundError
from temoto.managers.context.pose import Pose

__all__ = [
    "MAX_ATTRIBUTES_BYTES",
    "MAX_NAME_LEN",
    "ContextTree",
    "Item",
    "Record",
    "Removal",
    "check_item_name",
    "encode_attributes",
]

#: Longest item name (and maintainer, writer and type names).
MAX_NAME_LEN: Final = 256
#: Largest attributes object, as compact JSON in UTF-8 (keeps every record well inside one
#: LCM message).
MAX_ATTRIBUTES_BYTES: Final = 16_384
_MASK64: Final = (1 << 64) - 1


def check_item_name(what: str, value: object, *, empty: bool = False) -> str:
    """Check an item, type or robot name: 1 to 256 characters, no control characters.

    Args:
        what: The argument's description, for the error.
        value: The value.
        empty: Whether "" is allowed (a root's parent).

    Returns:
        The value.

    Raises:
        TypeError: If it is not a string.
        ValueError: If it is empty (unless allowed), too long, or has a control character.
    """
    if not isinstance(value, str):
        raise TypeError(f"{what} must be a string, got {type(value).__name__}")
    if not value:
        if empty:
            return value
        raise ValueError(f"{what} must not be empty")
    if len(value) > MAX_NAME_LEN:
        raise ValueError(f"{what} is {len(value)} characters long; at most {MAX_NAME_LEN}")
    if not value.isprintable():
        raise ValueError(f"{what} {value!r} has a control character")
    return value


def encode_attributes(attributes: Mapping[str, Any] | None) -> str:
    """User attributes as compact, key-sorted JSON.

    Args:
        attributes: A JSON object (string keys), or None for none.

    Returns:
        The JSON text (``"{}"`` for none).

    Raises:
        TypeError: If it is not a mapping or holds something JSON cannot represent.
        ValueError: If it holds NaN or infinity, or is larger than :data:`MAX_ATTRIBUTES_BYTES`.
    """
    if attributes is None:
        return "{}"
    if not isinstance(attributes, Mapping):
        raise TypeError(f"attributes must be a mapping, got {type(attributes).__name__}")
    text = json.dumps(dict(attributes), sort_keys=True, separators=(",", ":"), allow_nan=False)
    if len(text.encode()) > MAX_ATTRIBUTES_BYTES:
        raise ValueError(f"attributes take {len(text)} bytes; at most {MAX_ATTRIBUTES_BYTES}")
    return text


def _decode_attributes(text: str) -> str:
    """Check received attributes JSON; the canonical text. Raises ValueError."""
    try:
        value = json.loads(text)
    except (ValueError, RecursionError) as err:
        raise ValueError(f"attributes are not JSON: {err}") from None
    if not isinstance(value, dict):
        raise ValueError("attributes are not a JSON object")
    return encode_attributes(value)


@dataclass(frozen=True, slots=True)
class Item:
    """One item of the world model (a snapshot; the tree replaces it on every change).

    Attributes:
        name: Unique in the whole tree.
        type: ``map``, ``object``, ``robot``, ``component`` or any other non-empty string.
        parent: The parent item's name, "" for a root.
        pose: Relative to the parent (to the world for a root).
        maintainer: The robot that maintains the item.
        stamp_us: The wall clock of the last change, microseconds since the epoch.
        writer: The robot that made the last change.
        attributes_json: User attributes, compact key-sorted JSON (see :attr:`attributes`).
    """

    name: str
    type: str
    parent: str
    pose: Pose
    maintainer: str
    stamp_us: int
    writer: str
    attributes_json: str = "{}"

    @property
    def version(self) -> tuple[int, str]:
        """``(stamp_us, writer)``: the greater version wins."""
        return (self.stamp_us, self.writer)

    @property
    def attributes(self) -> dict[str, Any]:
        """The user attributes (a new dict on every access)."""
        value: dict[str, Any] = json.loads(self.attributes_json)
        return value

    def check(self) -> Item:
        """Check every field (for records received from other robots).

        Returns:
            The item, with canonical attributes.

        Raises:
            ValueError: If a field is invalid.
        """
        try:
            check_item_name("an item name", self.name)
            check_item_name("an item type", self.type)
            check_item_name("a parent name", self.parent, empty=True)
            check_item_name("a maintainer", self.maintainer)
            check_item_name("a writer", self.writer)
        except TypeError as err:
            raise ValueError(str(err)) from None
        if self.parent == self.name:
            raise ValueError(f"item {self.name!r} is its own parent")
        if not isinstance(self.pose, Pose):
            raise ValueError("the pose is not a Pose")
        if not 0 < self.stamp_us <= _MASK64 >> 1:
            raise ValueError(f"stamp {self.stamp_us} out of range")
        attributes = _decode_attributes(self.attributes_json)
        if attributes == self.attributes_json:
            return self
        return Item(
            self.name,
            self.type,
            self.parent,
            self.pose,
            self.maintainer,
            self.stamp_us,
            self.writer,
            attributes,
        )


@dataclass(frozen=True, slots=True)
class Removal:
    """A removed item (a tombstone): kept so that an older change cannot bring it back.

    Attributes:
        name: The item's name.
        stamp_us: When it was removed (wall clock, microseconds since the epoch).
        writer: The robot that removed it.
    """

    name: str
    stamp_us: int
    writer: str

    @property
    def version(self) -> tuple[int, str]:
        """``(stamp_us, writer)``."""
        return (self.stamp_us, self.writer)

    def check(self) -> Removal:
        """Check every field.

        Returns:
            The removal.

        Raises:
            ValueError: If a field is invalid.
        """
        try:
            check_item_name("an item name", self.name)
            check_item_name("a writer", self.writer)
        except TypeError as err:
            raise ValueError(str(err)) from None
        if not 0 < self.stamp_us <= _MASK64 >> 1:
            raise ValueError(f"stamp {self.stamp_us} out of range")
        return self


#: What the tree holds per name, and what travels between robots.
Record = Item | Removal


def _hash(item: Item) -> int:
    key = f"{item.name}\0{item.stamp_us}\0{item.writer}".encode()
    return int.from_bytes(hashlib.blake2b(key, digest_size=8).digest(), "big")


class ContextTree:
    """Items by name, with indexes by parent and by type; merges records by version.

    Not thread-safe: the Context Manager holds a lock around every call.
    """

    def __init__(self) -> None:
        self._items: dict[str, Item] = {}
        self._tombs: dict[str, Removal] = {}
        self._tomb_times: dict[str, float] = {}  # name -> local time it was stored (in order)
        self._children: dict[str, set[str]] = {}  # recorded parent -> live children
        self._by_type: dict[str, set[str]] = {}
        self._cut: dict[str, tuple[str, ...]] = {}  # cycle member whose link is ignored -> cycle
        self._cycle_of: dict[str, str] = {}  # cycle member -> the cut member of its cycle
        self._digest = 0

    def __len__(self) -> int:
        return len(self._items)

    def __contains__(self, name: object) -> bool:
        return name in self._items

    def __iter__(self) -> Iterator[str]:
        return iter(self._items)

    # ================================================================ merging

    def version(self, name: str) -> tuple[int, str] | None:
        """The version of the record held for a name (item or tombstone), or None."""
        record: Record | None = self._items.get(name) or self._tombs.get(name)
        return None if record is None else record.version

    def next_stamp(self, name: str, now_us: int) -> int:
        """The stamp for a local change of ``name``: the clock, but above the held version.

        A robot whose clock is behind the writer of an item can still change it.
        """
        held = self.version(name)
        return now_us if held is None or held[0] < now_us else held[0] + 1

    def merge(self, record: Record, now: float = 0.0) -> bool:
        """Apply a record if it is newer than the one held for its name.

        Args:
            record: A checked item or removal.
            now: The local monotonic time (when a tombstone was stored, for :meth:`expire`).

        Returns:
            Whether it was applied (False: stale, or the same version again).
        """
        held = self.version(record.name)
        if held is not None and held >= record.version:
            return False
        name = record.name
        old = self._items.pop(name, None)
        if old is not None:
            self._unindex(old)
        if self._tombs.pop(name, None) is not None:
            del self._tomb_times[name]
        if isinstance(record, Item):
            self._items[name] = record
            self._children.setdefault(record.parent, set()).add(name)
            self._by_type.setdefault(record.type, set()).add(name)
            self._digest = (self._digest + _hash(record)) & _MASK64
        else:
            self._tombs[name] = record
            self._tomb_times[name] = now
        self._relink(name)
        return True

    def expire(self, before: float) -> int:
        """Forget tombstones stored before a local time.

        Args:
            before: Local monotonic time.

        Returns:
            How many were forgotten.
        """
        gone = 0
        for name, stored in list(self._tomb_times.items()):
            if stored >= before:
                break  # stored in time order
            del self._tomb_times[name]
            del self._tombs[name]
            gone += 1
        return gone

    def _unindex(self, item: Item) -> None:
        siblings = self._children[item.parent]
        siblings.discard(item.name)
        if not siblings:
            del self._children[item.parent]
        same = self._by_type[item.type]
        same.discard(item.name)
        if not same:
            del self._by_type[item.type]
        self._digest = (self._digest - _hash(item)) & _MASK64

    def _relink(self, name: str) -> None:
        """After ``name`` changed: forget its old cycle, find the one it closes now (if any).

        Each item has one parent link, so an item is in at most one cycle, and a change of
        one item can only open or close a cycle through that item.
        """
        cut = self._cycle_of.get(name)
        if cut is not None:
            for member in self._cut.pop(cut):
                del self._cycle_of[member]
        item = self._items.get(name)
        if item is None:
            return
        path = [name]
        seen = {name}
        parent = item.parent
        while parent != name:
            node = self._items.get(parent)
            if node is None or parent in seen:
                return  # reaches a root, a missing parent, or another cycle
            seen.add(parent)
            path.append(parent)
            parent = node.parent
        oldest = min(path, key=lambda n: self._items[n].version)
        self._cut[oldest] = tuple(path)
        for member in path:
            self._cycle_of[member] = oldest

    # ================================================================ local changes

    def add(
        self,
        name: str,
        kind: str,
        parent: str,
        pose: Pose,
        maintainer: str,
        attributes_json: str,
        now_us: int,
        writer: str,
    ) -> Item:
        """Add a new item (checked; see ``ContextManager.add``)."""
        check_item_name("the item name", name)
        check_item_name("the item type", kind)
        check_item_name("the parent name", parent, empty=True)
        check_item_name("the maintainer", maintainer)
        if not isinstance(pose, Pose):
            raise TypeError(f"pose must be a Pose, got {pose.__class__.__name__}")
        if name in self._items:
            raise ContextError(f"item '{name}' exists already: update or move it instead")
        if parent == name:
            raise ContextCycleError(f"item '{name}' cannot be its own parent")
        if parent and parent not in self._items:
            raise ContextItemNotFoundError(
                f"cannot add '{name}': its parent '{parent}' is not in the world model"
            )
        stamp = self.next_stamp(name, now_us)
        item = Item(name, kind, parent, pose, maintainer, stamp, writer, attributes_json)
        self.merge(item)
        return item

    def update(
        self,
        name: str,
        *,
        kind: str | None,
        pose: Pose | None,
        maintainer: str | None,
        attributes_json: str | None,
        now_us: int,
        writer: str,
    ) -> Item:
        """Change an item's fields other than its parent (checked)."""
        old = self.get(name)
        if kind is not None:
            check_item_name("the item type", kind)
        if maintainer is not None:
            check_item_name("the maintainer", maintainer)
        if pose is not None and not isinstance(pose, Pose):
            raise TypeError(f"pose must be a Pose, got {pose.__class__.__name__}")
        item = Item(
            name,
            old.type if kind is None else kind,
            old.parent,
            old.pose if pose is None else pose,
            old.maintainer if maintainer is None else maintainer,
            self.next_stamp(name, now_us),
            writer,
            old.attributes_json if attributes_json is None else attributes_json,
        )
        self.merge(item)
        return item

    def move(self, name: str, parent: str, pose: Pose | None, now_us: int, writer: str) -> Item:
        """Re-parent an item (checked: the parent exists, no cycle)."""
        old = self.get(name)
        check_item_name("the parent name", parent, empty=True)
        if pose is not None and not isinstance(pose, Pose):
            raise TypeError(f"pose must be a Pose, got {pose.__class__.__name__}")
        if parent == name:
            raise ContextCycleError(f"item '{name}' cannot be its own parent")
        if parent:
            if parent not in self._items:
                raise ContextItemNotFoundError(
                    f"cannot move '{name}' under '{parent}': no such item in the world model"
                )
            seen: set[str] = set()
            up = parent
            while up and up not in seen:
                if up == name:
                    raise ContextCycleError(
                        f"cannot move '{name}' under '{parent}': '{parent}' is below '{name}'"
                    )
                seen.add(up)
                node = self._items.get(up)
                up = "" if node is None else node.parent
        if pose is None:
            pose = old.pose
            try:
                world = self.world_pose(name)
                base = self.world_pose(parent) if parent else Pose()
            except ContextError:
                pass  # detached: keep the relative pose
            else:
                pose = base.inverse().compose(world)
        item = Item(
            name,
            old.type,
            parent,
            pose,
            old.maintainer,
            self.next_stamp(name, now_us),
            writer,
            old.attributes_json,
        )
        self.merge(item)
        return item

    def remove(
        self, name: str, cascade: bool, now_us: int, writer: str, now: float
    ) -> list[Removal]:
        """Remove an item, and with ``cascade`` everything below it (children first)."""
        self.get(name)
        kids = self._children.get(name, ())
        if kids and not cascade:
            shown = ", ".join(sorted(kids)[:5]) + (", ..." if len(kids) > 5 else "")
            raise ContextError(
                f"cannot remove '{name}': it has {len(kids)} children ({shown});"
                " remove them first or ask for a cascade"
            )
        order: list[str] = []
        seen = {name}
        queue = collections.deque([name])
        while queue:
            node = queue.popleft()
            order.append(node)
            for child in self._children.get(node, ()):
                if child not in seen:
                    seen.add(child)
                    queue.append(child)
        removals = []
        for node in reversed(order):
            removal = Removal(node, self.next_stamp(node, now_us), writer)
            self.merge(removal, now)
            removals.append(removal)
        return removals

    # ================================================================ queries

    def get(self, name: str) -> Item:
        """An item by name.

        Raises:
            ContextItemNotFoundError: If there is none.
        """
        item = self._items.get(name)
        if item is None:
            raise ContextItemNotFoundError(f"no item '{name}' in the world model")
        return item

    def removed(self, name: str) -> Removal | None:
        """The tombstone of a removed item, or None."""
        return self._tombs.get(name)

    def is_detached(self, item: Item) -> bool:
        """Whether an item's parent link is not followed (parent missing, or a cut cycle)."""
        return bool(item.parent) and (item.parent not in self._items or item.name in self._cut)

    def find(self, kind: str) -> list[Item]:
        """The items of one type, sorted by name."""
        return [self._items[n] for n in sorted(self._by_type.get(kind, ()))]

    def types(self) -> dict[str, int]:
        """How many items of each type."""
        return {t: len(names) for t, names in sorted(self._by_type.items())}

    def children(self, name: str) -> list[Item]:
        """The attached children of an item ("" for the roots), sorted by name."""
        if name:
            self.get(name)
        return [self._items[c] for c in sorted(self._children.get(name, ())) if c not in self._cut]

    def subtree(self, name: str = "", depth: int | None = None) -> list[Item]:
        """An item and what is attached below it, breadth first; "" for the whole tree."""
        if depth is not None and (isinstance(depth, bool) or not isinstance(depth, int)):
            raise TypeError(f"depth must be an int or None, got {depth!r}")
        if depth is not None and depth < 0:
            raise ValueError(f"depth must be >= 0, got {depth}")
        level = [self.get(name)] if name else self.children("")
        out: list[Item] = []
        seen: set[str] = set()
        current = 0
        while level:
            out.extend(level)
            if depth is not None and current >= depth:
                break
            current += 1
            nxt: list[Item] = []
            for item in level:
                seen.add(item.name)
                for child in sorted(self._children.get(item.name, ())):
                    if child not in self._cut and child not in seen:
                        nxt.append(self._items[child])
            level = nxt
        return out

    def path(self, name: str) -> list[str]:
        """The names from the root down to an item.

        Raises:
            ContextItemNotFoundError: No such item.
            ContextError: The item or one above it is detached.
        """
        item = self.get(name)
        names = [name]
        while item.parent:
            if self.is_detached(item):
                raise ContextError(self._detached_why(name, item))
            item = self._items[item.parent]
            names.append(item.name)
        names.reverse()
        return names

    def world_pose(self, name: str) -> Pose:
        """An item's pose relative to its root (the poses composed up the tree).

        Raises:
            ContextItemNotFoundError: No such item.
            ContextError: The item or one above it is detached.
        """
        item = self.get(name)
        pose = item.pose
        while item.parent:
            if self.is_detached(item):
                raise ContextError(self._detached_why(name, item))
            item = self._items[item.parent]
            pose = item.pose.compose(pose)
        return pose

    def _detached_why(self, name: str, item: Item) -> str:
        above = "" if item.name == name else f" (above it, '{item.name}')"
        if item.name in self._cut:
            return f"'{name}' is detached{above}: a cycle of re-parents was cut there"
        return f"'{name}' is detached{above}: parent '{item.parent}' is not in the world model"

    def detached(self) -> list[Item]:
        """Items whose parent link is not followed, sorted by name."""
        names = set(self._cut)
        for parent, kids in self._children.items():
            if parent and parent not in self._items:
                names.update(kids)
        return [self._items[n] for n in sorted(names)]

    def items(self) -> list[Item]:
        """Every item, sorted by name."""
        return [self._items[n] for n in sorted(self._items)]

    def records(self) -> list[Record]:
        """Every item and tombstone, sorted by name (what a state answer carries)."""
        out: list[Record] = [*self._items.values(), *self._tombs.values()]
        out.sort(key=lambda r: r.name)
        return out

    def tombstones(self) -> int:
        """How many tombstones are kept."""
        return len(self._tombs)

    def digest(self) -> tuple[int, int]:
        """``(count, digest)`` of the items (tombstones not included)."""
        return len(self._items), self._digest
