"""temoto.testing.reaper: what a killed run leaves behind is ended; a normal end kills nothing."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Callable

from temoto.testing.reaper import marked_pids

#: An owner that starts the reaper, then a grandchild through a shell (a runner's robot), prints
#: the grandchild's pid, and either ends normally (argv[1] == "close") or waits to be killed.
OWNER = textwrap.dedent(
    """
    import subprocess, sys, time
    from temoto.testing.reaper import Reaper
    reaper = Reaper("TEMOTO_REAPER_TEST", sys.argv[2])
    shell = subprocess.Popen(["sh", "-c", "sleep 60 & echo $!; wait"], stdout=subprocess.PIPE,
                             text=True)
    print(shell.stdout.readline().strip(), flush=True)
    if sys.argv[1] == "close":
        reaper.close()
        sys.exit(0)
    time.sleep(60)
    """
)


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def _owner(mode: str, mark: str) -> tuple[subprocess.Popen[str], int]:
    owner = subprocess.Popen(
        [sys.executable, "-c", OWNER, mode, mark], stdout=subprocess.PIPE, text=True
    )
    assert owner.stdout is not None
    grandchild = int(owner.stdout.readline())
    return owner, grandchild


def _wait_until(predicate: Callable[[], object], timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.02)
    return bool(predicate())


def test_a_sigkilled_owner_leaves_no_process_behind() -> None:
    mark = f"kill-{os.getpid()}-{time.time_ns()}"
    owner, grandchild = _owner("wait", mark)
    assert _alive(grandchild)
    # the watcher, the shell and its sleep (the owner set the mark after it started)
    assert len(marked_pids("TEMOTO_REAPER_TEST", mark)) == 3
    owner.send_signal(signal.SIGKILL)
    owner.wait(5)
    owner.stdout.close()  # type: ignore[union-attr]
    assert _wait_until(lambda: not marked_pids("TEMOTO_REAPER_TEST", mark), 5.0), marked_pids(
        "TEMOTO_REAPER_TEST", mark
    )
    assert not _alive(grandchild)


def test_an_owner_that_ends_normally_kills_nothing() -> None:
    mark = f"close-{os.getpid()}-{time.time_ns()}"
    owner, grandchild = _owner("close", mark)
    try:
        assert owner.wait(10) == 0
        owner.stdout.close()  # type: ignore[union-attr]
        time.sleep(0.3)  # a watcher that reaped would have done so by now
        assert _alive(grandchild)  # left on purpose: checking for leftovers is the tests' job
    finally:
        os.kill(grandchild, signal.SIGKILL)
    assert _wait_until(lambda: not _alive(grandchild), 5.0)
