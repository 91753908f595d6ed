"""The simulated vehicle's link at each realism level: how often a stream looks stale.

The driver calls GLOBAL_POSITION_INT or ATTITUDE stale when none arrived for 3 of its periods
(0.3 s at the profiles' 10 Hz). A ``SimVehicle`` (not started: no socket, no threads) streams
those two at 10 Hz and the heartbeat at 1 Hz through its own realism path (the telemetry's lost
frames, the link's jitter and stalls kept in order, as its step loop does) for some virtual
hours on a manual clock, model step by model step; each batch's arrival is its release time.
The metrics are, per level: the stale events per virtual hour, counted as the driver judges
them (a batch of the vehicle's frames arrives while one of the two streams has been silent for
more than 3 periods: a stall that holds everything back is no stale stream), the share of frames
lost, and the p99 of the departure of a stream's inter-arrival time from its period among the
frames about one period apart (the jitter a receiver sees; lost frames and the bursts after a
stall left out). The seed is fixed, so a run repeats exactly.
"""

from __future__ import annotations

import itertools
import math
import struct
from collections.abc import Mapping

from bench.common import Results, percentile
from temoto.clock import ManualClock
from temoto.drivers.can_motor import cansimple as cs
from temoto.drivers.can_motor.sim import AxisModel, SimODrive
from temoto.drivers.mavlink import protocol as p
from temoto.drivers.mavlink.sim import DEFAULT_RATES, SimVehicle

SEED = 2026
STALE_PERIODS = 3
RATE_HZ = 10.0
SUPERVISED = ("GLOBAL_POSITION_INT", "ATTITUDE")


def _msg_id(frame: bytes) -> int:
    """The message id of a MAVLink 2 frame (bytes 7..9, little-endian)."""
    low, high = struct.unpack_from("<HB", frame, 7)
    return int(low | high << 16)


def _run(level: str, hours: float) -> Mapping[str, float]:
    sim = SimVehicle("quad", clock=ManualClock(), realism=level, seed=SEED)
    for name in DEFAULT_RATES:
        sim.telemetry.set_rate(name, 0.0)
    sim.telemetry.set_rate("HEARTBEAT", 1.0)
    for name in SUPERVISED:
        sim.telemetry.set_rate(name, RATE_HZ)
    ids = {p.MSG_ID[name]: name for name in SUPERVISED}
    last: dict[str, float] = {}
    gaps: dict[str, list[float]] = {name: [] for name in SUPERVISED}
    stale_events = 0
    flagged: set[str] = set()  # streams already counted stale in their current gap
    max_age = STALE_PERIODS / RATE_HZ
    dt = sim.state.dt
    steps = round(hours * 3600 / dt)
    with sim.state.lock:
        for i in range(steps):
            now = i * dt
            while sim._held and sim._held[0][0] <= now:  # what the step loop would have sent
                sim._held.popleft()
            before = len(sim._held)
            frames = sim._delayed(sim.telemetry.streams(now), now)
            arrival = now
            if len(sim._held) > before:  # held back: it arrives at its release
                arrival, frames = sim._held[-1]
            if not frames:
                continue
            for frame in frames:  # a batch arrives at once: the driver reads it all
                name = ids.get(_msg_id(frame))
                if name is None:
                    continue
                if name in last:
                    gaps[name].append(arrival - last[name])
                last[name] = arrival
                flagged.discard(name)
            for stream, seen in last.items():  # the driver's rule: the vehicle talks...
                if arrival - seen > max_age and stream not in flagged:
                    stale_events += 1  # ...but not this stream
                    flagged.add(stream)
    period = 1.0 / RATE_HZ
    every = [g for name in SUPERVISED for g in gaps[name]]
    sent = len(every) + len(SUPERVISED)
    lost = sum(sim.telemetry.lost.get(name, 0) for name in SUPERVISED)
    # one period apart (not a lost frame's double gap, nor a burst after a stall)
    deviation = [abs(g - period) for g in every if 0.5 * period < g < 1.5 * period]
    return {
        "stale_per_hour": stale_events / hours,
        "lost_pct": 100.0 * lost / (sent + lost),
        "jitter_p99_ms": 1000.0 * percentile(deviation, 99) if deviation else math.nan,
    }


def _add_stale(res: Results, name: str, level: str, per_hour: float, conditions: str) -> None:
    """A level's stale events per hour; at ``typical`` the goal is at most 0.5 an hour."""
    res.add(name, per_hour, "1/h", conditions, ("<=", 0.5) if level == "typical" else None)


def bench_realism(quick: bool) -> Results:
    """Stale events, lost frames and jitter of the vehicle's supervised streams per level."""
    res = Results()
    hours = {"off": 0.25, "typical": 1.0 if quick else 10.0, "harsh": 0.5 if quick else 2.0}
    for level, span in hours.items():
        got = _run(level, span)
        _add_stale(
            res,
            f"realism_{level}_stale_per_hour",
            level,
            got["stale_per_hour"],
            f"{span:g} virtual h, GLOBAL_POSITION_INT and ATTITUDE at 10 Hz, > 0.3 s silent",
        )
        res.add(f"realism_{level}_lost_pct", got["lost_pct"], "%")
        res.add(f"realism_{level}_jitter_p99_ms", got["jitter_p99_ms"], "ms")
    res.notes.append(f"seed {SEED}; a virtual clock, model steps of 20 ms, no socket")
    _add_can(res, quick)
    return res


# ---- CAN: an ODrive axis's encoder estimates at each level --------------------------------------

CAN_PERIOD = 0.01  # s: ODrive 0.6's default encoder_msg_rate_ms
#: The ODrive driver over a real bus: stale after 3 periods, at two looks a tenth of a period
#: apart (``temoto/drivers/can_motor/odrive.py``, ``_judge_streams``).
CAN_STALE = 3.1 * CAN_PERIOD


def _run_can(level: str, hours: float) -> Mapping[str, float]:
    """One ODrive axis's cyclic frames for ``hours`` of virtual time, through the tick loop."""
    clock = ManualClock()
    link = {"interface": "virtual", "channel": "bench-realism"}  # never opened
    sim = SimODrive(link, [AxisModel(1)], clock, realism=level, seed=SEED)
    enc = int(cs.Cmd.GET_ENCODER_ESTIMATES)
    arrivals: list[float] = []
    sent = [0]

    def send(aid: int, data: bytes, node: int) -> None:
        sent[0] += 1
        if cs.split_id(aid)[1] == enc:
            arrivals.append(clock.monotonic())

    sim.send = send  # type: ignore[method-assign]
    end, due = hours * 3600.0, 0.0
    while True:  # the simulator's tick loop, on the virtual clock
        now = clock.monotonic()
        if now >= due:
            sim.on_tick(now)
            due = max(due + sim.tick, now)
        wake = min(due, sim.send_due(now))
        if wake > end:
            break
        clock.set(wake)
    gaps = [b - a for a, b in itertools.pairwise(arrivals)]
    deviation = [abs(g - CAN_PERIOD) for g in gaps if 0.5 * CAN_PERIOD < g < 1.5 * CAN_PERIOD]
    return {
        "stale_per_hour": sum(1 for g in gaps if g > CAN_STALE) / hours,
        "late_pct": 100.0 * sim.transmitter.stalls / max(sent[0], 1),
        "jitter_p99_ms": 1000.0 * percentile(deviation, 99) if deviation else math.nan,
        "longest_gap_ms": 1000.0 * max(gaps, default=math.nan),
    }


def _add_can(res: Results, quick: bool) -> None:
    """Stale events, late frames and jitter of an ODrive's encoder estimates per level."""
    hours = {"off": 0.02, "typical": 0.1 if quick else 1.0, "harsh": 0.05 if quick else 0.5}
    for level, span in hours.items():
        got = _run_can(level, span)
        _add_stale(
            res,
            f"realism_{level}_can_stale_per_hour",
            level,
            got["stale_per_hour"],
            f"{span:g} virtual h, an ODrive's encoder estimates at 100 Hz, > 31 ms silent",
        )
        res.add(f"realism_{level}_can_late_pct", got["late_pct"], "%")
        res.add(f"realism_{level}_can_jitter_p99_ms", got["jitter_p99_ms"], "ms")
        res.add(f"realism_{level}_can_longest_gap_ms", got["longest_gap_ms"], "ms")
    res.notes.append(
        f"CAN: seed {SEED}; one SimODrive axis, heartbeats 100 ms, estimates 10 ms, its tick"
        " loop on a virtual clock, no bus"
    )
