"""CAN motor benchmark: a 500 Hz control loop of 8 ODrive axes on python-can's virtual bus.

``ODriveDriver`` drives 8 CANSimple nodes served by ``SimODrive`` in the same process (one GIL),
on a ``virtual`` python-can channel, in real time (``MonotonicClock``). Every 2 ms period the
loop sends a velocity set-point to all 8 axes (8 ``Set_Input_Vel`` frames) and reads the
encoder feedback from the driver's cache (``read_state``); the simulated ODrives send their
encoder estimates cyclically every 2 ms and heartbeats every 100 ms, as a real ODrive
configured with ``encoder_msg_rate_ms = 2`` would. One simulator serves the 8 nodes (python-can's
virtual bus copies every frame once per other bus on the channel, so 8 separate simulator
buses would measure python-can's copying rather than the driver).

The loop sleeps until each deadline (``time.sleep``, which releases the GIL to the receive
threads; spinning instead was measured to double the p99 jitter); deadlines are absolute
(``t0 + k * 2 ms``), so a late period does not shift the later ones.

Metrics: ``can_loop_500hz_rate_ratio`` (periods done / periods due over the run) and
``can_loop_p99_jitter_ms`` (p99 of |period - 2 ms|), plus the feedback age.
"""

from __future__ import annotations

import time

from bench.common import Results, median, percentile

NODES = 8
RATE = 500.0


def _loop(seconds: float) -> tuple[list[float], list[float], float, int]:
    from temoto.clock import MonotonicClock
    from temoto.drivers.can_motor.odrive import ODriveDriver, ODriveNode
    from temoto.drivers.can_motor.sim import SimODrive
    from temoto.drivers.capabilities import ControlMode, JointCommand

    period = 1.0 / RATE
    clock = MonotonicClock()
    link = {"interface": "virtual", "channel": f"bench-can-{time.monotonic_ns()}"}
    sim = SimODrive(link, list(range(NODES)), clock, heartbeat_period=0.1, encoder_period=period)
    nodes = [ODriveNode(i, f"wheel{i}") for i in range(NODES)]
    driver = ODriveDriver(
        "bench", link=link, nodes=nodes, clock=clock, init_timeout=2.0, encoder_period=period
    )
    joints = driver.joint_names
    gaps: list[float] = []
    ages: list[float] = []
    with sim, driver:
        driver.configure()
        driver.activate()
        n = int(seconds * RATE)
        t0 = time.perf_counter() + 0.05
        last = t0
        done = 0
        for k in range(n):
            deadline = t0 + k * period
            while True:
                left = deadline - time.perf_counter()
                if left <= 0:
                    break
                time.sleep(left)
            now = time.perf_counter()
            if k:
                gaps.append(now - last)
            last = now
            speed = 1.0 + (k % 100) * 0.01
            driver.command([JointCommand(j, ControlMode.VELOCITY, speed) for j in joints])
            state = driver.read_state()
            ages.append(clock.monotonic() - min(s.stamp for s in state.joints.values()))
            done += 1
        elapsed = last - t0 + period  # the last period counts until its deadline
        ok = driver.health().ok
        driver.deactivate()
    if not ok:
        raise RuntimeError("the driver faulted during the benchmark")
    return gaps, ages, done / (elapsed * RATE), sum(a.commands for a in sim.axes.values())


def bench_can(quick: bool) -> Results:
    """``can_loop_500hz_rate_ratio`` and ``can_loop_p99_jitter_ms``: 8 ODrive axes at 500 Hz."""
    out = Results()
    try:
        import can  # noqa: F401
    except ImportError:
        out.notes.append("python-can not installed (pip install 'temoto[can]'): skipped")
        return out
    seconds = 1.0 if quick else 10.0  # quick: the run's 60 s
    gaps, ages, ratio, received = _loop(seconds)
    target = 1.0 / RATE
    jitter = [abs(g - target) * 1e3 for g in gaps]
    out.add(
        "can_loop_500hz_rate_ratio",
        ratio,
        "ratio",
        f"{NODES} CANSimple axes (ODriveDriver + SimODrive, virtual bus, one process),"
        f" {seconds:g} s: periods done / periods due; {received} set-points reached the sim"
        f" of {len(gaps) + 1} x {NODES} sent",
        goal=(">=", 0.99),
    )
    out.add(
        "can_loop_p99_jitter_ms",
        percentile(jitter, 99),
        "ms",
        f"p99 of |period - 2 ms| over {len(gaps)} periods (median {median(jitter):.3f},"
        f" max {max(jitter):.3f})",
        goal=("<=", 1.0),
    )
    out.add(
        "can_loop_feedback_age_ms",
        median(ages) * 1e3,
        "ms",
        f"median age of the oldest axis' encoder estimate at read_state (p99"
        f" {percentile(ages, 99) * 1e3:.2f} ms); encoder estimates every 2 ms",
    )
    return out
