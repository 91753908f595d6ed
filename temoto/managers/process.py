"""The Process Manager: operating-system processes as registrar resources.

:class:`ProcessManager` is the ``"process"`` server on a :class:`~temoto.core.registrar.Registrar`.
A :class:`ProcessRequest` (executable, arguments, extra environment, working directory) loads
one process; equal requests share it. The manager notices an exit within milliseconds (pidfds on
one monitor thread, see :mod:`temoto.managers._procmon`) and reports it as ``FATAL`` to every
consumer; releasing the last reference stops the process's whole process group (SIGTERM, then
SIGKILL after a grace period). After a restart from the registrar's catalog it re-adopts the
processes that still run.

:class:`~temoto.managers.process_client.ProcessManagerClient` is the consumers' side.

See ``docs/process-manager.md`` for the design.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import signal
import subprocess
import threading
import time
import uuid
import weakref
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

from temoto.core.registrar import (
    LoadContext,
    Registrar,
    ResourceInfo,
    ResourceServer,
    Status,
)
from temoto.errors import (
    ResourceError,
    StateError,
)
from temoto.managers._process_stop import (
    DEAD_STATES,
    TOKEN_VARIABLE,
    GroupStopper,
    ProcessRecord,
    describe_exit,
    open_if_same,
    signal_group,
    wait_readable,
)
from temoto.managers._procmon import (
    ProcessMonitor,
    guard_group,
    process_start_time,
    process_state,
    spawn,
    unguard_group,
)

__all__ = [
    "TOKEN_VARIABLE",
    "ProcessManager",
    "ProcessRequest",
    "ProcessResponse",
    "hurry_all",
]

logger = logging.getLogger(__name__)


#: Every ProcessManager of this OS process, for :func:`hurry_all` (weakly: no lifetime effect).
_MANAGERS: weakref.WeakSet[ProcessManager] = weakref.WeakSet()


def hurry_all() -> None:
    """:meth:`ProcessManager.hurry` every manager of this process (for a second Ctrl-C).

    Safe to call from a signal handler.
    """
    for manager in list(_MANAGERS):
        manager.hurry()


# ============================================================================ request / response


def _check_text(value: object, what: str) -> str:
    if not isinstance(value, str):
        raise TypeError(f"{what} must be a str, not {type(value).__name__}")
    if "\0" in value:
        raise ValueError(f"{what} contains a NUL character: {value!r}")
    return value


@dataclass(frozen=True)
class ProcessRequest:
    """What process to run. Equal requests share one process.

    Lists (what JSON gives back) are accepted for ``args`` and ``env`` and stored as tuples;
    ``env`` may also be given as a mapping, and is stored sorted by name, so requests that differ
    only in the order of their variables are equal.

    Attributes:
        executable: A program name looked up on ``PATH`` (``shutil.which``), or a path to an
            executable file (absolute, or relative to ``cwd`` if it contains a ``/``).
        args: The arguments (without the program name).
        env: Extra environment variables as ``(name, value)`` pairs, added to the manager's
            own environment.
        cwd: The working directory, or None for the manager's.

    Raises:
        TypeError: A field has the wrong type (e.g. ``args`` given as one string).
        ValueError: An empty executable, a NUL character, a bad or repeated variable name.
    """

    executable: str
    args: tuple[str, ...] = ()
    env: tuple[tuple[str, str], ...] = ()
    cwd: str | None = None

    def __post_init__(self) -> None:
        if not _check_text(self.executable, "executable"):
            raise ValueError("executable is empty")
        args: object = self.args
        if isinstance(args, str | bytes) or not isinstance(args, Iterable):
            raise TypeError(f"args must be a sequence of str, not {type(args).__name__}")
        object.__setattr__(
            self, "args", tuple(_check_text(a, f"args[{i}]") for i, a in enumerate(args))
        )
        env: object = self.env
        if isinstance(env, Mapping):
            env = list(env.items())
        if isinstance(env, str | bytes) or not isinstance(env, Iterable):
            raise TypeError(f"env must be (name, value) pairs, not {type(env).__name__}")
        pairs: dict[str, str] = {}
        for i, pair in enumerate(env):
            if isinstance(pair, str | bytes) or not isinstance(pair, Iterable):
                raise TypeError(f"env[{i}] must be a (name, value) pair, not {pair!r}")
            items = tuple(pair)
            if len(items) != 2:
                raise TypeError(f"env[{i}] must be a (name, value) pair, not {pair!r}")
            name = _check_text(items[0], f"env[{i}] name")
            value = _check_text(items[1], f"env[{i}] value ({name})")
            if not name or "=" in name:
                raise ValueError(f"env[{i}]: bad variable name {name!r}")
            if name in pairs:
                raise ValueError(f"env: variable {name!r} is given twice")
            pairs[name] = value
        object.__setattr__(self, "env", tuple(sorted(pairs.items())))
        cwd: object = self.cwd
        if cwd is not None:
            if isinstance(cwd, os.PathLike):
                cwd = os.fspath(cwd)
            if not _check_text(cwd, "cwd"):
                raise ValueError("cwd is empty (use None for the manager's directory)")
            object.__setattr__(self, "cwd", cwd)

    @property
    def argv(self) -> list[str]:
        """The command line as given (``[executable, *args]``), before the executable is found."""
        return [self.executable, *self.args]


def _check_int(value: object, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise TypeError(f"{what} must be an int, not {type(value).__name__}")
    return value


@dataclass(frozen=True)
class ProcessResponse:
    """A running process, as the manager started it.

    Attributes:
        pid: Its process id.
        pgid: Its process group id (it leads its own session and group, so equal to ``pid``).
        start_time: The kernel's start time (clock ticks since boot, ``/proc/<pid>/stat``
            field 22); with ``pid`` it identifies the process across a manager restart.
        started_at: Wall-clock time it was started (seconds since the epoch).
        token: Its spawn token, the value of ``TEMOTO_PROCESS_TOKEN`` in its environment
            (and in that of everything it starts); "" if unknown.

    Raises:
        TypeError: A field has the wrong type.
    """

    pid: int
    pgid: int
    start_time: int
    started_at: float
    token: str = ""

    def __post_init__(self) -> None:
        for name in ("pid", "pgid", "start_time"):
            _check_int(getattr(self, name), name)
        if not isinstance(self.token, str):
            raise TypeError(f"token must be a str, not {type(self.token).__name__}")
        started: object = self.started_at
        if isinstance(started, bool) or not isinstance(started, int | float):
            raise TypeError(f"started_at must be a float, not {type(started).__name__}")
        object.__setattr__(self, "started_at", float(started))


# ============================================================================ the server


class ProcessManager(ResourceServer[ProcessRequest, ProcessResponse]):
    """The ``"process"`` resource server: starts, watches and stops processes.

    Creating it registers it on the registrar (with a restored catalog, that is when the
    processes of the previous run are re-adopted or reported dead).

    * **Load** validates the request (``ValueError`` for a program that cannot be found or a
      working directory that does not exist), starts the process in a new session (so it leads
      its own process group), stdin from ``/dev/null``, and returns as soon as the process
      exists; it does not wait for the program to be "ready". Its output (stdout and stderr
      together) goes to ``<log_dir>/<pid>.log`` with ``log_dir``, to this process's stdout and
      stderr with ``inherit_output=True``, else to ``/dev/null``. Inheriting is off by default:
      holding its stdout/stderr, processes would keep a pipe to a supervisor open (no EOF
      while they run), or die of SIGPIPE when its reader is gone.
    * **Exit**: when a process exits on its own, every consumer gets ``FATAL`` with the exit
      code or signal, within milliseconds.
    * **Unload** (last reference released) sends SIGTERM to the process group, waits up to
      ``grace`` seconds, then sends SIGKILL to whatever is left of the group (grandchildren
      included, also after the leader exited). It returns only when the leader is gone: the
      catalog forgets the resource when ``on_unload`` returns, and it must never forget a live
      process.
    * **Restore**: a process that still runs with the recorded pid *and* start time is
      re-adopted (watched, stoppable); anything else is reported ``FATAL`` "died while the
      manager was down". A pid reused by another process is never adopted.
    * **Death of this process** (``die_with_manager``, the default): every process gets SIGTERM
      from the kernel when this OS process ends, SIGKILL included (the Linux parent-death
      signal), and a guard process then SIGTERMs the rest of its group (grandchildren) and
      SIGKILLs whatever is left after ``grace``. See ``docs/process-manager.md`` for what this
      covers and what it does not.

    Args:
        registrar: The registrar to serve on (``register`` is called here).
        grace: Seconds between SIGTERM and SIGKILL when stopping.
        kill_timeout: Seconds to wait for a SIGKILLed process to disappear before giving up
            with an error (only a process stuck in the kernel takes that long).
        log_dir: Directory for the processes' output files (created if missing).
        inherit_output: Without ``log_dir``: let the processes write to this process's
            stdout and stderr (instead of ``/dev/null``).
        die_with_manager: Stop the processes when this OS process dies, however it dies
            (default). False lets them outlive it, for a manager restarted from its catalog
            to re-adopt them.

    Raises:
        ValueError: A negative ``grace``, both ``log_dir`` and ``inherit_output``, or a server
            named ``"process"`` is registered.
    """

    name: ClassVar[str] = "process"
    request_type: ClassVar[type[Any]] = ProcessRequest
    response_type: ClassVar[type[Any]] = ProcessResponse

    def __init__(
        self,
        registrar: Registrar,
        *,
        grace: float = 5.0,
        kill_timeout: float = 5.0,
        log_dir: str | os.PathLike[str] | None = None,
        inherit_output: bool = False,
        die_with_manager: bool = True,
    ) -> None:
        if grace < 0 or kill_timeout < 0:
            raise ValueError("grace and kill_timeout must be >= 0")
        if log_dir is not None and inherit_output:
            raise ValueError("give log_dir or inherit_output, not both")
        self.registrar = registrar
        self.log_dir = Path(log_dir) if log_dir is not None else None
        self.inherit_output = bool(inherit_output)
        self._lock = threading.Lock()
        # Readable once hurry() is called: ends every grace period then and from then on.
        self._hurry_fd = os.eventfd(0, os.EFD_CLOEXEC | os.EFD_NONBLOCK)
        weakref.finalize(self, os.close, self._hurry_fd)
        # Holds grace, kill_timeout and die_with_manager (the properties below read it).
        self._stopper = GroupStopper(
            float(grace),
            float(kill_timeout),
            self._hurry_fd,
            unguard=bool(die_with_manager),
            origin=self.name,
        )
        _MANAGERS.add(self)
        self._procs: dict[int, ProcessRecord] = {}
        self._closed = False
        self._monitor = ProcessMonitor(name="temoto-procmon")
        try:
            registrar.register(self)
        except BaseException:
            self._monitor.close()
            raise

    @property
    def grace(self) -> float:
        """Seconds between SIGTERM and SIGKILL when stopping."""
        return self._stopper.grace

    @grace.setter
    def grace(self, value: float) -> None:
        self._stopper.grace = float(value)

    @property
    def kill_timeout(self) -> float:
        """Seconds to wait for a SIGKILLed process to disappear before giving up."""
        return self._stopper.kill_timeout

    @kill_timeout.setter
    def kill_timeout(self, value: float) -> None:
        self._stopper.kill_timeout = float(value)

    @property
    def die_with_manager(self) -> bool:
        """Whether the processes are stopped when this OS process dies (however it dies)."""
        return self._stopper.unguard

    @die_with_manager.setter
    def die_with_manager(self, value: bool) -> None:
        self._stopper.unguard = bool(value)

    # --------------------------------------------------------------------- hooks

    def on_load(self, request: ProcessRequest, ctx: LoadContext) -> ProcessResponse:
        """Start a process.

        Args:
            request: What to run.
            ctx: The load context (the resource id is kept for status reports).

        Returns:
            The process's pid, process group, start time and start date.

        Raises:
            ValueError: The executable cannot be found or run, or ``cwd`` is not a directory.
            OSError: Starting it failed otherwise.
            StateError: The manager is shut down.
        """
        if self._closed:
            raise StateError("the process manager is shut down")
        argv, cwd = self._resolve(request)
        token = uuid.uuid4().hex
        env = {**os.environ, **dict(request.env), TOKEN_VARIABLE: token}
        # Before the spawn: if this process dies while (or right after) starting the child, the
        # restarted registrar hands the checkpoint to on_abandoned, which finds the child (and
        # anything it started) by this token, pid or not.
        ctx.checkpoint({"token": token})
        log, log_tmp = self._open_log()
        output: Any = log
        if log is None and not self.inherit_output:
            output = subprocess.DEVNULL
        try:
            proc = spawn(
                argv,
                death_signal=signal.SIGTERM if self.die_with_manager else None,
                stdin=subprocess.DEVNULL,
                stdout=output,
                stderr=subprocess.STDOUT if output is not None else None,
                close_fds=True,
                start_new_session=True,
                env=env,
                cwd=cwd,
            )
        except BaseException:
            if log is not None:
                log.close()
                os.unlink(log_tmp)
            raise
        # From here on the monitor waits for (reaps) this child through its pidfd. Marking the
        # Popen object finished keeps subprocess from waiting for it behind the monitor's back
        # (Popen.__del__ and subprocess's clean-up of dropped objects poll their children)
        # and from warning that it "is still running".
        proc.returncode = 0
        pid = proc.pid
        try:
            if log is not None:
                log.close()
                assert self.log_dir is not None
                os.replace(log_tmp, self.log_dir / f"{pid}.log")
            start_time = process_start_time(pid)  # a child is not reaped before we watch it
            if start_time is None:  # pragma: no cover - impossible for an unreaped child
                raise OSError(f"process {pid} vanished right after it was started")
            ctx.checkpoint({"token": token, "pid": pid, "pgid": pid, "start_time": start_time})
            record = ProcessRecord(pid, pid, start_time, request.executable, ctx.resource_id, True)
            if self.die_with_manager:
                guard_group(pid, f"{TOKEN_VARIABLE}={token}", self.grace)
            with self._lock:
                self._procs[pid] = record
            self._monitor.watch(pid, self._on_exit, child=True)
        except BaseException:
            with self._lock:
                self._procs.pop(pid, None)
            self._stopper.kill_at_once(pid)
            if self.die_with_manager:
                unguard_group(pid)
            raise
        logger.info("started process %d: %s", pid, " ".join(argv))
        return ProcessResponse(pid, pid, start_time, time.time(), token)

    def on_unload(self, request: ProcessRequest, response: ProcessResponse) -> None:
        """Stop a process and its whole process group; returns when the leader is gone.

        SIGTERM goes to the group; after ``grace`` seconds SIGKILL goes to what is left. A
        process that already exited is not signalled again, but group members it left behind
        (grandchildren) are stopped the same way.

        Args:
            request: The request it was started for.
            response: The process.

        Raises:
            ResourceError: The process survived SIGKILL for ``kill_timeout`` seconds.
        """
        with self._lock:
            record = self._procs.get(response.pid)
            if record is None or record.start_time != response.start_time:
                record = None
            else:
                record.stopping = True
        if record is None:
            # Not ours in this run: it died while the manager was down (reported on restore).
            # Its pid and group id may belong to others by now; what it started is found by
            # its token.
            self._stopper.stop_leftovers(response.token, f"left-overs of process {response.pid}")
            return
        try:
            pidfd = self._monitor.detach(record.pid)  # None: its exit was already reported
            self._stopper.stop(record, pidfd)
        finally:
            with self._lock:
                self._procs.pop(record.pid, None)

    def on_status(self, resource: ResourceInfo, status: Status, message: str) -> None:
        """Log statuses of this server's resources.

        Args:
            resource: The resource.
            status: Its status.
            message: The message.
        """
        logger.debug("status of %s: %s %s", resource.id, status.name, message)

    def on_restore(self, resource: ResourceInfo) -> tuple[Status, str] | None:
        """Re-adopt a process recorded in the catalog, if it still runs.

        It must still run with the recorded pid **and** start time (a later process that got
        the same pid has another start time and is never adopted).

        Args:
            resource: A restored resource.

        Returns:
            None if it was re-adopted (or had already failed before the restart), else
            ``(FATAL, "... died while the manager was down")``.
        """
        response = resource.response
        if not isinstance(response, ProcessResponse):
            response = ProcessResponse(**response)
        request = resource.request
        executable = getattr(request, "executable", "?")
        if resource.failed:
            return None  # its FATAL was reported before the restart
        if self._adopt(response, resource.id, executable):
            logger.info("re-adopted process %d (%s) for %s", response.pid, executable, resource.id)
            return None
        message = f"process {response.pid} ({executable}) died while the manager was down"
        logger.warning("%s", message)
        return Status.FATAL, message

    def on_abandoned(self, request: ProcessRequest, progress: Mapping[str, Any] | None) -> None:
        """After a restart: stop the process(es) of a load the crash interrupted.

        Args:
            request: The request being loaded.
            progress: The checkpoint of ``on_load``: the spawn token (made before the spawn),
                then pid, group and start time (right after it), or None.
        """
        if not progress:
            return
        token = progress.get("token")
        if "pid" in progress:
            try:
                pid = int(progress["pid"])
                pgid = int(progress["pgid"])
                start = int(progress["start_time"])
            except (KeyError, TypeError, ValueError):
                logger.warning("abandoned load of %s: unusable checkpoint %r", request, progress)
            else:
                pidfd = open_if_same(pid, start)
                if pidfd is not None:
                    logger.warning(
                        "stopping process %d (%s): its load was interrupted",
                        pid,
                        request.executable,
                    )
                    record = ProcessRecord(pid, pgid, start, request.executable, "", False, True)
                    self._stopper.stop(record, pidfd)
        if isinstance(token, str) and token:
            self._stopper.stop_leftovers(token, f"interrupted load of {request.executable}")

    # --------------------------------------------------------------------- lifecycle

    def shutdown(self, *, stop_processes: bool = False) -> None:
        """Stop the monitor thread, and the processes if asked to.

        Idempotent. After it, loads fail with :class:`StateError`. Processes left running
        can be re-adopted by a new manager on a restored registrar (in this OS process, or in
        another one with ``die_with_manager=False``); with ``die_with_manager`` they are
        stopped when this OS process ends. A process that survives SIGKILL is logged.

        Args:
            stop_processes: Stop every process first (all at once: SIGTERM to each group,
                ``grace`` seconds, SIGKILL; see :meth:`hurry`), without reporting their exits
                as failures. For a program that ends: nothing it started outlives it.
        """
        with self._lock:
            self._closed = True
        if stop_processes:
            try:
                self.stop_all()
            except ResourceError as err:
                logger.error("%s", err)
        self._monitor.close()

    def stop_all(self) -> list[int]:
        """Stop every process this manager watches, all at once; returns when they are gone.

        Each process group gets SIGTERM; after ``grace`` seconds (or at once after
        :meth:`hurry`) what is left gets SIGKILL. The exits are not reported as failures; the
        resources stay in the registrar until released (releasing them is then harmless).

        Returns:
            The pids of the group leaders that were stopped.

        Raises:
            ResourceError: A process survived SIGKILL for ``kill_timeout`` seconds.
        """
        with self._lock:
            records = [p for p in self._procs.values() if p.exit is None and not p.stopping]
            for record in records:
                record.stopping = True
        if not records:
            return []
        pidfds: dict[int, ProcessRecord] = {}
        for record in records:
            pidfd = self._monitor.detach(record.pid)
            if pidfd is not None:
                pidfds[pidfd] = record
        deadline = time.monotonic() + self.grace
        termed: set[int] = set()  # the groups that got SIGTERM here
        try:
            for pidfd, record in pidfds.items():
                if not wait_readable([pidfd], 0):
                    signal_group(record.pgid, signal.SIGTERM)
                    termed.add(record.pgid)
            left = set(pidfds) - wait_readable(pidfds, self.grace, self._hurry_fd)
            for pidfd in left:
                signal_group(pidfds[pidfd].pgid, signal.SIGKILL)
            stuck = left - wait_readable(left, self.kill_timeout)
            for pidfd, record in pidfds.items():
                if record.child and pidfd not in stuck:
                    with contextlib.suppress(ChildProcessError):
                        os.waitid(os.P_PIDFD, pidfd, os.WEXITED | os.WNOHANG)
        finally:
            for pidfd in pidfds:
                os.close(pidfd)
        for record in records:
            sent = signal.SIGTERM if record.pgid in termed else None
            self._stopper.stop_members(record, deadline, sent)
            if self.die_with_manager:
                unguard_group(record.pgid)
            with self._lock:
                self._procs.pop(record.pid, None)
        if stuck:
            raise ResourceError(
                f"processes {sorted(pidfds[f].pid for f in stuck)} survived SIGKILL for"
                f" {self.kill_timeout:g} s",
                origin=self.name,
            )
        logger.info("stopped processes %s", [r.pid for r in records])
        return [r.pid for r in records]

    def hurry(self) -> None:
        """Skip the grace periods: SIGKILL what does not stop at once after SIGTERM.

        For a second Ctrl-C: stops running now (in :meth:`stop_all`, :meth:`shutdown` and
        releases, also from another thread) and from then on skip their wait for SIGTERM to
        work. Processes are still stopped and reaped. Safe to call from a signal handler.
        """
        with contextlib.suppress(OSError):
            os.eventfd_write(self._hurry_fd, 1)

    def __enter__(self) -> ProcessManager:
        return self

    def __exit__(self, *exc: object) -> None:
        self.shutdown()

    def running(self) -> list[int]:
        """The pids of the processes this manager watches (started or re-adopted).

        Returns:
            Pids, in the order they were started or adopted.
        """
        with self._lock:
            return [p.pid for p in self._procs.values() if p.exit is None]

    # --------------------------------------------------------------------- internals

    def _resolve(self, request: ProcessRequest) -> tuple[list[str], str | None]:
        cwd = request.cwd
        if cwd is not None and not os.path.isdir(cwd):
            raise ValueError(f"working directory {cwd!r} does not exist or is not a directory")
        exe = request.executable
        if "/" in exe:
            path = exe if os.path.isabs(exe) or cwd is None else os.path.join(cwd, exe)
            if not os.path.isfile(path):
                raise ValueError(f"executable {exe!r} does not exist")
            if not os.access(path, os.X_OK):
                raise ValueError(f"executable {exe!r} is not executable")
            found = os.path.abspath(path)
        else:
            extra = dict(request.env)
            search = extra.get("PATH", os.environ.get("PATH", os.defpath))
            which = shutil.which(exe, path=search)
            if which is None:
                raise ValueError(f"executable {exe!r} was not found on PATH")
            found = which
        return [found, *request.args], cwd

    def _open_log(self) -> tuple[Any, str]:
        if self.log_dir is None:
            return None, ""
        self.log_dir.mkdir(parents=True, exist_ok=True)
        tmp = str(self.log_dir / f".starting-{uuid.uuid4().hex}.log")
        return open(tmp, "ab"), tmp

    def _on_exit(self, pid: int, returncode: int | None, sig: int | None) -> None:
        """Monitor callback (monitor thread): a watched process exited."""
        with self._lock:
            record = self._procs.get(pid)
            if record is None:
                return
            record.exit = (returncode, sig)
            stopping = record.stopping
        message = describe_exit(pid, record.executable, returncode, sig, record.child)
        if stopping:
            logger.debug("%s while being stopped", message)
            return
        logger.warning("%s", message)
        try:
            self.registrar.send_status(record.resource_id, Status.FATAL, message)
        except ResourceError as err:
            logger.error("could not report the exit of process %d: %s", pid, err)

    def _adopt(self, response: ProcessResponse, resource_id: str, executable: str) -> bool:
        pid = response.pid
        if process_start_time(pid) != response.start_time or process_state(pid) in DEAD_STATES:
            return False
        record = ProcessRecord(
            pid, response.pgid, response.start_time, executable, resource_id, False
        )
        if self.die_with_manager and response.token:
            guard_group(response.pgid, f"{TOKEN_VARIABLE}={response.token}", self.grace)
        with self._lock:
            self._procs[pid] = record
        try:
            self._monitor.watch(pid, self._on_exit, child=False)
        except ProcessLookupError:
            with self._lock:
                self._procs.pop(pid, None)
            return False
        # The pidfd now pins the process: check again that it is the same one (the pid could
        # have been reused between the first check and pidfd_open).
        if process_start_time(pid) != response.start_time:
            self._monitor.unwatch(pid)
            with self._lock:
                self._procs.pop(pid, None)
            return False
        return True


# ============================================================================ the client
