"""No input makes a command hang, and a signal always ends it.

Process tests: each runs ``python -m temoto`` (or a small script) in a child process with a
bounded wait; a hang is a test failure (``subprocess.TimeoutExpired``), never a stuck suite.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
GUIDE = ROOT / "examples" / "umrf-guide"
HELLO = GUIDE / "graphs" / "01_hello.graph.json"
BOUND = 30.0  # seconds a refused input may take on a loaded machine (it takes ~0.5 s)


def temoto(*args: str, cwd: Path = ROOT) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "temoto", *args],
        capture_output=True,
        text=True,
        timeout=BOUND,
        cwd=cwd,
        check=False,
    )


@pytest.fixture
def fifo(tmp_path: Path) -> Path:
    path = tmp_path / "f.json"
    os.mkfifo(path)
    return path


@pytest.mark.parametrize(
    "args",
    [
        pytest.param(["run", "{fifo}", "--actions", str(GUIDE / "actions")], id="run-graph"),
        pytest.param(["validate", "{fifo}"], id="validate"),
        pytest.param(["graph", "dot", "{fifo}"], id="graph-dot"),
        pytest.param(
            ["run", str(HELLO), "--actions", str(GUIDE / "actions"), "--trace", "{fifo}"],
            id="run-trace",
        ),
        pytest.param(["view", "{fifo}", "--port", "0"], id="view"),
    ],
)
def test_a_fifo_given_as_a_file_is_refused_in_one_line(fifo: Path, args: list[str]) -> None:
    # before: open() of a FIFO without a writer (or reader) blocked forever
    done = temoto(*(a.replace("{fifo}", str(fifo)) for a in args))
    assert done.returncode == 2, done.stderr
    assert done.stderr.count("\n") == 1, done.stderr
    assert f"{fifo}" in done.stderr
    assert "a FIFO, not a regular file" in done.stderr


BLOCKED = r"""
import os, sys
from temoto.cli.signals import SignalExit
with SignalExit(force_exit=1.0) as signals:
    print("ready", flush=True)
    os.open(sys.argv[1], os.O_RDONLY)  # a FIFO without a writer: blocks for ever
"""


def test_a_second_signal_ends_a_command_whose_main_thread_is_blocked(fifo: Path) -> None:
    proc = subprocess.Popen(
        [sys.executable, "-c", BLOCKED, str(fifo)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline() == "ready\n"
        time.sleep(0.2)  # into the open() (a signal before it is handled the same way)
        proc.send_signal(signal.SIGINT)
        time.sleep(0.2)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=BOUND)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130, err
    assert "exiting" in err
    assert "Traceback" not in err


def test_a_third_signal_exits_at_once(fifo: Path) -> None:
    script = BLOCKED.replace("force_exit=1.0", "force_exit=600.0")
    proc = subprocess.Popen(
        [sys.executable, "-c", script, str(fifo)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline() == "ready\n"
        for _ in range(3):
            time.sleep(0.2)
            proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=BOUND)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 143, err
    assert "exiting now" in err
