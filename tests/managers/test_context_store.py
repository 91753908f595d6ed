"""The world model on disk (``ContextManager(store=...)``): restarts, SIGKILL, damage."""

from __future__ import annotations

import itertools
import signal
import subprocess
import sys
from contextlib import ExitStack
from pathlib import Path

import pytest

from temoto.core.registrar.journal import Journal
from temoto.errors import CatalogCorruptError, ResourceBusyError
from temoto.managers.context import ContextManager, Pose
from temoto.managers.context.store import COMPACT_SLACK, WorldStore, record_from_json
from temoto.managers.context.tree import Item, Removal
from temoto.transport import FleetAuth, FleetLink, InProcessTransport

KEY = bytes(range(32))
_buses = itertools.count()


@pytest.fixture
def store(tmp_path: Path) -> Path:
    return tmp_path / "world.journal"


def test_every_change_is_there_after_a_restart(store: Path) -> None:
    first = ContextManager("scout", store=store)
    first.add("map", "map")
    first.add("shelf", "object", "map", Pose(3.0, 1.0), attributes={"levels": 4})
    first.add("box", "object", "shelf", Pose(0.0, 0.0, 1.2))
    first.update("shelf", pose=Pose(3.5, 1.0))
    first.add("bin", "object", "map", Pose(-1.0, 0.0))
    first.move("box", "bin")  # keeps its world pose
    first.remove("shelf")
    before, digest, world = first.dump(), first.digest(), first.world_pose("box")
    first.close()

    second = ContextManager("scout", store=store)
    try:
        assert second.dump() == before
        assert second.digest() == digest
        assert second.world_pose("box") == world
        assert second.path("box") == ["map", "bin", "box"]
        assert second.removed("shelf") is not None  # the tombstone too: an old change stays out
        assert second.get("map").attributes == {}
        # and it goes on from there
        second.add("cart", "robot", "map")
    finally:
        second.close()
    third = ContextManager("scout", store=store)
    try:
        assert "cart" in third
    finally:
        third.close()


def test_records_from_other_robots_are_stored_too(
    store: Path, request: pytest.FixtureRequest
) -> None:
    bus = f"ctx-store-{request.node.name}-{next(_buses)}"
    with ExitStack() as stack:

        def robot(name: str, **kwargs: object) -> tuple[ContextManager, InProcessTransport]:
            transport = InProcessTransport(bus)
            stack.callback(transport.close)
            link = FleetLink(transport, FleetAuth("ctx-store", name, KEY))
            manager = ContextManager(name, link=link, **kwargs)  # type: ignore[arg-type]
            stack.callback(manager.close)
            return manager, transport

        other, other_transport = robot("other")
        mine, mine_transport = robot("mine", store=store)
        other.add("map", "map")
        other.add("door", "object", "map", Pose(1.0, 2.0))
        other_transport.flush(5.0)
        mine_transport.flush(5.0)
        assert "door" in mine
        expected = mine.dump()
        mine.close()
    restored = ContextManager("mine", store=store)
    try:
        assert restored.dump() == expected
        assert restored.get("door").writer == "other"
    finally:
        restored.close()


_CHILD = """
import sys
from temoto.managers.context import ContextManager, Pose
ctx = ContextManager("child", store=sys.argv[1])
ctx.add("map", "map")
for i in range(100000):
    ctx.add(f"item{i}", "object", "map", Pose(float(i), 0.0))
    print(i, flush=True)
"""


def test_nothing_acknowledged_is_lost_on_sigkill(store: Path) -> None:
    child = subprocess.Popen(
        [sys.executable, "-c", _CHILD, str(store)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert child.stdout is not None
    try:
        last = -1
        for line in child.stdout:
            last = int(line)
            if last >= 300:
                break
        child.send_signal(signal.SIGKILL)  # mid-stream: the child is still adding
    finally:
        child.kill()
        child.communicate(timeout=30)
    assert last >= 300, "the child did not get going"
    restored = ContextManager("child", store=store)
    try:
        names = {item.name for item in restored.items()}
        # every add that returned (printed) is there, and nothing half-written broke the file
        assert {f"item{i}" for i in range(last + 1)} <= names
        assert restored.get(f"item{last}").pose == Pose(float(last), 0.0)
    finally:
        restored.close()


def test_the_file_is_compacted_and_still_restores(store: Path) -> None:
    ctx = ContextManager("scout", store=store)
    ctx.add("map", "map")
    ctx.add("rover", "robot", "map")
    for i in range(3 * COMPACT_SLACK):
        ctx.update("rover", pose=Pose(float(i), 0.0))
    ctx.close()
    reader = WorldStore(store, fsync="never")
    records = reader.open()
    reader.close()
    assert len(records) <= 2 * 2 + COMPACT_SLACK + 1  # rewritten: not 3,000 records
    restored = ContextManager("scout", store=store)
    try:
        assert restored.get("rover").pose == Pose(float(3 * COMPACT_SLACK - 1), 0.0)
    finally:
        restored.close()


def test_a_record_that_is_not_an_item_is_refused_naming_the_file(store: Path) -> None:
    journal = Journal(store, fsync="never")
    journal.open()
    journal.append({"op": "removal", "name": "x", "stamp_us": 5, "writer": "w"})
    journal.append({"op": "item", "name": "y"})  # fields missing
    journal.close()
    with pytest.raises(CatalogCorruptError, match=r"world\.journal: record 2 .*missing field"):
        ContextManager("scout", store=store)


def test_a_damaged_file_is_refused_and_left_alone(store: Path) -> None:
    ctx = ContextManager("scout", store=store)
    ctx.add("map", "map")
    ctx.add("a", "object", "map")
    ctx.close()
    data = bytearray(store.read_bytes())
    data[20] ^= 0xFF  # inside the first record, with a valid one after it: corruption
    store.write_bytes(bytes(data))
    with pytest.raises(CatalogCorruptError):
        ContextManager("scout", store=store)
    assert store.read_bytes() == bytes(data)


def test_one_process_at_a_time(store: Path) -> None:
    first = ContextManager("scout", store=store)
    try:
        with pytest.raises(ResourceBusyError):
            ContextManager("scout", store=store)
    finally:
        first.close()


def test_a_failed_write_is_counted_and_the_change_still_made(
    store: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    ctx = ContextManager("scout", store=store)
    try:
        ctx.add("map", "map")

        def full(_records: object) -> None:
            raise OSError(28, "No space left on device")

        monkeypatch.setattr(ctx._store, "append", full)
        ctx.add("a", "object", "map")
        assert "a" in ctx
        assert ctx.stats["store_errors"] == 1
    finally:
        ctx.close()


def test_json_records_round_trip() -> None:
    from temoto.managers.context.store import record_to_json

    item = Item("a", "object", "map", Pose(1.0, 2.0, 3.0), "r", 42, "w", '{"k":1}')
    removal = Removal("b", 43, "w")
    for record in (item, removal):
        assert record_from_json(record_to_json(record)) == record
    with pytest.raises(ValueError, match="unknown op"):
        record_from_json({"op": "teleport"})
    with pytest.raises(ValueError, match="pose"):
        record_from_json({**record_to_json(item), "pose": [1.0]})
