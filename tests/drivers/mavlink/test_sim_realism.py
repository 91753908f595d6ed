"""An imperfect world on request: the realism model and the simulated ArduCopter under it.

``off`` keeps the exact figures; ``typical`` and ``harsh`` add seeded noise to what the vehicle
reports (never to its true state), lose streamed frames, and delay what it sends (jitter, stalls),
in order. At ``typical`` the driver's supervision sees no fault and a flight ends as asked; at
``harsh`` a flight ends, landed or with a clear fault, within its deadline. On virtual time.
"""

from __future__ import annotations

import logging
import math
import statistics
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest

from temoto.clock import ManualClock
from temoto.drivers import DriverState, GeoPoint, Health
from temoto.drivers.mavlink import MavlinkDriver, SimVehicle
from temoto.drivers.mavlink import protocol as p
from temoto.drivers.mavlink.protocol import Codec
from temoto.drivers.realism import LEVELS, QUANTITIES, Realism, derive_seed, realism_level
from temoto.drivers.sim import Simulator
from temoto.errors import DriverError, ProfileError

HOME = (47.397742, 8.545594, 488.0)
GCS = Codec(255, 190)


# ---- the model -----------------------------------------------------------------------------------


def _draws(r: Realism, n: int = 50) -> list[float]:
    out: list[float] = []
    for i in range(n):
        out.append(r.noise("position", 0.0))
        out.append(float(r.lost()))
        out.append(r.delay(reply=i % 2 == 1))
    return out


def test_the_same_seed_and_device_replay_the_same_numbers() -> None:
    first = _draws(Realism("typical", seed=1234, device="quad"))
    assert first == _draws(Realism("typical", seed=1234, device="quad"))
    assert first != _draws(Realism("typical", seed=1235, device="quad"))
    assert first != _draws(Realism("typical", seed=1234, device="quad2"))  # each device its own
    # stable across processes (not Python's salted hash()): a fixed value
    assert derive_seed(1234, "quad", "noise") == derive_seed(1234, "quad", "noise")
    assert derive_seed(1234, "quad", "noise") != derive_seed(1234, "quad", "link")


def test_a_lost_frame_does_not_shift_the_noise_that_follows() -> None:
    a, b = Realism("harsh", seed=5, device="x"), Realism("harsh", seed=5, device="x")
    noise_a = [a.noise("altitude", 1.0) for _ in range(20)]
    noise_b = []
    for _ in range(20):
        b.lost()
        b.delay()
        noise_b.append(b.noise("altitude", 1.0))
    assert noise_a == noise_b


def test_off_is_exact_and_draws_nothing() -> None:
    r = Realism("off", seed=9, device="quad")
    assert not r.enabled
    assert r.seed is None
    assert r.describe() == "realism off"
    for quantity in QUANTITIES:
        assert r.noise(quantity, 1.2345) == 1.2345
    assert not any(r.lost() for _ in range(1000))
    assert r.delay() == 0.0
    assert r.delay(reply=True) == 0.0


def test_a_level_without_a_seed_picks_one_to_print() -> None:
    r = Realism("typical", device="quad")
    assert isinstance(r.seed, int)
    assert r.seed >= 0
    assert r.describe() == f"realism typical, seed {r.seed}"


@pytest.mark.parametrize("level", ["typical", "harsh"])
def test_the_rates_are_the_documented_ones(level: str) -> None:
    figures = LEVELS[level]
    r = Realism(level, seed=42, device="stats")
    n = 20_000
    for quantity in ("position", "altitude", "attitude"):
        samples = [r.noise(quantity, 10.0) for _ in range(n)]
        assert statistics.fmean(samples) == pytest.approx(10.0, abs=4 * figures.sigma[quantity])
        assert statistics.pstdev(samples) == pytest.approx(figures.sigma[quantity], rel=0.05)
    lost = sum(r.lost() for _ in range(200_000)) / 200_000
    assert lost == pytest.approx(figures.drop, rel=0.2)
    delays = [r.delay() for _ in range(100_000)]
    stalls = [d for d in delays if d >= figures.late_delay[0]]
    # a stall is at least late_delay[0]; jitter alone that long is > 5 sigma
    assert len(stalls) / len(delays) == pytest.approx(figures.late, rel=0.3)
    assert max(delays) <= figures.late_delay[1] + 6 * figures.jitter
    jitter = [d for d in delays if d < figures.late_delay[0]]
    # half-normal: mean sigma * sqrt(2/pi)
    assert statistics.fmean(jitter) == pytest.approx(
        figures.jitter * math.sqrt(2 / math.pi), rel=0.05
    )


def test_bad_levels_and_seeds_are_refused() -> None:
    with pytest.raises(ValueError, match="realism must be one of off, typical, harsh, got 'wild'"):
        realism_level("wild")
    with pytest.raises(ValueError, match="seed"):
        Realism("typical", seed=-1)
    with pytest.raises(ValueError, match="seed"):
        Realism("typical", seed=True)  # type: ignore[arg-type]
    with pytest.raises(KeyError, match="not a realism quantity"):
        Realism("typical", seed=1).noise("colour", 1.0)


# ---- the vehicle's frames --------------------------------------------------------------------


def _vehicle(realism: str, seed: int | None = 77) -> SimVehicle:
    sim = SimVehicle("quad", clock=ManualClock(), home=HOME, realism=realism, seed=seed)
    sim.state.pos[:] = [3.0, -4.0, 12.0]
    sim.state.vel[:] = [1.5, 0.5, -0.2]
    sim.state.yaw = 0.7
    return sim


def _stream(sim: SimVehicle, seconds: float = 20.0) -> list[bytes]:
    """Every frame the telemetry streams over ``seconds`` of model steps (no threads)."""
    frames: list[bytes] = []
    steps = round(seconds / sim.state.dt)
    with sim.state.lock:
        for i in range(steps):
            frames += sim.telemetry.streams(i * sim.state.dt)
    return frames


def _messages(frames: list[bytes], name: str) -> list[dict[str, Any]]:
    return [m.fields for f in frames for m in GCS.decode_datagram(f) if m.name == name]


def test_off_reports_the_exact_state() -> None:
    sim = _vehicle("off")
    assert not sim.realism.enabled
    frames = _stream(sim, 5.0)
    lat, lon, _up = sim.state.geo(sim.state.pos)
    positions = _messages(frames, "GLOBAL_POSITION_INT")
    assert len(positions) == 50  # 10 Hz, none lost
    assert {(m["lat"], m["lon"], m["relative_alt"], m["vx"]) for m in positions} == {
        (p.deg_e7(lat), p.deg_e7(lon), 12000, 150)
    }
    attitudes = _messages(frames, "ATTITUDE")
    assert {round(m["yaw"], 6) for m in attitudes} == {0.7}
    assert {m["voltage_battery"] for m in _messages(frames, "SYS_STATUS")} == {16800}
    assert sim.telemetry.lost == {}


def test_typical_noise_is_seeded_and_leaves_the_true_state_alone() -> None:
    one = _stream(_vehicle("typical", seed=77))
    assert one == _stream(_vehicle("typical", seed=77))  # replayed from the seed
    assert one != _stream(_vehicle("typical", seed=78))
    sim = _vehicle("typical", seed=77)
    positions = _messages(_stream(sim), "GLOBAL_POSITION_INT")
    assert sim.state.pos == [3.0, -4.0, 12.0]  # the model is untouched
    alts = [m["relative_alt"] / 1000 for m in positions]
    sigma = LEVELS["typical"].sigma["altitude"]
    assert len(set(alts)) > 100
    assert statistics.fmean(alts) == pytest.approx(
        12.0, abs=3 * sigma / math.sqrt(len(alts)) + 0.01
    )
    assert statistics.pstdev(alts) == pytest.approx(sigma, rel=0.25)
    norths = [(math.radians(m["lat"] / 1e7 - HOME[0])) * 6_378_137.0 for m in positions]
    assert statistics.pstdev(norths) == pytest.approx(LEVELS["typical"].sigma["position"], rel=0.25)
    assert max(abs(n - 3.0) for n in norths) < 6 * LEVELS["typical"].sigma["position"]


def test_harsh_loses_streamed_frames_at_its_rate() -> None:
    sim = _vehicle("harsh", seed=3)
    frames = _stream(sim, 60.0)
    sent = len(_messages(frames, "GLOBAL_POSITION_INT"))
    lost = sim.telemetry.lost.get("GLOBAL_POSITION_INT", 0)
    assert sent + lost == 600  # the schedule goes on: a lost frame is not sent later
    assert 0 < lost < 600 * LEVELS["harsh"].drop * 2.5
    assert sum(sim.telemetry.lost.values()) > lost  # every stream loses frames, heartbeats too


# ---- on the wire: delayed in order ---------------------------------------------------------


#: Real seconds the vehicle and the driver may take to catch up with one step of the clock.
SETTLE = 10.0


def _settled(sim: SimVehicle, driver: MavlinkDriver | None) -> bool:
    """The vehicle did all that was due, and the driver's socket holds nothing unread."""
    link = None if driver is None else driver._link
    return sim.settled() and (link is None or not link.pending())


def settle(sim: SimVehicle, driver: MavlinkDriver | None = None) -> None:
    """Wait (real time) until :func:`_settled`: the clock moves on only when both kept up.

    A thread that moves a virtual clock on its own runs it tens of times faster than real
    time; on a loaded machine the vehicle's step thread can then miss several of its frames'
    times in one go, and the driver would rightly call a stream stale.
    """
    deadline = time.monotonic() + SETTLE
    while not _settled(sim, driver):
        assert time.monotonic() < deadline, f"the vehicle did not keep up in {SETTLE} real s"
        time.sleep(0.0005)


def run_until(
    clock: ManualClock,
    pred: Callable[[], bool],
    seconds: float,
    step: float = 0.02,
    *,
    sim: SimVehicle,
    driver: MavlinkDriver | None = None,
) -> float:
    """Advance virtual time in ``step``s, in step with ``sim`` (and ``driver``), until ``pred()``.

    Returns:
        The virtual seconds it took.
    """
    start = clock.monotonic()
    while not pred():
        assert clock.monotonic() - start <= seconds, f"not within {seconds} virtual s"
        settle(sim, driver)
        clock.advance(step)
        time.sleep(0.0007)
    return clock.monotonic() - start


def test_the_link_delays_frames_but_keeps_their_order() -> None:
    import socket

    clock = ManualClock()
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(0.0)
    sim = SimVehicle(
        "quad", clock=clock, gcs=[rx.getsockname()], realism="harsh", seed=11, home=HOME
    )
    got: list[tuple[float, int]] = []  # (clock when read, time_boot_ms)

    def drain() -> None:
        while True:
            try:
                data = rx.recv(4096)
            except BlockingIOError:
                return
            for m in GCS.decode_datagram(data):
                if m.name == "GLOBAL_POSITION_INT":
                    got.append((clock.monotonic(), m.fields["time_boot_ms"]))

    sim.start()
    try:
        start = clock.monotonic()

        def enough() -> bool:
            drain()
            return clock.monotonic() - start >= 30.0

        run_until(clock, enough, 31.0, step=0.01, sim=sim)
    finally:
        sim.close()
        rx.close()
    stamps = [ms for _, ms in got]
    assert stamps == sorted(stamps)  # in order, stalls included
    assert 250 < len(stamps) < 300  # 10 Hz, a few lost
    # a stall holds frames back: some arrive much later than they were built
    ages = [t - ms / 1000 for t, ms in got]
    assert max(ages) - min(ages) >= LEVELS["harsh"].late_delay[0]


# ---- the driver: supervision and flights ---------------------------------------------------


def _make(clock: ManualClock, realism: str, seed: int) -> tuple[SimVehicle, MavlinkDriver]:
    config = {
        "link": "udpin:127.0.0.1:14550",
        "init_timeout": 2.0,
        "command_timeout": 0.5,
        "command_retries": 2,
        "sim": {
            "home": list(HOME),
            "speed": 8.0,
            "climb_rate": 4.0,
            "descent_rate": 3.0,
            "tau": 0.5,
            "realism": realism,
            "seed": seed,
        },
    }
    sim, settings = MavlinkDriver.simulate("quad", config, clock=clock)
    assert isinstance(sim, SimVehicle)
    driver = MavlinkDriver.from_profile("quad", settings, clock=clock, where="devices.quad")
    return sim, driver


def _ticking(
    clock: ManualClock, sim: SimVehicle, driver: MavlinkDriver, fn: Callable[[], Any]
) -> Any:
    """Call ``fn`` while a thread advances virtual time (20 ms a step, in step with both ends)."""
    done = threading.Event()

    def tick() -> None:
        while not done.wait(0.001):
            if _settled(sim, driver):
                clock.advance(0.02)

    ticker = threading.Thread(target=tick, name="temoto-test-ticker")
    ticker.start()
    try:
        return fn()
    finally:
        done.set()
        ticker.join()


@pytest.fixture
def flown() -> Iterator[
    Callable[[str, int], tuple[SimVehicle, MavlinkDriver, ManualClock, list[Health]]]
]:
    made: list[tuple[SimVehicle, MavlinkDriver]] = []

    def start(
        realism: str, seed: int
    ) -> tuple[SimVehicle, MavlinkDriver, ManualClock, list[Health]]:
        clock = ManualClock()
        sim, driver = _make(clock, realism, seed)
        made.append((sim, driver))
        sim.start()
        _ticking(clock, sim, driver, driver.configure)
        driver.activate()
        health: list[Health] = []
        driver.add_health_listener(health.append)
        return sim, driver, clock, health

    yield start
    for sim, driver in made:
        driver.shutdown()
        sim.close()


def _distance(a: GeoPoint, b: GeoPoint) -> float:
    north = math.radians(a.lat - b.lat) * 6_378_137.0
    east = math.radians(a.lon - b.lon) * 6_378_137.0 * math.cos(math.radians(a.lat))
    return math.hypot(north, east)


def test_typical_supervision_sees_no_false_fault_and_a_flight_ends_as_asked(
    flown: Callable[[str, int], tuple[SimVehicle, MavlinkDriver, ManualClock, list[Health]]],
) -> None:
    sim, d, clock, health = flown("typical", 2026)
    tel = d.telemetry
    run_until(clock, lambda: clock.monotonic() >= 60.0, 61.0, sim=sim, driver=d)  # a minute idle
    assert d.state is DriverState.ACTIVE
    assert health == []
    assert sim.realism.seed == 2026
    assert sum(sim.telemetry.lost.values()) > 0  # frames were lost, none noticed as a fault

    # the replies are delayed too: the clock must run while a command waits for its ack
    _ticking(clock, sim, d, d.arm)
    run_until(clock, lambda: tel().armed, 3.0, sim=sim, driver=d)
    _ticking(clock, sim, d, lambda: d.takeoff(10.0))
    run_until(clock, lambda: sim.pos[2] > 9.9, 20.0, sim=sim, driver=d)
    # what the driver hears is noisy: it is not the model's exact altitude
    heard = set()
    for _ in range(20):
        settle(sim, d)
        clock.advance(0.1)
        settle(sim, d)
        heard.add(round(tel().position.alt, 3))
    assert len(heard) > 3
    target = GeoPoint(HOME[0] + 0.0004, HOME[1] + 0.0003, 15.0)  # ~51 m away
    _ticking(clock, sim, d, lambda: d.goto(target))
    run_until(
        clock, lambda: _distance(tel().position, target) < 1.0, 40.0, sim=sim, driver=d
    )  # a FlyTo tolerance
    _ticking(clock, sim, d, d.land)
    run_until(clock, lambda: not tel().armed, 60.0, sim=sim, driver=d)
    assert tel().position.alt == pytest.approx(0.0, abs=1.5)
    assert _distance(GeoPoint(*sim.position()), GeoPoint(target.lat, target.lon, 0)) < 1.0
    assert d.state is DriverState.ACTIVE
    assert health == [], [h.error for h in health]


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_harsh_ends_a_flight_landed_or_with_a_clear_fault_never_a_hang(
    flown: Callable[[str, int], tuple[SimVehicle, MavlinkDriver, ManualClock, list[Health]]],
    seed: int,
) -> None:
    sim, d, clock, health = flown("harsh", seed)
    tel = d.telemetry

    def faulted() -> bool:
        return d.state is DriverState.FAULT

    def step(action: Callable[[], None], done: Callable[[], bool], seconds: float) -> bool:
        """Run ``action``, then wait for ``done`` or a fault; False once the driver faulted."""
        if faulted():
            return False
        try:
            _ticking(clock, sim, d, action)
        except DriverError:
            assert faulted() or health, "a command failed without a fault"
            return False
        run_until(clock, lambda: done() or faulted(), seconds, sim=sim, driver=d)
        return not faulted()

    flew = (
        step(d.arm, lambda: tel().armed, 5.0)
        and step(lambda: d.takeoff(8.0), lambda: sim.pos[2] > 7.9, 20.0)
        and step(
            lambda: d.goto(GeoPoint(HOME[0] + 0.0002, HOME[1], 8.0)),
            lambda: _distance(tel().position, GeoPoint(HOME[0] + 0.0002, HOME[1], 8.0)) < 1.5,
            30.0,
        )
        and step(d.land, lambda: not tel().armed, 60.0)
    )
    if flew:
        assert not sim.armed
        assert sim.pos[2] == pytest.approx(0.0, abs=0.01)
    else:
        errors = [h.error for h in health if h.error is not None]
        assert errors, "the flight stopped without a fault"
        text = str(errors[0])
        assert text.startswith("quad: "), text
        assert "stale" in text or "heartbeat" in text, text


def test_the_profile_keys_are_checked() -> None:
    clock = ManualClock()
    for sim_cfg, match in (
        ({"realism": "wild"}, r"sim\.realism: must be one of off, typical, harsh, got 'wild'"),
        ({"seed": -3}, r"sim\.seed: must be a non-negative integer, got -3"),
        ({"seed": 1.5}, r"sim\.seed: must be a non-negative integer"),
    ):
        with pytest.raises(ProfileError, match=match):
            MavlinkDriver.simulate(
                "quad", {"link": "udpin:127.0.0.1:1", "sim": sim_cfg}, clock=clock
            )
    sim, _ = MavlinkDriver.simulate(
        "quad", {"link": "udpin:127.0.0.1:1", "sim": {"realism": "harsh", "seed": 8}}, clock=clock
    )
    assert isinstance(sim, SimVehicle)
    assert sim.realism.level is LEVELS["harsh"]
    assert sim.realism.seed == 8
    default, _ = MavlinkDriver.simulate("quad", {"link": "udpin:127.0.0.1:1"}, clock=clock)
    assert isinstance(default, SimVehicle)
    assert not default.realism.enabled


def test_the_vehicle_logs_its_level_and_seed_so_a_run_can_be_replayed(
    caplog: pytest.LogCaptureFixture,
) -> None:
    with caplog.at_level(logging.INFO, logger="temoto.drivers.mavlink.sim"):
        SimVehicle("quad", clock=ManualClock(), realism="typical", seed=5)
        SimVehicle("quiet", clock=ManualClock())
    assert [r.getMessage() for r in caplog.records] == ["quad: realism typical, seed 5"]


def test_every_simulator_has_a_realism_off_by_default() -> None:
    class Bare(Simulator):
        def start(self) -> None:
            pass

        def close(self) -> None:
            pass

    bare = Bare()
    assert not bare.realism.enabled
    assert bare.realism.describe() == "realism off"
