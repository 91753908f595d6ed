"""`temoto serve` instances commanded by `temoto graph start|stop|watch` in other processes.

Over both transports: LCM multicast on loopback, or Zenoh clients of a `temoto router` started
first in the namespace (``_transports.py``).

Everything runs inside its own network namespace (`unshare -n`: loopback up, multicast routed
to it), so the host's interfaces are never touched. Needs root, `unshare` and `ip`.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from _transports import ROUTER_CODE, TRANSPORTS

ROOT = Path(__file__).resolve().parents[2]
ACTIONS = ROOT / "examples" / "actions" / "conformance"
MULTI = (
    ROOT.parent
    / "shared"
    / "conformance"
    / "umrf"
    / "upstream"
    / "actionengine_test_engine_test_multi_actor.graph.json"
)
ACTORS = ["Actor A", "Actor B", "Actor C"]
KEY = "6b" * 32

pytestmark = [
    pytest.mark.skipif(os.geteuid() != 0, reason="network namespaces need root"),
    pytest.mark.skipif(
        shutil.which("unshare") is None or shutil.which("ip") is None,
        reason="needs unshare and ip (util-linux, iproute2)",
    ),
    pytest.mark.skipif(not MULTI.is_file(), reason=f"upstream data not found at {MULTI}"),
]

# Runs inside the namespace: start the instances, wait for each one's "ready", then run the
# commands one after the other; report every command's exit status and output as JSON.
RUNNER = (
    ROUTER_CODE
    + r"""
import json, os, signal, subprocess, sys, time
subprocess.run(["ip", "link", "set", "lo", "up"], check=True)
subprocess.run(["ip", "route", "replace", "224.0.0.0/4", "dev", "lo"], check=True)
spec = json.loads(sys.argv[1])
temoto = [sys.executable, "-m", "temoto"]
fleet = ["--fleet-url", spec["url"]]
env = {**os.environ, "TEMOTO_FLEET_KEY": spec["key"]}
servers = []
report = {"steps": [], "servers": []}
router = start_router(spec["url"])
try:
    for actor in spec["actors"]:
        p = subprocess.Popen(
            [*temoto, "serve", "--actor", actor, "--actions", spec["actions"],
             "--feedback-period", "0.2", *fleet],
            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        servers.append(p)
    for p in servers:
        line = p.stdout.readline()  # bounded by the outer timeout of the whole runner
        assert line.strip() == "ready", (line, p.poll())
    for step in spec["steps"]:
        step_env = {**env, **step.get("env", {})}
        if step.get("no_key"):
            del step_env["TEMOTO_FLEET_KEY"]
        r = subprocess.run([*temoto, *step["argv"], *fleet], env=step_env, capture_output=True,
                           text=True, timeout=60)
        report["steps"].append({"argv": step["argv"], "code": r.returncode, "stdout": r.stdout,
                                "stderr": r.stderr[-2000:]})
finally:
    for p in servers:
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
    for p in servers:
        try:
            out, err = p.communicate(timeout=20)
        except subprocess.TimeoutExpired:
            p.kill()
            out, err = p.communicate()
        report["servers"].append({"code": p.returncode, "stderr": err[-2000:]})
    stop_router(router)
print(json.dumps(report))
"""
)


def scenario(steps: list[dict[str, Any]], url: str, timeout: float = 90) -> dict[str, Any]:
    spec = {"actors": ACTORS, "actions": str(ACTIONS), "url": url, "key": KEY, "steps": steps}
    env = {k: v for k, v in os.environ.items() if k != "TEMOTO_FLEET_KEY"}
    proc = subprocess.run(
        ["unshare", "-n", sys.executable, "-c", RUNNER, json.dumps(spec)],
        capture_output=True,
        text=True,
        timeout=timeout,
        env=env,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    report: dict[str, Any] = json.loads(proc.stdout)
    for server in report["servers"]:
        assert server["code"] == 0, server  # SIGTERM: a clean stop
    return report


def targets(*actors: str) -> list[str]:
    return [arg for a in actors for arg in ("--target", a)]


@pytest.mark.parametrize("url", TRANSPORTS)
def test_start_a_shared_graph_on_three_instances_and_watch_it_end(tmp_path: Path, url: str) -> None:
    timer = {
        "graph_name": "ticking",
        "graph_entry": [{"name": "TaTimer", "instance_id": 0}],
        "graph_exit": [{"name": "TaTimer", "instance_id": 0}],
        "actions": [
            {
                "name": "TaTimer",
                "instance_id": 0,
                "type": "sync",
                "input_parameters": {"count_until": {"pvf_type": "number", "pvf_value": 0}},
                "output_parameters": {"final_count": {"pvf_type": "number"}},
            }
        ],
    }
    timer_file = tmp_path / "ticking.graph.json"
    timer_file.write_text(json.dumps(timer))
    report = scenario(
        [
            {"argv": ["graph", "start", str(MULTI), *targets(*ACTORS)]},
            {"argv": ["graph", "start", str(timer_file), *targets("Actor B")]},
            {"argv": ["graph", "watch", "--once", "--json", "--duration", "1.0"]},
            {"argv": ["graph", "pause", "ticking", *targets("Actor B")]},
            {"argv": ["graph", "stop", "ticking", *targets("Actor B")]},
            {"argv": ["graph", "stop", "ticking", *targets("Actor A")]},
            {"argv": ["graph", "start", "no_such_graph", *targets("Actor C")]},
            {
                "argv": ["graph", "start", str(timer_file), *targets("Actor A"), "--timeout", "1"],
                "env": {"TEMOTO_FLEET_KEY": "5a" * 32},
            },
            {"argv": ["graph", "start", str(timer_file), *targets("Actor A")], "no_key": True},
        ],
        url,
    )
    steps = report["steps"]
    start, timer_start, watched, pause, stop, stop_a, missing, stranger, _ = steps
    assert start["code"] == 0, start
    for actor in ACTORS:
        assert f"{actor}: started 'engine_test_multi_actor'" in start["stdout"]
    assert timer_start["code"] == 0, timer_start
    # the watch heard every actor's run of the shared graph end on_true, and B's timer running
    assert watched["code"] == 0, watched
    heard = [json.loads(line) for line in watched["stdout"].splitlines()]
    shared = {h["actor"]: h for h in heard if h["graph"] == "engine_test_multi_actor"}
    assert sorted(shared) == ACTORS, heard
    assert all(h["result"] == "on_true" for h in shared.values()), shared
    ticking = [h for h in heard if h["graph"] == "ticking"]
    assert len(ticking) == 1
    assert ticking[0]["actor"] == "Actor B"
    assert ticking[0]["state"] == "RUNNING"
    assert ticking[0]["nodes"] == {"TaTimer_0": "RUNNING"}
    assert pause["code"] == 0, pause
    assert stop["code"] == 0, stop
    assert "Actor B: stopped 'ticking' (on_stopped)" in stop["stdout"]
    # A has no such run: it says so, and the command fails
    assert stop_a["code"] == 1
    assert "Actor A: failed:" in stop_a["stdout"]
    assert "ticking" in stop_a["stdout"]
    assert missing["code"] == 1
    assert "no_such_graph" in missing["stdout"]
    # a commander without the fleet key is not answered, and nothing starts
    assert stranger["code"] == 1
    assert "Actor A: no answer within 1 s" in stranger["stdout"]
    # and without any key the command line refuses to send
    no_key = steps[-1]
    assert no_key["code"] == 2
    assert "a fleet key is needed" in no_key["stderr"]
