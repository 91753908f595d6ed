"""Suite-wide fixtures: autouse leak checks that every test gets."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import pytest

THREAD_PREFIX = "temoto-"
THREAD_GRACE_S = 2.0


@pytest.fixture(autouse=True)
def no_leaked_temoto_threads() -> Iterator[None]:
    """Fail a test that leaves a ``temoto-*`` thread running.

    Owners join their threads in ``shutdown()``; a thread that is still alive after the test
    (and a grace period for threads that are already winding down) is a leak.
    """
    before = set(threading.enumerate())
    yield
    leftovers = [
        t for t in threading.enumerate() if t not in before and t.name.startswith(THREAD_PREFIX)
    ]
    deadline = time.monotonic() + THREAD_GRACE_S
    for thread in leftovers:
        thread.join(timeout=max(0.0, deadline - time.monotonic()))
    leaked = sorted(t.name for t in leftovers if t.is_alive())
    if leaked:
        pytest.fail(
            f"test leaked {len(leaked)} thread(s) still alive {THREAD_GRACE_S:g} s after it "
            f"ended: {', '.join(leaked)}",
            pytrace=False,
        )
