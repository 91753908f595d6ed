"""The Context Manager: a world model shared by the fleet (docs/design.md §6, thesis demo 5).

One :class:`ContextManager` runs per robot. It holds a :class:`~.tree.ContextTree` of items —
maps, objects, robots, components — each with a pose relative to its parent, and keeps it
equal to every other robot's over the fleet link, on the channel :data:`CONTEXT_CHANNEL`:

``context_update_t``
    A local change is published at once (one record per changed item: a cascade removal sends
    all of them). The same message carries a whole tree, in chunks of about 48 KB, answering a
    request.
``context_request_t``
    Sent when the manager starts ("send me your trees": every robot answers, so a late joiner
    gets the tree within one round trip), and to one robot whose digest stayed different from
    ours for two digests in a row (a change was missed).
``context_digest_t``
    Every ``period_s``: the count of items and an order-independent hash of their versions.

Receivers merge every record by version (:mod:`temoto.managers.context.tree`): the newest
wins, equal stamps are ordered by the writer's name, removals are tombstones kept for
``tombstone_s``. Every robot that has merged the same records holds the same tree, whatever
the order of arrival, so concurrent conflicting changes converge.

The manager is also the registrar server ``"context"`` (:class:`MaintainRequest`): a
resource is an item this robot maintains while the resource is held; the item is added (or
taken over) on load and removed when the last holder releases it. An action that acquires one
keeps the item in the world model exactly as long as its graph runs.

Threads: ``temoto-context`` sends digests and state answers and forgets old tombstones;
``temoto-context-calls`` runs the change listeners (:meth:`ContextManager.listen`). Bad
messages (undecodable, wrong type, invalid fields, our own robot's name) are counted in
:attr:`ContextManager.stats` and dropped, never raised.

Code: the synchronisation (sending, the timer, receiving and merging) is
:mod:`~temoto.managers.context.sync` (:class:`~temoto.managers.context.sync.ContextSync`, a base
of the manager); this module holds the manager's state, its local changes and queries, the
listeners, the world store and the registrar server.
"""

from __future__ import annotations

import json
import logging
import threading
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, Final

from temoto.clock import Clock, MonotonicClock
from temoto.core.registrar import LoadContext, Registrar, ResourceServer
from temoto.errors import ContextError
from temoto.fleet.common import CallQueue, Closing, check_seconds
from temoto.managers.context.pose import Pose
from temoto.managers.context.store import WorldStore
from temoto.managers.context.sync import CONTEXT_CHANNEL, ContextSync
from temoto.managers.context.tree import (
    ContextTree,
    Item,
    Record,
    Removal,
    check_item_name,
    encode_attributes,
)

if TYPE_CHECKING:
    from temoto.transport.link import FleetLink

__all__ = [
    "CONTEXT_CHANNEL",
    "CONTEXT_STATS",
    "Change",
    "ContextManager",
    "MaintainRequest",
    "MaintainResponse",
]

logger = logging.getLogger(__name__)


#: The counters of :attr:`ContextManager.stats`.
CONTEXT_STATS: Final = (
    "changes_sent",  # context_update_t with local changes
    "states_sent",  # context_update_t chunks answering a request
    "updates_received",  # context_update_t received (changes and state chunks)
    "updates_refused",  # context_update_t from a member the fleet policy denies world.publish
    "records_applied",  # received records newer than ours
    "records_stale",  # received records not newer than ours (duplicates, late, lost races)
    "records_invalid",  # received records with invalid fields (dropped)
    "store_errors",  # records that could not be written to the world store (disk full, ...)
    "requests_sent",
    "requests_received",
    "digests_sent",
    "digests_received",
    "digest_mismatches",  # digests differing from ours (a request follows if it persists)
    "decode_errors",  # payloads that codec.decode refused
    "unexpected",  # wrong type for the channel, empty names, our own robot name
    "impostor",  # naming another robot than their authenticated sender (docs/security.md)
    "send_errors",  # sends that failed (logged)
    "callback_errors",  # listener callbacks that raised (logged)
    "tombstones_expired",
)


@dataclass(frozen=True, slots=True)
class Change:
    """What a listener is told: items that changed (added, updated, moved or removed).

    Attributes:
        names: The items' names.
        robot: The robot whose message brought the change (this robot for a local change).
    """

    names: tuple[str, ...]
    robot: str


@dataclass(frozen=True)
class MaintainRequest:
    """A registrar request: keep an item in the world model while the resource is held.

    Attributes:
        item: The item's name.
        type: Its type.
        parent: Its parent ("" for a root); must exist.
        pose: ``(x, y, z, qx, qy, qz, qw)`` relative to the parent.
        attributes: A JSON object, as text.
        cascade: On release, remove the items below it too (else they are kept and the item
            stays while it has children).
    """

    item: str
    type: str = "object"
    parent: str = ""
    pose: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
    attributes: str = "{}"
    cascade: bool = False

    def __post_init__(self) -> None:
        object.__setattr__(self, "pose", tuple(self.pose))  # JSON gives lists back


@dataclass(frozen=True)
class MaintainResponse:
    """A maintained item.

    Attributes:
        item: Its name.
        stamp_us: The version stamp of the load's change.
    """

    item: str
    stamp_us: int


class ContextManager(ContextSync, ResourceServer[MaintainRequest, MaintainResponse], Closing):
    """One robot's world model, kept equal to the fleet's (see the module docstring).

    Args:
        robot: This robot's name: the writer of its changes, the default maintainer.
        link: The fleet link to synchronise over, or None for a world model of one robot.
        registrar: Registers the manager as the server ``"context"`` here, if given.
        period_s: Seconds between digests.
        tombstone_s: Seconds a removal is remembered (a change older than the removal that
            arrives within this time cannot bring the item back).
        clock: Monotonic time (periods, tombstones) and wall time (the stamps of changes).
        queue_capacity: Messages waiting for the receive handler at most (older ones are
            dropped; the digests repair what is lost).
        store: A file that keeps the world model across restarts (``store.py``): read at
            start, every record the tree takes appended at once. None: memory only.

    Raises:
        ValueError: If ``robot`` is not a valid name or a duration is not positive.
        TransportError: If the link's transport is closed.
        CatalogCorruptError: The store is damaged (beyond a torn last record).
        ResourceBusyError: Another process has the store open.
        OSError: The store cannot be opened or created.
    """

    name: ClassVar[str] = "context"
    request_type: ClassVar[type[Any]] = MaintainRequest
    response_type: ClassVar[type[Any]] = MaintainResponse

    def __init__(
        self,
        robot: str,
        *,
        link: FleetLink | None = None,
        registrar: Registrar | None = None,
        period_s: float = 1.0,
        tombstone_s: float = 600.0,
        clock: Clock | None = None,
        queue_capacity: int = 4096,
        store: str | Path | None = None,
    ) -> None:
        self._robot = check_item_name("robot", robot)
        self.period_s = check_seconds("period_s", period_s)
        self.tombstone_s = check_seconds("tombstone_s", tombstone_s)
        self._clock: Clock = clock or MonotonicClock()
        self._init_sync(link)
        self._lock = threading.Lock()
        self._wake = threading.Condition(self._lock)
        # Guarded by _lock.
        self._tree = ContextTree()
        self._closed = False
        self._counts = dict.fromkeys(CONTEXT_STATS, 0)
        self._listeners: list[Callable[[Change], None]] = []
        self._store: WorldStore | None = None
        if store is not None:
            self._restore(WorldStore(store))  # before anything runs: nothing to undo on error
        self._calls = CallQueue("temoto-context-calls", "a Context Manager listener")
        try:
            self._start_sync(queue_capacity)
        except BaseException:
            self._calls.close()
            raise
        if registrar is not None:
            registrar.register(self)

    def __repr__(self) -> str:
        state = "closed" if self._closed else "open"
        return f"<ContextManager robot={self._robot!r} items={len(self._tree)} {state}>"

    # ================================================================ properties

    @property
    def robot(self) -> str:
        """This robot's name."""
        return self._robot

    @property
    def stats(self) -> dict[str, int]:
        """A copy of the counters, one per name in :data:`CONTEXT_STATS`."""
        with self._lock:
            counts = dict(self._counts)
        counts["callback_errors"] += self._calls.errors
        return counts

    # ================================================================ changes

    def add(
        self,
        name: str,
        kind: str = "object",
        parent: str = "",
        pose: Pose | None = None,
        *,
        maintainer: str | None = None,
        attributes: Mapping[str, Any] | None = None,
    ) -> Item:
        """Add an item.

        Args:
            name: Unique in the tree.
            kind: The type: ``map``, ``object``, ``robot``, ``component`` or another
                non-empty string.
            parent: The parent item ("" for a root); it must exist.
            pose: Relative to the parent (default: the parent's origin).
            maintainer: The robot that maintains it (default: this robot).
            attributes: A JSON object of user data.

        Returns:
            The item as stored.

        Raises:
            ContextError: An item of that name exists (the tree is unchanged).
            ContextItemNotFoundError: The parent does not exist.
            ContextCycleError: The item names itself as its parent.
            ValueError: A name is empty, too long or has control characters; the attributes
                hold NaN or are too large.
            TypeError: An argument has the wrong type.
        """
        attrs = encode_attributes(attributes)
        with self._lock:
            self._check_open()
            item = self._tree.add(
                name,
                kind,
                parent,
                Pose() if pose is None else pose,
                self._robot if maintainer is None else maintainer,
                attrs,
                self._now_us(),
                self._robot,
            )
            self._persist([item])
        self._changed([item])
        return item

    def update(
        self,
        name: str,
        *,
        pose: Pose | None = None,
        kind: str | None = None,
        maintainer: str | None = None,
        attributes: Mapping[str, Any] | None = None,
    ) -> Item:
        """Change an item's pose, type, maintainer or attributes (None: keep).

        Args:
            name: The item.
            pose: The new pose, relative to its parent.
            kind: The new type.
            maintainer: The new maintainer.
            attributes: The new attributes (they replace the old ones).

        Returns:
            The item as stored.

        Raises:
            ContextItemNotFoundError: No such item.
            ValueError: An invalid name or attributes.
            TypeError: An argument has the wrong type.
        """
        attrs = None if attributes is None else encode_attributes(attributes)
        with self._lock:
            self._check_open()
            item = self._tree.update(
                name,
                kind=kind,
                pose=pose,
                maintainer=maintainer,
                attributes_json=attrs,
                now_us=self._now_us(),
                writer=self._robot,
            )
            self._persist([item])
        self._changed([item])
        return item

    def move(self, name: str, parent: str, pose: Pose | None = None) -> Item:
        """Re-parent an item (what is below it moves with it).

        Args:
            name: The item.
            parent: The new parent ("" for a root); it must exist and not be below the item.
            pose: The pose relative to the new parent; None keeps the item where it is in the
                world (its relative pose is recomputed), or keeps the relative pose when a
                world pose is unknown (detached).

        Returns:
            The item as stored.

        Raises:
            ContextItemNotFoundError: No such item or no such parent.
            ContextCycleError: The parent is the item or below it.
        """
        with self._lock:
            self._check_open()
            item = self._tree.move(name, parent, pose, self._now_us(), self._robot)
            self._persist([item])
        self._changed([item])
        return item

    def remove(self, name: str, *, cascade: bool = False) -> list[str]:
        """Remove an item; with ``cascade``, everything below it too.

        Args:
            name: The item.
            cascade: Remove the subtree; otherwise an item with children is refused.

        Returns:
            The removed names, children before their parents.

        Raises:
            ContextItemNotFoundError: No such item.
            ContextError: It has children and ``cascade`` is false (nothing is removed).
        """
        with self._lock:
            self._check_open()
            removals = self._tree.remove(
                name, bool(cascade), self._now_us(), self._robot, self._clock.monotonic()
            )
            self._persist(removals)
        self._changed(removals)
        return [r.name for r in removals]

    def _now_us(self) -> int:
        return round(self._clock.time() * 1e6)

    def _check_open(self) -> None:
        if self._closed:
            raise ContextError(f"the Context Manager of {self._robot!r} is closed")

    def _changed(self, records: Sequence[Record]) -> None:
        """Publish local changes and tell the listeners (lock not held)."""
        self._publish(records, "", "changes_sent")
        self._notify(tuple(r.name for r in records), self._robot)

    def _restore(self, store: WorldStore) -> None:
        """Rebuild the tree from the store's records (at start, before any thread runs)."""
        records = store.open()
        now = self._clock.monotonic()
        for record in records:
            self._tree.merge(record, now)
        self._store = store
        logger.info(
            "context %r: %d items restored from %s (%d records)",
            self._robot,
            len(self._tree),
            store.path,
            len(records),
        )
        self._compact()

    def _persist(self, records: Sequence[Record]) -> None:
        """Write records the tree took to the store (lock held); failures are counted."""
        store = self._store
        if store is None or not records:
            return
        try:
            store.append(records)
        except (OSError, RuntimeError) as err:  # RuntimeError: closed meanwhile
            self._counts["store_errors"] += len(records)
            if self._counts["store_errors"] == len(records):  # the first failure
                logger.error("context %r: cannot write %s: %s", self._robot, store.path, err)
            return
        self._compact()

    def _compact(self) -> None:
        """Rewrite the store when it holds many more records than the tree (lock held)."""
        store = self._store
        if store is None:
            return
        records = self._tree.records()
        if not store.should_compact(len(records)):
            return
        try:
            store.compact(records)
        except OSError as err:
            logger.warning("context %r: cannot compact %s: %s", self._robot, store.path, err)

    # ================================================================ queries

    def get(self, name: str) -> Item:
        """An item by name.

        Raises:
            ContextItemNotFoundError: No such item.
        """
        with self._lock:
            return self._tree.get(name)

    def __contains__(self, name: object) -> bool:
        with self._lock:
            return name in self._tree

    def __len__(self) -> int:
        with self._lock:
            return len(self._tree)

    def find(self, kind: str) -> list[Item]:
        """The items of one type, sorted by name."""
        with self._lock:
            return self._tree.find(kind)

    def types(self) -> dict[str, int]:
        """How many items there are of each type."""
        with self._lock:
            return self._tree.types()

    def children(self, name: str = "") -> list[Item]:
        """The attached children of an item ("" for the roots), sorted by name.

        Raises:
            ContextItemNotFoundError: No such item.
        """
        with self._lock:
            return self._tree.children(name)

    def subtree(self, name: str = "", depth: int | None = None) -> list[Item]:
        """An item and the items attached below it, breadth first, siblings by name.

        Args:
            name: The top item; "" for the whole tree (every root and what is below).
            depth: How many levels below the top to include (0: the top only; for "" the
                roots are level 0); None for all.

        Returns:
            The items.

        Raises:
            ContextItemNotFoundError: No such item.
            ValueError: A negative depth.
        """
        with self._lock:
            return self._tree.subtree(name, depth)

    def path(self, name: str) -> list[str]:
        """The names from the item's root down to the item.

        Raises:
            ContextItemNotFoundError: No such item.
            ContextError: The item or one above it is detached.
        """
        with self._lock:
            return self._tree.path(name)

    def world_pose(self, name: str) -> Pose:
        """An item's pose in its root's frame (the relative poses composed up the tree).

        Raises:
            ContextItemNotFoundError: No such item.
            ContextError: The item or one above it is detached (its chain has no root).
        """
        with self._lock:
            return self._tree.world_pose(name)

    def detached(self) -> list[Item]:
        """Items whose parent link is not followed (see the tree module).

        Their parent was removed by another robot, or a cycle of concurrent re-parents was
        cut there.
        """
        with self._lock:
            return self._tree.detached()

    def removed(self, name: str) -> Removal | None:
        """The tombstone of a removed item, if it is still remembered."""
        with self._lock:
            return self._tree.removed(name)

    def items(self) -> list[Item]:
        """Every item, sorted by name."""
        with self._lock:
            return self._tree.items()

    def dump(self) -> list[Record]:
        """Every item and remembered removal, sorted by name (compare robots with it)."""
        with self._lock:
            return self._tree.records()

    def digest(self) -> tuple[int, int]:
        """``(count, digest)`` as the digests carry them: equal on robots with equal trees."""
        with self._lock:
            return self._tree.digest()

    def listen(self, callback: Callable[[Change], None]) -> Callable[[], None]:
        """Be told of every change, local or received.

        Callbacks run on the ``temoto-context-calls`` thread, in order; they may call the
        manager.

        Args:
            callback: Called with a :class:`Change`.

        Returns:
            A function that ends the subscription (idempotent).
        """
        with self._lock:
            self._listeners.append(callback)

        def cancel() -> None:
            with self._lock:
                if callback in self._listeners:
                    self._listeners.remove(callback)

        return cancel

    def _notify(self, names: tuple[str, ...], robot: str) -> None:
        with self._lock:
            listeners = list(self._listeners)
        if not listeners or not names:
            return
        change = Change(names, robot)

        def call() -> None:
            for callback in listeners:
                try:
                    callback(change)
                except Exception:
                    with self._lock:
                        self._counts["callback_errors"] += 1
                    logger.exception("a Context Manager listener raised")

        self._calls.put(call)

    # ================================================================ registrar server

    def on_load(self, request: MaintainRequest, ctx: LoadContext) -> MaintainResponse:
        """Add the item (or take it over: move and update it), maintained by this robot."""
        pose = Pose(*request.pose)
        try:
            attributes = _json_object(request.attributes)
            encode_attributes(attributes)
        except (TypeError, ValueError) as err:
            raise ValueError(f"item '{request.item}': bad attributes: {err}") from None
        with self._lock:
            self._check_open()
            exists = request.item in self._tree
        if not exists:
            item = self.add(
                request.item,
                request.type,
                request.parent,
                pose,
                attributes=attributes,
            )
        else:
            self.move(request.item, request.parent, pose)
            item = self.update(
                request.item,
                kind=request.type,
                maintainer=self._robot,
                attributes=attributes,
            )
        return MaintainResponse(item.name, item.stamp_us)

    def on_unload(self, request: MaintainRequest, response: MaintainResponse) -> None:
        """Remove the item (with ``cascade``, its subtree).

        Unless another robot took it over or it is gone already; an item with children stays
        without ``cascade``.
        """
        with self._lock:
            if self._closed:
                return
            try:
                item = self._tree.get(request.item)
            except ContextError:
                return
        if item.maintainer != self._robot:
            return
        try:
            self.remove(request.item, cascade=request.cascade)
        except ContextError as err:
            logger.warning("context: kept item %r after its release: %s", request.item, err)

    # ================================================================ close

    def close(self) -> None:
        """Stop syncing, stop and join the threads. Idempotent; the tree stays readable.

        The fleet link and its transport stay the caller's to close.
        """
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._wake.notify_all()
        self._stop_sync()
        self._calls.close(drain=True)
        if self._store is not None:
            self._store.close()


def _json_object(text: str) -> dict[str, Any]:
    value = json.loads(text) if text else {}
    if not isinstance(value, dict):
        raise ValueError("attributes must be a JSON object")
    return value
