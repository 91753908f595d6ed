"""Keep the cyclic garbage collector out of bulk construction (graph parsing, planning, wiring).

Building a 10,000-action graph allocates a few hundred thousand objects that all live on; the
collector, triggered by allocation counts, would scan the growing heap several times over while
they are made (measured: three full collections, 140-270 ms of a 0.5 s start). None of those
objects is garbage, so the scans find nothing. :func:`collector_paused` turns automatic
collection off for the duration of such a burst and back on afterwards (only if it was on:
a program that disabled the collector keeps it disabled). Nothing is lost: garbage made
meanwhile is collected by the next automatic run.

Forcing that full collection right after construction instead (so it would not land in the
middle of the graph's execution) was measured and rejected: on this VM it made the following
execution slower, not faster (52 vs 18 us per action in a 10,000-action chain; the likely cause
is that the memory it frees goes back to the system and is faulted in again). What the engine
does instead for a large run of new nodes is :meth:`Pause.collect_young`: the scan of the new
objects that the first automatic collection would make anyway, done before the first action,
with the collector's counters starting from zero (a run that takes over an ended run's nodes
makes few new objects and skips it). Measured on a 10,000-action chain: no full collection
during the run any more (without it, one of 150-400 ms in half the runs), and 1-2 us per action
of collector time in the run. It is made while automatic collection is still paused: made after
it, the first allocation once the collector is back on triggers an automatic scan of the same
young objects first, so they were scanned twice (measured: 20-30 ms more per 10,000-action
start).
"""

from __future__ import annotations

import gc
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["Pause", "collector_paused"]


class Pause:
    """A pause of automatic collection (see :func:`collector_paused`)."""

    __slots__ = ("was_enabled",)

    def __init__(self, was_enabled: bool) -> None:
        self.was_enabled = was_enabled

    def collect_young(self) -> None:
        """Scan the young generations now, if automatic collection was on before the pause.

        After a burst made with the collector paused, the first automatic collection would
        scan every new object anyway, at whatever moment the next allocation comes. Doing it
        now puts that scan where the caller chooses (before a graph's first action), and
        starts the generation counters from zero, so the next full collection is as far away
        as the collector allows.

        Returns:
            None.
        """
        if self.was_enabled:
            gc.collect(1)


@contextmanager
def collector_paused() -> Iterator[Pause]:
    """Suspend automatic garbage collection inside the ``with`` block.

    Yields:
        The pause, whose :meth:`Pause.collect_young` scans the new objects before the block ends.

    Raises:
        Whatever the block raises (collection is restored first).
    """
    pause = Pause(gc.isenabled())
    gc.disable()
    try:
        yield pause
    finally:
        if pause.was_enabled:
            gc.enable()
