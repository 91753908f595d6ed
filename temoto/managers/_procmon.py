"""ProcessMonitor: one thread that notices process exits at once, through pidfds.

Every watched process gets a pidfd (``os.pidfd_open``); the kernel makes it readable when the
process exits. One thread (``temoto-procmon``) blocks on a selector over all the pidfds plus an
eventfd that wakes it to pick up added and removed watches: there is no polling interval, an
exit is seen within the scheduling latency of one thread wake-up.

For a process that is our child the monitor reaps it (``waitid`` on the pidfd) and reports its
exit code or the signal that killed it. A process that is not our child (one re-adopted after a
restart) cannot be waited for: its exit is reported with an unknown status, and its real parent
reaps it. Nothing else in the program may wait for a watched child (``Popen.wait``/``poll``,
``os.waitpid(-1)``): whoever reaps first gets the status.

Also here: :func:`process_start_time`, the start time the kernel records for a pid, which
tells a process apart from a later one that got the same pid.
"""

from __future__ import annotations

import contextlib
import logging
import os
import selectors
import threading
from collections.abc import Callable
from dataclasses import dataclass, field

from temoto.errors import StateError

__all__ = ["ExitCallback", "ProcessMonitor", "process_start_time", "process_state"]

logger = logging.getLogger(__name__)

ExitCallback = Callable[[int, "int | None", "int | None"], None]
"""``callback(pid, returncode, signal)``: exactly one of ``returncode`` and ``signal`` is set
for a reaped child; both are None when the status is unknown (not our child)."""


def _read_stat(pid: int) -> list[str] | None:
    """Fields 3 and on of ``/proc/<pid>/stat`` (index 0 is field 3, the state)."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            data = f.read()
    except (FileNotFoundError, ProcessLookupError):
        return None
    except OSError as err:  # e.g. ESRCH while the process is torn down
        logger.debug("cannot read /proc/%d/stat: %s", pid, err)
        return None
    # Field 2 is "(comm)", and comm may contain spaces and parentheses: it ends at the LAST ')'.
    _, sep, rest = data.rpartition(b")")
    if not sep:
        return None
    return rest.decode("ascii", errors="replace").split()


def process_start_time(pid: int) -> int | None:
    """The kernel's start time of a process: field 22 of ``/proc/<pid>/stat``.

    It is measured in clock ticks since boot, and together with the pid identifies a process:
    a later process that reuses the pid has a later start time.

    Args:
        pid: The process id.

    Returns:
        The start time in clock ticks since boot, or None if there is no such process.
    """
    fields = _read_stat(pid)
    if fields is None or len(fields) < 20:
        return None
    try:
        return int(fields[19])  # field 22; fields[0] is field 3
    except ValueError:
        return None


def process_state(pid: int) -> str | None:
    """The state letter of a process (field 3 of ``/proc/<pid>/stat``).

    Args:
        pid: The process id.

    Returns:
        ``"R"``, ``"S"``, ``"D"``, ``"Z"`` (exited, not yet reaped), ... or None if there is no
        such process.
    """
    fields = _read_stat(pid)
    return fields[0] if fields else None


@dataclass(eq=False)
class _Watch:
    pid: int
    fd: int
    callback: ExitCallback
    child: bool
    # Touched only by the monitor thread:
    registered: bool = False
    fd_closed: bool = False
    # Set under the monitor's lock by unwatch/detach:
    cancelled: bool = field(default=False)


class ProcessMonitor:
    """Watches processes for their exit, with pidfds and one selector thread.

    The thread starts in the constructor and stops in :meth:`close` (it is a daemon thread so
    that a forgotten ``close`` cannot hang interpreter exit; ``close`` joins it).

    Callbacks run **on the monitor thread**, one at a time, outside the monitor's lock. They
    must be quick: while one runs, no other exit is reported. They may call :meth:`watch`,
    :meth:`unwatch` and :meth:`detach`. An exception in a callback is logged and otherwise
    ignored.

    Args:
        name: Name of the monitor thread.
    """

    def __init__(self, *, name: str = "temoto-procmon") -> None:
        self._lock = threading.Lock()
        self._watches: dict[int, _Watch] = {}
        self._adds: list[_Watch] = []
        self._removes: list[_Watch] = []
        self._closing = False
        self._wake_fd = os.eventfd(0, os.EFD_CLOEXEC | os.EFD_NONBLOCK)
        self._selector = selectors.DefaultSelector()
        self._selector.register(self._wake_fd, selectors.EVENT_READ, None)
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    # --- public API -------------------------------------------------------------------------

    def watch(self, pid: int, callback: ExitCallback, *, child: bool) -> None:
        """Report the exit of a process.

        The pidfd is opened here, in the caller's thread, so a process that is already gone
        raises at once. A process that exits after ``watch`` returns (or that had exited but
        is not yet reaped) is reported exactly once, unless :meth:`unwatch` or :meth:`detach`
        comes first.

        Args:
            pid: The process id.
            callback: ``callback(pid, returncode, signal)``, called on the monitor thread.
            child: True if the process is a child of this process: the monitor reaps it and
                reports its exit code or signal. False for other processes (e.g. re-adopted
                after a restart): their exit is reported with ``returncode`` and ``signal``
                both None, unless the process turns out to be our child after all (a manager
                restarted within the same OS process), which is then reaped and reported as
                a child is.

        Raises:
            ProcessLookupError: If there is no process ``pid`` (already reaped).
            ValueError: If ``pid`` is already watched.
            StateError: If the monitor is closed.
        """
        fd = os.pidfd_open(pid)
        watch = _Watch(pid, fd, callback, child)
        with self._lock:
            problem: Exception | None = None
            if self._closing:
                problem = StateError("the process monitor is closed")
            elif pid in self._watches:
                problem = ValueError(f"process {pid} is already watched")
            else:
                self._watches[pid] = watch
                self._adds.append(watch)
                self._wake()
        if problem is not None:
            os.close(fd)
            raise problem

    def unwatch(self, pid: int) -> bool:
        """Stop watching a process (it is not reaped and not signalled).

        Args:
            pid: The process id.

        Returns:
            True if the watch was removed before its exit was reported (the callback will not
            be called); False if it was not watched, or its exit is already being reported.
        """
        return self._cancel(pid, keep_fd=False) is not None

    def detach(self, pid: int) -> int | None:
        """Stop watching a process and take over a pidfd for it.

        For the caller that wants to wait for (and reap) the process itself, e.g. while
        stopping it. The returned pidfd refers to the same process as the watch did, so there
        is no window in which a reused pid could be confused with it.

        Args:
            pid: The process id.

        Returns:
            A new pidfd the caller owns (and must close), or None if the process was not
            watched or its exit is already being reported (the callback runs or has run).
        """
        return self._cancel(pid, keep_fd=True)

    def watched(self) -> list[int]:
        """The pids being watched.

        Returns:
            The pids, in the order they were added.
        """
        with self._lock:
            return list(self._watches)

    def close(self) -> None:
        """Stop the monitor thread and close every pidfd; processes are left alone.

        Pending exits are not reported. Idempotent.

        Raises:
            Nothing.
        """
        with self._lock:
            if not self._closing:
                self._closing = True
                self._wake()
        if threading.current_thread() is not self._thread:
            self._thread.join()

    def __enter__(self) -> ProcessMonitor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- internals --------------------------------------------------------------------------

    def _cancel(self, pid: int, *, keep_fd: bool) -> int | None:
        """Remove a watch; returns a dup of its pidfd (or -1 if not ``keep_fd``), else None."""
        with self._lock:
            watch = self._watches.pop(pid, None)
            if watch is None:
                return None
            watch.cancelled = True
            # The monitor thread unregisters and closes the original; the caller gets a
            # duplicate, so the selector never sees an fd number closed behind its back.
            dup = os.dup(watch.fd) if keep_fd else -1
            self._removes.append(watch)
            self._wake()
        return dup

    def _wake(self) -> None:
        """Wake the monitor thread (call with the lock held: the fd lives until shutdown)."""
        with contextlib.suppress(BlockingIOError):  # saturated: a wake-up is pending anyway
            os.eventfd_write(self._wake_fd, 1)

    def _release(self, watch: _Watch) -> None:
        """Unregister and close a watch's pidfd (monitor thread only)."""
        if watch.registered:
            self._selector.unregister(watch.fd)
            watch.registered = False
        if not watch.fd_closed:
            os.close(watch.fd)
            watch.fd_closed = True

    def _run(self) -> None:
        try:
            while self._serve_once():
                pass
        except Exception:  # pragma: no cover - a bug; keep the traceback
            logger.exception("process monitor failed; exits are no longer reported")
        finally:
            self._shutdown()

    def _serve_once(self) -> bool:
        """One selector round; False when the monitor is closing."""
        for key, _ in self._selector.select():
            watch: _Watch | None = key.data
            if watch is None:
                if not self._apply_changes():
                    return False
            else:
                self._fired(watch)
        return True

    def _apply_changes(self) -> bool:
        with contextlib.suppress(BlockingIOError):
            os.eventfd_read(self._wake_fd)
        with self._lock:
            adds, self._adds = self._adds, []
            removes, self._removes = self._removes, []
            closing = self._closing
        for watch in adds:
            if not watch.cancelled:
                self._selector.register(watch.fd, selectors.EVENT_READ, watch)
                watch.registered = True
        for watch in removes:
            self._release(watch)
        return not closing

    def _fired(self, watch: _Watch) -> None:
        with self._lock:
            current = self._watches.get(watch.pid) is watch
            if current:
                del self._watches[watch.pid]
        if not current:
            # Cancelled: the pending removal closes it. Stop listening meanwhile.
            if watch.registered:
                self._selector.unregister(watch.fd)
                watch.registered = False
            return
        returncode, signal_number = self._reap(watch)
        self._release(watch)
        try:
            watch.callback(watch.pid, returncode, signal_number)
        except Exception:
            logger.exception("exit callback for process %d failed", watch.pid)

    @staticmethod
    def _reap(watch: _Watch) -> tuple[int | None, int | None]:
        try:
            result = os.waitid(os.P_PIDFD, watch.fd, os.WEXITED | os.WNOHANG)
        except ChildProcessError:
            if watch.child:
                logger.warning("process %d was reaped by someone else: status unknown", watch.pid)
            return None, None
        if result is None:  # pragma: no cover - a readable pidfd of a child is waitable
            logger.warning("process %d: exit reported but not waitable", watch.pid)
            return None, None
        if result.si_code == os.CLD_EXITED:
            return result.si_status, None
        return None, result.si_status  # CLD_KILLED or CLD_DUMPED

    def _shutdown(self) -> None:
        with self._lock:
            self._closing = True
            leftovers = list(self._watches.values()) + self._adds + self._removes
            self._watches.clear()
            self._adds.clear()
            self._removes.clear()
            os.close(self._wake_fd)  # under the lock: nobody wakes a closed fd
        for watch in leftovers:
            self._release(watch)
        self._selector.close()


def processes_with_environ(entry: bytes) -> list[int]:
    """Pids of processes (zombies included, this one excluded) whose environment has ``entry``.

    Args:
        entry: A whole ``NAME=value`` environment entry.

    Returns:
        The pids, sorted. Processes whose environment cannot be read (gone, not ours) are
        skipped.

    Raises:
        Nothing.
    """
    me = os.getpid()
    found: list[int] = []
    for name in os.listdir("/proc"):
        if not name.isdigit() or int(name) == me:
            continue
        try:
            with open(f"/proc/{name}/environ", "rb") as f:
                environ = f.read()
        except OSError:
            continue
        if entry in environ.split(b"\0"):
            found.append(int(name))
    return sorted(found)
