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


def test_a_step_between_reading_and_waiting_is_not_slept_through() -> None:
    # a loop reads the time, computes how long to wait, then waits: a step taken in between
    # woke nobody (nobody was waiting yet); the wait must not sleep until the step after it
    # (a simulator's model loop missed a test's step this way and the test waited 5 s in CI)
    clock = ManualClock()
    cond = threading.Condition()
    read, woke = threading.Event(), threading.Event()

    def loop() -> None:
        with cond:
            now = clock.monotonic()
            read.set()
            stepped.wait(5.0)  # the test's step lands here, before the wait below
            clock.wait(cond, 0.02 - (now - 0.0))
            woke.set()

    stepped = threading.Event()
    worker = threading.Thread(target=loop, daemon=True)
    worker.start()
    assert read.wait(5.0)
    clock.advance(0.0201)
    stepped.set()
    assert woke.wait(5.0), "the wait slept through the step it came after"
    worker.join(5.0)


def test_a_thread_that_saw_the_step_waits_for_the_next_one() -> None:
    clock = ManualClock()
    cond = threading.Condition()
    clock.advance(1.0)
    woke = threading.Event()

    def loop() -> None:
        with cond:
            clock.monotonic()  # saw the step above
            clock.wait(cond, 0.5)
            woke.set()

    worker = threading.Thread(target=loop, daemon=True)
    worker.start()
    assert not woke.wait(0.2)  # no step since it looked: it waits
    clock.advance(0.5)
    assert woke.wait(5.0)
    worker.join(5.0)
