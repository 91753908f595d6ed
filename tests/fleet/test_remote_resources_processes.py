"""Robot A uses a process of robot B, each an OS process, over LCM or Zenoh with a fleet key.

Over Zenoh both robots are clients of a `temoto router` started first in the namespace.

Runs inside its own network namespace (``unshare -n``: loopback up, multicast routed to it),
so the host's interfaces are never touched; ``_ris_robot.py driver`` starts both robots and
runs the scenario (its children are reaped, and the processes B started are killed, even when
it fails). Needs root, ``unshare`` and ``ip``; skipped otherwise.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from _transports import TRANSPORTS

from temoto.testing import ProcessLeakCheck
from temoto.transport import KEY_ENV

ROBOT = Path(__file__).resolve().parent / "_ris_robot.py"
KEY = "3c" * 32


def _namespace_problem() -> str | None:
    if os.geteuid() != 0:
        return "needs root to create a network namespace (unshare -n)"
    for tool in ("unshare", "ip"):
        if shutil.which(tool) is None:
            return f"needs the {tool!r} command"
    probe = subprocess.run(
        ["unshare", "-n", "true"], capture_output=True, text=True, timeout=10, check=False
    )
    if probe.returncode != 0:
        return f"unshare -n does not work here: {probe.stderr.strip()}"
    return None


@pytest.fixture(autouse=True)
def no_leaked_processes(monkeypatch: pytest.MonkeyPatch) -> Iterator[ProcessLeakCheck]:
    check = ProcessLeakCheck()
    monkeypatch.setenv(check.variable, check.mark)
    yield check
    leaked = check.kill_leftovers()
    if leaked:
        pytest.fail(f"test left processes running: {leaked}", pytrace=False)


def run_in_namespace(*args: str, timeout: float) -> dict[str, object]:
    """Run ``_ris_robot.py ARGS`` in a fresh network namespace; its JSON result."""
    setup = 'ip link set lo up && ip route replace 224.0.0.0/4 dev lo && exec "$0" "$@"'
    env = {**os.environ, KEY_ENV: KEY}
    proc = subprocess.run(
        ["unshare", "-n", "sh", "-c", setup, sys.executable, str(ROBOT), *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        env=env,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    result: dict[str, object] = json.loads(proc.stdout.strip().splitlines()[-1])
    return result


@pytest.mark.parametrize("url", TRANSPORTS)
def test_a_process_on_robot_b_is_watched_and_stopped_for_robot_a(url: str) -> None:
    problem = _namespace_problem()
    if problem:
        pytest.skip(problem)
    result = run_in_namespace("driver", url, timeout=60)
    latency = result["status_latency_s"]
    assert isinstance(latency, float)
    assert latency < 0.5, f"the crash on B reached A after {latency * 1e3:.1f} ms"
    message = result["status_message"]
    assert isinstance(message, str)
    assert message.startswith("robot 'B': process ")
    assert "SIGKILL" in message
    # released on A: stopped on B
    assert result["release_stop_s"] is not None
    # A killed: B noticed after the missed periods (3 x 0.1 s) and stopped A's process
    orphan = result["orphan_stop_s"]
    assert isinstance(orphan, float), "B did not stop the process of the dead robot A"
    assert orphan < 5.0
    stats = result["b_stats"]
    assert isinstance(stats, dict)
    remote, ris = stats["remote"], stats["ris"]
    assert remote["released_for_lost"] == 1
    assert remote["requests_received"] - remote["duplicates"] == 3
    assert remote["replies_sent"] >= 5  # 3 requests, 2 releases (the third: A was lost)
    assert remote["decode_errors"] == remote["unexpected"] == 0
    assert ris["lost"] == 1
    assert ris["decode_errors"] == ris["unexpected"] == 0
    assert result["b_code"] == 0
