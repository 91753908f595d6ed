"""A goal of a robot's feature and how it is going: :class:`Motion` (see :mod:`.features`).

:meth:`Motion.cancel` and :meth:`Motion.hold` call back into the controller that owns the
motion (its ``_halt`` and ``_hold``), which tells the devices to be still before they return;
:meth:`Motion.resume` sends the goal again.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Protocol

from temoto.errors import StateError

__all__ = ["Motion"]

logger = logging.getLogger(__name__)


class _Owner(Protocol):
    """The controller of a motion: what brings its devices to rest and back."""

    def _halt(self, motion: Motion) -> None: ...

    def _hold(self, motion: Motion) -> None: ...

    def _resume(self, motion: Motion) -> None: ...


class Motion:
    """One goal of one feature, and how it is going.

    Args:
        what: A description for messages (``navigate to (1.0, 2.0)``).
        owner: The controller that moves it (tells the devices on cancel, hold and resume).
    """

    def __init__(self, what: str, owner: _Owner | None = None) -> None:
        self.what = what
        self._owner = owner
        self._lock = threading.Lock()
        self._done = threading.Event()
        self._error: BaseException | None = None
        self._held = False
        self._superseded = False
        self._listeners: list[Callable[[], None]] = []
        self.progress = ""

    def __repr__(self) -> str:
        state = "done" if self.done else ("held" if self.held else "moving")
        return f"<Motion {self.what} {state}>"

    @property
    def done(self) -> bool:
        """Reached, failed or cancelled."""
        return self._done.is_set()

    @property
    def error(self) -> BaseException | None:
        """Why it did not reach its goal, or None."""
        with self._lock:
            return self._error

    @property
    def superseded(self) -> bool:
        """Ended because a newer goal for the same feature replaced it."""
        with self._lock:
            return self._superseded

    @property
    def held(self) -> bool:
        """Held where it is (see :meth:`hold`)."""
        with self._lock:
            return self._held

    def add_listener(self, listener: Callable[[], None]) -> None:
        """Call ``listener`` (no arguments) when the motion ends or makes progress.

        Args:
            listener: E.g. an action's ``wake``.
        """
        with self._lock:
            self._listeners.append(listener)
        if self.done:
            listener()

    def wait(self, timeout: float | None = None) -> bool:
        """Block (real time) until it ends.

        Args:
            timeout: Real seconds, or None.

        Returns:
            Whether it ended.
        """
        return self._done.wait(timeout)

    def hold(self) -> None:
        """Stop where it is until :meth:`resume`; returns when the devices were told."""
        with self._lock:
            if self._held or self._done.is_set():
                return
            self._held = True
        if self._owner is not None:
            self._owner._hold(self)

    def resume(self) -> None:
        """Go on after :meth:`hold` (the goal is sent again)."""
        with self._lock:
            if not self._held:
                return
            self._held = False
        if self._owner is not None and not self._done.is_set():
            self._owner._resume(self)

    def supersede(self) -> None:
        """End it because a newer goal for the same feature replaced it."""
        with self._lock:
            if self._done.is_set():
                return
            self._superseded = True
        self.cancel("superseded by a new goal")

    def cancel(self, why: str = "cancelled") -> None:
        """End it without reaching the goal; returns when its devices were told to be still.

        A superseded motion's devices already have the new goal: nothing is sent for it.

        Args:
            why: Recorded as the error.
        """
        if self._owner is not None and not self._done.is_set():
            self._owner._halt(self)  # a no-op when the goal is no longer the controller's
        self.finish(StateError(f"{self.what}: {why}"))

    def fail(self, error: BaseException) -> None:
        """End it with ``error`` (a device it commands faulted); as :meth:`cancel` otherwise.

        Args:
            error: What the action following it raises.
        """
        if self._owner is not None and not self._done.is_set():
            self._owner._halt(self)
        self.finish(error)

    def finish(self, error: BaseException | None = None) -> None:
        """Controller: the goal was reached (or not, with ``error``). Idempotent."""
        with self._lock:
            if self._done.is_set():
                return
            self._error = error
            self._done.set()
            listeners = list(self._listeners)
        for listener in listeners:
            try:
                listener()
            except Exception:
                logger.exception("a motion listener raised")
