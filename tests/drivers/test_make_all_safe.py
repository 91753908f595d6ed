"""make_all_safe: every device told its safe state at once, one line per device, always."""

from __future__ import annotations

import threading
import time

from temoto.drivers import DriverState, make_all_safe
from temoto.drivers.base import Driver


class Device(Driver):
    """A driver whose safe state waits for a confirmation (``silent``: none comes)."""

    kind = "device"
    safe_states = ("off",)

    def __init__(self, name: str, *, silent: bool = False) -> None:
        super().__init__(name)
        self.silent = silent
        self.fail = False
        self.sent = threading.Event()
        self.answer = threading.Event()

    def on_configure(self) -> None:
        pass

    def on_make_safe(self) -> str:
        if self.fail:
            raise OSError("Failed transmit")
        self.sent.set()
        if self.silent and not self.answer.wait(3.0):  # a reply that never comes
            return "off sent, not confirmed"
        return "OFF"

    def on_shutdown(self) -> None:
        pass


def started(*devices: Device) -> tuple[Device, ...]:
    for device in devices:
        device.configure()
        device.activate()
    return devices


def test_silent_devices_do_not_delay_the_others_and_each_has_its_line() -> None:
    quad, arm = Device("quad", silent=True), Device("arm", silent=True)
    base = Device("base")
    started(quad, arm, base)
    try:
        t0 = time.monotonic()
        done = {d.name: what for d, what in make_all_safe("SIGTERM")}
        took = time.monotonic() - t0
        assert all(d.sent.is_set() for d in (quad, arm, base))  # every one sent at once
        assert took < 2.0, took  # one after the other: 3 s per silent device
        assert done == {
            "arm": "safe state off sent, not confirmed within 0.2 s (no answer yet)",
            "base": "OFF",
            "quad": "safe state off sent, not confirmed within 0.2 s (no answer yet)",
        }
    finally:
        for device in (quad, arm, base):
            device.answer.set()
            device.shutdown()


def test_a_device_made_safe_already_is_not_reported_not_safe() -> None:
    (arm,) = started(Device("arm"))
    try:
        assert arm.make_safe("mission end") == "OFF"
        arm.fail = True  # the port is busy or closing: a second send fails
        done = {d.name: what for d, what in make_all_safe("SIGINT")}
        assert done["arm"] == ("OFF (sending it again failed: make safe: OSError: Failed transmit)")
    finally:
        arm.fail = False
        arm.shutdown()


def test_a_device_shut_down_meanwhile_gets_the_line_of_its_shutdown() -> None:
    (arm,) = started(Device("arm"))
    taken = [arm]  # the drivers as they were at the signal
    arm.shutdown()  # the main thread closed the robot first: its shutdown made it safe
    assert arm.state is DriverState.FINALIZED
    assert [(d.name, what) for d, what in make_all_safe("SIGTERM", drivers=taken)] == [
        ("arm", "OFF")
    ]


def test_a_device_its_shutdown_makes_safe_meanwhile_is_not_reported_not_safe() -> None:
    (arm,) = started(Device("arm"))
    failed, holding = threading.Event(), threading.Event()
    real = arm.on_make_safe

    def busy_port() -> str:  # the signal's send collides with the shutdown's on the port
        if not failed.is_set():
            failed.set()
            raise OSError("Failed transmit")
        return real()

    arm.on_make_safe = busy_port  # type: ignore[method-assign]

    def shutdown() -> None:
        with arm._lifecycle:  # as Driver.shutdown holds it
            holding.set()
            failed.wait(5)
            arm.make_safe("shutdown")

    closer = threading.Thread(target=shutdown, name="test-shutdown")
    closer.start()
    assert holding.wait(5)
    try:
        lines = {d.name: what for d, what in make_all_safe("SIGTERM", drivers=[arm])}
        assert lines["arm"] == "OFF (sending it again failed: make safe: OSError: Failed transmit)"
    finally:
        closer.join(5)
        arm.shutdown()
