"""The driver contract: every driver + simulator pair passes these tests (docs/development.md §6).

A driver's test module subclasses :class:`DriverContract` once and provides the ``rig``
fixture: a configured-but-not-started driver on a running simulator, and how to make the
driver do something observable. A hardware subclass (real device, gated by an environment
variable) can reuse everything except the fault tests.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import pytest

from temoto.clock import Clock, ManualClock
from temoto.drivers import Driver, DriverState, Health
from temoto.drivers.sim import Simulator
from temoto.errors import DriverError, DriverInitError, DriverTimeoutError, StateError

__all__ = ["DriverContract", "Rig", "eventually", "state"]

REAL_WAIT = 10.0  # real seconds any single wait may take before a test fails


def eventually(
    pred: Callable[[], bool],
    timeout: float,
    clock: Clock | None = None,
    step: float = 0.005,
) -> float:
    """Wait until ``pred()`` holds; on a :class:`ManualClock`, move virtual time meanwhile.

    Args:
        pred: The condition.
        timeout: Clock seconds it may take (virtual on a ManualClock).
        clock: The rig's clock.
        step: Virtual seconds per step on a ManualClock.

    Returns:
        The clock seconds it took.

    Raises:
        AssertionError: It did not hold in time.
    """
    manual = clock if isinstance(clock, ManualClock) else None
    start = clock.monotonic() if clock is not None else time.monotonic()
    real_deadline = time.monotonic() + REAL_WAIT + (0 if manual else timeout)
    while True:
        if pred():
            now = clock.monotonic() if clock is not None else time.monotonic()
            return now - start
        now = clock.monotonic() if clock is not None else time.monotonic()
        assert now - start <= timeout, f"not within {timeout} s"
        assert time.monotonic() < real_deadline, "the rig made no progress in real time"
        if manual is not None:
            manual.advance(step)
            time.sleep(0.0005)  # let the driver's and simulator's threads run
        else:
            time.sleep(step)


def state(driver: Driver) -> DriverState:
    """The driver's state, read afresh (keeps type checkers from narrowing across calls)."""
    return driver.state


@dataclass
class Rig:
    """A driver on its simulator, for the contract tests.

    Attributes:
        driver: The driver (``UNCONFIGURED``).
        sim: Its simulator (started).
        clock: The clock both use.
        act: Makes the ACTIVE driver do something through its capability API.
        acted: True once the effect of ``act`` shows in the driver's own state readings.
        stamp: The stamp of the driver's newest state reading.
        fault_bound: Clock seconds within which a silent device must be reported (3 poll or
            heartbeat periods, plus the reply timeout).
        init_timeout: Clock seconds within which ``configure`` against a silent device fails.
        silence: The fault that makes the device silent.
    """

    driver: Driver
    sim: Simulator
    clock: Clock
    act: Callable[[], None]
    acted: Callable[[], bool]
    stamp: Callable[[], float]
    fault_bound: float
    init_timeout: float
    silence: str = "silence"
    healths: list[Health] = field(default_factory=list)


class DriverContract:
    """Lifecycle, timestamps, commands, faults and recovery: the same tests for every driver."""

    @pytest.fixture
    def rig(self) -> Rig:
        """Override (usually as a generator fixture): a :class:`Rig`, torn down after."""
        pytest.fail("a DriverContract subclass must provide the rig fixture")

    # ---- lifecycle ---------------------------------------------------------------------------

    def test_legal_lifecycle(self, rig: Rig) -> None:
        d = rig.driver
        assert state(d) is DriverState.UNCONFIGURED
        assert not d.health().ok
        d.configure()
        assert state(d) is DriverState.INACTIVE
        d.activate()
        assert state(d) is DriverState.ACTIVE
        assert d.health().ok
        d.deactivate()
        assert state(d) is DriverState.INACTIVE
        d.activate()
        d.shutdown()
        assert state(d) is DriverState.FINALIZED

    def test_illegal_transitions_raise_state_error(self, rig: Rig) -> None:
        d = rig.driver
        with pytest.raises(StateError, match="UNCONFIGURED"):
            d.activate()
        with pytest.raises(StateError):
            d.deactivate()
        d.configure()
        with pytest.raises(StateError, match="INACTIVE"):
            d.configure()
        with pytest.raises(StateError, match="INACTIVE"):
            rig.act()  # a verb needs ACTIVE
        d.shutdown()
        with pytest.raises(StateError, match="FINALIZED"):
            d.configure()

    def test_shutdown_is_idempotent_from_every_state(self, rig: Rig) -> None:
        d = rig.driver
        d.shutdown()
        d.shutdown()
        assert state(d) is DriverState.FINALIZED

    def test_shutdown_while_active(self, rig: Rig) -> None:
        d = rig.driver
        d.configure()
        d.activate()
        d.shutdown()
        d.shutdown()
        assert state(d) is DriverState.FINALIZED

    # ---- state -------------------------------------------------------------------------------

    def test_state_stamps_never_go_back(self, rig: Rig) -> None:
        d = rig.driver
        d.configure()
        d.activate()
        stamps = [rig.stamp()]
        for _ in range(5):
            eventually(lambda: rig.stamp() > stamps[-1], rig.fault_bound, rig.clock)
            stamps.append(rig.stamp())
        assert stamps == sorted(stamps)
        d.shutdown()

    def test_a_command_reaches_the_device_and_shows_in_the_state(self, rig: Rig) -> None:
        d = rig.driver
        d.configure()
        d.activate()
        rig.act()
        eventually(rig.acted, 5.0, rig.clock)
        d.shutdown()

    # ---- faults ------------------------------------------------------------------------------

    def test_a_silent_device_is_a_fault_with_a_typed_error_in_bounded_time(self, rig: Rig) -> None:
        d = rig.driver
        got: list[Health] = []
        seen = threading.Event()

        def listen(health: Health) -> None:
            got.append(health)
            if health.state is DriverState.FAULT:
                seen.set()

        d.add_health_listener(listen)
        d.configure()
        d.activate()
        rig.sim.inject(rig.silence)
        took = eventually(seen.is_set, rig.fault_bound, rig.clock)
        assert took <= rig.fault_bound
        fault = next(h for h in got if h.state is DriverState.FAULT)
        assert isinstance(fault.error, DriverError)
        assert not d.health().ok
        with pytest.raises(StateError, match="FAULT"):
            rig.act()
        # the device comes back: the driver reports it and is usable again
        rig.sim.clear(rig.silence)
        eventually(
            lambda: d.state in (DriverState.ACTIVE, DriverState.INACTIVE),
            rig.fault_bound * 4,
            rig.clock,
        )
        if d.state is DriverState.INACTIVE:  # drivers that need an explicit re-enable
            d.activate()
        assert d.health().ok
        rig.act()
        eventually(rig.acted, 5.0, rig.clock)
        d.shutdown()

    def test_configure_against_a_silent_device_fails_in_time(self, rig: Rig) -> None:
        rig.sim.inject(rig.silence)
        errors: list[BaseException] = []

        def configure() -> None:
            try:
                rig.driver.configure()
            except BaseException as err:
                errors.append(err)

        thread = threading.Thread(target=configure)
        thread.start()
        eventually(lambda: not thread.is_alive(), rig.init_timeout * 2, rig.clock)
        thread.join(REAL_WAIT)
        assert len(errors) == 1
        assert isinstance(errors[0], DriverInitError | DriverTimeoutError)
        assert rig.driver.state is DriverState.UNCONFIGURED
        rig.driver.shutdown()
