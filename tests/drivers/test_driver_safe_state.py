"""The safe-state API every driver shares: make_safe, shutdown, make_all_safe, atexit."""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from temoto.drivers import DriverState, live_drivers, make_all_safe
from temoto.drivers.base import Driver
from temoto.errors import DriverOperationError, ProfileError


class Recorder(Driver):
    """A driver whose device is a list of what it was sent."""

    kind = "recorder"
    safe_states = ("off", "hold")

    def __init__(self, name: str, *, fail_safe: bool = False) -> None:
        super().__init__(name)
        self.sent: list[str] = []
        self.fail_safe = fail_safe

    def on_configure(self) -> None:
        self.sent.append("open")

    def on_activate(self) -> None:
        self.sent.append("on")

    def on_make_safe(self) -> str:
        if self.fail_safe:
            raise OSError("the link is gone")
        self.sent.append(self.safe_state)
        return f"{self.name} {self.safe_state.upper()}"

    def on_shutdown(self) -> None:
        self.sent.append("close")


def active(name: str = "dev", **kwargs: bool) -> Recorder:
    driver = Recorder(name, **kwargs)
    driver.configure()
    driver.activate()
    return driver


def test_make_safe_from_active_sends_the_safe_state_and_leaves_it_inactive() -> None:
    driver = active()
    assert driver.make_safe("test") == "dev OFF"
    assert driver.sent == ["open", "on", "off"]
    assert driver.state is DriverState.INACTIVE
    driver.shutdown()


def test_shutdown_makes_the_device_safe_before_it_closes_the_link() -> None:
    driver = active()
    driver.shutdown()
    assert driver.sent == ["open", "on", "off", "close"]
    assert driver.state is DriverState.FINALIZED
    assert driver.make_safe() is None  # no link any more: nothing is sent
    assert driver.sent[-1] == "close"


def test_a_driver_made_safe_in_fault_recovers_to_inactive_not_active() -> None:
    driver = active()
    driver.report_fault(DriverOperationError("dev: no heartbeat"))
    assert driver.make_safe("fault") == "dev OFF"
    assert driver.state is DriverState.FAULT  # the fault stays until the device answers
    driver.report_recovered()
    assert driver.state is DriverState.INACTIVE
    driver.shutdown()


def test_a_failing_safe_state_is_a_fault_and_shutdown_still_closes() -> None:
    driver = active(fail_safe=True)
    with pytest.raises(DriverOperationError, match="make safe: OSError: the link is gone"):
        driver.make_safe()
    assert driver.state is DriverState.FAULT
    driver.shutdown()
    assert driver.sent[-1] == "close"


def test_a_safe_state_failing_at_shutdown_is_one_line_not_a_traceback(
    caplog: pytest.LogCaptureFixture,
) -> None:
    driver = active(fail_safe=True)
    with caplog.at_level("WARNING", logger="temoto.drivers.base"):
        driver.shutdown()
    (record,) = [r for r in caplog.records if "failed" in r.getMessage()]
    assert record.getMessage() == (
        "driver dev: make safe at shutdown failed: dev: make safe: OSError: the link is gone"
    )
    assert record.exc_info is None  # a device's error, not a bug: no traceback
    assert driver.sent[-1] == "close"


def test_make_all_safe_reaches_every_configured_driver_and_reports_failures() -> None:
    fine, broken, fresh = active("fine"), active("broken", fail_safe=True), Recorder("fresh")
    try:
        assert fine in live_drivers()
        assert broken in live_drivers()
        assert fresh not in live_drivers()  # never configured: nothing to make safe
        done = dict(make_all_safe("test"))
        assert done[fine] == "fine OFF"
        assert done[broken].startswith("NOT SAFE: ")
        assert fresh not in done
    finally:
        for driver in (fine, broken):
            driver.shutdown()
    assert fine not in live_drivers()


def test_make_safe_does_not_wait_for_a_transition_stuck_on_another_thread() -> None:
    driver = active()
    held, release = threading.Event(), threading.Event()

    def stuck() -> None:
        with driver._lifecycle:  # a configure or recover that hangs on a dead device
            held.set()
            release.wait(5)

    thread = threading.Thread(target=stuck)
    thread.start()
    try:
        held.wait(5)
        t0 = time.monotonic()
        assert driver.make_safe() == "dev OFF"
        assert time.monotonic() - t0 < 1.0  # SAFE_LOCK_WAIT (0.05 s), then sent anyway
    finally:
        release.set()
        thread.join()
        driver.shutdown()


def test_the_profile_chooses_a_declared_safe_state() -> None:
    assert Recorder.safe_state_from({}, "p.yaml: devices.dev") == "off"
    assert Recorder.safe_state_from({"safe_state": "hold"}, "p.yaml: devices.dev") == "hold"
    with pytest.raises(ProfileError, match=r"p.yaml: devices.dev.safe_state: must be one of off"):
        Recorder.safe_state_from({"safe_state": "coast"}, "p.yaml: devices.dev")
    driver = Recorder("dev")
    with pytest.raises(ValueError, match="safe_state must be one of"):
        driver.safe_state = "coast"


def test_interpreter_exit_makes_a_driver_left_open_safe(tmp_path: Path) -> None:
    # a program that forgets to shut its driver down: atexit still makes the device safe
    log = tmp_path / "device.log"
    program = f"""
from temoto.drivers.base import Driver

class FileDevice(Driver):
    kind = "file"
    def on_configure(self): pass
    def on_make_safe(self):
        with open({str(log)!r}, "a") as f:
            f.write("idle\\n")
        return "idle"
    def on_shutdown(self): pass

d = FileDevice("dev")
d.configure()
d.activate()
raise SystemExit(3)
"""
    proc = subprocess.run(
        [sys.executable, "-W", "ignore", "-c", program],
        capture_output=True,
        text=True,
        timeout=30,
        check=False,
    )
    assert proc.returncode == 3, proc.stderr
    assert log.read_text() == "idle\n"
