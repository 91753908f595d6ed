"""The registrar's books: resources, references, dependencies, and the journal of every change.

Registrar internal (:mod:`~temoto.core.registrar.registry` is its only user). A :class:`Ledger`
holds the tables and the reference book and writes each change it makes to the journal
(:mod:`~temoto.core.registrar.records`) before it returns. It runs no server hook and no status
callback and takes no lock: the registrar calls it with its lock held.

Reference counts and dependency lists live in a :class:`~temoto.core._fast.RefBook` (integer
slots; compiled when the extension is built): each resource has a resource slot, each reference
a reference slot, and the book decides when a release was the last one and which references a
resource holds as dependencies, in acquisition order. Everything else (ids, clients,
priorities, callbacks) stays in the :class:`Entry` and :class:`Ref` objects.
"""

from __future__ import annotations

import collections
import itertools
import secrets
import threading
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, Final

from temoto.core._fast import RefBook
from temoto.core.registrar import records
from temoto.core.registrar.messages import (
    Reference,
    ResourceInfo,
    Status,
    StatusCallback,
    StatusUpdate,
    from_plain,
    request_key,
    to_plain,
)
from temoto.errors import (
    CatalogCorruptError,
    ResourceBusyError,
    ResourceClosedError,
    ResourceError,
    ResourceNotFoundError,
)

if TYPE_CHECKING:
    from temoto.core.registrar.journal import FsyncPolicy, Journal
    from temoto.core.registrar.server import ResourceServer

#: Status updates to deliver, each with the callbacks of its reference.
Notices = list[tuple[tuple[StatusCallback, ...], StatusUpdate]]

#: Compact the journal when it holds this many records more than the live state needs.
COMPACT_SLACK = 20_000
#: Every this many releases that unload nothing, the journal's length is looked at (as after
#: every load and unload), so taking and dropping a shared resource forever does not grow it
#: forever.
COMPACT_CHECK_RELEASES = 1024
#: Remember at least this many released reference ids (at most twice as many), to tell a
#: double release from an unknown id.
RELEASED_MEMORY = 10_000
#: Keep at most this many ``ref`` record layouts (one per resource, client, priority,
#: exclusive, holder); all are dropped when there are more.
REF_LAYOUTS = 4096

_NONE: Final[tuple[Ref, ...]] = ()  # no references pre-empted, none resumed


class Ref:
    """One reference (a ``call``): who holds which resource, and how."""

    __slots__ = (
        "callbacks",
        "client",
        "exclusive",
        "holder",
        "id",
        "priority",
        "slot",
        "suspended",
        "uid",
    )

    def __init__(
        self,
        ref_id: str,
        uid: str,
        client: str,
        priority: int,
        exclusive: bool,
        holder: str,
        suspended: bool = False,
    ) -> None:
        self.id = ref_id
        self.uid = uid
        self.client = client
        self.priority = priority
        self.exclusive = exclusive
        self.holder = holder  # resource id holding it as a dependency ("" for consumers)
        self.suspended = suspended
        self.callbacks: tuple[StatusCallback, ...] = ()  # replaced, never changed in place
        self.slot = -1  # reference slot in the book (-1: not in the book)

    def snapshot(self) -> Reference:
        """The reference as the registrar's queries show it."""
        return Reference(
            self.id,
            self.uid,
            self.client,
            self.priority,
            self.exclusive,
            self.suspended,
            self.holder,
        )

    def fields(self) -> records.RefFields:
        """The reference as records carry it."""
        return records.RefFields(
            self.id,
            self.uid,
            self.client,
            self.priority,
            self.exclusive,
            self.holder,
            self.suspended,
        )


class Entry:
    """One resource: its request, response, references and load state."""

    __slots__ = (
        "exclusive",
        "failed",
        "key",
        "loaded",
        "loader",
        "loading",
        "progress",
        "refs",
        "request",
        "response",
        "server",
        "slot",
        "suspended",
        "uid",
    )

    def __init__(
        self, uid: str, server: str, key: str, request: Any, response: Any = None, loader: int = 0
    ) -> None:
        self.uid = uid
        self.server = server
        self.key = key  # the request's key (messages.request_key)
        self.request = request
        self.response = response
        self.refs: dict[str, Ref] = {}  # in the order taken; the count is the book's
        self.exclusive = 0  # how many of refs are exclusive
        self.suspended = 0  # how many of refs are suspended
        self.failed = False
        self.loading = True
        self.loaded = threading.Event()
        self.loader = loader  # thread id running on_load
        self.progress: dict[str, Any] | None = None
        self.slot = -1  # resource slot in the book (-1: not, or no longer, in it)


class Ledger:
    """The tables of one registrar, its reference book, and its journal.

    Args:
        name: The registrar's name (error origins).
        journal: The open journal, or None for no persistence.

    Attributes:
        entries: Resources by id, in load order.
        live: The resource that equal requests share, by (server, request key).
        refs: References by id.
        book: Reference counts and dependency lists, by slot.
        slot_refs: References by reference slot.
        journal: The journal.
    """

    def __init__(self, name: str, journal: Journal | None) -> None:
        self.name = name
        self.journal = journal
        self.entries: dict[str, Entry] = {}
        self.live: dict[tuple[str, str], str] = {}
        self.refs: dict[str, Ref] = {}
        self.book = RefBook()
        self.slot_refs: dict[int, Ref] = {}
        # released reference ids: the newest (up to RELEASED_MEMORY), and the generation before
        self._released: set[str] = set()
        self._released_before: set[str] = set()
        self._ref_layouts: dict[tuple[str, str, int, bool, str], tuple[bytes, bytes]] = {}
        self._boot = secrets.token_hex(3)
        self._counter = itertools.count(1)
        self._quiet_releases = 0  # releases that unloaded nothing since the last look
        self._pending: records.ReplayState | None = None  # restored, not yet rebuilt

    @classmethod
    def open(
        cls,
        name: str,
        catalog: str | Path | None,
        restore: bool,
        fsync: FsyncPolicy,
        fsync_interval: float,
    ) -> Ledger:
        """A ledger on a new or (with ``restore``) replayed catalog; see ``Registrar``.

        Raises:
            CatalogCorruptError: If ``restore`` finds a corrupt catalog (the file is untouched).
            ResourceError: If a catalog exists and ``restore`` is false (it would be lost).
        """
        if catalog is None:
            return cls(name, None)
        path = Path(catalog)
        if path.exists() and path.stat().st_size and not restore:
            raise ResourceError(
                f"catalog {path} exists: start with restore=True to take over its resources,"
                " or remove it if they are gone",
                origin=name,
            )
        from temoto.core.registrar.journal import Journal

        # serialized: the registrar calls the ledger, and so the journal, under its lock
        journal = Journal(path, fsync=fsync, fsync_interval=fsync_interval, serialized=True)
        written = journal.open()
        ledger = cls(name, journal)
        try:
            if restore:
                state = records.replay(written, str(path))
                ledger._pending = state if state.entries else None
            elif written:
                journal.rewrite([])
        except BaseException:
            journal.close()  # let go of the file (and its lock): a corrupt catalog stays as is
            raise
        return ledger

    def write(self, record: records.Record) -> None:
        """Journal one record (nothing without a journal)."""
        if self.journal is not None:
            self.journal.append(record.plain())

    # ------------------------------------------------------------------------------ loading

    def begin(self, server: str, key: str, request: Any) -> Entry:
        """A new resource, loading in this thread (journaled)."""
        uid = f"{server}:{self._boot}-{next(self._counter)}"
        entry = Entry(uid, server, key, request, loader=threading.get_ident())
        entry.slot = self.book.new_resource()
        self.entries[uid] = entry
        self.live[(server, key)] = uid
        self.write(records.Begin(uid, server, to_plain(request)))
        return entry

    def checkpoint(self, uid: str, progress: Mapping[str, Any]) -> None:
        """Record a loading resource's progress (journaled).

        Raises:
            ResourceNotFoundError: No resource ``uid`` is loading.
            TypeError: The data cannot be serialised.
        """
        entry = self.entries.get(uid)
        if entry is None or not entry.loading:
            raise ResourceNotFoundError(f"no resource {uid} is loading", origin=self.name)
        entry.progress = to_plain(dict(progress))
        self.write(records.Progress(uid, entry.progress))

    def loaded(
        self,
        entry: Entry,
        response: Any,
        plain: Any,
        client: str,
        priority: int,
        exclusive: bool,
        holder: str,
        on_status: StatusCallback | None,
    ) -> Ref:
        """The load returned ``response`` (``plain``: as JSON data): its first reference."""
        entry.response = response
        entry.loading = False
        ref, _ = self.add_ref(entry, client, priority, exclusive, holder, on_status, False)
        self.write(records.Load(entry.uid, plain, ref.fields()))
        return ref

    # ------------------------------------------------------------------------------ references

    def add_ref(
        self,
        entry: Entry,
        client: str,
        priority: int,
        exclusive: bool,
        holder: str,
        on_status: StatusCallback | None,
        journaled: bool = True,
    ) -> tuple[Ref, tuple[Ref, ...] | list[Ref]]:
        """Add a reference, pre-empting lower-priority conflicting ones.

        Journaled as one ``ref`` record (with the ids it suspended) unless ``journaled`` is
        false: the first reference of a load is part of the ``load`` record.

        Returns:
            The reference and the references it suspended.

        Raises:
            ResourceBusyError: A conflicting reference of equal or higher priority holds it.
        """
        suspended: tuple[Ref, ...] | list[Ref] = _NONE
        if exclusive or entry.exclusive:  # else nothing can conflict
            suspended = self._pre_empt(entry, client, priority, exclusive)
        uid = entry.uid
        ref_id = f"{self._boot}-{next(self._counter)}"
        ref = Ref(ref_id, uid, client, priority, exclusive, holder)
        if on_status is not None:
            ref.callbacks = (on_status,)
        entry.refs[ref_id] = ref
        if exclusive:
            entry.exclusive += 1
        self.refs[ref_id] = ref
        ref.slot = slot = self.book.add_ref(entry.slot, self.entries[holder].slot if holder else -1)
        self.slot_refs[slot] = ref
        journal = self.journal
        if journaled and journal is not None:
            if not suspended and type(priority) is int and type(exclusive) is bool:
                key = (uid, client, priority, exclusive, holder)
                layout = self._ref_layouts.get(key)
                if layout is None:
                    layout = self._ref_layout(key)
                journal.append_json(layout[0] + ref_id.encode() + layout[1])
            else:
                self._write_ref(ref, suspended)
        return ref, suspended

    def _ref_layout(self, key: tuple[str, str, int, bool, str]) -> tuple[bytes, bytes]:
        layout = records.Ref.layout(*key)
        assert layout is not None  # the caller checked the types
        if len(self._ref_layouts) >= REF_LAYOUTS:
            self._ref_layouts.clear()
        self._ref_layouts[key] = layout
        return layout

    def _write_ref(self, ref: Ref, suspended: tuple[Ref, ...] | list[Ref]) -> None:
        """Journal a ``ref`` record that pre-empted others, or whose fields are of other types."""
        assert self.journal is not None
        suspends = [r.id for r in suspended] if suspended else ()
        text = records.Ref.text(
            ref.id, ref.uid, ref.client, ref.priority, ref.exclusive, ref.holder, False, suspends
        )
        if text is None:  # not the layout's types: the encoder decides
            self.journal.append(records.Ref(ref.fields(), tuple(suspends)).plain())
        else:
            self.journal.append_text(text)

    def _pre_empt(self, entry: Entry, client: str, priority: int, exclusive: bool) -> list[Ref]:
        """Suspend the active references that conflict with a new one, if it outranks them."""
        conflicting = [
            r for r in entry.refs.values() if not r.suspended and (r.exclusive or exclusive)
        ]
        if conflicting:
            strongest = max(conflicting, key=lambda r: r.priority)
            if strongest.priority >= priority:
                raise ResourceBusyError(
                    f"resource {entry.uid} is held "
                    f"{'exclusively ' if strongest.exclusive else ''}"
                    f"by '{strongest.client}' with priority {strongest.priority}"
                    f" (this request: priority {priority})",
                    origin=self.name,
                )
            for old in conflicting:
                old.suspended = True
            entry.suspended += len(conflicting)
        return conflicting

    def unref(self, reference_id: str) -> tuple[Ref, Entry, bool, tuple[Ref, ...] | list[Ref]]:
        """Remove a reference and journal it (one ``unref`` record).

        When the last active reference goes, the suspended ones become active again.

        Returns:
            The reference, its resource, whether it was the last reference, and the references
            resumed.

        Raises:
            ResourceClosedError: The reference was already released.
            ResourceNotFoundError: No such reference.
        """
        ref = self.refs.pop(reference_id, None)
        if ref is None:
            if reference_id in self._released or reference_id in self._released_before:
                raise ResourceClosedError(
                    f"reference {reference_id} was already released", origin=self.name
                )
            raise ResourceNotFoundError(f"no reference {reference_id}", origin=self.name)
        released = self._released
        if len(released) >= RELEASED_MEMORY:
            self._released_before = released
            self._released = released = set()
        released.add(reference_id)
        entry = self.entries[ref.uid]
        refs = entry.refs
        del refs[reference_id]
        if ref.exclusive:
            entry.exclusive -= 1
        if ref.suspended:
            entry.suspended -= 1
        del self.slot_refs[ref.slot]
        last = self.book.release(ref.slot) == 0  # also unlinks it from its holder's list
        ref.slot = -1
        resumed: tuple[Ref, ...] | list[Ref] = _NONE
        if not last and len(refs) == entry.suspended:  # no active reference left
            resumed = list(refs.values())
            for other in resumed:
                other.suspended = False
            entry.suspended = 0
        # one record, so a crash cannot leave only suspended references behind
        journal = self.journal
        if journal is not None:
            if resumed:
                journal.append_text(records.Unref.text(reference_id, [r.id for r in resumed]))
            else:
                journal.append_json(records.Unref.payload(reference_id))
        if last and self.live.get((entry.server, entry.key)) == entry.uid:
            del self.live[(entry.server, entry.key)]
        return ref, entry, last, resumed

    # ------------------------------------------------------------------------------ resources

    def forget(self, entry: Entry, record: type[records.Unload | records.Abandon]) -> None:
        """Drop a resource that has no references left, journaling ``record``."""
        if self.entries.get(entry.uid) is entry:
            del self.entries[entry.uid]
        if self.live.get((entry.server, entry.key)) == entry.uid:
            del self.live[(entry.server, entry.key)]
        if entry.slot >= 0:
            try:
                self.book.free_resource(entry.slot)
            except ValueError:
                # Dependencies whose release failed stay counted on their resources but are
                # no longer anybody's: off the list, so the slot can be reused.
                for slot in self.book.dependencies(entry.slot):
                    self.book.detach(slot)
                self.book.free_resource(entry.slot)
            entry.slot = -1
        self.write(record(entry.uid))

    def fail(self, entry: Entry) -> None:
        """Mark a resource failed (journaled): equal requests no longer share it."""
        if entry.failed:
            return
        entry.failed = True
        if self.live.get((entry.server, entry.key)) == entry.uid:
            del self.live[(entry.server, entry.key)]
        self.write(records.Failed(entry.uid))

    def recover(self, entry: Entry) -> None:
        """Share a failed resource again (journaled), unless a fresh one was loaded since."""
        if not entry.failed or entry.loading or (entry.server, entry.key) in self.live:
            return
        entry.failed = False
        self.live[(entry.server, entry.key)] = entry.uid
        self.write(records.Recovered(entry.uid))

    def set_response(self, entry: Entry, response: Any) -> None:
        """Replace a resource's response (journaled first).

        Raises:
            TypeError: The response cannot be serialised.
        """
        self.write(records.Response(entry.uid, to_plain(response)))
        entry.response = response

    # ------------------------------------------------------------------------------ queries

    def resolve(self, ident: str) -> Entry:
        """The resource of a resource or reference id.

        Raises:
            ResourceNotFoundError: Unknown id.
        """
        entry = self.entries.get(ident)
        if entry is None:
            ref = self.refs.get(ident)
            entry = self.entries.get(ref.uid) if ref is not None else None
        if entry is None:
            raise ResourceNotFoundError(f"no resource or reference '{ident}'", origin=self.name)
        return entry

    def dep_ids(self, entry: Entry) -> list[str]:
        """Ids of the references a resource holds as dependencies, oldest first."""
        if entry.slot < 0:
            return []
        return [self.slot_refs[slot].id for slot in self.book.dependencies(entry.slot)]

    def dependencies(self, entry: Entry) -> list[Entry]:
        """The live resources a resource's dependency references point to."""
        if entry.slot < 0:
            return []
        slots = self.book.dependencies(entry.slot)
        found = (self.entries.get(self.slot_refs[s].uid) for s in slots)
        return [e for e in found if e is not None]

    def info(self, entry: Entry) -> ResourceInfo:
        """A snapshot of a resource."""
        return ResourceInfo(
            entry.uid,
            entry.server,
            entry.request,
            entry.response,
            tuple(r.snapshot() for r in entry.refs.values()),
            tuple(self.dep_ids(entry)),
            entry.failed,
        )

    # ------------------------------------------------------------------------------ status

    def notices(self, refs: Iterable[Ref], status: Status, message: str, entry: Entry) -> Notices:
        """The updates ``refs`` (references to ``entry``) get for a status of ``entry``."""
        uid, hops = entry.uid, (entry.server,)
        return [(r.callbacks, StatusUpdate(r.id, uid, status, message, uid, hops)) for r in refs]

    def reach(
        self, entry: Entry, status: Status, message: str
    ) -> tuple[list[tuple[Entry, ResourceInfo]], Notices]:
        """Whom a status of ``entry`` reaches, up the dependency chain (breadth first).

        Returns:
            The resources (``entry``, then every resource holding a reached one as a
            dependency) with their snapshots, and the update each of their references gets.
        """
        origin = entry.uid
        seen = {origin}
        reached: list[tuple[Entry, ResourceInfo]] = []
        notices: Notices = []
        todo: collections.deque[tuple[Entry, tuple[str, ...]]] = collections.deque(
            [(entry, (entry.server,))]
        )
        while todo:
            current, hops = todo.popleft()
            reached.append((current, self.info(current)))
            for ref in list(current.refs.values()):
                update = StatusUpdate(ref.id, current.uid, status, message, origin, hops)
                notices.append((ref.callbacks, update))
                if ref.holder and ref.holder not in seen and ref.holder in self.entries:
                    seen.add(ref.holder)
                    up = self.entries[ref.holder]
                    todo.append((up, (*hops, up.server)))
        return reached, notices

    # ------------------------------------------------------------------------------ durability

    def quiet_release(self) -> bool:
        """Count a release that unloaded nothing; True every COMPACT_CHECK_RELEASES-th time."""
        self._quiet_releases += 1
        if self._quiet_releases < COMPACT_CHECK_RELEASES:
            return False
        self._quiet_releases = 0
        return True

    def may_compact(self) -> bool:
        """Whether the journal is long enough for :meth:`compact_if_due` to look (no lock)."""
        return self.journal is not None and self.journal.record_count >= COMPACT_SLACK

    def compact_if_due(self) -> None:
        """Rewrite the journal as a snapshot if it holds far more records than the state."""
        journal = self.journal
        if journal is None or journal.record_count < COMPACT_SLACK:
            return
        if journal.record_count < COMPACT_SLACK + 2 * (len(self.entries) + len(self.refs)):
            return
        journal.rewrite(record.plain() for record in self.snapshot())

    def snapshot(self) -> list[records.Record]:
        """The live state as records (what compaction writes)."""
        out: list[records.Record] = []
        entries = list(self.entries.values())
        for entry in entries:
            out.append(records.Begin(entry.uid, entry.server, to_plain(entry.request)))
            if entry.progress is not None:
                out.append(records.Progress(entry.uid, entry.progress))
        for entry in entries:
            deps = tuple(self.dep_ids(entry))
            if entry.loading:
                out.append(records.Deps(entry.uid, deps))
                continue
            refs = tuple(r.fields() for r in entry.refs.values())
            out.append(
                records.Load(entry.uid, to_plain(entry.response), None, refs, deps, entry.failed)
            )
        return out

    def rebuild_when_ready(
        self, servers: Mapping[str, ResourceServer[Any, Any]]
    ) -> list[Entry] | None:
        """Once ``servers`` has every server the replayed catalog names, fill the tables.

        Returns:
            The restored resources, in the journal's order; None if there is nothing to
            restore (or not yet).

        Raises:
            CatalogCorruptError: A request or response cannot be rebuilt by its server's types.
        """
        state = self._pending
        if state is None or {e.server for e in state.entries.values()} - set(servers):
            return None
        self._pending = None
        name = str(self.journal.path) if self.journal is not None else "catalog"
        refs: list[Ref] = []
        for uid, raw in state.entries.items():
            server = servers[raw.server]
            try:
                request = from_plain(server.request_type, raw.request)
                response = from_plain(server.response_type, raw.response) if raw.loaded else None
                key = request_key(request)
            except TypeError as err:
                raise CatalogCorruptError(
                    f"{name}: resource {uid} of server '{server.name}' cannot be rebuilt: {err}"
                ) from err
            entry = Entry(uid, server.name, key, request, response)
            entry.loading = not raw.loaded
            entry.failed = raw.failed
            entry.progress = raw.progress
            entry.slot = self.book.new_resource()
            entry.loaded.set()
            self.entries[uid] = entry
            if not entry.failed and not entry.loading:
                self.live[(server.name, key)] = uid
            for rec in raw.refs.values():
                ref = Ref(
                    rec.id, uid, rec.client, rec.priority, rec.exclusive, rec.holder, rec.suspended
                )
                entry.refs[ref.id] = ref
                entry.exclusive += bool(ref.exclusive)
                entry.suspended += bool(ref.suspended)
                self.refs[ref.id] = ref
                refs.append(ref)
        # Into the book: dependencies first, in each holder's recorded order (the book lists
        # them in acquisition order), then every other reference.
        for uid, raw in state.entries.items():
            holder = self.entries[uid]
            for dep in raw.deps:
                held = self.refs.get(dep)
                if held is not None and held.slot < 0:
                    self._book_ref(held, holder.slot)
        for ref in refs:
            if ref.slot < 0:
                self._book_ref(ref, -1)
        return list(self.entries.values())

    def _book_ref(self, ref: Ref, holder: int) -> None:
        ref.slot = self.book.add_ref(self.entries[ref.uid].slot, holder)
        self.slot_refs[ref.slot] = ref

    def restore_order(self, entries: Iterable[Entry]) -> list[Entry]:
        """The live ones of ``entries``, each after the resources it depends on."""
        order: list[Entry] = []
        seen: set[str] = set()
        for root in entries:
            if root.uid in seen or self.entries.get(root.uid) is not root:
                continue
            seen.add(root.uid)
            stack = [(root, iter(self.dependencies(root)))]
            while stack:
                node, todo = stack[-1]
                for dep in todo:
                    if dep.uid not in seen:
                        seen.add(dep.uid)
                        stack.append((dep, iter(self.dependencies(dep))))
                        break
                else:
                    stack.pop()
                    order.append(node)
        return order
