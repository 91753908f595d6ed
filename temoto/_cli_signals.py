"""How a command of the command line reacts to SIGINT and SIGTERM (ARCHITECTURE.md §8).

:class:`SignalExit` (the first signal stops, the second hurries), :class:`Interrupted` (what
the first one raises in the main thread) and :func:`make_devices_safe`. Used by ``temoto
run``, ``temoto serve``, ``temoto sim``, ``temoto router`` and the robot command; kept apart
from :mod:`temoto._cli_fleet` because a local command needs none of the fleet stack.
"""

from __future__ import annotations

import atexit
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from contextlib import suppress
from typing import Any

__all__ = ["FORCE_EXIT_S", "Interrupted", "SignalExit", "make_devices_safe"]

#: How long a command may take to end after a second signal before it exits by force
#: (``SignalExit(force_exit=...)``): the hurried clean-up (devices safe, processes killed
#: without grace) takes well under a second; a command stuck in a blocking call never ends.
FORCE_EXIT_S = 10.0


class Interrupted(KeyboardInterrupt):
    """Raised in the main thread by the first SIGINT or SIGTERM (see :class:`SignalExit`).

    A :class:`KeyboardInterrupt`, so code that already cleans up on Ctrl-C does the same on
    SIGTERM.

    Args:
        signum: The signal.
    """

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


class SignalExit:
    """How a command reacts to SIGINT and SIGTERM (ARCHITECTURE.md §8 "Signals").

    Use it as a context manager around the command (main thread only); the previous handlers
    are restored at the end, unless a signal came: then the command is ending, and later
    signals keep being taken as "hurry" until the process exits.

    * The **first** signal sets :attr:`stop` and, if ``raise_first`` (and :attr:`raising`
      is still true), raises :class:`Interrupted` in the main thread; otherwise the command
      watches :attr:`stop`.
    * A **second** signal (and any later one) sets :attr:`hurried`, calls the ``hurry``
      callbacks (by default :func:`temoto.managers.process.hurry_all`: process stops skip
      their grace period) and never raises, so that the clean-up it interrupts still runs.

    Args:
        raise_first: Raise :class:`Interrupted` on the first signal.
        hurry: Callbacks for the second signal (must be safe in a signal handler).
        first: Callbacks for the first signal, with its number (must be safe in a signal
            handler: start a thread, set a flag), called before anything is raised.
        force_exit: For a command's process only (never in a library or a test process):
            after the second signal, the process exits with :attr:`exit_code` at the latest
            this many seconds later, even if its main thread is stuck (in a blocking call, on
            a run that cannot end), devices made safe first; a third signal exits at once.
            None (the default): signals never end the process by force.
        force_exit_code: The status of that exit (default :attr:`exit_code`; ``temoto serve``
            exits 0 on a signal).
    """

    def __init__(
        self,
        *,
        raise_first: bool = False,
        hurry: tuple[Callable[[], None], ...] | None = None,
        first: tuple[Callable[[int], None], ...] = (),
        force_exit: float | None = None,
        force_exit_code: int | None = None,
    ) -> None:
        self.raise_first = raise_first
        self._first = first
        self.raising = raise_first
        self.signum: int | None = None
        self.count = 0
        self.stop = threading.Event()
        self.hurried = threading.Event()
        self._hurry = hurry
        self._previous: dict[int, Any] = {}
        self._force_exit = force_exit
        self._force_exit_code = force_exit_code
        self._exit_timer: threading.Thread | None = None

    @property
    def exit_code(self) -> int | None:
        """128 + the first signal's number (130 for SIGINT, 143 for SIGTERM), or None."""
        return None if self.signum is None else 128 + self.signum

    def __enter__(self) -> SignalExit:
        for signum in (signal.SIGINT, signal.SIGTERM):
            self._previous[signum] = signal.signal(signum, self._handle)
        return self

    def __exit__(self, *exc: object) -> None:
        if self.signum is not None:
            # The command is ending because of a signal: the handler stays, so that a second
            # Ctrl-C arriving while the interpreter winds down (after this block, before the
            # exit) hurries instead of raising KeyboardInterrupt where nothing catches it; and
            # once the last Python code has run, later signals are ignored (the interpreter's
            # finalisation resets a Python handler to the default action, which would kill the
            # process by the signal instead of letting it exit with its status).
            self.raising = False
            atexit.register(_ignore_late_signals)
            return
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)

    def _handle(self, signum: int, frame: object) -> None:
        self.count += 1
        name = signal.Signals(signum).name
        if self.signum is None:
            self.signum = signum
            self.stop.set()
            # os.write, not sys.stderr: the main thread may be inside a write to sys.stderr.
            _say(f"temoto: {name}: stopping (a second signal stops at once)\n")
            for at_first in self._first:
                at_first(signum)
            if self.raising:
                self.raising = False
                raise Interrupted(signum)
            return
        if not self.hurried.is_set():
            _say(f"temoto: {name} again: stopping at once\n")
        if self._force_exit is not None:
            code = 128 + self.signum if self._force_exit_code is None else self._force_exit_code
            if self._exit_timer is not None:  # a third signal: no more waiting
                _say(f"temoto: {name}: exiting now\n")
                os._exit(code)
            self._exit_timer = threading.Thread(
                target=_exit_later,
                args=(self._force_exit, code),
                name="temoto-signal-exit",
                daemon=True,  # it ends the process; nothing is left to join it
            )
            self._exit_timer.start()
        self.hurried.set()
        for callback in self._hurry if self._hurry is not None else _default_hurry():
            callback()


def _exit_later(delay: float, code: int) -> None:
    """End the process ``delay`` seconds from now, devices made safe first (``force_exit``)."""
    time.sleep(delay)
    _say(f"temoto: still not stopped {delay:g} s after the second signal: exiting\n")
    with suppress(Exception):
        make_devices_safe("the command did not stop after a second signal")
    with suppress(Exception):
        sys.stdout.flush()
    os._exit(code)


def _ignore_late_signals() -> None:
    """At exit (after the interpreter's threads were joined): ignore SIGINT and SIGTERM."""
    for signum in (signal.SIGINT, signal.SIGTERM):
        with suppress(ValueError, OSError):  # not the main thread, or a platform without it
            signal.signal(signum, signal.SIG_IGN)


def _say(text: str) -> None:
    """Write to standard error from a signal handler (one ``os.write``, errors ignored)."""
    with suppress(OSError):
        os.write(2, text.encode())


def _default_hurry() -> tuple[Callable[[], None], ...]:
    from temoto.managers.process import hurry_all

    return (hurry_all,)


def make_devices_safe(reason: str) -> None:
    """Put every device driven by this process in its safe state (``make_all_safe``).

    Drivers exist only if :mod:`temoto.drivers.base` was imported; it is not imported here
    (that would cost 0.1 s for a command that has no devices), and a module another thread is
    still importing has no driver yet. One line per device goes to
    standard error.

    Args:
        reason: Why (for the log).
    """
    base = sys.modules.get("temoto.drivers.base")
    # None, or still being imported by another thread (an action's import at that moment):
    # then no driver of it exists yet.
    make_all_safe = getattr(base, "make_all_safe", None)
    if make_all_safe is None:
        return
    for driver, what in make_all_safe(reason):
        sys.stderr.write(f"temoto: {driver.name}: {what}\n")
