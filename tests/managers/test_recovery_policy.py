"""The recovery policy's tries and waits, on a virtual clock, with a driver that fails on cue."""

from __future__ import annotations

import threading
import time
from typing import Any, ClassVar

import pytest
from _robots import robot_manager

import temoto.config
import temoto.managers.robot.manager
from temoto.clock import ManualClock
from temoto.config import parse_profile
from temoto.core.registrar import Status, StatusUpdate
from temoto.drivers import DriverState
from temoto.drivers.base import Driver
from temoto.errors import DriverOperationError, DriverTimeoutError
from temoto.managers.robot import RobotManagerClient


class Flaky(Driver):
    """A device whose recover() fails ``failures`` times (its watchdog expired, say)."""

    kind = "flaky"
    instances: ClassVar[list[Flaky]] = []

    def __init__(self, name: str, *, clock: Any = None) -> None:
        super().__init__(name, clock=clock)
        self.failures = 0
        self.tries: list[float] = []  # clock times of recover()
        Flaky.instances.append(self)

    def on_configure(self) -> None:
        pass

    def on_recover(self) -> None:
        self.tries.append(self.clock.monotonic())
        if self.failures > 0:
            self.failures -= 1
            raise DriverTimeoutError(f"{self.name}: node 3 (wheel): no heartbeat within 0.3 s")

    def on_shutdown(self) -> None:
        pass


class Statuses:
    def __init__(self) -> None:
        self.got: list[StatusUpdate] = []
        self.cond = threading.Condition()

    def __call__(self, update: StatusUpdate) -> None:
        with self.cond:
            self.got.append(update)
            self.cond.notify_all()


@pytest.fixture
def flaky(monkeypatch: pytest.MonkeyPatch) -> None:
    def driver_class(name: str) -> type[Driver]:
        assert name == "flaky"
        return Flaky

    monkeypatch.setattr(temoto.config, "driver_class", driver_class)
    monkeypatch.setattr(temoto.managers.robot.manager, "driver_class", driver_class)
    Flaky.instances.clear()


def start(recovery: Any) -> tuple[Any, ManualClock]:
    clock = ManualClock()
    doc: dict[str, Any] = {"robot": "r", "sim": False, "devices": {"dev": {"driver": "flaky"}}}
    if recovery is not None:
        doc["devices"]["dev"]["recovery"] = recovery
    return parse_profile(doc, file="r.yaml", clock=clock), clock


def run_clock(clock: ManualClock, until: Any, limit: float = 60.0) -> None:
    """Advance the virtual clock in small steps until ``until()`` (or ``limit`` seconds)."""
    end = clock.monotonic() + limit
    while not until():
        assert clock.monotonic() < end, "never happened"
        clock.advance(0.05)
        time.sleep(0.003)  # let the recovery thread see the new time


def test_tries_wait_doubling_and_the_device_comes_back(flaky: None) -> None:
    profile, clock = start({"tries": 4, "backoff": 0.5, "max_backoff": 1.5})
    with robot_manager("test-policy", profile, clock) as (registrar, _):
        statuses = Statuses()
        robot = RobotManagerClient(registrar).request(client="t", on_status=statuses)
        (driver,) = Flaky.instances[-1:]
        driver.failures = 2
        t0 = clock.monotonic()
        driver.report_fault(DriverOperationError("dev: node 3 (wheel): WATCHDOG_TIMER_EXPIRED"))
        run_clock(clock, lambda: any(u.status is Status.OK for u in statuses.got))
        # waits of 0.5, 1.0 and 1.5 s (doubling, capped by max_backoff), each after the last
        waits = [b - a for a, b in zip([t0, *driver.tries], driver.tries, strict=False)]
        assert waits == pytest.approx([0.5, 1.0, 1.5], abs=0.2)
        assert driver.state is DriverState.ACTIVE
        assert robot.healthy()
        assert [(u.status, u.message) for u in statuses.got] == [
            (Status.WARNING, "robot r, device dev: node 3 (wheel): WATCHDOG_TIMER_EXPIRED"),
            (Status.OK, "robot r, device dev: recovered on try 3/4"),
        ]


def test_a_device_that_keeps_failing_is_given_up_with_its_reason(flaky: None) -> None:
    profile, clock = start({"tries": 3, "backoff": 0.2, "max_backoff": 0.4})
    with robot_manager("test-policy", profile, clock) as (registrar, manager):
        statuses = Statuses()
        RobotManagerClient(registrar).request(client="t", on_status=statuses)
        (driver,) = Flaky.instances[-1:]
        driver.failures = 100
        driver.report_fault(DriverOperationError("dev: node 3 (wheel): WATCHDOG_TIMER_EXPIRED"))
        run_clock(clock, lambda: len(statuses.got) >= 2)
        assert len(driver.tries) == 3
        assert [(u.status, u.message) for u in statuses.got] == [
            (Status.WARNING, "robot r, device dev: node 3 (wheel): WATCHDOG_TIMER_EXPIRED"),
            (
                Status.FATAL,
                "robot r, device dev: gave up after 3 tries: node 3 (wheel): no heartbeat"
                " within 0.3 s",
            ),
        ]
        health = manager.robot().health()["dev"]
        assert health.state is DriverState.FAULT
        assert health.message == "gave up after 3 tries: node 3 (wheel): no heartbeat within 0.3 s"
        clock.advance(60.0)  # nothing more is tried
        time.sleep(0.05)
        assert len(driver.tries) == 3


def test_recovery_off_never_tries(flaky: None) -> None:
    profile, clock = start("off")
    with robot_manager("test-policy", profile, clock) as (registrar, manager):
        statuses = Statuses()
        RobotManagerClient(registrar).request(client="t", on_status=statuses)
        (driver,) = Flaky.instances[-1:]
        driver.report_fault(DriverOperationError("dev: node 3 (wheel): WATCHDOG_TIMER_EXPIRED"))
        run_clock(clock, lambda: manager.robot().health()["dev"].message.startswith("recovery"))
        clock.advance(60.0)
        time.sleep(0.05)
        assert driver.tries == []
        assert driver.state is DriverState.FAULT
        assert manager.robot().health()["dev"].message == (
            "recovery off: node 3 (wheel): WATCHDOG_TIMER_EXPIRED"
        )
