"""The Resource Registrar: reference counting, dependencies, status propagation, durability.

See ``docs/registrar.md`` for the semantics. In short: ``call`` loads a resource through its
server the first time an equal request arrives and only adds a reference afterwards; calls
made while a resource loads become its dependencies; ``release`` of the last reference
releases the dependencies, then unloads; ``send_status`` reaches every consumer, up the
dependency chain. Every change is appended to the journal before the call returns.

The registrar runs the protocol: server hooks, the thread-local loading stack, status
delivery, the restore after a crash. Its books (tables, reference counts, dependency lists) and
the journal records of their changes are the :class:`~temoto.core.registrar._ledger.Ledger`'s;
the records themselves are defined in :mod:`~temoto.core.registrar.records`.

Locking: one lock guards the ledger and its journal (opened ``serialized``: an append takes no
lock of its own). Server hooks and status callbacks run outside it, in the calling thread, so
they may call the registrar again.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any, Literal

from temoto.core.registrar import records
from temoto.core.registrar._ledger import Entry, Ledger, Notices
from temoto.core.registrar._restore import settle
from temoto.core.registrar.messages import (
    Reference,
    Resource,
    ResourceInfo,
    Status,
    StatusCallback,
    canonical_json,
    new_resource,
    request_key,
    to_plain,
)
from temoto.core.registrar.server import LoadContext, ResourceServer
from temoto.errors import (
    ResourceClosedError,
    ResourceError,
    ResourceLoadError,
    ResourceNotFoundError,
)

if TYPE_CHECKING:
    from pathlib import Path

__all__ = ["Registrar"]

logger = logging.getLogger(__name__)


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
        self._tls = threading.local()
        self._closed = False
        self._ledger = Ledger.open(name, catalog, restore, fsync, fsync_interval)

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
            restored = self._ledger.rebuild_when_ready(self._servers)
        if restored is not None:
            settle(self, self._ledger, self._lock, restored, self._unload, self._transient)

    def servers(self) -> list[str]:
        """Names of the registered servers.

        Returns:
            Sorted names.
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
        server = self._servers.get(name)  # registration only adds: no lock needed to read
        if server is None:
            raise self._no_server(name)
        return server

    def _no_server(self, name: str) -> ResourceNotFoundError:
        with self._lock:
            known = sorted(self._servers)
        return ResourceNotFoundError(
            f"no server named '{name}' (servers: {', '.join(known) or 'none'})", origin=self.name
        )

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
        holder: str | None = None,
    ) -> Resource[Any]:
        """Request a resource: load it on first use, or add a reference to it.

        Called from inside a server's ``on_load`` (same thread), the reference becomes a
        dependency of the resource being loaded.

        Args:
            server: The server's name.
            request: An instance of the server's ``request_type``.
            client: The consumer's name (for ``release_client`` and queries); for a
                dependency, ``"<registrar>/<holder>"`` if empty.
            priority: Higher pre-empts lower on conflicting exclusive use.
            exclusive: Want the resource alone.
            on_status: Called with every status update for this reference.
            holder: The id of a loading resource that takes the reference as a dependency
                (``LoadContext.call`` passes its own); "" for none. None (default): the
                resource whose ``on_load`` runs in this thread, if any.

        Returns:
            The reference (its id, the resource id, the response).

        Raises:
            ResourceNotFoundError: Unknown server, or ``holder`` is not loading.
            TypeError: The request has the wrong type or cannot be serialised.
            ResourceBusyError: A conflicting consumer of equal or higher priority holds it.
            ResourceLoadError: The server (or a nested one) failed; chained to the cause.
            ResourceClosedError: The registrar is closed.
        """
        if holder is None:
            stack: list[str] | None = getattr(self._tls, "loading", None)
            holder = stack[-1] if stack else ""
        srv = self._servers.get(server)
        if srv is None:
            raise self._no_server(server)
        if not isinstance(request, srv.request_type):
            raise TypeError(
                f"server '{server}' takes {srv.request_type.__name__} requests,"
                f" not {type(request).__name__}"
            )
        try:
            key = request_key(request)
        except TypeError as err:
            raise TypeError(f"request for server '{server}' cannot be serialised: {err}") from None
        if holder and not client:
            client = f"{self.name}/{holder}"
        ledger = self._ledger
        while True:
            with self._lock:
                if self._closed:
                    raise self._closed_error()
                if holder and holder not in ledger.entries:
                    raise ResourceNotFoundError(
                        f"no resource '{holder}' is loading", origin=self.name
                    )
                uid = ledger.live.get((server, key))
                if uid is None:
                    entry = ledger.begin(server, key, request)
                    break
                entry = ledger.entries[uid]
                if entry.loading:
                    if entry.loader == threading.get_ident():
                        raise ResourceLoadError(
                            f"server '{server}': the request depends on itself", origin=self.name
                        )
                    wait_for = entry.loaded
                else:
                    ref, pre_empted = ledger.add_ref(
                        entry, client, priority, exclusive, holder, on_status
                    )
                    result = new_resource(ref.id, uid, server, entry.request, entry.response)
                    if not pre_empted:
                        return result
                    message = f"pre-empted by '{client}' (priority {priority})"
                    notices = ledger.notices(pre_empted, Status.WARNING, message, entry)
                    wait_for = None
            if wait_for is None:
                self._deliver(notices)
                return result
            wait_for.wait()  # someone else is loading the same request: share their result
        return self._load(srv, entry, client, priority, exclusive, on_status, holder)

    def _load(
        self,
        srv: ResourceServer[Any, Any],
        entry: Entry,
        client: str,
        priority: int,
        exclusive: bool,
        on_status: StatusCallback | None,
        holder: str,
    ) -> Resource[Any]:
        stack: list[str] = self._tls.__dict__.setdefault("loading", [])
        stack.append(entry.uid)
        try:
            response = srv.on_load(entry.request, LoadContext(self, entry.uid, srv.name))
            if not isinstance(response, srv.response_type):
                raise TypeError(
                    f"on_load returned {type(response).__name__}, not {srv.response_type.__name__}"
                )
            plain = to_plain(response)
        except BaseException as err:
            stack.pop()
            error = ResourceLoadError(
                f"server '{srv.name}' could not load {canonical_json(entry.request)}: {err}",
                origin=self.name,
            )
            error.__cause__ = err
            self._rollback(entry)
            if isinstance(err, Exception):
                raise error from err
            raise
        stack.pop()
        with self._lock:
            ref = self._ledger.loaded(
                entry, response, plain, client, priority, exclusive, holder, on_status
            )
        entry.loaded.set()
        self._compact()
        return Resource(ref.id, entry.uid, srv.name, entry.request, response)

    def _rollback(self, entry: Entry) -> None:
        with self._lock:
            deps = self._ledger.dep_ids(entry)
        for dep in reversed(deps):
            try:
                self.release(dep)
            except ResourceError:
                logger.exception("rollback of %s: releasing %s failed", entry.uid, dep)
        with self._lock:
            self._ledger.forget(entry, records.Abandon)
        entry.loaded.set()

    def checkpoint(self, resource_id: str, progress: Mapping[str, Any]) -> None:
        """Record how far a load got (``LoadContext.checkpoint`` of the resource's ``on_load``).

        Args:
            resource_id: The resource being loaded.
            progress: JSON-serialisable data, handed to ``on_abandoned`` if the process dies
                before the load returns.

        Returns:
            None.

        Raises:
            ResourceNotFoundError: No resource of that id is loading.
            TypeError: If the data cannot be serialised.
        """
        with self._lock:
            self._ledger.checkpoint(resource_id, progress)

    def release(self, reference_id: str) -> bool:
        """Release one reference; the last one unloads the resource (dependencies first).

        Args:
            reference_id: What ``call`` returned as ``id``.

        Returns:
            True if the resource was unloaded.

        Raises:
            ResourceClosedError: The reference was already released, or the registrar is
                closed.
            ResourceNotFoundError: No such reference.
        """
        with self._lock:
            if self._closed:
                raise self._closed_error()
            _, entry, last, resumed = self._ledger.unref(reference_id)
            quiet = not (last or resumed)
            if quiet and not self._ledger.quiet_release():
                return False
            if not quiet:
                notices = self._ledger.notices(resumed, Status.OK, "resource returned", entry)
                deps = self._ledger.dep_ids(entry) if last else []
        if quiet:
            self._compact()
            return False
        self._deliver(notices)
        if last:
            self._unload(entry, deps)
        return last

    def _unload(self, entry: Entry, deps: list[str] | None = None) -> None:
        """Release a resource's dependencies (newest first), unload it, forget it.

        ``deps``: its dependency reference ids, if the caller read them under the lock.
        """
        if deps is None:
            with self._lock:
                deps = self._ledger.dep_ids(entry)
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
            self._ledger.forget(entry, records.Unload)
        self._compact()

    def release_client(self, client: str) -> int:
        """Release every reference a consumer holds.

        References released meanwhile by others are skipped.

        Args:
            client: The consumer's name.

        Returns:
            How many references were released.
        """
        with self._lock:
            refs = self._ledger.refs.values()
            ids = [r.id for r in refs if r.client == client and not r.holder]
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
            if self._closed:
                raise self._closed_error()
            refs = [r.snapshot() for r in self._ledger.refs.values() if not r.holder]
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
        with self._lock:
            entry = self._ledger.resolve(resource_id)
            if status is Status.FATAL:
                self._ledger.fail(entry)
            elif status is Status.OK:
                self._ledger.recover(entry)  # a device answers again: shared once more
            reached, notices = self._ledger.reach(entry, status, message)
            servers = self._servers
            hooks = [(servers[e.server], info) for e, info in reached if e.server in servers]
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
            ref = self._ledger.refs.get(reference_id)
            if ref is None:
                raise ResourceNotFoundError(f"no reference {reference_id}", origin=self.name)
            ref.callbacks = (*ref.callbacks, on_status)

    def _deliver(self, notices: Notices) -> None:
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
            return self._ledger.info(self._ledger.resolve(resource_id))

    def served(self, server: str) -> list[ResourceInfo]:
        """What a server currently serves (loaded resources, including failed ones).

        Args:
            server: The server's name.

        Returns:
            Snapshots, in load order.

        Raises:
            ResourceNotFoundError: Unknown server.
        """
        self.server(server)
        with self._lock:
            entries = self._ledger.entries.values()
            return [self._ledger.info(e) for e in entries if e.server == server and not e.loading]

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
            ledger = self._ledger
            return [ledger.info(e) for e in ledger.dependencies(ledger.resolve(resource_id))]

    def references(self, client: str | None = None) -> list[Reference]:
        """References, of one consumer or all.

        Args:
            client: A consumer name, or None for all.

        Returns:
            Snapshots.
        """
        with self._lock:
            refs = self._ledger.refs.values()
            return [r.snapshot() for r in refs if client is None or r.client == client]

    def resources(self) -> list[ResourceInfo]:
        """Every loaded resource.

        Returns:
            Snapshots, in load order.
        """
        with self._lock:
            entries = self._ledger.entries.values()
            return [self._ledger.info(e) for e in entries if not e.loading]

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
            entry = self._ledger.resolve(resource_id)
            srv = self._servers[entry.server]
            if not isinstance(response, srv.response_type):
                raise TypeError(
                    f"server '{entry.server}' responses are {srv.response_type.__name__}"
                )
            self._ledger.set_response(entry, response)

    def _compact(self) -> None:
        if self._ledger.may_compact():  # a cheap look first: no lock for a short journal
            with self._lock:
                self._ledger.compact_if_due()

    # ================================================================ closing

    def _closed_error(self) -> ResourceClosedError:
        return ResourceClosedError(f"registrar '{self.name}' is closed", origin=self.name)

    def close(self) -> None:
        """Flush and close the catalog; resources stay recorded (nothing is unloaded).

        Returns:
            None.
        """
        with self._lock:  # the journal is serialized by this lock: closed under it too
            if self._closed:
                return
            self._closed = True
            if self._ledger.journal is not None:
                self._ledger.journal.close()

    def __enter__(self) -> Registrar:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
