"""Run the benchmarks.

    python -m bench --quick --json FILE   # < 60 s
    python -m bench --json FILE           # full: more repetitions, a few extra variants
    python -m bench --only chain,fanout   # some groups
    python -m bench --profile chain       # cProfile hot spots (chain or fanout), no JSON

The JSON file maps metric names to ``{"value": <number>, "unit": "<unit>"}``; a readable table
and progress lines go to stdout. Exit status 1 if a benchmark group failed (the others are
still written).
"""

from __future__ import annotations

import argparse
import datetime
import json
import logging
import os
import platform
import subprocess
import sys
import time
import traceback
from collections.abc import Callable
from pathlib import Path

from bench import (
    can,
    component,
    context,
    dynamixel,
    engine,
    evolution,
    fleet,
    mavlink,
    peers,
    process,
    realism,
    registrar,
    ris,
    robot,
    ros2,
    safety,
    visualization,
)
from bench.common import Metric, Results

GROUPS: dict[str, tuple[str, Callable[[bool], Results]]] = {
    "chain": ("engine: chain of 10,000 no-op actions", engine.bench_chain),
    "round": ("engine: scheduling round in a 1,000-action chain", engine.bench_round),
    "fanout": ("engine: fan-out/fan-in of 1,000 no-op actions", engine.bench_fanout),
    "cyclic": ("engine: 100-action graph with cycles and a branch, 100 runs", engine.bench_cyclic),
    "start": ("engine: start() -> first action's on_run, small indexed graph", engine.bench_start),
    "load": ("engine: load a 10,000-action chain (parse + validate + start)", engine.bench_load),
    "rss": ("engine: idle RSS with 100 indexed graphs (subprocess)", engine.bench_rss),
    "import": ("import temoto (subprocesses)", engine.bench_import),
    "evolution": ("evolution kernel alone: compiled vs pure", evolution.bench_evolution),
    "peers": ("peer: py_trees, BehaviorTree.CPP (behaviortreepy), transitions", peers.bench_peers),
    "registrar": (
        "registrar: request+release pairs, status fan-out to 1,000 consumers",
        registrar.bench_registrar,
    ),
    "fleet": (
        "fleet: handshake of 2/3/5 and 20 (full: 10/20/50) actor processes, notification latency,"
        " throughput; 3 actors and throughput again over Zenoh (through a router, then peers)",
        fleet.bench_fleet,
    ),
    "process": (
        "process manager: crash detection, relaunch; supervisord side by side",
        process.bench_process,
    ),
    "ris": (
        "RIS: a process crash on robot B -> A's consumer, remote loads (2 processes)",
        ris.bench_ris,
    ),
    "dynamixel": (
        "dynamixel: SyncRead + SyncWrite of 6 servos over a pseudo-terminal",
        dynamixel.bench_dynamixel,
    ),
    "dxl_realism": (
        "dynamixel realism: polls of 6 servos at typical and harsh (late and lost replies)",
        dynamixel.bench_dynamixel_realism,
    ),
    "mavlink": (
        "mavlink: CPU of the driver handling 50 Hz telemetry (subprocess)",
        mavlink.bench_mavlink,
    ),
    "can": ("can: 8 CANSimple axes at 500 Hz on a virtual bus", can.bench_can),
    "realism": (
        "realism: the simulated vehicle's supervised streams per level (virtual hours)",
        realism.bench_realism,
    ),
    "component": (
        "component manager: active sensor killed -> substitute's data at the consumer",
        component.bench_component,
    ),
    "context": (
        "context manager: 3-robot convergence after a change, queries on 10,000 items",
        context.bench_context,
    ),
    "robot": (
        "robot manager: start-to-ready, idle RSS (subprocesses); stop -> still (in-process)",
        robot.bench_robot,
    ),
    "safety": (
        "safety: signal -> every device safe, seen by the simulators (subprocesses)",
        safety.bench_safety,
    ),
    "stale": (
        "safety: an ODrive's encoder stream stops -> driver fault (virtual CAN)",
        safety.bench_stale,
    ),
    "visualization": (
        "visualization: live Foxglove message cost (one client), display load -> first message",
        visualization.bench_visualization,
    ),
    "ros2": (
        "ros2: service round trip and publish latency, rclpy's own vs the bridge vs an action",
        ros2.bench_ros2,
    ),
}


def _goal_text(m: Metric) -> str:
    if m.goal is None:
        return ""
    op, bound = m.goal
    met = {"<=": m.value <= bound, "<": m.value < bound, ">=": m.value >= bound}.get(op)
    if met is None:
        met = m.value > bound
    if met:
        return f"goal {op} {bound:g}: met"
    if op in (">=", ">"):
        return (
            f"goal {op} {bound:g}: MISSED by {bound - m.value:.3g}"
            f" ({100 * (1 - m.value / bound):.0f}% short)"
        )
    return (
        f"goal {op} {bound:g}: MISSED by {m.value - bound:.3g} ({100 * (m.value / bound - 1):.0f}%)"
    )


def _fmt(value: float) -> str:
    if value >= 1000:
        return f"{value:,.0f}"
    if value >= 100:
        return f"{value:.1f}"
    return f"{value:.2f}"


def _header(mode: str) -> str:
    from temoto.core import _fast

    try:
        load = " ".join(f"{x:.2f}" for x in os.getloadavg())
    except OSError:
        load = "?"
    try:
        rev = subprocess.run(
            ["git", "describe", "--always", "--dirty"],
            cwd=Path(__file__).resolve().parent.parent,
            capture_output=True,
            text=True,
            timeout=10,
        ).stdout.strip()
    except OSError:
        rev = ""
    return (
        f"TeMoto benchmarks ({mode}) {datetime.datetime.now().isoformat(timespec='seconds')}"
        f" {('git ' + rev) if rev else ''}\n"
        f"  python {platform.python_version()} ({sys.executable}), {platform.machine()},"
        f" nproc {os.cpu_count()}, load average {load}, compiled extensions: {_fast.COMPILED}"
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench", description="TeMoto benchmarks")
    parser.add_argument("--quick", action="store_true", help="fewer repetitions (under 60 s)")
    parser.add_argument("--json", metavar="FILE", help="write {metric: {value, unit}} here")
    parser.add_argument(
        "--only", metavar="GROUPS", help=f"comma-separated subset of: {', '.join(GROUPS)}"
    )
    parser.add_argument(
        "--profile", choices=("chain", "fanout"), help="print cProfile hot spots and exit"
    )
    parser.add_argument(
        "--no-install", action="store_true", help="never pip install missing peers (bench extra)"
    )
    args = parser.parse_args(argv)
    if args.no_install:
        os.environ[peers.NO_INSTALL_ENV] = "1"

    # The engine warns when every worker is busy (the fan-out does that on purpose).
    logging.getLogger("temoto").setLevel(logging.ERROR)

    if args.profile:
        from bench import profiling

        profiling.main(args.profile)
        return 0

    names = (
        list(GROUPS) if not args.only else [n.strip() for n in args.only.split(",") if n.strip()]
    )
    unknown = [n for n in names if n not in GROUPS]
    if unknown:
        parser.error(f"unknown group(s) {', '.join(unknown)} (known: {', '.join(GROUPS)})")

    mode = "quick" if args.quick else "full"
    print(_header(mode), flush=True)
    t_all = time.perf_counter()
    metrics: list[Metric] = []
    notes: list[str] = []
    failed = []
    for i, name in enumerate(names, 1):
        title, fn = GROUPS[name]
        print(f"[{i}/{len(names)}] {title} ...", flush=True)
        t0 = time.perf_counter()
        try:
            res = fn(args.quick)
        except Exception:
            failed.append(name)
            print(f"      FAILED after {time.perf_counter() - t0:.1f} s:", flush=True)
            traceback.print_exc()
            continue
        metrics.extend(res.metrics)
        notes.extend(res.notes)
        shown = ", ".join(f"{m.name} = {_fmt(m.value)} {m.unit}" for m in res.metrics[:2])
        print(
            f"      done in {time.perf_counter() - t0:.1f} s{': ' + shown if shown else ''}",
            flush=True,
        )
        for note in res.notes:
            print(f"      note: {note}", flush=True)

    derived = engine.ratios(metrics)  # ours / the peers', when both ran in this run
    metrics.extend(derived.metrics)
    notes.extend(derived.notes)

    width = max([len(m.name) for m in metrics] + [6])
    print()
    print(f"{'metric':<{width}}  {'value':>10}  {'unit':<4}  goal / how")
    print(f"{'-' * width}  {'-' * 10}  {'-' * 4}  {'-' * 40}")
    for m in metrics:
        extra = _goal_text(m)
        how = f"{extra}; {m.note}" if extra and m.note else extra or m.note
        print(f"{m.name:<{width}}  {_fmt(m.value):>10}  {m.unit:<4}  {how}")
    for note in notes:
        print(f"note: {note}")
    print(f"\n{len(metrics)} metrics in {time.perf_counter() - t_all:.1f} s", flush=True)

    if args.json:
        data = {m.name: {"value": round(m.value, 4), "unit": m.unit} for m in metrics}
        with open(args.json, "w", encoding="utf-8") as f:
            json.dump(data, f, indent=2)
            f.write("\n")
        print(f"wrote {args.json}")
    if failed:
        print(f"FAILED groups: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
