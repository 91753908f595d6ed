"""Three `temoto run --actor` processes run upstream's three-actor graph, over LCM and Zenoh.

Over LCM the processes use multicast on loopback; over Zenoh they are clients of a `temoto
router` started first in the same namespace (``_transports.py``).

Each test runs inside its own network namespace (`unshare -n`: loopback up, multicast routed
to it); the host's interfaces are never touched, and the namespace goes away with its
processes. Needs root, `unshare` and `ip`; skipped otherwise.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

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
KEY = "6b" * 32  # a fixed 32-byte fleet key, hex

pytestmark = [
    pytest.mark.skipif(os.geteuid() != 0, reason="network namespaces need root"),
    pytest.mark.skipif(
        shutil.which("unshare") is None or shutil.which("ip") is None,
        reason="needs unshare and ip (util-linux, iproute2)",
    ),
    pytest.mark.skipif(not MULTI.is_file(), reason=f"upstream data not found at {MULTI}"),
]

# Runs inside the namespace: route multicast to loopback, start one process per actor, report.
RUNNER = (
    ROUTER_CODE
    + r"""
import json, os, subprocess, sys
subprocess.run(["ip", "link", "set", "lo", "up"], check=True)
subprocess.run(["ip", "route", "replace", "224.0.0.0/4", "dev", "lo"], check=True)
spec = json.loads(sys.argv[1])
router = start_router(spec["url"])
procs = []
for actor, env in spec["actors"]:
    procs.append(subprocess.Popen(
        [sys.executable, "-m", "temoto", "run", spec["graph"], "--actions", spec["actions"],
         "--actor", actor, "--fleet-url", spec["url"], *spec["extra"]],
        env={**os.environ, **env}, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
out = []
for p in procs:
    try:
        stdout, stderr = p.communicate(timeout=spec["timeout"])
    except subprocess.TimeoutExpired:
        p.kill()
        stdout, stderr = p.communicate()
    out.append({"code": p.returncode, "stdout": stdout, "stderr": stderr[-2000:]})
stop_router(router)
print(json.dumps(out))
"""
)


def run_actors(
    actors: list[tuple[str, dict[str, str]]], extra: list[str], timeout: float, url: str
) -> list:
    spec = {
        "actors": actors,
        "graph": str(MULTI),
        "actions": str(ACTIONS),
        "url": url,
        "extra": extra,
        "timeout": timeout,
    }
    env = {k: v for k, v in os.environ.items() if k != "TEMOTO_FLEET_KEY"}
    proc = subprocess.run(
        ["unshare", "-n", sys.executable, "-c", RUNNER, json.dumps(spec)],
        capture_output=True,
        text=True,
        timeout=timeout + 30,
        env=env,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)


@pytest.mark.parametrize("url", TRANSPORTS)
def test_three_actor_processes_end_on_true(url: str) -> None:
    results = run_actors([(a, {"TEMOTO_FLEET_KEY": KEY}) for a in ACTORS], [], 30, url)
    for actor, res in zip(ACTORS, results, strict=True):
        assert res["code"] == 0, f"{actor}: {res}"
        assert "engine_test_multi_actor: on_true" in res["stdout"], (actor, res)


@pytest.mark.parametrize("url", TRANSPORTS)
def test_an_actor_without_the_fleet_key_cannot_take_part(url: str) -> None:
    # A and B share the key; C has another one: nobody completes the handshake with C
    wrong = "5a" * 32
    actors = [
        ("Actor A", {"TEMOTO_FLEET_KEY": KEY}),
        ("Actor B", {"TEMOTO_FLEET_KEY": KEY}),
        ("Actor C", {"TEMOTO_FLEET_KEY": wrong}),
    ]
    results = run_actors(actors, ["--handshake-timeout", "1.5"], 20, url)
    for actor, res in zip(ACTORS, results, strict=True):
        assert res["code"] == 1, f"{actor}: {res}"
        assert "handshake" in res["stderr"].lower(), (actor, res["stderr"])


def test_a_shared_graph_needs_a_key_or_insecure() -> None:
    command = [sys.executable, "-m", "temoto", "run", str(MULTI), "--actions", str(ACTIONS)]
    proc = subprocess.run(
        [*command, "--actor", "Actor A"],
        capture_output=True,
        text=True,
        timeout=60,
        env={k: v for k, v in os.environ.items() if k != "TEMOTO_FLEET_KEY"},
        check=False,
    )
    assert proc.returncode == 2
    assert "a fleet key is needed" in proc.stderr
