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
