"""ProcessMonitor and the child helper program, with real processes."""

from __future__ import annotations

import contextlib
import os
import queue
import select
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from temoto.errors import StateError
from temoto.managers._procmon import ProcessMonitor, process_start_time, process_state
from temoto.managers._procmon import spawn as start_child
from temoto.testing import CHILD_MODULE, child_command

Exit = tuple[int, "int | None", "int | None"]


class Child:
    """A child program started by the test (not by a manager), with its stdout as lines."""

    def __init__(self, *, stdin: bool = False, **opts: object) -> None:
        self.proc = subprocess.Popen(
            child_command(on_stdin=stdin, **opts),  # type: ignore[arg-type]
            stdin=subprocess.PIPE if stdin else subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            start_new_session=True,
        )
        self.pid = self.proc.pid
        self.grandchildren: list[int] = []
        assert self.line() == f"ready {self.pid}"
        for _ in range(int(opts.get("grandchildren", 0))):  # type: ignore[call-overload]
            word, pid = self.line().split()
            assert word == "grandchild"
            self.grandchildren.append(int(pid))

    def line(self) -> str:
        assert self.proc.stdout is not None
        return self.proc.stdout.readline().decode().rstrip("\n")

    def send(self, command: str) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(command.encode() + b"\n")
        self.proc.stdin.flush()

    def close(self) -> None:
        for stream in (self.proc.stdin, self.proc.stdout):
            if stream is not None:
                stream.close()
        # Reaps it if nobody did; returns at once if the monitor already reaped it (ECHILD).
        if self.proc.returncode is None:
            try:
                self.proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


@pytest.fixture
def spawn() -> Iterator[type[Child]]:
    children: list[Child] = []

    class Tracked(Child):
        def __init__(self, **kw: object) -> None:
            super().__init__(**kw)  # type: ignore[arg-type]
            children.append(self)

    yield Tracked
    for child in children:
        for pid in (child.pid, *child.grandchildren):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        child.close()


@pytest.fixture
def monitor() -> Iterator[ProcessMonitor]:
    mon = ProcessMonitor()
    yield mon
    mon.close()


class Exits:
    """Collects exit reports; ``get`` blocks for the next one."""

    def __init__(self) -> None:
        self.queue: queue.Queue[tuple[float, Exit]] = queue.Queue()
        self.thread_names: list[str] = []

    def __call__(self, pid: int, returncode: int | None, sig: int | None) -> None:
        self.thread_names.append(threading.current_thread().name)
        self.queue.put((time.perf_counter(), (pid, returncode, sig)))

    def get(self, timeout: float = 5.0) -> Exit:
        return self.queue.get(timeout=timeout)[1]

    def get_timed(self, timeout: float = 5.0) -> tuple[float, Exit]:
        return self.queue.get(timeout=timeout)


def gone(pid: int) -> bool:
    state = process_state(pid)
    return state is None or state == "Z"


def wait_gone(pid: int, timeout: float = 5.0) -> None:
    """Wait (on a pidfd, no polling) until a process has exited."""
    try:
        fd = os.pidfd_open(pid)
    except ProcessLookupError:
        return
    try:
        ready, _, _ = select.select([fd], [], [], timeout)
        assert ready or gone(pid), f"process {pid} still runs after {timeout} s"
    finally:
        os.close(fd)


# --- the child program ------------------------------------------------------------------------


def test_child_prints_ready_first_and_exits_with_the_code_asked() -> None:
    out = subprocess.run(
        child_command(sleep=0.01, exit_code=7), capture_output=True, check=False, timeout=10
    )
    assert out.returncode == 7
    lines = out.stdout.decode().splitlines()
    assert lines[0].startswith("ready ")
    assert len(lines) == 1


def test_child_runs_as_a_module_too() -> None:
    out = subprocess.run(
        [sys.executable, "-m", CHILD_MODULE, "--exit", "3"],
        capture_output=True,
        check=False,
        timeout=10,
        cwd=Path(__file__).resolve().parents[2],
    )
    assert out.returncode == 3
    assert out.stdout.decode().startswith("ready ")
    assert out.stderr == b""  # no runpy warning: temoto.testing does not import child


def test_child_crash_is_sigabrt_and_bad_options_exit_2() -> None:
    out = subprocess.run(child_command(crash=True), capture_output=True, check=False, timeout=10)
    assert out.returncode == -signal.SIGABRT
    bad = subprocess.run(
        [*child_command(), "--grandchildren", "-1"], capture_output=True, check=False, timeout=10
    )
    assert bad.returncode == 2


def test_child_touch_writes_its_pid(tmp_path: Path) -> None:
    target = tmp_path / "pid"
    out = subprocess.run(
        child_command(exit_code=0, touch=target), capture_output=True, check=False, timeout=10
    )
    assert out.returncode == 0
    assert out.stdout.decode().split()[1] == target.read_text().strip()


def test_child_obeys_stdin_commands(spawn: type[Child]) -> None:
    child = spawn(stdin=True)
    child.send("nonsense")
    child.send("exit 5")
    assert child.proc.wait(timeout=5) == 5
    child = spawn(stdin=True)
    child.send("kill USR1")
    assert child.proc.wait(timeout=5) == -signal.SIGUSR1
    child = spawn(stdin=True)
    child.send("crash")
    assert child.proc.wait(timeout=5) == -signal.SIGABRT


def test_child_ignoring_term_survives_sigterm_and_grandchildren_share_its_group(
    spawn: type[Child], monitor: ProcessMonitor
) -> None:
    child = spawn(ignore_term=True, grandchildren=2)
    assert len(child.grandchildren) == 2
    for pid in child.grandchildren:
        assert os.getpgid(pid) == child.pid
    exits = Exits()
    monitor.watch(child.pid, exits, child=True)
    os.killpg(child.pid, signal.SIGTERM)
    with pytest.raises(queue.Empty):
        exits.get(timeout=0.3)
    assert not gone(child.pid)
    os.killpg(child.pid, signal.SIGKILL)
    assert exits.get() == (child.pid, None, signal.SIGKILL)
    for pid in child.grandchildren:  # killed too; wait until the kernel has torn them down
        wait_gone(pid)


# --- start time -------------------------------------------------------------------------------


def test_start_time_identifies_a_process(spawn: type[Child]) -> None:
    mine = process_start_time(os.getpid())
    assert isinstance(mine, int)
    child = spawn()
    theirs = process_start_time(child.pid)
    assert theirs is not None
    assert theirs >= mine
    assert process_start_time(2**22 + 12345) is None  # above pid_max
    assert process_state(child.pid) in {"R", "S"}


def test_start_time_survives_spaces_and_parentheses_in_the_command_name(
    tmp_path: Path, spawn: type[Child]
) -> None:
    # comm is the executable's base name: a symlink named like this puts ") (" into stat.
    weird = tmp_path / "a) b (c) 9 9"
    weird.symlink_to(sys.executable)
    proc = subprocess.Popen(
        [str(weird), "-I", "-S", "-c", "import signal; print('ready', flush=True); signal.pause()"],
        stdout=subprocess.PIPE,
    )
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline() == b"ready\n"
        with open(f"/proc/{proc.pid}/stat", "rb") as f:
            assert b"(a) b (c) 9 9) " in f.read()
        start = process_start_time(proc.pid)
        assert start is not None
        assert start >= (process_start_time(os.getpid()) or 0)
        assert process_state(proc.pid) in {"R", "S"}
    finally:
        proc.kill()
        proc.wait()
        assert proc.stdout is not None
        proc.stdout.close()


# --- the monitor ------------------------------------------------------------------------------


def test_exit_code_is_reported_on_the_monitor_thread_and_the_child_is_reaped(
    spawn: type[Child], monitor: ProcessMonitor
) -> None:
    child = spawn(stdin=True)
    exits = Exits()
    monitor.watch(child.pid, exits, child=True)
    assert monitor.watched() == [child.pid]
    child.send("exit 3")
    assert exits.get() == (child.pid, 3, None)
    assert exits.thread_names == ["temoto-procmon"]
    assert monitor.watched() == []
    with pytest.raises(ChildProcessError):
        os.waitpid(child.pid, os.WNOHANG)  # already reaped by the monitor
    assert process_state(child.pid) is None


@pytest.mark.parametrize(
    ("command", "expected"),
    [("crash", signal.SIGABRT), ("kill SEGV", signal.SIGSEGV), ("kill TERM", signal.SIGTERM)],
)
def test_death_by_signal_is_reported_as_the_signal(
    spawn: type[Child], monitor: ProcessMonitor, command: str, expected: int
) -> None:
    child = spawn(stdin=True)
    exits = Exits()
    monitor.watch(child.pid, exits, child=True)
    child.send(command)
    assert exits.get() == (child.pid, None, expected)


def test_crash_detection_latency_is_milliseconds(
    spawn: type[Child], monitor: ProcessMonitor
) -> None:
    latencies = []
    for _ in range(3):
        child = spawn()
        exits = Exits()
        monitor.watch(child.pid, exits, child=True)
        t0 = time.perf_counter()
        os.kill(child.pid, signal.SIGKILL)
        t1, report = exits.get_timed()
        assert report == (child.pid, None, signal.SIGKILL)
        latencies.append(t1 - t0)
    sys.stderr.write(
        f"procmon kill-to-callback latency: {[f'{x * 1e3:.2f}' for x in latencies]} ms\n"
    )
    assert max(latencies) < 1.0  # typically well under 1 ms; the bound is for slow CI machines


def test_many_processes_are_each_reported_once(spawn: type[Child], monitor: ProcessMonitor) -> None:
    children = [spawn(stdin=True) for _ in range(8)]
    exits = Exits()
    for child in children:
        monitor.watch(child.pid, exits, child=True)
    for code, child in enumerate(children):
        child.send(f"exit {code}")
    got = sorted((exits.get() for _ in children), key=lambda e: e[1] or 0)
    assert got == [(c.pid, code, None) for code, c in enumerate(children)]
    with pytest.raises(queue.Empty):
        exits.get(timeout=0.05)


def test_a_process_that_is_not_our_child_exits_with_unknown_status(
    spawn: type[Child], monitor: ProcessMonitor
) -> None:
    child = spawn(grandchildren=1)
    grandchild = child.grandchildren[0]
    exits = Exits()
    monitor.watch(grandchild, exits, child=False)
    os.kill(grandchild, signal.SIGKILL)
    assert exits.get() == (grandchild, None, None)


def test_a_child_watched_as_adopted_is_still_reaped_with_its_status(
    spawn: type[Child], monitor: ProcessMonitor
) -> None:
    # A manager restarted inside the same OS process adopts its own former children.
    child = spawn(stdin=True)
    exits = Exits()
    monitor.watch(child.pid, exits, child=False)
    child.send("exit 4")
    assert exits.get() == (child.pid, 4, None)


def test_an_already_exited_unreaped_child_is_reported_at_once(
    spawn: type[Child], monitor: ProcessMonitor
) -> None:
    child = spawn(stdin=True)
    child.send("exit 9")
    fd = os.pidfd_open(child.pid)
    try:
        import select

        assert select.select([fd], [], [], 5)[0] == [fd]  # now a zombie
    finally:
        os.close(fd)
    exits = Exits()
    monitor.watch(child.pid, exits, child=True)
    assert exits.get() == (child.pid, 9, None)


def test_unwatch_and_detach(spawn: type[Child], monitor: ProcessMonitor) -> None:
    a, b = spawn(stdin=True), spawn(stdin=True)
    exits = Exits()
    monitor.watch(a.pid, exits, child=True)
    monitor.watch(b.pid, exits, child=True)
    assert monitor.unwatch(a.pid) is True
    assert monitor.unwatch(a.pid) is False
    fd = monitor.detach(b.pid)
    assert fd is not None
    assert monitor.detach(b.pid) is None
    try:
        a.send("exit 1")
        b.send("exit 2")
        assert a.proc.wait(timeout=5) == 1  # nobody else reaped it
        result = os.waitid(os.P_PIDFD, fd, os.WEXITED)  # the detached pidfd is ours
        assert result is not None
        assert (result.si_pid, result.si_status) == (b.pid, 2)
        b.proc.returncode = 2
    finally:
        os.close(fd)
    with pytest.raises(queue.Empty):
        exits.get(timeout=0.1)
    assert monitor.watched() == []


def test_watch_errors(spawn: type[Child], monitor: ProcessMonitor) -> None:
    with pytest.raises(ProcessLookupError):
        monitor.watch(2**22 + 12345, Exits(), child=True)
    child = spawn()
    monitor.watch(child.pid, Exits(), child=True)
    with pytest.raises(ValueError, match="already watched"):
        monitor.watch(child.pid, Exits(), child=True)
    monitor.close()
    with pytest.raises(StateError):
        monitor.watch(child.pid, Exits(), child=True)


def test_close_leaves_processes_alone_and_is_idempotent(spawn: type[Child]) -> None:
    mon = ProcessMonitor(name="temoto-procmon-test")
    child = spawn()
    exits = Exits()
    mon.watch(child.pid, exits, child=True)
    mon.close()
    mon.close()
    assert not any(t.name == "temoto-procmon-test" for t in threading.enumerate())
    assert process_state(child.pid) in {"R", "S"}
    os.kill(child.pid, signal.SIGKILL)
    assert child.proc.wait(timeout=5) == -signal.SIGKILL
    with pytest.raises(queue.Empty):
        exits.get(timeout=0.05)


def test_a_failing_callback_is_logged_and_the_monitor_goes_on(
    spawn: type[Child], monitor: ProcessMonitor, caplog: pytest.LogCaptureFixture
) -> None:
    exits = Exits()

    def boom(pid: int, returncode: int | None, sig: int | None) -> None:
        exits(pid, returncode, sig)
        raise RuntimeError("callback bug")

    a, b = spawn(stdin=True), spawn(stdin=True)
    monitor.watch(a.pid, boom, child=True)
    a.send("exit 1")
    assert exits.get() == (a.pid, 1, None)
    monitor.watch(b.pid, exits, child=True)
    b.send("exit 2")
    assert exits.get() == (b.pid, 2, None)
    assert f"exit callback for process {a.pid} failed" in caplog.text


def test_callbacks_may_watch_and_unwatch(spawn: type[Child], monitor: ProcessMonitor) -> None:
    a, b, c = spawn(stdin=True), spawn(stdin=True), spawn(stdin=True)
    exits = Exits()

    def chain(pid: int, returncode: int | None, sig: int | None) -> None:
        monitor.watch(b.pid, exits, child=True)
        monitor.unwatch(c.pid)
        exits(pid, returncode, sig)

    monitor.watch(a.pid, chain, child=True)
    monitor.watch(c.pid, exits, child=True)
    a.send("exit 1")
    assert exits.get() == (a.pid, 1, None)
    c.send("exit 3")
    b.send("exit 2")
    assert exits.get() == (b.pid, 2, None)
    with pytest.raises(queue.Empty):
        exits.get(timeout=0.05)


# --- spawn: children that die with this process ------------------------------------------------


def test_spawn_forks_from_one_long_lived_thread() -> None:
    # The parent-death signal fires when the forking *thread* ends: a child spawned on behalf
    # of a thread that then ends must live on.
    spawned: list[subprocess.Popen[bytes]] = []
    caller = threading.Thread(
        target=lambda: spawned.append(start_child(child_command(), stdout=subprocess.PIPE))
    )
    caller.start()
    caller.join()
    (proc,) = spawned
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline().decode().strip() == f"ready {proc.pid}"
        assert process_state(proc.pid) not in (None, "Z")
        # forked by the spawner thread, which is still there
        assert "process-spawner" in [t.name for t in threading.enumerate()]
    finally:
        proc.kill()
        proc.wait()
        if proc.stdout is not None:
            proc.stdout.close()


def test_spawn_hands_back_the_errors_of_popen() -> None:
    with pytest.raises(FileNotFoundError):
        start_child(["/nonexistent/program"])
    with pytest.raises(ValueError, match="preexec_fn"):
        start_child(["true"], preexec_fn=os.getpid)
