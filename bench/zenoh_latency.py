"""Where a Zenoh message's time goes: transport ping-pong, and fleets of N actor processes.

``python -m bench.zenoh_latency [--reps 3] [--count 500]``: in a private network namespace
(``unshare -n``; needs root and ``ip``), two processes bounce a 300-byte message through
:class:`~temoto.transport.base.Transport` ``publish``/``subscribe``: over LCM (``udpm://``),
between Zenoh peers, and between Zenoh clients of a ``temoto router``; each variant ``--reps``
times, interleaved, so that the load of the machine falls on all alike. Prints the median
one-way time (half the round trip) of each repetition, in ms.

``python -m bench.zenoh_latency --actors 50 [--rounds 3]``: the fleet group's actor program
(bench/fleet.py) with N processes, over Zenoh clients of a ``temoto router`` and then over LCM:
per round the time until every actor's ``handshake()`` returned and the ring of notifications
through all of them (``handshake_N_actors_ms`` and ``ring_N_actors_ms`` of the full fleet group,
which runs them over LCM only).

Not part of ``python -m bench``: docs/zenoh.md ("Latency") and bench/README.md quote it.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

from bench import fleet
from bench.common import median

# One side of the ping-pong: "pong" answers every PING with a PONG; "ping" measures.
PINGPONG = r"""
import statistics, sys, threading, time
from temoto.transport import open_transport
role, url, count = sys.argv[1], sys.argv[2], int(sys.argv[3])
t = open_transport(url)
me, other = ("PING", "PONG") if role == "ping" else ("PONG", "PING")
got, stamps = threading.Event(), []
def on(channel, data):
    if role == "pong":
        t.publish(me, data)
    else:
        stamps.append(time.perf_counter())
        got.set()
t.subscribe(other, on)
if role == "pong":
    print("ready", flush=True)
    sys.stdin.readline()
else:
    while True:  # until the other side answers: its subscription has reached us
        got.clear()
        t.publish(me, b"x")
        if got.wait(0.05):
            break
    one_way = []
    for _ in range(count):
        got.clear()
        sent = time.perf_counter()
        t.publish(me, b"y" * 300)
        if not got.wait(2.0):
            raise SystemExit("no answer within 2 s")
        one_way.append((stamps[-1] - sent) / 2 * 1e3)
        time.sleep(0.002)  # idle between messages, as a fleet's notifications are
    print(statistics.median(one_way), flush=True)
t.close()
"""

# Runs inside the namespace: the router, then every variant --reps times.
RUNNER = r"""
import json, subprocess, sys
subprocess.run(["ip", "link", "set", "lo", "up"], check=True)
subprocess.run(["ip", "route", "replace", "224.0.0.0/4", "dev", "lo"], check=True)
spec = json.loads(sys.argv[1])
router = subprocess.Popen([sys.executable, "-m", "temoto", "router", "--listen",
                           "tcp/127.0.0.1:7447"], stdin=subprocess.DEVNULL,
                          stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
assert "listening on" in router.stdout.readline()
out = {name: [] for name in spec["variants"]}
for _ in range(spec["reps"]):
    for name, (ping_url, pong_url) in spec["variants"].items():
        pong = subprocess.Popen([sys.executable, "-c", spec["code"], "pong", pong_url, "0"],
                                stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        assert pong.stdout.readline().strip() == "ready"
        ping = subprocess.run([sys.executable, "-c", spec["code"], "ping", ping_url,
                               str(spec["count"])], capture_output=True, text=True, timeout=120)
        pong.stdin.write("\n")
        pong.stdin.flush()
        pong.wait(30)
        if ping.returncode != 0:
            raise SystemExit(f"{name}: {ping.stderr[-2000:]}")
        out[name].append(float(ping.stdout))
router.terminate()
router.wait(10)
print(json.dumps(out))
"""

VARIANTS = {
    "lcm": (fleet.URL, fleet.URL),
    "zenoh_peers": ("zenoh:?listen=tcp/127.0.0.1:7448", "zenoh:tcp/127.0.0.1:7448?mode=peer"),
    "zenoh_router": ("zenoh:tcp/127.0.0.1:7447", "zenoh:tcp/127.0.0.1:7447"),
}


def ping_pong(reps: int, count: int) -> dict[str, list[float]]:
    """Median one-way ms of each repetition, by variant."""
    spec = {"variants": VARIANTS, "reps": reps, "count": count, "code": PINGPONG}
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parent.parent)}
    proc = subprocess.run(
        ["unshare", "-n", sys.executable, "-c", RUNNER, json.dumps(spec)],
        capture_output=True,
        text=True,
        timeout=600,
        env=env,
        check=False,
    )
    if proc.returncode != 0:
        raise SystemExit(f"ping-pong failed: {proc.stderr[-3000:]}")
    result: dict[str, list[float]] = json.loads(proc.stdout)
    return result


def fleet_rounds(url: str | list[str], n: int, rounds: int, router: bool) -> list[dict[str, float]]:
    """Handshake and ring ms of each round of ``n`` actor processes (bench/fleet.py's worker)."""
    spec: dict[str, object] = {
        "sizes": [n],
        "rounds": rounds,
        "rounds_of": {},
        "worker": fleet.WORKER,
        "flood": fleet.FLOOD,
        "flood_n": 100,
        "key": fleet.KEY,
        "url": url,
    }
    if router:
        spec["router"] = fleet.ROUTER
    out = []
    for rnd in fleet._run(spec)[str(n)]:
        hand = [w["hand"] for w in rnd]
        ring = [w.get("ring_done") for w in rnd]
        out.append(
            {
                "handshake_ms": max(hand) * 1e3 if None not in hand else float("nan"),
                "ring_ms": (max(ring) - rnd[0]["ring_start"]) * 1e3
                if None not in ring
                else float("nan"),
            }
        )
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--reps", type=int, default=3, help="repetitions of each variant")
    parser.add_argument("--count", type=int, default=500, help="messages per repetition")
    parser.add_argument("--actors", type=int, help="run N actor processes instead")
    parser.add_argument("--rounds", type=int, default=3, help="rounds of --actors")
    args = parser.parse_args()
    if os.geteuid() != 0:
        raise SystemExit("needs root (a private network namespace)")
    print(f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    if args.actors:
        for name, url, router in (
            ("zenoh_router", fleet.ZENOH_URL, True),
            ("lcm", fleet.URL, False),
        ):
            rounds = fleet_rounds(url, args.actors, args.rounds, router)
            for key in ("handshake_ms", "ring_ms"):
                values = [r[key] for r in rounds]
                shown = ", ".join(f"{v:.0f}" for v in values)
                print(
                    f"{name:13s} {args.actors} actors {key}: median {median(values):.0f} ({shown})"
                )
    else:
        for name, values in ping_pong(args.reps, args.count).items():
            shown = ", ".join(f"{v:.3f}" for v in values)
            print(f"{name:13s} one-way ms: median {median(values):.3f} ({shown})")
    print(f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
