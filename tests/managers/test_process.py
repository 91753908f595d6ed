"""ProcessManager and ProcessManagerClient on a real Registrar, with real child processes."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import queue
import select
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from temoto.core.registrar import Registrar, Status, StatusUpdate
from temoto.errors import ResourceLoadError, StateError
from temoto.managers import (
    ProcessHandle,
    ProcessManager,
    ProcessManagerClient,
    ProcessRequest,
    ProcessResponse,
)
from temoto.managers._process_stop import group_members as _group_members
from temoto.managers._procmon import process_start_time, process_state
from temoto.managers.process import TOKEN_VARIABLE, hurry_all
from temoto.testing import child_command

GRACE = 0.3


# --- fixtures and helpers ---------------------------------------------------------------------


def release_everything(registrar: Registrar) -> None:
    for ref in registrar.references():
        if not ref.holder:
            registrar.release(ref.id)


@pytest.fixture
def registrar() -> Iterator[Registrar]:
    reg = Registrar("test")
    yield reg
    reg.close()


@pytest.fixture
def log_dir(tmp_path: Path) -> Path:
    return tmp_path / "logs"


@pytest.fixture
def manager(registrar: Registrar, log_dir: Path) -> Iterator[ProcessManager]:
    mgr = ProcessManager(registrar, grace=GRACE, log_dir=log_dir)
    yield mgr
    release_everything(registrar)
    mgr.shutdown()


class PidPipe:
    """A named pipe the child writes its pid into (``--touch``), read without polling."""

    def __init__(self, path: Path) -> None:
        os.mkfifo(path)
        self.path = path
        # O_RDWR: the pipe always has a writer (us), so no EOF between children.
        self.fd = os.open(path, os.O_RDWR | os.O_NONBLOCK)
        self.buffer = b""

    def next_pid(self, timeout: float = 10.0) -> int:
        deadline = time.monotonic() + timeout
        while b"\n" not in self.buffer:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([self.fd], [], [], left)[0]:
                raise TimeoutError("no pid arrived on the pipe")
            self.buffer += os.read(self.fd, 4096)
        line, self.buffer = self.buffer.split(b"\n", 1)
        return int(line)

    def nothing_for(self, seconds: float) -> bool:
        return not self.buffer and not select.select([self.fd], [], [], seconds)[0]

    def close(self) -> None:
        os.close(self.fd)


@pytest.fixture
def pipe(tmp_path: Path) -> Iterator[PidPipe]:
    p = PidPipe(tmp_path / "pids")
    yield p
    p.close()


def child_request(**opts: Any) -> ProcessRequest:
    argv = child_command(**opts)
    return ProcessRequest(argv[0], tuple(argv[1:]))


class Statuses:
    """Collects status updates; ``get`` blocks for the next one."""

    def __init__(self) -> None:
        self.queue: queue.Queue[tuple[float, StatusUpdate]] = queue.Queue()

    def __call__(self, update: StatusUpdate) -> None:
        self.queue.put((time.perf_counter(), update))

    def get(self, timeout: float = 5.0) -> StatusUpdate:
        return self.queue.get(timeout=timeout)[1]

    def get_timed(self, timeout: float = 5.0) -> tuple[float, StatusUpdate]:
        return self.queue.get(timeout=timeout)

    def none_for(self, seconds: float) -> bool:
        try:
            self.queue.get(timeout=seconds)
        except queue.Empty:
            return True
        return False


def gone(pid: int) -> bool:
    """Exited (a zombie waiting for its parent counts as gone)."""
    return process_state(pid) in {None, "Z"}


def alive(pid: int) -> bool:
    return not gone(pid)


def reap(pid: int) -> None:
    """Kill and reap a child of this test process that no manager owns any more."""
    with contextlib.suppress(ProcessLookupError):
        os.killpg(pid, signal.SIGKILL)
    with contextlib.suppress(ChildProcessError):
        os.waitpid(pid, 0)


def grandchildren_in_log(log_dir: Path, pid: int) -> list[int]:
    lines = (log_dir / f"{pid}.log").read_text().splitlines()
    assert lines[0] == f"ready {pid}"
    return [int(line.split()[1]) for line in lines[1:] if line.startswith("grandchild ")]


def on_change_event(
    handle: ProcessHandle, when: Callable[[ProcessHandle], bool]
) -> threading.Event:
    event = threading.Event()

    def hook(h: ProcessHandle) -> None:
        if when(h):
            event.set()

    handle.on_change = hook
    return event


# --- request and response values --------------------------------------------------------------


def test_request_and_response_round_trip_through_json() -> None:
    req = ProcessRequest("prog", ("a", "b"), (("Z", "1"), ("A", "2")), "/tmp")
    assert req.env == (("A", "2"), ("Z", "1"))  # sorted: order does not change identity
    again = ProcessRequest(**json.loads(json.dumps(dataclasses.asdict(req))))
    assert again == req
    assert hash(again) == hash(req)
    resp = ProcessResponse(12, 12, 345, 1.5)
    assert ProcessResponse(**json.loads(json.dumps(dataclasses.asdict(resp)))) == resp
    assert ProcessResponse(1, 1, 2, 3).started_at == 3.0
    assert ProcessRequest("p", env={"B": "1", "A": "2"}) == ProcessRequest(  # type: ignore[arg-type]
        "p", env=(("A", "2"), ("B", "1"))
    )
    assert ProcessRequest("p", ["x"]) == ProcessRequest("p", ("x",))  # type: ignore[arg-type]
    assert req.argv == ["prog", "a", "b"]


@pytest.mark.parametrize(
    ("kwargs", "error", "match"),
    [
        ({"executable": 3}, TypeError, "executable must be a str"),
        ({"executable": ""}, ValueError, "executable is empty"),
        ({"executable": "p", "args": "abc"}, TypeError, "args must be a sequence"),
        ({"executable": "p", "args": ("a", 1)}, TypeError, r"args\[1\] must be a str"),
        ({"executable": "p", "args": ("a\0b",)}, ValueError, "NUL"),
        ({"executable": "p", "env": (("A",),)}, TypeError, "pair"),
        ({"executable": "p", "env": "A=1"}, TypeError, "env must be"),
        ({"executable": "p", "env": (("A=B", "1"),)}, ValueError, "bad variable name"),
        ({"executable": "p", "env": (("A", "1"), ("A", "2"))}, ValueError, "given twice"),
        ({"executable": "p", "env": (("A", 1),)}, TypeError, "value"),
        ({"executable": "p", "cwd": 5}, TypeError, "cwd must be a str"),
        ({"executable": "p", "cwd": ""}, ValueError, "cwd is empty"),
    ],
)
def test_bad_requests_are_refused_with_a_clear_error(
    kwargs: dict[str, Any], error: type[Exception], match: str
) -> None:
    with pytest.raises(error, match=match):
        ProcessRequest(**kwargs)


def test_bad_responses_are_refused() -> None:
    with pytest.raises(TypeError, match="pid must be an int"):
        ProcessResponse("1", 1, 1, 1.0)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="started_at"):
        ProcessResponse(1, 1, 1, "now")  # type: ignore[arg-type]


@pytest.mark.usefixtures("manager")
def test_loads_that_cannot_run_fail_with_the_reason(registrar: Registrar, tmp_path: Path) -> None:
    script = tmp_path / "not-executable.sh"
    script.write_text("#!/bin/sh\n")
    cases = [
        (ProcessRequest("temoto-no-such-program-xyz"), "was not found on PATH"),
        (ProcessRequest(sys.executable, cwd=str(tmp_path / "nowhere")), "does not exist"),
        (ProcessRequest(str(tmp_path / "missing")), "does not exist"),
        (ProcessRequest(str(script)), "is not executable"),
    ]
    for request, message in cases:
        with pytest.raises(ResourceLoadError, match=message) as info:
            registrar.call("process", request)
        assert isinstance(info.value.__cause__, ValueError)
    assert registrar.resources() == []
    with pytest.raises(TypeError, match="ProcessRequest"):
        registrar.call("process", {"executable": "true"})


# --- loading, exits, stopping -----------------------------------------------------------------


def test_a_process_runs_in_its_own_group_and_stops_with_sigterm_on_release(
    registrar: Registrar, manager: ProcessManager, pipe: PidPipe, log_dir: Path
) -> None:
    statuses = Statuses()
    res = registrar.call("process", child_request(touch=pipe.path), on_status=statuses)
    resp = res.response
    assert isinstance(resp, ProcessResponse)
    assert pipe.next_pid() == resp.pid
    assert resp.pgid == resp.pid == os.getpgid(resp.pid)
    assert os.getsid(resp.pid) == resp.pid
    assert resp.start_time == process_start_time(resp.pid)
    assert abs(resp.started_at - time.time()) < 60
    assert (log_dir / f"{resp.pid}.log").read_text() == f"ready {resp.pid}\n"
    assert manager.running() == [resp.pid]
    t0 = time.monotonic()
    assert registrar.release(res.id) is True
    assert time.monotonic() - t0 < GRACE  # SIGTERM was enough: no grace period spent
    assert gone(resp.pid)
    assert manager.running() == []
    assert statuses.none_for(0.1)  # a stop we asked for is not a failure


def test_extra_environment_and_working_directory(
    registrar: Registrar, manager: ProcessManager, tmp_path: Path, log_dir: Path
) -> None:
    code = "import os; print(os.getcwd(), os.environ['TEMOTO_X'], os.environ['HOME'] != '')"
    statuses = Statuses()
    request = ProcessRequest(sys.executable, ("-c", code), (("TEMOTO_X", "42"),), str(tmp_path))
    res = registrar.call("process", request, on_status=statuses)
    update = statuses.get()
    assert update.status is Status.FATAL
    assert update.message.endswith("exited with code 0")
    assert (log_dir / f"{res.response.pid}.log").read_text() == f"{tmp_path} 42 True\n"
    registrar.release(res.id)


def test_relative_executable_is_found_from_cwd(
    registrar: Registrar, manager: ProcessManager, tmp_path: Path
) -> None:
    (tmp_path / "bin").mkdir()
    prog = tmp_path / "bin" / "prog"
    prog.write_text("#!/bin/sh\nexit 5\n")
    prog.chmod(0o755)
    statuses = Statuses()
    res = registrar.call(
        "process", ProcessRequest("bin/prog", cwd=str(tmp_path)), on_status=statuses
    )
    assert statuses.get().message.endswith("exited with code 5")
    registrar.release(res.id)


@pytest.mark.parametrize(
    ("opts", "expected"),
    [
        ({"sleep": 0.3, "exit_code": 3}, "exited with code 3"),
        ({"sleep": 0.3, "crash": True}, "was killed by signal SIGABRT"),
        ({"sleep": 0.3}, "exited with code 0"),
    ],
)
def test_an_exit_is_fatal_for_every_consumer_with_code_or_signal(
    registrar: Registrar, manager: ProcessManager, opts: dict[str, Any], expected: str
) -> None:
    first, second = Statuses(), Statuses()
    request = child_request(**opts)
    a = registrar.call("process", request, client="a", on_status=first)
    b = registrar.call("process", request, client="b", on_status=second)
    pid = a.response.pid
    for statuses in (first, second):
        update = statuses.get()
        assert update.status is Status.FATAL
        assert update.message == f"process {pid} ({request.executable}) {expected}"
        assert update.origin == a.resource_id
    assert registrar.info(a.id).failed
    assert manager.running() == []
    registrar.release(a.id)
    registrar.release(b.id)


def test_crash_is_reported_within_milliseconds(
    registrar: Registrar, manager: ProcessManager, pipe: PidPipe
) -> None:
    latencies = []
    for sig in (signal.SIGSEGV, signal.SIGKILL, signal.SIGSEGV):
        statuses = Statuses()
        res = registrar.call("process", child_request(touch=pipe.path), on_status=statuses)
        pid = pipe.next_pid()
        t0 = time.perf_counter()
        os.kill(pid, sig)
        t1, update = statuses.get_timed()
        latencies.append(t1 - t0)
        assert update.status is Status.FATAL
        assert update.message.endswith(f"was killed by signal {signal.Signals(sig).name}")
        registrar.release(res.id)
    sys.stderr.write(f"kill-to-FATAL latency: {[f'{x * 1e3:.2f}' for x in latencies]} ms\n")
    assert max(latencies) < 1.0  # milliseconds in practice; the benchmark holds the real goal


def test_a_failed_resource_is_replaced_by_a_fresh_process_for_new_calls(
    registrar: Registrar, manager: ProcessManager, pipe: PidPipe
) -> None:
    statuses = Statuses()
    request = child_request(touch=pipe.path)
    old = registrar.call("process", request, on_status=statuses)
    pid = pipe.next_pid()
    os.kill(pid, signal.SIGKILL)
    assert statuses.get().status is Status.FATAL
    new = registrar.call("process", request)
    assert new.resource_id != old.resource_id
    assert pipe.next_pid() == new.response.pid != pid
    registrar.release(old.id)
    assert alive(new.response.pid)
    registrar.release(new.id)
    assert gone(new.response.pid)


def test_equal_requests_share_one_process(
    registrar: Registrar, manager: ProcessManager, pipe: PidPipe
) -> None:
    argv = child_command(touch=pipe.path)
    a = registrar.call(
        "process", ProcessRequest(argv[0], tuple(argv[1:]), (("A", "1"), ("B", "2")))
    )
    lists: Any = (list(argv[1:]), {"B": "2", "A": "1"})  # as JSON would give them back
    b = registrar.call("process", ProcessRequest(argv[0], *lists))
    assert a.resource_id == b.resource_id
    assert a.response == b.response
    pid = pipe.next_pid()
    assert pipe.nothing_for(0.2)  # one process only
    assert manager.running() == [pid]
    assert registrar.release(a.id) is False
    assert alive(pid)
    assert registrar.release(b.id) is True
    assert gone(pid)


def test_a_child_ignoring_sigterm_is_killed_after_the_grace_period(
    registrar: Registrar,
    manager: ProcessManager,
    pipe: PidPipe,
    caplog: pytest.LogCaptureFixture,
) -> None:
    statuses = Statuses()
    res = registrar.call(
        "process", child_request(ignore_term=True, touch=pipe.path), on_status=statuses
    )
    pid = pipe.next_pid()  # its SIGTERM handler is in place
    t0 = time.monotonic()
    registrar.release(res.id)
    elapsed = time.monotonic() - t0
    assert GRACE <= elapsed < GRACE + 2
    assert gone(pid)
    assert "ignored SIGTERM" in caplog.text
    assert statuses.none_for(0.05)


@pytest.mark.parametrize("ignore_term", [False, True])
def test_grandchildren_are_gone_after_release(
    registrar: Registrar,
    manager: ProcessManager,
    pipe: PidPipe,
    log_dir: Path,
    ignore_term: bool,
) -> None:
    res = registrar.call(
        "process", child_request(grandchildren=3, ignore_term=ignore_term, touch=pipe.path)
    )
    pid = pipe.next_pid()
    grandchildren = grandchildren_in_log(log_dir, pid)
    assert len(grandchildren) == 3
    assert all(alive(g) and os.getpgid(g) == pid for g in grandchildren)
    registrar.release(res.id)
    assert gone(pid)
    assert [g for g in grandchildren if alive(g)] == []


def test_grandchildren_left_by_a_crashed_leader_are_stopped_on_release(
    registrar: Registrar, manager: ProcessManager, pipe: PidPipe, log_dir: Path
) -> None:
    statuses = Statuses()
    res = registrar.call(
        "process", child_request(grandchildren=2, touch=pipe.path), on_status=statuses
    )
    pid = pipe.next_pid()
    grandchildren = grandchildren_in_log(log_dir, pid)
    os.kill(pid, signal.SIGKILL)
    assert statuses.get().status is Status.FATAL
    assert all(alive(g) for g in grandchildren)  # the group outlives its leader
    registrar.release(res.id)
    assert [g for g in grandchildren if alive(g)] == []


@pytest.mark.parametrize("inherit", [False, True])
def test_output_goes_to_dev_null_or_is_inherited(pipe: PidPipe, inherit: bool) -> None:
    with Registrar() as reg, ProcessManager(reg, grace=GRACE, inherit_output=inherit) as mgr:
        assert mgr.log_dir is None
        res = reg.call("process", child_request(touch=pipe.path))
        pid = pipe.next_pid()
        assert pid == res.response.pid
        for fd in (1, 2):
            target = os.readlink(f"/proc/{pid}/fd/{fd}")
            assert target == (os.readlink(f"/proc/self/fd/{fd}") if inherit else "/dev/null")
        assert os.readlink(f"/proc/{pid}/fd/0") == "/dev/null"
        reg.release(res.id)
        assert gone(res.response.pid)
    with Registrar() as reg, pytest.raises(ValueError, match="not both"):
        ProcessManager(reg, log_dir="x", inherit_output=True)


def test_a_process_that_exits_during_its_load_is_failed_for_the_client(
    registrar: Registrar, manager: ProcessManager
) -> None:
    # `true` may exit before the registrar has recorded the reference: its FATAL then reaches
    # nobody, but the resource is marked failed and the client reacts anyway.
    with ProcessManagerClient(registrar, "c", on_failure="report") as client:
        for _ in range(5):
            handle = client.load("true")
            failed = on_change_event(handle, lambda h: h.failed)
            if not handle.failed:
                assert failed.wait(5)
            assert handle.last_status is not None
            assert handle.last_status.status is Status.FATAL
            client.release(handle)


def test_shutdown_leaves_processes_running_and_refuses_new_loads(
    registrar: Registrar, pipe: PidPipe
) -> None:
    mgr = ProcessManager(registrar, grace=GRACE)
    res = registrar.call("process", child_request(touch=pipe.path))
    pid = pipe.next_pid()
    mgr.shutdown()
    mgr.shutdown()
    assert not any(t.name == "temoto-procmon" for t in threading.enumerate())
    assert alive(pid)
    with pytest.raises(ResourceLoadError) as info:
        registrar.call("process", child_request(sleep=1))
    assert isinstance(info.value.__cause__, StateError)
    reap(pid)
    registrar.release(res.id)


def test_a_second_process_server_is_refused(registrar: Registrar, manager: ProcessManager) -> None:
    with pytest.raises(ValueError, match="already registered"):
        ProcessManager(registrar)
    assert [t.name for t in threading.enumerate()].count("temoto-procmon") == 1


# --- the client -------------------------------------------------------------------------------


def test_client_relaunches_a_crashed_process_by_default(
    registrar: Registrar, manager: ProcessManager, pipe: PidPipe, log_dir: Path
) -> None:
    with ProcessManagerClient(registrar, "tester") as client:
        argv = child_command(touch=pipe.path)
        handle = client.load(argv[0], *argv[1:])
        first = pipe.next_pid()
        assert handle.pid == first
        relaunched = on_change_event(handle, lambda h: h.relaunches == 1)
        old_ref = handle.reference_id
        os.kill(first, signal.SIGSEGV)
        assert relaunched.wait(5)
        second = pipe.next_pid()
        assert handle.pid == second != first
        assert handle.reference_id != old_ref
        assert not handle.failed
        assert handle.last_status is not None
        assert "SIGSEGV" in handle.last_status.message
        assert (log_dir / f"{second}.log").read_text() == f"ready {second}\n"
        assert [r.id for r in registrar.references("tester")] == [handle.reference_id]
        assert manager.running() == [second]
        client.release(handle)
        assert gone(second)
        assert registrar.references("tester") == []
        client.release(handle)  # idempotent


def test_report_policy_does_not_relaunch(
    registrar: Registrar, manager: ProcessManager, pipe: PidPipe
) -> None:
    with ProcessManagerClient(registrar, "tester", on_failure="report") as client:
        argv = child_command(touch=pipe.path)
        handle = client.load(argv[0], *argv[1:])
        pid = pipe.next_pid()
        failed = on_change_event(handle, lambda h: h.failed)
        os.kill(pid, signal.SIGKILL)
        assert failed.wait(5)
        assert handle.pid == pid
        assert handle.relaunches == 0
        assert registrar.info(handle.reference_id).failed
        assert pipe.nothing_for(0.3)
        assert manager.running() == []
    assert registrar.references() == []


def test_a_callable_policy_gets_handle_and_update(
    registrar: Registrar, manager: ProcessManager, pipe: PidPipe
) -> None:
    seen: queue.Queue[tuple[ProcessHandle, StatusUpdate, str]] = queue.Queue()

    def policy(handle: ProcessHandle, update: StatusUpdate) -> None:
        seen.put((handle, update, threading.current_thread().name))

    with ProcessManagerClient(registrar, "me", on_failure=policy) as client:
        argv = child_command(touch=pipe.path)
        handle = client.load(argv[0], *argv[1:])
        os.kill(pipe.next_pid(), signal.SIGKILL)
        got, update, thread = seen.get(timeout=5)
        assert got is handle
        assert update.status is Status.FATAL
        assert thread == "temoto-process-client-me"


def test_relaunching_gives_up_after_the_budget(
    registrar: Registrar, manager: ProcessManager, caplog: pytest.LogCaptureFixture
) -> None:
    with ProcessManagerClient(registrar, "c", max_relaunches=2, relaunch_window=60) as client:
        argv = child_command(exit_code=1)
        handle = client.load(argv[0], *argv[1:])
        failed = on_change_event(handle, lambda h: h.failed)
        assert failed.wait(10)
        assert handle.relaunches == 2
        assert "not relaunching: 2 relaunches within 60 s" in caplog.text
        assert manager.running() == []


def test_client_checks_its_arguments(registrar: Registrar, manager: ProcessManager) -> None:
    with pytest.raises(ValueError, match="on_failure"):
        ProcessManagerClient(registrar, "c", on_failure="ignore")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="max_relaunches"):
        ProcessManagerClient(registrar, "c", max_relaunches=-1)
    client = ProcessManagerClient(registrar, "c")
    client.close()
    with pytest.raises(StateError):
        client.load("true")


# --- restart from the catalog -----------------------------------------------------------------


def restart(
    catalog: Path, old: tuple[Registrar, ProcessManager] | None = None
) -> tuple[Registrar, ProcessManager]:
    """Drop a manager and its registrar without releasing anything, and start new ones."""
    if old is not None:
        old[1].shutdown()
        old[0].close()
    reg = Registrar("test", catalog=catalog, restore=True)
    return reg, ProcessManager(reg, grace=GRACE)


@pytest.fixture
def catalog(tmp_path: Path) -> Path:
    return tmp_path / "catalog.journal"


def test_a_running_process_is_re_adopted_after_a_restart(catalog: Path, pipe: PidPipe) -> None:
    reg1 = Registrar("test", catalog=catalog)
    mgr1 = ProcessManager(reg1, grace=GRACE)
    res = reg1.call("process", child_request(touch=pipe.path), client="c")
    pid = pipe.next_pid()
    reg2, mgr2 = restart(catalog, (reg1, mgr1))
    try:
        assert mgr2.running() == [pid]
        info = reg2.info(res.id)
        assert not info.failed
        assert info.response == res.response
        statuses = Statuses()
        reg2.subscribe(res.id, statuses)
        os.kill(pid, signal.SIGSEGV)
        update = statuses.get()
        assert update.status is Status.FATAL
        assert update.message.startswith(f"process {pid} ")
        reg2.release(res.id)
    finally:
        release_everything(reg2)
        mgr2.shutdown()
        reg2.close()


def test_a_re_adopted_process_can_be_stopped(catalog: Path, pipe: PidPipe, log_dir: Path) -> None:
    reg1 = Registrar("test", catalog=catalog)
    mgr1 = ProcessManager(reg1, grace=GRACE, log_dir=log_dir)
    res = reg1.call("process", child_request(grandchildren=2, touch=pipe.path), client="c")
    pid = pipe.next_pid()
    grandchildren = grandchildren_in_log(log_dir, pid)
    reg2, mgr2 = restart(catalog, (reg1, mgr1))
    try:
        assert reg2.release(res.id) is True
        assert gone(pid)
        assert [g for g in grandchildren if alive(g)] == []
        reap(pid)  # the old manager's child (same test process): a zombie until reaped
    finally:
        mgr2.shutdown()
        reg2.close()


def test_a_process_that_died_while_down_is_reported_and_relaunched_by_reattach(
    catalog: Path, pipe: PidPipe, caplog: pytest.LogCaptureFixture
) -> None:
    reg1 = Registrar("test", catalog=catalog)
    mgr1 = ProcessManager(reg1, grace=GRACE)
    client1 = ProcessManagerClient(reg1, "c")
    argv = child_command(touch=pipe.path)
    handle1 = client1.load(argv[0], *argv[1:])
    pid = pipe.next_pid()
    mgr1.shutdown()
    reg1.close()
    reap(pid)  # dies while nothing watches it (its real parent reaps it, as init would)
    reg2, mgr2 = restart(catalog)
    try:
        assert f"process {pid} ({argv[0]}) died while the manager was down" in caplog.text
        assert reg2.info(handle1.reference_id).failed
        assert mgr2.running() == []
        with ProcessManagerClient(reg2, "c") as client2:
            handles = client2.reattach()
            assert [h.reference_id for h in handles] == [handle1.reference_id]
            handle = handles[0]
            relaunched = on_change_event(handle, lambda h: h.relaunches == 1)
            if handle.relaunches == 0:
                assert relaunched.wait(5)
            assert handle.last_status is not None
            assert "was down" in handle.last_status.message
            new_pid = pipe.next_pid()
            assert handle.pid == new_pid != pid
            assert mgr2.running() == [new_pid]
        assert gone(new_pid)
    finally:
        release_everything(reg2)
        mgr2.shutdown()
        reg2.close()
    client1.close()  # its registrar is closed: nothing to release there


def test_a_pid_with_another_start_time_is_never_adopted(catalog: Path, pipe: PidPipe) -> None:
    reg1 = Registrar("test", catalog=catalog)
    mgr1 = ProcessManager(reg1, grace=GRACE)
    res = reg1.call("process", child_request(touch=pipe.path), client="c")
    pid = pipe.next_pid()
    real = res.response
    # As if the recorded process had died and its pid had gone to this other process.
    fake = dataclasses.replace(real, start_time=real.start_time - 1, token="f" * 32)
    reg1.update_response(res.resource_id, fake)
    reg2, mgr2 = restart(catalog, (reg1, mgr1))
    try:
        assert mgr2.running() == []
        assert reg2.info(res.id).failed
        reg2.release(res.id)  # unload must not touch the stranger that has the pid now
        assert alive(pid)
    finally:
        reap(pid)
        mgr2.shutdown()
        reg2.close()


def test_an_interrupted_load_is_undone_on_restore(
    registrar: Registrar, manager: ProcessManager, pipe: PidPipe
) -> None:
    # The registrar calls on_abandoned with the last checkpoint of on_load: the spawn token
    # (taken before the spawn), then pid, group and start time (right after it).
    request = child_request(grandchildren=1, touch=pipe.path)
    token = "a" * 32
    proc = subprocess.Popen(
        [request.executable, *request.args],
        start_new_session=True,
        stdout=subprocess.DEVNULL,
        env={**os.environ, TOKEN_VARIABLE: token},
    )
    try:
        pid = pipe.next_pid()
        start = process_start_time(pid)
        assert start is not None
        manager.on_abandoned(request, {"pid": pid, "pgid": pid, "start_time": start - 1})
        assert alive(pid)  # not the process the checkpoint names, and no token given
        manager.on_abandoned(request, None)
        manager.on_abandoned(request, {"pid": "x"})
        manager.on_abandoned(request, {"token": "b" * 32})
        assert alive(pid)
        manager.on_abandoned(request, {"pid": pid, "pgid": pid, "start_time": start})
        assert gone(pid)
    finally:
        proc.kill()
        proc.wait()


def test_a_load_interrupted_before_the_pid_was_known_is_undone_by_its_token(
    registrar: Registrar, manager: ProcessManager, pipe: PidPipe
) -> None:
    request = child_request(grandchildren=2, touch=pipe.path)
    token = "c" * 32
    proc = subprocess.Popen(
        [request.executable, *request.args],
        start_new_session=True,
        stdout=subprocess.PIPE,
        env={**os.environ, TOKEN_VARIABLE: token},
    )
    try:
        pid = pipe.next_pid()  # written after the ready and grandchild lines
        manager.on_abandoned(request, {"token": token})
        assert gone(pid)
        proc.wait(5)
        assert proc.stdout is not None
        lines = proc.stdout.read().decode().splitlines()
        grandchildren = [int(x.split()[1]) for x in lines if x.startswith("grandchild ")]
        assert len(grandchildren) == 2
        assert [g for g in grandchildren if alive(g)] == []
    finally:
        proc.kill()
        proc.wait()
        if proc.stdout is not None:
            proc.stdout.close()


def test_left_overs_of_a_process_that_died_while_down_are_stopped_on_release(
    catalog: Path, pipe: PidPipe, log_dir: Path
) -> None:
    reg1 = Registrar("test", catalog=catalog)
    mgr1 = ProcessManager(reg1, grace=GRACE, log_dir=log_dir)
    res = reg1.call("process", child_request(grandchildren=2, touch=pipe.path), client="c")
    pid = pipe.next_pid()
    grandchildren = grandchildren_in_log(log_dir, pid)
    mgr1.shutdown()
    reg1.close()
    os.kill(pid, signal.SIGKILL)  # the leader dies while nothing watches; its group lives on
    os.waitpid(pid, 0)
    reg2, mgr2 = restart(catalog)
    try:
        assert reg2.info(res.id).failed
        assert all(alive(g) for g in grandchildren)
        reg2.release(res.id)
        assert [g for g in grandchildren if alive(g)] == []
    finally:
        release_everything(reg2)
        mgr2.shutdown()
        reg2.close()


def test_every_process_carries_its_spawn_token(
    registrar: Registrar, manager: ProcessManager, pipe: PidPipe
) -> None:
    res = registrar.call("process", child_request(touch=pipe.path))
    pid = pipe.next_pid()
    token = res.response.token
    assert len(token) == 32
    with open(f"/proc/{pid}/environ", "rb") as f:
        assert f"{TOKEN_VARIABLE}={token}".encode() in f.read().split(b"\0")
    registrar.release(res.id)


# --- stopping everything, hurrying, dying with this process -----------------------------------


def test_stop_all_stops_every_group_at_once_without_failures(
    registrar: Registrar, pipe: PidPipe, log_dir: Path
) -> None:
    grace = 0.5
    mgr = ProcessManager(registrar, grace=grace, log_dir=log_dir)
    try:
        statuses = Statuses()
        pids, grandchildren = [], []
        request = child_request(grandchildren=1, ignore_term=True, touch=pipe.path)
        for i in range(3):  # each ignores SIGTERM: each needs the whole grace period
            # (requests that differ, or they would share one process)
            registrar.call(
                "process", dataclasses.replace(request, env={"N": str(i)}), on_status=statuses
            )
            pids.append(pipe.next_pid())
            grandchildren += grandchildren_in_log(log_dir, pids[-1])
        t0 = time.monotonic()
        assert sorted(mgr.stop_all()) == sorted(pids)
        elapsed = time.monotonic() - t0
        assert grace <= elapsed < 2 * grace  # in parallel, not one grace period after another
        assert [p for p in pids + grandchildren if alive(p)] == []
        assert mgr.running() == []
        assert statuses.none_for(0.05)  # a stop is not a failure
        assert mgr.stop_all() == []
    finally:
        release_everything(registrar)  # harmless now: nothing left to stop
        mgr.shutdown()


def test_shutdown_can_stop_the_processes(registrar: Registrar, pipe: PidPipe) -> None:
    mgr = ProcessManager(registrar, grace=GRACE)
    registrar.call("process", child_request(grandchildren=1, touch=pipe.path))
    pid = pipe.next_pid()
    mgr.shutdown(stop_processes=True)
    assert gone(pid)
    with contextlib.suppress(ChildProcessError):  # reaped by the manager: nothing to wait for
        assert os.waitpid(pid, os.WNOHANG) == (0, 0)
    release_everything(registrar)


def test_hurry_skips_the_grace_period_of_a_stop_under_way(
    registrar: Registrar, pipe: PidPipe
) -> None:
    mgr = ProcessManager(registrar, grace=30.0)
    try:
        res = registrar.call("process", child_request(ignore_term=True, touch=pipe.path))
        pid = pipe.next_pid()
        releasing = threading.Thread(target=registrar.release, args=(res.id,))
        t0 = time.monotonic()
        releasing.start()
        assert releasing.is_alive()  # waiting out the 30 s grace period
        hurry_all()  # what a second Ctrl-C does: every manager of the process
        releasing.join(5)
        assert not releasing.is_alive()
        assert time.monotonic() - t0 < 5
        assert gone(pid)
        # and from now on: SIGKILL right after SIGTERM
        registrar.call("process", child_request(ignore_term=True, touch=pipe.path))
        pid = pipe.next_pid()
        t0 = time.monotonic()
        release_everything(registrar)
        assert time.monotonic() - t0 < 5
        assert gone(pid)
    finally:
        release_everything(registrar)
        mgr.shutdown()


#: Starts a manager with the given keyword arguments and a child, prints the child's pid, and
#: waits to be killed.
PARENT = """
import sys, time
from temoto.core.registrar import Registrar
from temoto.managers import ProcessManager
from temoto.managers.process import ProcessRequest
registrar = Registrar("parent")
manager = ProcessManager(registrar, grace=0.5, **eval(sys.argv[1]))
ref = registrar.call("process", ProcessRequest(*eval(sys.argv[2])), client="c")
print(ref.response.pid, flush=True)
time.sleep(60)
"""


@pytest.mark.parametrize("die_with_manager", [True, False])
def test_processes_die_with_the_managers_process_unless_told_otherwise(
    die_with_manager: bool,
) -> None:
    argv = child_command(grandchildren=1)
    parent = subprocess.Popen(
        [
            sys.executable,
            "-c",
            PARENT,
            repr({"die_with_manager": die_with_manager}),
            repr((argv[0], tuple(argv[1:]))),
        ],
        stdout=subprocess.PIPE,
    )
    try:
        assert parent.stdout is not None
        pid = int(parent.stdout.readline())
        parent.kill()
        parent.wait()
        deadline = time.monotonic() + 3
        while alive(pid) and die_with_manager and time.monotonic() < deadline:
            time.sleep(0.01)
        assert gone(pid) is die_with_manager
    finally:
        if parent.stdout is not None:
            parent.stdout.close()
        if not die_with_manager:  # orphans now, as asked: kill them and wait until gone
            os.killpg(pid, signal.SIGKILL)
            deadline = time.monotonic() + 5
            while _group_members(pid) and time.monotonic() < deadline:
                time.sleep(0.01)
