"""Dynamixel benchmark: SyncRead + SyncWrite cycles of a 6-servo chain over a pseudo-terminal.

dynamixel-sdk (the client, as in the driver) talks to ``SimDynamixelChain`` on a
pseudo-terminal opened at the 1 Mbaud setting. A pseudo-terminal ignores the baud rate, so this
measures the software path (SDK packet building and parsing, the simulator, the kernel's pty),
not the wire: on a real 1 Mbaud bus the 6 status packets (6 x 21 bytes) and the two instruction
packets add roughly 2 ms of transfer time per cycle, plus each servo's Return Delay Time. The
simulator runs in the same process as the SDK (one GIL), as in the tests.

One cycle = SyncRead of present current, velocity and position (10 bytes each, 6 servos)
+ SyncWrite of 6 goal positions. The rate is the median over 0.25 s windows.
"""

from __future__ import annotations

import time
from typing import Any

from bench.common import Results, median

IDS = tuple(range(1, 7))


def _cycles_per_second(quick: bool) -> tuple[list[float], int]:
    import dynamixel_sdk as dxl

    from temoto.drivers.dynamixel.sim import SimDynamixelChain

    window = 0.25
    duration = 1.0 if quick else 5.0  # quick: the run's 60 s
    rates: list[float] = []
    errors = 0
    with SimDynamixelChain(dict.fromkeys(IDS, "XM430-W350"), name="bench") as sim:
        port: Any = dxl.PortHandler(sim.path)
        if not port.openPort() or not port.setBaudRate(1_000_000):
            raise RuntimeError(f"cannot open {sim.path}")
        try:
            ph: Any = dxl.PacketHandler(2.0)
            read: Any = dxl.GroupSyncRead(port, ph, 126, 10)
            write: Any = dxl.GroupSyncWrite(port, ph, 116, 4)
            for i in IDS:
                read.addParam(i)
                write.addParam(i, [0, 8, 0, 0])
                ph.write1ByteTxRx(port, i, 64, 1)
            end = time.perf_counter() + duration
            while time.perf_counter() < end:
                start, n = time.perf_counter(), 0
                while time.perf_counter() - start < window:
                    if read.txRxPacket() != dxl.COMM_SUCCESS:
                        errors += 1
                    goal = 2048 + (n % 200)
                    for i in IDS:
                        write.changeParam(i, list(goal.to_bytes(4, "little")))
                    if write.txPacket() != dxl.COMM_SUCCESS:
                        errors += 1
                    n += 1
                rates.append(n / (time.perf_counter() - start))
        finally:
            port.closePort()
    return rates, errors


def bench_dynamixel(quick: bool) -> Results:
    """``dxl_syncrw_hz``: SyncRead + SyncWrite cycles per second of 6 simulated servos."""
    out = Results()
    try:
        import dynamixel_sdk  # noqa: F401
    except ImportError:
        out.notes.append("dynamixel-sdk not installed (pip install 'temoto[dynamixel]'): skipped")
        return out
    rates, errors = _cycles_per_second(quick)
    out.add(
        "dxl_syncrw_hz",
        median(rates),
        "Hz",
        f"6 servos, pty at the 1 Mbaud setting (baud ignored), {len(rates)} windows,"
        f" min {min(rates):.0f}, max {max(rates):.0f}, {errors} failed transfers",
        goal=(">=", 100.0),
    )
    return out


# ---- realism: late status packets (issue 30) ---------------------------------------------------

REALISM_SEED = 2026


def _late_polls(level: str, polls: int) -> dict[str, float]:
    """The driver's poll sequence against a chain at ``level``: what times out, what is late.

    Each poll is a SyncRead of present current, velocity and position of the six servos (10
    bytes each); after every tenth good one, a SyncRead of the status (3 bytes) and one of
    Hardware Error Status (1 byte), as the driver polls. Through :class:`SdkPort` with
    dynamixel-sdk's own 34 ms reply timeout (a real adapter's), back to back (no poll period).
    """
    from temoto.clock import ManualClock
    from temoto.drivers.dynamixel import control_table as ct
    from temoto.drivers.dynamixel._sdk import COMM_SUCCESS, SdkPort
    from temoto.drivers.dynamixel.sim import SimDynamixelChain

    ids = list(IDS)
    failed = wrong = longest_run = run = 0
    round_trips: list[float] = []
    with SimDynamixelChain(
        dict.fromkeys(IDS, "XM430-W350"),
        clock=ManualClock(),
        name="bench",
        realism=level,
        seed=REALISM_SEED,
    ) as sim:
        port = SdkPort(sim.path, 1_000_000, reply_timeout=0.034)
        port.open()
        try:
            fast = port.sync_reader(*ct.FAST_READ, ids)
            slow = port.sync_reader(*ct.STATUS_READ, ids)
            errors = port.sync_reader(ct.HARDWARE_ERROR_STATUS.address, 1, ids)
            good = 0
            for _ in range(polls):
                start = time.perf_counter()
                result, _, _ = fast.read()
                round_trips.append(time.perf_counter() - start)
                if result != COMM_SUCCESS:
                    failed += 1
                    run += 1
                    longest_run = max(longest_run, run)
                    continue
                run = 0
                good += 1
                if good % 10 == 0 and slow.read()[0] == COMM_SUCCESS:
                    result, bits, _ = errors.read()
                    wrong += result == COMM_SUCCESS and any(b[0] for b in bits.values())
            late, longest, strays = sim.replies_late, sim.longest_late, port.stray_packets
        finally:
            port.close()
    return {
        "failed_pct": 100.0 * failed / polls,
        "longest_failed_run": float(longest_run),
        "late": float(late),
        "longest_late_ms": 1000.0 * longest,
        "max_round_trip_ms": 1000.0 * max(round_trips),
        "strays": float(strays),
        "wrong": float(wrong),
    }


def bench_dynamixel_realism(quick: bool) -> Results:
    """``dxl_realism_<level>_failed_polls_pct``: polls of a chain at each realism level that fail.

    ``off`` is the baseline: polls that fail on a loaded machine with no realism at all.

    Args:
        quick: 150 polls per level instead of 3000 (some 5 s on a loaded machine).

    Returns:
        Per level the failed polls' share, with the late polls, the longest delay, the longest
        round trip, the late answers dropped and the false hardware errors in the note.
    """
    out = Results()
    try:
        import dynamixel_sdk  # noqa: F401
    except ImportError:
        out.notes.append("dynamixel-sdk not installed (pip install 'temoto[dynamixel]'): skipped")
        return out
    polls = 150 if quick else 3000
    for level in ("off", "typical", "harsh"):  # off: what the machine's load alone fails
        r = _late_polls(level, polls)
        out.add(
            f"dxl_realism_{level}_failed_polls_pct",
            r["failed_pct"],
            "%",
            f"{polls} polls of 6 servos, seed {REALISM_SEED}, 34 ms timeout: {r['late']:.0f} late"
            f" (longest {r['longest_late_ms']:.1f} ms), longest round trip"
            f" {r['max_round_trip_ms']:.1f} ms, at most {r['longest_failed_run']:.0f} failed in a"
            f" row, {r['strays']:.0f} late answers dropped, {r['wrong']:.0f} false hardware errors",
        )
    return out
