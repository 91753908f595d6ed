"""FleetActorLink: handshake, notifications and liveness between actors on an in-process bus."""

from __future__ import annotations

import itertools
import json
import logging
import struct
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import ExitStack
from typing import Any

import pytest
from _ris_helpers import Got  # the fleet tests' shared callback recorder

from temoto.clock import ManualClock
from temoto.core.states import Result
from temoto.errors import FleetError, StateError
from temoto.fleet import HANDSHAKE_CHANNEL, NOTIFY_CHANNEL, STATS, FleetActorLink
from temoto.fleet.actors import ACK_CHANNEL_PREFIX, ack_channel
from temoto.lcm_types import action_ack_t, action_notification_t, handshake_t
from temoto.transport import FleetAuth, FleetLink, InProcessTransport, Opened, codec
from temoto.transport.inprocess import live_buses

KEY = bytes(range(32))
FLEET = "test-fleet"
WAIT_S = 5.0
CALLS_THREAD = "temoto-fleet-actors-calls"
_buses = itertools.count()


class Fleet:
    """Makes links on one bus; everything made is closed when the test ends."""

    def __init__(self, bus: str, stack: ExitStack) -> None:
        self.bus = bus
        self._stack = stack

    def fleet_link(self, sender: str) -> FleetLink:
        transport = self._stack.enter_context(InProcessTransport(self.bus))
        return FleetLink(transport, FleetAuth(FLEET, sender, KEY))

    def link(self, actor: str, **kwargs: Any) -> FleetActorLink:
        return self._stack.enter_context(FleetActorLink(self.fleet_link(actor), actor, **kwargs))

    def links(self, *actors: str, **kwargs: Any) -> list[FleetActorLink]:
        return [self.link(a, **kwargs) for a in actors]


@pytest.fixture
def fleet(request: pytest.FixtureRequest) -> Iterator[Fleet]:
    bus = f"fleet-{request.node.name}-{next(_buses)}"
    with ExitStack() as stack:
        yield Fleet(bus, stack)
    assert bus not in live_buses()


def concurrently(*calls: Callable[[], object], timeout: float = 20.0) -> list[BaseException | None]:
    """Run the calls in threads at once; what each raised (None if it returned)."""
    errors: list[BaseException | None] = [None] * len(calls)
    start = threading.Barrier(len(calls))

    def run(i: int, call: Callable[[], object]) -> None:
        start.wait()
        try:
            call()
        except BaseException as err:
            errors[i] = err

    threads = [
        threading.Thread(target=run, args=(i, c), name=f"test-call-{i}")
        for i, c in enumerate(calls)
    ]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout)
        assert not thread.is_alive(), "a call did not return"
    return errors


def handshaking(
    link: FleetActorLink, actors: list[str], timeout: float = WAIT_S, session: str = "s1"
) -> Callable[[], None]:
    return lambda: link.handshake("g", session, actors, timeout)


class Raw:
    """A hand-driven fleet member: sends any message, records what comes back on channels."""

    def __init__(self, link: FleetLink, *channels: str) -> None:
        self.link = link
        self.got = Got()
        for channel in channels:
            link.listen(channel, lambda opened: self.got(opened))

    def send(self, channel: str, msg: Any) -> None:
        self.link.send(channel, *codec.encode(msg))

    def decoded(self) -> list[Any]:
        return [codec.decode(o.type, o.payload) for (o,) in self.got.calls]

    def acks(self) -> list[Any]:
        return [
            codec.decode(o.type, o.payload)
            for (o,) in self.got.calls
            if isinstance(o, Opened) and o.type == "action_ack_t"
        ]


def interrupted(
    call: Callable[[], object], begun: Got, interrupt: Callable[[], object]
) -> list[BaseException]:
    """Run a blocking ``call`` in a thread; once ``begun`` got a message, ``interrupt``; what
    the call raised."""
    got: list[BaseException] = []

    def run() -> None:
        try:
            call()
        except BaseException as err:
            got.append(err)

    thread = threading.Thread(target=run, name="test-blocked")
    thread.start()
    begun.wait_for(1)  # the call's first message is out
    interrupt()
    thread.join(WAIT_S)
    return got


def notification(nid: str, actor: str, action: str, result: str, outputs: str) -> Any:
    msg = action_notification_t()
    msg.notification_id, msg.graph, msg.session = nid, "g", "s1"
    msg.action, msg.actor, msg.result, msg.outputs = action, actor, result, outputs
    return msg


def handshake(phase: int, actor: str, graph: str = "g", session: str = "s1") -> Any:
    msg = handshake_t()
    msg.phase, msg.graph, msg.session, msg.actor = phase, graph, session, actor
    msg.stamp_us = round(time.time() * 1e6)
    msg.actors, msg.heard = "", b""
    return msg


def set_heard(msg: Any, actors: list[str], heard: dict[str, int]) -> Any:
    """Fill a handshake's actor list and heard stamps (by place; its sender's: its stamp)."""
    msg.actors = json.dumps(actors, separators=(",", ":"))
    stamps = [msg.stamp_us if a == msg.actor else heard.get(a, 0) for a in actors]
    msg.heard = struct.pack(f">{len(actors)}q", *stamps)
    return msg


def heard_of(msg: Any) -> dict[str, int]:
    """The peers a handshake says its sender heard (its own place left out)."""
    actors = json.loads(msg.actors)
    stamps = struct.unpack(f">{len(actors)}q", msg.heard)
    return {a: t for a, t in zip(actors, stamps, strict=True) if t and a != msg.actor}


# --- handshake --------------------------------------------------------------------------------


@pytest.mark.parametrize("n", [2, 3, 5])
def test_every_actor_completes_a_concurrent_handshake(fleet: Fleet, n: int) -> None:
    names = [f"robot{i}" for i in range(n)]
    links = fleet.links(*names)
    errors = concurrently(*(handshaking(link, names) for link in links))
    assert errors == [None] * n
    for link in links:
        stats = link.stats
        assert stats["handshakes_sent"] >= 2  # a JOIN, then READY
        assert stats["handshakes_received"] >= n - 1
        assert stats["decode_errors"] == stats["unexpected"] == stats["send_errors"] == 0


def test_a_missing_actor_fails_the_others_in_time_and_is_named(fleet: Fleet) -> None:
    a, b = fleet.links("A", "B")
    t0 = time.monotonic()
    errors = concurrently(
        handshaking(a, ["A", "B", "C"], 0.5), handshaking(b, ["A", "B", "C"], 0.5)
    )
    elapsed = time.monotonic() - t0
    assert 0.5 <= elapsed < 2.0
    for err in errors:
        assert isinstance(err, FleetError)
        assert "no answer from 'C'" in str(err)  # (or 'the other gave up; no answer ...')
        assert "'B' by" not in str(err)  # A and B heard each other
        assert "'A' by" not in str(err)


def test_a_late_joiner_still_completes(fleet: Fleet) -> None:
    a, b, c = fleet.links("A", "B", "C")
    names = ["A", "B", "C"]

    def late() -> None:
        threading.Event().wait(0.2)  # C starts 0.2 s after the others
        c.handshake("g", "s1", names, 3.0)

    assert concurrently(handshaking(a, names, 3.0), handshaking(b, names, 3.0), late) == [None] * 3


def test_every_newly_heard_peer_of_a_small_fleet_is_answered_at_once(fleet: Fleet) -> None:
    # Five actors start one after the other. Were only A's first three JOINs answered at once,
    # the fourth peer (D) would be answered a resend period later: with resend_s = 5 s nobody
    # would be done before 5 s.
    names = ["A", "B", "C", "D", "E"]
    links = fleet.links(*names, resend_s=5.0, silence_s=60.0)
    a = links[0]
    starts: list[float] = []

    def staggered(i: int) -> Callable[[], None]:
        def call() -> None:
            while a.stats["handshakes_sent"] < i:  # A answered the ones started before
                time.sleep(0.005)
            starts.append(time.monotonic())
            links[i].handshake("g", "s1", names, 20.0)

        return call

    assert concurrently(*(staggered(i) for i in range(5)), timeout=30.0) == [None] * 5
    assert time.monotonic() - min(starts) < 2.5  # not a resend period (5 s)


def test_a_join_heard_before_the_handshake_starts_is_kept(fleet: Fleet) -> None:
    a, b = fleet.links("A", "B")
    seen = Raw(fleet.fleet_link("X"), HANDSHAKE_CHANNEL)
    errors: list[BaseException | None] = []
    thread = threading.Thread(
        target=lambda: errors.extend(concurrently(handshaking(a, ["A", "B"]))), name="test-early"
    )
    thread.start()
    try:
        seen.got.wait_for(2)  # A has resent its JOIN
        deadline = time.monotonic() + WAIT_S
        while b.stats["handshakes_received"] < 1 and time.monotonic() < deadline:
            time.sleep(0.005)  # B's own transport thread delivers on its own schedule
        b.handshake("g", "s1", ["A", "B"], WAIT_S)
    finally:
        thread.join(WAIT_S)
    assert errors == [None]
    seen.got.wait_until(  # X's transport thread delivers on its own schedule too
        lambda calls: any(codec.decode(o.type, o.payload).actor == "B" for (o,) in calls)
    )
    first_of_b = next(m for m in seen.decoded() if m.actor == "B")
    assert list(heard_of(first_of_b)) == ["A"]  # B's very first JOIN names A


def test_two_sessions_run_side_by_side(fleet: Fleet) -> None:
    a, b = fleet.links("A", "B")
    errors = concurrently(
        handshaking(a, ["A", "B"], session="s1"),
        handshaking(b, ["A", "B"], session="s1"),
        handshaking(a, ["A", "B"], session="s2"),
        handshaking(b, ["A", "B"], session="s2"),
    )
    assert errors == [None] * 4


def test_handshakes_of_different_sessions_do_not_mix(fleet: Fleet) -> None:
    a, b, c = fleet.links("A", "B", "C")
    names = ["A", "B", "C"]
    errors = concurrently(
        handshaking(a, names, 0.5, session="s1"),
        handshaking(b, names, 0.5, session="s1"),
        handshaking(c, names, 0.5, session="s2"),
    )
    assert all(isinstance(err, FleetError) for err in errors)
    assert "no answer from 'C'" in str(errors[0])
    assert "no answer from 'C'" in str(errors[1])
    assert "no answer from 'A', 'B'" in str(errors[2])


def test_handshakes_of_other_graphs_do_not_mix(fleet: Fleet) -> None:
    a, b = fleet.links("A", "B")
    errors = concurrently(
        lambda: a.handshake("g1", "s1", ["A", "B"], 0.4),
        lambda: b.handshake("g2", "s1", ["A", "B"], 0.4),
    )
    assert all(isinstance(err, FleetError) for err in errors)


def test_an_actor_that_gives_up_makes_the_others_fail_at_once(fleet: Fleet) -> None:
    a, b = fleet.links("A", "B")
    names = ["A", "B", "C"]
    t0 = time.monotonic()
    errors = concurrently(handshaking(a, names, 0.3), handshaking(b, names, 10.0))
    assert time.monotonic() - t0 < 3.0  # B did not wait its 10 s
    assert isinstance(errors[0], FleetError)
    assert "timed out" in str(errors[0])
    assert isinstance(errors[1], FleetError)
    assert "'A' gave up" in str(errors[1])


def test_a_run_can_handshake_again_after_end(fleet: Fleet) -> None:
    a, b = fleet.links("A", "B")
    for _ in range(3):
        assert concurrently(handshaking(a, ["A", "B"]), handshaking(b, ["A", "B"])) == [None] * 2
        a.end("g", "s1")
        b.end("g", "s1")


def test_every_run_gets_one_run_id_on_every_actor_and_a_new_one_each_time(fleet: Fleet) -> None:
    names = ["A", "B", "C"]
    links = fleet.links(*names)
    seen: list[str] = []
    for _ in range(2):
        ids: list[str] = []
        calls = [
            lambda link=link, ids=ids: ids.append(link.handshake("g", "s1", names, WAIT_S))
            for link in links
        ]
        assert concurrently(*calls) == [None] * 3
        assert len(set(ids)) == 1, ids  # agreed
        (run_id,) = set(ids)
        assert run_id.startswith("s1@")
        assert run_id not in seen  # the same session name, another run
        seen.append(run_id)
        # messages of the run name it by its run id: a notification under it is delivered
        got = Got()
        links[1].expect("g", run_id, "Step_0", "A", got)
        links[0].notify("g", run_id, "Step_0", Result.TRUE, {}, ["B", "C"], WAIT_S)
        got.wait_for(1)
        for link in links:
            link.end("g", run_id)


def test_a_peer_still_in_the_previous_run_does_not_complete_a_new_one(fleet: Fleet) -> None:
    a, b = fleet.links("A", "B")
    assert concurrently(handshaking(a, ["A", "B"]), handshaking(b, ["A", "B"])) == [None] * 2
    a.end("g", "s1")  # B is still in the run: it answers, but its heard list is the old one
    done = Got()
    errors: list[BaseException] = []

    def again() -> None:
        try:
            a.handshake("g", "s1", ["A", "B"], WAIT_S)
        except BaseException as err:
            errors.append(err)
        done()

    thread = threading.Thread(target=again, name="test-again")
    thread.start()
    try:
        assert not threading.Event().wait(0.3)
        assert done.calls == []  # stale answers do not complete it
        b.end("g", "s1")
        b.handshake("g", "s1", ["A", "B"], WAIT_S)
        done.wait_for(1)
    finally:
        thread.join(WAIT_S)
    assert errors == []


def test_a_late_joiner_answered_after_the_run_ended_agrees_on_its_run_id(fleet: Fleet) -> None:
    # A completes and ends its run while B, whose READYs were lost, still joins: A answers B's
    # JOIN with the READY of the ended run. That READY must carry the run id agreed, or B agrees
    # on its own proposal and never hears A's END under its id (it found A lost instead: the
    # property test, 1 run in 8).
    a = fleet.link("A")
    b = Raw(fleet.fleet_link("B"), HANDSHAKE_CHANNEL)
    agreed: list[str] = []
    thread = threading.Thread(
        target=lambda: agreed.append(a.handshake("g", "s1", ["A", "B"], WAIT_S)),
        name="test-a",
    )
    thread.start()
    try:
        b.got.wait_until(lambda calls: any(m.actor == "A" for m in b.decoded()))
        first = next(m for m in b.decoded() if m.actor == "A")
        join = set_heard(handshake(1, "B"), ["A", "B"], {"A": first.stamp_us})
        join.run_id = "s1@ffffffffffff"  # larger than A's proposal: A's is the run id
        b.send(HANDSHAKE_CHANNEL, join)
    finally:
        thread.join(WAIT_S)
    (run_id,) = agreed
    assert run_id != join.run_id

    def ready(m: Any) -> bool:
        return bool(m.phase == 2 and m.actors and m.graph == "g")

    b.got.wait_until(lambda calls: any(ready(m) for m in b.decoded()))  # A's own READY
    a.end("g", run_id, result=Result.TRUE)
    seen = len(b.got.calls)
    late = set_heard(handshake(1, "B"), ["A", "B"], {"A": first.stamp_us})  # a newer JOIN
    late.run_id = join.run_id
    b.send(HANDSHAKE_CHANNEL, late)

    b.got.wait_until(lambda calls: any(ready(m) for m in b.decoded()[seen:]))
    answer = next(m for m in b.decoded()[seen:] if ready(m))
    assert heard_of(answer) == {"B": join.stamp_us}  # its frozen heard list
    assert answer.run_id == run_id


def test_handshake_arguments(fleet: Fleet) -> None:
    (a,) = fleet.links("A")
    a.handshake("g", "s1", ["A"], 0.0)  # alone: nothing to wait for
    with pytest.raises(ValueError, match="do not include this actor"):
        a.handshake("g", "s1", ["B", "C"], 1.0)
    with pytest.raises(ValueError, match="timeout"):
        a.handshake("g", "s1", ["A", "B"], -1.0)
    with pytest.raises(ValueError, match="graph"):
        a.handshake("", "s1", ["A", "B"], 1.0)


def test_a_second_handshake_of_the_same_run_is_refused(fleet: Fleet) -> None:
    a, _ = fleet.links("A", "B")
    errors = concurrently(handshaking(a, ["A", "C"], 0.5), handshaking(a, ["A", "C"], 0.5))
    kinds = sorted(type(err).__name__ for err in errors)
    assert kinds == ["FleetError", "StateError"]
    assert any(isinstance(err, StateError) and "is running" in str(err) for err in errors)


def test_end_fails_a_running_handshake(fleet: Fleet) -> None:
    (a,) = fleet.links("A")
    seen = Raw(fleet.fleet_link("X"), HANDSHAKE_CHANNEL)
    got = interrupted(
        lambda: a.handshake("g", "s1", ["A", "C"], WAIT_S), seen.got, lambda: a.end("g", "s1")
    )
    assert len(got) == 1
    assert isinstance(got[0], FleetError)
    assert "ended" in str(got[0])


# --- notifications ----------------------------------------------------------------------------


def test_notify_returns_when_acknowledged_and_expect_before_gets_it(fleet: Fleet) -> None:
    a, b = fleet.links("A", "B")
    got = Got()
    b.expect("g", "s1", "Move_1", "A", got)
    a.notify("g", "s1", "Move_1", Result.TRUE, {"x": 1.5}, ["B"], WAIT_S)
    assert got.wait_for(1) == [(Result.TRUE, {"x": 1.5})]
    assert got.threads == [CALLS_THREAD]
    assert a.stats["acks_received"] >= 1
    assert b.stats["acks_sent"] >= 1


def test_a_notification_that_arrived_first_is_delivered_on_expect(fleet: Fleet) -> None:
    a, b = fleet.links("A", "B")
    a.notify("g", "s1", "Move_1", Result.FALSE, {}, ["B"], WAIT_S)  # nobody expects it yet
    got = Got()
    b.expect("g", "s1", "Move_1", "A", got)
    assert got.wait_for(1) == [(Result.FALSE, {})]
    assert got.threads == [CALLS_THREAD]  # not on the caller's thread


def test_outputs_round_trip(fleet: Fleet) -> None:
    a, b = fleet.links("A", "B")
    outputs: Mapping[str, Any] = {
        "text": "hällo",
        "count": 3,
        "ratio": 0.25,
        "ok": True,
        "nothing": None,
        "pose": {"frame": "map", "xyz": [1.0, 2.0, 3.0], "meta": {"deep": [False, {"k": "v"}]}},
    }
    got = Got()
    b.expect("g", "s1", "Detect_2", "A", got)
    a.notify("g", "s1", "Detect_2", Result.TRUE, outputs, ["B"], WAIT_S)
    assert got.wait_for(1) == [(Result.TRUE, outputs)]


def test_every_listed_actor_must_acknowledge(fleet: Fleet) -> None:
    a, b, c = fleet.links("A", "B", "C")
    got_b, got_c = Got(), Got()
    b.expect("g", "s1", "Move_1", "A", got_b)
    c.expect("g", "s1", "Move_1", "A", got_c)
    a.notify("g", "s1", "Move_1", Result.STOPPED, {}, ["A", "B", "C"], WAIT_S)
    assert got_b.wait_for(1) == got_c.wait_for(1) == [(Result.STOPPED, {})]


def test_a_missing_actor_makes_notify_fail_naming_it(fleet: Fleet) -> None:
    a, _ = fleet.links("A", "B")
    t0 = time.monotonic()
    with pytest.raises(FleetError, match=r"not acknowledged by 'C' within 0\.3 s") as info:
        a.notify("g", "s1", "Move_1", Result.TRUE, {}, ["B", "C"], 0.3)
    assert 0.3 <= time.monotonic() - t0 < 2.0
    assert "'B'" not in str(info.value)
    # resent after the period in which only B acknowledged (a period that brought an
    # acknowledgement is not followed by a copy)
    assert a.stats["notifications_sent"] >= 2


def test_resends_are_acknowledged_and_delivered_once(fleet: Fleet) -> None:
    a, b = fleet.links("A", "B")
    first, second, flush = Got(), Got(), Got()
    b.expect("g", "s1", "Move_1", "A", first)
    b.expect("g", "s1", "Move_1", "A", second)  # would take a second notification
    with pytest.raises(FleetError, match="'C'"):  # C never answers, so A resends to all
        a.notify("g", "s1", "Move_1", Result.TRUE, {"n": 1}, ["B", "C"], 0.75)
    # B handles its channel in order: once this one is acknowledged, the copies are handled.
    b.expect("g", "s1", "Flush_1", "A", flush)
    a.notify("g", "s1", "Flush_1", Result.TRUE, {}, ["B"], WAIT_S)
    flush.wait_for(1)
    assert first.calls == [(Result.TRUE, {"n": 1})]
    assert second.calls == []
    stats = b.stats
    assert stats["duplicates"] >= 2
    assert stats["acks_sent"] == stats["notifications_received"]  # every copy acknowledged


def test_an_action_that_runs_again_is_a_new_notification(fleet: Fleet) -> None:
    a, b = fleet.links("A", "B")
    got1, got2 = Got(), Got()
    b.expect("g", "s1", "Loop_1", "A", got1)
    a.notify("g", "s1", "Loop_1", Result.TRUE, {"i": 1}, ["B"], WAIT_S)
    a.notify("g", "s1", "Loop_1", Result.FALSE, {"i": 2}, ["B"], WAIT_S)
    b.expect("g", "s1", "Loop_1", "A", got2)
    assert got1.wait_for(1) == [(Result.TRUE, {"i": 1})]
    assert got2.wait_for(1) == [(Result.FALSE, {"i": 2})]


def test_a_cancelled_expectation_leaves_the_notification_for_the_next(fleet: Fleet) -> None:
    a, b = fleet.links("A", "B")
    cancelled, later = Got(), Got()
    cancel = b.expect("g", "s1", "Move_1", "A", cancelled)
    cancel()
    cancel()  # idempotent
    a.notify("g", "s1", "Move_1", Result.TRUE, {}, ["B"], WAIT_S)
    b.expect("g", "s1", "Move_1", "A", later)
    assert later.wait_for(1) == [(Result.TRUE, {})]
    assert cancelled.calls == []


def test_notifications_of_other_runs_actions_and_actors_are_kept_apart(fleet: Fleet) -> None:
    a, b, c = fleet.links("A", "B", "C")
    got = {k: Got() for k in ("s1/A", "s2/A", "s1/C", "other")}
    c.expect("g", "s1", "Move_1", "A", got["s1/A"])
    c.expect("g", "s2", "Move_1", "A", got["s2/A"])
    a.expect("g", "s1", "Move_1", "C", got["s1/C"])
    c.expect("g", "s1", "Move_1", "B", got["other"])
    a.notify("g", "s2", "Move_1", Result.FALSE, {"run": 2}, ["C"], WAIT_S)
    a.notify("g", "s1", "Move_1", Result.TRUE, {"run": 1}, ["C"], WAIT_S)
    c.notify("g", "s1", "Move_1", Result.ERROR, {}, ["A"], WAIT_S)
    assert got["s1/A"].wait_for(1) == [(Result.TRUE, {"run": 1})]
    assert got["s2/A"].wait_for(1) == [(Result.FALSE, {"run": 2})]
    assert got["s1/C"].wait_for(1) == [(Result.ERROR, {})]
    assert got["other"].calls == []
    assert b.stats["acks_sent"] >= 2  # B acknowledges what it hears, expected or not


def test_end_drops_what_was_kept_for_the_run(fleet: Fleet) -> None:
    a, b = fleet.links("A", "B")
    a.notify("g", "s1", "Move_1", Result.TRUE, {}, ["B"], WAIT_S)
    b.end("g", "s1")
    dropped, flush = Got(), Got()
    b.expect("g", "s1", "Move_1", "A", dropped)
    b.expect("g", "s1", "Flush_1", "A", flush)
    a.notify("g", "s1", "Flush_1", Result.TRUE, {}, ["B"], WAIT_S)
    flush.wait_for(1)
    assert dropped.calls == []


def test_a_late_resend_after_end_is_acknowledged_but_not_taken_again(fleet: Fleet) -> None:
    (b,) = fleet.links("B")
    raw = Raw(fleet.fleet_link("X"), ack_channel("X"))
    first, again, flush = Got(), Got(), Got()
    b.expect("g", "s1", "Move_1", "X", first)
    raw.send(NOTIFY_CHANNEL, notification("n1", "X", "Move_1", "on_true", ""))
    first.wait_for(1)
    b.end("g", "s1")
    b.expect("g", "s1", "Move_1", "X", again)
    b.expect("g", "s1", "Flush_1", "X", flush)
    raw.send(NOTIFY_CHANNEL, notification("n1", "X", "Move_1", "on_true", ""))  # the ack was lost
    raw.send(NOTIFY_CHANNEL, notification("n2", "X", "Flush_1", "on_true", ""))
    flush.wait_for(1)
    assert again.calls == []
    raw.got.wait_for(3)
    assert [ack.notification_id for ack in raw.acks()] == ["n1", "n1", "n2"]
    assert b.stats["duplicates"] == 1


def test_a_member_naming_another_actor_is_dropped_and_logged(
    fleet: Fleet, caplog: pytest.LogCaptureFixture
) -> None:
    # X seals with its own key but writes "C" as the actor of a notification, an
    # acknowledgement and a handshake: B takes none of them (docs/security.md)
    (b,) = fleet.links("B")
    x = Raw(fleet.fleet_link("X"), ack_channel("X"), ack_channel("C"))
    taken, flush = Got(), Got()
    b.expect("g", "s1", "Move_1", "C", taken)
    b.expect("g", "s1", "Flush_1", "X", flush)
    with caplog.at_level(logging.WARNING, logger="temoto.fleet.common"):
        x.send(NOTIFY_CHANNEL, notification("n1", "C", "Move_1", "on_true", ""))
        x.send(HANDSHAKE_CHANNEL, handshake(1, "C"))
        ack = action_ack_t()
        ack.notification_id, ack.graph, ack.session, ack.actor = "n9", "g", "s1", "C"
        x.send(ack_channel("B"), ack)
        x.send(NOTIFY_CHANNEL, notification("n2", "X", "Flush_1", "on_true", ""))  # as itself
        flush.wait_for(1)
        deadline = time.monotonic() + WAIT_S  # three channels: each has its own queue
        while b.stats["impostor"] < 3 and time.monotonic() < deadline:
            time.sleep(0.01)
    assert taken.calls == []
    assert b.stats["impostor"] == 3
    assert b.stats["handshakes_received"] == 0
    assert b.stats["acks_received"] == 0
    x.got.wait_for(1)
    assert [a.notification_id for a in x.acks()] == ["n2"]  # only its own notification
    lines = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    for kind in ("action_notification_t", "handshake_t", "action_ack_t"):
        assert any(
            f"a {kind}" in line and "sent by 'X' whose actor names 'C'" in line for line in lines
        ), lines


def test_what_was_never_started_here_is_forgotten_after_stray_s(fleet: Fleet) -> None:
    a = fleet.link("A")
    b = fleet.link("B", stray_s=0.2)
    a.notify("g", "s1", "Move_1", Result.TRUE, {}, ["B"], WAIT_S)  # kept by B for a while
    assert not threading.Event().wait(0.5)
    forgotten, flush = Got(), Got()
    b.expect("g", "s1", "Move_1", "A", forgotten)
    b.expect("g", "s1", "Flush_1", "A", flush)
    a.notify("g", "s1", "Flush_1", Result.TRUE, {}, ["B"], WAIT_S)
    flush.wait_for(1)
    assert forgotten.calls == []


def test_end_fails_a_waiting_notify(fleet: Fleet) -> None:
    (a,) = fleet.links("A")
    seen = Raw(fleet.fleet_link("X"), NOTIFY_CHANNEL)
    got = interrupted(
        lambda: a.notify("g", "s1", "Move_1", Result.TRUE, {}, ["C"], WAIT_S),
        seen.got,
        lambda: a.end("g", "s1"),
    )
    assert len(got) == 1
    assert isinstance(got[0], FleetError)
    assert "the run was ended before 'C' acknowledged" in str(got[0])


@pytest.mark.parametrize(
    ("graph", "session", "why"), [("g", "s1", "gave up the run"), ("", "", "left the fleet")]
)
def test_a_peer_that_leaves_fails_a_waiting_notify_at_once(
    fleet: Fleet, graph: str, session: str, why: str
) -> None:
    (a,) = fleet.links("A")
    c = Raw(fleet.fleet_link("C"), NOTIFY_CHANNEL)
    t0 = time.monotonic()
    got = interrupted(
        lambda: a.notify("g", "s1", "Move_1", Result.TRUE, {}, ["C", "D"], WAIT_S),
        c.got,
        lambda: c.send(HANDSHAKE_CHANNEL, handshake(3, "C", graph=graph, session=session)),
    )
    assert len(got) == 1
    assert isinstance(got[0], FleetError)
    assert f"'C' {why} before 'C', 'D' acknowledged" in str(got[0])
    assert time.monotonic() - t0 < WAIT_S / 2  # not the notify timeout


def test_a_leave_of_another_run_does_not_fail_a_notify(fleet: Fleet) -> None:
    (a,) = fleet.links("A")
    c = Raw(fleet.fleet_link("C"), NOTIFY_CHANNEL)
    got = interrupted(
        lambda: a.notify("g", "s1", "Move_1", Result.TRUE, {}, ["C"], 1.0),
        c.got,
        lambda: c.send(HANDSHAKE_CHANNEL, handshake(3, "C", graph="g", session="s2")),
    )
    assert len(got) == 1
    assert "was not acknowledged by 'C' within 1 s" in str(got[0])


def test_outputs_that_are_not_json_are_refused(fleet: Fleet) -> None:
    a, _ = fleet.links("A", "B")
    with pytest.raises(FleetError, match="not JSON-ready"):
        a.notify("g", "s1", "Move_1", Result.TRUE, {"x": object()}, ["B"], WAIT_S)
    a.notify("g", "s1", "Move_1", Result.TRUE, {}, ["A"], 0.0)  # nobody else: nothing to do


def test_a_bad_result_or_outputs_become_an_error_and_are_still_acknowledged(
    fleet: Fleet, caplog: pytest.LogCaptureFixture
) -> None:
    (b,) = fleet.links("B")
    raw = Raw(fleet.fleet_link("X"), ack_channel("X"))
    got = {name: Got() for name in ("unknown", "garbled", "array", "fine")}
    for name, got_it in got.items():
        b.expect("g", "s1", name, "X", got_it)
    raw.send(NOTIFY_CHANNEL, notification("n1", "X", "unknown", "on_maybe", '{"a": 1}'))
    raw.send(NOTIFY_CHANNEL, notification("n2", "X", "garbled", "on_true", "{not json"))
    raw.send(NOTIFY_CHANNEL, notification("n3", "X", "array", "on_true", "[1, 2]"))
    raw.send(NOTIFY_CHANNEL, notification("n4", "X", "fine", "on_false", ""))
    assert got["unknown"].wait_for(1) == [(Result.ERROR, {"a": 1})]
    assert got["garbled"].wait_for(1) == [(Result.ERROR, {})]
    assert got["array"].wait_for(1) == [(Result.ERROR, {})]
    assert got["fine"].wait_for(1) == [(Result.FALSE, {})]
    raw.got.wait_for(4)
    acks = raw.acks()
    assert sorted(ack.notification_id for ack in acks) == ["n1", "n2", "n3", "n4"]
    assert {(ack.actor, ack.graph, ack.session) for ack in acks} == {("B", "g", "s1")}
    assert "unknown result 'on_maybe'" in caplog.text
    assert "not JSON" in caplog.text


def test_undecodable_and_unexpected_messages_are_counted_not_raised(fleet: Fleet) -> None:
    (b,) = fleet.links("B")
    raw = Raw(fleet.fleet_link("X"), ack_channel("X"))
    raw.link.send(NOTIFY_CHANNEL, "action_notification_t", b"\x00garbage")
    raw.link.send(HANDSHAKE_CHANNEL, "handshake_t", b"\x01garbage")
    raw.link.send(HANDSHAKE_CHANNEL, "no_such_t", b"")
    raw.send(HANDSHAKE_CHANNEL, notification("n0", "X", "Move_1", "on_true", ""))  # wrong channel
    bad_phase = handshake(7, "X")
    raw.send(HANDSHAKE_CHANNEL, bad_phase)
    stray_ack = action_ack_t()
    stray_ack.notification_id, stray_ack.actor = "n9", "X"
    stray_ack.graph, stray_ack.session = "g", "s1"
    raw.send(NOTIFY_CHANNEL, stray_ack)  # acknowledgements have their own channels now
    raw.send(NOTIFY_CHANNEL, notification("n1", "X", "Move_1", "on_true", ""))
    raw.got.wait_for(1)  # its ack: everything before it was handled (one dispatch thread)
    stats = b.stats
    assert stats["decode_errors"] == 3
    assert stats["unexpected"] == 3
    assert stats["notifications_received"] == 1


def test_a_raising_callback_is_counted_and_the_link_goes_on(fleet: Fleet) -> None:
    a, b = fleet.links("A", "B")

    def boom(result: Result, outputs: Mapping[str, Any]) -> None:
        raise RuntimeError("callback failed")

    got = Got()
    b.expect("g", "s1", "Move_1", "A", boom)
    b.expect("g", "s1", "Move_2", "A", got)
    a.notify("g", "s1", "Move_1", Result.TRUE, {}, ["B"], WAIT_S)
    a.notify("g", "s1", "Move_2", Result.TRUE, {}, ["B"], WAIT_S)
    got.wait_for(1)
    assert b.stats["callback_errors"] == 1


# --- liveness ---------------------------------------------------------------------------------


def test_an_actor_whose_link_closes_during_a_run_is_lost_at_once(fleet: Fleet) -> None:
    a, b = fleet.links("A", "B", silence_s=3.0)
    assert concurrently(handshaking(a, ["A", "B"]), handshaking(b, ["A", "B"])) == [None] * 2
    lost = Got()
    a.watch(["B"], lost)
    t0 = time.monotonic()
    b.close()
    assert lost.wait_for(1) == [("B", "left")]
    assert time.monotonic() - t0 < 2.0  # the LEAVE, not the 3 s of silence
    assert lost.threads == [CALLS_THREAD]
    assert a.stats["lost"] == 1


def test_an_actor_that_gives_up_its_run_is_lost_at_once(fleet: Fleet) -> None:
    a, b = fleet.links("A", "B", silence_s=3.0)
    assert concurrently(handshaking(a, ["A", "B"]), handshaking(b, ["A", "B"])) == [None] * 2
    lost = Got()
    a.watch(["B"], lost)
    t0 = time.monotonic()
    b.end("g", "s1", gave_up=True)  # stopped or failed there: LEAVE
    assert lost.wait_for(1) == [("B", "left")]
    assert time.monotonic() - t0 < 2.0


def test_an_actor_that_ends_its_run_normally_is_not_lost(fleet: Fleet) -> None:
    a, b = fleet.links("A", "B", silence_s=0.5)
    assert concurrently(handshaking(a, ["A", "B"]), handshaking(b, ["A", "B"])) == [None] * 2
    lost = Got()
    a.watch(["B"], lost)
    b.end("g", "s1")  # finished: heartbeats go on for grace_s, no LEAVE
    with pytest.raises(AssertionError):
        lost.wait_for(1, timeout=1.0)


def test_a_peer_that_finished_the_run_may_go_quiet(fleet: Fleet) -> None:
    a = fleet.link("A", silence_s=0.3)
    with ExitStack() as b_stack:
        b = b_stack.enter_context(FleetActorLink(fleet.fleet_link("B"), "B", linger_s=0))
        assert concurrently(handshaking(a, ["A", "B"]), handshaking(b, ["A", "B"])) == [None] * 2
        lost = Got()
        a.watch(["B"], lost, graph="g", session="s1")
        other = Got()
        a.watch(["B"], other)  # not for the run: B is still missed when it goes quiet
        b.end("g", "s1")  # finished there: END
    # B's link is closed now (silent); A does not miss it for the run it finished
    assert other.wait_for(1) == [("B", "not heard for 0.3 s")]
    assert lost.calls == []


def test_end_of_a_peer_releases_a_notification_waiting_for_it(fleet: Fleet) -> None:
    a, b = fleet.links("A", "B")
    assert concurrently(handshaking(a, ["A", "B"]), handshaking(b, ["A", "B"])) == [None] * 2
    seen = Raw(fleet.fleet_link("X"), NOTIFY_CHANNEL)
    c = Raw(fleet.fleet_link("C"))  # C's END comes from C (a member speaks only as itself)
    got = interrupted(
        lambda: a.notify("g", "s1", "Move_1", Result.TRUE, {}, ["B", "C"], WAIT_S),
        seen.got,
        lambda: (b.end("g", "s1"), c.send(HANDSHAKE_CHANNEL, handshake(4, "C"))),
    )
    assert got == []  # returned: B acknowledged or finished, C finished
    assert a.notify("g", "s1", "Move_2", Result.TRUE, {}, ["C"], WAIT_S) is None  # not waited


def test_notify_fails_at_once_for_a_peer_known_to_be_silent(fleet: Fleet) -> None:
    a, b = fleet.links("A", "B", silence_s=0.3)
    assert concurrently(handshaking(a, ["A", "B"]), handshaking(b, ["A", "B"])) == [None] * 2
    lost = Got()
    a.watch(["B"], lost)
    b.close()  # LEAVE, then silent
    lost.wait_for(1)
    t0 = time.monotonic()
    with pytest.raises(FleetError, match="actor 'B' was lost"):
        a.notify("g", "s1", "Move_1", Result.TRUE, {}, ["B"], WAIT_S)
    assert time.monotonic() - t0 < 2.0  # the message is the at-once path's; this bounds it


def test_a_notification_waiting_for_a_peer_that_falls_silent_fails_after_silence_s(
    fleet: Fleet,
) -> None:
    a = fleet.link("A", silence_s=0.4)
    c = Raw(fleet.fleet_link("C"), NOTIFY_CHANNEL)
    c.send(HANDSHAKE_CHANNEL, handshake(2, "C"))  # heard once, then never again
    t0 = time.monotonic()
    with pytest.raises(FleetError, match=r"'C' was not heard for 0\.4 s"):
        a.notify("g", "s1", "Move_1", Result.TRUE, {}, ["C"], WAIT_S)
    assert time.monotonic() - t0 < WAIT_S / 2


def test_close_repeats_end_for_a_run_that_just_finished(fleet: Fleet) -> None:
    a, b = fleet.links("A", "B")
    assert concurrently(handshaking(a, ["A", "B"]), handshaking(b, ["A", "B"])) == [None] * 2
    watcher = Raw(fleet.fleet_link("X"), HANDSHAKE_CHANNEL)
    b.end("g", "s1")
    t0 = time.monotonic()
    b.close()
    assert 0.25 <= time.monotonic() - t0 < 2.0  # lingered for linger_s
    ends = [m for m in watcher.decoded() if m.phase == 4 and m.actor == "B"]
    assert len(ends) >= 2  # at end, and again while closing


def test_close_lingers_while_a_peer_still_resends_a_notification_of_the_ended_run(
    fleet: Fleet,
) -> None:
    """Our acknowledgement (and END) did not reach it: over a lossy TCP link they can be held
    up for seconds, and exiting took them along (test_zenoh_netns.py's 25 % loss run)."""
    a, b = fleet.links("A", "B")
    assert concurrently(handshaking(a, ["A", "B"]), handshaking(b, ["A", "B"])) == [None] * 2
    b.close()
    a.end("g", "s1", result=Result.TRUE)
    peer = fleet.fleet_link("B")  # B, still resending its notification of the run
    assert peer.wait_for_peers(["A"], WAIT_S)
    closing = threading.Thread(target=a.close, name="test-close")
    closing.start()
    msg = notification("B/g/s1/Move_1/1", "B", "Move_1", "on_true", "")
    for _ in range(15):  # 1.5 s: past linger_s, resent 10 times as often as it must be
        peer.send(NOTIFY_CHANNEL, *codec.encode(msg))
        closing.join(0.1)
    assert closing.is_alive(), "close() returned while a peer still waited for its answer"
    closing.join(WAIT_S)  # the resends stopped (it got its answer): close returns
    assert not closing.is_alive()


def test_close_lingers_while_a_peer_still_runs_the_ended_run(fleet: Fleet) -> None:
    """Its heartbeats of the run say that our END has not reached it (every copy lost): closing
    waits, answering each with END, until it goes quiet, so it ends with our result instead
    of finding us lost after silence_s (the shared-run property, bounds in docs/fleet.md)."""
    a, b = fleet.links("A", "B")
    ids: list[str] = []
    assert (
        concurrently(
            lambda: ids.append(a.handshake("g", "s1", ["A", "B"], WAIT_S)),
            handshaking(b, ["A", "B"]),
        )
        == [None] * 2
    )
    b.close()
    a.end("g", ids[0], result=Result.TRUE)
    peer = fleet.fleet_link("B")  # B, still in the run: it sends its heartbeats of it
    assert peer.wait_for_peers(["A"], WAIT_S)
    heartbeat = handshake(2, "B")
    heartbeat.run_id = ids[0]  # a heartbeat of that run (not of a new one of its session)
    closing = threading.Thread(target=a.close, name="test-close")
    closing.start()
    for _ in range(15):  # 1.5 s: past linger_s, a heartbeat every 0.1 s
        peer.send(HANDSHAKE_CHANNEL, *codec.encode(heartbeat))
        closing.join(0.1)
    assert closing.is_alive(), "close() returned while a peer still ran the ended run"
    closing.join(WAIT_S)  # the heartbeats stopped (it heard END): close returns
    assert not closing.is_alive()


def test_an_actor_that_falls_silent_is_lost_within_silence_s(fleet: Fleet) -> None:
    a, b = fleet.links("A", "B", silence_s=0.3)
    lost = Got()
    a.watch(["B"], lost)
    b.watch(["A"], Got())  # B is alive: it sends heartbeats while it watches
    assert not threading.Event().wait(0.8)
    assert lost.calls == []
    t0 = time.monotonic()
    b.close()  # no run is active: it just falls silent
    assert lost.wait_for(1, timeout=2.0) == [("B", "not heard for 0.3 s")]
    assert time.monotonic() - t0 < 1.5


def test_heartbeats_go_on_while_a_run_is_active_and_stop_after_end(fleet: Fleet) -> None:
    # heartbeats every 0.2 s (a third of the silence): generous for a loaded machine
    a, b = fleet.links("A", "B", silence_s=0.6, grace_s=0.0)
    assert concurrently(handshaking(a, ["A", "B"]), handshaking(b, ["A", "B"])) == [None] * 2
    lost = Got()
    a.watch(["B"], lost)  # B watches nothing: only its running run keeps it heard
    assert not threading.Event().wait(1.5)
    assert lost.calls == []
    b.end("g", "s1")  # nothing active on B any more (no grace): its heartbeats stop
    assert lost.wait_for(1, timeout=3.0) == [("B", "not heard for 0.6 s")]


def test_an_actor_never_heard_is_lost_after_silence_s(fleet: Fleet) -> None:
    (a,) = fleet.links("A", silence_s=0.2)
    lost = Got()
    t0 = time.monotonic()
    a.watch(["A", "Ghost"], lost)  # this actor itself is never watched
    assert lost.wait_for(1) == [("Ghost", "not heard for 0.2 s")]
    assert time.monotonic() - t0 >= 0.2
    assert not threading.Event().wait(0.3)
    assert lost.calls == [("Ghost", "not heard for 0.2 s")]  # once


def test_silences_are_measured_on_the_injected_clock(fleet: Fleet) -> None:
    clock = ManualClock()
    (a,) = fleet.links("A", silence_s=0.2, clock=clock)
    lost = Got()
    a.watch(["Ghost"], lost)
    assert lost.quiet_for(1, 0.6)  # three silences of real time: the clock has not moved
    clock.advance(0.19)
    assert lost.quiet_for(1, 0.1)
    clock.advance(0.01)  # wakes the timer, which waits on the clock
    assert lost.wait_for(1) == [("Ghost", "not heard for 0.2 s")]


def test_a_handshake_times_out_on_the_injected_clock(fleet: Fleet) -> None:
    clock = ManualClock()
    (a,) = fleet.links("A", clock=clock)
    errors: list[BaseException] = []

    def shake() -> None:
        try:
            a.handshake("g", "s", ["A", "Ghost"], timeout=60.0)
        except BaseException as err:
            errors.append(err)

    thread = threading.Thread(target=shake, name="test-handshake")
    thread.start()
    for _ in range(200):  # a minute of clock time per step, until the call gave up
        clock.advance(60.0)
        thread.join(0.05)
        if not thread.is_alive():
            break
    assert not thread.is_alive()
    assert len(errors) == 1
    assert isinstance(errors[0], FleetError)
    assert "timed out after 60 s" in str(errors[0])


def test_close_lingers_in_real_time_on_a_manual_clock(fleet: Fleet) -> None:
    a = fleet.link("A", clock=ManualClock())
    b = fleet.link("B")
    assert concurrently(handshaking(a, ["A", "B"]), handshaking(b, ["A", "B"])) == [None] * 2
    a.end("g", "s1")  # a run that just finished: close() repeats its END for linger_s
    closing = threading.Thread(target=a.close, name="test-close")
    t0 = time.monotonic()
    closing.start()
    closing.join(WAIT_S)  # the virtual clock never moves: close must not wait for it
    assert not closing.is_alive()
    assert time.monotonic() - t0 >= 0.25


def test_a_plain_function_is_refused_as_a_clock(fleet: Fleet) -> None:
    with pytest.raises(TypeError, match=r"temoto\.clock\.Clock.*MonotonicClock"):
        FleetActorLink(fleet.fleet_link("A"), "A", clock=time.monotonic)  # type: ignore[arg-type]


def test_a_leave_of_the_fleet_is_lost_at_once(fleet: Fleet) -> None:
    (a,) = fleet.links("A", silence_s=3.0)
    raw = Raw(fleet.fleet_link("X"), HANDSHAKE_CHANNEL)
    lost = Got()
    a.watch(["X"], lost)
    raw.send(HANDSHAKE_CHANNEL, handshake(3, "X", graph="", session=""))
    assert lost.wait_for(1) == [("X", "left")]
    late = Got()
    a.watch(["X"], late)  # it left and was not heard since
    assert late.wait_for(1) == [("X", "left")]


def test_cancel_stops_reporting(fleet: Fleet) -> None:
    (a,) = fleet.links("A", silence_s=0.2)
    lost, other = Got(), Got()
    cancel = a.watch(["Ghost"], lost)
    a.watch(["Ghost"], other)
    cancel()
    cancel()  # idempotent
    other.wait_for(1)
    assert not threading.Event().wait(0.2)
    assert lost.calls == []


# --- lifecycle --------------------------------------------------------------------------------


def test_close_fails_waiting_calls_and_later_ones(fleet: Fleet) -> None:
    (a,) = fleet.links("A")
    seen = Raw(fleet.fleet_link("X"), HANDSHAKE_CHANNEL)

    def close_twice() -> None:
        a.close()
        a.close()  # idempotent

    got = interrupted(lambda: a.handshake("g", "s1", ["A", "C"], WAIT_S), seen.got, close_twice)
    assert [str(e) for e in got] == ["the fleet link is closed"]
    with pytest.raises(FleetError, match="closed"):
        a.notify("g", "s1", "Move_1", Result.TRUE, {}, ["B"], 1.0)
    with pytest.raises(FleetError, match="closed"):
        a.expect("g", "s1", "Move_1", "B", Got())
    with pytest.raises(FleetError, match="closed"):
        a.watch(["B"], Got())
    a.end("g", "s1")  # harmless
    assert not [t for t in threading.enumerate() if t.name.startswith("temoto-fleet-actors")]


def test_link_properties_and_arguments(fleet: Fleet) -> None:
    link = fleet.fleet_link("A")
    with pytest.raises(ValueError, match="actor"):
        FleetActorLink(link, "")
    with pytest.raises(ValueError, match="resend_s"):
        FleetActorLink(link, "A", resend_s=0)
    with pytest.raises(ValueError, match="silence_s"):
        FleetActorLink(link, "A", silence_s=float("nan"))
    with FleetActorLink(link, "A", resend_s=0.1, silence_s=0.6) as a:
        assert a.actor == "A"
        assert a.heartbeat_s == pytest.approx(0.2)
        assert set(a.stats) == set(STATS)
        assert "FleetActorLink actor='A' open" in repr(a)
        names = {t.name for t in threading.enumerate()}
        assert {"temoto-fleet-actors", CALLS_THREAD} <= names
    assert "closed" in repr(a)


def test_the_links_parts_hold_one_state_by_reference(fleet: Fleet) -> None:
    # The handshake, the notifications and the supervision share the link's one state: none
    # keeps its own alias of a table, a condition or the lock (an alias goes stale the day
    # the state rebinds one, and hides what a part reads).
    with fleet.link("A") as a:
        state = a._st
        shared = {id(v): k for k, v in vars(state).items() if not isinstance(v, int | float | str)}
        for part in (a, a._handshakes, a._notices, a._supervisor):
            aliases = sorted(k for k, v in vars(part).items() if id(v) in shared)
            assert not aliases, f"{type(part).__name__} copies {aliases} of the link's state"
            assert part is a or part._st is state


def test_messages_are_what_the_lcm_definitions_say(fleet: Fleet) -> None:
    a, b = fleet.links("A", "B")
    raw_hs = Raw(fleet.fleet_link("X"), HANDSHAKE_CHANNEL)
    raw_nt = Raw(fleet.fleet_link("Y"), NOTIFY_CHANNEL, ack_channel("A"))
    assert concurrently(handshaking(a, ["A", "B"]), handshaking(b, ["A", "B"])) == [None] * 2
    a.notify("g", "s1", "Move_1", Result.TRUE, {"b": 2, "a": 1}, ["B"], WAIT_S)
    raw_nt.got.wait_for(2)
    notes = [codec.decode(o.type, o.payload) for (o,) in raw_nt.got.calls]
    note = next(n for n in notes if n.__class__.__name__ == "action_notification_t")
    assert note.notification_id.startswith("A/g/s1/Move_1/")
    assert (note.graph, note.session, note.action, note.actor) == ("g", "s1", "Move_1", "A")
    assert note.result == "on_true"
    assert json.loads(note.outputs) == {"a": 1, "b": 2}
    assert note.outputs == '{"a":1,"b":2}'  # sorted keys
    ack = next(n for n in notes if isinstance(n, action_ack_t))
    assert (ack.notification_id, ack.actor) == (note.notification_id, "B")

    def decoded(calls: list[tuple[Any, ...]]) -> list[Any]:
        return [codec.decode(o.type, o.payload) for (o,) in calls]

    def a_ready(calls: list[tuple[Any, ...]]) -> bool:  # heartbeats come on their own time
        return any(m.phase == handshake_t.READY and m.actor == "A" for m in decoded(calls))

    hs = decoded(raw_hs.got.wait_until(a_ready))
    joins = [m for m in hs if m.phase == handshake_t.JOIN and m.actor == "A"]
    readies = [m for m in hs if m.phase == handshake_t.READY and m.actor == "A" and m.heard]
    assert joins
    assert readies
    assert all(m.actors == '["A","B"]' for m in joins + readies)
    assert list(heard_of(readies[0])) == ["B"]
    assert all(len(m.heard) == 16 for m in joins + readies)  # a stamp per actor, by place


def test_an_acknowledgement_goes_to_the_notifying_actor_alone(fleet: Fleet) -> None:
    a, b = fleet.links("A", "B")
    fleetwide = Raw(fleet.fleet_link("Y"), NOTIFY_CHANNEL, ack_channel("B"))
    to_a = Raw(fleet.fleet_link("Z"), ack_channel("A"))
    a.notify("g", "s1", "Move_1", Result.TRUE, {}, ["B"], WAIT_S)
    (ack,) = to_a.got.wait_for(1)[0]
    assert (ack.channel, ack.type) == ("TEMOTO_ACK_A", "action_ack_t")
    assert b.stats["acks_sent"] == 1
    assert a.stats["acks_received"] == 1
    b.notify("g", "s1", "Move_2", Result.TRUE, {}, ["A"], WAIT_S)  # after A's ack, if it came
    types = {(o.channel, o.type) for (o,) in fleetwide.got.wait_for(3)}
    assert types == {  # no acknowledgement on the fleet-wide channel
        ("TEMOTO_ACK_B", "action_ack_t"),
        ("TEMOTO_NOTIFY", "action_notification_t"),
    }


def test_ack_channel_names_a_plain_actor_and_hashes_any_other() -> None:
    assert ack_channel("robot_1") == "TEMOTO_ACK_robot_1"
    assert ack_channel("arm-2.left:x") == "TEMOTO_ACK_arm-2.left:x"
    odd, long = ack_channel("robot #1"), ack_channel("r" * 41)
    for channel in (odd, long):
        assert channel.startswith(ACK_CHANNEL_PREFIX)
        assert len(channel) == len(ACK_CHANNEL_PREFIX) + 16
        int(channel[len(ACK_CHANNEL_PREFIX) :], 16)
    assert odd != long
    assert ack_channel("robot #1") == odd  # the same on every actor
    with pytest.raises(ValueError, match="actor must be a non-empty string"):
        ack_channel("")


def test_a_ready_without_heard_list_leaves_the_peers_report_standing(fleet: Fleet) -> None:
    (a,) = fleet.links("A")
    x = Raw(fleet.fleet_link("X"), HANDSHAKE_CHANNEL)
    y = Raw(fleet.fleet_link("Y"), HANDSHAKE_CHANNEL)
    done: list[BaseException | None] = []
    thread = threading.Thread(
        target=lambda: done.extend(concurrently(handshaking(a, ["A", "X", "Y"]))), daemon=True
    )
    thread.start()

    def joins_of_a(calls: list[tuple[Any, ...]]) -> list[Any]:
        msgs = [codec.decode(o.type, o.payload) for (o,) in calls]
        return [m for m in msgs if m.actor == "A" and m.phase == handshake_t.JOIN]

    join = joins_of_a(x.got.wait_until(lambda calls: bool(joins_of_a(calls))))[0]

    def report(actor: str, phase: int, heard: dict[str, int]) -> Any:
        return set_heard(handshake(phase, actor), ["A", "X", "Y"], heard)

    x_join = report("X", handshake_t.JOIN, {"A": join.stamp_us, "Y": 1})
    x.send(HANDSHAKE_CHANNEL, x_join)
    heartbeat = handshake(handshake_t.READY, "X")  # newer, but says nothing of the handshake
    heartbeat.stamp_us = x_join.stamp_us + 1
    x.send(HANDSHAKE_CHANNEL, heartbeat)
    y.send(HANDSHAKE_CHANNEL, report("Y", handshake_t.JOIN, {"A": join.stamp_us, "X": 1}))
    thread.join(WAIT_S + 5)
    assert done == [None]  # X's JOIN still says X heard A and Y


# --- the compact handshake (handshake_t version 2) --------------------------------------------


def test_a_peer_with_another_actor_list_is_read_by_its_own_list(
    fleet: Fleet, caplog: pytest.LogCaptureFixture
) -> None:
    """X's copy of the graph names a fourth actor: its stamps are read by its own list (the
    places differ from A's), the handshake completes as every pair of A's list is heard, and
    A warns with X's list."""
    (a,) = fleet.links("A")
    x = Raw(fleet.fleet_link("X"), HANDSHAKE_CHANNEL)
    y = Raw(fleet.fleet_link("Y"), HANDSHAKE_CHANNEL)
    done: list[BaseException | None] = []
    thread = threading.Thread(
        target=lambda: done.extend(concurrently(handshaking(a, ["A", "X", "Y"]))), daemon=True
    )
    thread.start()

    def joins_of_a(calls: list[tuple[Any, ...]]) -> list[Any]:
        msgs = [codec.decode(o.type, o.payload) for (o,) in calls]
        return [m for m in msgs if m.actor == "A" and m.phase == handshake_t.JOIN]

    join = joins_of_a(x.got.wait_until(lambda calls: bool(joins_of_a(calls))))[0]
    assert join.actors == '["A","X","Y"]'
    x_join = handshake(handshake_t.JOIN, "X")  # A at place 1 of X's list, not at place 0
    x.send(HANDSHAKE_CHANNEL, set_heard(x_join, ["0", "A", "X", "Y"], {"A": join.stamp_us, "Y": 1}))
    y_join = set_heard(handshake(handshake_t.JOIN, "Y"), ["A", "X", "Y"], {"A": join.stamp_us})
    y_join.heard = y_join.heard[:16] + struct.pack(">q", 0)  # Y has not heard X yet
    with caplog.at_level(logging.WARNING, logger="temoto.fleet"):
        y.send(HANDSHAKE_CHANNEL, y_join)
        thread.join(0.3)
        assert thread.is_alive()  # Y's report misses X: not done
        later = set_heard(handshake(handshake_t.JOIN, "Y"), ["A", "X", "Y"], {"A": 1, "X": 1})
        later.stamp_us = y_join.stamp_us + 1
        y.send(HANDSHAKE_CHANNEL, later)  # ... but A's stamp in it is not this call's
        thread.join(0.3)
        assert thread.is_alive()
        later.stamp_us += 1
        y.send(HANDSHAKE_CHANNEL, set_heard(later, ["A", "X", "Y"], {"A": join.stamp_us, "X": 1}))
        thread.join(WAIT_S + 5)
    assert done == [None]
    assert "'X' lists the actors ['0', 'A', 'X', 'Y'], this actor ['A', 'X', 'Y']" in caplog.text


def test_a_join_with_stamps_that_are_not_whole_is_dropped_and_counted(fleet: Fleet) -> None:
    (a,) = fleet.links("A")
    x = Raw(fleet.fleet_link("X"), HANDSHAKE_CHANNEL)
    bad = set_heard(handshake(handshake_t.JOIN, "X"), ["A", "X"], {"A": 1})
    bad.heard = bad.heard[:-1]
    x.send(HANDSHAKE_CHANNEL, bad)
    deadline = time.monotonic() + WAIT_S
    while a.stats["unexpected"] < 1 and time.monotonic() < deadline:
        time.sleep(0.005)
    assert a.stats["unexpected"] == 1
    with pytest.raises(FleetError, match="no answer from 'X'"):
        a.handshake("g", "s1", ["A", "X"], 0.2)  # the bad JOIN was not taken as X's report


def test_a_big_handshake_sends_its_joins_no_faster_than_the_fleet_budget(fleet: Fleet) -> None:
    """40 actors, resend_s 0.05: JOINs at most every 0.2 s (resend_s * 40 / 10) after the first
    three, however fast new peers arrive (every 10 ms here), so the fleet's JOINs per second
    do not grow with its size. (Without the budget: one answer per 0.05 s, about 14.)"""
    names = ["A", *(f"P{i:02d}" for i in range(39))]
    a = fleet.link("A", resend_s=0.05)
    peer = Raw(fleet.fleet_link("Peers"), HANDSHAKE_CHANNEL)
    done: list[BaseException | None] = []
    thread = threading.Thread(
        target=lambda: done.extend(concurrently(handshaking(a, names, 0.8))), daemon=True
    )
    thread.start()
    peer.got.wait_for(1)  # A's first JOIN
    for name in names[1:]:
        peer.send(HANDSHAKE_CHANNEL, set_heard(handshake(handshake_t.JOIN, name), names, {}))
        time.sleep(0.01)
    thread.join(WAIT_S + 5)
    assert len(done) == 1
    assert isinstance(done[0], FleetError)  # the peers never heard each other
    joins = [m for m in peer.decoded() if m.actor == "A" and m.phase == handshake_t.JOIN]
    assert 3 <= len(joins) <= 9, len(joins)
    assert all(len(j.heard) == 8 * 40 for j in joins)


def test_a_handshake_of_an_older_release_is_named_once(
    fleet: Fleet, caplog: pytest.LogCaptureFixture
) -> None:
    (a,) = fleet.links("A")
    old = Raw(fleet.fleet_link("Old-release-1"), HANDSHAKE_CHANNEL)
    _, payload = codec.encode(set_heard(handshake(handshake_t.JOIN, "Old"), ["A", "Old"], {}))
    v1 = bytes.fromhex("253b31dc311612e4") + (1).to_bytes(2, "big") + payload[10:]
    with caplog.at_level(logging.WARNING, logger="temoto.fleet"):
        for _ in range(3):
            old.link.send(HANDSHAKE_CHANNEL, "handshake_t", v1)
        deadline = time.monotonic() + WAIT_S
        while a.stats["decode_errors"] < 3 and time.monotonic() < deadline:
            time.sleep(0.005)
    assert a.stats["decode_errors"] == 3
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert warnings == [
        "dropping the messages of 'Old-release-1' on 'TEMOTO_HANDSHAKE': handshake_t: version 1"
        " is not supported (this build speaks version 2; the sender runs another release)"
        " (this warning once per sender)"
    ]
