"""A manager process for the crash-consistency test (not a test module).

Usage: ``python crash_worker.py CATALOG WORKDIR SEED START END [--restore]``

It builds a Registrar on CATALOG with a Process Manager and a "group" server whose resources
depend on 1-3 process resources (nested dependencies), prints its accounting as one JSON line
(``state {...}``), then runs operations START..END-1, each after a line on stdin. Operation i
is chosen from the registrar's own state with ``random.Random(f"{SEED}-{i}")``: release one of
the consumers' references, or request a group or a process for one of three consumers. It
prints ``begin i`` before and ``done i <json>`` after each operation, so the test knows which
ones completed before it SIGKILLs the process. After END it prints ``ops-done``, waits for a
line on stdin (the test no longer kills it), releases everything, prints its final accounting
and ``finished``, and exits.

Every child process gets ``--touch WORKDIR/<name>.pid`` on its command line, so the test can
find every process this worker ever started (orphans included) by WORKDIR.
"""

from __future__ import annotations

import json
import random
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from temoto.core.registrar import LoadContext, Registrar, ResourceServer
from temoto.core.registrar.messages import canonical_json
from temoto.managers.process import ProcessManager, ProcessRequest

PROCESSES = ("p0", "p1", "p2", "p3", "p4", "p5")
GROUPS = ("g0", "g1", "g2", "g3")
CLIENTS = ("c0", "c1", "c2")


@dataclass(frozen=True)
class GroupRequest:
    name: str
    members: tuple[str, ...]

    def __post_init__(self) -> None:
        object.__setattr__(self, "members", tuple(self.members))


@dataclass(frozen=True)
class GroupResponse:
    pids: tuple[int, ...]

    def __post_init__(self) -> None:
        object.__setattr__(self, "pids", tuple(self.pids))


def process_request(workdir: Path, name: str) -> ProcessRequest:
    return ProcessRequest(
        executable=sys.executable,
        args=("-m", "temoto.testing.child", "--touch", str(workdir / f"{name}.pid")),
    )


class GroupServer(ResourceServer[GroupRequest, GroupResponse]):
    name = "group"
    request_type = GroupRequest
    response_type = GroupResponse

    def __init__(self, registrar: Registrar, workdir: Path) -> None:
        self.registrar = registrar
        self.workdir = workdir

    def on_load(self, request: GroupRequest, ctx: LoadContext) -> GroupResponse:
        pids = []
        for member in request.members:
            ref = self.registrar.call("process", process_request(self.workdir, member))
            pids.append(ref.response.pid)
        return GroupResponse(tuple(pids))

    def on_unload(self, request: GroupRequest, response: GroupResponse) -> None:
        pass


def accounting(registrar: Registrar) -> dict[str, Any]:
    refs = [
        {"id": r.id, "client": r.client, "resource": r.resource_id}
        for r in registrar.references()
        if not r.holder
    ]
    resources = []
    for info in registrar.resources():
        resources.append(
            {
                "id": info.id,
                "server": info.server,
                "key": canonical_json(info.request),
                "pid": getattr(info.response, "pid", None),
                "refs": len(info.references),
                "deps": sorted(d.id for d in registrar.dependencies(info.id)),
                "failed": info.failed,
            }
        )
    return {"refs": sorted(refs, key=lambda r: r["id"]), "resources": resources}


def say(line: str) -> None:
    sys.stdout.write(line + "\n")
    sys.stdout.flush()


def main() -> int:
    catalog, workdir, seed, start, end = (
        Path(sys.argv[1]),
        Path(sys.argv[2]),
        sys.argv[3],
        int(sys.argv[4]),
        int(sys.argv[5]),
    )
    restore = "--restore" in sys.argv
    registrar = Registrar("crash", catalog=catalog, restore=restore)
    # children write to files, not to our stdout: the test reads it until end-of-file
    manager = ProcessManager(registrar, grace=0.5, log_dir=workdir / "logs")
    registrar.register(GroupServer(registrar, workdir))
    say("state " + json.dumps(accounting(registrar)))
    for i in range(start, end):
        # Each operation waits for the test's go-ahead: the first while it checks the restored
        # state, the others so that this process never runs ahead of what the test has read.
        sys.stdin.readline()
        rng = random.Random(f"{seed}-{i}")
        held = sorted(r.id for r in registrar.references() if not r.holder)
        say(f"begin {i}")
        if held and rng.random() < 0.45:
            ref_id = rng.choice(held)
            registrar.release(ref_id)
            say(f"done {i} " + json.dumps({"op": "release", "id": ref_id}))
            continue
        client = rng.choice(CLIENTS)
        if rng.random() < 0.5:
            members = tuple(sorted(rng.sample(PROCESSES, rng.randint(1, 3))))
            request: Any = GroupRequest(rng.choice(GROUPS), members)
            server = "group"
        else:
            request = process_request(workdir, rng.choice(PROCESSES))
            server = "process"
        ref = registrar.call(server, request, client=client)
        say(
            f"done {i} "
            + json.dumps(
                {
                    "op": "call",
                    "id": ref.id,
                    "client": client,
                    "server": server,
                    "key": canonical_json(request),
                    "resource": ref.resource_id,
                }
            )
        )
    say("ops-done")
    sys.stdin.readline()  # the test stops killing before the final release
    for client in CLIENTS:
        registrar.release_client(client)
    say("state " + json.dumps(accounting(registrar)))
    manager.shutdown()
    registrar.close()
    say("finished")
    return 0


if __name__ == "__main__":
    sys.exit(main())
