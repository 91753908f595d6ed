"""A member speaks only as itself: an impostor process against honest ones.

The impostor is a library-level process (``_impostor.py``) that seals with its own valid key
(the roster member ``guest``) and names another member inside its messages: the actor of a
shared run's handshakes and notifications, the actor of command replies and feedback, the robot
of RIS adverts and world-model updates. `temoto run`, `temoto graph start` and a whole
:class:`~temoto.instance.Instance` must not take it for that member (docs/security.md, *Who
may say what*).

Every process runs over LCM multicast inside its own network namespace (`unshare -n`: loopback
up, multicast routed to it). Needs root, `unshare` and `ip`. Each test takes 10 - 25 s.
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

from temoto.transport.identity import Identity, Roster

ROOT = Path(__file__).resolve().parents[2]
ACTIONS = ROOT / "examples" / "actions" / "conformance"
IMPOSTOR = Path(__file__).with_name("_impostor.py")


def _action(name: str, actor: str, inputs: dict[str, str], **links: Any) -> dict[str, Any]:
    return {
        "name": name,
        "actor": actor,
        "instance_id": 0,
        "type": "sync",
        "input_parameters": {
            k: {"pvf_type": "string", **({"pvf_value": v} if v else {})} for k, v in inputs.items()
        },
        "output_parameters": {
            "string_out" if name == "TaRelayString" else "result": {"pvf_type": "string"}
        }
        if name != "TaCompareString"
        else {},
        **links,
    }


def _child(name: str, out: str) -> list[dict[str, Any]]:
    return [{"name": name, "instance_id": 0, "remap": [{"from": out, "to": "str_a"}]}]


def _parent(name: str) -> list[dict[str, Any]]:
    conditions = ["on_true -> run", "on_false -> bypass", "on_error -> bypass"]
    return [{"name": name, "instance_id": 0, "required": True, "conditions": conditions}]


#: Upstream's three-actor graph (actionengine_test_engine_test_multi_actor), actors A, B, C.
SHARED = {
    "graph_name": "shared",
    "graph_entry": [{"name": "TaRelayString", "instance_id": 0}],
    "graph_exit": [{"name": "TaCompareString", "instance_id": 0}],
    "actions": [
        _action(
            "TaRelayString", "Actor A", {"string_in": "String from Actor A"},
            children=_child("TaAddString", "string_out"),
        ),
        _action(
            "TaAddString", "Actor B", {"str_a": "", "str_b": "string from Actor B"},
            parents=_parent("TaRelayString"), children=_child("TaCompareString", "result"),
        ),
        _action(
            "TaCompareString", "Actor C",
            {"str_a": "", "str_b": "String from Actor A and string from Actor B"},
            parents=_parent("TaAddString"),
        ),
    ],
}  # fmt: skip
URL = "udpm://239.255.76.67:7667?ttl=0"
MEMBERS = ("Actor A", "Actor B", "Actor C", "operator", "guest")

pytestmark = [
    pytest.mark.skipif(os.geteuid() != 0, reason="network namespaces need root"),
    pytest.mark.skipif(
        shutil.which("unshare") is None or shutil.which("ip") is None,
        reason="needs unshare and ip (util-linux, iproute2)",
    ),
]

# Runs inside the namespace: start the processes (waiting for the "ready" of those that say
# it), run the steps one after the other, then collect every process's output as JSON.
RUNNER = r"""
import json, subprocess, sys
subprocess.run(["ip", "link", "set", "lo", "up"], check=True)
subprocess.run(["ip", "route", "replace", "224.0.0.0/4", "dev", "lo"], check=True)
spec = json.loads(sys.argv[1])
procs, report = [], {"procs": [], "steps": []}
try:
    for p in spec["procs"]:
        procs.append(subprocess.Popen(p["argv"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                      text=True))
        if p.get("ready"):
            line = procs[-1].stdout.readline()
            assert line.strip() == "ready", (line, procs[-1].poll(), procs[-1].stderr.read())
    for argv in spec["steps"]:
        r = subprocess.run(argv, capture_output=True, text=True, timeout=60)
        report["steps"].append({"code": r.returncode, "stdout": r.stdout,
                                "stderr": r.stderr[-3000:]})
finally:
    for p in procs:
        try:
            out, err = p.communicate(timeout=spec["timeout"])
        except subprocess.TimeoutExpired:
            p.kill()
            out, err = p.communicate()
        report["procs"].append({"code": p.returncode, "stdout": out, "stderr": err[-4000:]})
print(json.dumps(report))
"""


class Fleet:
    """Identities of every member and the roster, in a temporary directory."""

    def __init__(self, tmp_path: Path) -> None:
        self.dir = tmp_path
        self.roster = tmp_path / "fleet.roster"
        roster = Roster({})
        for name in MEMBERS:
            identity = Identity.generate(name)
            identity.save(self.id_file(name))
            roster.add(name, identity.public_key)
        roster.save(self.roster)
        self.graph = tmp_path / "shared.json"
        self.graph.write_text(json.dumps(SHARED))

    def id_file(self, name: str) -> Path:
        return self.dir / f"{name.replace(' ', '_')}.id"

    def keys(self, name: str) -> list[str]:
        return ["--fleet-identity", str(self.id_file(name)), "--fleet-roster", str(self.roster)]

    def impostor(self, role: str, *args: str, member: str = "guest") -> list[str]:
        files = [str(self.id_file(member)), str(self.roster)]
        return [sys.executable, str(IMPOSTOR), role, URL, *files, *args]

    def run(
        self, procs: list[dict[str, Any]], steps: list[list[str]] = (), timeout: float = 40
    ) -> dict[str, Any]:
        spec = {"procs": procs, "steps": list(steps), "timeout": timeout}
        env = {k: v for k, v in os.environ.items() if not k.startswith("TEMOTO_FLEET")}
        proc = subprocess.run(
            ["unshare", "-n", sys.executable, "-c", RUNNER, json.dumps(spec)],
            capture_output=True,
            text=True,
            timeout=timeout + 60,
            env=env,
            check=False,
        )
        assert proc.returncode == 0, proc.stderr[-3000:]
        report: dict[str, Any] = json.loads(proc.stdout)
        return report


TEMOTO = [sys.executable, "-m", "temoto"]


def temoto_run(fleet: Fleet, actor: str) -> list[str]:
    return [
        *TEMOTO, "run", str(fleet.graph), "--actions", str(ACTIONS), "--actor", actor,
        "--fleet-url", URL, "--handshake-timeout", "6", "--timeout", "20", *fleet.keys(actor),
    ]  # fmt: skip


def test_an_impostor_cannot_take_part_in_a_shared_run(tmp_path: Path) -> None:
    # guest runs "Actor A"'s part, sealing with its own key; B and C are honest `temoto run`s
    fleet = Fleet(tmp_path)
    report = fleet.run(
        [
            {"argv": temoto_run(fleet, "Actor B")},
            {"argv": temoto_run(fleet, "Actor C")},
            {"argv": fleet.impostor("actor", "Actor A", str(fleet.graph), str(ACTIONS))},
        ]
    )
    b, c, guest = report["procs"]
    for honest in (b, c):
        assert honest["code"] != 0, honest  # the handshake never completes without A
        assert "on_true" not in honest["stdout"], honest
        assert "sent by 'guest' whose actor names 'Actor A'" in honest["stderr"], honest
    assert "on_true" not in guest["stdout"], guest


def test_an_impostor_cannot_answer_a_command_in_another_robot_s_name(tmp_path: Path) -> None:
    # "Actor B" is not running; guest answers commands and sends feedback as "Actor B"
    fleet = Fleet(tmp_path)
    graph = tmp_path / "to_absent_B.json"
    graph.write_text(json.dumps({**SHARED, "graph_name": "to_absent_B"}))
    start = [
        *TEMOTO, "graph", "start", str(graph), "--target", "Actor B", "--timeout", "4",
        "--fleet-url", URL, *fleet.keys("operator"),
    ]  # fmt: skip
    report = fleet.run(
        [{"argv": fleet.impostor("replier", "Actor B", "8"), "ready": True}], steps=[start]
    )
    (step,) = report["steps"]
    assert step["code"] != 0, step
    assert "started" not in step["stdout"], step
    assert "Actor B" in step["stdout"] + step["stderr"], step  # named as not answering


def test_an_impostor_cannot_advertise_or_change_the_world_model_as_another(
    tmp_path: Path,
) -> None:
    # guest advertises and publishes world-model items as "Actor C" (which is not running);
    # "Actor A" is an honest Instance that reports what it took in
    fleet = Fleet(tmp_path)
    report = fleet.run(
        [
            {"argv": fleet.impostor("world", "Actor C", "6"), "ready": True},
            {
                "argv": fleet.impostor("observer", "Actor A", "4", str(ACTIONS), member="Actor A"),
                "ready": True,
            },
        ]
    )
    world, observer = report["procs"]
    assert observer["code"] == 0, observer
    seen = json.loads(observer["stdout"].strip().splitlines()[-1])
    assert "Actor C" not in seen["robots"], seen
    assert not [name for name in seen["items"] if name.startswith("crate")], seen
    assert seen["impostor"]["ris"] > 0, seen
    assert seen["impostor"]["context"] > 0, seen
    assert world["code"] == 0, world
