"""The consumers' side of the Process Manager: ``ProcessManagerClient``.

``load`` / ``release`` processes by value, and a reaction to failures: by default the failed
process is released and requested again (relaunch), as upstream's ``ProcessManagerInterface``
does; ``"report"`` only logs; a callable decides. See ``docs/process-manager.md``.
"""

from __future__ import annotations

import contextlib
import logging
import os
import queue
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Literal, TypeAlias

from temoto.core.registrar import (
    Registrar,
    Status,
    StatusUpdate,
)
from temoto.errors import (
    ResourceClosedError,
    ResourceNotFoundError,
    StateError,
)
from temoto.managers.process import ProcessManager, ProcessRequest, ProcessResponse

__all__ = ["FailurePolicy", "ProcessHandle", "ProcessManagerClient"]

logger = logging.getLogger(__name__)


@dataclass(eq=False)
class ProcessHandle:
    """A consumer's process, kept up to date across relaunches.

    The fields change in place when the client relaunches the process (a new reference, a new
    pid); ``on_change`` (if set) is called after every change, on the client's worker thread.

    Attributes:
        request: The request (the same across relaunches).
        reference_id: The current registrar reference ("" after release or a failed
            relaunch).
        resource_id: The current resource.
        response: The current process.
        relaunches: How many times it was relaunched.
        failed: True while the current process is known dead and no relaunch is coming
            (policy ``"report"``, a failed relaunch, or the relaunch budget used up).
        released: True once released.
        last_status: The last FATAL status received, if any.
        on_change: Called with the handle after a relaunch, or when the handle gives up.
    """

    request: ProcessRequest
    reference_id: str
    resource_id: str
    response: ProcessResponse
    relaunches: int = 0
    failed: bool = False
    released: bool = False
    last_status: StatusUpdate | None = None
    on_change: Callable[[ProcessHandle], None] | None = None
    _history: deque[float] = field(default_factory=deque, init=False, repr=False)

    @property
    def pid(self) -> int:
        """The current process id."""
        return self.response.pid


FailurePolicy: TypeAlias = (
    Literal["relaunch", "report"] | Callable[[ProcessHandle, StatusUpdate], None]
)
"""How a :class:`ProcessManagerClient` reacts to a FATAL status of one of its processes."""

_STOP = object()


class ProcessManagerClient:
    """Loads and releases processes for one consumer, and reacts when they die.

    Reactions (``on_failure``) to a ``FATAL`` status of one of its processes:

    * ``"relaunch"`` (default, as upstream): release the failed reference and load the same
      request again (the registrar gives a fresh resource for a request whose resource
      failed); the handle is updated in place. At most ``max_relaunches`` relaunches within
      ``relaunch_window`` seconds per handle; beyond that it gives up: logs an error, sets
      ``handle.failed`` and calls ``handle.on_change``.
    * ``"report"``: log it and set ``handle.failed``; the handle keeps its (failed) reference
      until released.
    * a callable ``f(handle, update)``: your own reaction.

    Reactions run on a worker thread of the client (``temoto-process-client-<client>``,
    started on the first failure, joined by :meth:`close`), never on the monitor thread that
    reports the exit: a relaunch may wait for the failed process's group to stop.

    Args:
        registrar: The registrar with a ``"process"`` server.
        client: The consumer name the references are taken for.
        on_failure: The reaction, see above.
        max_relaunches: Relaunch budget per handle within ``relaunch_window``; None for no
            limit.
        relaunch_window: Seconds.

    Raises:
        ValueError: An unknown policy or a negative budget.
    """

    def __init__(
        self,
        registrar: Registrar,
        client: str,
        *,
        on_failure: FailurePolicy = "relaunch",
        max_relaunches: int | None = 10,
        relaunch_window: float = 60.0,
    ) -> None:
        if not callable(on_failure) and on_failure not in ("relaunch", "report"):
            raise ValueError(
                f"on_failure must be 'relaunch', 'report' or a callable, not {on_failure!r}"
            )
        if max_relaunches is not None and max_relaunches < 0:
            raise ValueError("max_relaunches must be >= 0 or None")
        self.registrar = registrar
        self.client = client
        self.on_failure = on_failure
        self.max_relaunches = max_relaunches
        self.relaunch_window = float(relaunch_window)
        self._lock = threading.Lock()
        self._handles: dict[str, ProcessHandle] = {}  # by reference id
        self._all: list[ProcessHandle] = []
        self._queue: queue.SimpleQueue[StatusUpdate | object] = queue.SimpleQueue()
        # The worker thread and the closed flag have their own lock: status callbacks (on the
        # monitor thread) must never wait for ``_lock``, which a release may hold for ``grace``.
        self._thread_lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._closed = False

    # --------------------------------------------------------------------- public API

    def load(
        self,
        executable: str,
        *args: str,
        env: Mapping[str, str] | None = None,
        cwd: str | os.PathLike[str] | None = None,
    ) -> ProcessHandle:
        """Start (or share) a process.

        Args:
            executable: The program (on ``PATH``, or a path).
            *args: Its arguments.
            env: Extra environment variables.
            cwd: The working directory.

        Returns:
            The handle.

        Raises:
            TypeError: Bad argument types.
            ValueError: A bad request (before it reaches the registrar).
            ResourceLoadError: The manager could not start it (the cause is chained).
            StateError: The client is closed.
        """
        request = ProcessRequest(
            executable,
            tuple(args),
            tuple((env or {}).items()),
            os.fspath(cwd) if cwd is not None else None,
        )
        with self._lock:
            if self._closed:
                raise StateError(f"process client '{self.client}' is closed")
            resource = self.registrar.call(
                ProcessManager.name, request, client=self.client, on_status=self._on_status
            )
            handle = ProcessHandle(request, resource.id, resource.resource_id, resource.response)
            self._handles[resource.id] = handle
            self._all.append(handle)
        self._check_failed_at_load(handle, resource.id)
        return handle

    def release(self, handle: ProcessHandle) -> None:
        """Release a process (it stops when no other consumer holds it). Idempotent.

        Args:
            handle: What :meth:`load` returned.
        """
        with self._lock:
            if handle.released:
                return
            handle.released = True
            if handle in self._all:
                self._all.remove(handle)
            ref = handle.reference_id
            handle.reference_id = ""
            self._handles.pop(ref, None)
            if ref:
                with contextlib.suppress(ResourceClosedError, ResourceNotFoundError):
                    self.registrar.release(ref)

    def release_all(self) -> None:
        """Release every process of this client."""
        with self._lock:
            handles = list(self._all)
        for handle in reversed(handles):
            self.release(handle)

    def handles(self) -> list[ProcessHandle]:
        """The handles not yet released.

        Returns:
            Handles, in load order.
        """
        with self._lock:
            return list(self._all)

    def reattach(self) -> list[ProcessHandle]:
        """After a restart from the catalog: take over this client's process references.

        Builds a handle for each reference the registrar holds for ``client`` on the process
        server, subscribes to its status, and applies the failure reaction to those that died
        while the manager was down (their FATAL was sent before anyone could subscribe).

        Returns:
            The new handles.

        Raises:
            StateError: The client is closed.
        """
        attached: list[ProcessHandle] = []
        with self._lock:
            if self._closed:
                raise StateError(f"process client '{self.client}' is closed")
            for ref in self.registrar.references(self.client):
                if ref.holder or ref.id in self._handles:
                    continue
                info = self.registrar.info(ref.id)
                if info.server != ProcessManager.name:
                    continue
                handle = ProcessHandle(info.request, ref.id, info.id, info.response)
                self._handles[ref.id] = handle
                self._all.append(handle)
                self.registrar.subscribe(ref.id, self._on_status)
                attached.append(handle)
        for handle in attached:
            self._check_failed_at_load(
                handle, handle.reference_id, "failed while the process manager was down"
            )
        return attached

    def close(self) -> None:
        """Release everything and stop the worker thread. Idempotent."""
        self.release_all()
        with self._thread_lock:
            self._closed = True
            thread = self._thread
        if thread is not None:
            self._queue.put(_STOP)
            if thread is not threading.current_thread():
                thread.join()

    def __enter__(self) -> ProcessManagerClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --------------------------------------------------------------------- internals

    def _check_failed_at_load(
        self,
        handle: ProcessHandle,
        reference_id: str,
        message: str = "exited before its load completed",
    ) -> None:
        # A process that dies while its load is still being recorded is marked failed before
        # this reference (and its callback) exists: its FATAL reached nobody. React here.
        try:
            info = self.registrar.info(reference_id)
        except ResourceNotFoundError:
            return
        if info.failed:
            pid = handle.response.pid
            update = StatusUpdate(
                reference_id,
                info.id,
                Status.FATAL,
                f"process {pid} ({handle.request.executable}) {message}",
                info.id,
                (ProcessManager.name,),
            )
            self._on_status(update)

    def _on_status(self, update: StatusUpdate) -> None:
        """Registrar callback (runs in the reporting thread): hand FATALs to the worker."""
        if update.status is not Status.FATAL:
            logger.debug("%s: %s %s", update.reference_id, update.status.name, update.message)
            return
        with self._thread_lock:
            if self._closed:
                return
            if self._thread is None:
                self._thread = threading.Thread(
                    target=self._work, name=f"temoto-process-client-{self.client}", daemon=True
                )
                self._thread.start()
        self._queue.put(update)

    def _work(self) -> None:
        while True:
            item = self._queue.get()
            if item is _STOP:
                return
            assert isinstance(item, StatusUpdate)
            try:
                self._react(item)
            except Exception:
                logger.exception("reaction to %s failed", item)

    def _react(self, update: StatusUpdate) -> None:
        with self._lock:
            handle = self._handles.get(update.reference_id)
            if handle is None or handle.released or self._closed:
                return  # released, or already relaunched (a duplicate report)
            if handle.last_status is not None and handle.last_status.reference_id == (
                update.reference_id
            ):
                return  # the same failure, reported twice
            handle.last_status = update
        policy = self.on_failure
        if callable(policy):
            policy(handle, update)
            return
        if policy == "report":
            logger.error("client '%s': %s", self.client, update.message)
            handle.failed = True
            self._changed(handle)
            return
        self._relaunch(handle, update)

    def _relaunch(self, handle: ProcessHandle, update: StatusUpdate) -> None:
        now = time.monotonic()
        history = handle._history
        while history and now - history[0] > self.relaunch_window:
            history.popleft()
        if self.max_relaunches is not None and len(history) >= self.max_relaunches:
            logger.error(
                "client '%s': %s; not relaunching: %d relaunches within %g s",
                self.client,
                update.message,
                len(history),
                self.relaunch_window,
            )
            handle.failed = True
            self._changed(handle)
            return
        logger.warning("client '%s': %s; relaunching", self.client, update.message)
        with self._lock:
            if handle.released or self._closed:
                return
            old = handle.reference_id
            self._handles.pop(old, None)
            with contextlib.suppress(ResourceClosedError, ResourceNotFoundError):
                self.registrar.release(old)
            history.append(now)
            try:
                resource = self.registrar.call(
                    ProcessManager.name,
                    handle.request,
                    client=self.client,
                    on_status=self._on_status,
                )
            except Exception as err:
                logger.error("client '%s': relaunch of %s failed: %s", self.client, old, err)
                handle.reference_id = ""
                handle.failed = True
                new_ref = ""
            else:
                handle.reference_id = resource.id
                handle.resource_id = resource.resource_id
                handle.response = resource.response
                handle.relaunches += 1
                handle.failed = False
                self._handles[resource.id] = handle
                new_ref = resource.id
        self._changed(handle)
        if new_ref:
            self._check_failed_at_load(handle, new_ref)

    @staticmethod
    def _changed(handle: ProcessHandle) -> None:
        hook = handle.on_change
        if hook is not None:
            try:
                hook(handle)
            except Exception:
                logger.exception("on_change hook of process %d failed", handle.pid)
