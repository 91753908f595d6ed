from __future__ import annotations

import logging
import threading
from collections.abc import Iterator

import pytest

from temoto.errors import TransportError
from temoto.testing.inbox import Inbox
from temoto.transport import InProcessTransport, Subscription, Transport, open_transport
from temoto.transport.inprocess import InProcessSubscription, live_buses

WAIT_S = 5.0


def flush(transport: InProcessTransport) -> None:
    """Wait until the transport's dispatcher has handled what was queued before this call."""
    assert transport.flush(WAIT_S)


@pytest.fixture
def bus(request: pytest.FixtureRequest) -> str:
    return f"test-{request.node.name}"


@pytest.fixture
def pair(bus: str) -> Iterator[tuple[InProcessTransport, InProcessTransport]]:
    with InProcessTransport(bus) as a, InProcessTransport(bus) as b:
        yield a, b
    assert bus not in live_buses()


def test_every_instance_on_the_bus_receives_including_the_sender(
    pair: tuple[InProcessTransport, InProcessTransport],
) -> None:
    a, b = pair
    inbox_a, inbox_b = Inbox(), Inbox()
    a.subscribe("CHAT", inbox_a)
    b.subscribe("CHAT", inbox_b)
    a.publish("CHAT", b"hello")
    b.publish("CHAT", bytearray(b"world"))  # type: ignore[arg-type]
    for inbox in (inbox_a, inbox_b):
        items = inbox.wait_for(2)
        assert sorted(d for _, d, _ in items) == [b"hello", b"world"]
        assert {c for c, _, _ in items} == {"CHAT"}
        assert all(isinstance(d, bytes) for _, d, _ in items)


def test_handlers_run_on_the_receivers_dispatch_thread_not_the_publishers(
    pair: tuple[InProcessTransport, InProcessTransport], bus: str
) -> None:
    a, b = pair
    inbox_a, inbox_b = Inbox(), Inbox()
    a.subscribe("CHAT", inbox_a)
    b.subscribe("CHAT", inbox_b)
    a.publish("CHAT", b"x")
    ((_, _, thread_a),) = inbox_a.wait_for(1)
    ((_, _, thread_b),) = inbox_b.wait_for(1)
    assert thread_a == thread_b == f"temoto-inproc-{bus}"
    assert threading.current_thread().name != thread_a
    assert a._thread is not b._thread


def test_buses_with_different_names_are_isolated(bus: str) -> None:
    with InProcessTransport(bus + "-1") as one, InProcessTransport(bus + "-2") as two:
        inbox_one, inbox_two = Inbox(), Inbox()
        one.subscribe("CHAT", inbox_one)
        two.subscribe("CHAT", inbox_two)
        one.publish("CHAT", b"for one")
        inbox_one.wait_for(1)
        flush(two)
        assert inbox_two.data == []
        assert live_buses()[bus + "-1"] == 1


def test_channels_are_isolated_and_matched_exactly(
    pair: tuple[InProcessTransport, InProcessTransport],
) -> None:
    a, b = pair
    inbox = Inbox()
    b.subscribe("A.B", inbox)
    a.publish("AxB", b"not a pattern")
    a.publish("A.B/C", b"not a prefix")
    a.publish("A.B", b"exact")
    assert inbox.wait_for(1)[0][1] == b"exact"
    flush(b)
    assert inbox.data == [b"exact"]


def test_messages_of_one_publisher_arrive_in_order(
    pair: tuple[InProcessTransport, InProcessTransport],
) -> None:
    a, b = pair
    inbox = Inbox()
    b.subscribe("SEQ", inbox)
    for i in range(200):
        a.publish("SEQ", i.to_bytes(2, "big"))
    inbox.wait_for(200)
    assert [int.from_bytes(d, "big") for d in inbox.data] == list(range(200))


def test_unsubscribe_stops_delivery_and_is_idempotent(
    pair: tuple[InProcessTransport, InProcessTransport],
) -> None:
    a, b = pair
    inbox, other = Inbox(), Inbox()
    sub = b.subscribe("CHAT", inbox)
    b.subscribe("CHAT", other)
    a.publish("CHAT", b"1")
    inbox.wait_for(1)
    sub.unsubscribe()
    sub.unsubscribe()
    assert not sub.active
    a.publish("CHAT", b"2")
    other.wait_for(2)
    flush(b)
    assert inbox.data == [b"1"]
    assert repr(sub) == "<InProcessSubscription 'CHAT' unsubscribed>"


def test_a_handler_may_unsubscribe_itself(
    pair: tuple[InProcessTransport, InProcessTransport],
) -> None:
    a, b = pair
    seen: list[bytes] = []
    done = threading.Event()
    subs: list[Subscription] = []

    def once(channel: str, data: bytes) -> None:
        seen.append(data)
        subs[0].unsubscribe()
        done.set()

    subs.append(b.subscribe("ONCE", once))
    a.publish("ONCE", b"1")
    a.publish("ONCE", b"2")
    assert done.wait(WAIT_S)
    flush(b)
    assert seen == [b"1"]


def test_a_raising_handler_is_logged_and_counted_and_the_thread_survives(
    pair: tuple[InProcessTransport, InProcessTransport], caplog: pytest.LogCaptureFixture
) -> None:
    a, b = pair
    inbox = Inbox()

    def broken(channel: str, data: bytes) -> None:
        raise RuntimeError(f"cannot handle {data!r}")

    bad = b.subscribe("CHAT", broken)
    b.subscribe("CHAT", inbox)
    with caplog.at_level(logging.ERROR, logger="temoto.transport"):
        for i in range(3):
            a.publish("CHAT", bytes([i]))
        inbox.wait_for(3)
    assert b.handler_errors == 3
    assert bad.handler_errors == 3
    assert a.handler_errors == 0
    assert b._thread.is_alive()
    # Rate-limited: the first raise is logged with its traceback, the next ones of the same
    # second are only counted.
    records = [r for r in caplog.records if "raised" in r.getMessage()]
    assert len(records) == 1
    assert records[0].exc_info is not None
    assert "cannot handle" in caplog.text
    assert "'CHAT'" in records[0].getMessage()


def test_a_full_subscription_queue_drops_its_oldest_messages_and_counts_them(
    pair: tuple[InProcessTransport, InProcessTransport],
) -> None:
    a, b = pair
    gate = threading.Event()
    entered = threading.Event()
    blocked: list[bytes] = []

    def slow(channel: str, data: bytes) -> None:
        entered.set()
        assert gate.wait(WAIT_S)
        blocked.append(data)

    inbox = Inbox()
    bounded = b.subscribe("BUSY", slow, queue_capacity=3)
    unbounded = b.subscribe("BUSY", inbox)
    a.publish("BUSY", b"0")
    assert entered.wait(WAIT_S)  # the dispatcher is now stuck in slow(b"0")
    for i in range(1, 10):
        a.publish("BUSY", str(i).encode())
    assert isinstance(bounded, InProcessSubscription)
    assert isinstance(unbounded, InProcessSubscription)
    assert bounded.dropped == 6
    assert unbounded.dropped == 0
    gate.set()
    inbox.wait_for(10)
    flush(b)
    assert blocked == [b"0", b"7", b"8", b"9"]
    assert inbox.data == [str(i).encode() for i in range(10)]


def test_close_joins_the_dispatch_thread_and_leaves_the_bus(bus: str) -> None:
    t = InProcessTransport(bus)
    thread = t._thread
    assert thread.is_alive()
    assert thread.daemon
    assert live_buses()[bus] == 1
    t.close()
    assert not thread.is_alive()
    assert bus not in live_buses()
    t.close()  # idempotent
    assert t.closed
    assert repr(t) == f"<InProcessTransport bus={bus!r} closed>"


def test_a_closed_transport_refuses_work_and_receives_nothing(bus: str) -> None:
    with InProcessTransport(bus) as a:
        b = InProcessTransport(bus)
        inbox = Inbox()
        b.subscribe("CHAT", inbox)
        b.close()
        a.publish("CHAT", b"after close")
        with pytest.raises(TransportError, match="closed"):
            b.publish("CHAT", b"x")
        with pytest.raises(TransportError, match="closed"):
            b.subscribe("CHAT", inbox)
        assert inbox.data == []


def test_close_from_a_handler_does_not_deadlock(bus: str) -> None:
    t = InProcessTransport(bus)
    done = threading.Event()

    def closer(channel: str, data: bytes) -> None:
        t.close()
        done.set()

    t.subscribe("CLOSE", closer)
    t.publish("CLOSE", b"")
    assert done.wait(WAIT_S)
    t._thread.join(WAIT_S)
    assert not t._thread.is_alive()


@pytest.mark.parametrize("channel", ["", "has space", "star*", "x" * 64, "ümlaut"])
def test_bad_channel_names_are_refused(channel: str, bus: str) -> None:
    with InProcessTransport(bus) as t:
        with pytest.raises(ValueError, match="channel name"):
            t.publish(channel, b"")
        with pytest.raises(ValueError, match="channel name"):
            t.subscribe(channel, Inbox())


def test_bad_arguments_are_refused(bus: str) -> None:
    with pytest.raises(ValueError, match="bus name"):
        InProcessTransport("")
    with InProcessTransport(bus) as t:
        with pytest.raises(TypeError, match="bytes"):
            t.publish("CHAT", "text")  # type: ignore[arg-type]
        with pytest.raises(TypeError, match="callable"):
            t.subscribe("CHAT", None)  # type: ignore[arg-type]
        for capacity in (0, -1, True, 1.5):
            with pytest.raises(ValueError, match="queue_capacity"):
                t.subscribe("CHAT", Inbox(), queue_capacity=capacity)  # type: ignore[arg-type]


def test_open_transport_makes_an_in_process_transport_from_its_url(bus: str) -> None:
    with open_transport(f"inproc://{bus}") as t:
        assert isinstance(t, InProcessTransport)
        assert isinstance(t, Transport)
        assert t.bus == bus
    with open_transport("inproc://") as t:
        assert isinstance(t, InProcessTransport)
        assert t.bus == "default"


def test_flush_waits_for_the_handlers_of_what_was_published_before(bus: str) -> None:
    release = threading.Event()
    handled: list[bytes] = []

    def slow(channel: str, data: bytes) -> None:
        release.wait(WAIT_S)
        handled.append(data)

    with InProcessTransport(bus) as rx, InProcessTransport(bus) as tx:
        rx.subscribe("SLOW", slow)
        tx.publish("SLOW", b"1")
        tx.publish("SLOW", b"2")
        assert not rx.flush(0.05)  # the first handler is still blocked
        release.set()
        assert rx.flush(WAIT_S)
        assert handled == [b"1", b"2"]
    assert not rx.flush(0.01)  # closed
