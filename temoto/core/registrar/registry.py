"""The Resource Registrar: reference counting, dependencies, status propagation, durability.

See ``docs/registrar.md`` for the semantics. In short: ``call`` loads a resource through its
server the first time an equal request arrives and only adds a reference afterwards; calls
made while a resource loads become its dependencies; ``release`` of the last reference
releases the dependencies, then unloads; ``send_status`` reaches every consumer, up the
dependency chain. Every change is appended to the journal before the call returns.

Reference counts and dependency lists live in a :class:`~temoto.core._fast.RefBook` (integer
slots; compiled when the extension is built): each resource has a resource slot, each reference
a reference slot, and the book decides when a release was the last one and which references a
resource holds as dependencies, in acquisition order. Everything else (ids, clients,
priorities, callbacks) stays in the ``_Entry``/``_Ref`` objects.

Locking: one lock guards the tables and the book. Server hooks and status callbacks run outside
it, in the calling thread, so they may call the registrar again.
"""

from __future__ import annotations

import collections
import itertools
import json.encoder
import logging
import secrets
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, TypeVar

from temoto.core._fast import RefBook
from temoto.core.registrar._replay import ReplayState, replay
from temoto.core.registrar.messages import (
    Reference,
    Resource,
    ResourceInfo,
    Status,
    StatusUpdate,
    canonical_json,
    from_plain,
    to_plain,
)
from temoto.core.registrar.server import LoadContext, ResourceServer
from temoto.errors import (
    CatalogCorruptError,
    ResourceBusyError,
    ResourceClosedError,
    ResourceError,
    ResourceLoadError,
    ResourceNotFoundError,
)

if TYPE_CHECKING:
    from temoto.core.registrar.journal import Journal

__all__ = ["Registrar"]

logger = logging.getLogger(__name__)

T = TypeVar("T")
StatusCallback = Callable[[StatusUpdate], None]

#: Compact the journal when it holds this many records more than the live state needs.
COMPACT_SLACK = 20_000
#: Remember this many released reference ids, to tell a double release from an unknown id.
RELEASED_MEMORY = 10_000

# Precompiled layouts of the journal records written for every deduplicated request (a "ref"
# record per call, an "unref" per release): the very bytes the journal's encoder would give
# (keys sorted, no spaces, UTF-8), without building a dict and walking it for each.
_REF = (
    '{"client":%s,"exclusive":%s,"holder":%s,"id":%s,"op":"ref","priority":%d,'
    '"suspended":%s,"suspends":%s,"uid":%s}'
)
_UNREF = '{"id":%s,"op":"unref","resumes":%s}'
_JSON_BOOL = {True: "true", False: "false"}
_json_str = json.encoder.encode_basestring  # the encoder's own string quoting (C)


def _json_list(items: list[str]) -> str:
    """A list of strings as the encoder writes it."""
    return "[" + ",".join(map(_json_str, items)) + "]" if items else "[]"


@dataclass(slots=True)
class _Ref:
    id: str
    uid: str
    client: str
    priority: int
    exclusive: bool
    holder: str  # resource id that holds this reference as a dependency ("" for consumers)
    suspended: bool = False
    callbacks: list[StatusCallback] = field(default_factory=list)
    suspends: list[str] = field(default_factory=list)
    slot: int = -1  # reference slot in the registrar's RefBook (-1: not in the book)

    def snapshot(self) -> Reference:
        return Reference(
            self.id,
            self.uid,
            self.client,
            self.priority,
            self.exclusive,
            self.suspended,
            self.holder,
        )

    def record(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "uid": self.uid,
            "client": self.client,
            "priority": self.priority,
            "exclusive": self.exclusive,
            "holder": self.holder,
            "suspended": self.suspended,
        }


@dataclass(slots=True)
class _Entry:
    uid: str
    server: str
    key: str
    request: Any
    response: Any = None
    refs: dict[str, _Ref] = field(default_factory=dict)  # the count is the RefBook's
    failed: bool = False
    loading: bool = True
    loaded: threading.Event = field(default_factory=threading.Event)
    load_error: BaseException | None = None
    loader: int = 0  # thread id running on_load
    progress: dict[str, Any] | None = None
    slot: int = -1  # resource slot in the registrar's RefBook (-1: not, or no longer, in it)

    def active(self) -> list[_Ref]:
        return [r for r in self.refs.values() if not r.suspended]


class Registrar:
    """Counts references to resources, tracks dependencies, propagates status, persists.

    Args:
        name: This registrar's name (in messages and error origins).
        catalog: The journal file, or None for no persistence.
        restore: Replay an existing catalog (after a crash) instead of starting empty.
        fsync: ``"group"`` (default: fsync at most every ``fsync_interval``), ``"always"``
            (every change), ``"never"``.
        fsync_interval: Seconds between grouped fsyncs.
        transient: With ``restore``: which consumers (by client name) died with the process
            that wrote the catalog. Their references are released at restore, before the
            servers are asked about their resources (what only they held is unloaded). None
            (default): every consumer is expected back (it re-attaches with ``subscribe``).

    Raises:
        CatalogCorruptError: If ``restore`` finds a corrupt catalog (the file is untouched).
        ResourceError: If a catalog exists and ``restore`` is false (it would be lost).
    """

    def __init__(
        self,
        name: str = "temoto",
        *,
        catalog: str | Path | None = None,
        restore: bool = False,
        fsync: Literal["group", "always", "never"] = "group",
        fsync_interval: float = 0.1,
        transient: Callable[[str], bool] | None = None,
    ) -> None:
        self.name = name
        self._transient = transient
        self._lock = threading.Lock()
        self._servers: dict[str, ResourceServer[Any, Any]] = {}
        self._entries: dict[str, _Entry] = {}
        self._live: dict[tuple[str, str], str] = {}
        self._refs: dict[str, _Ref] = {}
        self._book = RefBook()  # reference counts and dependency lists, by slot
        self._slot_refs: dict[int, _Ref] = {}  # reference slot -> reference
        self._released: collections.OrderedDict[str, None] = collections.OrderedDict()
        self._tls = threading.local()
        self._boot = secrets.token_hex(3)
        self._counter = itertools.count(1)
        self._journal: Journal | None = None
        self._restored: ReplayState | None = None
        self._closed = False
        if catalog is not None:
            path = Path(catalog)
            if path.exists() and path.stat().st_size and not restore:
                raise ResourceError(
                    f"catalog {path} exists: start with restore=True to take over its resources,"
                    " or remove it if they are gone",
                    origin=name,
                )
            from temoto.core.registrar.journal import Journal

            self._journal = Journal(path, fsync=fsync, fsync_interval=fsync_interval)
            records = self._journal.open()
            if restore:
                self._restored = replay(records, str(path))
                if not self._restored.entries:
                    self._restored = None
            elif records:
                self._journal.rewrite([])

    # ================================================================ servers

    def register(self, server: ResourceServer[Any, Any]) -> None:
        """Add a server; with a restored catalog, its resources are re-checked now.

        Args:
            server: The server (its ``name`` must be unique here).

        Returns:
            None.

        Raises:
            ValueError: If a server of that name is registered.
            CatalogCorruptError: If the catalog names resources this server cannot rebuild.
        """
        with self._lock:
            if server.name in self._servers:
                raise ValueError(f"a server named '{server.name}' is already registered")
            self._servers[server.name] = server
        if self._restored is not None:
            self._restore_ready()

    def servers(self) -> list[str]:
        """Names of the registered servers.

        Returns:
            Sorted names.

        Raises:
            Nothing.
        """
        with self._lock:
            return sorted(self._servers)

    def server(self, name: str) -> ResourceServer[Any, Any]:
        """The server registered under ``name`` (for a manager's client to find its manager).

        Args:
            name: The server's name.

        Returns:
            The server object.

        Raises:
            ResourceNotFoundError: No server has that name.
        """
        return self._server(name)

    # ================================================================ call / release

    def call(
        self,
        server: str,
        request: Any,
        *,
        client: str = "",
        priority: int = 0,
        exclusive: bool = False,
        on_status: StatusCallback | None = None,
    ) -> Resource[Any]:
        """Request a resource: load it on first use, or add a reference to it.

        Called from inside a server's ``on_load`` (same thread), the reference becomes a
        dependency of the resource being loaded.

        Args:
            server: The server's name.
            request: An instance of the server's ``request_type``.
            client: The consumer's name (for ``release_client`` and queries).
            priority: Higher pre-empts lower on conflicting exclusive use.
            exclusive: Want the resource alone.
            on_status: Called with every status update for this reference.

        Returns:
            The reference (its id, the resource id, the response).

        Raises:
            ResourceNotFoundError: Unknown server.
            TypeError: The request has the wrong type or cannot be serialised.
            ResourceBusyError: A conflicting consumer of equal or higher priority holds it.
            ResourceLoadError: The server (or a nested one) failed; chained to the cause.
        """
        stack: list[str] = getattr(self._tls, "loading", [])
        holder = stack[-1] if stack else ""
        return self._call(server, request, client, priority, exclusive, on_status, holder=holder)

    def _call(
        self,
        server: str,
        request: Any,
        client: str,
        priority: int,
        exclusive: bool,
        on_status: StatusCallback | None,
        *,
        holder: str,
    ) -> Resource[Any]:
        srv = self._server(server)
        if not isinstance(request, srv.request_type):
            raise TypeError(
                f"server '{server}' takes {srv.request_type.__name__} requests,"
                f" not {type(request).__name__}"
            )
        try:
            key = canonical_json(request)
        except TypeError as err:
            raise TypeError(f"request for server '{server}' cannot be serialised: {err}") from None
        if holder and not client:
            client = f"{self.name}/{holder}"
        while True:
            notices: list[tuple[list[StatusCallback], StatusUpdate]] = []
            with self._lock:
                self._check_open()
                if holder and holder not in self._entries:
                    raise ResourceNotFoundError(
                        f"no resource '{holder}' is loading", origin=self.name
                    )
                uid = self._live.get((server, key))
                if uid is None:
                    entry = self._begin(server, key, request)
                    break
                entry = self._entries[uid]
                if entry.loading:
                    if entry.loader == threading.get_ident():
                        raise ResourceLoadError(
                            f"server '{server}': the request depends on itself", origin=self.name
                        )
                    wait_for = entry.loaded
                else:
                    ref = self._add_ref(
                        entry, client, priority, exclusive, holder, on_status, notices
                    )
                    self._write_ref(ref)
                    result = Resource(ref.id, entry.uid, server, entry.request, entry.response)
                    wait_for = None
            if wait_for is None:
                self._deliver(notices)
                return result
            wait_for.wait()  # someone else is loading the same request: share their result
        return self._load(srv, entry, client, priority, exclusive, on_status, holder)

    def _begin(self, server: str, key: str, request: Any) -> _Entry:
        uid = f"{server}:{self._boot}-{next(self._counter)}"
        entry = _Entry(uid, server, key, request, loader=threading.get_ident())
        entry.slot = self._book.new_resource()
        self._entries[uid] = entry
        self._live[(server, key)] = uid
        self._write({"op": "begin", "uid": uid, "server": server, "request": to_plain(request)})
        return entry

    def _load(
        self,
        srv: ResourceServer[Any, Any],
        entry: _Entry,
        client: str,
        priority: int,
        exclusive: bool,
        on_status: StatusCallback | None,
        holder: str,
    ) -> Resource[Any]:
        stack: list[str] = self._tls.__dict__.setdefault("loading", [])
        stack.append(entry.uid)
        ctx = LoadContext(self, entry.uid, srv.name)
        try:
            response = srv.on_load(entry.request, ctx)
            if not isinstance(response, srv.response_type):
                raise TypeError(
                    f"on_load returned {type(response).__name__}, not {srv.response_type.__name__}"
                )
            plain = to_plain(response)
        except BaseException as err:
            stack.pop()
            error = ResourceLoadError(
                f"server '{srv.name}' could not load {entry.key}: {err}", origin=self.name
            )
            error.__cause__ = err
            self._rollback(entry, error)
            if isinstance(err, Exception):
                raise error from err
            raise
        stack.pop()
        with self._lock:
            entry.response = response
            entry.loading = False
            ref = self._add_ref(entry, client, priority, exclusive, holder, on_status, [])
            self._write({"op": "load", "uid": entry.uid, "response": plain, "ref": ref.record()})
        entry.loaded.set()
        self._maybe_compact()
        return Resource(ref.id, entry.uid, srv.name, entry.request, response)

    def _rollback(self, entry: _Entry, error: BaseException) -> None:
        with self._lock:
            deps = self._dep_ids(entry)
        for dep in reversed(deps):
            try:
                self.release(dep)
            except ResourceError:
                logger.exception("rollback of %s: releasing %s failed", entry.uid, dep)
        with self._lock:
            self._forget(entry)
            entry.load_error = error
            self._write({"op": "abandon", "uid": entry.uid})
        entry.loaded.set()

    def _add_ref(
        self,
        entry: _Entry,
        client: str,
        priority: int,
        exclusive: bool,
        holder: str,
        on_status: StatusCallback | None,
        notices: list[tuple[list[StatusCallback], StatusUpdate]],
    ) -> _Ref:
        """Add a reference (lock held), pre-empting lower-priority conflicting ones."""
        conflicting = [r for r in entry.active() if r.exclusive or exclusive]
        if conflicting:
            strongest = max(conflicting, key=lambda r: r.priority)
            if strongest.priority >= priority:
                raise ResourceBusyError(
                    f"resource {entry.uid} is held {'exclusively ' if strongest.exclusive else ''}"
                    f"by '{strongest.client}' with priority {strongest.priority}"
                    f" (this request: priority {priority})",
                    origin=self.name,
                )
            for ref in conflicting:
                ref.suspended = True
        ref = _Ref(
            f"{self._boot}-{next(self._counter)}", entry.uid, client, priority, exclusive, holder
        )
        ref.suspends = [r.id for r in conflicting]  # journaled with the reference: one record
        if on_status is not None:
            ref.callbacks.append(on_status)
        entry.refs[ref.id] = ref
        self._refs[ref.id] = ref
        ref.slot = self._book.add_ref(entry.slot, self._entries[holder].slot if holder else -1)
        self._slot_refs[ref.slot] = ref
        if conflicting:
            message = f"pre-empted by '{client}' (priority {priority})"
            for old in conflicting:
                notices.append(
                    (list(old.callbacks), self._update(old, Status.WARNING, message, entry))
                )
        return ref

    def release(self, reference_id: str) -> bool:
        """Release one reference; the last one unloads the resource (dependencies first).

        Args:
            reference_id: What ``call`` returned as ``id``.

        Returns:
            True if the resource was unloaded.

        Raises:
            ResourceClosedError: The reference was already released.
            ResourceNotFoundError: No such reference.
        """
        notices: list[tuple[list[StatusCallback], StatusUpdate]] = []
        with self._lock:
            self._check_open()
            ref = self._refs.pop(reference_id, None)
            if ref is None:
                if reference_id in self._released:
                    raise ResourceClosedError(
                        f"reference {reference_id} was already released", origin=self.name
                    )
                raise ResourceNotFoundError(f"no reference {reference_id}", origin=self.name)
            self._released[reference_id] = None
            if len(self._released) > RELEASED_MEMORY:
                self._released.popitem(last=False)
            entry = self._entries[ref.uid]
            del entry.refs[reference_id]
            del self._slot_refs[ref.slot]
            last = self._book.release(ref.slot) == 0  # also unlinks it from its holder's list
            ref.slot = -1
            resumed = [] if last or entry.active() else list(entry.refs.values())
            for other in resumed:
                other.suspended = False
            # one record, so a crash cannot leave only suspended references behind
            if self._journal is not None:
                self._journal.append_text(
                    _UNREF % (_json_str(reference_id), _json_list([r.id for r in resumed]))
                )
            if resumed:
                for other in resumed:
                    update = self._update(other, Status.OK, "resource returned", entry)
                    notices.append((list(other.callbacks), update))
            if last and self._live.get((entry.server, entry.key)) == entry.uid:
                del self._live[(entry.server, entry.key)]
            deps = self._dep_ids(entry) if last else []
        self._deliver(notices)
        if last:
            self._unload(entry, deps)
        return last

    def _unload(self, entry: _Entry, deps: list[str] | None = None) -> None:
        """Release a resource's dependencies (newest first), unload it, forget it.

        ``deps``: its dependency reference ids, if the caller read them under the lock.
        """
        if deps is None:
            with self._lock:
                deps = self._dep_ids(entry)
        for dep in reversed(deps):
            try:
                self.release(dep)
            except ResourceError:
                logger.exception("unloading %s: releasing dependency %s failed", entry.uid, dep)
        server = self._servers.get(entry.server)
        if server is not None and not entry.loading:
            try:
                server.on_unload(entry.request, entry.response)
            except Exception:
                logger.exception("server '%s' failed to unload %s", entry.server, entry.uid)
        with self._lock:
            self._forget(entry)
            self._write({"op": "unload", "uid": entry.uid})
        self._maybe_compact()

    def _forget(self, entry: _Entry) -> None:
        """Drop a resource that has no references left (lock held)."""
        if self._entries.get(entry.uid) is entry:
            del self._entries[entry.uid]
        if self._live.get((entry.server, entry.key)) == entry.uid:
            del self._live[(entry.server, entry.key)]
        if entry.slot >= 0:
            try:
                self._book.free_resource(entry.slot)
            except ValueError:
                # Dependencies whose release failed stay counted on their resources but are
                # no longer anybody's: off the list, so the slot can be reused.
                for slot in self._book.dependencies(entry.slot):
                    self._book.detach(slot)
                self._book.free_resource(entry.slot)
            entry.slot = -1

    def release_client(self, client: str) -> int:
        """Release every reference a consumer holds.

        Args:
            client: The consumer's name.

        Returns:
            How many references were released.

        Raises:
            Nothing for references released meanwhile by others.
        """
        with self._lock:
            ids = [r.id for r in self._refs.values() if r.client == client and not r.holder]
        count = 0
        for ref_id in reversed(ids):
            try:
                self.release(ref_id)
                count += 1
            except (ResourceClosedError, ResourceNotFoundError):
                pass
        return count

    def release_consumers(self, select: Callable[[Reference], bool] | None = None) -> int:
        """Release consumers' references (not dependencies), newest first.

        For a program that ends, or whose consumers are gone: what only they held is unloaded
        (dependencies first), and the catalog no longer lists it.

        Args:
            select: Which references (all if None); called without the registrar's lock.

        Returns:
            How many references were released.

        Raises:
            ResourceClosedError: The registrar is closed.
        """
        with self._lock:
            self._check_open()
            refs = [r.snapshot() for r in self._refs.values() if not r.holder]
        chosen = [r.id for r in refs if select is None or select(r)]
        count = 0
        for ref_id in reversed(chosen):
            try:
                self.release(ref_id)
                count += 1
            except ResourceNotFoundError:
                pass  # released meanwhile (e.g. by an unload this loop caused)
            except ResourceClosedError:
                if self._closed:
                    raise
        return count

    # ================================================================ status

    def send_status(self, resource_id: str, status: Status, message: str = "") -> int:
        """Report a resource's status to its server and every consumer, up the dependency chain.

        Args:
            resource_id: A resource id (or any reference id to it).
            status: The status; FATAL also marks the resource failed (new equal requests
                then load a fresh resource); OK on a failed resource marks it recovered
                (shared again by new equal requests) unless a fresh one was loaded since.
            message: What happened.

        Returns:
            How many consumer references were reached (all levels).

        Raises:
            ResourceNotFoundError: Unknown id.
        """
        hooks: list[tuple[ResourceServer[Any, Any], ResourceInfo]] = []
        notices: list[tuple[list[StatusCallback], StatusUpdate]] = []
        with self._lock:
            entry = self._resolve(resource_id)
            if status is Status.FATAL and not entry.failed:
                entry.failed = True
                if self._live.get((entry.server, entry.key)) == entry.uid:
                    del self._live[(entry.server, entry.key)]
                self._write({"op": "failed", "uid": entry.uid})
            elif (
                status is Status.OK
                and entry.failed
                and (entry.server, entry.key) not in self._live
                and not entry.loading
            ):
                # recovered (a device answers again): equal requests share it once more,
                # unless a fresh one was loaded meanwhile
                entry.failed = False
                self._live[(entry.server, entry.key)] = entry.uid
                self._write({"op": "recovered", "uid": entry.uid})
            origin = entry.uid
            seen = {entry.uid}
            todo: collections.deque[tuple[_Entry, tuple[str, ...]]] = collections.deque(
                [(entry, (entry.server,))]
            )
            while todo:
                current, hops = todo.popleft()
                server = self._servers.get(current.server)
                if server is not None:
                    hooks.append((server, self._info(current)))
                for ref in list(current.refs.values()):
                    update = StatusUpdate(ref.id, current.uid, status, message, origin, hops)
                    notices.append((list(ref.callbacks), update))
                    if ref.holder and ref.holder not in seen and ref.holder in self._entries:
                        seen.add(ref.holder)
                        up = self._entries[ref.holder]
                        todo.append((up, (*hops, up.server)))
        for server, info in hooks:
            try:
                server.on_status(info, status, message)
            except Exception:
                logger.exception("server '%s' on_status raised", server.name)
        self._deliver(notices)
        return len(notices)

    def subscribe(self, reference_id: str, on_status: StatusCallback) -> None:
        """Add a status callback to a reference (e.g. after a restart from the catalog).

        Args:
            reference_id: The reference.
            on_status: The callback.

        Returns:
            None.

        Raises:
            ResourceNotFoundError: Unknown reference.
        """
        with self._lock:
            ref = self._refs.get(reference_id)
            if ref is None:
                raise ResourceNotFoundError(f"no reference {reference_id}", origin=self.name)
            ref.callbacks.append(on_status)

    def _update(self, ref: _Ref, status: Status, message: str, entry: _Entry) -> StatusUpdate:
        return StatusUpdate(ref.id, entry.uid, status, message, entry.uid, (entry.server,))

    def _deliver(self, notices: list[tuple[list[StatusCallback], StatusUpdate]]) -> None:
        for callbacks, update in notices:
            for callback in callbacks:
                try:
                    callback(update)
                except Exception:
                    logger.exception("status callback for %s raised", update.reference_id)

    # ================================================================ queries

    def info(self, resource_id: str) -> ResourceInfo:
        """A resource (by resource id or reference id).

        Args:
            resource_id: The id.

        Returns:
            A snapshot.

        Raises:
            ResourceNotFoundError: Unknown id.
        """
        with self._lock:
            return self._info(self._resolve(resource_id))

    def served(self, server: str) -> list[ResourceInfo]:
        """What a server currently serves (loaded resources, including failed ones).

        Args:
            server: The server's name.

        Returns:
            Snapshots, in load order.

        Raises:
            ResourceNotFoundError: Unknown server.
        """
        self._server(server)
        with self._lock:
            return [
                self._info(e)
                for e in self._entries.values()
                if e.server == server and not e.loading
            ]

    def dependencies(self, resource_id: str) -> list[ResourceInfo]:
        """The resources a resource depends on (directly).

        Args:
            resource_id: Resource or reference id.

        Returns:
            Snapshots of the resources its dependency references point to.

        Raises:
            ResourceNotFoundError: Unknown id.
        """
        with self._lock:
            entry = self._resolve(resource_id)
            return [
                self._info(self._entries[self._slot_refs[slot].uid])
                for slot in self._book.dependencies(entry.slot)
            ]

    def references(self, client: str | None = None) -> list[Reference]:
        """References, of one consumer or all.

        Args:
            client: A consumer name, or None for all.

        Returns:
            Snapshots.

        Raises:
            Nothing.
        """
        with self._lock:
            return [
                r.snapshot() for r in self._refs.values() if client is None or r.client == client
            ]

    def resources(self) -> list[ResourceInfo]:
        """Every loaded resource.

        Returns:
            Snapshots, in load order.

        Raises:
            Nothing.
        """
        with self._lock:
            return [self._info(e) for e in self._entries.values() if not e.loading]

    def update_response(self, resource_id: str, response: Any) -> None:
        """Replace a resource's stored response (e.g. data known only after loading).

        Args:
            resource_id: Resource or reference id.
            response: The new response (the server's ``response_type``).

        Returns:
            None.

        Raises:
            ResourceNotFoundError: Unknown id.
            TypeError: Wrong type or not serialisable.
        """
        with self._lock:
            entry = self._resolve(resource_id)
            srv = self._servers[entry.server]
            if not isinstance(response, srv.response_type):
                raise TypeError(
                    f"server '{entry.server}' responses are {srv.response_type.__name__}"
                )
            self._write({"op": "response", "uid": entry.uid, "response": to_plain(response)})
            entry.response = response

    # ================================================================ persistence

    def _write(self, record: dict[str, Any]) -> None:
        if self._journal is not None:
            self._journal.append(record)

    def _write_ref(self, ref: _Ref) -> None:
        """Journal a new reference from the precompiled layout (the bytes the encoder gives)."""
        journal = self._journal
        if journal is None:
            return
        if type(ref.priority) is not int or type(ref.exclusive) is not bool:
            # not the layout's types: let the encoder decide
            self._write({"op": "ref", **ref.record(), "suspends": ref.suspends})
            return
        journal.append_text(
            _REF
            % (
                _json_str(ref.client),
                _JSON_BOOL[ref.exclusive],
                _json_str(ref.holder),
                _json_str(ref.id),
                ref.priority,
                _JSON_BOOL[ref.suspended],
                _json_list(ref.suspends),
                _json_str(ref.uid),
            )
        )

    def _checkpoint(self, uid: str, progress: Mapping[str, Any]) -> None:
        with self._lock:
            entry = self._entries.get(uid)
            if entry is None or not entry.loading:
                raise ResourceNotFoundError(f"no resource {uid} is loading", origin=self.name)
            entry.progress = to_plain(dict(progress))
            self._write({"op": "progress", "uid": uid, "data": entry.progress})

    def _maybe_compact(self) -> None:
        journal = self._journal
        if journal is None or journal.record_count < COMPACT_SLACK:
            return
        with self._lock:
            live = len(self._entries) + len(self._refs)
            if journal.record_count < COMPACT_SLACK + 2 * live:
                return
            journal.rewrite(self._snapshot_records())

    def _snapshot_records(self) -> list[dict[str, Any]]:
        """The live state as journal records (compaction)."""
        records: list[dict[str, Any]] = []
        entries = list(self._entries.values())
        for entry in entries:
            records.append(
                {
                    "op": "begin",
                    "uid": entry.uid,
                    "server": entry.server,
                    "request": to_plain(entry.request),
                }
            )
            if entry.progress is not None:
                records.append({"op": "progress", "uid": entry.uid, "data": entry.progress})
        for entry in entries:
            if entry.loading:
                records.append({"op": "deps", "uid": entry.uid, "deps": self._dep_ids(entry)})
                continue
            records.append(
                {
                    "op": "load",
                    "uid": entry.uid,
                    "response": to_plain(entry.response),
                    "ref": None,
                    "refs": [r.record() for r in entry.refs.values()],
                    "deps": self._dep_ids(entry),
                    "failed": entry.failed,
                }
            )
        return records

    def _restore_ready(self) -> None:
        """Once every server the catalog names is registered, rebuild and settle its state."""
        assert self._restored is not None
        state = self._restored
        with self._lock:
            missing = {e["server"] for e in state.entries.values()} - set(self._servers)
        if missing:
            return
        self._restored = None
        name = self._journal_name()
        refs: list[_Ref] = []
        with self._lock:
            for uid, raw in state.entries.items():
                server = self._servers[raw["server"]]
                try:
                    request = from_plain(server.request_type, raw["request"])
                    response = (
                        from_plain(server.response_type, raw["response"]) if raw["loaded"] else None
                    )
                    key = canonical_json(request)
                except TypeError as err:
                    raise CatalogCorruptError(
                        f"{name}: resource {uid} of server '{server.name}' cannot be rebuilt: {err}"
                    ) from err
                entry = _Entry(uid, server.name, key, request, response)
                entry.loading = not raw["loaded"]
                entry.failed = raw["failed"]
                entry.progress = raw["progress"]
                entry.slot = self._book.new_resource()
                entry.loaded.set()
                self._entries[uid] = entry
                if not entry.failed and not entry.loading:
                    self._live[(server.name, key)] = uid
                for rec in raw["refs"].values():
                    ref = _Ref(
                        rec["id"],
                        uid,
                        rec["client"],
                        rec["priority"],
                        rec["exclusive"],
                        rec["holder"],
                        rec["suspended"],
                    )
                    entry.refs[ref.id] = ref
                    self._refs[ref.id] = ref
                    refs.append(ref)
            # Into the book: dependencies first, in each holder's recorded order (the book
            # lists them in acquisition order), then every other reference.
            for uid, raw in state.entries.items():
                holder = self._entries[uid]
                for dep in raw["deps"]:
                    held = self._refs.get(dep)
                    if held is not None and held.slot < 0:
                        self._book_ref(held, self._entries[held.uid], holder.slot)
            for ref in refs:
                if ref.slot < 0:
                    self._book_ref(ref, self._entries[ref.uid], -1)
            restored = list(self._entries.values())
        logger.info("restored %d resources from %s", len(restored), name)
        # Settle what the crash left, before any server is asked about its resources (a
        # resource unloaded here is never reported on): a resource whose last reference had
        # been released is unloaded; the references of consumers that died with the previous
        # process are released; a half-done load is undone (its dependencies released, the
        # server told to clean up).
        for entry in restored:
            with self._lock:
                if entry.slot < 0 or entry.loading or self._book.count(entry.slot):
                    continue
                if self._live.get((entry.server, entry.key)) == entry.uid:
                    del self._live[(entry.server, entry.key)]
            logger.warning("restore: %s had been released; unloading it", entry.uid)
            self._unload(entry)
        if self._transient is not None:
            transient = self._transient
            gone = self.release_consumers(lambda ref: transient(ref.client))
            if gone:
                logger.info("restore: released %d references of consumers that are gone", gone)
        for entry in restored:
            if entry.loading and entry.uid in self._entries:
                logger.warning("restore: the load of %s was interrupted; undoing it", entry.uid)
                with self._lock:
                    deps = self._dep_ids(entry)
                for dep in reversed(deps):
                    if dep in self._refs:
                        self.release(dep)
                try:
                    self._servers[entry.server].on_abandoned(entry.request, entry.progress)
                except Exception:
                    logger.exception("server '%s' failed to undo %s", entry.server, entry.uid)
                with self._lock:
                    self._forget(entry)
                    self._write({"op": "abandon", "uid": entry.uid})
        # Then each server re-checks what is left of its resources (re-adopts them, or reports
        # them failed), dependencies before the resources holding them; a verdict is reported
        # at once, so a holder's server sees its dependencies' failures.
        with self._lock:
            order = self._restore_order(restored)
        for entry in order:
            with self._lock:
                if self._entries.get(entry.uid) is not entry or entry.loading:
                    continue  # unloaded meanwhile (by an earlier hook's release): not reported
                info = self._info(entry)
            verdict = self._servers[entry.server].on_restore(info)
            if verdict is not None and entry.uid in self._entries:
                self.send_status(entry.uid, verdict[0], verdict[1])

    def _restore_order(self, entries: list[_Entry]) -> list[_Entry]:
        """Live ``entries``, each after the resources it depends on (lock held)."""

        def deps(entry: _Entry) -> list[_Entry]:
            if entry.slot < 0:
                return []
            found = (
                self._entries.get(self._slot_refs[s].uid)
                for s in self._book.dependencies(entry.slot)
            )
            return [e for e in found if e is not None]

        order: list[_Entry] = []
        seen: set[str] = set()
        for root in entries:
            if root.uid in seen or self._entries.get(root.uid) is not root:
                continue
            seen.add(root.uid)
            stack = [(root, iter(deps(root)))]
            while stack:
                node, todo = stack[-1]
                for dep in todo:
                    if dep.uid not in seen:
                        seen.add(dep.uid)
                        stack.append((dep, iter(deps(dep))))
                        break
                else:
                    stack.pop()
                    order.append(node)
        return order

    def _journal_name(self) -> str:
        return str(self._journal.path) if self._journal is not None else "catalog"

    # ================================================================ helpers

    def _server(self, name: str) -> ResourceServer[Any, Any]:
        with self._lock:
            server = self._servers.get(name)
            known = sorted(self._servers)
        if server is None:
            raise ResourceNotFoundError(
                f"no server named '{name}' (servers: {', '.join(known) or 'none'})",
                origin=self.name,
            )
        return server

    def _book_ref(self, ref: _Ref, entry: _Entry, holder: int) -> None:
        """Enter a reference into the book (lock held); ``holder`` is a resource slot or -1."""
        ref.slot = self._book.add_ref(entry.slot, holder)
        self._slot_refs[ref.slot] = ref

    def _dep_ids(self, entry: _Entry) -> list[str]:
        """Ids of the references a resource holds as dependencies, oldest first (lock held)."""
        if entry.slot < 0:
            return []
        return [self._slot_refs[slot].id for slot in self._book.dependencies(entry.slot)]

    def _info(self, entry: _Entry) -> ResourceInfo:
        """A snapshot of a resource (lock held)."""
        return ResourceInfo(
            entry.uid,
            entry.server,
            entry.request,
            entry.response,
            tuple(r.snapshot() for r in entry.refs.values()),
            tuple(self._dep_ids(entry)),
            entry.failed,
        )

    def _resolve(self, ident: str) -> _Entry:
        entry = self._entries.get(ident)
        if entry is None:
            ref = self._refs.get(ident)
            entry = self._entries.get(ref.uid) if ref is not None else None
        if entry is None:
            raise ResourceNotFoundError(f"no resource or reference '{ident}'", origin=self.name)
        return entry

    def _check_open(self) -> None:
        if self._closed:
            raise ResourceClosedError(f"registrar '{self.name}' is closed", origin=self.name)

    def close(self) -> None:
        """Flush and close the catalog; resources stay recorded (nothing is unloaded).

        Returns:
            None.

        Raises:
            Nothing.
        """
        with self._lock:
            if self._closed:
                return
            self._closed = True
        if self._journal is not None:
            self._journal.close()

    def __enter__(self) -> Registrar:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
