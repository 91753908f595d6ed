"""Resource Registrar benchmarks: request + release throughput and status fan-out.

Every measurement uses a fresh :class:`temoto.core.registrar.Registrar` with the catalog (the
journal) **on** unless the metric says otherwise: a file in a temporary directory, default
``fsync="group"`` (a background thread fsyncs at most every 100 ms; every record is still in
the kernel's page cache, copied into the journal's shared mapping, before the call returns).
The servers do nothing (no-op ``on_load`` / ``on_unload``), so the
numbers are the registrar's own cost. One warm-up round is discarded, ``gc.collect()`` runs
between rounds, the collector stays enabled while timing.

``registrar_speedup`` times the registrar's bookkeeping kernel alone (``RefBook``, see
``temoto/core/_fast/_refbook_py.py``): the same fixed sequence of ``add_ref`` / ``release`` /
``dependencies`` calls on the pure-Python and the compiled book, both imported directly in this
process.
"""

from __future__ import annotations

import gc
import importlib
import json
import math
import os
import random
import subprocess
import sys
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

from bench.common import Results, median, now, percentile, repeat
from temoto.core.registrar import LoadContext, Registrar, ResourceServer, Status, StatusUpdate

# >= this many deduplicated request+release pairs per second: the goal in the VM's fast mode
# (>= 60 k in its slow one)
GOAL_DEDUP_PAIRS = 100_000.0
GOAL_BOOK_SPEEDUP = 5.0  # compiled RefBook >= 5x the pure one on the op sequence below

# RefBook op sequence: BOOK_RESOURCES resources, BOOK_PREFILL references taken before timing,
# then BOOK_OPS operations: add_ref 45 % (holder: a random resource half the time, else -1),
# release of a random live reference 40 %, dependencies() of a random resource 15 %.
BOOK_RESOURCES = 3_000
BOOK_PREFILL = 20_000
BOOK_OPS = 200_000
BOOK_SEED = 20240611
BOOK_MIN_SAMPLE_S = 0.2  # a sample repeats the sequence (fresh books) to last this long (quick)

# Status fan-out hierarchy (see bench/README.md): 1 bottom resource, FAN_MID level-2 resources
# depending on it, FAN_TOP_PER_MID level-3 resources depending on each level-2 one; consumers:
# FAN_CONSUMERS_TOP references on every level-3 resource and FAN_CONSUMERS_MID on every
# level-2 one.
FAN_MID = 10
FAN_TOP_PER_MID = 10
FAN_CONSUMERS_TOP = 9
FAN_CONSUMERS_MID = 10
FAN_CONSUMERS = FAN_MID * (FAN_TOP_PER_MID * FAN_CONSUMERS_TOP + FAN_CONSUMERS_MID)  # 1,000


@dataclass(frozen=True)
class BenchRequest:
    """A request with a typical shape: a name, a number, a short list of arguments."""

    name: str
    n: int = 0
    args: tuple[str, ...] = ("--flag", "value")


@dataclass(frozen=True)
class BenchResponse:
    value: int = 0


class NoopServer(ResourceServer[BenchRequest, BenchResponse]):
    """Loads and unloads instantly."""

    name = "bench_noop"
    request_type = BenchRequest
    response_type = BenchResponse

    def on_load(self, request: BenchRequest, ctx: LoadContext) -> BenchResponse:
        return BenchResponse(request.n)

    def on_unload(self, request: BenchRequest, response: BenchResponse) -> None:
        pass


class DependServer(ResourceServer[BenchRequest, BenchResponse]):
    """Each resource depends on one resource of ``lower`` (``request.n`` picks which)."""

    def __init__(self, name: str, lower: str, pick: Callable[[BenchRequest], BenchRequest]):
        self.name = name  # type: ignore[misc]  # instance-level name: several of these
        self.lower = lower
        self.pick = pick

    request_type = BenchRequest
    response_type = BenchResponse

    def on_load(self, request: BenchRequest, ctx: LoadContext) -> BenchResponse:
        ctx.registrar.call(self.lower, self.pick(request))  # recorded as a dependency
        return BenchResponse(request.n)

    def on_unload(self, request: BenchRequest, response: BenchResponse) -> None:
        pass


class _Registrar:
    """A fresh registrar (catalog in a temp dir, or none), closed and removed afterwards."""

    def __init__(self, catalog: bool, fsync: str = "group") -> None:
        self.catalog = catalog
        self.fsync = fsync

    def __enter__(self) -> Registrar:
        self._tmp = tempfile.TemporaryDirectory(prefix="temoto-bench-")
        path = Path(self._tmp.name) / "catalog.tjl" if self.catalog else None
        self.reg = Registrar("bench", catalog=path, fsync=self.fsync)  # type: ignore[arg-type]
        return self.reg

    def __exit__(self, *exc: object) -> None:
        self.reg.close()
        self._tmp.cleanup()


# ---------------------------------------------------------------------------- pairs per second


def dedup_pairs(n: int, catalog: bool) -> float:
    """Pairs/s: call an equal request to one already held, release the new reference; n times."""
    with _Registrar(catalog) as reg:
        reg.register(NoopServer())
        held = reg.call("bench_noop", BenchRequest("shared"), client="holder")
        request = BenchRequest("shared")  # equal to the held one, not the same object
        call, release = reg.call, reg.release
        t0 = now()
        for _ in range(n):
            release(call("bench_noop", request, client="bench").id)
        dt = now() - t0
        if len(reg.references()) != 1:
            raise RuntimeError("dedup: references left over")
        reg.release(held.id)
    return n / dt


def dedup_op_p50_us(n: int, catalog: bool) -> tuple[float, float]:
    """Median µs of one call and of one release in ``n`` deduplicated pairs (as dedup_pairs).

    Each call and each release is timed alone with ``perf_counter``; the timer's own median
    cost (two reads back to back) is subtracted. For finding where a pair's time goes, not a
    metric of the bench.
    """
    from time import perf_counter as pc

    with _Registrar(catalog) as reg:
        reg.register(NoopServer())
        reg.call("bench_noop", BenchRequest("shared"), client="holder")
        request = BenchRequest("shared")
        call, release = reg.call, reg.release
        calls, releases, timer = [0.0] * n, [0.0] * n, [0.0] * n
        for i in range(n):
            t0 = pc()
            ref = call("bench_noop", request, client="bench")
            t1 = pc()
            release(ref.id)
            t2 = pc()
            timer[i] = pc() - t2
            calls[i], releases[i] = t1 - t0, t2 - t1
    own = median(timer)
    return (median(calls) - own) * 1e6, (median(releases) - own) * 1e6


def new_pairs(n: int, catalog: bool) -> float:
    """Pairs/s: each call loads a new resource (no-op server), its release unloads it."""
    requests = [BenchRequest("fresh", i) for i in range(n)]
    with _Registrar(catalog) as reg:
        reg.register(NoopServer())
        call, release = reg.call, reg.release
        t0 = now()
        for request in requests:
            if not release(call("bench_noop", request, client="bench").id):
                raise RuntimeError("new: the release did not unload the resource")
        dt = now() - t0
        if reg.resources():
            raise RuntimeError("new: resources left over")
    return n / dt


# --------------------------------------------------------------------------------- status fan-out


class _Fanout:
    """The 3-level hierarchy with FAN_CONSUMERS consumer callbacks (see module constants)."""

    def __init__(self, reg: Registrar) -> None:
        self.reg = reg
        self.count = 0
        self.target = FAN_CONSUMERS
        self.t_last = 0.0
        reg.register(NoopServer())  # bottom
        reg.register(DependServer("bench_mid", "bench_noop", lambda r: BenchRequest("bottom")))
        reg.register(
            DependServer(
                "bench_top", "bench_mid", lambda r: BenchRequest("mid", r.n // FAN_TOP_PER_MID)
            )
        )
        self.refs: list[Any] = []
        for m in range(FAN_MID):
            for c in range(FAN_CONSUMERS_MID):
                self.refs.append(
                    reg.call(
                        "bench_mid", BenchRequest("mid", m), client=f"mc{m}.{c}", on_status=self.cb
                    )
                )
            for t in range(m * FAN_TOP_PER_MID, (m + 1) * FAN_TOP_PER_MID):
                for c in range(FAN_CONSUMERS_TOP):
                    self.refs.append(
                        reg.call(
                            "bench_top",
                            BenchRequest("top", t),
                            client=f"tc{t}.{c}",
                            on_status=self.cb,
                        )
                    )
        self.bottom = reg.served("bench_noop")
        if len(self.bottom) != 1 or len(reg.served("bench_mid")) != FAN_MID:
            raise RuntimeError("fan-out: hierarchy not built as intended")
        if len(reg.served("bench_top")) != FAN_MID * FAN_TOP_PER_MID:
            raise RuntimeError("fan-out: wrong number of level-3 resources")
        if len(self.refs) != FAN_CONSUMERS:
            raise RuntimeError("fan-out: wrong number of consumers")

    def cb(self, update: StatusUpdate) -> None:
        self.count += 1
        if self.count == self.target:
            self.t_last = now()

    def once(self) -> float:
        """ms from send_status on the bottom resource to the last consumer callback."""
        self.count = 0
        self.t_last = 0.0
        t0 = now()
        reached = self.reg.send_status(self.bottom[0].id, Status.ERROR, "bench")
        if self.count != FAN_CONSUMERS or not self.t_last:
            raise RuntimeError(f"fan-out: {self.count} callbacks ran, expected {FAN_CONSUMERS}")
        # references reached also counts the dependency references (level 2 -> 1, 3 -> 2)
        if reached != FAN_CONSUMERS + FAN_MID + FAN_MID * FAN_TOP_PER_MID:
            raise RuntimeError(f"fan-out: send_status reached {reached} references")
        return (self.t_last - t0) * 1e3


# ------------------------------------------------------------------------------------ the group


def bench_registrar(quick: bool) -> Results:
    out = Results()
    reps = 3 if quick else 15
    n_dedup = 10_000 if quick else 50_000
    n_new = 2_500 if quick else 20_000

    dedup = repeat(lambda: dedup_pairs(n_dedup, True), reps)
    out.add(
        "registrar_dedup_pairs_per_s",
        median(dedup),
        "1/s",
        f"median of {reps} rounds of {n_dedup:,} call+release of a held request; catalog on"
        f" (fsync group); range {min(dedup):,.0f}-{max(dedup):,.0f}",
        (">=", GOAL_DEDUP_PAIRS),
    )
    new = repeat(lambda: new_pairs(n_new, True), reps)
    out.add(
        "registrar_new_pairs_per_s",
        median(new),
        "1/s",
        f"median of {reps} rounds of {n_new:,} load+unload (no-op server); catalog on;"
        f" range {min(new):,.0f}-{max(new):,.0f}",
    )
    nocat = repeat(lambda: dedup_pairs(n_dedup, False), reps)
    out.add(
        "registrar_dedup_pairs_per_s_nocatalog",
        median(nocat),
        "1/s",
        f"as registrar_dedup_pairs_per_s without a catalog; range"
        f" {min(nocat):,.0f}-{max(nocat):,.0f}",
    )
    if not quick:
        nocat_new = repeat(lambda: new_pairs(n_new, False), reps)
        out.add(
            "registrar_new_pairs_per_s_nocatalog",
            median(nocat_new),
            "1/s",
            "as registrar_new_pairs_per_s without a catalog",
        )

    fan_reps = 30 if quick else 200
    with _Registrar(True) as reg:
        fan = _Fanout(reg)
        times = repeat(fan.once, fan_reps, warmup=3)
    out.add(
        "registrar_status_fanout_1000_ms",
        median(times),
        "ms",
        f"median of {fan_reps}; send_status(ERROR) on the bottom resource -> the last of"
        f" {FAN_CONSUMERS} consumer callbacks; 3 levels"
        f" (1 / {FAN_MID} / {FAN_MID * FAN_TOP_PER_MID} resources)",
    )
    out.add(
        "registrar_status_fanout_1000_ms_p99",
        percentile(times, 99),
        "ms",
        "p99 of the same",
    )

    _book_speedup(out, quick)

    from temoto.core import _fast

    dedup_value = median(dedup)
    whole = (
        " (whole registrar: the journal, locking and request keys dominate a pair, so this"
        " stays near 1.0 whatever the bookkeeping kernel gains; see registrar_speedup)"
    )
    if not _fast.COMPILED:
        out.add(
            "registrar_dedup_speedup",
            1.0,
            "x",
            "1.0 by definition: no compiled extension in use (temoto.core._fast.COMPILED is"
            " False), so compiled and pure Python are the same code",
        )
    elif os.environ.get("TEMOTO_NO_EXTENSIONS"):
        out.add(
            "registrar_dedup_speedup", 1.0, "x", "this process runs with TEMOTO_NO_EXTENSIONS set"
        )
    else:
        out.add(
            "registrar_dedup_speedup",
            dedup_value / _pure_dedup(n_dedup, reps),
            "x",
            "registrar_dedup_pairs_per_s / the same measured in a subprocess with"
            " TEMOTO_NO_EXTENSIONS=1" + whole,
        )
    return out


# ------------------------------------------------------------------------------- RefBook kernel

Op = tuple[int, int, int]  # (0, res, holder): add_ref; (1, ref, 0): release; (2, res, 0): deps


def book_program() -> tuple[list[tuple[int, int]], list[Op], int]:
    """The fixed op sequence, with the exact slots (both builds hand out slots alike).

    Returns:
        The prefill as (resource, holder) pairs, the ops, and the number of live references
        at the end.
    """
    from temoto.core._fast._refbook_py import RefBook

    rng = random.Random(BOOK_SEED)
    book = RefBook()
    resources = [book.new_resource() for _ in range(BOOK_RESOURCES)]

    def holder() -> int:
        return rng.choice(resources) if rng.random() < 0.5 else -1

    prefill = [(rng.choice(resources), holder()) for _ in range(BOOK_PREFILL)]
    live = [book.add_ref(res, h) for res, h in prefill]
    ops: list[Op] = []
    for _ in range(BOOK_OPS):
        x = rng.random()
        if x < 0.45 or not live:
            res, h = rng.choice(resources), holder()
            live.append(book.add_ref(res, h))
            ops.append((0, res, h))
        elif x < 0.85:
            i = rng.randrange(len(live))
            live[i], live[-1] = live[-1], live[i]
            ref = live.pop()
            book.release(ref)
            ops.append((1, ref, 0))
        else:
            ops.append((2, rng.choice(resources), 0))
    return prefill, ops, len(live)


def _book_pass(
    mod: ModuleType, prefill: list[tuple[int, int]], ops: list[Op], n_live: int
) -> float:
    """Seconds for the op sequence on a fresh, prefilled book of ``mod`` (setup not timed)."""
    book = mod.RefBook()
    for _ in range(BOOK_RESOURCES):
        book.new_resource()
    for res, h in prefill:
        book.add_ref(res, h)
    add, release, dependencies = book.add_ref, book.release, book.dependencies
    t0 = now()
    for code, a, b in ops:
        if code == 0:
            add(a, b)
        elif code == 1:
            release(a)
        else:
            dependencies(a)
    dt = now() - t0
    if book.live_refs() != n_live:
        raise RuntimeError(f"refbook: {book.live_refs()} references left, expected {n_live}")
    return dt


def _book_speedup(out: Results, quick: bool) -> None:
    """registrar_speedup: pure / compiled RefBook time on the fixed op sequence."""
    reps = 5 if quick else 15
    target = BOOK_MIN_SAMPLE_S if quick else 2 * BOOK_MIN_SAMPLE_S
    pure = importlib.import_module("temoto.core._fast._refbook_py")
    compiled: ModuleType | None = None
    missing = ""
    try:
        compiled = importlib.import_module("temoto.core._fast._refbook_c")
    except ImportError as err:
        missing = f"compiled build not installed ({err})"
    prefill, ops, n_live = book_program()
    mods = {"pure": pure} if compiled is None else {"pure": pure, "compiled": compiled}
    # The warm-up pass of each build sets how many passes one sample adds up (>= target s),
    # so the short compiled passes are not at the mercy of one scheduler time slice.
    passes = {
        name: max(1, math.ceil(target / _book_pass(mod, prefill, ops, n_live)))
        for name, mod in mods.items()
    }
    times: dict[str, list[float]] = {name: [] for name in mods}
    order = list(mods)
    for i in range(reps):  # alternate the builds, and which goes first
        for name in order if i % 2 == 0 else order[::-1]:
            gc.collect()
            total = sum(_book_pass(mods[name], prefill, ops, n_live) for _ in range(passes[name]))
            times[name].append(total / passes[name])
    ns = {name: median(values) / BOOK_OPS * 1e9 for name, values in times.items()}
    what = (
        f"{BOOK_OPS:,} ops in random order (add_ref 45 %, release 40 %, dependencies 15 %) on"
        f" {BOOK_RESOURCES:,} resources holding {BOOK_PREFILL:,} references at the start, one op"
        " per iteration of a plain for loop"
    )
    if compiled is None:
        out.add(
            "registrar_speedup",
            1.0,
            "x",
            f"1.0, not measured: the RefBook {missing}",
            (">=", GOAL_BOOK_SPEEDUP),
        )
        out.notes.append(f"registrar: RefBook {missing}; registrar_speedup reported as 1.0")
    else:
        out.add(
            "registrar_speedup",
            ns["pure"] / ns["compiled"],
            "x",
            f"pure / compiled RefBook time: median of {reps} alternating samples, each the mean"
            f" of {passes['pure']} (pure) / {passes['compiled']} (compiled) passes of {what};"
            f" pure {ns['pure']:.0f} ns/op, compiled {ns['compiled']:.0f} ns/op (the loop's"
            " own cost included in both)",
            (">=", GOAL_BOOK_SPEEDUP),
        )
        out.add(
            "registrar_book_ns_per_op",
            ns["compiled"],
            "ns",
            f"compiled RefBook: one pass of {what} / {BOOK_OPS:,}",
        )
    out.add("registrar_book_ns_per_op_pure", ns["pure"], "ns", "the same, pure RefBook")


def _pure_dedup(n: int, reps: int) -> float:
    """registrar_dedup_pairs_per_s measured in a subprocess with the compiled extensions off."""
    repo = Path(__file__).resolve().parent.parent
    code = (
        "import json; from bench.common import median, repeat;"
        " from bench.registrar import dedup_pairs;"
        f" print(json.dumps(median(repeat(lambda: dedup_pairs({n}, True), {reps}))))"
    )
    env = dict(os.environ, TEMOTO_NO_EXTENSIONS="1")
    path = env.get("PYTHONPATH", "")
    env["PYTHONPATH"] = str(repo) + (os.pathsep + path if path else "")
    done = subprocess.run(
        [sys.executable, "-c", code],
        env=env,
        cwd=repo,
        check=True,
        capture_output=True,
        text=True,
        timeout=600,
    )
    return float(json.loads(done.stdout.strip().splitlines()[-1]))
