"""RIS benchmarks: a process crash on robot B reaching a consumer on robot A; remote loads.

Robot A and robot B are separate processes (``tests/fleet/_ris_robot.py``, the program the
multi-process test runs), each with its own LCM transport on ``udpm://`` (ttl 0) and a fleet
key, inside a private network namespace made by ``unshare -n`` (loopback up, multicast routed
to it), so the host's interfaces are never touched. Needs root, ``unshare`` and ``ip``;
otherwise the group is skipped with a note. Both robots share the host's clock, so the crash
latency is a difference of ``time.time()`` taken in two processes.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

from bench.common import Results, median, percentile

ROOT = Path(__file__).resolve().parent.parent
ROBOT = ROOT / "tests" / "fleet" / "_ris_robot.py"
KEY = "5e" * 32


def _available() -> str:
    if os.geteuid() != 0:
        return "the RIS benchmarks need root (a private network namespace per run)"
    for tool in ("unshare", "ip"):
        if shutil.which(tool) is None:
            return f"the RIS benchmarks need {tool}"
    if not ROBOT.is_file():
        return f"the RIS benchmarks need {ROBOT} (the robot program of the tests)"
    return ""


def bench_ris(quick: bool) -> Results:
    out = Results()
    why = _available()
    if why:
        out.notes.append(f"{why}: remote_status_ms/remote_load_ms skipped")
        return out
    rounds = 20 if quick else 100
    setup = 'ip link set lo up && ip route replace 224.0.0.0/4 dev lo && exec "$0" "$@"'
    env = {**os.environ, "PYTHONPATH": str(ROOT), "TEMOTO_FLEET_KEY": KEY}
    proc = subprocess.run(
        ["unshare", "-n", "sh", "-c", setup, sys.executable, str(ROBOT), "bench", str(rounds)],
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
        check=False,
    )
    if proc.returncode != 0:
        raise RuntimeError(f"RIS benchmark failed: {proc.stderr[-3000:]}")
    data = json.loads(proc.stdout.strip().splitlines()[-1])
    status = [s * 1e3 for s in data["status_s"]]
    loads = data["load_ms"]
    how = (
        "robot A and robot B as two processes, LCM udpm:// on loopback in a private namespace,"
        " key on"
    )
    out.add(
        "remote_status_ms",
        median(status),
        "ms",
        f"{how}: kill -9 of a process B started for A -> FATAL in A's consumer callback;"
        f" median of {rounds}",
        ("<=", 50.0),
    )
    out.add("remote_status_ms_p99", percentile(status, 99), "ms", "p99 of the same")
    out.add(
        "remote_load_ms",
        median(loads),
        "ms",
        f"{how}: RemoteResources.request('process', ...) on A -> returned with B's pid"
        f" (request, spawn on B, reply); median of {rounds}",
    )
    out.add("remote_load_ms_p99", percentile(loads, 99), "ms", "p99 of the same")
    return out
