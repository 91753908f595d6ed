"""What the managers' tests share: no process left behind, and commands started as programs."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable, Iterator
from typing import Any

import pytest

from temoto.testing import ProcessLeakCheck


@pytest.fixture(autouse=True)
def no_leaked_processes(monkeypatch: pytest.MonkeyPatch) -> Iterator[ProcessLeakCheck]:
    """Every process a test here starts must be gone when it ends (stragglers are killed)."""
    check = ProcessLeakCheck()
    monkeypatch.setenv(check.variable, check.mark)
    yield check
    leaked = check.kill_leftovers()
    if leaked:
        pytest.fail(f"test left processes running: {leaked}", pytrace=False)


@pytest.fixture
def python_m() -> Iterator[Callable[..., subprocess.Popen[str]]]:
    """Starts ``python -m ARGS...`` (``subprocess.Popen``'s keywords, text mode); after the
    test, also a failed one, kills what still runs and closes its pipes."""
    started: list[subprocess.Popen[str]] = []

    def start(*args: str, **popen: Any) -> subprocess.Popen[str]:
        proc = subprocess.Popen([sys.executable, "-m", *args], text=True, **popen)
        started.append(proc)
        return proc

    yield start
    for proc in started:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        for stream in (proc.stdout, proc.stderr):
            if stream is not None:
                stream.close()
