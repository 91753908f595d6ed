"""Process Manager benchmarks: crash detection, failure propagation, relaunch; supervisord peer.

The child program is ``python -m temoto.testing.child --touch FILE``: before it prints its first
line (``ready <pid>``) it writes its pid to FILE, atomically (a temporary file renamed into
place). The bench watches the directory with inotify (``IN_MOVED_TO``), so "the child runs its
first line" is observed without polling, in the bench's own thread, with ``time.perf_counter``.

Every child is killed with ``os.kill(pid, SIGKILL)``; the time is taken just before the call.
TeMoto runs with the catalog on (a journal in a temporary directory, default ``fsync="group"``).
Every process the bench starts (children, supervisord) is stopped in ``finally`` blocks; a
:class:`temoto.testing.ProcessLeakCheck` marker in the children's environment catches anything
left over, which is killed and reported.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import os
import random
import select
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from bench.common import Results, median, now, percentile
from temoto.core.registrar import LoadContext, Registrar, ResourceServer, Status, StatusUpdate
from temoto.testing import ProcessLeakCheck

REPO = Path(__file__).resolve().parent.parent
CHILD = [sys.executable, "-m", "temoto.testing.child"]
WAIT = 10.0  # seconds before a missing event fails the benchmark
BATCH = 10  # children alive at a time in the crash-detection series

GOAL_DETECT_P50_MS = ("<=", 1.0)
GOAL_DETECT_P99_MS = ("<=", 5.0)
GOAL_RELAUNCH_OVERHEAD_MS = ("<=", 5.0)
GOAL_TWO_LEVELS_MS = ("<=", 10.0)

# ----------------------------------------------------------------------------------- inotify

_IN_MODIFY = 0x00000002
_IN_MOVED_TO = 0x00000080
_EVENT = struct.Struct("iIII")  # wd, mask, cookie, len; then len bytes of name


class DirWatch:
    """inotify on one directory: wait for events about given file names, no polling."""

    def __init__(self, directory: str | Path, mask: int = _IN_MOVED_TO) -> None:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        self._fd = libc.inotify_init1(os.O_NONBLOCK | os.O_CLOEXEC)
        if self._fd < 0:
            raise OSError(ctypes.get_errno(), "inotify_init1 failed")
        if libc.inotify_add_watch(self._fd, os.fsencode(str(directory)), mask) < 0:
            err = ctypes.get_errno()
            os.close(self._fd)
            raise OSError(err, f"inotify_add_watch {directory} failed")
        self._poll = select.poll()
        self._poll.register(self._fd, select.POLLIN)

    def drain(self) -> None:
        """Forget the events that happened so far."""
        with contextlib.suppress(BlockingIOError):
            while os.read(self._fd, 65536):
                pass

    def wait(self, names: set[str], timeout: float = WAIT) -> float:
        """Block until an event about one of ``names``; the perf_counter time of the wake-up."""
        deadline = now() + timeout
        while True:
            left = deadline - now()
            if left <= 0:
                raise TimeoutError(f"no inotify event for {sorted(names)} within {timeout} s")
            if not self._poll.poll(left * 1e3):
                continue
            t = now()
            try:
                data = os.read(self._fd, 65536)
            except BlockingIOError:
                continue
            off = 0
            while off < len(data):
                length = _EVENT.unpack_from(data, off)[3]
                name = data[off + _EVENT.size : off + _EVENT.size + length].rstrip(b"\0")
                off += _EVENT.size + length
                if os.fsdecode(name) in names:
                    return t

    def close(self) -> None:
        os.close(self._fd)


def read_pid(path: Path) -> int | None:
    try:
        return int(path.read_text().strip())
    except (FileNotFoundError, ValueError):
        return None


def wait_pid_file(path: Path, pid: int, timeout: float = WAIT) -> None:
    """Wait (not timed: 2 ms sleeps) until ``path`` holds ``pid``."""
    deadline = time.monotonic() + timeout
    while read_pid(path) != pid:
        if time.monotonic() > deadline:
            raise TimeoutError(f"child {pid} did not write {path} within {timeout} s")
        time.sleep(0.002)


def stats(values: list[float]) -> str:
    return (
        f"n={len(values)}: p50 {median(values):.3g}, p90 {percentile(values, 90):.3g},"
        f" p99 {percentile(values, 99):.3g}, max {max(values):.3g} ms"
    )


# ------------------------------------------------------------------------------ the context


@dataclass
class _Ctx:
    """Temp dir, leak marker and the environment the children get."""

    tmp: Path
    leak: ProcessLeakCheck
    env_extra: dict[str, str] = field(default_factory=dict)

    @classmethod
    def make(cls) -> _Ctx:
        tmp = Path(tempfile.mkdtemp(prefix="temoto-bench-proc-"))
        leak = ProcessLeakCheck()
        path = os.environ.get("PYTHONPATH", "")
        return cls(
            tmp,
            leak,
            {
                "PYTHONPATH": str(REPO) + (os.pathsep + path if path else ""),
                leak.variable: leak.mark,
            },
        )

    def env(self) -> dict[str, str]:
        return {**os.environ, **self.env_extra}

    def child_args(self, touch: Path) -> tuple[str, ...]:
        return ("-m", "temoto.testing.child", "--touch", str(touch))


def plain_spawn_ms(ctx: _Ctx, watch: DirWatch) -> float:
    """subprocess.Popen of the child (as the manager starts it) -> its --touch file (ms)."""
    touch = ctx.tmp / "plain.pid"
    touch.unlink(missing_ok=True)
    watch.drain()
    t0 = now()
    proc = subprocess.Popen(
        [sys.executable, *ctx.child_args(touch)],
        env=ctx.env(),
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.STDOUT,
        close_fds=True,
        start_new_session=True,
    )
    try:
        t1 = watch.wait({touch.name})
        if read_pid(touch) != proc.pid:
            raise RuntimeError("plain spawn: the touch file holds another pid")
    finally:
        with contextlib.suppress(ProcessLookupError):
            proc.kill()
        proc.wait(5)
    return (t1 - t0) * 1e3


# ------------------------------------------------------------------------------------ TeMoto


@dataclass(frozen=True)
class WrapRequest:
    touch: str


@dataclass(frozen=True)
class WrapResponse:
    pid: int


class WrapServer(ResourceServer[WrapRequest, WrapResponse]):
    """A resource that depends on a process resource (the child, touching ``request.touch``)."""

    name = "bench_wrap"
    request_type = WrapRequest
    response_type = WrapResponse

    def __init__(self, ctx: _Ctx) -> None:
        self.ctx = ctx

    def on_load(self, request: WrapRequest, ctx: LoadContext) -> WrapResponse:
        from temoto.managers import ProcessRequest

        proc = ctx.registrar.call(
            "process",
            ProcessRequest(
                sys.executable,
                self.ctx.child_args(Path(request.touch)),
                tuple(self.ctx.env_extra.items()),
            ),
        )
        return WrapResponse(proc.response.pid)

    def on_unload(self, request: WrapRequest, response: WrapResponse) -> None:
        pass


class _Slot:
    """One consumer reference's first FATAL: when its callback ran."""

    def __init__(self) -> None:
        self.t = 0.0
        self.event = threading.Event()

    def callback(self, update: StatusUpdate) -> None:
        if update.status is Status.FATAL and not self.event.is_set():
            self.t = now()
            self.event.set()


Loader = Callable[[Registrar, Path, _Slot], tuple[int, str, bool]]
"""Loads one process for a consumer: (pid, reference id, whether it writes the touch file)."""


def _load_child(ctx: _Ctx) -> Loader:
    from temoto.managers import ProcessRequest

    def load(reg: Registrar, touch: Path, slot: _Slot) -> tuple[int, str, bool]:
        request = ProcessRequest(
            sys.executable, ctx.child_args(touch), tuple(ctx.env_extra.items())
        )
        res = reg.call("process", request, client="bench", on_status=slot.callback)
        return res.response.pid, res.id, True

    return load


def _load_sleep(ctx: _Ctx) -> Loader:
    from temoto.managers import ProcessRequest

    def load(reg: Registrar, touch: Path, slot: _Slot) -> tuple[int, str, bool]:
        # The touch path only makes the request unique; ``sleep`` runs once Popen returned.
        request = ProcessRequest("sleep", ("1000",), (("BENCH_ID", touch.name),))
        res = reg.call("process", request, client="bench", on_status=slot.callback)
        return res.response.pid, res.id, False

    return load


def _load_wrapped(reg: Registrar, touch: Path, slot: _Slot) -> tuple[int, str, bool]:
    res = reg.call("bench_wrap", WrapRequest(str(touch)), client="bench", on_status=slot.callback)
    return res.response.pid, res.id, True


def _temoto_batch(
    reg: Registrar, ctx: _Ctx, load: Loader, k: int, tag: str, serial: int
) -> list[float]:
    """k children loaded through the registrar, all alive, then killed one by one.

    Returns the ms from os.kill to the consumer's FATAL callback, per kill.
    """
    lat: list[float] = []
    batch: list[tuple[int, str, _Slot, Path | None]] = []
    try:
        for j in range(k):
            path = ctx.tmp / f"{tag}-{serial + j}.pid"
            slot = _Slot()
            pid, ref, touches = load(reg, path, slot)
            batch.append((pid, ref, slot, path if touches else None))
        for pid, _, _, touch in batch:
            if touch is not None:
                wait_pid_file(touch, pid)  # the child runs its program
        time.sleep(0.02)
        for pid, _, slot, _ in batch:
            t_kill = now()
            os.kill(pid, signal.SIGKILL)
            if not slot.event.wait(WAIT):
                raise TimeoutError(f"{tag}: no FATAL for killed process {pid}")
            lat.append((slot.t - t_kill) * 1e3)
            time.sleep(0.01)  # let the monitor finish with it
    finally:
        for _, ref, _, _ in batch:
            with contextlib.suppress(Exception):
                reg.release(ref)
    return lat


def _floor_batch(ctx: _Ctx, argv: list[str], k: int, touches: bool, serial: int) -> list[float]:
    """The floor, without TeMoto: k children started as the manager starts them, all alive,
    killed one by one; ms from os.kill until the bench's own pidfd of the child is readable."""
    lat: list[float] = []
    procs: list[tuple[subprocess.Popen[bytes], int]] = []
    try:
        with open(ctx.tmp / "floor.log", "ab") as log:
            for j in range(k):
                touch = ctx.tmp / f"floor-{serial + j}.pid"
                proc = subprocess.Popen(
                    [*argv, "--touch", str(touch)] if touches else argv,
                    env=ctx.env(),
                    stdin=subprocess.DEVNULL,
                    stdout=log,
                    stderr=subprocess.STDOUT,
                    close_fds=True,
                    start_new_session=True,
                )
                procs.append((proc, os.pidfd_open(proc.pid)))
        if touches:
            for j, (proc, _) in enumerate(procs):
                wait_pid_file(ctx.tmp / f"floor-{serial + j}.pid", proc.pid)
        time.sleep(0.02)
        for proc, fd in procs:
            poll = select.poll()
            poll.register(fd, select.POLLIN)
            t_kill = now()
            os.kill(proc.pid, signal.SIGKILL)
            if not poll.poll(WAIT * 1e3):
                raise TimeoutError(f"floor: process {proc.pid} did not exit")
            lat.append((now() - t_kill) * 1e3)
            time.sleep(0.01)
    finally:
        for proc, fd in procs:
            with contextlib.suppress(ProcessLookupError):
                proc.kill()
            proc.wait(5)
            os.close(fd)
    return lat


def kill_series(
    reg: Registrar,
    ctx: _Ctx,
    load: Loader,
    n: int,
    tag: str,
    floor: tuple[list[str], bool, int] | None = None,
) -> tuple[list[float], list[float]]:
    """n SIGKILLs through TeMoto, BATCH children alive at a time. With ``floor`` (argv, whether
    it takes --touch, how many), floor batches of the same size follow the first TeMoto
    batches (interleaved) until that many floor kills are done."""
    lat: list[float] = []
    bare: list[float] = []
    serial = 0
    while len(lat) < n:
        k = min(BATCH, n - len(lat))
        lat += _temoto_batch(reg, ctx, load, k, tag, serial)
        if floor is not None and len(bare) < floor[2]:
            bare += _floor_batch(ctx, floor[0], min(k, floor[2] - len(bare)), floor[1], serial)
        serial += k
    return lat, bare


class _SpawnClock:
    """Records perf_counter() whenever anything in this process calls subprocess.Popen."""

    def __enter__(self) -> list[float]:
        self.calls: list[float] = []
        self.real = real = subprocess.Popen
        calls = self.calls

        class Clocked(real):  # type: ignore[valid-type, misc]
            def __init__(self, *args: Any, **kwargs: Any) -> None:
                calls.append(now())
                super().__init__(*args, **kwargs)

        subprocess.Popen = Clocked  # type: ignore[misc]
        return calls

    def __exit__(self, *exc: object) -> None:
        subprocess.Popen = self.real  # type: ignore[misc]


def relaunch_series(
    reg: Registrar, ctx: _Ctx, watch: DirWatch, n: int
) -> tuple[list[float], list[float], list[float]]:
    """Kill -> relaunched child's first line (ms), interleaved with plain spawns (ms).

    Also returns kill -> the manager's Popen call for the new child (ms).
    """
    from temoto.managers import ProcessManagerClient

    touch = ctx.tmp / "relaunch.pid"
    relaunch: list[float] = []
    plain: list[float] = []
    to_spawn: list[float] = []
    # Default policy ("relaunch"); no relaunch budget, so 100 kills in a minute are allowed.
    with (
        ProcessManagerClient(reg, "bench-relaunch", max_relaunches=None) as client,
        _SpawnClock() as spawns,
    ):
        handle = client.load(sys.executable, *ctx.child_args(touch), env=ctx.env_extra)
        wait_pid_file(touch, handle.pid)
        for i in range(n + 1):
            if i % 2:  # alternate the order, so drift and after-effects hit both alike
                plain_ms = plain_spawn_ms(ctx, watch)
            time.sleep(0.02)
            old = handle.pid
            old_count = handle.relaunches
            watch.drain()
            spawns.clear()
            t_kill = now()
            os.kill(old, signal.SIGKILL)
            while True:
                t_new = watch.wait({touch.name})
                pid = read_pid(touch)
                if pid is not None and pid != old:
                    break
            t_spawn = spawns[0] if spawns else None  # None: the manager bypassed the wrapper
            deadline = time.monotonic() + WAIT
            while handle.relaunches == old_count or handle.pid != pid:
                if time.monotonic() > deadline:
                    raise TimeoutError("relaunch: the handle was not updated")
                time.sleep(0.001)
            if not i % 2:
                time.sleep(0.02)
                plain_ms = plain_spawn_ms(ctx, watch)
            if i:  # the first one is a warm-up
                relaunch.append((t_new - t_kill) * 1e3)
                if t_spawn is not None:
                    to_spawn.append((t_spawn - t_kill) * 1e3)
                plain.append(plain_ms)
    return relaunch, plain, to_spawn


def temoto_series(quick: bool, ctx: _Ctx, out: Results) -> list[float]:
    """The TeMoto metrics; returns the plain-spawn samples (for the supervisord comparison)."""
    from temoto.managers import ProcessManager

    kills = 10 if quick else 100
    floors = 4 if quick else 100  # kills of the floor series (no TeMoto)
    extra = 4 if quick else 50  # two-level failures, sleep children
    relaunches = 5 if quick else 100
    reg = Registrar("bench", catalog=ctx.tmp / "catalog.tjl")
    manager = ProcessManager(reg, log_dir=ctx.tmp / "logs", grace=2.0)
    reg.register(WrapServer(ctx))
    watch = DirWatch(ctx.tmp)
    child = _load_child(ctx)
    try:
        kill_series(reg, ctx, child, 3, "warmup", (CHILD, True, 3))
        detect, bare = kill_series(reg, ctx, child, kills, "detect", (CHILD, True, floors))
        levels, _ = kill_series(reg, ctx, _load_wrapped, extra, "two")
        small, bare_small = kill_series(
            reg, ctx, _load_sleep(ctx), extra, "sleep", (["sleep", "1000"], False, extra)
        )
        relaunch, plain, to_spawn = relaunch_series(reg, ctx, watch, relaunches)
    finally:
        watch.close()
        for ref in reg.references():
            if not ref.holder:
                with contextlib.suppress(Exception):
                    reg.release(ref.id)
        manager.shutdown()
        reg.close()

    q = " (quick mode)" if quick else ""
    out.add(
        "crash_detect_p50_ms",
        median(detect),
        "ms",
        f"{kills} SIGKILLs{q} of python -m temoto.testing.child: os.kill -> consumer's FATAL"
        f" callback; {BATCH} children alive",
        GOAL_DETECT_P50_MS,
    )
    out.add("crash_detect_p99_ms", percentile(detect, 99), "ms", stats(detect), GOAL_DETECT_P99_MS)
    out.add(
        "crash_detect_bare_pidfd_p50_ms",
        median(bare),
        "ms",
        "floor, no TeMoto: os.kill -> the bench's own pidfd of the same child readable"
        f" (batches interleaved with the above); {stats(bare)}",
    )
    out.add(
        "crash_detect_sleep_p50_ms",
        median(small),
        "ms",
        f"as crash_detect_p50_ms with /bin/sleep children (small: fast teardown); {stats(small)}",
    )
    out.add(
        "crash_detect_sleep_bare_pidfd_p50_ms",
        median(bare_small),
        "ms",
        f"floor for /bin/sleep children; {stats(bare_small)}",
    )
    out.add(
        "failure_two_levels_ms",
        median(levels),
        "ms",
        f"{extra} SIGKILLs{q}: process <- bench_wrap resource <- consumer; kill -> consumer's"
        f" callback; {stats(levels)}",
        GOAL_TWO_LEVELS_MS,
    )
    out.add(
        "relaunch_overhead_ms",
        median(relaunch) - median(plain),
        "ms",
        f"{relaunches} kills{q}: median(kill -> relaunched child's first line)"
        " - median(Popen -> first line), interleaved",
        GOAL_RELAUNCH_OVERHEAD_MS,
    )
    if not to_spawn:
        out.notes.append(
            "relaunch_kill_to_spawn_ms skipped: the Process Manager no longer calls"
            " subprocess.Popen through the module attribute the bench wraps"
        )
    else:
        out.add(
            "relaunch_kill_to_spawn_ms",
            median(to_spawn),
            "ms",
            f"kill -> the manager calls Popen for the new child (wrapped Popen); {stats(to_spawn)}",
            GOAL_RELAUNCH_OVERHEAD_MS,
        )
    out.add(
        "relaunch_ms", median(relaunch), "ms", f"kill -> relaunched first line; {stats(relaunch)}"
    )
    out.add("plain_spawn_ms", median(plain), "ms", f"Popen -> first line; {stats(plain)}")
    return plain


# ------------------------------------------------------------------------------- supervisord

_SUPERVISORD_CONF = """\
[unix_http_server]
file={tmp}/supervisor.sock

[supervisord]
nodaemon=true
logfile={tmp}/supervisord.log
loglevel=info
pidfile={tmp}/supervisord.pid
childlogdir={tmp}

[rpcinterface:supervisor]
supervisor.rpcinterface_factory = supervisor.rpcinterface:make_main_rpcinterface

[program:child]
command={command}
autostart=true
autorestart=true
startsecs=0
startretries=1000
stdout_logfile={tmp}/child.out
stderr_logfile={tmp}/child.err
"""


def _supervisor_version() -> str | None:
    try:
        import importlib.util
        from importlib.metadata import version

        if importlib.util.find_spec("supervisor") is None:
            return None

        return version("supervisor")
    except Exception:
        return None


def _wait_log(log: Path, offset: int, watch: DirWatch, text: str) -> float:
    """perf_counter time at which the bench saw the write that put ``text`` in the log.

    ``watch`` (IN_MODIFY on the log's directory) must have been drained before the event.
    """
    deadline = now() + WAIT
    needle = text.encode()
    seen = b""
    with open(log, "rb") as f:
        f.seek(offset)
        while True:
            t = watch.wait({log.name}, max(0.001, deadline - now()))
            seen += f.read()
            if needle in seen:
                return t


def supervisord_series(quick: bool, ctx: _Ctx, out: Results, plain: list[float]) -> None:
    ver = _supervisor_version()
    if ver is None:
        out.notes.append(
            "supervisor is not importable: peer_supervisord_* skipped (pip install supervisor;"
            " it is not a project dependency)"
        )
        return
    kills = 1 if quick else 100  # each takes about a second: supervisord polls once a second
    tmp = ctx.tmp / "supervisord"
    tmp.mkdir()
    touch = tmp / "child.pid"
    conf = tmp / "supervisord.conf"
    log = tmp / "supervisord.log"
    conf.write_text(
        _SUPERVISORD_CONF.format(
            tmp=tmp, command=" ".join([sys.executable, *ctx.child_args(touch)])
        )
    )
    rng = random.Random(20261121)
    watch = DirWatch(tmp)
    logwatch = DirWatch(tmp, _IN_MODIFY)
    sv = subprocess.Popen(  # children inherit its environment (PYTHONPATH, leak marker)
        [sys.executable, "-m", "supervisor.supervisord", "-n", "-c", str(conf)],
        env=ctx.env(),
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    exited: list[float] = []
    restarted: list[float] = []
    pid: int | None = None
    try:
        watch.wait({touch.name}, 30)
        pid = read_pid(touch)
        for i in range(kills + 1):
            time.sleep(rng.uniform(0.05, 0.25))
            assert pid is not None
            offset = log.stat().st_size
            watch.drain()
            logwatch.drain()
            t_kill = now()
            os.kill(pid, signal.SIGKILL)
            t_exit = _wait_log(log, offset, logwatch, "exited: child (terminated by SIGKILL")
            while True:
                t_new = watch.wait({touch.name})
                new = read_pid(touch)
                if new is not None and new != pid:
                    break
            pid = new
            if i:  # the first kill is a warm-up
                exited.append((t_exit - t_kill) * 1e3)
                restarted.append((t_new - t_kill) * 1e3)
    finally:
        # Not measured: SIGKILL supervisord, then its child (a SIGTERM made supervisord stop
        # the child and exit at its next once-a-second poll: about 1.1 s of the quick run).
        # The child runs in a process group of its own, so it is killed by its pid.
        with contextlib.suppress(ProcessLookupError):
            os.killpg(sv.pid, signal.SIGKILL)
        sv.wait(5)
        if pid is not None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        watch.close()
        logwatch.close()

    what = (
        f"supervisor {ver}, {kills} SIGKILL{'s' * (kills != 1)}{' (quick mode)' if quick else ''}"
    )
    out.add(
        "peer_supervisord_detect_p50_ms",
        median(restarted),
        "ms",
        f"{what}: kill -> supervisord's relaunched child runs its first line (--touch file)",
    )
    out.add("peer_supervisord_detect_p90_ms", percentile(restarted, 90), "ms", stats(restarted))
    out.add(
        "peer_supervisord_relaunch_overhead_ms",
        median(restarted) - median(plain),
        "ms",
        "as relaunch_overhead_ms: peer_supervisord_detect_p50_ms - plain_spawn_ms",
    )
    out.add(
        "peer_supervisord_exit_logged_p50_ms",
        median(exited),
        "ms",
        "kill -> supervisord logs 'exited: child (terminated by SIGKILL)' (it reaped the child)",
    )
    out.add("peer_supervisord_exit_logged_p90_ms", percentile(exited, 90), "ms", stats(exited))


# ------------------------------------------------------------------------------------- group


def bench_process(quick: bool) -> Results:
    out = Results()
    ctx = _Ctx.make()
    try:
        plain = temoto_series(quick, ctx, out)
        supervisord_series(quick, ctx, out, plain)
    finally:
        leaked = ctx.leak.kill_leftovers()
        shutil.rmtree(ctx.tmp, ignore_errors=True)
    if leaked:
        out.notes.append(f"processes left running were killed: {leaked}")
    return out
