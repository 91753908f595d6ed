"""A consumer's status callback that records what it is told, for the component tests."""

from __future__ import annotations

import threading

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
