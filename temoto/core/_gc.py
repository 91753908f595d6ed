"""Keep the cyclic garbage collector out of bulk construction (graph parsing, planning, wiring).

Building a 10,000-action graph allocates a few hundred thousand objects that all live on; the
collector, triggered by allocation counts, would scan the growing heap several times over while
they are made (measured: three full collections, 140-270 ms of a 0.5 s start). None of those
objects is garbage, so the scans find nothing. :func:`collector_paused` turns automatic
collection off for the duration of such a burst and back on afterwards (only if it was on:
a program that disabled the collector keeps it disabled). Nothing is lost: garbage made
meanwhile is collected by the next automatic run.

The new objects still count towards the collector's next *full* collection, which would then
land in the middle of the graph's execution (measured: one 60-100 ms pause inside a
10,000-action chain). For a large graph the engine therefore runs that collection itself with
:func:`collect_now`, after wiring and before the first action starts: the pause moves from the
execution to the start, where a robot is not yet acting.
"""

from __future__ import annotations

import gc
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["collect_now", "collector_paused"]


@contextmanager
def collector_paused() -> Iterator[None]:
    """Suspend automatic garbage collection inside the ``with`` block.

    Yields:
        Nothing.

    Raises:
        Whatever the block raises (collection is restored first).
    """
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was_enabled:
            gc.enable()


def collect_now() -> None:
    """Run a full collection now (if automatic collection is on), so it does not come later.

    Returns:
        None.

    Raises:
        Nothing.
    """
    if gc.isenabled():
        gc.collect()
