"""Resource Registrar benchmarks: request + release throughput and status fan-out.

Every measurement uses a fresh :class:`temoto.core.registrar.Registrar` with the catalog (the
journal) **on** unless the metric says otherwise: a file in a temporary directory, default
``fsync="group"`` (a background thread fsyncs at most every 100 ms; every record is still
``os.write``-n before the call returns). The servers do nothing (no-op ``on_load`` /
``on_unload``), so the numbers are the registrar's own cost. One warm-up round is discarded,
``gc.collect()`` runs between rounds, the collector stays enabled while timing.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bench.common import Results, median, now, percentile, repeat
from temoto.core.registrar import LoadContext, Registrar, ResourceServer, Status, StatusUpdate

GOAL_DEDUP_PAIRS = 50_000.0  # >= this many deduplicated request+release pairs per second

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
    reps = 5 if quick else 15
    n_dedup = 20_000 if quick else 50_000
    n_new = 5_000 if quick else 20_000

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

    from temoto.core import _fast

    dedup_value = median(dedup)
    if not _fast.COMPILED:
        out.add(
            "registrar_speedup",
            1.0,
            "x",
            "1.0 by definition: no compiled extension in use (temoto.core._fast.COMPILED is"
            " False), so compiled and pure Python are the same code",
        )
    elif os.environ.get("TEMOTO_NO_EXTENSIONS"):
        out.add("registrar_speedup", 1.0, "x", "this process runs with TEMOTO_NO_EXTENSIONS set")
    else:
        out.add(
            "registrar_speedup",
            dedup_value / _pure_dedup(quick),
            "x",
            "registrar_dedup_pairs_per_s / the same in a subprocess with TEMOTO_NO_EXTENSIONS=1",
        )
    return out


def _pure_dedup(quick: bool) -> float:
    """registrar_dedup_pairs_per_s in a subprocess with the compiled extensions disabled."""
    repo = Path(__file__).resolve().parent.parent
    with tempfile.TemporaryDirectory() as tmp:
        target = Path(tmp) / "pure.json"
        cmd = [sys.executable, "-m", "bench", "--only", "registrar", "--json", str(target)]
        if quick:
            cmd.append("--quick")
        env = dict(os.environ, TEMOTO_NO_EXTENSIONS="1")
        path = env.get("PYTHONPATH", "")
        env["PYTHONPATH"] = str(repo) + (os.pathsep + path if path else "")
        subprocess.run(cmd, env=env, cwd=repo, check=True, stdout=subprocess.DEVNULL, timeout=600)
        return float(json.loads(target.read_text())["registrar_dedup_pairs_per_s"]["value"])
