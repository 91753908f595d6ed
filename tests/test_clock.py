"""ManualClock: virtual time that tests and simulators move by hand."""

from __future__ import annotations

import threading

import pytest

from temoto import Clock, ManualClock

WAIT = 5.0


def test_it_reads_what_it_was_moved_to() -> None:
    clock = ManualClock(start=10.0, epoch=1000.0)
    assert isinstance(clock, Clock)
    assert clock.monotonic() == 10.0
    assert clock.time() == 1000.0
    assert clock.advance(2.5) == 12.5
    assert clock.time() == 1002.5
    assert clock.set(20.0) == 20.0
    assert clock.real_seconds(3.0) == 3.0


@pytest.mark.parametrize("bad", [-1.0, float("nan"), float("inf")])
def test_it_does_not_go_back_or_jump_to_infinity(bad: float) -> None:
    clock = ManualClock()
    with pytest.raises(ValueError, match="finite, non-negative"):
        clock.advance(bad)
    with pytest.raises(ValueError, match="does not go back"):
        ManualClock(start=5.0).set(4.0)
    with pytest.raises(ValueError, match="finite"):
        ManualClock(start=float("nan"))


def test_a_wait_ends_when_virtual_time_passes_its_deadline() -> None:
    clock = ManualClock()
    cond = threading.Condition()
    results: list[bool] = []
    started = threading.Event()

    def waiter() -> None:
        with cond:
            started.set()
            results.append(clock.wait(cond, 1.0))

    thread = threading.Thread(target=waiter)
    thread.start()
    assert started.wait(WAIT)
    with cond:  # the waiter is inside wait() once it released the lock
        pass
    clock.advance(0.5)  # woken, not yet due: it reports True (check your predicate)
    thread.join(WAIT)
    assert results == [True]
    results.clear()
    thread = threading.Thread(target=waiter)
    started.clear()
    thread.start()
    assert started.wait(WAIT)
    with cond:
        pass
    clock.advance(1.0)
    thread.join(WAIT)
    assert results == [False]


def test_a_notify_wakes_a_waiter_before_its_deadline() -> None:
    clock = ManualClock()
    cond = threading.Condition()
    flag: list[bool] = []
    results: list[bool] = []

    def waiter() -> None:
        with cond:
            while not flag:
                if not clock.wait(cond, 100.0):
                    break
            results.append(bool(flag))

    thread = threading.Thread(target=waiter)
    thread.start()
    with cond:
        flag.append(True)
        cond.notify_all()
    thread.join(WAIT)
    assert results == [True]
    assert clock.monotonic() == 0.0


def test_a_zero_or_past_deadline_does_not_block() -> None:
    clock = ManualClock()
    cond = threading.Condition()
    with cond:
        assert clock.wait(cond, 0.0) is False
        assert clock.wait(cond, -1.0) is False
