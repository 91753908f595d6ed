"""Helpers for tests of TeMoto and of code built on it (in the spirit of ``trio.testing``).

Processes:

* ``python -m temoto.testing.child`` (:mod:`temoto.testing.child`) is a scriptable child
  program: it prints ``ready <pid>``, then sleeps, exits with a code, crashes, ignores SIGTERM,
  forks grandchildren or obeys commands on stdin, as its options say. :func:`child_command`
  builds its command line.
* :class:`ProcessLeakCheck` finds the processes a test started and left running (children,
  grandchildren, anything that inherited the test's environment), kills them, and tells the test
  which ones there were::

      @pytest.fixture(autouse=True)
      def no_leaked_processes(monkeypatch):
          check = ProcessLeakCheck()
          monkeypatch.setenv(check.variable, check.mark)
          yield check
          leaked = check.kill_leftovers()
          if leaked:
              pytest.fail(f"test left processes running: {leaked}")

Devices and robots:

* ``python -m temoto.testing.simhost`` (:mod:`temoto.testing.simhost`) runs one device
  simulator in a process of its own and prints the device's state on every change;
  ``python -m temoto.testing.exitpaths`` (:mod:`temoto.testing.exitpaths`) takes the robot
  command out by one way (mission end, fault, exception, signals, SIGKILL) and reports what the
  device saw (``docs/safety.md``).
* :class:`temoto.testing.robots.FakeRobot` is a robot handle's read side (pose, joints, vehicle,
  health) for tests of code that samples a robot.

Fleets:

* :func:`temoto.testing.fleet.settle` hands the hellos of in-process
  :class:`~temoto.transport.auth.FleetAuth` members to one another until they are settled.

Actions:

* :class:`Script` (:mod:`temoto.testing.scripted`) makes scripted actions: per node, what each
  run returns, which outputs it sets, how long it waits (on the engine's clock) and whether it
  waits for its stop; it records every run and hook call, and a test can wait for a node's
  start without polling (``docs/python-api.md``).

Importing this package has no side effects and does not import :mod:`temoto.testing.child`
(so ``python -m temoto.testing.child`` runs without a ``runpy`` warning), nor the engine:
:class:`Script`, :class:`Outcome`, :class:`Run` and :class:`ScriptedAction` are imported from
:mod:`temoto.testing.scripted` on first use.
"""

from __future__ import annotations

import contextlib
import os
import selectors
import signal
import sys
import time
import uuid
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from temoto.testing.scripted import Outcome, Run, Script, ScriptedAction

__all__ = [
    "CHILD_MODULE",
    "CHILD_SCRIPT",
    "Outcome",
    "ProcessLeakCheck",
    "Run",
    "Script",
    "ScriptedAction",
    "child_command",
]

_SCRIPTED = frozenset({"Outcome", "Run", "Script", "ScriptedAction"})


def __getattr__(name: str) -> Any:
    """The scripted-action names, imported on first use (they import the engine's modules)."""
    if name in _SCRIPTED:
        from temoto.testing import scripted

        return getattr(scripted, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


CHILD_MODULE = "temoto.testing.child"
"""The module to run with ``python -m`` for the scriptable child program."""

CHILD_SCRIPT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "child.py")
"""The child program's file (it imports only the standard library, so it runs by path too)."""


def child_command(
    *,
    sleep: float | None = None,
    exit_code: int | None = None,
    crash: bool = False,
    ignore_term: bool = False,
    grandchildren: int = 0,
    on_stdin: bool = False,
    touch: str | os.PathLike[str] | None = None,
    python: str | None = None,
) -> list[str]:
    """The command line that runs the child program with the given behaviour.

    Args:
        sleep: Seconds to sleep before exiting (None: forever, unless ``exit_code`` or
            ``crash`` is given, which then happen at once).
        exit_code: Exit code after the sleep.
        crash: Abort (SIGABRT) after the sleep.
        ignore_term: Ignore SIGTERM (grandchildren inherit this).
        grandchildren: How many grandchildren to fork (same process group; they sleep until
            killed).
        on_stdin: Obey ``exit N`` / ``crash`` / ``kill SIG`` lines on standard input.
        touch: A file to write the child's pid to at start.
        python: The interpreter; ``sys.executable`` if None.

    Returns:
        The argument list. It runs ``temoto/testing/child.py`` by path in isolated mode
        (``python -I -S .../child.py``): the same program as ``python -m
        temoto.testing.child``, but it starts in half the time because it imports neither
        ``site`` nor the ``temoto`` package.
    """
    argv = [python or sys.executable, "-I", "-S", CHILD_SCRIPT]
    if sleep is not None:
        argv += ["--sleep", repr(float(sleep))]
    if exit_code is not None:
        argv += ["--exit", str(int(exit_code))]
    if crash:
        argv.append("--crash")
    if ignore_term:
        argv.append("--ignore-term")
    if grandchildren:
        argv += ["--grandchildren", str(int(grandchildren))]
    if on_stdin:
        argv.append("--on-stdin")
    if touch is not None:
        argv += ["--touch", os.fspath(touch)]
    return argv


class ProcessLeakCheck:
    """Finds, by an environment marker, the processes a test started and left behind.

    Put ``variable=mark`` into the environment of the test process (``monkeypatch.setenv``)
    before it starts anything: every process started from then on, and every process those
    fork, inherits it. :meth:`leftovers` lists the live ones (read from
    ``/proc/<pid>/environ``; processes of other users are skipped), :meth:`kill_leftovers`
    kills them with SIGKILL and waits until they are gone.

    Args:
        variable: The environment variable to use.
    """

    def __init__(self, variable: str = "TEMOTO_TEST_PROCESS_MARK") -> None:
        self.variable = variable
        self.mark = uuid.uuid4().hex
        self._needle = f"{variable}={self.mark}".encode()

    def leftovers(self) -> list[int]:
        """The live processes (not zombies) that carry the marker, except this one.

        Returns:
            Their pids, sorted.
        """
        from temoto.managers._procmon import (  # here: keeps importing this module light
            process_state,
            processes_with_environ,
        )

        return [
            pid
            for pid in processes_with_environ(self._needle)
            if process_state(pid) not in ("Z", "X", "x", None)
        ]

    def kill_leftovers(self, timeout: float = 5.0) -> list[int]:
        """Kill every leftover process and wait until each has exited.

        Leftovers that are children of this process are reaped.

        Args:
            timeout: How long to wait for them in total.

        Returns:
            The pids that were left over (empty if none).
        """
        pids = self.leftovers()
        fds: dict[int, int] = {}
        for pid in pids:
            with contextlib.suppress(ProcessLookupError):
                fds[pid] = os.pidfd_open(pid)
                signal.pidfd_send_signal(fds[pid], signal.SIGKILL)
        deadline = time.monotonic() + timeout
        with selectors.DefaultSelector() as sel:
            for pid, fd in fds.items():
                sel.register(fd, selectors.EVENT_READ, pid)
            while sel.get_map() and (left := deadline - time.monotonic()) > 0:
                for key, _ in sel.select(left):
                    sel.unregister(key.fd)
        for fd in fds.values():
            with contextlib.suppress(ChildProcessError):
                os.waitid(os.P_PIDFD, fd, os.WEXITED | os.WNOHANG)
            os.close(fd)
        return pids
