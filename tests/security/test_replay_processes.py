"""A replay across a restart, with processes: a captured `temoto graph start` replayed to a
restarted `temoto serve` is refused.

Inside its own network namespace (`unshare -n`: loopback up, multicast routed to it), a passive
LCM listener records every datagram on ``TEMOTO_GRAPH_CMD`` while `temoto graph start` starts a
ticking graph on instance A; A is stopped and started again on the same fleet key, and the
listener re-publishes the captured bytes (seconds after the capture: inside the old 30 s clock
window); the graph must not run again (``"TaTimer_0": "RUNNING"``). Needs root, `unshare` and
`ip`.
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

ROOT = Path(__file__).resolve().parents[2]
ACTIONS = ROOT / "examples" / "actions" / "conformance"
URL = "udpm://239.255.76.67:7667?ttl=0"
KEY = "6b" * 32

pytestmark = [
    pytest.mark.skipif(os.geteuid() != 0, reason="network namespaces need root"),
    pytest.mark.skipif(
        shutil.which("unshare") is None or shutil.which("ip") is None,
        reason="needs unshare and ip (util-linux, iproute2)",
    ),
]

RUNNER = r"""
import json, os, signal, subprocess, sys, threading
import lcm
subprocess.run(["ip", "link", "set", "lo", "up"], check=True)
subprocess.run(["ip", "route", "replace", "224.0.0.0/4", "dev", "lo"], check=True)
spec = json.loads(sys.argv[1])
temoto = [sys.executable, "-m", "temoto"]
fleet = ["--fleet-url", spec["url"]]
env = {**os.environ, "TEMOTO_FLEET_KEY": spec["key"]}
captured, lock = [], threading.Lock()
lc = lcm.LCM(spec["url"])
def take(channel, data):
    with lock:
        captured.append(data)
lc.subscribe("TEMOTO_GRAPH_CMD", take)
done = threading.Event()
def pump():
    while not done.is_set():
        lc.handle_timeout(50)
threading.Thread(target=pump, daemon=True).start()
def serve():
    p = subprocess.Popen(
        [*temoto, "serve", "--actor", "A", "--actions", spec["actions"],
         "--feedback-period", "0.2", *fleet],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    line = p.stdout.readline()
    assert line.strip() == "ready", (line, p.poll())
    return p
def stop(p):
    p.send_signal(signal.SIGTERM)
    out, err = p.communicate(timeout=30)
    return {"code": p.returncode, "stderr": err[-3000:]}
def run(*argv):
    r = subprocess.run([*temoto, *argv, *fleet], env=env, capture_output=True, text=True,
                       timeout=60)
    return {"code": r.returncode, "stdout": r.stdout, "stderr": r.stderr[-2000:]}
def replay(frames):
    for data in frames:
        lc.publish("TEMOTO_GRAPH_CMD", data)
    return len(frames)
report = {}
a = serve()
report["start"] = run("graph", "start", spec["graph"], "--target", "A")
report["before"] = run("graph", "watch", "--once", "--json", "--duration", "1.0")
report["first_boot"] = stop(a)
with lock:
    frames = list(captured)  # what the listener heard: the start and its re-sends
a = serve()
report["replayed"] = replay(frames)
# an authentic start of another graph: the watch below hears A, so silence about the
# replayed one means it did not run
report["other"] = run("graph", "start", spec["other"], "--target", "A")
report["after"] = run("graph", "watch", "--once", "--json", "--duration", "1.5")
report["replayed_again"] = replay(frames)  # A has met the watcher meanwhile: still refused
report["after_again"] = run("graph", "watch", "--once", "--json", "--duration", "1.0")
report["second_boot"] = stop(a)
done.set()
print(json.dumps(report))
"""


def runs(watch: dict[str, Any], graph: str = "ticking") -> list[dict[str, Any]]:
    assert watch["code"] == 0, watch  # it heard A
    heard = [json.loads(line) for line in watch["stdout"].splitlines()]
    return [h for h in heard if h["graph"] == graph and h["actor"] == "A"]


def test_a_captured_start_replayed_to_a_restarted_serve_does_not_run(tmp_path: Path) -> None:
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
    graph = tmp_path / "ticking.graph.json"
    graph.write_text(json.dumps(timer))
    other = tmp_path / "other.graph.json"
    other.write_text(json.dumps({**timer, "graph_name": "other"}))
    spec = {
        "url": URL,
        "key": KEY,
        "actions": str(ACTIONS),
        "graph": str(graph),
        "other": str(other),
    }
    env = {k: v for k, v in os.environ.items() if k != "TEMOTO_FLEET_KEY"}
    proc = subprocess.run(
        ["unshare", "-n", sys.executable, "-c", RUNNER, json.dumps(spec)],
        capture_output=True,
        text=True,
        timeout=180,
        env=env,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    report = json.loads(proc.stdout)
    assert report["start"]["code"] == 0, report["start"]
    assert report["first_boot"]["code"] == 0, report["first_boot"]
    assert report["second_boot"]["code"] == 0, report["second_boot"]
    # the first boot ran the graph: the capture holds an authentic start
    (running,) = runs(report["before"])
    assert running["nodes"] == {"TaTimer_0": "RUNNING"}
    assert report["replayed"] >= 1
    assert report["replayed_again"] == report["replayed"]
    # the restarted instance runs what it is asked now, and never the captured start, however
    # often it was shown the captured bytes
    assert report["other"]["code"] == 0, report["other"]
    assert len(runs(report["after"], "other")) == 1
    assert runs(report["after"]) == []
    assert runs(report["after_again"]) == []
