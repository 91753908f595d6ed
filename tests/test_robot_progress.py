"""The built-in robot actions log how a motion goes: at most once per period of clock time,
only when it changed, never after the end; virtual time, no robot needed."""

from __future__ import annotations

import threading
from collections.abc import Iterator

import pytest

from temoto.actions.builtin.robot._common import (
    DEADLINE_FACTOR,
    DEADLINE_SLACK,
    PROGRESS_PERIOD,
    RobotAction,
)
from temoto.actions.builtin.robot.navigate_to import NavigateTo
from temoto.clock import ManualClock
from temoto.core.action import RunControl
from temoto.errors import ActionError, StopRequested
from temoto.managers.robot.features import Motion
from temoto.testing.robots import FakeRobot


class _Probe(RobotAction):
    """Follows a motion the test controls; its progress is the controller's text."""

    def on_run(self) -> bool:
        raise AssertionError("not used: the test calls run_motion")


class _CountingClock(ManualClock):
    """A manual clock that counts the waits begun on it (to step a follower in lockstep)."""

    def __init__(self) -> None:
        super().__init__()
        self.waits = 0
        self.changed = threading.Condition()

    def wait(self, cond: threading.Condition, seconds: float | None) -> bool:
        with self.changed:
            self.waits += 1
            self.changed.notify_all()
        return super().wait(cond, seconds)

    def await_wait(self, count: int) -> None:
        """Block (real time, at most 5 s) until the ``count``-th wait has begun."""
        with self.changed:
            assert self.changed.wait_for(lambda: self.waits >= count, 5), "the follower hangs"


class _Run:
    """A probe bound to a manual clock, following ``motion`` in a thread."""

    def __init__(self, timeout: float | None = None, estimate: float | None = None) -> None:
        self.estimate = estimate
        self.clock = _CountingClock()
        self.control = RunControl(self.clock)
        self.action = _Probe()
        self.action.initialize(self.control, "Probe_0", "g", {}, {})
        self.action._begin({"timeout": timeout} if timeout else {})
        self.motion = Motion("move")
        self.result: list[object] = []
        self.thread = threading.Thread(target=self._follow, daemon=True)
        self.thread.start()

    def _follow(self) -> None:
        try:
            estimate = None if self.estimate is None else (lambda: self.estimate or 0.0)
            self.result.append(self.action.run_motion(lambda: self.motion, estimate))
        except (StopRequested, Exception) as err:
            self.result.append(err)

    def step(self, progress: str, *, goes_on: bool = True) -> None:
        """The controller reports ``progress``; a period of clock time passes, and the
        follower has logged (or not) and waits for the next period."""
        waits = self.clock.waits
        self.clock.await_wait(max(waits, 1))  # the follower waits for this period
        self.motion.progress = progress
        self.clock.advance(PROGRESS_PERIOD)
        if goes_on:
            self.clock.await_wait(waits + 1)  # ... and then for the next one

    def end(self) -> object:
        self.thread.join(5)
        assert not self.thread.is_alive()
        return self.result[0]

    def logs(self) -> list[str]:
        return [m.message for m in reversed(self.action.log_snapshot())]


@pytest.fixture
def run() -> Iterator[_Run]:
    r = _Run()
    yield r
    r.motion.cancel("test over")
    r.thread.join(5)


def test_progress_is_logged_once_per_period_and_only_when_it_changes(run: _Run) -> None:
    run.step("1.5 m left")
    run.step("1.5 m left")  # no news: not logged again
    run.step("0.7 m left")
    run.motion.progress = "0.0 m left"
    run.motion.finish()
    assert run.end() is True
    assert run.logs() == ["1.5 m left", "0.7 m left"]


def test_a_motion_shorter_than_a_period_logs_no_progress(run: _Run) -> None:
    run.motion.progress = "0.2 m left"
    run.motion.finish()
    assert run.end() is True
    assert run.logs() == []


def test_a_timeout_cancels_the_motion_and_says_so() -> None:
    run = _Run(timeout=2 * PROGRESS_PERIOD)
    run.step("3 m left")
    run.step("2 m left", goes_on=False)  # the timeout
    assert run.end() is False
    assert run.motion.done
    assert run.logs()[-1] == f"move: not done within {2 * PROGRESS_PERIOD:g} s"


def test_a_stop_cancels_the_motion() -> None:
    run = _Run()
    run.control.request_stop()
    assert isinstance(run.end(), StopRequested)
    assert run.motion.done


def test_a_missed_deadline_stops_the_motion_and_fails_with_the_reason() -> None:
    run = _Run(estimate=1.0)  # the deadline: 1.5 * 1 s + 5 s = 6.5 s of clock time
    deadline = DEADLINE_FACTOR * 1.0 + DEADLINE_SLACK
    periods = int(deadline // PROGRESS_PERIOD)
    for i in range(periods):
        run.step(f"{periods - i} m left")
    run.step("0.4 m left", goes_on=False)  # the last half period: the deadline
    error = run.end()
    assert isinstance(error, ActionError), error
    assert str(error).startswith(f"_Probe: not move within {deadline:.1f} s (0.4 m left)"), error
    assert run.motion.done
    assert "timed out" in str(run.motion.error)


def test_an_explicit_timeout_wins_over_the_deadline() -> None:
    run = _Run(timeout=PROGRESS_PERIOD, estimate=100.0)
    run.step("3 m left", goes_on=False)
    assert run.end() is False


def test_navigate_to_says_where_it_should_be_and_how_far_it_is() -> None:
    action = NavigateTo()
    robot = FakeRobot(step=0.0, y=0.5)
    action._goal = (robot, 2.0, 0.5)  # type: ignore[assignment]
    assert action.missed(Motion("navigate to (2, 0.5)")) == ("at (2, 0.5)", "2.0 m left")
