"""MAVLink safety: safe state, GCS failsafe, stream supervision, an untrusting link.

Against SimVehicle, and, for what matters to safety, against ``Autopilot`` below: a small
emulator of ArduCopter's side written from the ArduPilot documentation and the MAVLink common
message set (not from our simulator), encoding with pymavlink directly.
"""

from __future__ import annotations

import contextlib
import math
import socket
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from typing import Any

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mav2  # type: ignore[import-untyped]
from test_mavlink import HOME, configure, run_until, ticking

from temoto.clock import ManualClock, ScaledClock
from temoto.drivers import DriverState
from temoto.drivers.mavlink import MavlinkDriver, SimVehicle
from temoto.drivers.mavlink import protocol as p
from temoto.drivers.mavlink.link import LinkSpec, UdpLink
from temoto.errors import (
    DriverInitError,
    DriverOperationError,
    DriverTimeoutError,
    MavlinkCommandError,
    ProfileError,
)


def rig(
    clock: ManualClock, sim: Mapping[str, Any] | None = None, **keys: Any
) -> tuple[SimVehicle, MavlinkDriver]:
    config = {
        "link": "udpin:127.0.0.1:14550",
        "init_timeout": 2.0,
        "command_timeout": 0.3,
        "command_retries": 1,
        **keys,
        "sim": {"home": list(HOME), "climb_rate": 4.0, "tau": 0.5, **(sim or {})},
    }
    simulator, settings = MavlinkDriver.simulate("quad", config, clock=clock)
    assert isinstance(simulator, SimVehicle)
    driver = MavlinkDriver.from_profile("quad", settings, clock=clock, where="devices.quad")
    return simulator, driver


@pytest.fixture
def clock() -> ManualClock:
    return ManualClock()


@pytest.fixture
def active(clock: ManualClock) -> Iterator[tuple[SimVehicle, MavlinkDriver]]:
    sim, driver = rig(clock)
    sim.start()
    try:
        configure(driver, clock)
        driver.activate()
        yield sim, driver
    finally:
        driver.shutdown()
        sim.close()


def take_off(d: MavlinkDriver, clock: ManualClock, altitude: float = 3.0) -> None:
    d.arm()
    d.takeoff(altitude)
    run_until(clock, lambda: d.telemetry().position.alt > altitude - 0.3, 10.0)


def kill(d: MavlinkDriver) -> None:
    """What SIGKILL does to the driver: its threads and socket go, nothing more is sent."""
    d.on_shutdown()


# ---- safe state (SimVehicle) ---------------------------------------------------------------


def test_on_the_ground_the_safe_state_sends_nothing(
    active: tuple[SimVehicle, MavlinkDriver], clock: ManualClock
) -> None:
    sim, d = active
    assert d.safe_state == "loiter"
    assert d.make_safe("test") == "vehicle on the ground: disarmed, nothing to do"
    assert d.state is DriverState.INACTIVE
    d.activate()
    d.arm()
    run_until(clock, lambda: d.telemetry().armed, 2.0)
    run_until(clock, lambda: d._landed_state == p.MAV_LANDED_STATE_ON_GROUND, 2.0)
    assert d.make_safe("test") == "vehicle on the ground: armed and landed, nothing sent"
    assert p.MAV_CMD_DO_SET_MODE not in [cmd for cmd, _ in sim.acks]
    assert sim.mode == "STABILIZE"


@pytest.mark.parametrize(("state", "mode"), [("loiter", "LOITER"), ("brake", "BRAKE"),
                                             ("land", "LAND"), ("rtl", "RTL")])  # fmt: skip
def test_in_the_air_the_safe_state_sets_its_mode(
    active: tuple[SimVehicle, MavlinkDriver], clock: ManualClock, state: str, mode: str
) -> None:
    sim, d = active
    d.safe_state = state
    take_off(d, clock)
    assert d.make_safe("test") == f"vehicle {mode}"
    assert sim.mode == mode
    assert (p.MAV_CMD_DO_SET_MODE, p.MAV_RESULT_ACCEPTED) in sim.acks
    assert d.state is DriverState.INACTIVE


def test_from_fault_the_safe_state_is_sent_anyway(
    active: tuple[SimVehicle, MavlinkDriver], clock: ManualClock
) -> None:
    sim, d = active
    take_off(d, clock)
    sim.inject("no_heartbeat")  # the driver goes FAULT, the vehicle still listens
    run_until(clock, lambda: d.state is DriverState.FAULT, 5.0)
    done = d.make_safe("test")
    assert done is not None
    assert done.startswith("vehicle LOITER sent, not confirmed (not heard")
    run_until(clock, lambda: sim.mode == "LOITER", 1.0)
    assert d.state is DriverState.FAULT


def test_shutdown_in_the_air_leaves_the_vehicle_loitering(clock: ManualClock) -> None:
    sim, d = rig(clock, safe_state="brake")
    with sim:
        configure(d, clock)
        d.activate()
        take_off(d, clock)
        d.shutdown()
        assert sim.mode == "BRAKE"
        assert sim.armed
        assert sim.airborne


def test_the_safe_state_key() -> None:
    config = {"link": "udpin:127.0.0.1:0", "safe_state": "rtl"}
    d = MavlinkDriver.from_profile("quad", config, clock=ManualClock(), where="devices.quad")
    assert d.safe_state == "rtl"
    assert MavlinkDriver.safe_states == ("loiter", "brake", "land", "rtl")
    with pytest.raises(ProfileError, match=r"devices\.quad\.safe_state: must be one of loiter"):
        MavlinkDriver.from_profile(
            "quad", {**config, "safe_state": "hover"}, clock=ManualClock(), where="devices.quad"
        )


# ---- GCS failsafe (SimVehicle) -------------------------------------------------------------


@pytest.mark.parametrize(("enable", "mode"), [(1, "RTL"), (5, "LAND"), (7, "BRAKE")])
def test_the_gcs_failsafe_acts_when_the_driver_dies(
    clock: ManualClock, enable: int, mode: str
) -> None:
    sim, d = rig(clock, gcs_failsafe={"enable": enable, "timeout": 3})
    with sim:
        configure(d, clock)
        assert (sim.param("FS_GCS_ENABLE"), sim.param("FS_GCS_TIMEOUT")) == (enable, 3.0)
        d.activate()
        take_off(d, clock)
        kill(d)
        took = run_until(clock, lambda: sim.mode == mode, 6.0)
        assert sim.gcs_failsafe
        assert 3.0 - d.heartbeat_period < took <= 3.0 + d.heartbeat_period
        d.shutdown()


def test_the_gcs_failsafe_disarms_a_landed_vehicle_and_leaves_a_disarmed_one(
    clock: ManualClock,
) -> None:
    sim, d = rig(clock, gcs_failsafe={"enable": 1})
    with sim:
        configure(d, clock)
        d.activate()
        d.arm()
        kill(d)
        took = run_until(clock, lambda: not sim.armed, 5.0 + 1.0)
        assert took > 5.0 - d.heartbeat_period  # FS_GCS_TIMEOUT's default, 5 s
        assert sim.mode == "STABILIZE"
        assert not sim.airborne
        d.shutdown()
    sim, d = rig(clock, gcs_failsafe={"enable": 1})
    with sim:
        configure(d, clock)
        kill(d)
        run_until(clock, lambda: sim.gcs_failsafe, 6.5)
        assert (sim.mode, sim.armed) == ("STABILIZE", False)
        d.shutdown()


def test_a_vehicle_watching_another_gcs_is_refused(clock: ManualClock) -> None:
    sim, d = rig(clock, sim={"params": {"SYSID_MYGCS": 254}}, gcs_failsafe={"enable": 5})
    with sim, pytest.raises(DriverInitError, match=r"watches system 254 .* gcs_system_id 255"):
        configure(d, clock)
    assert d.state is DriverState.UNCONFIGURED


@pytest.mark.parametrize(
    ("keys", "path"),
    [
        ({"gcs_failsafe": 5}, "devices.quad.gcs_failsafe: must be a mapping"),
        ({"gcs_failsafe": {"enable": 9}}, "devices.quad.gcs_failsafe.enable: must be an integer"),
        ({"gcs_failsafe": {"enable": 1.5}}, "devices.quad.gcs_failsafe.enable"),
        ({"gcs_failsafe": {"timeout": 1}}, "devices.quad.gcs_failsafe.timeout: must be a number"),
        ({"gcs_failsafe": {"action": 1}}, "devices.quad.gcs_failsafe.action: unknown key"),
        (
            {"gcs_failsafe": {"timeout": 3}, "heartbeat_period": 2},  # half ArduPilot's least
            "devices.quad.heartbeat_period: must be a number in (0, 1] s",
        ),
        ({"sim": {"params": {"FOO": 1}}}, "devices.quad.sim.params.FOO: not a simulated"),
    ],
)
def test_bad_failsafe_keys_name_the_key(keys: dict[str, Any], path: str) -> None:
    config = {"link": "udpin:127.0.0.1:0", **keys}
    with pytest.raises(ProfileError) as info:
        MavlinkDriver.from_profile("quad", config, clock=ManualClock(), where="devices.quad")
    assert path in str(info.value)


def test_a_standalone_simulator_shows_its_gcs_failsafe_on_the_wire(clock: ManualClock) -> None:
    """What a test in another process sees: a plain SimVehicle, a GCS that stops, the wire."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as gcs:
        gcs.bind(("127.0.0.1", 0))
        gcs.settimeout(0.0)
        params = {"FS_GCS_ENABLE": 5, "FS_GCS_TIMEOUT": 2}
        sim = SimVehicle(clock=clock, gcs=[gcs.getsockname()], params=params)
        sim.start()
        mav = mav2.MAVLink(None, 255, 190)
        seen: dict[str, Any] = {}

        def send(msg: Any) -> None:
            gcs.sendto(msg.pack(mav), sim.address)

        def heartbeat() -> None:
            send(mav.heartbeat_encode(mav2.MAV_TYPE_GCS, mav2.MAV_AUTOPILOT_INVALID, 0, 0, 4))

        def command(cmd: int, *params: float) -> None:
            send(mav.command_long_encode(1, 1, cmd, 0, *params, *[0.0] * (7 - len(params))))

        def step(beating: bool) -> None:
            if beating and round(clock.monotonic() / 0.02) % 50 == 0:
                heartbeat()
            clock.advance(0.02)
            time.sleep(0.0007)
            while True:
                try:
                    data = gcs.recv(65536)
                except BlockingIOError:
                    return
                for msg in mav2.MAVLink(None, 255, 190).parse_buffer(data) or []:
                    seen[msg.get_type()] = msg

        try:
            heartbeat()
            command(mav2.MAV_CMD_DO_SET_MODE, mav2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 4)
            command(mav2.MAV_CMD_COMPONENT_ARM_DISARM, 1)
            command(mav2.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, math.nan, math.nan, 5)
            while (
                "GLOBAL_POSITION_INT" not in seen or seen["GLOBAL_POSITION_INT"].relative_alt < 4500
            ):
                assert clock.monotonic() < 10.0, "no takeoff"
                step(beating=True)
            start = clock.monotonic()
            while seen["HEARTBEAT"].custom_mode != LAND:
                assert clock.monotonic() - start <= 2.0 + 1.0 + 0.1, "no failsafe on the wire"
                step(beating=False)
            assert seen["HEARTBEAT"].base_mode & mav2.MAV_MODE_FLAG_SAFETY_ARMED
        finally:
            sim.close()


# ---- supervision (SimVehicle) --------------------------------------------------------------


@pytest.mark.parametrize("stream", ["GLOBAL_POSITION_INT", "ATTITUDE"])
def test_a_stream_that_stops_while_heartbeats_go_on_is_stale(
    active: tuple[SimVehicle, MavlinkDriver], clock: ManualClock, stream: str
) -> None:
    sim, d = active
    run_until(clock, lambda: clock.monotonic() >= 1.0, 2.0)
    sim.set_rate(stream, 0)
    took = run_until(clock, lambda: d.state is DriverState.FAULT, 2.0)
    assert took <= 0.3 + 0.2  # 3 periods of 0.1 s, plus the watch's 0.1 s round
    error = d.health().error
    assert isinstance(error, DriverTimeoutError)
    assert f"{stream} stale" in str(error)
    assert d.telemetry().heartbeat_age < 1.1  # the heartbeats went on
    sim.set_rate(stream, 10)
    run_until(clock, lambda: d.state is DriverState.ACTIVE, 1.0)


def test_a_vehicle_on_this_machine_gets_the_in_process_floor_on_a_fast_clock() -> None:
    """Our simulator (or SITL) shares the cores: its streams may be 0.2 real s late.

    On a clock ten times faster than real time, 3 periods of a 10 Hz stream are 30 ms of real
    time: a simulator thread in the robot's own process, starved that long on a loaded
    machine, made the driver call GLOBAL_POSITION_INT stale mid-flight (a whole-suite run at
    load 12-50). A vehicle whose frames come from a loopback address is given
    ``STALE_REAL_FLOOR_IN_PROCESS`` (0.2 real s: 2 clock s here), as the CAN drivers' virtual
    bus is; a stream that really stops is still a fault, named.
    """
    clock = ScaledClock(10)
    config = {
        "link": "udpin:127.0.0.1:14550",
        "init_timeout": 60.0,  # clock seconds: 6 real s for a loaded machine
        "command_timeout": 5.0,
        "heartbeat_timeout": 20.0,  # the stream, not the heartbeat, is under test
    }
    sim, settings = MavlinkDriver.simulate("quad", config, clock=clock)
    d = MavlinkDriver.from_profile("quad", settings, clock=clock, where="devices.quad")
    sim.start()
    try:
        d.configure()
        d.activate()
        stopped = clock.monotonic()
        sim.set_rate("GLOBAL_POSITION_INT", 0)
        deadline = time.monotonic() + 30.0
        while d.state is not DriverState.FAULT:
            assert time.monotonic() < deadline, "the stopped stream was never called stale"
            time.sleep(0.002)
        took = clock.monotonic() - stopped
        error = d.health().error
        assert isinstance(error, DriverTimeoutError)
        assert "GLOBAL_POSITION_INT stale: none for over 2 s (expected every 0.1 s)" in str(error)
        assert took > 2.0 - 0.1  # not before the floor (its last frame may be a period old)
    finally:
        d.shutdown()
        sim.close()


@pytest.mark.parametrize(
    ("addr", "here"),
    [
        (("127.0.0.1", 14550), True),
        (("127.0.1.1", 5760), True),
        (("::1", 14550, 0, 0), True),
        (("192.168.1.20", 14550), False),
        (("fe80::1%eth0", 14550, 0, 2), False),
        (None, False),  # a serial line
    ],
)
def test_which_vehicle_addresses_are_on_this_machine(addr: Any, here: bool) -> None:
    from temoto.drivers.mavlink.driver import _on_this_machine

    assert _on_this_machine(addr) is here


def test_one_bad_frame_is_counted_several_make_a_fault(
    active: tuple[SimVehicle, MavlinkDriver], clock: ManualClock
) -> None:
    sim, d = active
    frame = sim.codec.encode(
        "HEARTBEAT", type=2, autopilot=3, base_mode=0, custom_mode=0, system_status=3,
        mavlink_version=3,
    )  # fmt: skip
    bad = p.corrupt(frame)
    before = d.bad_frames
    sim.send_raw(bad)
    run_until(clock, lambda: d.bad_frames == before + 1, 1.0)
    run_until(clock, lambda: clock.monotonic() > 3.0, 3.0)
    assert d.state is DriverState.ACTIVE
    for _ in range(5):
        sim.send_raw(bad)
        clock.advance(0.05)
    run_until(clock, lambda: d.state is DriverState.FAULT, 1.0)
    error = d.health().error
    assert isinstance(error, DriverOperationError)
    assert "corrupt frames (bad CRC) from the vehicle's address: 5 or more within 1 s" in str(error)
    run_until(clock, lambda: d.state is DriverState.ACTIVE, 2.0)


def _garbage() -> bytes:
    """10 bytes whose MAVLink 2 header claims a 255-byte payload."""
    return bytes([0xFD, 255, 0, 0, 7, 1, 1, 0, 0, 0])


def _flood(clock: ManualClock, send: Callable[[], None], count: int) -> None:
    """``count`` sends at 50 per virtual second while the vehicle streams."""
    for _ in range(count):
        send()
        clock.advance(0.02)
        time.sleep(0.0007)


def test_garbage_datagrams_from_elsewhere_do_not_cut_valid_traffic(
    active: tuple[SimVehicle, MavlinkDriver], clock: ManualClock
) -> None:
    sim, d = active
    port = int(d.link_spec.port)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as other:
        before = d.messages_received
        _flood(clock, lambda: other.sendto(_garbage(), ("127.0.0.1", port)), 100)
        run_until(clock, lambda: d.foreign_frames >= 100, 1.0)
    got = d.messages_received - before
    assert got >= 2.0 * (10 + 10) * 0.8  # position and attitude at 10 Hz for 2 s, at least
    assert d.state is DriverState.ACTIVE
    assert d._link is not None
    assert d._link.peer == sim.address


def test_garbage_from_the_vehicle_is_a_corrupt_link_but_valid_frames_still_pass(
    active: tuple[SimVehicle, MavlinkDriver], clock: ManualClock
) -> None:
    sim, d = active
    before = d.messages_received
    _flood(clock, lambda: sim.send_raw(_garbage()), 100)
    assert d.messages_received - before >= 2.0 * (10 + 10) * 0.8
    error = d.health().error
    assert isinstance(error, DriverOperationError)
    assert "corrupt frames" in str(error)
    run_until(clock, lambda: d.state is DriverState.ACTIVE, 2.0)


@pytest.mark.parametrize("ids", [(2, 1), (1, 191)], ids=["another-system", "another-component"])
def test_a_foreign_heartbeat_flood_does_not_steal_the_replies(
    active: tuple[SimVehicle, MavlinkDriver], ids: tuple[int, int]
) -> None:
    sim, d = active
    port = int(d.link_spec.port)
    foreign = p.Codec(*ids)
    beat = foreign.encode(
        "HEARTBEAT", type=p.MAV_TYPE_QUADROTOR, autopilot=p.MAV_AUTOPILOT_ARDUPILOTMEGA,
        base_mode=0, custom_mode=0, system_status=3, mavlink_version=3,
    )  # fmt: skip
    stop = threading.Event()
    heard: list[bytes] = []

    def flood(sock: socket.socket) -> None:
        sock.settimeout(0.0)
        while not stop.is_set():
            sock.sendto(beat, ("127.0.0.1", port))
            with contextlib.suppress(BlockingIOError):
                heard.append(sock.recv(65536))
            time.sleep(0.002)

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as other:
        other.bind(("127.0.0.1", 0))
        thread = threading.Thread(target=flood, args=(other,))
        thread.start()
        try:
            for mode in ["LOITER", "ALT_HOLD"] * 5:
                d.set_mode(mode)  # each waits for its ack: none may go to the flooder
        finally:
            stop.set()
            thread.join()
    assert sim.mode == "ALT_HOLD"
    assert heard == []
    assert d._link is not None
    assert d._link.peer == sim.address


def test_each_datagram_is_parsed_on_its_own() -> None:
    vehicle, gcs = p.Codec(1, 1), p.Codec(255, 190)
    frame = vehicle.encode("COMMAND_ACK", command=400, result=0)
    assert gcs.decode_datagram(_garbage()) == []
    assert gcs.bad_frames == 1  # the truncated frame
    assert [m.name for m in gcs.decode_datagram(frame)] == ["COMMAND_ACK"]
    assert gcs.decode(_garbage()) == []  # a byte stream instead waits for the rest...
    assert gcs.decode(frame) == []  # ...and the real frame is swallowed


def test_a_udpin_link_sends_only_where_it_is_told() -> None:
    link = UdpLink(LinkSpec("udpin", "127.0.0.1", 0))
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as a:
        a.bind(("127.0.0.1", 0))
        a.settimeout(1.0)
        try:
            a.sendto(b"hello", link.address)
            data, sender = link.receive(1.0)
            assert (data, sender) == (b"hello", a.getsockname())
            assert link.peer is None  # receiving is not trusting
            assert link.write(b"x") is False
            assert link.accept_peer(sender) is True
            assert link.accept_peer(sender) is False
            assert link.write(b"reply") is True
            assert a.recv(100) == b"reply"
        finally:
            link.close()


# ---- an independent ArduCopter emulator (from the ArduPilot docs) ---------------------------

#: ArduCopter flight mode numbers (ArduPilot Copter docs, "Flight Modes").
STABILIZE, GUIDED, LOITER, RTL, LAND, BRAKE = 0, 4, 5, 6, 9, 17
MODES_NEEDING_GPS = {GUIDED, LOITER, RTL, BRAKE}
#: FS_GCS_ENABLE actions in the air (ArduCopter parameter docs): 1 RTL, 2 RTL (or continue an
#: AUTO mission), 3 SmartRTL or RTL, 4 SmartRTL or Land, 5 Land, 6 Auto DO_LAND_START or RTL,
#: 7 Brake or Land; 0 off. This emulator has no SmartRTL path and no mission.
FS_ACTION = {1: RTL, 2: RTL, 3: RTL, 4: LAND, 5: LAND, 6: RTL, 7: BRAKE}


class Autopilot:
    """ArduCopter's MAVLink side, only what these tests need, from the vendor's documents.

    * HEARTBEAT and EXTENDED_SYS_STATE at 1 Hz to the GCS address (MAVLink common set).
    * COMMAND_LONG: COMPONENT_ARM_DISARM refused with MAV_RESULT_FAILED, its "PreArm: ..."
      STATUSTEXT ``text_delay`` seconds after the ack (ArduPilot queues texts; the ack goes
      at once); DO_SET_MODE with custom modes, FAILED for a GPS mode without GPS; NAV_TAKEOFF
      accepted when armed in GUIDED, FAILED otherwise (the climb is the test's to start: until
      then the vehicle reports ON_GROUND, as a copter spooling up does); anything else
      UNSUPPORTED.
    * PARAM_REQUEST_READ / PARAM_SET answered with PARAM_VALUE (MAVLink parameter protocol).
    * GCS failsafe (ArduCopter docs): only after a heartbeat from SYSID_MYGCS was seen; no
      heartbeat for FS_GCS_TIMEOUT s: disarmed → nothing, landed → disarm, flying → the
      FS_GCS_ENABLE action.
    """

    def __init__(
        self, clock: ManualClock, gcs_port: int, *, gps: bool = True, text_delay: float = 0.02
    ) -> None:
        self.clock = clock
        self.gcs = ("127.0.0.1", gcs_port)
        self.gps, self.text_delay = gps, text_delay
        self.mav = mav2.MAVLink(None, 1, 1)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.01)
        self.lock = threading.Lock()
        self.mode, self.armed, self.flying = STABILIZE, False, False
        self.params = {
            "FS_GCS_ENABLE": [0.0, mav2.MAV_PARAM_TYPE_INT8],
            "FS_GCS_TIMEOUT": [5.0, mav2.MAV_PARAM_TYPE_REAL32],
            "SYSID_MYGCS": [255.0, mav2.MAV_PARAM_TYPE_INT16],
        }
        self.gcs_seen: float | None = None
        self.failsafe = False
        self.mode_commands = 0
        self.texts: list[tuple[float, str]] = []  # (due, text)
        self.stop = threading.Event()
        self.threads = [threading.Thread(target=self._rx), threading.Thread(target=self._tick)]

    def __enter__(self) -> Autopilot:
        for thread in self.threads:
            thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        for thread in self.threads:
            while thread.is_alive():
                self.clock.advance(0.0)  # wakes the tick thread's virtual-time wait
                thread.join(0.01)
        self.sock.close()

    def send(self, msg: Any) -> None:
        self.sock.sendto(msg.pack(self.mav), self.gcs)

    def _tick(self) -> None:
        cond = threading.Condition()
        next_beat = 0.0
        while not self.stop.is_set():
            now = self.clock.monotonic()
            with self.lock:
                if now >= next_beat:
                    next_beat = now + 1.0
                    base = mav2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
                    base |= mav2.MAV_MODE_FLAG_SAFETY_ARMED if self.armed else 0
                    self.send(self.mav.heartbeat_encode(2, 3, base, self.mode, 4, 3))
                    landed = 2 if self.flying else 1  # MAV_LANDED_STATE_IN_AIR / ON_GROUND
                    self.send(self.mav.extended_sys_state_encode(0, landed))
                due = [t for t in self.texts if t[0] <= now]
                self.texts = [t for t in self.texts if t[0] > now]
                for _, text in due:
                    self.send(self.mav.statustext_encode(2, text.encode()))
                self._gcs_failsafe(now)
            with cond:
                self.clock.wait(cond, 0.02)

    def _gcs_failsafe(self, now: float) -> None:
        enable, timeout = int(self.params["FS_GCS_ENABLE"][0]), self.params["FS_GCS_TIMEOUT"][0]
        if enable == 0 or self.gcs_seen is None:
            return
        lost = now - self.gcs_seen > timeout
        if lost and not self.failsafe:
            self.failsafe = True
            if not self.armed:
                return
            if not self.flying:
                self.armed = False
            else:
                self.mode = FS_ACTION.get(enable, RTL)
        elif not lost:
            self.failsafe = False

    def _rx(self) -> None:
        while not self.stop.is_set():
            try:
                data = self.sock.recv(65536)
            except TimeoutError:
                continue
            parser = mav2.MAVLink(None, 1, 1)
            for msg in parser.parse_buffer(data) or []:
                with self.lock:
                    self._handle(msg)

    def _handle(self, msg: Any) -> None:
        kind = msg.get_type()
        if kind == "HEARTBEAT" and msg.get_srcSystem() == self.params["SYSID_MYGCS"][0]:
            self.gcs_seen = self.clock.monotonic()
        elif kind == "COMMAND_LONG":
            result = mav2.MAV_RESULT_UNSUPPORTED
            if msg.command == mav2.MAV_CMD_COMPONENT_ARM_DISARM and msg.param1 == 1:
                result = mav2.MAV_RESULT_FAILED
                due = self.clock.monotonic() + self.text_delay
                self.texts.append((due, "PreArm: Need 3D Fix"))
            elif msg.command == mav2.MAV_CMD_NAV_TAKEOFF:
                ok = self.armed and self.mode == GUIDED
                result = mav2.MAV_RESULT_ACCEPTED if ok else mav2.MAV_RESULT_FAILED
            elif msg.command == mav2.MAV_CMD_DO_SET_MODE:
                self.mode_commands += 1
                wanted = int(msg.param2)
                if wanted in MODES_NEEDING_GPS and not self.gps:
                    result = mav2.MAV_RESULT_FAILED
                else:
                    self.mode, result = wanted, mav2.MAV_RESULT_ACCEPTED
            ack = self.mav.command_ack_encode(msg.command, result)
            ack.target_system, ack.target_component = msg.get_srcSystem(), msg.get_srcComponent()
            self.send(ack)
        elif kind in ("PARAM_REQUEST_READ", "PARAM_SET"):
            name = msg.param_id
            if name not in self.params:
                return
            if kind == "PARAM_SET":
                self.params[name][0] = float(msg.param_value)
            value, ptype = self.params[name]
            index = list(self.params).index(name)
            self.send(self.mav.param_value_encode(name.encode(), value, ptype, 3, index))


@pytest.fixture
def autopilot(clock: ManualClock) -> Iterator[tuple[Autopilot, MavlinkDriver]]:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    d = MavlinkDriver(
        "quad",
        link=f"udpin:127.0.0.1:{port}",
        clock=clock,
        init_timeout=2.0,
        command_timeout=0.3,
        command_retries=1,
        stream_rate=0,  # the emulator streams only what it streams by itself
        gcs_failsafe={"enable": 5, "timeout": 3},
    )
    with Autopilot(clock, port) as ap:
        try:
            yield ap, d
        finally:
            d.shutdown()


def test_emulator_safe_state_on_the_ground_and_in_the_air(
    autopilot: tuple[Autopilot, MavlinkDriver], clock: ManualClock
) -> None:
    ap, d = autopilot
    configure(d, clock)
    assert [ap.params[n][0] for n in ("FS_GCS_ENABLE", "FS_GCS_TIMEOUT")] == [5.0, 3.0]
    d.activate()
    assert d.make_safe("test") == "vehicle on the ground: disarmed, nothing to do"
    with ap.lock:
        ap.armed = True
    run_until(clock, lambda: d.telemetry().armed, 2.0)
    assert d.make_safe("test") == "vehicle on the ground: armed and landed, nothing sent"
    assert ap.mode_commands == 0
    with ap.lock:
        ap.flying = True
    run_until(clock, lambda: d._landed_state == p.MAV_LANDED_STATE_IN_AIR, 2.0)
    assert d.make_safe("test") == "vehicle LOITER"
    assert ap.mode == LOITER


def test_emulator_a_take_off_not_yet_seen_in_the_air_is_sent_the_safe_mode(
    autopilot: tuple[Autopilot, MavlinkDriver], clock: ManualClock
) -> None:
    # ON_GROUND comes at 2 Hz: after a take-off it may describe a vehicle already leaving the
    # ground (the exit-path CI run: SIGINT at lift-off, "nothing sent", the climb went on)
    ap, d = autopilot
    configure(d, clock)
    d.activate()
    with ap.lock:
        ap.armed, ap.mode = True, GUIDED
    run_until(clock, lambda: d.telemetry().armed and d.telemetry().mode == "GUIDED", 2.0)
    ticking(clock, lambda: d.takeoff(10.0))
    after = clock.monotonic()
    run_until(clock, lambda: d._landed_at is not None and d._landed_at > after, 2.0)
    assert d._landed_state == p.MAV_LANDED_STATE_ON_GROUND  # what the vehicle says
    assert d.make_safe("test") == "vehicle LOITER"
    assert ap.mode == LOITER
    # once seen in the air and landed again, "on the ground" is believed
    d.activate()
    with ap.lock:
        ap.flying = True
    run_until(clock, lambda: d._landed_state == p.MAV_LANDED_STATE_IN_AIR, 2.0)
    with ap.lock:
        ap.flying = False
    run_until(clock, lambda: d._landed_state == p.MAV_LANDED_STATE_ON_GROUND, 2.0)
    commands = ap.mode_commands
    assert d.make_safe("test") == "vehicle on the ground: armed and landed, nothing sent"
    assert ap.mode_commands == commands


def test_emulator_without_gps_refuses_loiter_and_is_landed(
    autopilot: tuple[Autopilot, MavlinkDriver], clock: ManualClock
) -> None:
    ap, d = autopilot
    ap.gps = False
    configure(d, clock)
    with ap.lock:
        ap.armed = ap.flying = True
    run_until(clock, lambda: d._landed_state == p.MAV_LANDED_STATE_IN_AIR, 2.0)
    assert d.make_safe("test") == "vehicle LAND (LOITER refused: MAV_RESULT_FAILED)"
    assert ap.mode == LAND


@pytest.mark.parametrize(("delay", "attached"), [(0.02, True), (0.3, True), (0.8, False)])
def test_emulator_prearm_text_after_the_ack(
    autopilot: tuple[Autopilot, MavlinkDriver], clock: ManualClock, delay: float, attached: bool
) -> None:
    ap, d = autopilot
    ap.text_delay = delay
    configure(d, clock)
    d.activate()
    errors: list[MavlinkCommandError] = []

    def arm() -> None:
        with pytest.raises(MavlinkCommandError) as info:
            d.arm()
        errors.append(info.value)

    ticking(clock, arm)
    (error,) = errors
    assert error.result == p.MAV_RESULT_FAILED
    assert ("PreArm: Need 3D Fix" in str(error)) is attached
    run_until(clock, lambda: "PreArm: Need 3D Fix" in d.telemetry().status_texts, 2.0)


@pytest.mark.parametrize(
    ("flying", "mode", "armed"), [(True, LAND, True), (False, STABILIZE, False)]
)
def test_emulator_gcs_failsafe_when_the_driver_dies(
    autopilot: tuple[Autopilot, MavlinkDriver],
    clock: ManualClock,
    flying: bool,
    mode: int,
    armed: bool,
) -> None:
    ap, d = autopilot
    configure(d, clock)
    with ap.lock:
        ap.armed, ap.flying = True, flying
    run_until(clock, lambda: ap.gcs_seen is not None and clock.monotonic() > 2.0, 3.0)
    kill(d)
    took = run_until(clock, lambda: ap.failsafe, 5.0)
    assert 3.0 - d.heartbeat_period < took <= 3.0 + d.heartbeat_period
    assert (ap.mode, ap.armed) == (mode, armed)
