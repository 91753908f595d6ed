"""Robot Manager: start-to-ready time and idle memory of a whole robot instance.

Each round starts ``python -m temoto.managers.robot --profile <profile> --local`` (serving, no
mission) as a fresh process, measures from ``Popen`` to its "robot '<name>' ready" line (profile
load, instance, simulators, drivers configured and activated, robot loaded), reads its VmRSS
after it has idled for a second (half a second in quick mode), and stops it with SIGTERM.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from bench.common import Results, median

ROOT = Path(__file__).resolve().parents[1]
PROFILE = ROOT / "hw_profiles" / "sim_mobile_manipulator.yaml"


def _rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status", encoding="ascii") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    raise RuntimeError(f"no VmRSS for {pid}")


def _one(profile: Path, idle_s: float) -> tuple[float, float]:
    env = {k: v for k, v in os.environ.items() if k != "TEMOTO_FLEET_KEY"}
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        [sys.executable, "-m", "temoto.managers.robot", "--profile", str(profile), "--local"],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
        env=env,
    )
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        ready = time.perf_counter() - t0
        if "ready" not in line:
            raise RuntimeError(f"the robot did not get ready: {line!r} (exit {proc.poll()})")
        time.sleep(idle_s)  # idle: the control loop and the drivers' threads keep running
        rss = _rss_mb(proc.pid)
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return ready, rss


def bench_robot(quick: bool) -> Results:
    out = Results()
    if not PROFILE.is_file():
        out.notes.append(f"{PROFILE.name} not found: robot_manager_* skipped")
        return out
    rounds = 2 if quick else 10
    idle_s = 0.5 if quick else 1.0
    samples = [_one(PROFILE, idle_s) for _ in range(rounds)]
    ready = [s[0] for s in samples]
    rss = [s[1] for s in samples]
    how = f"{PROFILE.name} (simulators in-process), --local, {rounds} fresh processes"
    idle = f"VmRSS after {idle_s:g} s idle"
    out.add(
        "robot_manager_ready_s",
        median(ready),
        "s",
        f"{how}: Popen -> 'ready' line; min {min(ready):.2f}, max {max(ready):.2f}",
        ("<=", 1.5),
    )
    out.add(
        "robot_manager_idle_rss_mb",
        median(rss),
        "MB",
        f"{how}: {idle}; min {min(rss):.1f}, max {max(rss):.1f}",
        ("<=", 60.0),
    )
    return out
