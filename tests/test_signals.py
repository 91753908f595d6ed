"""Signals and crashes of the commands end with the documented exit code and nothing left behind.

docs/design.md §8 "Signals": ``temoto run`` and ``temoto demo`` exit 130 on SIGINT and 143 on
SIGTERM, ``temoto serve`` exits 0 on either; no traceback; a second signal stops at once but
still cleans up; no process of ours is left (checked in ``/proc`` by an environment marker
that every process the command starts inherits). And the Process Manager's children (and
their children) die when the manager's process is SIGKILLed.

Each command runs as a real subprocess; a signal is sent once the command has printed the line
that says it is busy (a process of its own running), never after a sleep.
"""

from __future__ import annotations

import json
import os
import select
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from temoto.cli.signals import SignalExit
from temoto.testing import ProcessLeakCheck

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.timeout(30)

#: An action that drives a device (BUSY_DEVICE: a file standing for the device, whose content
#: is its state; the driver is a real Driver subclass, so make_all_safe reaches it) and
#: acquires a process (the test child, with one grandchild) from the Process Manager. It says
#: "busy <pid>" once the process and its grandchild exist, then waits for its stop request,
#: or ignores it if BUSY_STUBBORN is set (for the second signal).
BUSY_ACTION = """
import os
import sys
import time

from temoto import Action
from temoto.drivers.base import Driver
from temoto.managers.process import ProcessRequest
from temoto.testing import child_command


class FileDevice(Driver):
    safe_states = ("off",)

    def __init__(self, path):
        super().__init__("file_device")
        self.path = path

    def on_configure(self):
        self._write("configured")

    def on_activate(self):
        self._write("running")

    def on_make_safe(self):
        self._write(self.safe_state)
        return f"device {self.safe_state}"

    def on_shutdown(self):
        pass

    def _write(self, text):
        with open(self.path, "w") as f:
            f.write(text)


DEVICES = []


class TaBusy(Action):
    def on_run(self) -> bool:
        device = FileDevice(os.environ["BUSY_DEVICE"])
        device.configure()
        device.activate()
        DEVICES.append(device)  # kept alive (drivers are found through weak references)
        touch = os.environ["BUSY_TOUCH"]
        stubborn = bool(os.environ.get("BUSY_STUBBORN"))
        argv = child_command(grandchildren=1, touch=touch, ignore_term=stubborn)
        self.acquire("process", ProcessRequest(argv[0], tuple(argv[1:])))
        while not os.path.exists(touch):  # written after the grandchild exists
            time.sleep(0.005)
        with open(touch) as f:
            sys.stdout.write(f"busy {f.read().strip()}\\n")
        sys.stdout.flush()
        while stubborn:
            time.sleep(0.05)
        self.wait_until_stopped()
        return True
"""

BUSY_UMRF = {"name": "TaBusy", "type": "sync", "input_parameters": {}, "output_parameters": {}}

BUSY_GRAPH = {
    "graph_name": "busy",
    "graph_entry": [{"name": "TaBusy", "instance_id": 0}],
    "graph_exit": [{"name": "TaBusy", "instance_id": 0}],
    "actions": [{"name": "TaBusy", "instance_id": 0, "type": "sync"}],
}

#: A program that holds a Process Manager: it loads, from a thread that then ends, a shell that
#: starts a grandchild and prints its pid; then it prints "ready" and waits to be killed.
MANAGER_PARENT = r"""
import os, sys, threading, time
from temoto.core.registrar import Registrar
from temoto.managers import ProcessManager
from temoto.managers.process import ProcessRequest

registrar = Registrar("parent")
manager = ProcessManager(registrar, grace=1.0, inherit_output=True)
shell = "sleep 300 & echo grandchild $!; sleep 300"

def load():
    ref = registrar.call("process", ProcessRequest("sh", ("-c", shell)), client="c")
    # one write(2) of a whole line: the grandchild writes to the same pipe, and print()'s
    # pieces could interleave with its line ("childgrandchild 6643", " 6641")
    os.write(1, f"child {ref.response.pid}\n".encode())

loader = threading.Thread(target=load)
loader.start()
loader.join()  # the thread that asked for the process is gone: the child must live on
print("ready", flush=True)
time.sleep(300)
"""


@pytest.fixture
def leaks(monkeypatch: pytest.MonkeyPatch) -> Iterator[ProcessLeakCheck]:
    check = ProcessLeakCheck()
    monkeypatch.setenv(check.variable, check.mark)
    yield check
    check.kill_leftovers()


def none_left(check: ProcessLeakCheck, within: float = 3.0) -> list[int]:
    """The processes of ours still alive once ``within`` seconds have passed (or none are)."""
    deadline = time.monotonic() + within
    left = check.leftovers()
    while left and time.monotonic() < deadline:
        time.sleep(0.01)
        left = check.leftovers()
    return left


#: The commands a test started, ended and closed after it by :func:`_end_commands`.
_STARTED: list[subprocess.Popen[bytes]] = []


@pytest.fixture(autouse=True)
def _end_commands() -> Iterator[None]:
    """After each test, also a failed one: no command left running, no pipe left open.

    A test failing before it waited for its command would leave both to the garbage collector,
    whose ResourceWarning would then fail a later test (test_structure's import check).
    """
    yield
    while _STARTED:
        proc = _STARTED.pop()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        for stream in (proc.stdout, proc.stderr):
            if stream is not None:
                stream.close()


class Command:
    """A ``temoto`` command in a subprocess, its standard output read line by line."""

    def __init__(self, args: list[str], env: dict[str, str] | None = None) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, *args],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            env={**os.environ, **(env or {})},
            cwd=ROOT,
        )
        _STARTED.append(self.proc)
        self.lines: list[str] = []
        self._buf = b""

    def wait_for(self, prefix: str, timeout: float = 15.0, *, anywhere: bool = False) -> str:
        """Read standard output until a line starts with ``prefix`` (or holds it); returns it."""
        assert self.proc.stdout is not None
        fd = self.proc.stdout.fileno()
        deadline = time.monotonic() + timeout
        while True:
            for line in self.lines:
                if line.startswith(prefix) or (anywhere and prefix in line):
                    return line
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([fd], [], [], left)[0]:
                raise AssertionError(f"no line {prefix!r} in {timeout} s: {self.lines}")
            data = os.read(fd, 65536)
            if not data:
                err = self.proc.stderr.read().decode() if self.proc.stderr else ""
                raise AssertionError(f"no line {prefix!r}; it ended: {self.lines}\n{err}")
            self._buf += data
            *done, self._buf = self._buf.split(b"\n")
            self.lines.extend(x.decode() for x in done)

    def signal(self, *signums: int) -> float:
        """Send the signals (50 ms apart); returns when the first was sent (monotonic)."""
        t0 = time.monotonic()
        for i, signum in enumerate(signums):
            if i:
                time.sleep(0.05)
            self.proc.send_signal(signum)
        return t0

    def finish(self, timeout: float = 10.0) -> tuple[int, str]:
        """Wait for the exit; returns the exit status and standard error.

        The rest of standard output goes to :attr:`lines`.
        """
        out, err = self.proc.communicate(timeout=timeout)
        self.lines.extend((self._buf + out).decode().splitlines())
        return self.proc.returncode, err.decode()


@pytest.fixture
def busy_graph(tmp_path: Path) -> tuple[Path, Path]:
    actions = tmp_path / "actions"
    actions.mkdir()
    (actions / "ta_busy.py").write_text(BUSY_ACTION)
    (actions / "ta_busy.umrf.json").write_text(json.dumps(BUSY_UMRF))
    graph = tmp_path / "busy.graph.json"
    graph.write_text(json.dumps(BUSY_GRAPH))
    return graph, actions


# --- temoto run --------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("signums", "code", "entry"),
    [
        ((signal.SIGINT,), 130, ("temoto", "run")),
        ((signal.SIGTERM,), 143, ("temoto", "run")),
        ((signal.SIGTERM,), 143, ("temoto.cli.run",)),  # the command's own entry: the same
    ],
    ids=["SIGINT", "SIGTERM", "python-m-temoto.cli.run-SIGTERM"],
)
def test_run_stops_the_graph_and_its_processes_on_a_signal(
    busy_graph: tuple[Path, Path],
    tmp_path: Path,
    leaks: ProcessLeakCheck,
    signums: tuple[int, ...],
    code: int,
    entry: tuple[str, ...],
) -> None:
    graph, actions = busy_graph
    device = tmp_path / "device"
    run = Command(
        ["-m", *entry, str(graph), "--actions", str(actions)],
        {"BUSY_TOUCH": str(tmp_path / "child.pid"), "BUSY_DEVICE": str(device)},
    )
    child = int(run.wait_for("busy ").split()[1])
    assert child in leaks.leftovers()
    assert device.read_text() == "running"
    run.signal(*signums)
    status, err = run.finish()
    assert status == code, err
    assert "Traceback" not in err
    assert "busy: on_stopped" in run.lines
    assert "temoto: file_device: device off" in err  # made safe by the command, not atexit
    assert device.read_text() == "off"
    assert none_left(leaks) == []


def test_run_a_second_sigint_stops_at_once(
    busy_graph: tuple[Path, Path], tmp_path: Path, leaks: ProcessLeakCheck
) -> None:
    # The action ignores its stop request (the engine would wait 5 s for it) and its process
    # and grandchild ignore SIGTERM (the manager would wait 5 s before SIGKILL).
    graph, actions = busy_graph
    run = Command(
        ["-m", "temoto", "run", str(graph), "--actions", str(actions)],
        {
            "BUSY_TOUCH": str(tmp_path / "child.pid"),
            "BUSY_STUBBORN": "1",
            "BUSY_DEVICE": str(tmp_path / "device"),
        },
    )
    run.wait_for("busy ")
    t0 = run.signal(signal.SIGINT, signal.SIGINT)
    status, err = run.finish()
    assert status == 130, err
    assert time.monotonic() - t0 < 4.0  # well under the 5 s + 5 s the waits would take
    assert "Traceback" not in err
    assert "stopping at once" in err
    assert "temoto: file_device: device off" in err
    assert none_left(leaks) == []


# --- temoto demo -------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("signums", "code"),
    [((signal.SIGINT,), 130), ((signal.SIGTERM,), 143), ((signal.SIGINT, signal.SIGINT), 130)],
    ids=["SIGINT", "SIGTERM", "SIGINT-twice"],
)
def test_demo_1_leaves_no_sensor_process_behind(
    leaks: ProcessLeakCheck, signums: tuple[int, ...], code: int
) -> None:
    demo = Command(["-m", "temoto", "demo", "1"])
    demo.wait_for("display: receiving from lidar_3d", anywhere=True)
    assert leaks.leftovers(), "the sensor process should be running"
    demo.signal(*signums)
    status, err = demo.finish()
    assert status == code, err
    assert "Traceback" not in err
    assert none_left(leaks) == []


# --- temoto serve ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("signums", "entry"),
    [
        ((signal.SIGINT,), ("temoto", "serve")),
        ((signal.SIGTERM,), ("temoto", "serve")),
        ((signal.SIGINT, signal.SIGINT), ("temoto", "serve")),
        ((signal.SIGINT,), ("temoto.cli.serve",)),  # the command's own entry: the same
    ],
    ids=["SIGINT", "SIGTERM", "SIGINT-twice", "python-m-temoto.cli.serve-SIGINT"],
)
def test_serve_exits_0_on_a_signal(
    leaks: ProcessLeakCheck, signums: tuple[int, ...], entry: tuple[str, ...]
) -> None:
    serve = Command(["-m", *entry, "--actor", "a", "--fleet-url", "inproc://signals", "--insecure"])
    serve.wait_for("ready")
    serve.signal(*signums)
    status, err = serve.finish()
    assert status == 0, err
    assert "Traceback" not in err
    assert none_left(leaks) == []


# --- SIGKILL of a Process Manager's process ----------------------------------------------------


def test_children_and_grandchildren_die_with_a_sigkilled_manager(
    leaks: ProcessLeakCheck,
) -> None:
    parent = Command(["-c", textwrap.dedent(MANAGER_PARENT)])
    try:
        child = int(parent.wait_for("child ").split()[1])
        grandchild = int(parent.wait_for("grandchild ").split()[1])
        parent.wait_for("ready")
        # Alive after the thread that loaded the child ended (the parent-death signal is tied
        # to the forking thread, so that thread must not be the caller's).
        assert {child, grandchild} <= set(leaks.leftovers())
        os.kill(parent.proc.pid, signal.SIGKILL)
        # Not communicate(): a child left alive would hold the output pipe open.
        assert parent.proc.wait(5) == -signal.SIGKILL
        assert none_left(leaks) == []
    finally:
        # on every way out, also a failed wait above: no process or pipe is left for the
        # garbage collector to warn about in a later test (a ResourceWarning is an error)
        if parent.proc.poll() is None:
            parent.proc.kill()
            parent.proc.wait()
        for stream in (parent.proc.stdout, parent.proc.stderr):
            if stream is not None:
                stream.close()


# --- temoto actions | head ---------------------------------------------------------------------


def test_a_closed_output_pipe_is_no_traceback() -> None:
    proc = subprocess.Popen(
        [sys.executable, "-m", "temoto", "actions", "--actions", "examples/actions/conformance"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        cwd=ROOT,
    )
    assert proc.stdout is not None
    proc.stdout.close()  # like `head` that has read enough, before anything is written
    _, err = proc.communicate(timeout=20)
    assert proc.returncode == 141, err
    assert err.decode() == ""


# --- SignalExit after its block ----------------------------------------------------------------


def test_a_signal_after_the_block_of_a_signalled_command_hurries_and_raises_nothing() -> None:
    # A second Ctrl-C may land while the command winds down after its SignalExit block; the
    # default handler would raise KeyboardInterrupt there (a traceback, a wrong exit status).
    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    hurried: list[str] = []
    try:
        with SignalExit(hurry=(lambda: hurried.append("hurry"),)) as signals:
            os.kill(os.getpid(), signal.SIGINT)
            assert signals.stop.wait(5.0)
        os.kill(os.getpid(), signal.SIGINT)  # after the block: taken, not raised
        os.kill(os.getpid(), signal.SIGTERM)
        deadline = time.monotonic() + 5.0  # the signals' thread calls the hurry callbacks
        while len(hurried) < 2 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert hurried == ["hurry", "hurry"]
        assert signals.exit_code == 130
    finally:
        signals.close()  # the process goes on: the signals' thread ends
        for signum, handler in before.items():
            signal.signal(signum, handler)


def test_a_block_left_without_a_signal_restores_the_handlers() -> None:
    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    with SignalExit():
        assert signal.getsignal(signal.SIGINT) is not before[signal.SIGINT]
    assert {s: signal.getsignal(s) for s in before} == before


LATE_SIGNAL = r"""
import atexit, os, signal, sys
from temoto.cli.signals import SignalExit

def late():  # registered first, so it runs after SignalExit's own exit hook (last in, first out)
    print("at exit:", signal.getsignal(signal.SIGINT) is signal.SIG_IGN, flush=True)
    os.kill(os.getpid(), signal.SIGINT)  # a second Ctrl-C while the interpreter finishes

atexit.register(late)
with SignalExit() as signals:
    os.kill(os.getpid(), signal.SIGINT)
    signals.stop.wait(5)
sys.exit(signals.exit_code)
"""


def test_a_signal_while_the_interpreter_finishes_leaves_the_exit_status_alone() -> None:
    # Finalisation resets a Python signal handler to the default action: a second Ctrl-C then
    # killed the process by SIGINT (status -2) instead of letting it exit 130.
    proc = subprocess.run(
        [sys.executable, "-c", LATE_SIGNAL], capture_output=True, text=True, timeout=30, cwd=ROOT
    )
    assert proc.stdout.splitlines()[-1] == "at exit: True", proc.stderr
    assert proc.returncode == 130, proc.stderr
    assert "Traceback" not in proc.stderr


def test_devices_are_made_safe_while_another_thread_imports_the_drivers(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # A signal while an action's import of temoto.drivers.base is half done: the module is in
    # sys.modules without make_all_safe yet (the serve command exited 1 with a traceback).
    import types

    from temoto.cli.signals import make_devices_safe

    monkeypatch.setitem(sys.modules, "temoto.drivers.base", types.ModuleType("half-imported"))
    make_devices_safe("a signal")  # nothing to make safe, and no AttributeError


# --- no signal can hang a command ------------------------------------------------------------

HELD_LOCK = r"""
import faulthandler, os, signal, sys
from temoto.cli.signals import SignalExit

faulthandler.dump_traceback_later(10, exit=True)  # a hang: a traceback and exit 1
with SignalExit() as signals:
    # where the main thread is inside signals.stop.wait(): holding the event's lock; a
    # handler that sets the event there waits for itself
    with signals.stop._cond:
        os.kill(os.getpid(), signal.SIGTERM)
        print("went on", flush=True)
    print("stopped:", signals.stop.wait(10), flush=True)
sys.exit(signals.exit_code)
"""


def test_a_signal_inside_the_stop_event_s_own_wait_does_not_hang() -> None:
    # The robot command hung on a SIGTERM right after "serving": the handler ran inside
    # stop.wait() and its stop.set() waited for the lock that wait held.
    proc = subprocess.run(
        [sys.executable, "-c", HELD_LOCK], capture_output=True, text=True, timeout=60, cwd=ROOT
    )
    assert proc.stdout.splitlines() == ["went on", "stopped: True"], proc.stderr
    assert proc.returncode == 143, proc.stderr
    assert "SIGTERM: stopping" in proc.stderr


MISSED_WAKEUP = r"""
import faulthandler, os, signal, sys
from temoto.cli.signals import SignalExit

faulthandler.dump_traceback_later(20, exit=True)
with SignalExit() as signals:
    # the signal lands where the main thread cannot run its handler: as when it lands just
    # before the main thread blocks in stop.wait(), or in another thread of the process
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM})
    os.kill(os.getpid(), signal.SIGTERM)
    print("stopped:", signals.stop.wait(10), flush=True)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGTERM})
sys.exit(signals.exit_code)
"""


def test_a_signal_the_main_thread_does_not_run_still_stops_the_command() -> None:
    proc = subprocess.run(
        [sys.executable, "-c", MISSED_WAKEUP], capture_output=True, text=True, timeout=60, cwd=ROOT
    )
    assert proc.stdout.splitlines() == ["stopped: True"], proc.stderr
    assert proc.returncode == 143, proc.stderr
