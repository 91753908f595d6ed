"""LcmTransport on LCM's ``memq://`` provider, which delivers within one LCM instance only."""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterator

import pytest

from temoto.errors import TransportError
from temoto.testing.inbox import Inbox
from temoto.transport import FleetAuth, FleetLink, LcmTransport, Opened, open_transport
from temoto.transport.lcm import LcmSubscription

WAIT_S = 5.0


def flush(t: LcmTransport) -> None:
    """Wait until messages published before this call have been dispatched (memq is FIFO)."""
    inbox = Inbox()
    sub = t.subscribe("FLUSH", inbox)
    t.publish("FLUSH", b"")
    inbox.wait_for(1)
    sub.unsubscribe()


@pytest.fixture
def memq() -> Iterator[LcmTransport]:
    with LcmTransport("memq://") as t:
        yield t


def test_publish_and_subscribe_round_trip_on_the_receive_thread(memq: LcmTransport) -> None:
    inbox = Inbox()
    memq.subscribe("ROUND_TRIP", inbox)
    memq.publish("ROUND_TRIP", b"\x00payload\xff")
    memq.publish("ROUND_TRIP", memoryview(b"second"))  # type: ignore[arg-type]
    items = inbox.wait_for(2)
    assert [(c, d) for c, d, _ in items] == [
        ("ROUND_TRIP", b"\x00payload\xff"),
        ("ROUND_TRIP", b"second"),
    ]
    assert {name for _, _, name in items} == {"temoto-lcm"}


def test_channels_are_matched_exactly_not_as_patterns(memq: LcmTransport) -> None:
    inbox = Inbox()
    memq.subscribe("A.B", inbox)
    memq.publish("AxB", b"lcm's regex would match this")
    memq.publish("A.B", b"exact")
    flush(memq)
    assert inbox.data == [b"exact"]


def test_unsubscribe_stops_delivery(memq: LcmTransport) -> None:
    inbox, other = Inbox(), Inbox()
    sub = memq.subscribe("CHAT", inbox)
    memq.subscribe("CHAT", other)
    memq.publish("CHAT", b"1")
    inbox.wait_for(1)
    sub.unsubscribe()
    sub.unsubscribe()
    memq.publish("CHAT", b"2")
    other.wait_for(2)
    flush(memq)
    assert inbox.data == [b"1"]
    assert isinstance(sub, LcmSubscription)
    assert sub._lcm_sub is None  # removed from LCM by the receive thread


def test_a_raising_handler_is_counted_and_the_thread_survives(
    memq: LcmTransport, caplog: pytest.LogCaptureFixture
) -> None:
    def broken(channel: str, data: bytes) -> None:
        raise ValueError("bad message")

    bad = memq.subscribe("CHAT", broken)
    inbox = Inbox()
    memq.subscribe("CHAT", inbox)
    with caplog.at_level(logging.ERROR, logger="temoto.transport"):
        memq.publish("CHAT", b"1")
        memq.publish("CHAT", b"2")
        inbox.wait_for(2)
    assert memq.handler_errors == bad.handler_errors == 2
    assert memq._thread.is_alive()
    assert "bad message" in caplog.text


def test_queue_capacity_is_given_to_the_lcm_subscription(memq: LcmTransport) -> None:
    # LCM enforces it in its network providers; memq:// queues without a limit, so this test
    # only checks that the capacity was set and messages still flow.
    inbox = Inbox()
    sub = memq.subscribe("BUSY", inbox, queue_capacity=2)
    assert isinstance(sub, LcmSubscription)
    assert sub.queue_capacity == 2
    assert sub._lcm_sub is not None
    for i in range(5):
        memq.publish("BUSY", str(i).encode())
    inbox.wait_for(5)


def test_close_joins_the_receive_thread_and_refuses_more_work() -> None:
    t = LcmTransport("memq://")
    thread = t._thread
    assert thread.name == "temoto-lcm"
    sub = t.subscribe("CHAT", Inbox())
    t.close()
    assert not thread.is_alive()
    assert not sub.active
    assert t._lcm is None
    t.close()
    with pytest.raises(TransportError, match="closed"):
        t.publish("CHAT", b"x")
    with pytest.raises(TransportError, match="closed"):
        t.subscribe("CHAT", Inbox())
    sub.unsubscribe()  # after close: harmless
    assert repr(t) == "<LcmTransport 'memq://' closed>"


def test_close_from_a_handler_ends_the_thread() -> None:
    t = LcmTransport("memq://")
    done = threading.Event()

    def closer(channel: str, data: bytes) -> None:
        t.close()
        done.set()

    t.subscribe("CLOSE", closer)
    t.publish("CLOSE", b"")
    assert done.wait(WAIT_S)
    t._thread.join(WAIT_S)
    assert not t._thread.is_alive()


def test_an_unknown_provider_is_a_transport_error() -> None:
    with pytest.raises(TransportError, match="nosuch://"):
        LcmTransport("nosuch://")


def test_a_bad_timeout_is_refused() -> None:
    with pytest.raises(ValueError, match="handle_timeout_s"):
        LcmTransport("memq://", handle_timeout_s=0)


def test_open_transport_makes_an_lcm_transport_for_lcm_urls() -> None:
    with open_transport("memq://") as t:
        assert isinstance(t, LcmTransport)


def test_a_fleet_link_round_trip_over_lcm(memq: LcmTransport) -> None:
    # memq delivers our own messages back, as udpm multicast does: two members share it here.
    key = bytes(range(32))
    alpha = FleetLink(memq, FleetAuth("fleet", "alpha", key))
    beta = FleetLink(memq, FleetAuth("fleet", "beta", key))
    got: list[Opened] = []
    done = threading.Event()

    def on_beta(opened: Opened) -> None:
        got.append(opened)
        done.set()

    beta.listen("TEMOTO_NOTIFY", on_beta)
    alpha.listen("TEMOTO_NOTIFY", lambda opened: None)
    alpha.send("TEMOTO_NOTIFY", "action_ack_t", b"inner")
    assert done.wait(WAIT_S)
    flush(memq)
    assert [(o.sender, o.type, o.payload) for o in got] == [("alpha", "action_ack_t", b"inner")]
    assert alpha.stats["self"] >= 1  # its notification echoed back (and its hellos)
    assert beta.stats["accepted"] == 1
