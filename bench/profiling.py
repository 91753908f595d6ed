"""cProfile of the engine benchmarks across threads: ``python -m bench --profile chain|fanout``.

cProfile only sees the thread that enabled it, and the engine runs actions on worker threads,
so every thread started while profiling gets its own profiler (via ``threading.setprofile``)
and the statistics are merged: one table for the worker threads (execution and evolution) and
one for the calling thread (``start()``: planning and validation, then ``wait()``).

Timers: the chain runs on one worker at a time while the caller blocks in ``wait()``, so the
default (wall-clock, low-overhead) timer is used and blocking calls are left out. The fan-out
keeps up to 64 threads runnable and contending for the GIL, where wall time would be charged to
whatever frame a descheduled thread was in, so it uses per-thread CPU time
(``time.thread_time``), which costs more per call and so inflates small, frequent functions.
"""

from __future__ import annotations

import cProfile
import gc
import io
import pstats
import threading
import time
from typing import Any

from bench.common import chain_graph, fanout_graph
from bench.engine import CHAIN_N, FANOUT_N, make_catalog, run_once
from temoto import parse_graph

# Calls that block (their own time is waiting, not work); left out of the tables and totals.
BLOCKING = (
    "<method 'acquire' of '_thread.lock' objects>",
    "<method 'acquire' of '_thread.RLock' objects>",
    "<method 'get' of '_queue.SimpleQueue' objects>",
)


def _profile(
    graph_doc: dict[str, Any], reps: int, timer: Any
) -> tuple[pstats.Stats | None, pstats.Stats]:
    catalog = make_catalog()
    graph = parse_graph(graph_doc)
    run_once(graph, catalog, instrumented=False)  # warm-up, not profiled
    workers: list[cProfile.Profile] = []
    lock = threading.Lock()

    def bootstrap(frame: Any, event: str, arg: Any) -> None:
        prof = cProfile.Profile(timer) if timer else cProfile.Profile()
        with lock:
            workers.append(prof)
        prof.enable()  # replaces this hook for the rest of the thread's life

    main = cProfile.Profile(timer) if timer else cProfile.Profile()
    for _ in range(reps):
        gc.collect()
        threading.setprofile(bootstrap)
        main.enable()
        try:
            run_once(graph, catalog, instrumented=False)  # shutdown joins every worker
        finally:
            main.disable()
            threading.setprofile(None)  # type: ignore[arg-type]
    worker_stats = None
    for prof in workers:
        prof.disable()
        if worker_stats is None:
            worker_stats = pstats.Stats(prof)
        else:
            worker_stats.add(prof)
    return worker_stats, pstats.Stats(main)


def _table(
    stats: pstats.Stats, title: str, top: int, only_temoto: bool, by_cum: bool = False
) -> str:
    raw: dict[Any, Any] = {k: v for k, v in stats.stats.items() if k[2] not in BLOCKING}  # type: ignore[attr-defined]
    total = sum(v[2] for v in raw.values()) or 1.0
    rows = []
    for (file, line, func), (_cc, ncalls, tottime, cumtime, _callers) in raw.items():
        if only_temoto and "/temoto/" not in file:
            continue
        where = file.split("/temoto/", 1)[-1] if "/temoto/" in file else file.rsplit("/", 1)[-1]
        rows.append((tottime, cumtime, ncalls, f"{where}:{line}({func})"))
    rows.sort(key=lambda r: r[1] if by_cum else r[0], reverse=True)
    buf = io.StringIO()
    scope = "temoto functions" if only_temoto else "all functions"
    order = "cumulative" if by_cum else "own"
    buf.write(
        f"{title}: top {top} {scope} by {order} time"
        f" (% of the threads' total, {total * 1e3:.1f} ms)\n"
    )
    buf.write(f"  {'own %':>6} {'own ms':>8} {'cum %':>6} {'cum ms':>8} {'calls':>8}  function\n")
    for tottime, cumtime, ncalls, name in rows[:top]:
        buf.write(
            f"  {100 * tottime / total:6.1f} {tottime * 1e3:8.1f} {100 * cumtime / total:6.1f}"
            f" {cumtime * 1e3:8.1f} {ncalls:8d}  {name}\n"
        )
    return buf.getvalue()


def main(which: str, reps: int = 10, top: int = 15) -> None:
    doc = chain_graph(CHAIN_N) if which == "chain" else fanout_graph(FANOUT_N)
    timer = None if which == "chain" else time.thread_time
    workers, caller = _profile(doc, reps, timer)
    clock = "wall clock, blocking calls left out" if timer is None else "per-thread CPU time"
    print(
        f"cProfile ({clock}) of the {which} benchmark ({reps} runs, profiler overhead included)\n"
    )
    if workers is not None:
        print(_table(workers, "worker threads", top, only_temoto=True))
        print(_table(workers, "worker threads", top, only_temoto=False))
        print(_table(workers, "worker threads", top, only_temoto=True, by_cum=True))
    print(_table(caller, "calling thread (start: plan + validate; wait)", top, only_temoto=True))
    print(_table(caller, "calling thread (start: plan + validate; wait)", top, only_temoto=False))
