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
import ctypes
import logging
import os
import queue
import selectors
import signal
import subprocess
import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, cast

from temoto.errors import StateError

__all__ = [
    "ExitCallback",
    "ProcessMonitor",
    "guard_group",
    "guard_pid",
    "process_start_time",
    "process_state",
    "spawn",
    "unguard_group",
]

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


# ============================================================================ spawning

#: ``prctl`` option number of PR_SET_PDEATHSIG (``<linux/prctl.h>``).
_PR_SET_PDEATHSIG = 1

#: The guard process (see :class:`_Guard`), run as ``python -I -S -c _GUARD_SOURCE``. It is a
#: string, not a module, so that it starts in ~10 ms without importing ``site`` or ``temoto``.
#: Protocol on its standard input, one line each: ``+ PGID TOKEN GRACE`` (a group to stop if
#: this process dies; TOKEN is a whole ``NAME=value`` environment entry that its members
#: carry), ``- PGID`` (forget it). End of input (this process is gone, however it ended):
#: SIGTERM every remembered group that still has a member carrying its token, SIGKILL what is
#: left after GRACE seconds, then exit.
_GUARD_SOURCE = r"""
import os, signal, time
for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
    signal.signal(s, signal.SIG_IGN)
groups = {}
buf = b""
while True:
    try:
        data = os.read(0, 65536)
    except InterruptedError:
        continue
    if not data:
        break
    buf += data
    *lines, buf = buf.split(b"\n")
    for line in lines:
        f = line.split()
        if len(f) == 4 and f[0] == b"+":
            groups[int(f[1])] = (f[2], float(f[3]))
        elif len(f) == 2 and f[0] == b"-":
            groups.pop(int(f[1]), None)

def ours(pgid, token):
    members, marked = 0, False
    for name in os.listdir("/proc"):
        if not name.isdigit():
            continue
        try:
            with open("/proc/" + name + "/stat", "rb") as fh:
                st = fh.read().rpartition(b")")[2].split()
            if len(st) < 3 or st[0] in (b"Z", b"X", b"x") or int(st[2]) != pgid:
                continue
            members += 1
            with open("/proc/" + name + "/environ", "rb") as fh:
                marked = marked or token in fh.read().split(b"\0")
        except OSError:
            continue
    return members > 0 and marked

def kill(pgid, sig):
    try:
        os.killpg(pgid, sig)
    except OSError:
        pass

start = time.monotonic()
live = {}
for pgid, (token, grace) in groups.items():
    if ours(pgid, token):
        kill(pgid, signal.SIGTERM)
        live[pgid] = (token, start + grace)
while live:
    time.sleep(0.01)
    for pgid, (token, deadline) in list(live.items()):
        if not ours(pgid, token):
            del live[pgid]
        elif time.monotonic() >= deadline:
            kill(pgid, signal.SIGKILL)
            del live[pgid]
"""


def _load_prctl() -> Callable[..., int] | None:
    """The C library's ``prctl`` through ctypes (resolved in the parent), or None."""
    try:
        fn = ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):  # pragma: no cover - not glibc/musl on Linux
        return None
    fn.argtypes = [ctypes.c_int, ctypes.c_ulong, ctypes.c_ulong, ctypes.c_ulong, ctypes.c_ulong]
    fn.restype = ctypes.c_int
    return cast("Callable[..., int]", fn)


@dataclass(eq=False)
class _Job:
    run: Callable[[], Any]
    done: threading.Event = field(default_factory=threading.Event)
    result: Any = None
    error: BaseException | None = None


class _Spawner:
    """The one long-lived thread of this process that forks children (see :func:`spawn`).

    It belongs to the OS process, not to any object, and is never joined: it must outlive
    every child it forked. It is therefore named ``process-spawner``, outside the
    ``temoto-`` prefix of threads that an owner joins on shutdown.
    """

    def __init__(self) -> None:
        self.prctl = _load_prctl()
        self.jobs: queue.SimpleQueue[_Job] = queue.SimpleQueue()
        self.thread = threading.Thread(target=self._run, name="process-spawner", daemon=True)
        self.thread.start()

    def call(self, run: Callable[[], Any]) -> Any:
        if threading.current_thread() is self.thread:
            return run()
        job = _Job(run)
        self.jobs.put(job)
        job.done.wait()
        if job.error is not None:
            raise job.error
        return job.result

    def _run(self) -> None:
        while True:
            job = self.jobs.get()
            try:
                job.result = job.run()
            except BaseException as err:  # handed to the caller
                job.error = err
            finally:
                job.done.set()
            del job


class _Guard:
    """A helper process that stops registered process groups when this process dies.

    It is started on the first registration, in its own session (a Ctrl-C or a signal to
    this process's group does not reach it), with an empty environment (it is not one of
    "our" processes for leak checks: it exits by itself), ignoring SIGINT, SIGTERM and
    SIGHUP. It reads a pipe whose only writer is this process: end of input means this process
    is gone, SIGKILL included. If it is killed, the next registration starts a new one and
    hands it every group still registered.
    """

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.fd = -1
        self.pid = 0
        self.groups: dict[int, str] = {}

    def _start(self) -> None:
        read_fd, write_fd = os.pipe2(os.O_CLOEXEC)
        try:
            proc = subprocess.Popen(
                [sys.executable, "-I", "-S", "-c", _GUARD_SOURCE],
                stdin=read_fd,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
                close_fds=True,
                start_new_session=True,
                env={},
            )
        except BaseException:
            os.close(write_fd)
            raise
        finally:
            os.close(read_fd)
        # It outlives this process on purpose and is never waited for (it exits after the end
        # of its input; init reaps it): keep subprocess from polling it.
        proc.returncode = 0
        self.fd, self.pid = write_fd, proc.pid

    def add(self, pgid: int, line: str) -> None:
        with self.lock:
            self.groups[pgid] = line
            self._send(line)

    def remove(self, pgid: int) -> None:
        with self.lock:
            if self.groups.pop(pgid, None) is not None:
                self._send(f"- {pgid}")

    def _send(self, line: str) -> None:
        for attempt in (1, 2):
            try:
                if self.fd < 0:
                    self._start()
                    # A new guard (the first, or after one was killed) learns every group.
                    text = "".join(f"{g}\n" for g in self.groups.values())
                else:
                    text = line + "\n"
                os.write(self.fd, text.encode())
                return
            except OSError as err:
                if self.fd >= 0:
                    os.close(self.fd)
                    self.fd, self.pid = -1, 0
                if attempt == 2:
                    logger.error(
                        "cannot start the process guard (%s): grandchildren may outlive a"
                        " crash of this process",
                        err,
                    )

    def forget_after_fork(self) -> None:
        if self.fd >= 0:
            with contextlib.suppress(OSError):
                os.close(self.fd)
        self.lock = threading.Lock()
        self.fd, self.pid, self.groups = -1, 0, {}


_state_lock = threading.Lock()
_spawner: _Spawner | None = None
_guard = _Guard()


def _forget_after_fork() -> None:
    """In a forked child: its parent's spawner thread does not exist here, nor its guard."""
    global _spawner, _state_lock
    _spawner = None
    _state_lock = threading.Lock()
    _guard.forget_after_fork()


os.register_at_fork(after_in_child=_forget_after_fork)


def _the_spawner() -> _Spawner:
    global _spawner
    with _state_lock:
        if _spawner is None:
            _spawner = _Spawner()
        return _spawner


def spawn(
    argv: list[str], *, death_signal: int | None = signal.SIGTERM, **popen: Any
) -> subprocess.Popen[bytes]:
    """Start a child process that gets ``death_signal`` when this process dies.

    The parent-death signal (Linux ``PR_SET_PDEATHSIG``) is set in the child between fork and
    exec. The kernel sends it when the *thread* that forked the child ends, not the process, so
    every child is forked by one daemon thread, ``temoto-spawner``, that lives as long as this
    process. The child then checks that its parent is still the process that forked it (the
    parent may have died before the signal was set): if not, it sends itself the signal.

    Args:
        argv: The command line.
        death_signal: The signal for the child when this process dies, or None for none.
        **popen: Keyword arguments for :class:`subprocess.Popen` (not ``preexec_fn``).

    Returns:
        The Popen object.

    Raises:
        OSError: Starting the program failed.
        ValueError: Bad Popen arguments (``preexec_fn`` among them).
    """
    if "preexec_fn" in popen:
        raise ValueError("spawn() cannot take a preexec_fn: it sets its own")
    spawner = _the_spawner()
    if death_signal is None or spawner.prctl is None:
        return cast(
            "subprocess.Popen[bytes]", spawner.call(lambda: subprocess.Popen(argv, **popen))
        )
    prctl, sig, parent = spawner.prctl, int(death_signal), os.getpid()

    def in_child() -> (
        None
    ):  # after fork, before exec: no locks, no logging, no allocation-heavy work
        prctl(_PR_SET_PDEATHSIG, sig, 0, 0, 0)
        if os.getppid() != parent:
            os.kill(os.getpid(), sig)
            os._exit(128 + sig)

    return cast(
        "subprocess.Popen[bytes]",
        spawner.call(lambda: subprocess.Popen(argv, preexec_fn=in_child, **popen)),
    )


def guard_group(pgid: int, token_entry: str, grace: float) -> None:
    """Have the guard process stop a process group if this process dies (SIGKILL included).

    Args:
        pgid: The group.
        token_entry: A whole ``NAME=value`` environment entry its members carry; a group with
            no such member (its id reused by others) is left alone.
        grace: Seconds between SIGTERM and SIGKILL.
    """
    _guard.add(pgid, f"+ {pgid} {token_entry} {grace:.3f}")


def unguard_group(pgid: int) -> None:
    """Forget a group given to :func:`guard_group` (it was stopped).

    Args:
        pgid: The group.
    """
    _guard.remove(pgid)


def guard_pid() -> int:
    """The guard process's pid, or 0 if none was started (for tests).

    Returns:
        The pid.
    """
    return _guard.pid
