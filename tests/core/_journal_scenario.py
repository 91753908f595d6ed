"""A registrar scenario that writes every kind of journal record (the fixtures' source).

``tests/data/registrar/*.tjl`` were written by this scenario running on the registrar before its
records got one typed definition (git ``90291e4``); ``test_registrar_records.py`` runs it again
on the current code and compares the bytes, and restores the fixtures.

Deterministic: the registrar's boot token (``secrets.token_hex``) is fixed by the caller, the
scenario runs in one thread, and compaction is forced (``compact=True``) by the caller setting
the compaction slack to 0.
"""

from __future__ import annotations

import contextlib
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from temoto.core.registrar import LoadContext, Registrar, ResourceServer, Status
from temoto.errors import ResourceLoadError

#: What ``secrets.token_hex`` returns while the scenario runs.
BOOT = "b00701"


@dataclass(frozen=True)
class Req:
    name: str
    n: int = 0
    tags: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "tags", tuple(self.tags))  # JSON gives lists back


@dataclass(frozen=True)
class Resp:
    value: str
    n: int = 0


@dataclass
class Server(ResourceServer[Req, Resp]):
    """Loads a dependency from ``sub`` (if set); ``broken`` fails, ``crash`` copies the journal."""

    name: str  # type: ignore[misc]
    sub: str = ""
    crash_copy: tuple[Path, Path] | None = None  # (the journal, where to copy it)
    abandoned: list[tuple[str, Any]] = field(default_factory=list)
    unloads: list[str] = field(default_factory=list)

    request_type = Req
    response_type = Resp

    def on_load(self, request: Req, ctx: LoadContext) -> Resp:
        if self.sub:
            ctx.checkpoint({"step": "sub", "note": "Grüße ✓", "n": request.n})
            ctx.registrar.call(self.sub, Req(f"{request.name}-dep", request.n, ("x", "ÿ")))
        if request.name == "broken":
            raise RuntimeError("refused")
        if request.name == "crash" and self.crash_copy is not None:
            shutil.copyfile(*self.crash_copy)
        return Resp(f"{self.name}:{request.name}", request.n)

    def on_unload(self, request: Req, response: Resp) -> None:
        self.unloads.append(request.name)

    def on_abandoned(self, request: Req, progress: Any) -> None:
        self.abandoned.append((request.name, progress))


def servers(crash_copy: tuple[Path, Path] | None = None) -> tuple[Server, Server]:
    """The scenario's two servers: ``upper`` (each resource depends on one of ``lower``)."""
    return Server("upper", sub="lower", crash_copy=crash_copy), Server("lower")


def run(path: Path, crash_copy: Path | None = None) -> None:
    """Write the scenario's journal at ``path``; with ``crash_copy``, end by a load whose journal
    is copied there while it runs (what a SIGKILL in the middle of a load leaves)."""
    rr = Registrar("scenario", catalog=path, fsync="never")
    upper, lower = servers(None if crash_copy is None else (path, crash_copy))
    rr.register(upper)
    rr.register(lower)
    top = rr.call("upper", Req("a", 1, ("t",)), client="graph/node ✓")  # begin, progress, load
    shared = rr.call("lower", Req("s"), client="c1")
    rr.call("lower", Req("s"), client='c2 "quoted"')  # ref
    boss = rr.call("lower", Req("s"), client="boss", priority=5, exclusive=True)  # suspends
    rr.release(boss.id)  # unref with resumes
    with contextlib.suppress(ResourceLoadError):  # abandon (after its dependency's unload)
        rr.call("upper", Req("broken"), client="c1")
    rr.send_status(shared.resource_id, Status.FATAL, "gone")  # failed
    rr.send_status(shared.resource_id, Status.OK, "back")  # recovered
    rr.update_response(top.resource_id, Resp("new ✓", 2))  # response
    dead = rr.call("lower", Req("dead"), client="c5")
    rr.send_status(dead.id, Status.FATAL, "stays failed")  # failed, while held
    rr.call("lower", Req("d"), client="x")
    rr.call("lower", Req("d"), client="y", priority=1, exclusive=True)  # x stays suspended
    gone = rr.call("lower", Req("g", 2**40), client="c3", priority=-3)
    rr.release(gone.id)  # unref, unload
    if crash_copy is not None:
        rr.call("upper", Req("crash", 3), client="c4")
    rr.close()
