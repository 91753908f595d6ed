"""The vehicle's own mode changes, link gaps, and components that are not the autopilot.

Against SimVehicle (its GCS failsafe, its ``link_loss``) on a virtual clock, and raw frames from
pymavlink-free senders built with the driver's own codec under other component ids.
"""

from __future__ import annotations

import contextlib
import logging
import socket

import pytest
from test_mavlink import HOME, configure, run_until
from test_mavlink_safety import rig, take_off

from temoto.clock import ManualClock
from temoto.drivers import DriverState
from temoto.drivers.mavlink import MavlinkDriver, ModeChange
from temoto.drivers.mavlink import protocol as p
from temoto.errors import ProfileError


class _Shut:
    """``contextlib.closing`` for a driver: shut down however the test ends."""

    def __init__(self, driver: MavlinkDriver) -> None:
        self.driver = driver

    def close(self) -> None:
        self.driver.shutdown()


@pytest.fixture
def clock() -> ManualClock:
    return ManualClock()


def test_a_gcs_failsafe_during_a_short_outage_is_seen_within_a_heartbeat(
    clock: ManualClock, caplog: pytest.LogCaptureFixture
) -> None:
    """A 2 s outage, shorter than heartbeat_timeout (3 s), in which the vehicle went RTL."""
    sim, d = rig(clock, sim={"params": {"FS_GCS_ENABLE": 1, "FS_GCS_TIMEOUT": 2}})
    with sim, contextlib.closing(_Shut(d)):
        configure(d, clock)
        d.activate()
        heard: list[ModeChange] = []
        d.add_mode_listener(heard.append)
        take_off(d, clock, 3.0)
        assert d.telemetry().mode == "GUIDED"
        caplog.set_level(logging.INFO, logger="temoto.drivers.mavlink")
        sim.inject("link_loss")
        run_until(clock, lambda: sim.mode == "RTL", 2.0 + 1.0)  # FS_GCS_TIMEOUT, then RTL
        back = clock.monotonic()
        sim.clear("link_loss")
        # the first heartbeat after the outage (ArduPilot sends one a second) shows the mode
        run_until(clock, lambda: (d._last_hb or 0.0) > back, 2.0)
        assert d.telemetry().mode == "RTL"
        assert "stale" not in caplog.text  # the link, not a stream, was out
        assert "quad: the vehicle switched GUIDED -> RTL (not commanded" in caplog.text
        gaps = [r for r in caplog.records if "no message from the autopilot" in r.message]
        assert gaps
        assert gaps[0].levelno == logging.WARNING
        said = gaps[0].message
        assert "quad: no message from the autopilot (system 1, component 1) for " in said
        assert d.link_gaps >= 1  # (a starved test thread can add one of its own)
        change = d.last_mode_change
        assert change is not None
        assert (change.old, change.new, change.commanded) == ("GUIDED", "RTL", False)
        assert d.uncommanded_mode_changes == 1
        assert heard[-1] == change  # listeners hear it as it comes
        assert [(c.new, c.commanded) for c in heard] == [("GUIDED", True), ("RTL", False)]


def test_a_commanded_mode_change_is_no_warning(
    clock: ManualClock, caplog: pytest.LogCaptureFixture
) -> None:
    sim, d = rig(clock)
    with sim, contextlib.closing(_Shut(d)):
        configure(d, clock)
        d.activate()
        take_off(d, clock, 3.0)
        caplog.set_level(logging.INFO, logger="temoto.drivers.mavlink")
        d.set_mode("LOITER")
        run_until(clock, lambda: d.telemetry().mode == "LOITER", 1.5)
        change = d.last_mode_change
        assert change is not None
        assert (change.old, change.new, change.commanded) == ("GUIDED", "LOITER", True)
        assert "quad: the vehicle switched GUIDED -> LOITER" in caplog.text
        assert not [r for r in caplog.records if r.levelno >= logging.WARNING]
        assert d.uncommanded_mode_changes == 0
        d.shutdown()


def test_another_component_of_the_system_is_ignored_and_counted(
    clock: ManualClock, caplog: pytest.LogCaptureFixture
) -> None:
    """A companion (component 100) saying "on ground" at the goal changes nothing we trust."""
    sim, d = rig(clock)
    with sim, contextlib.closing(_Shut(d)):
        configure(d, clock)
        d.activate()
        take_off(d, clock, 3.0)
        run_until(clock, lambda: d._landed_state == p.MAV_LANDED_STATE_IN_AIR, 2.0)
        caplog.set_level(logging.WARNING, logger="temoto.drivers.mavlink")
        companion = p.Codec(1, 100)
        frames = [
            companion.encode("EXTENDED_SYS_STATE", vtol_state=0,
                             landed_state=p.MAV_LANDED_STATE_ON_GROUND),
            companion.encode("GLOBAL_POSITION_INT", time_boot_ms=0, lat=int(HOME[0] * 1e7),
                             lon=int((HOME[1] + 0.01) * 1e7), alt=0, relative_alt=0, vx=0,
                             vy=0, vz=0, hdg=0),
            companion.encode("HEARTBEAT", type=p.MAV_TYPE_QUADROTOR,
                             autopilot=p.MAV_AUTOPILOT_ARDUPILOTMEGA, base_mode=0,
                             custom_mode=p.mode_number("LAND"), system_status=3,
                             mavlink_version=3),
        ]  # fmt: skip
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as other:
            for _ in range(10):
                for frame in frames:
                    other.sendto(frame, ("127.0.0.1", int(d.link_spec.port)))
                    sim.send_raw(frame)  # also from the vehicle's own address
                clock.advance(0.02)
            run_until(clock, lambda: d.ignored_messages.get("system 1 component 100") == 60, 2.0)
        t = d.telemetry()
        assert t.position.alt > 2.0
        assert abs(t.position.lon - HOME[1]) < 0.001
        assert t.mode == "GUIDED"
        assert d._landed_state == p.MAV_LANDED_STATE_IN_AIR
        warned = [r for r in caplog.records if "component 100" in r.message]
        assert len(warned) == 1  # once per source, then rate-limited
        assert "only the autopilot (system 1, component 1) is trusted" in warned[0].message
        assert d.make_safe("test") == "vehicle LOITER"
        assert d.state is DriverState.INACTIVE
        d.shutdown()


# ---- profile checks against ArduPilot --------------------------------------------------------


@pytest.mark.parametrize(
    ("keys", "said"),
    [
        ({"safe_state": None}, "devices.quad.safe_state: empty (null)"),
        ({"heartbeat_timeout": None}, "devices.quad.heartbeat_timeout: empty (null)"),
        ({"heartbeat_timeout": 1.0}, "devices.quad.heartbeat_timeout: must be a number in [2"),
        ({"heartbeat_timeout": 600}, "devices.quad.heartbeat_timeout: must be a number in [2"),
        ({"heartbeat_period": 1.5}, "devices.quad.heartbeat_period: must be a number in (0, 1]"),
        ({"init_timeout": 0.5}, "devices.quad.init_timeout: must be a number >= 1 s"),
        ({"stream_rate": 100}, "devices.quad.stream_rate: must be a number in [0, 50]"),
        ({"component_id": 0}, "devices.quad.component_id: must be an integer 1..255"),
        ({"system_id": 255}, "devices.quad.gcs_system_id: gcs_system_id must differ"),
        (
            {"gcs_failsafe": {"timeout": 2}},  # heartbeat_timeout 3 by default
            "devices.quad.heartbeat_timeout: heartbeat_timeout must be at most the GCS failsafe",
        ),
        ({"gcs_failsafe": {"timeout": 150}}, "devices.quad.gcs_failsafe.timeout: must be a"),
    ],
)
def test_a_profile_against_ardupilot_names_the_key(keys: dict[str, object], said: str) -> None:
    config = {"link": "udpin:127.0.0.1:0", **keys}
    with pytest.raises(ProfileError) as info:
        MavlinkDriver.from_profile("quad", config, clock=ManualClock(), where="devices.quad")
    assert said in str(info.value)
    assert "\n" not in str(info.value)


def test_null_keys_that_mean_something_are_accepted() -> None:
    config = {"link": "udpin:127.0.0.1:0", "system_id": None, "gcs_failsafe": None}
    d = MavlinkDriver.from_profile("quad", config, clock=ManualClock(), where="devices.quad")
    assert (d.system_id, d.failsafe_params, d.safe_state) == (None, {}, "loiter")


def test_a_mode_asked_is_used_up_by_its_change(
    clock: ManualClock, caplog: pytest.LogCaptureFixture
) -> None:
    """Paused (LOITER), resumed (GUIDED), then the vehicle's own LOITER: not commanded.

    Before, an ask stayed good for a window of clock time (here 2 tries of 2 s and two
    heartbeats: 6 s), so the pilot's LOITER a few seconds after a pause's was taken for the
    driver's own.
    """
    sim, d = rig(clock, command_timeout=2.0)
    with sim, contextlib.closing(_Shut(d)):
        configure(d, clock)
        d.activate()
        take_off(d, clock, 3.0)
        caplog.set_level(logging.INFO, logger="temoto.drivers.mavlink")
        d.set_mode("LOITER")
        run_until(clock, lambda: d.telemetry().mode == "LOITER", 1.5)
        d.set_mode("GUIDED")
        run_until(clock, lambda: d.telemetry().mode == "GUIDED", 1.5)
        with sim.state.lock:  # the pilot's switch
            sim.flight.set_mode("LOITER")
        run_until(clock, lambda: d.telemetry().mode == "LOITER", 1.5)
        change = d.last_mode_change
        assert change is not None
        assert (change.old, change.new, change.commanded) == ("GUIDED", "LOITER", False)
        assert d.uncommanded_mode_changes == 1
        assert "quad: the vehicle switched GUIDED -> LOITER (not commanded" in caplog.text


def test_the_record_of_a_mode_asked_survives_a_recoverys_configure(
    clock: ManualClock,
) -> None:
    """The safe state's LOITER, sent before a recovery configures again, shown after it.

    Before, configure forgot the asks and the mode before: the LOITER that showed after the
    recovery was no change at all, and the flight controller took it for the vehicle's own.
    """
    sim, d = rig(clock)
    with sim, contextlib.closing(_Shut(d)):
        configure(d, clock)
        d.activate()
        take_off(d, clock, 3.0)
        d.set_mode("LOITER")  # acknowledged; its HEARTBEAT not read yet
        with d._cond:
            d._reset()  # what a recovery's configure does to the driver's state
        run_until(clock, lambda: d.telemetry().mode == "LOITER", 1.5)
        change = d.last_mode_change
        assert change is not None
        assert (change.old, change.new, change.commanded) == ("GUIDED", "LOITER", True)
        assert d.uncommanded_mode_changes == 0
