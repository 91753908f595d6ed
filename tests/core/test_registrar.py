from __future__ import annotations

import threading
from dataclasses import dataclass, field
from typing import Any

import pytest

from temoto.core.registrar import (
    LoadContext,
    Registrar,
    ResourceInfo,
    ResourceServer,
    Status,
    StatusUpdate,
)
from temoto.errors import (
    ResourceBusyError,
    ResourceClosedError,
    ResourceLoadError,
    ResourceNotFoundError,
)


@dataclass(frozen=True)
class Req:
    name: str
    subs: tuple[str, ...] = ()
    fail: bool = False

    def __post_init__(self) -> None:
        object.__setattr__(self, "subs", tuple(self.subs))  # JSON gives lists back


@dataclass(frozen=True)
class Resp:
    value: str


@dataclass
class Counting(ResourceServer[Req, Resp]):
    """A server that loads by requesting `subs` from `sub_server`, and counts its calls."""

    registrar: Registrar
    name: str = "m1"  # type: ignore[misc]
    sub_server: str = ""
    loads: list[str] = field(default_factory=list)
    unloads: list[str] = field(default_factory=list)
    statuses: list[tuple[str, Status, str]] = field(default_factory=list)

    request_type = Req
    response_type = Resp

    def on_load(self, request: Req, ctx: LoadContext) -> Resp:
        self.loads.append(request.name)
        for sub in request.subs:
            self.registrar.call(self.sub_server, Req(sub))
        if request.fail:
            raise RuntimeError(f"{request.name} refused")
        return Resp(f"{self.name}:{request.name}")

    def on_unload(self, request: Req, response: Resp) -> None:
        self.unloads.append(request.name)

    def on_status(self, resource: ResourceInfo, status: Status, message: str) -> None:
        self.statuses.append((resource.request.name, status, message))


def chain() -> tuple[Registrar, Counting, Counting]:
    rr = Registrar("rr")
    r1 = Counting(rr, name="m1", sub_server="m2")
    r2 = Counting(rr, name="m2")
    rr.register(r1)
    rr.register(r2)
    return rr, r1, r2


def test_upstream_chain_of_three_loads_and_unloads_with_exact_counts() -> None:
    rr, r1, r2 = chain()
    first = rr.call("m1", Req("R1", ("R2a", "R2b")), client="m0")
    assert (len(r1.loads), len(r2.loads)) == (1, 2)
    second = rr.call("m1", Req("R1'", ("R2a", "R2b")), client="m0")
    assert len(r1.loads) + len(r2.loads) == 4  # R2a and R2b are reused
    extra = rr.call("m2", Req("R2a"), client="m0")
    assert len(rr.info(extra.id).references) == 3
    assert rr.release(extra.id) is False
    assert rr.release(first.id) is True
    assert rr.release(second.id) is True
    assert (sorted(r1.unloads), sorted(r2.unloads)) == (["R1", "R1'"], ["R2a", "R2b"])
    assert rr.resources() == []
    rr.call("m1", Req("R1", ("R2a", "R2b")), client="m0")
    assert len(r1.loads) + len(r2.loads) == 7


def test_equal_requests_share_one_resource_with_one_reference_each() -> None:
    rr, r1, _ = chain()
    a = rr.call("m1", Req("x"), client="a")
    b = rr.call("m1", Req("x"), client="b")
    assert a.id != b.id
    assert a.resource_id == b.resource_id
    assert a.response == b.response
    assert r1.loads == ["x"]
    assert rr.info(a.resource_id).consumers == ["a", "b"]


class Failing(Counting):
    def on_load(self, request: Req, ctx: LoadContext) -> Resp:
        raise RuntimeError("the origin")


class Top(Counting):
    def on_load(self, request: Req, ctx: LoadContext) -> Resp:
        self.registrar.call("side", Req("dep-1"))  # acquired first, must be rolled back
        self.registrar.call("m1", Req("mid", ("bottom",)))
        return Resp("never")


def test_nested_failure_rolls_back_and_forwards_the_error_chain() -> None:
    rr = Registrar("rr")
    side = Counting(rr, name="side")
    for server in (side, Top(rr, name="m0"), Counting(rr, name="m1", sub_server="m2")):
        rr.register(server)
    rr.register(Failing(rr, name="m2"))
    with pytest.raises(ResourceLoadError) as caught:
        rr.call("m0", Req("top"), client="c")
    records = caught.value.to_records()
    # the origin, plus one forwarding link per server it passed (upstream's error stack)
    assert [r.type for r in records] == ["ResourceLoadError"] * 3 + ["RuntimeError"]
    assert "server 'm0'" in records[0].message
    assert "server 'm2'" in records[2].message
    assert records[-1].message == "the origin"
    assert side.unloads == ["dep-1"]  # the first dependency was rolled back
    assert rr.resources() == []  # nothing stored
    assert rr.references() == []


def test_dependencies_are_recorded_and_cascade_on_release() -> None:
    rr, r1, r2 = chain()
    top = rr.call("m1", Req("R1", ("a", "b")), client="c")
    deps = rr.dependencies(top.resource_id)
    assert sorted(d.request.name for d in deps) == ["a", "b"]
    rr.release(top.id)
    assert sorted(r2.unloads) == ["a", "b"]
    assert r1.unloads == ["R1"]


def test_status_reaches_every_consumer_and_travels_up_the_chain() -> None:
    rr, r1, r2 = chain()
    got: list[StatusUpdate] = []
    top_a = rr.call("m1", Req("R1", ("a",)), client="c1", on_status=got.append)
    top_b = rr.call("m1", Req("R1", ("a",)), client="c2", on_status=got.append)
    direct = rr.call("m2", Req("a"), client="c3", on_status=got.append)
    bottom = rr.info(direct.id)
    reached = rr.send_status(bottom.id, Status.FATAL, "process died")
    assert reached == 4  # R1's dependency reference, c3, then c1 and c2 one level up
    assert {u.reference_id for u in got} == {top_a.id, top_b.id, direct.id}
    up = next(u for u in got if u.reference_id == top_a.id)
    assert up.status is Status.FATAL
    assert up.hops == ("m2", "m1")
    assert up.origin == bottom.id
    assert r2.statuses == [("a", Status.FATAL, "process died")]
    assert r1.statuses == [("R1", Status.FATAL, "process died")]


def test_a_failed_resource_is_not_shared_with_new_requests() -> None:
    rr, _, r2 = chain()
    old = rr.call("m2", Req("p"), client="a")
    rr.send_status(old.id, Status.FATAL, "died")
    new = rr.call("m2", Req("p"), client="a")
    assert new.resource_id != old.resource_id
    assert r2.loads == ["p", "p"]
    rr.release(old.id)
    assert r2.unloads == ["p"]


def test_ok_after_fatal_recovers_the_resource_for_new_requests() -> None:
    rr, _, r2 = chain()
    old = rr.call("m2", Req("p"), client="a")
    rr.send_status(old.id, Status.FATAL, "device silent")
    rr.send_status(old.id, Status.OK, "device answers again")
    again = rr.call("m2", Req("p"), client="b")
    assert again.resource_id == old.resource_id  # shared again, not loaded twice
    assert r2.loads == ["p"]
    assert not rr.info(old.id).failed


def test_ok_does_not_recover_a_resource_replaced_by_a_fresh_one() -> None:
    rr, _, r2 = chain()
    old = rr.call("m2", Req("p"), client="a")
    rr.send_status(old.id, Status.FATAL, "died")
    new = rr.call("m2", Req("p"), client="a")
    rr.send_status(old.id, Status.OK, "late")
    assert rr.info(old.id).failed
    assert rr.call("m2", Req("p"), client="c").resource_id == new.resource_id
    assert r2.loads == ["p", "p"]


def test_a_recovery_survives_a_restart(tmp_path: Any) -> None:
    path = tmp_path / "rr.catalog"
    rr, _, _ = build(path)
    ref = rr.call("m2", Req("p"), client="a")
    rr.send_status(ref.id, Status.FATAL, "silent")
    rr.send_status(ref.id, Status.OK, "back")
    rr.close()
    again, _, r2 = build(path, restore=True)
    assert again.call("m2", Req("p"), client="b").resource_id == ref.resource_id
    assert r2.loads == []
    again.close()


def test_release_client_releases_everything_it_holds() -> None:
    rr, r1, _ = chain()
    rr.call("m1", Req("x"), client="action")
    rr.call("m1", Req("y"), client="action")
    rr.call("m1", Req("y"), client="other")
    assert rr.release_client("action") == 2
    assert r1.unloads == ["x"]
    assert [r.client for r in rr.references()] == ["other"]


def test_bad_input_gives_typed_errors() -> None:
    rr, _, _ = chain()
    with pytest.raises(ResourceNotFoundError, match="no server named 'nope'"):
        rr.call("nope", Req("x"))
    with pytest.raises(TypeError, match="takes Req requests"):
        rr.call("m1", {"name": "x"})
    ref = rr.call("m1", Req("x"))
    rr.release(ref.id)
    with pytest.raises(ResourceClosedError, match="already released"):
        rr.release(ref.id)
    with pytest.raises(ResourceNotFoundError):
        rr.release("no-such-id")

    @dataclass(frozen=True)
    class Odd(Req):
        blob: Any = None

    class OddServer(Counting):
        request_type = Odd

    rr.register(OddServer(rr, name="odd"))
    with pytest.raises(TypeError, match="cannot be serialised"):
        rr.call("odd", Odd("x", blob=object()))


def test_exclusive_higher_priority_pre_empts_and_hands_back() -> None:
    rr, r1, _ = chain()
    low_updates: list[StatusUpdate] = []
    low = rr.call(
        "m1", Req("arm"), client="task", priority=1, exclusive=True, on_status=low_updates.append
    )
    with pytest.raises(ResourceBusyError, match="priority 1"):
        rr.call("m1", Req("arm"), client="peer", priority=1, exclusive=True)
    high = rr.call("m1", Req("arm"), client="safety", priority=5, exclusive=True)
    assert [u.status for u in low_updates] == [Status.WARNING]
    assert "pre-empted by 'safety'" in low_updates[0].message
    assert {r.client: r.suspended for r in rr.references()} == {"task": True, "safety": False}
    assert rr.release(high.id) is False  # the suspended consumer keeps it loaded
    assert [u.status for u in low_updates] == [Status.WARNING, Status.OK]
    assert low_updates[1].message == "resource returned"
    assert r1.loads == ["arm"]
    rr.release(low.id)
    assert r1.unloads == ["arm"]


def test_concurrent_equal_requests_load_once() -> None:
    gate = threading.Event()

    class Slow(Counting):
        def on_load(self, request: Req, ctx: LoadContext) -> Resp:
            gate.wait(5)
            return super().on_load(request, ctx)

    rr = Registrar("rr")
    slow = Slow(rr, name="slow")
    rr.register(slow)
    results: list[Any] = []
    threads = [
        threading.Thread(target=lambda: results.append(rr.call("slow", Req("x")))) for _ in range(5)
    ]
    for t in threads:
        t.start()
    gate.set()
    for t in threads:
        t.join(5)
    assert slow.loads == ["x"]
    assert len({r.resource_id for r in results}) == 1
    assert len({r.id for r in results}) == 5


# ================ persistence


def build(path: Any, restore: bool = False) -> tuple[Registrar, Counting, Counting]:
    rr = Registrar("rr", catalog=path, restore=restore, fsync="never")
    r1 = Counting(rr, name="m1", sub_server="m2")
    r2 = Counting(rr, name="m2")
    rr.register(r1)
    rr.register(r2)
    return rr, r1, r2


def accounting(rr: Registrar) -> list[tuple[Any, ...]]:
    return sorted(
        (i.id, i.server, i.request.name, tuple(sorted(i.consumers)), len(i.dependencies), i.failed)
        for i in rr.resources()
    )


def test_restore_gives_back_exactly_the_same_accounting(tmp_path: Any) -> None:
    path = tmp_path / "rr.catalog"
    rr, _, _ = build(path)
    a = rr.call("m1", Req("R1", ("a", "b")), client="x")
    rr.call("m1", Req("R1", ("a", "b")), client="y")
    c = rr.call("m2", Req("c"), client="x")
    rr.release(c.id)
    rr.call("m2", Req("a"), client="z", exclusive=True, priority=3)
    before = accounting(rr)
    refs_before = sorted(rr.references(), key=lambda r: r.id)
    rr.close()  # as if killed: nothing released
    again, r1, r2 = build(path, restore=True)
    assert accounting(again) == before
    assert sorted(again.references(), key=lambda r: r.id) == refs_before
    assert (r1.loads, r2.loads) == ([], [])  # nothing is loaded twice
    # and it keeps working: releasing the restored references unloads in cascade
    again.release(a.id)
    again.release_client("y")
    assert r1.unloads == ["R1"]
    assert sorted(r2.unloads) == ["b"]  # 'a' is still held by z
    again.close()


def test_a_catalog_is_never_overwritten_without_restore(tmp_path: Any) -> None:
    path = tmp_path / "rr.catalog"
    rr, _, _ = build(path)
    rr.call("m2", Req("a"))
    rr.close()
    with pytest.raises(Exception, match="restore=True"):
        Registrar("rr", catalog=path)


# ================ resources held by actions (RAII)


def test_actions_release_their_resources_when_the_graph_ends_and_notice_failures() -> None:
    from temoto import Action, ActionCatalog, ActionEngine, parse_graph, parse_umrf
    from temoto.core.states import Result
    from temoto.errors import ResourceBrokenError

    rr, _, r2 = chain()
    seen: list[str] = []
    acquired = threading.Event()

    class Holder(Action):
        def on_run(self) -> bool:
            self.acquire("m2", Req("camera"))
            acquired.set()
            try:
                self.wait_until_stopped(10)
            except ResourceBrokenError as err:
                seen.append(str(err))
                return False
            return True

    catalog = ActionCatalog(use_entry_points=False)
    catalog.register(Holder, parse_umrf({"name": "Holder", "type": "sync"}))
    graph = parse_graph({"graph_name": "g", "actions": [{"name": "Holder", "type": "sync"}]})
    with ActionEngine("me", actions=catalog, registrar=rr) as engine:
        engine.start(graph)
        assert acquired.wait(5)
        (camera,) = rr.resources()
        assert camera.consumers == ["g/Holder_0"]
        rr.send_status(camera.id, Status.FATAL, "camera unplugged")
        assert engine.wait("g", 5) is Result.FALSE
        assert seen == ["the m2 resource is FATAL: camera unplugged"]  # m2: the server
    # the release runs on a worker right after the graph ends; shutdown joined the workers
    assert rr.resources() == []
    assert r2.unloads == ["camera"]


def test_a_stopped_graph_releases_its_resources_without_another_engine_call() -> None:
    from temoto import Action, ActionCatalog, ActionEngine, parse_graph, parse_umrf
    from temoto.core.states import Result

    rr, _, r2 = chain()
    acquired = threading.Event()
    unloaded = threading.Event()

    class Holder(Action):
        def on_run(self) -> bool:
            self.acquire("m2", Req("camera"))
            acquired.set()
            self.wait_until_stopped(10)
            return True

    def on_unload(request: Req, response: Resp) -> None:
        Counting.on_unload(r2, request, response)
        unloaded.set()

    r2.on_unload = on_unload  # type: ignore[method-assign]
    catalog = ActionCatalog(use_entry_points=False)
    catalog.register(Holder, parse_umrf({"name": "Holder", "type": "sync"}))
    graph = parse_graph({"graph_name": "g", "actions": [{"name": "Holder", "type": "sync"}]})
    with ActionEngine("me", actions=catalog, registrar=rr) as engine:
        engine.start(graph)
        assert acquired.wait(5)
        assert engine.stop("g", timeout=5) is Result.STOPPED
        # released by the worker that finished the stopped action, not by a later call
        assert unloaded.wait(5), "the stopped graph still holds its resource"
        assert rr.resources() == []


def test_pre_emption_survives_a_restart(tmp_path: Any) -> None:
    path = tmp_path / "rr.catalog"
    rr, _, _ = build(path)
    low = rr.call("m2", Req("arm"), client="task", priority=1, exclusive=True)
    high = rr.call("m2", Req("arm"), client="safety", priority=5, exclusive=True)
    rr.close()
    again, _, r2 = build(path, restore=True)
    states = {r.client: r.suspended for r in again.references()}
    assert states == {"task": True, "safety": False}
    back: list[StatusUpdate] = []
    again.subscribe(low.id, back.append)
    again.release(high.id)
    assert [(u.status, u.message) for u in back] == [(Status.OK, "resource returned")]
    again.release(low.id)
    assert r2.unloads == ["arm"]
    again.close()
    third, _, _ = build(path, restore=True)
    assert third.resources() == []
    third.close()


@dataclass
class Undoing(Counting):
    """Records what the restore asked it to undo or check."""

    abandoned: list[tuple[str, Any]] = field(default_factory=list)
    verdicts: dict[str, tuple[Status, str]] = field(default_factory=dict)

    def on_abandoned(self, request: Req, progress: Any) -> None:
        self.abandoned.append((request.name, progress))

    def on_restore(self, resource: ResourceInfo) -> tuple[Status, str] | None:
        return self.verdicts.get(resource.request.name)


def test_restore_undoes_a_load_the_crash_interrupted(tmp_path: Any) -> None:
    from temoto.core.registrar.journal import Journal

    path = tmp_path / "rr.catalog"
    rr = Registrar("rr", catalog=path, fsync="never")
    rr.register(Counting(rr, name="m1", sub_server="m2"))
    rr.register(Counting(rr, name="m2"))
    held = rr.call("m2", Req("dep"), client="x")
    rr.close()
    # what a crash in the middle of loading "top" (after it acquired "dep") leaves behind
    journal = Journal(path, fsync="never")
    journal.open()
    journal.append(
        {
            "op": "begin",
            "uid": "m1:old-1",
            "server": "m1",
            "request": {"name": "top", "subs": [], "fail": False},
        }
    )
    journal.append({"op": "progress", "uid": "m1:old-1", "data": {"pid": 4242}})
    journal.append(
        {
            "op": "ref",
            "id": "old-2",
            "uid": held.resource_id,
            "client": "rr/m1:old-1",
            "priority": 0,
            "exclusive": False,
            "holder": "m1:old-1",
            "suspended": False,
            "suspends": [],
        }
    )
    journal.close()
    again = Registrar("rr", catalog=path, restore=True, fsync="never")
    top = Undoing(again, name="m1", sub_server="m2")
    bottom = Undoing(again, name="m2")
    again.register(top)
    assert again.resources() == []  # nothing is visible until every server is back
    again.register(bottom)
    assert top.abandoned == [("top", {"pid": 4242})]
    (dep,) = again.resources()
    assert dep.consumers == ["x"]  # the interrupted load's reference was released
    assert bottom.unloads == []
    again.close()


def test_restore_finishes_an_interrupted_release_and_reports_what_died(tmp_path: Any) -> None:
    from temoto.core.registrar.journal import Journal

    path = tmp_path / "rr.catalog"
    rr = Registrar("rr", catalog=path, fsync="never")
    rr.register(Counting(rr, name="m1", sub_server="m2"))
    rr.register(Counting(rr, name="m2"))
    going = rr.call("m2", Req("going"), client="x")
    staying = rr.call("m2", Req("staying"), client="x")
    rr.close()
    journal = Journal(path, fsync="never")
    journal.open()
    journal.append({"op": "unref", "id": going.id, "resumes": []})  # crash before the unload
    journal.close()
    again = Registrar("rr", catalog=path, restore=True, fsync="never")
    m2 = Undoing(again, name="m2")
    m2.verdicts = {"staying": (Status.FATAL, "died while the manager was down")}
    again.register(Counting(again, name="m1", sub_server="m2"))
    got: list[StatusUpdate] = []
    again.register(m2)
    assert m2.unloads == ["going"]
    again.subscribe(staying.id, got.append)
    (info,) = again.resources()
    assert info.failed
    assert m2.statuses == [("staying", Status.FATAL, "died while the manager was down")]
    again.close()


def test_a_corrupt_catalog_is_refused_and_left_untouched(tmp_path: Any) -> None:
    from temoto.errors import CatalogCorruptError

    path = tmp_path / "rr.catalog"
    rr, _, _ = build(path)
    for name in "abcdef":
        rr.call("m2", Req(name), client="x")
    rr.close()
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(CatalogCorruptError):
        Registrar("rr", catalog=path, restore=True)
    assert path.read_bytes() == bytes(data)


def test_a_catalog_whose_records_do_not_fit_is_corrupt(tmp_path: Any) -> None:
    from temoto.core.registrar.journal import Journal
    from temoto.errors import CatalogCorruptError

    path = tmp_path / "rr.catalog"
    journal = Journal(path, fsync="never")
    journal.open()
    journal.append({"op": "unref", "id": "never-taken"})
    journal.close()
    with pytest.raises(CatalogCorruptError, match="record 1"):
        Registrar("rr", catalog=path, restore=True)


# ================================================================ precompiled record layouts


@pytest.mark.parametrize(
    ("client", "holder", "suspends", "exclusive", "priority"),
    [
        ("bench", "", [], False, 0),
        ('Grüße "quoted"\\ / \n 日本語 \U0001f916', "r-9", ["a-1", 'b"2'], True, -7),
        ("", "x", ["only"], False, 2**40),
    ],
)
def test_the_ref_and_unref_layouts_write_the_encoders_very_bytes(
    client: str, holder: str, suspends: list[str], exclusive: bool, priority: int
) -> None:
    from temoto.core.registrar import records
    from temoto.core.registrar.journal import encode

    for suspended, pre_empted in ((True, suspends), (False, suspends), (False, [])):
        fields = records.RefFields("a-1", "u-1", client, priority, exclusive, holder, suspended)
        record = records.Ref(fields, tuple(pre_empted))
        text = records.Ref.text(
            "a-1", "u-1", client, priority, exclusive, holder, suspended, pre_empted
        )
        assert text is not None
        assert text.encode("utf-8") == encode(record.plain()) == record.encode()
    unref = records.Unref(client, tuple(suspends))
    assert records.Unref.text(client, suspends).encode("utf-8") == encode(unref.plain())
    assert unref.encode() == encode({"op": "unref", "id": client, "resumes": suspends})


@pytest.mark.parametrize(
    ("client", "holder", "exclusive", "priority"),
    [
        ("bench", "", False, 0),
        ('Grüße "quoted"\\ / \n 日本語 \U0001f916', "r-9", True, -7),
        ("", "x ✓", False, 2**40),
    ],
)
def test_the_ref_layout_around_an_id_and_the_unref_payload_are_the_encoders_very_bytes(
    client: str, holder: str, exclusive: bool, priority: int
) -> None:
    from temoto.core.registrar import records
    from temoto.core.registrar.journal import encode

    layout = records.Ref.layout("u-1 ✓", client, priority, exclusive, holder)
    assert layout is not None
    for ref_id in ("0a1b2c-1", "ffffff-123456789"):
        fields = records.RefFields(ref_id, "u-1 ✓", client, priority, exclusive, holder)
        assert layout[0] + ref_id.encode() + layout[1] == encode(records.Ref(fields).plain())
    for ref_id in ("0a1b2c-1", 'a "quoted" ✓'):
        assert records.Unref.payload(ref_id) == encode(records.Unref(ref_id).plain())
    assert records.Ref.layout("u", "c", True, False, "") is None  # bool priority
    assert records.Ref.layout("u", "c", 1, 1, "") is None  # int exclusive


def test_references_of_more_clients_than_the_layout_cache_holds_replay_exactly(
    tmp_path: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    from temoto.core.registrar import _ledger

    monkeypatch.setattr(_ledger, "REF_LAYOUTS", 8)
    path = tmp_path / "catalog.tjl"
    rr, _, _ = build(path)
    refs = [rr.call("m2", Req("shared"), client=f"c{i % 20}", priority=i % 3) for i in range(60)]
    for ref in refs[::3]:
        rr.release(ref.id)
    before = accounting(rr)
    rr.close()
    again, _, _ = build(path, restore=True)
    try:
        assert accounting(again) == before
        assert len(again.references()) == 40
    finally:
        again.close()


def test_a_double_release_is_told_from_an_unknown_id_for_the_last_released_ids(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from temoto.core.registrar import _ledger

    monkeypatch.setattr(_ledger, "RELEASED_MEMORY", 10)
    rr, _, _ = chain()
    held = rr.call("m2", Req("a"), client="keeper")
    ids = [rr.call("m2", Req("a"), client="passer").id for _ in range(35)]
    for ref_id in ids:
        rr.release(ref_id)
    for ref_id in ids[-10:]:  # at least RELEASED_MEMORY of them are remembered
        with pytest.raises(ResourceClosedError, match="already released"):
            rr.release(ref_id)
    with pytest.raises(ResourceNotFoundError):
        rr.release(ids[0])  # at most twice as many: the oldest is forgotten
    with pytest.raises(ResourceNotFoundError):
        rr.release("no-such-id")
    rr.release(held.id)


def test_a_reference_of_other_types_than_the_layouts_is_written_by_the_encoder() -> None:
    from temoto.core.registrar import records
    from temoto.core.registrar.journal import encode

    assert records.Ref.text("a", "u", "c", True, False, "", False, ()) is None  # bool priority
    assert records.Ref.text("a", "u", "c", 1, 1, "", False, ()) is None  # int exclusive
    fields = records.RefFields("a", "u", "c", True, 1, "")  # type: ignore[arg-type]
    record = records.Ref(fields)
    assert record.encode() == encode(record.plain())
    assert b'"priority":true' in record.encode()


def test_deduplicated_pairs_journal_what_a_restore_reads_back(tmp_path: Any) -> None:
    path = tmp_path / "catalog.tjl"
    rr, _, _ = build(path)
    held = rr.call("m2", Req("shared"), client="holder")
    refs = [rr.call("m2", Req("shared"), client=f"c{i} ✓") for i in range(3)]
    rr.release(refs[1].id)
    before = accounting(rr)
    rr.close()
    again, _, _ = build(path, restore=True)
    try:
        assert accounting(again) == before
        (info,) = again.resources()
        assert sorted(info.consumers) == sorted(["holder", "c0 ✓", "c2 ✓"])
        assert held.id != refs[0].id
    finally:
        again.close()


def test_request_keys_of_a_dataclass_use_its_fields_in_order_of_name() -> None:
    from temoto.core.registrar.messages import canonical_json

    assert canonical_json(Req("x")) == canonical_json(Req("x"))
    assert canonical_json(Req("x")) != canonical_json(Req("y"))
    assert canonical_json({"b": 1, "a": [2]}) == '{"a":[2],"b":1}'


def test_taking_and_dropping_a_shared_resource_forever_does_not_grow_the_journal_forever(
    tmp_path: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    from temoto.core.registrar import _ledger

    monkeypatch.setattr(_ledger, "COMPACT_SLACK", 200)
    path = tmp_path / "rr.catalog"
    rr, _, r2 = build(path)
    keep = rr.call("m2", Req("a"), client="keeper")  # holds it: later releases unload nothing
    for _ in range(3 * _ledger.COMPACT_CHECK_RELEASES):
        rr.release(rr.call("m2", Req("a"), client="passer").id)
    journal = rr._ledger.journal
    assert journal is not None
    # 6,144 records were appended; compaction ran at each 1,024th release
    assert journal.record_count < 2 * _ledger.COMPACT_CHECK_RELEASES + 200
    before = accounting(rr)
    rr.close()
    again, _, r2 = build(path, restore=True)
    assert accounting(again) == before
    assert [r.id for r in again.references()] == [keep.id]
    assert r2.loads == []
    again.close()


def test_the_fast_resource_maker_makes_the_same_frozen_value() -> None:
    import dataclasses

    from temoto.core.registrar.messages import Resource, new_resource

    made = new_resource("a-1", "m2:b-1", "m2", Req("x"), Resp("y"))
    plain = Resource("a-1", "m2:b-1", "m2", Req("x"), Resp("y"))
    assert type(made) is Resource
    assert made == plain
    assert hash(made) == hash(plain)
    assert repr(made) == repr(plain)
    with pytest.raises(dataclasses.FrozenInstanceError):
        made.id = "other"  # type: ignore[misc]
