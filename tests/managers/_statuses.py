"""A consumer's status callback that records what it is told, for the component tests."""

from __future__ import annotations

import threading
from collections.abc import Callable

from temoto.core.registrar import Status, StatusUpdate

#: Seconds a test waits for a status before it fails.
WAIT = 10.0


class Statuses:
    """Collects a consumer's statuses; waits for them on a condition."""

    def __init__(self) -> None:
        self.got: list[StatusUpdate] = []
        self._cond = threading.Condition()

    def __call__(self, update: StatusUpdate) -> None:
        with self._cond:
            self.got.append(update)
            self._cond.notify_all()

    def wait(self, status: Status, count: int = 1) -> list[StatusUpdate]:
        """Wait for ``count`` updates with ``status``; returns every update with it."""
        with self._cond:
            ok = self._cond.wait_for(
                lambda: sum(u.status is status for u in self.got) >= count, WAIT
            )
            assert ok, self.got
            return [u for u in self.got if u.status is status]

    def first(self, status: Status) -> StatusUpdate:
        """Wait for the first update with ``status`` and return it."""
        return self.wait(status)[0]

    def wait_for(
        self, pred: Callable[[StatusUpdate], bool], what: str, timeout: float = WAIT
    ) -> StatusUpdate:
        """Wait for the first update that ``pred`` accepts (``what`` names it if none comes)."""
        with self._cond:
            found = self._cond.wait_for(
                lambda: next((u for u in self.got if pred(u)), None), timeout
            )
            assert found, f"no {what}; got {[(u.status.value, u.message) for u in self.got]}"
            return found
