"""Context Manager sync: three robots on an in-process bus converge; late joiner; digests."""

from __future__ import annotations

import itertools
import threading
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from functools import partial
from typing import Any

import pytest

from temoto.clock import ManualClock
from temoto.lcm_types import context_item_t, context_update_t, handshake_t
from temoto.managers.context import CONTEXT_CHANNEL, CONTEXT_STATS, ContextManager, Pose
from temoto.managers.context._wire import chunks, from_wire
from temoto.managers.context.tree import Item
from temoto.transport import FleetAuth, FleetLink, InProcessTransport, codec
from temoto.transport.inprocess import live_buses

KEY = bytes(range(32))
WAIT_S = 5.0
_buses = itertools.count()


class Bus:
    """Robots (each with its own transport, link and Context Manager) on one in-process bus."""

    def __init__(self, name: str, stack: ExitStack) -> None:
        self.name = name
        self.stack = stack
        self.transports: list[InProcessTransport] = []
        self.managers: list[ContextManager] = []
        self.changed = threading.Condition()
        self.generation = 0

    def link(self, sender: str) -> FleetLink:
        transport = InProcessTransport(self.name)
        self.stack.callback(transport.close)
        self.transports.append(transport)
        return FleetLink(transport, FleetAuth("ctx-fleet", sender, KEY))

    def robot(self, name: str, **kwargs: Any) -> ContextManager:
        manager = ContextManager(name, link=self.link(name), **kwargs)
        self.stack.callback(manager.close)
        manager.listen(self._poke)
        self.managers.append(manager)
        return manager

    def _poke(self, _change: object) -> None:
        with self.changed:
            self.generation += 1
            self.changed.notify_all()

    def _moved(self, generation: int) -> bool:
        return self.generation != generation

    def converge(self, managers: list[ContextManager] | None = None) -> list[Any]:
        """Wait until every manager holds the same records (woken by their changes)."""
        group = managers or self.managers
        deadline = time.monotonic() + WAIT_S
        while True:
            with self.changed:
                generation = self.generation
            for transport in self.transports:
                transport.flush(WAIT_S)
            dumps = [m.dump() for m in group]
            if all(d == dumps[0] for d in dumps):
                return dumps[0]
            with self.changed:
                left = deadline - time.monotonic()
                woken = self.changed.wait_for(partial(self._moved, generation), left)
            assert woken, "\n".join(f"{m.robot}: {m.dump()}" for m in group)


@pytest.fixture
def bus(request: pytest.FixtureRequest) -> Iterator[Bus]:
    name = f"ctx-{request.node.name}-{next(_buses)}"
    with ExitStack() as stack:
        yield Bus(name, stack)
    assert name not in live_buses()


@contextmanager
def held(*transports: InProcessTransport) -> Iterator[None]:
    """Block the receive threads of some members: what is sent to them meanwhile waits."""
    release = threading.Event()
    entered = threading.Semaphore(0)

    def block(_channel: str, _data: bytes) -> None:
        entered.release()
        release.wait(WAIT_S)

    subs = [t.subscribe("TEST_HOLD", block) for t in transports]
    try:
        transports[0].publish("TEST_HOLD", b"")  # every member of the bus holding gets it
        for _ in transports:
            assert entered.acquire(timeout=WAIT_S)
        yield
    finally:
        release.set()
        for sub in subs:
            sub.unsubscribe()


def test_a_change_reaches_every_robot(bus: Bus) -> None:
    a, b, c = bus.robot("A"), bus.robot("B"), bus.robot("C")
    a.add("map", "map")
    bus.converge()
    b.add("trash", "object", "map", Pose(2.0, 1.0))
    c.add("bin", "object", "map", Pose(4.0, 0.0))
    bus.converge()
    assert c.get("trash").maintainer == "B"
    a.move("trash", "bin", Pose())
    bus.converge()
    assert b.path("trash") == ["map", "bin", "trash"]
    assert b.world_pose("trash").x == pytest.approx(4.0)
    c.remove("bin", cascade=True)
    dump = bus.converge()
    assert [r.name for r in dump if isinstance(r, Item)] == ["map"]
    assert a.stats["changes_sent"] >= 2
    assert a.stats["records_applied"] >= 4


def test_concurrent_conflicting_changes_converge(bus: Bus) -> None:
    a, b, c = bus.robot("A"), bus.robot("B"), bus.robot("C")
    a.add("map", "map")
    a.add("x", "object", "map")
    a.add("y", "object", "map")
    a.add("shelf", "object", "map")
    bus.converge()
    with held(*bus.transports):  # nobody hears the others until every change is made
        # three robots add the same name differently
        a.add("cup", "object", "map", Pose(1.0))
        b.add("cup", "mug", "map", Pose(2.0))
        c.add("cup", "glass", "map", Pose(3.0))
        # two re-parents that close a cycle once merged
        a.move("x", "y")
        b.move("y", "x")
        # a parent removed on one robot while another adds a child under it
        c.remove("shelf", cascade=True)
        a.add("book", "object", "shelf")
        # update and removal of the same item
        b.update("map", attributes={"floor": 2})
        threads = [
            threading.Thread(target=m.update, args=("map",), kwargs={"pose": Pose(i)})
            for i, m in enumerate((a, b, c))
        ]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
    dump = bus.converge()
    for manager in (a, b, c):
        assert manager.digest() == a.digest()
        assert manager.detached() == a.detached()
        assert manager.subtree() == a.subtree()
    assert "cup" in a
    # the cycle is cut at one place, the child of the removed shelf is detached, nothing lost
    detached = {i.name for i in a.detached()}
    assert "book" in detached
    assert len(detached & {"x", "y"}) == 1
    assert {r.name for r in dump} >= {"map", "x", "y", "cup", "book", "shelf"}


def test_late_joiner_receives_the_tree(bus: Bus) -> None:
    a, b = bus.robot("A"), bus.robot("B")
    a.add("map", "map")
    bus.converge()
    for i in range(1500):  # more than one chunk
        (a if i % 2 else b).add(f"obj{i}", "object", "map", attributes={"i": i, "pad": "x" * 40})
    b.remove("obj3")
    bus.converge()
    c = bus.robot("C")
    dump = bus.converge()
    assert len(c) == 1500
    assert c.removed("obj3") is not None
    assert len(dump) == 1501
    # chunked: whoever answered C first (A or B, a race) sent its tree in two chunks or more
    assert max(r.stats["states_sent"] for r in (a, b)) >= 2
    assert len(list(chunks(a.dump()))) >= 2


def test_a_missed_change_is_repaired_through_the_digests(bus: Bus) -> None:
    answers = threading.Condition()
    answered: list[str] = []

    def heard(opened: Any) -> None:
        if opened.type == "context_update_t":
            with answers:
                answered.append(codec.decode(opened.type, opened.payload).requester)
                answers.notify_all()

    _raw(bus).listen(CONTEXT_CHANNEL, heard)
    a = bus.robot("A", period_s=0.02)
    b = bus.robot("B", period_s=0.02)
    with answers:  # A has answered B's start-up request: B can learn only through digests now
        assert answers.wait_for(lambda: "B" in answered, WAIT_S)
    a.add("map", "map")
    bus.converge()
    # A learns of a change that B never heard (as if its message had been lost)
    missed = Item("lost", "object", "map", Pose(), "Z", a.get("map").stamp_us + 1, "Z")
    with a._lock:
        a._tree.merge(missed)
    assert "lost" not in b
    bus.converge()
    assert b.get("lost") == missed
    assert b.stats["digest_mismatches"] >= 2 or a.stats["digest_mismatches"] >= 2
    assert a.stats["requests_received"] + b.stats["requests_received"] >= 2  # join + repair


def _raw(bus: Bus) -> FleetLink:
    return bus.link("R")


def _update(robot: str, *items: Any) -> Any:
    msg = context_update_t()
    msg.robot, msg.requester, msg.chunk, msg.chunks = robot, "", 0, 1
    msg.items = list(items)
    return msg


def _item(name: str, **fields: Any) -> Any:
    wire = context_item_t()
    wire.name, wire.type, wire.parent = name, "object", ""
    wire.maintainer = wire.writer = "R"
    wire.qw, wire.stamp_us, wire.attributes = 1.0, 5, "{}"
    for key, value in fields.items():
        setattr(wire, key, value)
    return wire


def test_bad_messages_are_counted_never_raised(bus: Bus) -> None:
    a = bus.robot("A")
    a.add("map", "map")
    raw = _raw(bus)
    # keys agreed both ways: what R sends opens at once (so the flushes below see it handled)
    assert raw.wait_for_peers(["A"], WAIT_S)
    assert a._link is not None
    assert a._link.wait_for_peers(["R"], WAIT_S)
    raw.send(CONTEXT_CHANNEL, "context_update_t", b"garbage")
    raw.send(CONTEXT_CHANNEL, *codec.encode(handshake_t()))
    raw.send(CONTEXT_CHANNEL, *codec.encode(_update("A", _item("spoof"))))  # A's name: impostor
    raw.send(CONTEXT_CHANNEL, *codec.encode(_update("", _item("anon"))))
    bad = [
        _item(""),
        _item("nan", x=float("nan")),
        _item("zero_q", qw=0.0),
        _item("self_parent", parent="self_parent"),
        _item("no_stamp", stamp_us=0),
        _item("bad_json", attributes="{"),
        _item("list_json", attributes="[]"),
        _item("ctrl\x01"),
        _item("no_type", type=""),
    ]
    raw.send(CONTEXT_CHANNEL, *codec.encode(_update("R", *bad, _item("good"))))
    for transport in bus.transports:
        assert transport.flush(WAIT_S)
    stats = a.stats
    assert stats["decode_errors"] == 1
    assert stats["unexpected"] == 2
    assert stats["impostor"] == 1  # R speaking as A (docs/security.md)
    assert stats["records_invalid"] == len(bad)
    assert [i.name for i in a.items()] == ["good", "map"]
    assert set(stats) == set(CONTEXT_STATS)


def test_wire_round_trip() -> None:
    item = Item("a", "object", "b", Pose(1, 2, 3, 0, 0, 1, 1), "m", 7, "w", '{"k":[1,2]}')
    for batch in chunks([item]):
        assert [from_wire(w) for w in batch] == [item]


def test_digests_follow_the_manual_clock(bus: Bus) -> None:
    clock = ManualClock()
    got = threading.Condition()
    digests: list[str] = []

    def heard(opened: Any) -> None:
        if opened.type == "context_digest_t":
            with got:
                digests.append(codec.decode(opened.type, opened.payload).robot)
                got.notify_all()

    _raw(bus).listen(CONTEXT_CHANNEL, heard)
    a = bus.robot("A", clock=clock, period_s=1.0)
    bus.robot("B", clock=clock, period_s=1.0)
    with got:  # both send one digest at start
        assert got.wait_for(lambda: sorted(digests) == ["A", "B"], WAIT_S)
    sent = a.stats["digests_sent"]
    clock.advance(1.0)  # a period later: one more each
    with got:
        for _ in range(50):
            if got.wait_for(lambda: len(digests) == 4, 0.1):
                break
            clock.advance(0.0)  # a timer that read the clock just before the advance waits on
    assert len(digests) == 4
    assert a.stats["digests_sent"] == sent + 1
