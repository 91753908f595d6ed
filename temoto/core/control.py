"""Stop and pause signals of one node: what the engine sets and an action's helpers wait on.

Engine internal: actions use the helpers on :class:`~temoto.core.action.Action` (``sleep``,
``wait_for``, ``wait_until_stopped``, ``stop_requested``). The engine's node
(:class:`temoto.core._runtime.Node`) is a subclass: a node carries its action's signals
itself, so it costs the garbage collector one object, not two.
"""

from __future__ import annotations

import threading
from typing import TYPE_CHECKING

from temoto.errors import ResourceBrokenError

if TYPE_CHECKING:
    from temoto.clock import Clock
    from temoto.core.registrar.messages import StatusUpdate

__all__ = ["RunControl"]

#: Guards the lazy creation of RunControl condition variables (rare: once per waiting node).
_COND_CREATION = threading.Lock()


class RunControl:
    """Stop and pause signals of one node, shared by the engine and the action's helpers.

    One condition variable carries every signal, so helpers wait without polling. Engine
    internal: actions use the helpers on :class:`Action`.

    Args:
        clock: The engine's clock.
    """

    __slots__ = ("acquired", "broken", "clock", "condition", "logged", "paused", "stop")

    def __init__(self, clock: Clock) -> None:
        self.clock = clock
        #: the condition variable, made on first use (most runs never wait): while it is None,
        #: no helper waits, and the flags may be set without it
        self.condition: threading.Condition | None = None
        self.stop = False
        self.paused = False
        #: failures of acquired resources, not yet raised (a list from the first one on)
        self.broken: list[StatusUpdate] | None = None
        #: set when an action of this node first writes its runtime log (``Action.log``): until
        #: then the engine need not copy the log at the end of each run
        self.logged = False
        #: set when an action of this node first acquires a resource (``Action.acquire``):
        #: until then the engine need not ask it what it holds when the run ends
        self.acquired = False

    @property
    def cond(self) -> threading.Condition:
        """The condition variable every helper waits on and every signal notifies."""
        cond = self.condition
        if cond is None:
            with _COND_CREATION:
                cond = self.condition
                if cond is None:
                    cond = self.condition = threading.Condition(threading.Lock())
        return cond

    def report_broken(self, update: StatusUpdate) -> None:
        """An acquired resource failed: the next helper call raises ResourceBrokenError.

        Args:
            update: The failure.

        Returns:
            None.
        """
        with self.cond:
            if self.broken is None:
                self.broken = []
            self.broken.append(update)
            self.cond.notify_all()

    def raise_broken(self) -> None:
        """Raise for the oldest unreported failure (the lock must be held).

        Returns:
            None.

        Raises:
            ResourceBrokenError: If an acquired resource failed.
        """
        if self.broken:
            update = self.broken.pop(0)
            # the server's name, not the resource's id (``robot:5f3b-1`` means nothing to a
            # person); the id stays in the log and the error's origin
            server = update.resource_id.partition(":")[0]
            raise ResourceBrokenError(
                f"the {server} resource is {update.status.value}: {update.message}",
                origin=update.origin,
            )

    def reset(self) -> None:
        """Clear the stop and pause flags before a new run.

        Returns:
            None.
        """
        if self.condition is None:  # no helper ever waited: nobody to race with between runs
            self.stop = False
            self.paused = False
            return
        with self.condition:
            self.stop = False
            self.paused = False

    def request_stop(self) -> None:
        """Ask the running action to stop; wakes every helper.

        Returns:
            None.
        """
        with self.cond:
            self.stop = True
            self.cond.notify_all()

    def set_paused(self, paused: bool) -> None:
        """Pause or resume the helpers.

        Args:
            paused: The new pause flag.

        Returns:
            None.
        """
        with self.cond:
            self.paused = paused
            self.cond.notify_all()
