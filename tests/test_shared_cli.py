"""Upstream's three-actor graph as three ``temoto run --actor`` processes over LCM multicast.

Each actor's ``--trace`` ends with its one result line (the README's ``on_true``), and an
actor with a wrong fleet key is named, with the reason, in the WARNING lines of the others.
Each test runs inside its own network namespace (``unshare -n``: loopback up, multicast routed
to it; the host's interfaces are never touched). Needs root, ``unshare`` and ``ip``.
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

ROOT = Path(__file__).resolve().parents[1]
ACTIONS = ROOT / "examples" / "actions" / "conformance"
UPSTREAM = ROOT.parent / "shared" / "conformance" / "umrf" / "upstream"
MULTI = UPSTREAM / "actionengine_test_engine_test_multi_actor.graph.json"
ACTORS = ["Actor A", "Actor B", "Actor C"]
KEY = "3c" * 32
WRONG_KEY = "c3" * 32
URL = "udpm://239.255.76.67:7667?ttl=0"

pytestmark = [
    pytest.mark.skipif(os.geteuid() != 0, reason="network namespaces need root"),
    pytest.mark.skipif(
        shutil.which("unshare") is None or shutil.which("ip") is None,
        reason="needs unshare and ip (util-linux, iproute2)",
    ),
    pytest.mark.skipif(not MULTI.is_file(), reason=f"no conformance data at {MULTI}"),
    pytest.mark.timeout(90),
]

#: Runs inside the namespace: route multicast to loopback, one process per actor, report.
RUNNER = r"""
import json, os, subprocess, sys
subprocess.run(["ip", "link", "set", "lo", "up"], check=True)
subprocess.run(["ip", "route", "replace", "224.0.0.0/4", "dev", "lo"], check=True)
spec = json.loads(sys.argv[1])
procs = [
    subprocess.Popen(
        [sys.executable, "-m", "temoto", "run", spec["graph"], "--actions", spec["actions"],
         "--actor", actor, "--fleet-url", spec["url"], "--trace", trace, *spec["extra"]],
        env={**os.environ, "TEMOTO_FLEET_KEY": key},
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    for actor, key, trace in spec["actors"]
]
out = []
for p in procs:
    try:
        stdout, stderr = p.communicate(timeout=spec["timeout"])
    except subprocess.TimeoutExpired:
        p.kill()
        stdout, stderr = p.communicate()
    out.append({"code": p.returncode, "stdout": stdout, "stderr": stderr[-4000:]})
print(json.dumps(out))
"""


def run_actors(
    tmp_path: Path, keys: list[str], extra: list[str], timeout: float
) -> list[dict[str, Any]]:
    traces = [tmp_path / f"trace_{n}.jsonl" for n in range(len(ACTORS))]
    spec = {
        "actors": [[a, k, str(t)] for a, k, t in zip(ACTORS, keys, traces, strict=True)],
        "graph": str(MULTI),
        "actions": str(ACTIONS),
        "url": URL,
        "extra": extra,
        "timeout": timeout,
    }
    proc = subprocess.run(
        ["unshare", "-n", sys.executable, "-c", RUNNER, json.dumps(spec)],
        capture_output=True,
        text=True,
        timeout=timeout + 30,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr
    results: list[dict[str, Any]] = json.loads(proc.stdout)
    for res, trace in zip(results, traces, strict=True):
        lines = trace.read_text(encoding="utf-8").splitlines() if trace.exists() else []
        res["trace"] = [json.loads(line) for line in lines]
    return results


def test_every_actors_trace_ends_with_the_one_shared_result(tmp_path: Path) -> None:
    results = run_actors(tmp_path, [KEY] * 3, [], timeout=40)
    for actor, res in zip(ACTORS, results, strict=True):
        assert res["code"] == 0, f"{actor}: {res}"
        assert res["stdout"].splitlines()[0] == "engine_test_multi_actor: on_true", res
        records = res["trace"]
        assert [r for r in records if "result" in r] == [
            {"graph": "engine_test_multi_actor", "result": "on_true"}
        ], (actor, records)
        assert records[-1] == {"graph": "engine_test_multi_actor", "result": "on_true"}


def test_a_wrong_key_is_named_in_the_other_actors_warnings(tmp_path: Path) -> None:
    results = run_actors(tmp_path, [KEY, KEY, WRONG_KEY], ["--handshake-timeout", "1.5"], 30)
    for actor, res in zip(ACTORS, results, strict=True):
        assert res["code"] == 1, f"{actor}: {res}"
    for res in results[:2]:
        warnings = [
            line
            for line in res["stderr"].splitlines()
            if line.startswith("WARNING temoto.transport.auth:") and "dropped" in line
        ]
        assert any("from 'Actor C': wrong mac" in line for line in warnings), res["stderr"]
        # one line of its own for each sender and reason; repeats go into summaries
        assert sum("from 'Actor C': wrong mac" in line for line in warnings) == 1
        # the drops after the first line are summarised when the command ends
        assert any("more messages in the last" in line for line in warnings), res["stderr"]
    # and Actor C says who it cannot hear
    assert "from 'Actor A': wrong mac" in results[2]["stderr"]
    assert "from 'Actor B': wrong mac" in results[2]["stderr"]
