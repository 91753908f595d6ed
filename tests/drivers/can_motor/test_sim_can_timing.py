"""The CAN simulators' transmit timing at each realism level: jitter and late frames.

The figures are ``temoto.drivers.realism.CAN_TIMING`` (``docs/simulators.md``, "Realism"): at
``typical`` and ``harsh`` an ODrive's cyclic frames and a MIT motor's replies leave after a
half-normal jitter, and now and then a late frame stalls the node (its later frames wait
behind it, in order); ``off`` sends every frame at its scheduled time, exactly. Each test runs
the simulator's own tick loop step by step on a manual clock (no thread, no bus): the virtual
time moves to the next tick or held frame, so the figures are exact and repeat from the seed.
"""

from __future__ import annotations

import itertools
import statistics
import uuid
from typing import Any

import can
import pytest

from temoto.clock import ManualClock
from temoto.drivers.can_motor import cansimple as cs
from temoto.drivers.can_motor import mitmode as mm
from temoto.drivers.can_motor.sim import AxisModel, MitModel, SimMitMotor, SimODrive
from temoto.drivers.can_motor.sim_bus import CanDeviceSim
from temoto.drivers.realism import CAN_TIMING

ENC = int(cs.Cmd.GET_ENCODER_ESTIMATES)
HB = int(cs.Cmd.HEARTBEAT)
PERIOD = 0.01  # s: the encoder estimates' default rate
HALF_NORMAL_MEDIAN = 0.6745  # the median of |N(0, sigma)| in sigma


def link() -> dict[str, Any]:
    return {"interface": "virtual", "channel": f"timing-{uuid.uuid4().hex[:8]}"}


class Wire:
    """What a simulator sends and when; what its transmitter was asked (ready → release)."""

    def __init__(self, sim: CanDeviceSim, clock: ManualClock) -> None:
        self.sent: list[tuple[float, int, bytes]] = []  # (clock time, arbitration id, data)
        self.asked: list[tuple[float, float]] = []  # (ready, release)
        sim.send = lambda aid, data, node: self.sent.append(  # type: ignore[method-assign]
            (clock.monotonic(), aid, bytes(data))
        )
        transmitter = getattr(sim, "transmitter", None)
        if transmitter is not None:
            release = transmitter.release

            def logged(node: int, ready: float, *, reply: bool = False) -> float:
                at = release(node, ready, reply=reply)
                self.asked.append((ready, at))
                return float(at)

            transmitter.release = logged

    def times(self, cmd: int | None = None) -> list[float]:
        return [t for t, aid, _ in self.sent if cmd is None or cs.split_id(aid)[1] == cmd]

    def delays(self) -> list[float]:
        return [at - ready for ready, at in self.asked]


def held_next(sim: CanDeviceSim, now: float) -> float:
    """The simulator's held frames due by ``now`` sent; when its next one is due."""
    send_due = getattr(sim, "send_due", None)
    return float(send_due(now)) if send_due is not None else float("inf")


def run_odrive(seconds: float, **kwargs: Any) -> tuple[SimODrive, Wire]:
    """An ODrive axis streaming (heartbeats 100 ms, estimates 10 ms) for ``seconds``."""
    clock = ManualClock()
    sim = SimODrive(link(), [AxisModel(1)], clock, **kwargs)
    wire = Wire(sim, clock)
    due = 0.0
    while True:  # the tick thread's loop, step by step
        now = clock.monotonic()
        if now >= due:
            sim.on_tick(now)
            due = max(due + sim.tick, now)
        wake = min(due, held_next(sim, now))
        if wake > seconds:
            return sim, wire
        clock.set(wake)


def gaps(times: list[float]) -> list[float]:
    return [b - a for a, b in itertools.pairwise(times)]


def test_odrive_streams_at_off_leave_exactly_on_their_periods() -> None:
    sim, wire = run_odrive(10.0)
    enc, hb = wire.times(ENC), wire.times(HB)
    assert len(enc) == 1001
    assert len(hb) == 101
    assert all(abs(g - PERIOD) < 1e-9 for g in gaps(enc))
    assert all(abs(g - 0.1) < 1e-9 for g in gaps(hb))
    assert all(at == ready for ready, at in wire.asked)
    assert sim.transmitter.stalls == 0


@pytest.mark.parametrize("level", ["typical", "harsh"])
def test_odrive_streams_jitter_and_now_and_then_a_frame_is_late(level: str) -> None:
    timing = CAN_TIMING[level]
    seconds = 60.0
    sim, wire = run_odrive(seconds, realism=level, seed=2026)
    delays = wire.delays()
    made = round(seconds / PERIOD) + round(seconds / 0.1)  # cyclic frames made and not lost
    assert len(delays) == made - sim.frames_lost + 2
    # every frame leaves when the transmitter said, never before it was made, in order
    sent = [t for t, _, _ in wire.sent]
    assert sent == [at for _, at in wire.asked][: len(sent)]
    assert len(wire.asked) - len(sent) <= 2  # the last tick's, still held at the end
    assert all(d >= 0 for d in delays)
    assert wire.times() == sorted(wire.times())
    # the jitter: half-normal, its median 0.67 sigma
    median = statistics.median(delays) / (HALF_NORMAL_MEDIAN * timing.jitter)
    assert 0.8 < median < 1.2
    # late frames at the level's share (binomial: within a factor two of ~70 or ~700)
    assert 0.5 * timing.late * len(delays) < sim.transmitter.stalls < 2 * timing.late * len(delays)
    # a late one: at least the shortest stall; none longer than the longest stall plus jitter and
    # the frame that was ahead of it in the queue
    late = [d for d in delays if d >= timing.late_delay[0]]
    assert len(late) >= sim.transmitter.stalls
    assert max(delays) < timing.late_delay[1] + 8 * timing.jitter + PERIOD
    # the encoder stream: about one period apart, the departure's spread that of two jitters
    enc = [g for g in gaps(wire.times(ENC)) if 0.5 * PERIOD < g < 1.5 * PERIOD]
    spread = statistics.pstdev(enc)
    assert 0.6 * timing.jitter < spread < 1.6 * timing.jitter  # sqrt(2 (1 - 2/pi)) = 0.85 sigma
    # replayed from the seed; another seed, other times
    assert run_odrive(2.0, realism=level, seed=2026)[1].sent == [
        s for s in wire.sent if s[0] <= 2.0
    ]
    assert run_odrive(2.0, realism=level, seed=2027)[1].sent != [
        s for s in wire.sent if s[0] <= 2.0
    ]


def test_typical_never_leaves_an_estimate_stream_silent_for_three_periods() -> None:
    # over a real bus the driver calls estimates stale when none came for 3 periods at two looks
    # a tenth of a period apart (31 ms): typical's late frames (at most 8 ms) and lost ones
    # (0.2 %) together stay below it for 4 virtual minutes
    sim, wire = run_odrive(240.0, realism="typical", seed=7)
    assert sim.transmitter.stalls > 0
    assert sim.frames_lost > 0
    assert max(gaps(wire.times(ENC))) < 3.1 * PERIOD


def run_mit(polls: int, **kwargs: Any) -> tuple[SimMitMotor, Wire, list[float]]:
    """A MIT motor polled every 10 ms (the driver's default rate); the poll times."""
    clock = ManualClock()
    motor = MitModel.of(1, "AK80-9")
    sim = SimMitMotor(link(), [motor], clock, **kwargs)
    wire = Wire(sim, clock)
    frame = mm.encode_command(mm.MitCommand(0.0, 0.0, 0.0, 0.0, 0.0), motor.ranges)
    asked: list[float] = []
    poll = 0.0
    while len(asked) < polls or held_next(sim, clock.monotonic()) < float("inf"):
        now = clock.monotonic()
        if now >= poll and len(asked) < polls:
            sim.on_frame(can.Message(arbitration_id=1, data=frame, is_extended_id=False))
            asked.append(now)
            poll += PERIOD
        wake = min(poll if len(asked) < polls else float("inf"), held_next(sim, now))
        if wake == float("inf"):
            break
        clock.set(wake)
    return sim, wire, asked


def test_mit_replies_at_off_leave_at_once() -> None:
    sim, wire, asked = run_mit(500)
    assert wire.times() == asked
    assert sim.transmitter.stalls == 0


@pytest.mark.parametrize("level", ["typical", "harsh"])
def test_mit_replies_jitter_and_now_and_then_one_is_late(level: str) -> None:
    timing = CAN_TIMING[level]
    sim, wire, asked = run_mit(6000, realism=level, seed=11)
    times = wire.times()
    assert len(times) == len(asked)  # every poll answered (replies are never lost)
    assert times == sorted(times)
    delays = [t - a for t, a in zip(times, asked, strict=True)]
    assert all(d >= 0 for d in delays)
    median = statistics.median(delays) / (HALF_NORMAL_MEDIAN * timing.jitter)
    assert 0.8 < median < 1.2
    assert 0.5 * timing.late * len(asked) < sim.transmitter.stalls < 2 * timing.late * len(asked)
    assert max(delays) < timing.late_delay[1] + 8 * timing.jitter + PERIOD
    # the driver faults after 3 polls in a row unanswered: a reply is never that late
    assert max(delays) < 3 * PERIOD
    assert run_mit(200, realism=level, seed=11)[1].sent == wire.sent[:200]


@pytest.mark.parametrize("level", ["typical", "harsh"])
def test_odrive_answers_to_requests_never_overtake_a_late_frame(level: str) -> None:
    # one transmit queue per node: an RTR answer queues behind the node's held frames; one
    # that left at once put an old heartbeat after a newer one (CLOSED_LOOP, IDLE,
    # CLOSED_LOOP: "two devices answer as node 1" in a loaded CI run)
    clock = ManualClock()
    sim = SimODrive(link(), [AxisModel(1)], clock, realism=level, seed=7)
    wire = Wire(sim, clock)
    request = can.Message(arbitration_id=(1 << 5) | HB, is_remote_frame=True, is_extended_id=False)
    due, asked, overtaken = 0.0, 0, 0
    while clock.monotonic() < 30.0:
        now = clock.monotonic()
        if now >= due:
            sim.on_tick(now)
            due = max(due + sim.tick, now)
        with sim._cond:
            held = [entry for entry in sim._later if entry[4] == 1]
        if held:  # a frame of node 1 waits: ask for a heartbeat now
            before = len(wire.sent)
            sim.on_frame(request)
            asked += 1
            overtaken += len(wire.sent) > before  # the answer left before the held frame
        clock.set(min(due, held_next(sim, now)))
    assert asked > 100
    assert overtaken == 0
    assert wire.times() == sorted(wire.times())
