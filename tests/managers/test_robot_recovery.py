"""A faulted device comes back as its recovery policy says, or the manager gives up loudly.

A process pause (SIGSTOP/SIGCONT of the robot) is modelled with the simulators' ``link_loss``:
nothing reaches the devices (their watchdogs expire: the ODrive axes go IDLE with
WATCHDOG_TIMER_EXPIRED, the Dynamixel servos stop) and nothing comes back, then the link
returns. The robots run on a faster clock (the simulators share this process).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
from _robots import robot_manager
from _statuses import Statuses

from temoto import ScaledClock
from temoto.config import parse_profile
from temoto.core.registrar import Status
from temoto.drivers import DriverState
from temoto.drivers.recovery import RecoveryPolicy
from temoto.errors import ProfileError, ResourceBrokenError
from temoto.managers.robot import RobotManagerClient

ROOT = Path(__file__).resolve().parents[2]
PROFILES = ROOT / "hw_profiles"
WAIT = 20.0


def profile(name: str, clock: ScaledClock, **recovery: Any) -> Any:
    doc = yaml.safe_load((PROFILES / name).read_text())
    for device in doc["devices"].values():
        if device["driver"] == "odrive_can":
            device["heartbeat_period"] = 0.25  # a loaded machine must not miss three
        if recovery:
            device["recovery"] = recovery.get("policy", recovery)
    return parse_profile(doc, file=name, clock=clock)


def pause(sims: list[Any], clock: ScaledClock, seconds: float) -> None:
    """Nothing in, nothing out for ``seconds`` of the clock (the devices' watchdogs expire)."""
    for sim in sims:
        sim.inject("link_loss")
    end = clock.monotonic() + seconds
    while clock.monotonic() < end:
        time.sleep(0.01)
    for sim in sims:
        sim.clear("link_loss")


def wait_until(pred: Any, what: str, timeout: float = WAIT) -> None:
    deadline = time.monotonic() + timeout
    while not pred():
        assert time.monotonic() < deadline, what
        time.sleep(0.02)


@pytest.fixture
def mobile() -> Iterator[Any]:
    clock = ScaledClock(3)
    prof = profile("sim_mobile_manipulator.yaml", clock)
    with robot_manager("test-recovery", prof, clock) as (registrar, manager):
        yield registrar, manager, clock


def test_devices_whose_watchdogs_expired_in_a_pause_come_back(
    mobile: Any, caplog: pytest.LogCaptureFixture
) -> None:
    registrar, manager, clock = mobile
    caplog.set_level(logging.INFO, logger="temoto.managers.robot.manager")
    statuses = Statuses()
    robot = RobotManagerClient(registrar).request(client="test", on_status=statuses)
    assert robot.healthy()
    sims = [manager.simulator("base"), manager.simulator("arm")]
    drive = robot.navigate_to(100.0, 0.0)  # far away: under way when the pause comes
    pause(sims, clock, 4.0)  # past the 1 s watchdogs (the servos count real seconds: 1.3 s)
    # the base's axes disarmed by their watchdog: the driver sees it once the link is back (a
    # WARNING: the recovery will bring it back, and the robot's other features go on meanwhile)
    statuses.wait_for(lambda u: u.status is Status.WARNING, "WARNING", WAIT)
    for device in ("base", "arm"):
        statuses.wait_for(
            lambda u, d=device: (
                u.status is Status.OK and f"device {d}: recovered on try" in u.message
            ),
            f"OK for {device}",
            WAIT,
        )
    wait_until(robot.healthy, "the robot is not healthy after the recovery")
    # the goal set before the fault ended with it: the recovered base holds where it is
    assert drive.done
    assert drive.error is not None
    x0 = robot.pose()[0]
    end = clock.monotonic() + 1.0
    while clock.monotonic() < end:
        time.sleep(0.02)
    assert abs(robot.pose()[0] - x0) < 0.05, (x0, robot.pose())
    text = caplog.text
    for device in ("base", "arm"):
        assert f"robot sim_mobile_manipulator, device {device}: recovery try 1/5" in text
        assert f"robot sim_mobile_manipulator, device {device}: recovered on try" in text
    # the consumers' messages name the robot and the device once ("base: base:" no more)
    fatal = next(u for u in statuses.got if u.status is Status.WARNING)
    assert fatal.message.startswith("robot sim_mobile_manipulator, device ")
    assert "base: base:" not in fatal.message
    assert "arm: arm:" not in fatal.message
    # the robot moves again
    motion = robot.move_to_pose("reach")
    assert motion.wait(WAIT), motion
    assert motion.error is None


def test_a_device_that_keeps_failing_ends_fatal_with_the_reason(
    caplog: pytest.LogCaptureFixture,
) -> None:
    clock = ScaledClock(3)
    prof = profile("sim_arm.yaml", clock, tries=2, backoff=0.2, max_backoff=0.3)
    caplog.set_level(logging.INFO, logger="temoto.managers.robot.manager")
    with robot_manager("test-give-up", prof, clock) as (registrar, manager):
        statuses = Statuses()
        robot = RobotManagerClient(registrar).request(client="test", on_status=statuses)
        manager.simulator("arm").inject("link_loss")  # never comes back
        gave_up = statuses.wait_for(
            lambda u: u.status is Status.FATAL and "gave up" in u.message, "gave up", WAIT
        )
        assert gave_up.message.startswith("robot sim_arm, device arm: gave up after 2 tries: "), (
            gave_up.message
        )
        health = manager.robot().health()["arm"]
        assert health.state is DriverState.FAULT
        assert health.message.startswith("gave up after 2 tries: "), health.message
        assert not robot.healthy()
        text = caplog.text
        assert "robot sim_arm, device arm: recovery try 1/2" in text
        assert "robot sim_arm, device arm: recovery try 2/2 failed: " in text
        assert "robot sim_arm, device arm: gave up after 2 tries: " in text
        # the link comes back: it stays out of service (no OK after giving up)
        manager.simulator("arm").clear()
        time.sleep(0.5)
        assert not any(u.status is Status.OK for u in statuses.got)
        assert manager.robot().health()["arm"].message.startswith("gave up after 2 tries")


def test_recovery_off_leaves_the_device_faulted_and_says_so(
    caplog: pytest.LogCaptureFixture,
) -> None:
    clock = ScaledClock(3)
    prof = profile("sim_arm.yaml", clock, policy=False)  # YAML's `recovery: off`
    assert prof.devices["arm"].config["recovery"] is False
    caplog.set_level(logging.INFO, logger="temoto.managers.robot.manager")
    with robot_manager("test-recovery-off", prof, clock) as (registrar, manager):
        statuses = Statuses()
        robot = RobotManagerClient(registrar).request(client="test", on_status=statuses)
        sim = manager.simulator("arm")
        pause([sim], clock, 2.0)
        statuses.wait_for(lambda u: u.status is Status.FATAL, "FATAL", WAIT)
        wait_until(lambda: "recovery off" in caplog.text, "no line says recovery is off")
        time.sleep(1.0)  # the chain answers again: nothing activates it
        assert not robot.healthy()
        assert not any(u.status is Status.OK for u in statuses.got)
        health = manager.robot().health()["arm"]
        assert health.state is DriverState.FAULT
        assert health.message.startswith("recovery off: "), health.message
        line = next(r.getMessage() for r in caplog.records if "recovery off" in r.getMessage())
        assert line.startswith("robot sim_arm, device arm: FAULT: "), line
        assert line.endswith(
            "; recovery off: it stays out of service until the robot is loaded again"
        )


def test_the_recovery_key_of_a_profile() -> None:
    clock = ScaledClock(1)
    prof = profile("sim_arm.yaml", clock, tries=3, backoff=0.5, max_backoff=5)
    assert prof.devices["arm"].config["recovery"] == {"tries": 3, "backoff": 0.5, "max_backoff": 5}
    policy = RecoveryPolicy(True, 3, 0.5, 5.0)
    assert [policy.delay(k) for k in (1, 2, 3, 4, 5)] == [0.5, 1.0, 2.0, 4.0, 5.0]
    with pytest.raises(ProfileError) as bad:
        profile("sim_arm.yaml", clock, tries=0)
    assert str(bad.value) == (
        "sim_arm.yaml: devices.arm.recovery.tries: must be an integer 1..100, got 0"
    )
    with pytest.raises(ProfileError) as bad:
        profile("sim_arm.yaml", clock, retries=3)
    assert str(bad.value) == (
        "sim_arm.yaml: devices.arm.recovery.retries: unknown key (known: backoff, max_backoff,"
        " tries)"
    )
    with pytest.raises(ProfileError) as bad:
        profile("sim_arm.yaml", clock, backoff=2.0, max_backoff=1.0)
    assert str(bad.value) == (
        "sim_arm.yaml: devices.arm.recovery.max_backoff: must be >= backoff (2 s), got 1 s"
    )
    with pytest.raises(ProfileError) as bad:
        profile("sim_arm.yaml", clock, policy="sometimes")
    assert str(bad.value) == (
        "sim_arm.yaml: devices.arm.recovery: must be off, on or a mapping of tries, backoff,"
        " max_backoff; got 'sometimes'"
    )


def test_a_hardware_error_is_not_cleared_automatically(caplog: pytest.LogCaptureFixture) -> None:
    clock = ScaledClock(3)
    prof = profile("sim_arm.yaml", clock)  # the default policy: 5 tries
    caplog.set_level(logging.INFO, logger="temoto.managers.robot.manager")
    with robot_manager("test-hardware", prof, clock) as (registrar, manager):
        statuses = Statuses()
        robot = RobotManagerClient(registrar).request(client="test", on_status=statuses)
        manager.simulator("arm").inject("hardware_error", kind="overheat", device=3)
        statuses.wait_for(lambda u: u.status is Status.FATAL, "FATAL", WAIT)
        wait_until(
            lambda: "not recovered automatically" in caplog.text, "no line says it is not tried"
        )
        end = clock.monotonic() + 3.0  # longer than the first waits of the default policy
        while clock.monotonic() < end:
            time.sleep(0.02)
        assert "recovery try" not in caplog.text  # an overheating servo is not re-armed
        assert not robot.healthy()
        health = manager.robot().health()["arm"]
        assert health.state is DriverState.FAULT
        assert health.message.startswith(
            "not recovered automatically (the device reports a hardware error): "
        ), health.message


def test_a_fault_of_the_arm_fails_only_what_needs_the_arm_while_it_recovers(mobile: Any) -> None:
    """Issue 25 item 2: an action that needs a FAULT device fails at once with its reason; a
    drive that does not use it goes on (the recovery runs meanwhile: a WARNING, not FATAL)."""
    registrar, manager, clock = mobile
    statuses = Statuses()
    robot = RobotManagerClient(registrar).request(client="test", on_status=statuses)
    wait_until(robot.healthy, "the robot is not healthy at its start")
    drive = robot.navigate_to(100.0, 0.0)  # far away: under way all along
    reach = robot.move_to_pose("reach")
    manager.simulator("arm").inject("link_loss")  # the arm's polls go unanswered
    warned = statuses.wait_for(
        lambda u: u.status is not Status.OK and "device arm" in u.message, "arm fault", WAIT
    )
    assert warned.status is Status.WARNING, warned  # the recovery will run: not FATAL
    assert reach.wait(WAIT)  # the arm's goal ended with the device's reason
    assert isinstance(reach.error, ResourceBrokenError), reach.error
    assert str(reach.error).startswith("robot sim_mobile_manipulator, device arm: "), reach.error
    with pytest.raises(ResourceBrokenError, match="device 'arm' is FAULT"):
        robot.move_to_pose("home")  # needs the faulted arm: fails at once
    x0 = robot.pose()[0]
    end = clock.monotonic() + 1.5
    while clock.monotonic() < end:
        time.sleep(0.02)
    assert not drive.done, drive.error  # the base's goal goes on
    assert robot.pose()[0] > x0 + 0.05, (x0, robot.pose())
    manager.simulator("arm").clear("link_loss")
    statuses.wait_for(
        lambda u: u.status is Status.OK and "device arm: recovered on try" in u.message,
        "OK for the arm",
        WAIT,
    )
    assert not drive.done, drive.error
    assert not any(u.status is Status.FATAL for u in statuses.got), statuses.got
    motion = robot.move_to_pose("home")  # the recovered arm moves again
    assert motion.wait(WAIT), motion
    assert motion.error is None
    drive.cancel()
