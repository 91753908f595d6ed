"""The registrar's catalog records: one definition, byte-for-byte the format of older journals.

The fixtures in ``tests/data/registrar`` were written by ``_journal_scenario.py`` running on
the registrar before its records were typed (git ``90291e4``).
"""

from __future__ import annotations

import random
import secrets
import shutil
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import _journal_scenario as scenario
import pytest

from temoto.core.registrar import Registrar, _ledger, records
from temoto.core.registrar.messages import canonical_json, request_key
from temoto.errors import ResourceBusyError

DATA = Path(__file__).parent.parent / "data" / "registrar"
FIXTURES = ("scenario.tjl", "compacted-run.tjl", "crashed-while-loading.tjl")


def payloads(path: Path) -> list[bytes]:
    """The record payloads of a journal file, as stored (journal.py's frame format)."""
    data = path.read_bytes()
    assert data[:9] == b"TEMOTOJ1\x01"
    out, off = [], 9
    while off < len(data):
        length, _crc, _seq = struct.unpack_from("<IIQ", data, off)
        out.append(data[off + 16 : off + 16 + length])
        off += 16 + length
    return out


@pytest.fixture
def fixed_boot(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(secrets, "token_hex", lambda n: scenario.BOOT)


@pytest.mark.usefixtures("fixed_boot")
def test_the_scenario_writes_the_older_registrars_journal_byte_for_byte(tmp_path: Path) -> None:
    scenario.run(tmp_path / "scenario.tjl")
    assert (tmp_path / "scenario.tjl").read_bytes() == (DATA / "scenario.tjl").read_bytes()


@pytest.mark.usefixtures("fixed_boot")
def test_compaction_writes_the_older_registrars_snapshot_byte_for_byte(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(_ledger, "COMPACT_SLACK", -(10**6))  # compact at every load and unload
    scenario.run(tmp_path / "compacted-run.tjl", crash_copy=tmp_path / "crashed.tjl")
    for mine, theirs in (("compacted-run.tjl", "compacted-run.tjl"), ("crashed.tjl", FIXTURES[2])):
        assert (tmp_path / mine).read_bytes() == (DATA / theirs).read_bytes()


@pytest.mark.parametrize("name", FIXTURES)
def test_every_stored_record_parses_and_encodes_back_to_its_bytes(name: str) -> None:
    import json

    for payload in payloads(DATA / name):
        raw = json.loads(payload)
        record = records.RECORDS[raw["op"]].parse(raw)
        assert record.encode() == payload
        assert record.plain() == raw


def test_the_fixtures_hold_every_kind_of_record() -> None:
    import json

    seen = set()
    for name in FIXTURES:
        for payload in payloads(DATA / name):
            raw = json.loads(payload)
            seen.add(raw["op"] + (" snapshot" if "refs" in raw else ""))
    assert seen == {*records.RECORDS, "load snapshot"}


def restore(tmp_path: Path, name: str) -> tuple[Registrar, scenario.Server, scenario.Server]:
    path = tmp_path / name
    shutil.copyfile(DATA / name, path)
    rr = Registrar("scenario", catalog=path, restore=True, fsync="never")
    upper, lower = scenario.servers()
    rr.register(upper)
    rr.register(lower)
    return rr, upper, lower


def test_an_older_registrars_journal_restores_what_it_held(tmp_path: Path) -> None:
    Resp = scenario.Resp  # noqa: N806
    rr, _, lower = restore(tmp_path, "scenario.tjl")
    try:
        got = {
            info.request.name: (
                info.server,
                info.response,
                [(r.client, r.priority, r.exclusive, r.suspended) for r in info.references],
                len(info.dependencies),
                info.failed,
            )
            for info in rr.resources()
        }
        dep_client = "scenario/upper:b00701-1"
        assert got == {
            "a": ("upper", Resp("new ✓", 2), [("graph/node ✓", 0, False, False)], 1, False),
            "a-dep": ("lower", Resp("lower:a-dep", 1), [(dep_client, 0, False, False)], 0, False),
            "s": ("lower", Resp("lower:s"), [("c1", 0, 0, 0), ('c2 "quoted"', 0, 0, 0)], 0, False),
            "dead": ("lower", Resp("lower:dead"), [("c5", 0, False, False)], 0, True),
            "d": ("lower", Resp("lower:d"), [("x", 0, False, True), ("y", 1, True, 0)], 0, False),
        }
        assert rr.info("upper:b00701-1").request == scenario.Req("a", 1, ("t",))
        # recovered: shared again; failed: a fresh one for an equal request
        assert rr.call("lower", scenario.Req("s")).resource_id == "lower:b00701-5"
        assert rr.call("lower", scenario.Req("dead")).resource_id not in got
        with pytest.raises(ResourceBusyError):
            rr.call("lower", scenario.Req("d"), client="z", exclusive=True, priority=1)
        assert lower.unloads == []
    finally:
        rr.close()


def test_an_older_registrars_journal_of_a_crash_mid_load_is_settled(tmp_path: Path) -> None:
    rr, upper, lower = restore(tmp_path, "crashed-while-loading.tjl")
    try:
        assert upper.abandoned == [("crash", {"n": 3, "note": "Grüße ✓", "step": "sub"})]
        assert lower.unloads == ["crash-dep"]  # the interrupted load's dependency
        assert sorted(i.request.name for i in rr.resources()) == ["a", "a-dep", "d", "dead", "s"]
    finally:
        rr.close()


def test_replay_refuses_an_unknown_operation_and_a_malformed_reference() -> None:
    from temoto.errors import CatalogCorruptError

    begin = {"op": "begin", "uid": "u", "server": "s", "request": {}}
    with pytest.raises(CatalogCorruptError, match=r"record 2 \('grow'\)"):
        records.replay([begin, {"op": "grow", "uid": "u"}], "c")
    with pytest.raises(CatalogCorruptError, match=r"record 2 \('load'\)"):
        records.replay([begin, {"op": "load", "uid": "u", "response": {}, "ref": "x"}], "c")
    with pytest.raises(CatalogCorruptError, match=r"record 1 \(\['begin'\]\)"):
        records.replay([{"op": ["begin"]}], "c")


def test_a_refused_catalog_is_let_go_of(tmp_path: Path) -> None:
    from temoto.core.registrar.journal import Journal
    from temoto.errors import CatalogCorruptError

    path = tmp_path / "c.tjl"
    journal = Journal(path, fsync="never")
    journal.open()
    journal.append({"op": "unref", "id": "never-taken"})
    journal.close()
    with pytest.raises(CatalogCorruptError):
        Registrar("rr", catalog=path, restore=True)
    again = Journal(path, fsync="never")
    assert len(again.open()) == 1  # not locked by the refused registrar, and untouched
    again.close()


# ------------------------------------------------------------------------ request keys


@dataclass(frozen=True)
class Base:
    a: int
    b: str = "x"


@dataclass(frozen=True)
class Same(Base):
    pass


@dataclass(frozen=True)
class WithC(Base):
    c: int = 0


@dataclass(frozen=True)
class WithD(Base):
    d: int = 0


@dataclass(frozen=True)
class Nested:
    inner: Base
    items: tuple[Any, ...] = ()


@dataclass(frozen=True)
class One:
    only: Any


@dataclass(frozen=True)
class Empty:
    pass


KEYED = [
    Base(1),
    Base(1, "y"),
    Same(1),
    WithC(1),
    WithD(1),
    WithC(1, "x", 2),
    WithD(1, "x", 2),
    Nested(Base(1)),
    Nested(Same(1)),
    Nested(Base(2), ({"k": [1, 2]}, "ü")),
    One([1]),
    One((1,)),
    One("1"),
    One(None),
    Empty(),
]


@pytest.mark.parametrize("first", KEYED, ids=repr)
def test_request_keys_are_equal_exactly_when_the_canonical_json_is(first: Any) -> None:
    for second in KEYED:
        same_json = canonical_json(first) == canonical_json(second)
        assert (request_key(first) == request_key(second)) is same_json, (first, second)


def test_a_request_that_cannot_be_a_key_says_why() -> None:
    loop: list[Any] = []
    loop.append(loop)
    with pytest.raises(TypeError, match="circular"):
        request_key(One(loop))
    with pytest.raises(TypeError, match="not JSON serial"):
        request_key(One(object()))
    with pytest.raises(TypeError, match="Out of range"):
        request_key(One(float("nan")))


@pytest.mark.parametrize(
    "value",
    [{"a": float("nan")}, [float("inf")], {"k": object()}, {(1, 2): "tuple key"}, "loop"],
    ids=["nan", "inf", "object", "tuple-key", "loop"],
)
def test_to_plain_refuses_what_json_dumps_refuses_with_the_same_exception(value: Any) -> None:
    import json

    from temoto.core.registrar.journal import encode
    from temoto.core.registrar.messages import to_plain

    if value == "loop":
        value = []
        value.append(value)
    with pytest.raises((TypeError, ValueError)) as theirs:
        json.dumps(value, allow_nan=False)
    with pytest.raises(theirs.type):
        to_plain(value)
    if "nan" not in repr(value) and "inf" not in repr(value):  # the journal writes those
        with pytest.raises(TypeError):  # the journal's payload: TypeError for all it refuses
            encode({"v": value})
    assert to_plain({"ok": [1, 2.5, None, "ü"], "b": {1: True}}) == {
        "ok": [1, 2.5, None, "ü"],
        "b": {1: True},
    }


# ------------------------------------------------------------------------ the books' counters


def test_the_ledgers_counts_of_exclusive_and_suspended_references_stay_exact() -> None:
    rr = Registrar("rr")
    _, lower = scenario.servers()
    rr.register(lower)
    rng = random.Random(20261127)
    held: list[str] = []
    for _ in range(3000):
        if held and rng.random() < 0.45:
            rr.release(held.pop(rng.randrange(len(held))))
        else:
            try:
                got = rr.call(
                    "lower",
                    scenario.Req(rng.choice("pq")),
                    client=f"c{rng.randrange(5)}",
                    priority=rng.randrange(4),
                    exclusive=rng.random() < 0.3,
                )
                held.append(got.id)
            except ResourceBusyError:
                pass
        for entry in rr._ledger.entries.values():
            refs = list(entry.refs.values())
            assert entry.exclusive == sum(bool(r.exclusive) for r in refs)
            assert entry.suspended == sum(r.suspended for r in refs)
            assert not refs or entry.suspended < len(refs)  # someone is always active
    rr.close()
