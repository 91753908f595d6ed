"""Fleet link benchmarks: handshake, notification latency, authenticated throughput.

Every actor is a separate process with its own LCM transport on ``udpm://`` (ttl 0), inside a
private network namespace made by ``unshare -n`` (loopback up, multicast routed to it), so the
host's interfaces are never touched. Then the same for 3 actors and the flood over Zenoh, twice,
each in another private namespace on loopback TCP: every process a client of a ``temoto
router`` (``*_zenoh``), and Zenoh peers that connect to each other directly (``*_zenoh_peers``,
like LCM's processes: no hop in the middle); skipped with a note when the zenoh extra is
missing. Needs root, ``unshare`` and ``ip``; otherwise the group is skipped with a note. All
processes share the host's clock, so one-way times are differences of ``time.time()`` taken in
different processes.
"""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

from bench.common import Results, median, percentile
from temoto.transport.identity import Identity, Roster

URL = "udpm://239.255.76.67:7667?ttl=0"
ROUTER = "tcp/127.0.0.1:7447"
ZENOH_URL = f"zenoh:{ROUTER}"
# Zenoh peers: process i listens on port 7450 + i; the first waits, the others connect to it
# and, told of each other by Zenoh's gossip, to each other (the RUNNER gives process i the URL
# [min(i, 1)] with {port} filled in). Without a listener of its own on loopback a peer is not
# reachable by the others (the default one, on [::]:0, is not advertised on loopback), and
# the first one forwards nothing between them.
PEER = "tcp/127.0.0.1:7450"
ZENOH_PEER_URLS = [f"zenoh:?listen={PEER}", f"zenoh:{PEER}?mode=peer&listen=tcp/127.0.0.1:{{port}}"]
KEY = "42" * 32

# One actor process: build the link, say "ready", then per round wait for "go <t>", shake hands,
# notify or expect one action, and report the times as one JSON line.
WORKER = r"""
import json, sys, threading, time
from temoto.core.states import Result
from temoto.fleet import FleetActorLink
from temoto.transport import FleetAuth, FleetLink, key_from_text, open_transport
actor, actors, url, key = sys.argv[1], json.loads(sys.argv[2]), sys.argv[3], sys.argv[4]
transport = open_transport(url)
link = FleetActorLink(FleetLink(transport, FleetAuth("bench", actor, key_from_text(key))), actor)
print("ready", flush=True)
for line in sys.stdin:
    words = line.split()
    if words[0] == "quit":
        break
    session, t_go = words[1], float(words[2])
    before = link.stats
    try:
        run = link.handshake("bench", session, actors, 10.0)
    except Exception as err:
        print(json.dumps({"hand": None, "sent": 0, "error": str(err)[:200]}), flush=True)
        continue
    t_hand = time.time()
    sent = link.stats["handshakes_sent"] - before["handshakes_sent"]
    got_hs = link.stats["handshakes_received"] - before["handshakes_received"]
    me, n = actors.index(actor), len(actors)
    # the ring's expectations first: a ring notification may come before Act_0's
    lock, heard, turn, got_all = threading.Lock(), set(), threading.Event(), threading.Event()
    def on_ring(j):
        def take(result, outputs):
            with lock:
                heard.add(j)
                if len(heard) == n - 1:
                    got_all.set()
            if j == me - 1:
                turn.set()
        return take
    for j in range(n):
        if j != me:
            link.expect("bench", run, f"Ring_{j}", actors[j], on_ring(j))
    got = []
    if me == 0:
        t_send = time.time()
        try:
            link.notify("bench", run, "Act_0", Result.TRUE, {"x": 1}, actors[1:], 10.0)
            acked, why = time.time() - t_send, None
        except Exception as err:
            acked, why = None, str(err)[:200]
        out = {"hand": t_hand - t_go, "send": t_send, "acked": acked, "sent": sent,
               "got": got_hs, "error": why}
    else:
        done = threading.Event()
        link.expect("bench", run, "Act_0", actors[0],
                    lambda r, o: (got.append(time.time()), done.set()))
        t_expect = time.time()  # a notification that came before waited for this
        done.wait(10.0)
        out = {"hand": t_hand - t_go, "recv": got[0] if got else None, "sent": sent,
               "got": got_hs, "expect": t_expect}
    # the ring: actor i waits for Ring_{i-1} of actor i-1, then notifies Ring_i to all (as
    # the engine does for a node of a shared graph whose every node is on the next actor)
    if me == 0:
        out["ring_start"] = time.time()
    ring_error = None
    if me == 0 or turn.wait(30.0):
        try:
            link.notify("bench", run, f"Ring_{me}", Result.TRUE, {}, actors, 30.0)
        except Exception as err:
            ring_error = str(err)[:200]
    else:
        ring_error = f"Ring_{me - 1} did not come"
    if ring_error is None and not got_all.wait(30.0):
        ring_error = f"heard {len(heard)} of {n - 1} ring notifications"
    out["ring_done"] = None if ring_error else time.time()
    out["ring_error"] = ring_error
    out["stats"] = link.stats
    link.end("bench", run)
    print(json.dumps(out), flush=True)
link.close()
transport.close()
"""

# Throughput: "send" publishes N sealed messages as fast as it can; "recv" counts them. Before
# that the sender probes until the receiver has heard one (and says "ready"): over Zenoh a
# subscription reaches the publishers asynchronously, and the first messages were lost.
FLOOD = r"""
import select, sys, threading, time
from temoto.transport import FleetAuth, FleetLink, key_from_text, open_transport
from temoto.transport.identity import Credentials
role, url, key, n = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4])
transport = open_transport(url)
if key.startswith("roster:"):  # a key per member: identities send.id, recv.id in that folder
    folder = key[len("roster:"):]
    secret = Credentials.load(f"{folder}/{role}.id", f"{folder}/roster.yaml")
else:
    secret = key_from_text(key)
link = FleetLink(transport, FleetAuth("bench", role, secret))
if role == "recv":
    count, first, last, done = [0], [0.0], [0.0], threading.Event()
    def on(msg):
        count[0] += 1
        if count[0] == 1: first[0] = time.time()
        last[0] = time.time()
        if count[0] >= n: done.set()
    link.listen("BENCH_FLOOD", on, queue_capacity=100000)
    heard, probes = threading.Event(), [0]
    def on_probe(msg):
        probes[0] += 1
        heard.set()
    link.listen("BENCH_PROBE", on_probe)
    heard.wait(60)
    print("ready", flush=True)
    seen = -1
    while not done.wait(0.5) and count[0] != seen:  # ends when all came, or none for 0.5 s
        seen = count[0]
    print(count[0], first[0], last[0], link.stats.get("accepted", 0) - probes[0], flush=True)
else:
    payload = b"x" * 200
    if not link.wait_for_peers(["recv"], 30.0):  # the hellos crossed: every message opens
        sys.exit(f"flood sender: no session with the receiver within 30 s ({url})")
    print("ready", flush=True)
    while not select.select([sys.stdin], [], [], 0.01)[0]:
        link.send("BENCH_PROBE", "bench_t", b"")
    sys.stdin.readline()
    t0 = time.time()
    for i in range(n):
        link.send("BENCH_FLOOD", "bench_t", payload)
    print(time.time() - t0, flush=True)
transport.close()
"""

# Runs inside the namespace: routes multicast to loopback, then runs the spec's scenario.
RUNNER = r"""
import json, os, subprocess, sys, time
subprocess.run(["ip", "link", "set", "lo", "up"], check=True)
subprocess.run(["ip", "route", "replace", "224.0.0.0/4", "dev", "lo"], check=True)
spec = json.loads(sys.argv[1])
def start(code, args):
    return subprocess.Popen([sys.executable, "-c", code, *args], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
def url(i):  # one URL for all, or [the first process's, the others' with {port}]
    urls = spec["url"]
    return urls if isinstance(urls, str) else urls[min(i, 1)].format(port=7450 + i)
router = None
if spec.get("router"):  # Zenoh: every process is a client of this router
    router = subprocess.Popen([sys.executable, "-m", "temoto", "router", "--listen",
                               spec["router"]], stdin=subprocess.DEVNULL,
                              stdout=subprocess.PIPE, text=True)
    line = router.stdout.readline()
    assert "listening on" in line, f"the router did not start: {line!r}"
result, took = {}, {}
for n in spec["sizes"]:
    t0 = time.monotonic()
    actors = [f"actor_{i}" for i in range(n)]
    procs = [start(spec["worker"], [a, json.dumps(actors), url(i), spec["key"]])
             for i, a in enumerate(actors)]
    for p in procs:
        line = p.stdout.readline().strip()
        assert line == "ready", f"{n} actors: an actor did not start: {line!r}"
    t1 = time.monotonic()
    rounds = []
    for r in range(spec["rounds_of"].get(str(n), spec["rounds"])):
        t_go = time.time()
        for p in procs:
            p.stdin.write(f"go s{n}_{r} {t_go}\n"); p.stdin.flush()
        rounds.append([json.loads(p.stdout.readline()) for p in procs])
    for p in procs:
        p.stdin.write("quit\n"); p.stdin.flush()
    for p in procs:
        p.wait(30)
    result[str(n)] = rounds
    took[f"{n} actors"] = [round(t1 - t0, 2), round(time.monotonic() - t1, 2)]
for flood, key in spec.get("floods", {"flood": spec["key"]}).items():
    t0 = time.monotonic()
    recv = start(spec["flood"], ["recv", url(0), key, str(spec["flood_n"])])
    send = start(spec["flood"], ["send", url(1), key, str(spec["flood_n"])])
    line = send.stdout.readline().strip()
    assert line == "ready", f"{flood}: the sender did not start: {line!r}"
    line = recv.stdout.readline().strip()
    assert line == "ready", f"{flood}: the receiver heard no probe: {line!r}"
    send.stdin.write("go\n"); send.stdin.flush()
    send_s = float(send.stdout.readline())
    count, first, last, accepted = recv.stdout.readline().split()
    send.wait(30); recv.wait(30)
    result[flood] = {"sent": spec["flood_n"], "send_s": send_s, "received": int(count),
                     "first": float(first), "last": float(last), "accepted": int(accepted)}
    took[flood] = [0.0, round(time.monotonic() - t0, 2)]
result["took"] = took
if router is not None:
    router.terminate()
    router.wait(10)
print(json.dumps(result))
"""


def _available() -> str:
    if os.geteuid() != 0:
        return "the fleet benchmarks need root (a private network namespace per run)"
    for tool in ("unshare", "ip"):
        if shutil.which(tool) is None:
            return f"the fleet benchmarks need {tool}"
    return ""


def _run(spec: dict[str, Any]) -> dict[str, Any]:
    """Run RUNNER with ``spec`` in a private network namespace; its JSON result."""
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parent.parent)}
    env.pop("TEMOTO_FLEET_KEY", None)
    proc = subprocess.run(
        ["unshare", "-n", sys.executable, "-c", RUNNER, json.dumps(spec)],
        capture_output=True,
        text=True,
        timeout=600,
        env=env,
        check=False,
    )
    if proc.returncode != 0:
        raise RuntimeError(f"fleet benchmark failed: {proc.stderr[-3000:]}")
    result: dict[str, Any] = json.loads(proc.stdout)
    return result


def bench_fleet(quick: bool) -> Results:
    out = Results()
    why = _available()
    if why:
        out.notes.append(f"{why}: handshake_*/notify_* skipped")
        return out
    rounds = 6 if quick else 50
    # The big fleets: full 10, 20 and 50 actors; quick only 10 (the quick contract is 60 s for
    # every group, and each actor is a Python process that imports temoto on 2 cores: 20 of
    # them took 3.5 s to start).
    bigs = (10,) if quick else (10, 20, 50)
    big_rounds = {"10": 1 if quick else 3, "20": 3, "50": 5}
    flood_n = 10_000 if quick else 100_000  # quick: each of the four floods ≈ 1 s
    folder = Path(tempfile.mkdtemp(prefix="temoto-bench-keys-"))
    roster = Roster({})
    for role in ("send", "recv"):
        identity = Identity.generate(role)
        identity.save(folder / f"{role}.id")
        roster.add(role, identity.public_key)
    roster.save(folder / "roster.yaml")
    spec = {
        "sizes": [2, 3, 5, *bigs],
        "rounds": rounds,
        "rounds_of": {str(n): big_rounds[str(n)] for n in bigs},
        "worker": WORKER,
        "flood": FLOOD,
        "flood_n": flood_n,
        "url": URL,
        "key": KEY,
        "floods": {"flood": KEY, "flood_roster": f"roster:{folder}"},
    }
    try:
        data = _run(spec)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    _note_took(out, data, "LCM")
    for n in (2, 3, 5):  # a handshake that timed out (a loaded machine) is left out, and said
        done = [rnd for rnd in data[str(n)] if all(w["hand"] is not None for w in rnd)]
        if len(done) < len(data[str(n)]):
            out.notes.append(f"{n} actors: {len(data[str(n)]) - len(done)} handshakes timed out")
        data[str(n)] = done
    for n in (2, 3, 5):
        per_round = [max(w["hand"] for w in rnd) * 1e3 for rnd in data[str(n)]]
        name = f"handshake_{n}_actors_ms"
        out.add(
            name,
            median(per_round),
            "ms",
            f"{n} actor processes, LCM udpm:// on loopback in a private namespace, key on:"
            f" 'go' written to all -> the last one's handshake() returned; median of {rounds}"
            " rounds (new session each)",
            ("<=", 5.0) if n == 3 else None,
        )
        out.add(f"{name}_p99", percentile(per_round, 99), "ms", f"p99 of the same {rounds}")

    def per_actor_s(rnds: list[list[dict[str, Any]]], key: str = "sent") -> float:
        return median([sum(w[key] / max(w["hand"], 1e-3) for w in rnd) / len(rnd) for rnd in rnds])

    completed: dict[int, list[list[dict[str, Any]]]] = {}
    for n in bigs:
        tried = data[str(n)]
        big = [rnd for rnd in tried if all(w["hand"] is not None for w in rnd)]
        completed[n] = big
        if len(big) < len(tried):
            out.notes.append(
                f"{n} actors: {len(tried) - len(big)} of {len(tried)} handshakes did not"
                " complete within 10 s"
            )
        if not big:
            continue
        out.add(
            f"handshake_{n}_actors_ms",
            median([max(w["hand"] for w in rnd) * 1e3 for rnd in big]),
            "ms",
            f"{n} actor processes (one per actor, spawned before 'go'), as"
            f" handshake_N_actors_ms; median of the {len(big)} of {len(tried)} rounds that"
            " completed",
            ("<=", 5000.0) if n == 50 else None,
        )
        out.add(
            f"handshake_msgs_per_actor_s_{n}",
            per_actor_s(big),
            "1/s",
            f"{n} actors: handshake_t messages an actor sent during its handshake() (JOINs,"
            " READY, heartbeats) / its handshake time, mean over actors, median of"
            f" {len(big)} rounds; received: {per_actor_s(big, 'got'):.0f}/s per actor",
        )
    biggest = max((n for n in bigs if completed[n]), default=None)
    if biggest is not None:
        out.add(
            "handshake_msgs_per_actor_s",
            per_actor_s(completed[biggest]),
            "1/s",
            f"handshake_msgs_per_actor_s_{biggest} (the biggest fleet of this mode); 5 actors:"
            f" {per_actor_s(data['5']):.1f}/s (a handshake of a few ms: its first JOINs and"
            " its READY)",
        )

    def ring_ms(rnds: list[list[dict[str, Any]]]) -> list[float]:
        return [
            (max(w["ring_done"] for w in rnd) - rnd[0]["ring_start"]) * 1e3
            for rnd in rnds
            if all(w.get("ring_done") is not None for w in rnd)
        ]

    ring_sizes = [(5, data["5"])] + ([(biggest, completed[biggest])] if biggest else [])
    for n, rnds in ring_sizes:
        rings = ring_ms(rnds)
        if len(rings) < len(rnds):
            errors = {w["ring_error"] for rnd in rnds for w in rnd if w.get("ring_error")}
            out.notes.append(
                f"{n} actors: {len(rnds) - len(rings)} of {len(rnds)} rings did not end"
                f" everywhere ({'; '.join(sorted(errors))[:300]})"
            )
        if rings:
            out.add(
                f"ring_{n}_actors_ms",
                median(rings),
                "ms",
                f"{n} actor processes after their handshake: actor i waits for Ring_(i-1) of"
                f" actor i-1, then notifies Ring_i to all the others; actor 0's first notify()"
                f" -> the last actor has every Ring_j and its own acknowledged; median of the"
                f" {len(rings)} of {len(rnds)} rounds that ended",
                None,
            )
    for n, rnds in completed.items():
        unacked = sum(1 for rnd in rnds if rnd[0].get("acked") is None)
        if unacked:
            out.notes.append(
                f"{n} actors: the notification to {n - 1} actors was not acknowledged within"
                f" 10 s in {unacked} of {len(rnds)} rounds"
            )
    latencies = []
    acked = []
    for rnd in data["3"]:
        sender = rnd[0]
        if sender["acked"] is not None:
            acked.append(sender["acked"] * 1e3)
        latencies += [(w["recv"] - sender["send"]) * 1e3 for w in rnd[1:] if w["recv"]]
    out.add(
        "notify_latency_ms",
        median(latencies),
        "ms",
        f"3 actors: time.time() before notify() in one process -> the expect() callback in"
        f" another; median of {len(latencies)} (2 receivers x {rounds} rounds)",
        ("<=", 1.0),
    )
    out.add("notify_latency_ms_p99", percentile(latencies, 99), "ms", "p99 of the same")
    _add_ready_latency(out, data["3"], "", None)
    out.add(
        "notify_acked_ms",
        median(acked),
        "ms",
        "3 actors: notify() call -> returned (both acknowledgements in); median",
    )
    flood = data["flood"]
    span = max(flood["last"] - flood["first"], 1e-9)
    out.add(
        "fleet_msgs_per_s",
        flood["received"] / span,
        "1/s",
        f"one process sends {flood['sent']:,} sealed 200-byte messages (fleet key: encrypted"
        f" with ChaCha20-Poly1305 in a session per boot, docs/security.md) as fast as it can,"
        f" another opens them: received {flood['received']:,} (UDP drops the rest when the"
        f" receiver falls behind), accepted {flood['accepted']:,}; received / (last - first"
        f" arrival)",
    )
    roster_flood = data["flood_roster"]
    out.add(
        "fleet_msgs_per_s_roster",
        roster_flood["received"] / max(roster_flood["last"] - roster_flood["first"], 1e-9),
        "1/s",
        f"as fleet_msgs_per_s with a key per member (identities and a roster: a MAC per"
        f" recipient besides the encryption): received {roster_flood['received']:,},"
        f" accepted {roster_flood['accepted']:,}",
    )
    out.add(
        "fleet_send_msgs_per_s",
        flood["sent"] / max(flood["send_s"], 1e-9),
        "1/s",
        "the sender's rate: seal + publish",
    )
    _bench_zenoh(out, spec, rounds, quick)
    return out


def _bench_zenoh(out: Results, lcm_spec: dict[str, Any], rounds: int, quick: bool) -> None:
    """The 3-actor handshake, notification latency and flood again, over Zenoh, twice.

    First through a ``temoto router`` (``*_zenoh``: every message crosses it, as between
    subnets), then (full mode only: the quick run's 60 s) between peers connected directly
    (``*_zenoh_peers``: the same topology as LCM's), each in a namespace of its own.
    """
    if importlib.util.find_spec("zenoh") is None:
        out.notes.append("the zenoh extra is not installed: *_zenoh skipped")
        return
    # the goal: within 2x of LCM, measured in the same run
    lcm = {m.name: m.value for m in out.metrics}
    base = {**lcm_spec, "sizes": [3], "rounds_of": {}}
    base.pop("floods", None)  # one flood, with the fleet key (the default)
    _bench_zenoh_run(
        out,
        lcm,
        {**base, "url": ZENOH_URL, "router": ROUTER},
        "_zenoh",
        "3 actor processes, each a Zenoh client of a temoto router, loopback TCP, key on",
        "sender -> router -> receiver",
    )
    if quick:
        out.notes.append("*_zenoh_peers: full mode only")
        return
    _bench_zenoh_run(
        out,
        lcm,
        {**base, "url": ZENOH_PEER_URLS},
        "_zenoh_peers",
        f"3 actor processes, Zenoh peers, each listening on loopback TCP; they connect to the"
        f" first one's {PEER} and to each other, key on",
        "sender -> receiver, no router",
    )


def _bench_zenoh_run(
    out: Results, lcm: dict[str, float], spec: dict[str, Any], suffix: str, where: str, path: str
) -> None:
    """One Zenoh topology: its metrics are named ``<LCM metric><suffix>``."""

    def within_2x(name: str, bigger_is_better: bool = False) -> tuple[str, float] | None:
        if name not in lcm:
            return None
        return (">=", lcm[name] / 2) if bigger_is_better else ("<=", lcm[name] * 2)

    data = _run(spec)
    _note_took(out, data, suffix[1:])
    done = [rnd for rnd in data["3"] if all(w["hand"] is not None for w in rnd)]
    if len(done) < len(data["3"]):
        out.notes.append(
            f"{suffix[1:]}, 3 actors: {len(data['3']) - len(done)} handshakes timed out"
        )
    if done:
        out.add(
            f"handshake_3_actors_ms{suffix}",
            median([max(w["hand"] for w in rnd) * 1e3 for rnd in done]),
            "ms",
            f"as handshake_3_actors_ms over Zenoh ({where}); median of {len(done)} rounds",
            within_2x("handshake_3_actors_ms"),
        )
    latencies = [(w["recv"] - rnd[0]["send"]) * 1e3 for rnd in done for w in rnd[1:] if w["recv"]]
    if latencies:
        out.add(
            f"notify_latency_ms{suffix}",
            median(latencies),
            "ms",
            f"as notify_latency_ms over Zenoh ({where}: {path}); median of {len(latencies)}",
            within_2x("notify_latency_ms"),
        )
        out.add(f"notify_latency_ms{suffix}_p99", percentile(latencies, 99), "ms", "p99")
        _add_ready_latency(out, done, suffix, within_2x("notify_latency_ready_ms"))
    flood = data["flood"]
    out.add(
        f"fleet_msgs_per_s{suffix}",
        flood["received"] / max(flood["last"] - flood["first"], 1e-9),
        "1/s",
        f"as fleet_msgs_per_s over Zenoh ({path}, loopback TCP): received"
        f" {flood['received']:,} of {flood['sent']:,}, accepted {flood['accepted']:,}; the"
        f" sender's rate {flood['sent'] / max(flood['send_s'], 1e-9):,.0f}/s",
        within_2x("fleet_msgs_per_s", bigger_is_better=True),
    )


def _note_took(out: Results, data: dict[str, Any], label: str) -> None:
    """Where a fleet run's time went: seconds to start each part's processes, then to run it."""
    took = data.pop("took", {})
    parts = ", ".join(f"{part} {start:g} + {run:g}" for part, (start, run) in took.items())
    out.notes.append(f"{label} run, seconds (start + run): {parts}")


def _add_ready_latency(
    out: Results, rnds: list[list[dict[str, Any]]], suffix: str, goal: tuple[str, float] | None
) -> None:
    """``notify_latency_ready_ms<suffix>``: the notifications whose receiver was waiting.

    notify_latency_ms also counts the time a receiver was still ending its own handshake when
    the notification came (it waits for the receiver's expect()): the actors' handshakes end
    up to a few ms apart on a loaded machine. This counts only receivers whose expect() was
    registered before the sender's notify() began.
    """
    ready = [
        (w["recv"] - rnd[0]["send"]) * 1e3
        for rnd in rnds
        for w in rnd[1:]
        if w["recv"] and w["expect"] < rnd[0]["send"]
    ]
    total = sum(1 for rnd in rnds for w in rnd[1:] if w["recv"])
    if ready:
        out.add(
            f"notify_latency_ready_ms{suffix}",
            median(ready),
            "ms",
            f"as notify_latency_ms{suffix}, for the {len(ready)} of {total} receivers that were"
            " waiting (their expect() registered) before notify() began; median",
            goal,
        )
