"""How the Process Manager stops processes: whole process groups, SIGTERM then SIGKILL.

:class:`GroupStopper` stops a process and everything left in its process group (grandchildren,
also after the leader exited): SIGTERM to the group, up to ``grace`` seconds for it to work
(cut short by the manager's hurry eventfd), SIGKILL to what is left, and an error naming the
pids that survive SIGKILL for ``kill_timeout`` seconds. It also stops the processes that carry
a spawn token (the left-overs of a load a crash interrupted, or of a process that died while
the manager was down). Each process is reached through a pidfd opened only while it still runs
with the recorded start time, so a reused pid is never signalled. The helpers read ``/proc``
(group members, token holders) and wait on pidfds with a selector, never by polling.

Used by :class:`~temoto.managers.process.ProcessManager`; ``docs/process-manager.md`` is the
design.
"""

from __future__ import annotations

import contextlib
import logging
import os
import selectors
import signal
import time
from collections.abc import Iterable
from dataclasses import dataclass

from temoto.errors import ResourceError
from temoto.managers._procmon import (
    process_start_time,
    process_state,
    processes_with_environ,
    unguard_group,
)

__all__ = [
    "DEAD_STATES",
    "TOKEN_VARIABLE",
    "GroupStopper",
    "ProcessRecord",
    "describe_exit",
    "group_members",
    "open_if_same",
    "signal_group",
    "token_processes",
    "wait_readable",
]

logger = logging.getLogger(__name__)

#: States of /proc/<pid>/stat that mean "no longer running".
DEAD_STATES = frozenset({"Z", "X", "x"})


#: Environment variable holding each started process's spawn token (inherited by whatever it
#: starts): it finds the processes of a load interrupted by a crash, and left-overs of a process
#: that died while the manager was down.
TOKEN_VARIABLE = "TEMOTO_PROCESS_TOKEN"


@dataclass(eq=False)
class ProcessRecord:
    """What the manager knows about one process it started or adopted."""

    pid: int
    pgid: int
    start_time: int
    executable: str
    resource_id: str
    child: bool
    stopping: bool = False
    exit: tuple[int | None, int | None] | None = None


def describe_exit(
    pid: int, executable: str, returncode: int | None, sig: int | None, child: bool
) -> str:
    who = f"process {pid} ({executable})"
    if returncode is not None:
        return f"{who} exited with code {returncode}"
    if sig is not None:
        try:
            name = signal.Signals(sig).name
        except ValueError:
            name = f"signal {sig}"
        return f"{who} was killed by signal {name}"
    if child:
        return f"{who} exited (status unknown: it was reaped elsewhere)"
    return f"{who} exited (status unknown: not a child of this manager)"


def wait_readable(fds: Iterable[int], timeout: float | None, hurry: int = -1) -> set[int]:
    """Block until every fd is readable or ``timeout`` passes; returns the readable ones.

    ``hurry``, if given, is an fd that ends the wait early when it is readable.
    """
    ready: set[int] = set()
    deadline = None if timeout is None else time.monotonic() + timeout
    with selectors.DefaultSelector() as sel:
        for fd in fds:
            sel.register(fd, selectors.EVENT_READ)
        if hurry >= 0:
            sel.register(hurry, selectors.EVENT_READ, "hurry")
        while len(sel.get_map()) > (hurry >= 0):
            left = None if deadline is None else max(0.0, deadline - time.monotonic())
            events = sel.select(left)
            if not events:
                break
            if any(key.data == "hurry" for key, _ in events):
                ready.update(key.fd for key, _ in events if key.data != "hurry")
                break
            for key, _ in events:
                ready.add(key.fd)
                sel.unregister(key.fd)
    return ready


def token_processes(token: str) -> list[tuple[int, int]]:
    """Live processes (pid, start time) whose environment holds ``TEMOTO_PROCESS_TOKEN=token``."""
    found: list[tuple[int, int]] = []
    for pid in processes_with_environ(f"{TOKEN_VARIABLE}={token}".encode()):
        start = process_start_time(pid)
        if start is not None and process_state(pid) not in DEAD_STATES:
            found.append((pid, start))
    return found


def group_members(pgid: int) -> list[tuple[int, int]]:
    """Live processes (pid, start time) whose process group is ``pgid``, from ``/proc``."""
    members: list[tuple[int, int]] = []
    for name in os.listdir("/proc"):
        if not name.isdigit():
            continue
        try:
            with open(f"/proc/{name}/stat", "rb") as f:
                data = f.read()
        except OSError:
            continue
        fields = data.rpartition(b")")[2].split()
        # fields[0] is field 3 (state), fields[2] field 5 (pgrp), fields[19] field 22.
        if len(fields) < 20 or fields[0].decode() in DEAD_STATES:
            continue
        if int(fields[2]) == pgid:
            members.append((int(name), int(fields[19])))
    return members


def open_if_same(pid: int, start_time: int) -> int | None:
    """A pidfd for ``pid`` if it still runs with ``start_time``, else None."""
    try:
        fd = os.pidfd_open(pid)
    except ProcessLookupError:
        return None
    if process_start_time(pid) != start_time or process_state(pid) in DEAD_STATES:
        os.close(fd)
        return None
    return fd


def signal_group(pgid: int, sig: int) -> None:
    """Send ``sig`` to process group ``pgid`` (nothing if the group is gone)."""
    with contextlib.suppress(ProcessLookupError):
        os.killpg(pgid, sig)


class GroupStopper:
    """Stops processes and their process groups (see the module docstring).

    Args:
        grace: Seconds between SIGTERM and SIGKILL.
        kill_timeout: Seconds to wait for a SIGKILLed process to disappear.
        hurry_fd: An fd that, once readable, ends every grace period at once.
        unguard: Whether stopped groups have a guard process to dismiss (``die_with_manager``).
        origin: The name errors carry as their origin (the server's name).
    """

    def __init__(
        self, grace: float, kill_timeout: float, hurry_fd: int, *, unguard: bool, origin: str
    ) -> None:
        self.grace = grace
        self.kill_timeout = kill_timeout
        self.hurry_fd = hurry_fd
        self.unguard = unguard
        self.origin = origin

    def stop(self, record: ProcessRecord, pidfd: int | None) -> None:
        """SIGTERM the group, wait for the leader up to ``grace``, SIGKILL the rest; reap."""
        deadline = time.monotonic() + self.grace
        sent: int | None = None  # the last signal sent to the group
        try:
            if pidfd is not None and not wait_readable([pidfd], 0):
                signal_group(record.pgid, signal.SIGTERM)
                sent = signal.SIGTERM
                if not wait_readable([pidfd], self.grace, self.hurry_fd):
                    logger.warning(
                        "process %d (%s) ignored SIGTERM for %.3g s: sending SIGKILL",
                        record.pid,
                        record.executable,
                        self.grace,
                    )
                    signal_group(record.pgid, signal.SIGKILL)
                    sent = signal.SIGKILL
                    if not wait_readable([pidfd], self.kill_timeout):
                        raise ResourceError(
                            f"process {record.pid} ({record.executable}) survived SIGKILL for"
                            f" {self.kill_timeout:g} s",
                            origin=self.origin,
                        )
            if pidfd is not None:
                with contextlib.suppress(ChildProcessError):
                    os.waitid(os.P_PIDFD, pidfd, os.WEXITED | os.WNOHANG)
        finally:
            if pidfd is not None:
                os.close(pidfd)
        if sent is None:
            deadline = time.monotonic() + self.grace
        self.stop_members(record, deadline, sent)
        if self.unguard:
            unguard_group(record.pgid)
        logger.info("stopped process %d (%s)", record.pid, record.executable)

    def stop_members(self, record: ProcessRecord, deadline: float, sent: int | None) -> None:
        """Stop what is left of the leader's process group (grandchildren).

        ``sent`` is the signal the group already got (None, SIGTERM or SIGKILL); ``deadline``
        ends the grace period of SIGTERM.
        """
        try:
            os.killpg(record.pgid, 0)  # cheap: is anyone left in the group?
        except ProcessLookupError:
            return
        except PermissionError:
            pass
        self.stop_processes(
            group_members(record.pgid), deadline, sent, f"process group {record.pgid}", record.pgid
        )

    def stop_processes(
        self,
        members: list[tuple[int, int]],
        deadline: float,
        sent: int | None,
        what: str,
        pgid: int | None = None,
    ) -> None:
        """Stop processes given as (pid, start time): SIGTERM, wait until ``deadline``, SIGKILL.

        ``sent`` is the signal they already got (None, SIGTERM or SIGKILL); ``pgid``, if given,
        is their group, SIGKILLed as a whole too.
        """
        fds: dict[int, int] = {}
        try:
            for pid, start in members:
                fd = open_if_same(pid, start)
                if fd is not None:
                    fds[fd] = pid
            if not fds:
                return
            if sent is None:
                for fd in fds:
                    with contextlib.suppress(ProcessLookupError):
                        signal.pidfd_send_signal(fd, signal.SIGTERM)
            left = set(fds)
            if sent != signal.SIGKILL:
                left -= wait_readable(fds, max(0.0, deadline - time.monotonic()), self.hurry_fd)
            if left:
                if sent != signal.SIGKILL:
                    logger.warning(
                        "%s: %d process(es) still running after SIGTERM: SIGKILL", what, len(left)
                    )
                for fd in left:
                    with contextlib.suppress(ProcessLookupError):
                        signal.pidfd_send_signal(fd, signal.SIGKILL)
                if pgid is not None:
                    # Members forked after the scan are reached through the group id, which
                    # their living siblings keep from being reused.
                    signal_group(pgid, signal.SIGKILL)
                stuck = left - wait_readable(left, self.kill_timeout)
                if stuck:
                    raise ResourceError(
                        f"{what}: {sorted(fds[f] for f in stuck)} survived SIGKILL for"
                        f" {self.kill_timeout:g} s",
                        origin=self.origin,
                    )
        finally:
            for fd in fds:
                os.close(fd)

    def stop_leftovers(self, token: str, what: str) -> None:
        """Stop every process that carries the spawn token (and is not dead yet)."""
        if not token:
            return
        members = token_processes(token)
        if members:
            logger.warning("%s: stopping %s", what, sorted(pid for pid, _ in members))
            self.stop_processes(members, time.monotonic() + self.grace, None, what)

    def kill_at_once(self, pid: int) -> None:
        """Undo a spawn whose load failed after the process started: SIGKILL and reap."""
        signal_group(pid, signal.SIGKILL)
        with contextlib.suppress(ChildProcessError):
            os.waitpid(pid, 0)
