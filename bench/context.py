"""Context Manager benchmarks: convergence of three robots after a change; queries on 10,000 items.

``context_converge_3_ms``: robots A, B and C are three processes, each with its own LCM
transport on ``udpm://`` (ttl 0) and a fleet key, inside a private network namespace made by
``unshare -n`` (loopback up, multicast routed to it), as in ``bench/ris.py``. A changes its
tree (adds an item); B and C note the wall clock when their listener is told and their
digest; the convergence time is the later of the two minus A's clock before the change (one
host clock), and the digests must equal A's. Without root, ``unshare`` or ``ip``, the three
robots run in this process on an in-process bus instead (noted).

Run ``python -m bench.context`` for the group alone; the coordinator and robot modes are the
programs the namespace runs.
"""

from __future__ import annotations

import json
import os
import random
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import IO, Any

from bench.common import Results, median, now, percentile

ROOT = Path(__file__).resolve().parent.parent
KEY = "c7" * 32
URL = "udpm://239.255.76.67:7667?ttl=0"


# ------------------------------------------------------------------------------ queries


def _big_tree() -> Any:
    from temoto.managers.context import ContextManager, Pose

    manager = ContextManager("bench")
    manager.add("world", "map")
    for b in range(10):
        manager.add(f"b{b}", "map", "world", Pose(100.0 * b))
        for r in range(10):
            room = f"b{b}r{r}"
            manager.add(room, "room", f"b{b}", Pose(0.0, 10.0 * r))
            for o in range(99):
                kind = "cup" if o == 0 else "object"
                manager.add(f"{room}o{o}", kind, room, Pose(0.1 * o, 0.2, 0.8))
    return manager


def _per_call_us(fn: Any, args: list[Any]) -> float:
    t0 = now()
    for arg in args:
        fn(arg)
    return (now() - t0) / len(args) * 1e6


def _bench_queries(out: Results, quick: bool) -> None:
    manager = _big_tree()
    try:
        size = len(manager)
        rng = random.Random(7)
        names = [
            f"b{rng.randrange(10)}r{rng.randrange(10)}o{rng.randrange(99)}" for _ in range(2000)
        ]
        reps = 5 if quick else 15
        get = median([_per_call_us(manager.get, names) for _ in range(reps)])
        world = median([_per_call_us(manager.world_pose, names) for _ in range(reps)])
        finds = median([_per_call_us(manager.find, ["cup"] * 50) for _ in range(reps)])
        rooms = [f"b{rng.randrange(10)}r{rng.randrange(10)}" for _ in range(50)]
        subtree = median([_per_call_us(manager.subtree, rooms) for _ in range(reps)])
        whole = median([_per_call_us(manager.subtree, [""] * 3) for _ in range(3)])
    finally:
        manager.close()
    how = f"{size} items (world/10 buildings/100 rooms/99 objects each), one process"
    out.add("context_query_10000_us", get, "us", f"{how}: get(name); median of {reps} x 2000")
    out.add("context_world_pose_10000_us", world, "us", f"{how}: world_pose (depth 4)")
    out.add("context_find_type_10000_us", finds, "us", f"{how}: find(type) -> 100 items")
    out.add("context_subtree_10000_us", subtree, "us", f"{how}: subtree(room) -> 100 items")
    out.add("context_subtree_all_10000_ms", whole / 1000, "ms", f"{how}: subtree() -> all")


# ------------------------------------------------------------------------------ convergence


def _available() -> str:
    if os.geteuid() != 0:
        return "needs root (a private network namespace)"
    for tool in ("unshare", "ip"):
        if shutil.which(tool) is None:
            return f"needs {tool}"
    return ""


def _converge_processes(rounds: int) -> list[float]:
    setup = 'ip link set lo up && ip route replace 224.0.0.0/4 dev lo && exec "$0" "$@"'
    env = {**os.environ, "PYTHONPATH": str(ROOT), "TEMOTO_FLEET_KEY": KEY}
    proc = subprocess.run(
        [
            "unshare",
            "-n",
            "sh",
            "-c",
            setup,
            sys.executable,
            "-m",
            "bench.context",
            "coordinator",
            str(rounds),
        ],
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
        cwd=ROOT,
        check=False,
    )
    if proc.returncode != 0:
        raise RuntimeError(f"context benchmark failed: {proc.stderr[-3000:]}")
    data: list[float] = json.loads(proc.stdout.strip().splitlines()[-1])["converge_s"]
    return data


def _converge_inprocess(rounds: int) -> list[float]:
    from temoto.managers.context import Change, ContextManager
    from temoto.transport import FleetAuth, FleetLink, InProcessTransport

    cond = threading.Condition()
    heard: dict[str, float] = {}
    transports, managers = [], []
    try:
        for name in ("A", "B", "C"):
            transport = InProcessTransport("bench-context")
            transports.append(transport)
            link = FleetLink(transport, FleetAuth("bench", name, bytes.fromhex(KEY)))
            manager = ContextManager(name, link=link)
            managers.append(manager)

            def told(change: Change, who: str = name) -> None:
                with cond:
                    for item in change.names:
                        heard[f"{who}:{item}"] = time.perf_counter()
                    cond.notify_all()

            if name != "A":
                manager.listen(told)
        a, b, c = managers
        a.add("map", "map")
        out = []
        for i in range(rounds + 3):
            item = f"obj{i}"
            t0 = time.perf_counter()
            a.add(item, "object", "map")
            with cond:
                cond.wait_for(lambda item=item: f"B:{item}" in heard and f"C:{item}" in heard, 5)
            if b.digest() != a.digest() or c.digest() != a.digest():
                raise RuntimeError("the trees differ after the change")
            if i >= 3:
                out.append(max(heard[f"B:{item}"], heard[f"C:{item}"]) - t0)
        return out
    finally:
        for manager in managers:
            manager.close()
        for transport in transports:
            transport.close()


def bench_context(quick: bool) -> Results:
    out = Results()
    _bench_queries(out, quick)
    rounds = 30 if quick else 200
    why = _available()
    if why:
        samples = _converge_inprocess(rounds)
        how = "A, B, C in one process on an in-process bus (no namespace: " + why + ")"
    else:
        samples = _converge_processes(rounds)
        how = "A, B, C as three processes, LCM udpm:// on loopback in a private namespace, key on"
    ms = [s * 1e3 for s in samples]
    out.add(
        "context_converge_3_ms",
        median(ms),
        "ms",
        f"{how}: A adds an item -> B's and C's listeners told, digests equal; median of {rounds}",
        ("<=", 20.0),
    )
    out.add("context_converge_3_ms_p99", percentile(ms, 99), "ms", "p99 of the same")
    return out


# ------------------------------------------------------------------------------ programs


def _robot(name: str) -> None:
    """A robot B or C: prints ``item wall_time count digest`` for every change it is told."""
    from temoto.managers.context import Change, ContextManager
    from temoto.transport import FleetAuth, FleetLink, key_from_env, open_transport

    transport = open_transport(URL)
    lock = threading.Lock()
    try:
        link = FleetLink(transport, FleetAuth("bench", name, key_from_env()))
        with ContextManager(name, link=link) as manager:

            def told(change: Change) -> None:
                t = time.time()
                count, digest = manager.digest()
                with lock:
                    for item in change.names:
                        print(f"{item} {t!r} {count} {digest}", flush=True)

            manager.listen(told)
            print("ready", flush=True)
            sys.stdin.read()  # until the coordinator closes our stdin
    finally:
        transport.close()


def _wait_line(pipe: IO[str], item: str) -> tuple[float, tuple[int, int]]:
    while True:
        line = pipe.readline()
        if not line:
            raise RuntimeError("a robot exited")
        parts = line.split()
        if parts and parts[0] == item:
            return float(parts[1]), (int(parts[2]), int(parts[3]))


def _coordinator(rounds: int) -> None:
    """Robot A: starts B and C, changes its tree ``rounds`` times, prints the timings as JSON."""
    from temoto.managers.context import ContextManager
    from temoto.transport import FleetAuth, FleetLink, key_from_env, open_transport

    children = [
        subprocess.Popen(
            [sys.executable, "-m", "bench.context", "robot", name],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            cwd=ROOT,
        )
        for name in ("B", "C")
    ]
    transport = open_transport(URL)
    try:
        for child in children:
            assert child.stdout is not None
            if child.stdout.readline().strip() != "ready":
                raise RuntimeError("a robot did not start")
        link = FleetLink(transport, FleetAuth("bench", "A", key_from_env()))
        samples = []
        with ContextManager("A", link=link) as a:
            a.add("map", "map")
            for child in children:
                assert child.stdout is not None
                _wait_line(child.stdout, "map")
            for i in range(rounds + 5):
                item = f"obj{i}"
                t0 = time.time()
                a.add(item, "object", "map")
                seen = []
                for child in children:
                    assert child.stdout is not None
                    seen.append(_wait_line(child.stdout, item))
                if any(digest != a.digest() for _, digest in seen):
                    raise RuntimeError(f"the trees differ after {item}")
                if i >= 5:
                    samples.append(max(t for t, _ in seen) - t0)
        print(json.dumps({"converge_s": samples}))
    finally:
        for child in children:
            if child.stdin is not None:
                child.stdin.close()
        for child in children:
            child.wait(timeout=30)
        transport.close()


def main(argv: list[str]) -> None:
    if argv[:1] == ["robot"]:
        _robot(argv[1])
    elif argv[:1] == ["coordinator"]:
        _coordinator(int(argv[1]))
    else:
        for metric in bench_context(quick="--quick" in argv).metrics:
            print(f"{metric.name:32} {metric.value:10.3f} {metric.unit:3} {metric.note}")


if __name__ == "__main__":
    main(sys.argv[1:])
