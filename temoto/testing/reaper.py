"""Processes marked by an environment variable, and a reaper that ends them when their owner dies.

A test run starts processes that start processes (``unshare -n`` runners, robots, simulators,
routers). When the run ends normally, each test stops what it started. When the run itself is
killed (SIGKILL, an out-of-memory kill, a CI time-out of the test command alone), nothing runs
its clean-up, and the grandchildren live on: a runner in its network namespace keeps its robots
going with nobody to read them.

Every descendant inherits its parent's environment, so a variable set once in the owner marks
them all (:func:`marked_pids` finds them through ``/proc/<pid>/environ``, which holds the
environment a process started with). :class:`Reaper` starts a small watcher process (this module
run as ``python -m temoto.testing.reaper NAME=VALUE``) that waits, without spinning, on a pidfd of
its owner and on a pipe from it. When the owner dies in any way the watcher sends SIGKILL to every
process still marked; an owner that ends normally says goodbye on the pipe first
(:meth:`Reaper.close`), and the watcher exits without touching anything.

Standard library only; Linux (``/proc``).
"""

from __future__ import annotations

import os
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

__all__ = ["Reaper", "marked_pids", "reap"]

#: What the owner writes before closing the pipe when it ends normally.
_BYE = b"bye\n"
#: The owner's pid, given to the watcher (it may die before the watcher asks for its parent).
_OWNER_VARIABLE = "TEMOTO_REAPER_OWNER"
#: Passes over ``/proc`` when reaping (a process forking as it is killed leaves a child behind).
_PASSES = 5


def marked_pids(name: str, value: str) -> list[int]:
    """Pids of live (not zombie) processes whose starting environment holds ``name=value``.

    Args:
        name: The environment variable.
        value: Its value.

    Returns:
        The pids, this process's own included if it is marked.
    """
    found = []
    needle = f"{name}={value}".encode()
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            if needle in (entry / "environ").read_bytes().split(b"\0"):
                stat = (entry / "stat").read_text()
                if stat[stat.rindex(")") + 2] != "Z":
                    found.append(int(entry.name))
        except OSError:  # gone meanwhile, or not ours to read
            continue
    return found


def reap(name: str, value: str) -> list[int]:
    """SIGKILL every process marked ``name=value`` except this one.

    Returns:
        The pids that were sent SIGKILL.
    """
    killed: list[int] = []
    for _ in range(_PASSES):
        pids = [pid for pid in marked_pids(name, value) if pid != os.getpid()]
        if not pids:
            break
        for pid in pids:
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                continue
            if pid not in killed:
                killed.append(pid)
        time.sleep(0.05)
    return killed


class Reaper:
    """A watcher that SIGKILLs every marked process if this process dies without :meth:`close`.

    Args:
        name: The environment variable that marks this process's descendants. It is set in
            ``os.environ`` here, so processes started from now on carry it.
        value: Its value (unique per owner: a pid and a time are enough).
    """

    def __init__(self, name: str, value: str) -> None:
        self.name, self.value = name, value
        os.environ[name] = value
        # the watcher is marked too (it inherits the environment) and leaves itself out
        self._proc = subprocess.Popen(
            [sys.executable, "-m", __name__, f"{name}={value}"],
            env={**os.environ, _OWNER_VARIABLE: str(os.getpid())},
            stdin=subprocess.PIPE,
            stdout=subprocess.DEVNULL,
            stderr=None,
            start_new_session=True,  # a Ctrl-C to the owner's group does not reach it
        )

    def close(self) -> None:
        """The owner ends normally: the watcher exits and kills nothing."""
        stdin = self._proc.stdin
        if stdin is None or stdin.closed:
            return
        try:
            stdin.write(_BYE)
            stdin.close()
        except BrokenPipeError:
            pass
        try:
            self._proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait()


def _wait_for_owner(owner: int) -> bool:
    """Block until the owner says goodbye on stdin (True) or dies (False).

    The owner's death is watched through a pidfd, not through the pipe: a process the owner
    forked without exec (``multiprocessing``'s fork) holds the pipe open after the owner is gone.
    """
    stdin = sys.stdin.buffer.fileno()
    try:
        pidfd = os.pidfd_open(owner)
    except ProcessLookupError:
        return False
    except (AttributeError, OSError):  # no pidfd (kernel < 5.3): look at the parent each 0.5 s
        pidfd = -1
    if os.getppid() != owner:  # it died before the pidfd was open (this process was re-parented)
        return False
    poller = select.poll()
    poller.register(stdin, select.POLLIN)
    if pidfd >= 0:
        poller.register(pidfd, select.POLLIN)
    said = b""
    while True:
        for fd, _ in poller.poll(None if pidfd >= 0 else 500):
            if fd == pidfd:
                return False
            chunk = os.read(stdin, 64)
            said += chunk
            if said == _BYE:
                return True
            if not chunk:  # closed without goodbye: only the owner's death decides now
                poller.unregister(stdin)
        if pidfd < 0 and os.getppid() != owner:
            return False


def main(argv: list[str] | None = None) -> int:
    """The watcher: wait for the owner to say goodbye or die; reap in the second case."""
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1 or "=" not in args[0]:
        sys.stderr.write("usage: python -m temoto.testing.reaper NAME=VALUE\n")
        return 2
    name, value = args[0].split("=", 1)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # only the owner decides
    if _wait_for_owner(int(os.environ.get(_OWNER_VARIABLE, os.getppid()))):
        return 0
    killed = reap(name, value)
    if killed:
        pids = " ".join(map(str, killed))
        sys.stderr.write(
            f"temoto.testing.reaper: the owner of {name}={value} died; killed {len(killed)} "
            f"process(es) it had left: {pids}\n"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
