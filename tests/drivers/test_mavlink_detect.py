"""MavlinkDriver.detect: vehicles found by listening only, as entries from_profile takes."""

from __future__ import annotations

import logging
import math
import os
import socket
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from types import SimpleNamespace
from typing import Any

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mav

from temoto.clock import MonotonicClock
from temoto.drivers import DriverState
from temoto.drivers.mavlink import MavlinkDriver, SimVehicle
from temoto.drivers.mavlink import detect as detect_module
from temoto.drivers.mavlink import protocol as p
from temoto.drivers.mavlink.link import Link, LinkSpec

HOME = (47.397742, 8.545594, 488.0)
TIMEOUT = 0.5  # real seconds of listening per link; the simulated vehicle beats at 10 Hz
SLACK = 2.0  # real seconds detect may take beyond its timeout on a loaded machine


# ---- helpers -------------------------------------------------------------------------------


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
        return port


def heartbeat(codec: p.Codec, mav_type: int, autopilot: int) -> bytes:
    return codec.encode(
        "HEARTBEAT",
        type=mav_type,
        autopilot=autopilot,
        base_mode=0,
        custom_mode=0,
        system_status=p.MAV_STATE_STANDBY,
        mavlink_version=3,
    )


def quad_heartbeat(system: int, component: int = 1) -> bytes:
    return heartbeat(
        p.Codec(system, component), p.MAV_TYPE_QUADROTOR, p.MAV_AUTOPILOT_ARDUPILOTMEGA
    )


@contextmanager
def sending(port: int, frames: list[bytes]) -> Iterator[None]:
    """Send ``frames`` to 127.0.0.1:``port`` every 20 ms (as other MAVLink nodes would)."""
    stop = threading.Event()
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)

    def run() -> None:
        while not stop.is_set():
            for frame in frames:
                with suppress(OSError):  # nobody listens yet
                    sock.sendto(frame, ("127.0.0.1", port))
            stop.wait(0.02)

    thread = threading.Thread(target=run, name="test-mavlink-sender")
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()
        sock.close()


def eventually(pred: Callable[[], bool], seconds: float) -> None:
    deadline = time.monotonic() + seconds
    while not pred():
        assert time.monotonic() < deadline, f"not within {seconds} s"
        time.sleep(0.01)


@pytest.fixture
def quad() -> Iterator[tuple[SimVehicle, dict[str, Any]]]:
    """A simulated quad streaming (heartbeat at 10 Hz, real time) to a free loopback port."""
    config = {
        "link": "udpin:127.0.0.1:14550",
        "sim": {"home": list(HOME), "rates": {"HEARTBEAT": 10}},
    }
    sim, settings = MavlinkDriver.simulate("quad", config, clock=MonotonicClock())
    assert isinstance(sim, SimVehicle)
    sim.start()
    try:
        yield sim, settings
    finally:
        sim.close()


class FakeLink(Link):
    """A link that hands out ``chunks`` and then stays silent; it records writes and close."""

    def __init__(self, spec: LinkSpec, chunks: list[bytes]) -> None:
        self.spec = spec
        self.chunks = list(chunks)
        self.written: list[bytes] = []
        self.closed = False
        self._never = threading.Event()

    def read(self, timeout: float) -> bytes:
        if self.chunks:
            return self.chunks.pop(0)
        self._never.wait(timeout)
        return b""

    def write(self, data: bytes) -> bool:
        self.written.append(data)
        return True

    def close(self) -> None:
        self.closed = True


@pytest.fixture
def fake_links(monkeypatch: pytest.MonkeyPatch) -> dict[str, Any]:
    """Replace the driver's open_link: serial devices answer at the baud in ``answers``."""
    state: dict[str, Any] = {"answers": {}, "opened": [], "missing": set()}

    def open_link(spec: LinkSpec) -> Link:
        if spec.device in state["missing"]:
            raise OSError(f"[Errno 2] could not open port {spec.device}")
        garbage = bytes(range(7, 250, 3))  # what a port at the wrong baud rate delivers
        chunks = [garbage]
        if state["answers"].get(spec.device) == spec.baud:
            chunks += [quad_heartbeat(1), garbage, quad_heartbeat(1)]
        link = FakeLink(spec, chunks)
        state["opened"].append(link)
        return link

    monkeypatch.setattr(detect_module, "open_link", open_link)
    return state


# ---- a simulated vehicle -------------------------------------------------------------------


def test_a_simulated_vehicle_is_found_and_its_entry_flies(
    quad: tuple[SimVehicle, dict[str, Any]], caplog: pytest.LogCaptureFixture
) -> None:
    sim, settings = quad
    link = settings["link"]
    with caplog.at_level(logging.INFO, logger="temoto.drivers.mavlink"):
        entries = MavlinkDriver.detect([link], timeout=TIMEOUT)
    assert entries == [{"driver": "mavlink", "link": link, "system_id": 1, "component_id": 1}]
    assert "MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_ARDUPILOTMEGA" in caplog.text
    assert sim.received == {}  # detect sent nothing

    clock = MonotonicClock()
    driver = MavlinkDriver.from_profile("quad", entries[0], clock=clock, where="devices.quad")
    with driver:
        assert driver.system_id == 1
        driver.configure()
        driver.activate()
        eventually(lambda: math.isclose(driver.telemetry().position.lat, HOME[0]), 5.0)
        telemetry = driver.telemetry()
        assert telemetry.mode == "STABILIZE"
        assert not telemetry.armed
        assert telemetry.heartbeat_age < 1.0
        assert sim.received.get("COMMAND_LONG", 0) >= 1  # the driver, unlike detect, talks
    assert driver.state is DriverState.FINALIZED


def test_detect_sends_nothing(
    quad: tuple[SimVehicle, dict[str, Any]], monkeypatch: pytest.MonkeyPatch
) -> None:
    sim, settings = quad
    opened: list[Link] = []
    writes: list[bytes] = []
    real_open = detect_module.open_link

    def spying_open(spec: LinkSpec) -> Link:
        link = real_open(spec)
        real_write = link.write

        def write(data: bytes) -> bool:
            writes.append(data)
            return real_write(data)

        link.write = write  # type: ignore[method-assign]
        opened.append(link)
        return link

    monkeypatch.setattr(detect_module, "open_link", spying_open)
    assert len(MavlinkDriver.detect([settings["link"]], timeout=TIMEOUT)) == 1
    assert len(opened) == 1
    assert writes == []
    assert sim.received == {}
    assert sim.acks == []


# ---- nothing, or nothing that flies ----------------------------------------------------------


def test_a_silent_link_gives_nothing_within_the_timeout() -> None:
    timeout = 0.3
    started = time.monotonic()
    assert MavlinkDriver.detect([f"udpin:127.0.0.1:{free_port()}"], timeout=timeout) == []
    took = time.monotonic() - started
    assert timeout * 0.9 <= took < timeout + SLACK


@pytest.mark.parametrize("timeout", [0, 0.0, -1.0, math.nan, math.inf])
def test_a_timeout_that_is_not_positive_and_finite_raises(timeout: float) -> None:
    with pytest.raises(ValueError, match="timeout must be a positive number"):
        MavlinkDriver.detect(["udpin:127.0.0.1:1"], timeout=timeout)


@pytest.mark.parametrize(
    ("link", "match"),
    [
        ("ftp:x", "unknown link 'ftp:x'"),
        ("tcp:127.0.0.1:5760", "unknown link 'tcp:127.0.0.1:5760'"),
        (14550, "must be text, got 14550"),
        ({"interface": "socketcan", "channel": "can0"}, "must be text"),
        ("udpin:127.0.0.1", "needs HOST:PORT"),
    ],
)
def test_a_link_not_in_a_known_scheme_raises_before_listening(link: Any, match: str) -> None:
    started = time.monotonic()
    with pytest.raises(ValueError, match=match):
        MavlinkDriver.detect([f"udpin:127.0.0.1:{free_port()}", link], timeout=5.0)
    assert time.monotonic() - started < 1.0  # the good link was not listened to first


def test_ground_stations_and_companion_computers_are_not_vehicles() -> None:
    port = free_port()
    frames = [
        heartbeat(p.Codec(255, 190), p.MAV_TYPE_GCS, p.MAV_AUTOPILOT_ARDUPILOTMEGA),
        heartbeat(p.Codec(1, 191), mav.MAV_TYPE_ONBOARD_CONTROLLER, p.MAV_AUTOPILOT_INVALID),
        heartbeat(p.Codec(1, 100), mav.MAV_TYPE_CAMERA, p.MAV_AUTOPILOT_INVALID),
    ]
    with sending(port, frames):
        assert MavlinkDriver.detect([f"udp:127.0.0.1:{port}"], timeout=TIMEOUT) == []


def test_every_vehicle_on_a_link_is_an_entry(caplog: pytest.LogCaptureFixture) -> None:
    port = free_port()
    link = f"udp:127.0.0.1:{port}"
    frames = [
        heartbeat(p.Codec(255, 190), p.MAV_TYPE_GCS, p.MAV_AUTOPILOT_INVALID),
        quad_heartbeat(1),
        heartbeat(p.Codec(1, 100), mav.MAV_TYPE_CAMERA, p.MAV_AUTOPILOT_INVALID),
        heartbeat(p.Codec(2, 1), mav.MAV_TYPE_HEXAROTOR, mav.MAV_AUTOPILOT_PX4),
        quad_heartbeat(4, component=50),  # an autopilot on a component other than 1
    ]
    with (
        caplog.at_level(logging.INFO, logger="temoto.drivers.mavlink"),
        sending(port, frames),
    ):
        entries = MavlinkDriver.detect([link], timeout=TIMEOUT)
    assert sorted(entries, key=lambda e: e["system_id"]) == [
        {"driver": "mavlink", "link": link, "system_id": 1, "component_id": 1},
        {"driver": "mavlink", "link": link, "system_id": 2, "component_id": 1},
        {"driver": "mavlink", "link": link, "system_id": 4, "component_id": 50},
    ]
    assert "MAV_TYPE_HEXAROTOR, MAV_AUTOPILOT_PX4" in caplog.text
    assert any(
        r.levelno == logging.WARNING and "not an ArduPilot" in r.getMessage()
        for r in caplog.records
    )
    for entry in entries:
        driver = MavlinkDriver.from_profile("quad", entry, clock=MonotonicClock(), where="d.q")
        assert (driver.system_id, driver.component_id) == (
            entry["system_id"],
            entry["component_id"],
        )
        driver.shutdown()


def test_a_link_that_cannot_be_opened_is_skipped(caplog: pytest.LogCaptureFixture) -> None:
    port = free_port()
    with (
        socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as taken,
        sending(port, [quad_heartbeat(1)]),
    ):
        taken.bind(("127.0.0.1", free_port()))
        busy = f"udpin:127.0.0.1:{taken.getsockname()[1]}"
        good = f"udpin:127.0.0.1:{port}"
        with caplog.at_level(logging.WARNING, logger="temoto.drivers.mavlink"):
            entries = MavlinkDriver.detect([busy, good], timeout=TIMEOUT)
    assert [e["link"] for e in entries] == [good]
    assert f"skipping {busy}" in caplog.text


# ---- serial: baud rates, candidates ----------------------------------------------------------


def test_a_serial_link_without_a_baud_rate_is_tried_at_each(fake_links: dict[str, Any]) -> None:
    fake_links["answers"]["/dev/ttyFAKE0"] = 921600
    entries = MavlinkDriver.detect(["serial:/dev/ttyFAKE0"], timeout=0.2)
    assert entries == [
        {
            "driver": "mavlink",
            "link": "serial:/dev/ttyFAKE0?baud=921600",
            "system_id": 1,
            "component_id": 1,
        }
    ]
    opened: list[FakeLink] = fake_links["opened"]
    assert [link.spec.baud for link in opened] == [57600, 115200, 921600]
    assert all(link.closed and not link.written for link in opened)
    MavlinkDriver.from_profile("q", entries[0], clock=MonotonicClock(), where="q").shutdown()


def test_the_sweep_stops_at_the_first_baud_rate_that_works(fake_links: dict[str, Any]) -> None:
    fake_links["answers"]["/dev/ttyFAKE0"] = 57600
    entries = MavlinkDriver.detect(["serial:/dev/ttyFAKE0"], timeout=0.2)
    assert [e["link"] for e in entries] == ["serial:/dev/ttyFAKE0?baud=57600"]
    assert [link.spec.baud for link in fake_links["opened"]] == [57600]


def test_a_given_baud_rate_is_the_only_one_tried(fake_links: dict[str, Any]) -> None:
    fake_links["answers"]["/dev/ttyFAKE0"] = 921600
    assert MavlinkDriver.detect(["serial:/dev/ttyFAKE0?baud=115200"], timeout=0.1) == []
    assert [link.spec.baud for link in fake_links["opened"]] == [115200]
    entries = MavlinkDriver.detect(["serial:/dev/ttyFAKE0?baud=921600"], timeout=0.1)
    assert [e["link"] for e in entries] == ["serial:/dev/ttyFAKE0?baud=921600"]


def test_a_missing_serial_port_is_skipped_once(
    fake_links: dict[str, Any], caplog: pytest.LogCaptureFixture
) -> None:
    fake_links["missing"].add("/dev/ttyGONE")
    with caplog.at_level(logging.WARNING, logger="temoto.drivers.mavlink"):
        assert MavlinkDriver.detect(["serial:/dev/ttyGONE"], timeout=0.1) == []
    assert fake_links["opened"] == []
    assert caplog.text.count("skipping serial:/dev/ttyGONE?baud=57600") == 1


def test_without_links_every_serial_port_and_the_gcs_port_are_looked_at(
    fake_links: dict[str, Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    list_ports = pytest.importorskip("serial.tools.list_ports")
    ports = [SimpleNamespace(device="/dev/ttyFAKE1"), SimpleNamespace(device="/dev/ttyFAKE0")]
    monkeypatch.setattr(list_ports, "comports", lambda: ports)
    fake_links["answers"]["/dev/ttyFAKE1"] = 115200
    entries = MavlinkDriver.detect(timeout=0.05)
    assert [str(link.spec) for link in fake_links["opened"]] == [
        "serial:/dev/ttyFAKE0?baud=57600",
        "serial:/dev/ttyFAKE0?baud=115200",
        "serial:/dev/ttyFAKE0?baud=921600",
        "serial:/dev/ttyFAKE1?baud=57600",
        "serial:/dev/ttyFAKE1?baud=115200",
        "udpin:0.0.0.0:14550",
    ]
    assert [e["link"] for e in entries] == ["serial:/dev/ttyFAKE1?baud=115200"]


@pytest.mark.skipif(os.name != "posix", reason="needs a pseudo-terminal")
def test_a_vehicle_on_a_real_serial_port(monkeypatch: pytest.MonkeyPatch) -> None:
    """A pseudo-terminal through pyserial: the first baud rate works (a pty has none)."""
    pytest.importorskip("serial")
    import tty

    master, slave = os.openpty()
    tty.setraw(slave)
    name = os.ttyname(slave)
    stop = threading.Event()

    def autopilot() -> None:
        while not stop.wait(0.02):
            os.write(master, quad_heartbeat(7))

    thread = threading.Thread(target=autopilot, name="test-mavlink-pty")
    thread.start()
    try:
        entries = MavlinkDriver.detect([f"serial:{name}"], timeout=0.3)
    finally:
        stop.set()
        thread.join()
        os.close(slave)
        os.close(master)
    assert entries == [
        {
            "driver": "mavlink",
            "link": f"serial:{name}?baud=57600",
            "system_id": 7,
            "component_id": 1,
        }
    ]


def test_two_vehicles_with_one_system_id_are_named_a_duplicate(
    caplog: pytest.LogCaptureFixture,
) -> None:
    port = free_port()
    link = f"udpin:127.0.0.1:{port}"
    with (
        sending(port, [quad_heartbeat(1)]),
        sending(port, [quad_heartbeat(1)]),
        caplog.at_level(logging.WARNING, logger="temoto.drivers.mavlink"),
    ):
        found = MavlinkDriver.detect(link, timeout=TIMEOUT)
    assert [(e["system_id"], e["component_id"]) for e in found] == [(1, 1)]
    assert f"mavlink detect: {link}: duplicate system id 1: component 1 heartbeats" in caplog.text
