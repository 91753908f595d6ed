"""How a command of the command line reacts to SIGINT and SIGTERM (docs/design.md §8).

:class:`SignalExit` (the first signal stops, the second hurries), :class:`Interrupted` (what
the first one raises in the main thread), :func:`stop_on_signals` (a wait that a signal ends)
and :func:`make_devices_safe`. Used by ``temoto run``, ``temoto serve``, ``temoto sim``,
``temoto router``, ``temoto demo``, ``temoto view``, ``temoto graph watch``, the robot command
and the simulator host of the tests. The signal handler itself takes no lock and starts no
thread: a thread of :class:`SignalExit`'s (``temoto-signals``) does the work.
"""

from __future__ import annotations

import atexit
import logging
import os
import selectors
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from typing import Any

__all__ = ["FORCE_EXIT_S", "Interrupted", "SignalExit", "make_devices_safe", "stop_on_signals"]

logger = logging.getLogger(__name__)

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


class _Watcher:
    """The thread that acts on SIGINT and SIGTERM, outside the signal handler.

    A Python signal handler runs in the main thread between two bytecodes, wherever that
    thread is: inside ``threading.Event.wait`` holding the event's lock, inside
    ``Thread.start`` holding the thread registry's lock, inside a driver's lock. A handler
    that takes any lock (``Event.set``, starting a thread, a buffered write) may wait for
    the very code it interrupted, forever. And a signal can land in the main thread just
    before it blocks (in a lock's wait): its Python handler then runs only when the wait
    ends, which for ``stop.wait()`` is never.

    So the signal is taken by the interpreter's wake-up file descriptor
    (:func:`signal.set_wakeup_fd`: one byte per signal, written by the C-level handler, in
    whichever thread got it), and this thread (``temoto-signals``) reads it and does what
    the signal asks, with no lock of the interrupted code held. The Python-level handler
    does only what needs no lock.

    Args:
        on_signal: Called on this thread with each signal's number, in order.
        handler: The Python-level handler (must take no lock).
        signums: The signals taken.
    """

    def __init__(
        self,
        on_signal: Callable[[int], None],
        handler: Callable[[int, Any], None],
        signums: tuple[int, ...] = (signal.SIGINT, signal.SIGTERM),
    ) -> None:
        self._on_signal = on_signal
        self._handler = handler
        self._signums = signums
        self._previous: dict[int, Any] = {}
        self._previous_wakeup = -1
        self._read, self._write = os.pipe()
        os.set_blocking(self._write, False)  # set_wakeup_fd needs it
        self._thread = threading.Thread(target=self._run, name="temoto-signals", daemon=True)
        #: Absolute time.monotonic() of a force-exit (see SignalExit), checked by the thread.
        self.deadline: float | None = None
        self.on_deadline: Callable[[], None] | None = None

    def install(self) -> None:
        """Start the thread, then take the signals (main thread only)."""
        self._thread.start()
        # the wake-up fd first: a signal after the handlers are in is never missed
        self._previous_wakeup = signal.set_wakeup_fd(self._write, warn_on_full_buffer=False)
        for signum in self._signums:
            self._previous[signum] = signal.signal(signum, self._handler)

    def restore(self) -> None:
        """Give the signals back to the previous handlers and end the thread (main thread)."""
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)
        self._previous.clear()
        with suppress(ValueError):
            signal.set_wakeup_fd(self._previous_wakeup)
        with suppress(OSError):
            os.write(self._write, b"\0")  # no signal has number 0: the end
        self._thread.join()
        os.close(self._read)
        os.close(self._write)

    def _run(self) -> None:
        with selectors.DefaultSelector() as selector:
            selector.register(self._read, selectors.EVENT_READ)
            self._loop(selector)

    def _loop(self, selector: selectors.BaseSelector) -> None:
        while True:
            wait = None if self.deadline is None else max(0.0, self.deadline - time.monotonic())
            if not selector.select(wait):
                if self.on_deadline is not None:
                    self.on_deadline()
                self.deadline = None
                continue
            data = os.read(self._read, 64)
            for signum in data:
                if signum == 0:
                    return
                if signum in self._signums:
                    try:
                        self._on_signal(signum)
                    except Exception:  # a callback's fault must not end the signals' thread
                        logger.exception("handling %s", signal.Signals(signum).name)


class SignalExit:
    """How a command reacts to SIGINT and SIGTERM (docs/design.md §8 "Signals").

    Use it as a context manager around the command (main thread only); the previous handlers
    are restored at the end, unless a signal came: then the command is ending, and later
    signals keep being taken as "hurry" until the process exits (:meth:`close` gives them
    back, for a process that goes on).

    * The **first** signal sets :attr:`stop` and, if ``raise_first`` (and :attr:`raising`
      is still true), raises :class:`Interrupted` in the main thread; otherwise the command
      watches :attr:`stop`.
    * A **second** signal (and any later one) sets :attr:`hurried`, calls the ``hurry``
      callbacks (by default :func:`temoto.managers.process.hurry_all`: process stops skip
      their grace period) and never raises, so that the clean-up it interrupts still runs.

    Everything but the raise is done on a thread of its own (``temoto-signals``), never in
    the signal handler: the handler interrupts the main thread wherever it is, possibly
    inside :attr:`stop`'s own ``wait`` holding its lock, and a lock taken there would wait
    for itself (see :class:`_Watcher`). So the main thread sees :attr:`stop` set shortly
    after the signal, not at once; :attr:`signum` is set by the handler too, before it
    raises.

    Args:
        raise_first: Raise :class:`Interrupted` on the first signal.
        hurry: Callbacks for the second signal (called on the signals' thread).
        first: Callbacks for the first signal, with its number (called on the signals'
            thread; one that takes long delays a second signal's handling).
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
        self._handled = False
        self._force_exit = force_exit
        self._force_exit_code = force_exit_code
        self._watcher: _Watcher | None = None

    @property
    def exit_code(self) -> int | None:
        """128 + the first signal's number (130 for SIGINT, 143 for SIGTERM), or None."""
        return None if self.signum is None else 128 + self.signum

    def __enter__(self) -> SignalExit:
        self._watcher = _Watcher(self._on_signal, self._handle)
        self._watcher.install()
        return self

    def __exit__(self, *exc: object) -> None:
        if self.signum is not None or self.count:
            # The command is ending because of a signal: the handler stays, so that a second
            # Ctrl-C arriving while the interpreter winds down (after this block, before the
            # exit) hurries instead of raising KeyboardInterrupt where nothing catches it; and
            # once the last Python code has run, later signals are ignored (the interpreter's
            # finalisation resets a Python handler to the default action, which would kill the
            # process by the signal instead of letting it exit with its status).
            self.raising = False
            atexit.register(_ignore_late_signals)
            return
        self.close()

    def close(self) -> None:
        """Give the signals back to the handlers before the block, and end the thread.

        Done at the block's end when no signal came; after a signal, only a process that
        goes on (a test) calls it.
        """
        if self._watcher is not None:
            self._watcher.restore()
            self._watcher = None

    def _handle(self, signum: int, frame: object) -> None:
        # The main thread, between two bytecodes, maybe inside a lock: no lock here, no
        # thread started, no buffered write. The signals' thread does the rest.
        if self.signum is None:
            self.signum = signum
        first, self._handled = not self._handled, True
        if first and self.raising:
            self.raising = False
            raise Interrupted(signum)

    def _on_signal(self, signum: int) -> None:
        """One signal, on the signals' thread."""
        self.count += 1
        name = signal.Signals(signum).name
        if self.count == 1:
            if self.signum is None:
                self.signum = signum
            _say(f"temoto: {name}: stopping (a second signal stops at once)\n")
            self.stop.set()
            for at_first in self._first:
                at_first(signum)
            return
        if not self.hurried.is_set():
            _say(f"temoto: {name} again: stopping at once\n")
        watcher = self._watcher
        if self._force_exit is not None and watcher is not None:
            code = self.exit_code or 0
            if self._force_exit_code is not None:
                code = self._force_exit_code
            if watcher.on_deadline is not None:  # a third signal: no more waiting
                _say(f"temoto: {name}: exiting now\n")
                os._exit(code)
            delay = self._force_exit
            watcher.on_deadline = lambda: _exit_now(delay, code)
            watcher.deadline = time.monotonic() + delay
        self.hurried.set()
        for callback in self._hurry if self._hurry is not None else _default_hurry():
            callback()


def _exit_now(delay: float, code: int) -> None:
    """End the process, devices made safe first (``force_exit``, ``delay`` s after the signal)."""
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


@contextmanager
def stop_on_signals(
    stop: threading.Event, signums: tuple[int, ...] = (signal.SIGINT, signal.SIGTERM)
) -> Iterator[threading.Event]:
    """Set ``stop`` on each of ``signums`` while the block runs (main thread only).

    For a command or a helper process whose signals only end a wait: the event is set on the
    signals' thread, never in the signal handler (which may interrupt the main thread inside
    ``stop.wait()``, holding the event's lock: see :class:`_Watcher`). The previous handlers
    are back after the block.

    Args:
        stop: The event to set.
        signums: The signals taken.

    Yields:
        ``stop``.
    """
    watcher = _Watcher(lambda _signum: stop.set(), _ignore, signums)
    watcher.install()
    try:
        yield stop
    finally:
        watcher.restore()


def _ignore(signum: int, frame: object) -> None:
    """The Python-level handler when the signals' thread does everything."""
