"""Virtual time that waits for a Dynamixel driver's polls (a helper of the Dynamixel tests).

:func:`contract.eventually` moves a :class:`~temoto.clock.ManualClock` 5 ms (or ``step``) per
half millisecond of real time, while each poll's replies take real time (dynamixel-sdk's reply
timeouts are real): on a loaded machine virtual time then runs past three poll periods before
a poll lands and the driver rightly reports its present position stale. :func:`follow` moves
the clock one poll period at a time, each once the driver has polled at the current instant.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from temoto.clock import ManualClock
from temoto.drivers.dynamixel.driver import DynamixelDriver

#: Real seconds to wait for one poll before moving on anyway (a lost reply).
POLL_WAIT = 0.5


def follow(
    driver: DynamixelDriver,
    clock: ManualClock,
    pred: Callable[[], bool],
    timeout: float,
    real_timeout: float = 30.0,
) -> float:
    """Wait until ``pred()`` holds, moving virtual time one poll period per poll.

    Args:
        driver: The polling driver (configured).
        clock: Its clock.
        pred: The condition.
        timeout: Virtual seconds it may take.
        real_timeout: Real seconds it may take.

    Returns:
        The virtual seconds it took.

    Raises:
        AssertionError: It did not hold in time.
    """
    start = clock.monotonic()
    real_end = time.monotonic() + real_timeout
    while not pred():
        now = clock.monotonic()
        assert now - start <= timeout, f"not within {timeout} s"
        assert time.monotonic() < real_end, "the rig made no progress in real time"
        polled = time.monotonic() + POLL_WAIT
        while driver.read_state().stamp < now and time.monotonic() < polled:
            time.sleep(0.0005)
        clock.advance(driver.period)
    return clock.monotonic() - start
