"""ZenohTransport: clients of an in-process router (and peers) on loopback TCP.

Every test uses a fleet prefix of its own (``?prefix=``), so tests running at the same time on
this machine cannot hear each other, and free ports picked by the kernel.
"""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest

from temoto.errors import TransportError
from temoto.testing.inbox import Inbox
from temoto.transport import FleetAuth, FleetLink, Opened, ZenohTransport, open_transport
from temoto.transport import zenoh as zenoh_module
from temoto.transport.zenoh import (
    DEFAULT_PREFIX,
    ZenohSubscription,
    ZenohUrl,
    channel_key,
    open_router,
    parse_zenoh_url,
)

pytest.importorskip("zenoh", reason="the zenoh extra is not installed")

from _zenoh_helpers import WAIT_S, free_port, prefix, until_routed


@pytest.fixture
def router() -> Iterator[str]:
    """An in-process router on a free loopback port; yields a client URL for it."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    session = open_router((endpoint,))
    try:
        yield f"zenoh:{endpoint}?prefix={prefix()}"
    finally:
        session.close()


@pytest.fixture
def pair(router: str) -> Iterator[tuple[ZenohTransport, ZenohTransport]]:
    with ZenohTransport(router) as a, ZenohTransport(router) as b:
        yield a, b


# --- the URL ------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("url", "expected"),
    [
        ("zenoh:", ZenohUrl("peer", (), (), DEFAULT_PREFIX, None)),
        (
            "zenoh:tcp/10.0.0.1:7447",
            ZenohUrl("client", ("tcp/10.0.0.1:7447",), (), DEFAULT_PREFIX, None),
        ),
        (
            "zenoh:tcp/a:7447,udp/b:7447?mode=peer&listen=tcp/0.0.0.0:7448&prefix=site1/fleet",
            ZenohUrl(
                "peer", ("tcp/a:7447", "udp/b:7447"), ("tcp/0.0.0.0:7448",), "site1/fleet", None
            ),
        ),
        (
            "zenoh:tcp/[::1]:7447#iface=lo?timeout=0.5",
            ZenohUrl("client", ("tcp/[::1]:7447#iface=lo",), (), DEFAULT_PREFIX, None, 0.5),
        ),
        (
            "zenoh:/etc/temoto/zenoh.json5?prefix=x",
            ZenohUrl(None, (), (), "x", "/etc/temoto/zenoh.json5"),
        ),
    ],
)
def test_urls_parse_to_mode_endpoints_and_prefix(url: str, expected: ZenohUrl) -> None:
    assert parse_zenoh_url(url) == expected


@pytest.mark.parametrize(
    ("url", "blamed"),
    [
        ("zenoh:10.0.0.1:7447", "endpoint '10.0.0.1:7447'"),
        ("zenoh:tcp/a:1,", "endpoint ''"),
        ("zenoh:?mode=client", "a client needs the endpoint of a router"),
        ("zenoh:tcp/a:1?mode=router", "mode must be peer or client"),
        ("zenoh:tcp/a:1?ttl=1", "unknown parameter 'ttl=1'"),
        ("zenoh:tcp/a:1?prefix=a/*", "prefix 'a/*'"),
        ("zenoh:tcp/a:1?prefix=a&prefix=b", "prefix= given twice"),
        ("zenoh:?listen=7447", "listen '7447'"),
        ("zenoh:z.json5?mode=peer", "the file sets the mode"),
        ("zenoh:z.json5?timeout=1", "the file sets the timeout"),
        ("zenoh:tcp/a:1?timeout=-1", "timeout must be 0 to 3600 seconds, not '-1'"),
        ("zenoh:tcp/a:1?timeout=soon", "timeout must be 0 to 3600 seconds, not 'soon'"),
    ],
)
def test_malformed_urls_name_the_part_at_fault(url: str, blamed: str) -> None:
    with pytest.raises(ValueError, match="zenoh") as info:
        parse_zenoh_url(url)
    assert blamed in str(info.value)
    with pytest.raises(TransportError) as opened:
        open_transport(url)
    assert blamed in str(opened.value)


def test_open_transport_makes_a_zenoh_transport_from_a_zenoh_url(router: str) -> None:
    with open_transport(router) as t:
        assert isinstance(t, ZenohTransport)
        assert t.prefix == router.rsplit("=", 1)[1]
        assert "open" in repr(t)
    assert "closed" in repr(t)


def test_channels_map_one_to_one_onto_single_key_chunks() -> None:
    assert channel_key("temoto", "TEMOTO_NOTIFY") == "temoto/TEMOTO_NOTIFY"
    assert channel_key("a/b", "x/y") == "a/b/x~y"
    channels = ["a/b", "a~b", "/a", "a/", "a//b", "a.b:c-d_e"]
    keys = [channel_key("p", c) for c in channels if "~" not in c]
    assert len(set(keys)) == len(keys)
    assert all("//" not in k and not k.endswith("/") for k in keys)


# --- messaging through a router -----------------------------------------------------------------


def test_a_round_trip_through_the_router_runs_on_the_receive_thread(
    pair: tuple[ZenohTransport, ZenohTransport],
) -> None:
    a, b = pair
    inbox = Inbox()
    b.subscribe("ROUND/TRIP", inbox)
    until_routed(a, b)
    a.publish("ROUND/TRIP", b"\x00payload\xff")
    a.publish("ROUND/TRIP", memoryview(b"second"))  # type: ignore[arg-type]
    items = inbox.wait_for(2)
    assert [(c, d) for c, d, _ in items] == [
        ("ROUND/TRIP", b"\x00payload\xff"),
        ("ROUND/TRIP", b"second"),
    ]
    assert {name for _, _, name in items} == {"temoto-zenoh"}
    assert a.peers()  # the router


def test_a_transport_hears_its_own_messages_but_never_on_the_publishers_thread(
    pair: tuple[ZenohTransport, ZenohTransport],
) -> None:
    a, _ = pair
    inbox = Inbox()
    a.subscribe("SELF", inbox)
    a.publish("SELF", b"mine")
    assert inbox.wait_for(1)[0] == ("SELF", b"mine", "temoto-zenoh")


def test_messages_of_one_publisher_arrive_in_order_across_channels(
    pair: tuple[ZenohTransport, ZenohTransport],
) -> None:
    a, b = pair
    inbox = Inbox()
    b.subscribe("SEQ_A", inbox)
    b.subscribe("SEQ_B", inbox)
    until_routed(a, b)
    for i in range(300):
        a.publish("SEQ_A" if i % 2 else "SEQ_B", i.to_bytes(2, "big"))
    inbox.wait_for(300)
    assert [int.from_bytes(d, "big") for d in inbox.data] == list(range(300))


def test_channels_are_matched_exactly_and_prefixes_keep_fleets_apart(router: str) -> None:
    other_fleet = router.rsplit("=", 1)[0] + "=" + prefix()
    with (
        ZenohTransport(router) as a,
        ZenohTransport(router) as b,
        ZenohTransport(other_fleet) as c,
    ):
        inbox, stranger = Inbox(), Inbox()
        b.subscribe("A.B", inbox)
        c.subscribe("A.B", stranger)
        until_routed(a, b)
        until_routed(c, c)
        a.publish("AxB", b"a pattern would match this")
        a.publish("A/B", b"another chunk")
        a.publish("A.B", b"exact")
        inbox.wait_for(1)
        until_routed(a, b)  # later messages of a have arrived: nothing else is on its way
        c.publish("A.B", b"own fleet")
        stranger.wait_for(1)
        assert inbox.data == [b"exact"]
        assert stranger.data == [b"own fleet"]


def test_unsubscribe_stops_delivery_and_a_handler_may_unsubscribe_itself(
    pair: tuple[ZenohTransport, ZenohTransport],
) -> None:
    a, b = pair
    inbox, other = Inbox(), Inbox()
    once: list[bytes] = []
    sub = b.subscribe("CHAT", inbox)
    b.subscribe("CHAT", other)

    once_done = threading.Event()

    def one_shot(channel: str, data: bytes) -> None:
        once.append(data)
        me.unsubscribe()
        once_done.set()

    me = b.subscribe("CHAT", one_shot)
    until_routed(a, b)
    a.publish("CHAT", b"1")
    inbox.wait_for(1)
    sub.unsubscribe()
    sub.unsubscribe()
    a.publish("CHAT", b"2")
    other.wait_for(2)
    assert once_done.wait(WAIT_S)
    assert inbox.data == [b"1"]
    assert once == [b"1"]
    assert not sub.active
    assert not me.active
    assert isinstance(sub, ZenohSubscription)
    assert sub not in b._by_key.get(sub.key, [])


def test_a_raising_handler_is_counted_and_the_thread_survives(
    pair: tuple[ZenohTransport, ZenohTransport], caplog: pytest.LogCaptureFixture
) -> None:
    a, _ = pair
    calls: list[bytes] = []
    second = threading.Event()

    def broken(channel: str, data: bytes) -> None:
        calls.append(data)
        if len(calls) == 2:
            second.set()
        raise ValueError("bad message")

    bad = a.subscribe("CHAT", broken)
    inbox, after = Inbox(), Inbox()
    a.subscribe("CHAT", inbox)
    a.subscribe("AFTER", after)
    a.publish("CHAT", b"1")
    a.publish("CHAT", b"2")
    inbox.wait_for(2)
    assert second.wait(WAIT_S)
    # one receive thread: once it has handled a later message, the second raise was counted
    a.publish("AFTER", b"")
    after.wait_for(1)
    assert bad.handler_errors == 2
    assert a.handler_errors == 2
    assert "bad message" in caplog.text


def test_a_full_subscription_queue_drops_its_oldest_messages(
    pair: tuple[ZenohTransport, ZenohTransport],
) -> None:
    a, _ = pair
    release = threading.Event()
    blocked = threading.Event()

    def stuck(channel: str, data: bytes) -> None:
        blocked.set()
        release.wait(WAIT_S)

    a.subscribe("STUCK", stuck)
    a.publish("STUCK", b"")
    assert blocked.wait(WAIT_S)  # the receive thread is busy from now on
    inbox = Inbox()
    sub = a.subscribe("BOUNDED", inbox, queue_capacity=3)
    for i in range(10):
        a.publish("BOUNDED", bytes([i]))
    assert isinstance(sub, ZenohSubscription)
    # a's own messages are in its Zenoh channel once publish() returns; the thread moves them
    # all to the queue (which keeps the last 3) before it calls the next handler
    release.set()
    inbox.wait_for(3)
    a.publish("BOUNDED", b"\xff")
    inbox.wait_for(4)
    assert inbox.data == [b"\x07", b"\x08", b"\x09", b"\xff"]
    assert sub.dropped == 7


def test_while_a_handler_runs_zenohs_channel_keeps_the_newest_messages(
    router: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(zenoh_module, "RECEIVE_CHANNEL_CAPACITY", 4)
    with ZenohTransport(router) as a:
        release, blocked = threading.Event(), threading.Event()

        def stuck(channel: str, data: bytes) -> None:
            blocked.set()
            release.wait(WAIT_S)

        a.subscribe("STUCK", stuck)
        inbox = Inbox()
        a.subscribe("ALL", inbox)  # no queue_capacity: no bound of its own
        a.publish("STUCK", b"")
        assert blocked.wait(WAIT_S)
        for i in range(10):
            a.publish("ALL", bytes([i]))
        release.set()
        inbox.wait_for(4)
        a.publish("ALL", b"\xff")
        inbox.wait_for(5)
        assert inbox.data == [b"\x06", b"\x07", b"\x08", b"\x09", b"\xff"]


def test_close_joins_the_thread_and_refuses_more_work(router: str) -> None:
    t = ZenohTransport(router)
    inbox = Inbox()
    t.subscribe("X", inbox)
    t.close()
    t.close()
    assert t.closed
    assert not t.peers()
    assert not any(th.name == "temoto-zenoh" and th.is_alive() for th in [t._thread])
    with pytest.raises(TransportError, match="closed"):
        t.publish("X", b"")
    with pytest.raises(TransportError, match="closed"):
        t.subscribe("X", inbox)


def test_close_from_a_handler_ends_the_thread(router: str) -> None:
    t = ZenohTransport(router)
    done = threading.Event()

    def closer(channel: str, data: bytes) -> None:
        t.close()
        done.set()

    t.subscribe("BYE", closer)
    t.publish("BYE", b"")
    assert done.wait(WAIT_S)
    t._thread.join(WAIT_S)
    assert not t._thread.is_alive()


def test_a_fleet_link_round_trip_keeps_the_envelopes_unchanged(
    pair: tuple[ZenohTransport, ZenohTransport],
) -> None:
    a, b = pair
    key = bytes(range(32))
    alpha = FleetLink(a, FleetAuth("fleet", "alpha", key))
    beta = FleetLink(b, FleetAuth("fleet", "beta", key))
    got: list[Opened] = []
    done = threading.Event()

    def on_beta(opened: Opened) -> None:
        got.append(opened)
        done.set()

    beta.listen("TEMOTO_NOTIFY", on_beta)
    until_routed(a, b)
    # the intruder comes once the route is up: its hello (with the wrong key, the message beta
    # counts as forged) would otherwise be published before anyone could receive it
    intruder = FleetLink(a, FleetAuth("fleet", "mallory", bytes(32)))
    intruder.send("TEMOTO_NOTIFY", "action_ack_t", b"forged")
    alpha.send("TEMOTO_NOTIFY", "action_ack_t", b"inner")
    assert done.wait(WAIT_S)
    until_routed(a, b)
    assert [(o.sender, o.type, o.payload) for o in got] == [("alpha", "action_ack_t", b"inner")]
    assert beta.stats["accepted"] == 1
    # the forged message may be handled after the genuine one (another callback thread): wait
    # for its count rather than reading it once
    deadline = time.monotonic() + WAIT_S
    while beta.stats["forged"] < 1 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert beta.stats["forged"] == 1, str(dict(beta.stats))


# --- sessions without a router, and failures ----------------------------------------------------


def test_two_peers_talk_directly_without_a_router() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    fleet = prefix()
    with (
        ZenohTransport(f"zenoh:?listen={endpoint}&prefix={fleet}") as a,
        ZenohTransport(f"zenoh:{endpoint}?mode=peer&prefix={fleet}") as b,
    ):
        inbox = Inbox()
        b.subscribe("P2P", inbox)
        until_routed(a, b)
        a.publish("P2P", b"direct")
        inbox.wait_for(1)
        assert inbox.data[-1] == b"direct"


def test_a_client_without_a_router_fails_with_a_hint() -> None:
    url = f"zenoh:tcp/127.0.0.1:{free_port()}?timeout=0"
    started = time.monotonic()
    with pytest.raises(TransportError, match="temoto router") as info:
        open_transport(url)
    assert url in str(info.value)
    assert ".rs:" not in str(info.value)  # the Rust source location is cut off
    assert time.monotonic() - started < WAIT_S


def test_a_client_keeps_trying_until_its_router_is_up() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    routers: list[Any] = []
    trying = threading.Event()
    opened: list[ZenohTransport] = []

    def client() -> None:
        trying.set()
        opened.append(ZenohTransport(f"zenoh:{endpoint}?timeout=10&prefix={prefix()}"))

    thread = threading.Thread(target=client)
    thread.start()
    try:
        assert trying.wait(WAIT_S)
        routers.append(open_router((endpoint,)))  # started after the client
        thread.join(WAIT_S * 2)
        assert opened, "the client did not reach the router started after it"
        assert len(opened[0].peers()) == 1
    finally:
        thread.join()
        for t in opened:
            t.close()
        for r in routers:
            r.close()


def test_a_missing_configuration_file_is_named(tmp_path: Any) -> None:
    missing = tmp_path / "nowhere.json5"
    with pytest.raises(TransportError, match=r"nowhere\.json5"):
        ZenohTransport(f"zenoh:{missing}")


def test_a_configuration_file_is_used_as_it_is(tmp_path: Any) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_router((endpoint,))
    try:
        conf = tmp_path / "robot.json5"
        conf.write_text(
            f'{{ mode: "client", connect: {{ endpoints: ["{endpoint}"] }},'
            " scouting: { multicast: { enabled: false } } }\n"
        )
        fleet = prefix()
        with (
            ZenohTransport(f"zenoh:{conf}?prefix={fleet}") as a,
            ZenohTransport(f"zenoh:{endpoint}?prefix={fleet}") as b,
        ):
            inbox = Inbox()
            b.subscribe("CONF", inbox)
            until_routed(a, b)
            assert len(a.peers()) == 1  # the router, as the file said
    finally:
        router.close()


def test_without_the_wheel_the_error_names_the_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "zenoh", None)  # import zenoh now raises ImportError
    with pytest.raises(TransportError, match=r"pip install 'temoto\[zenoh\]'"):
        open_transport("zenoh:tcp/127.0.0.1:7447")
    with pytest.raises(TransportError, match=r"temoto\[zenoh\]"):
        open_router(("tcp/127.0.0.1:7447",))


def test_a_router_on_a_port_in_use_fails_naming_it() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    first = open_router((endpoint,))
    try:
        with pytest.raises(TransportError, match=f"cannot listen on {endpoint}"):
            open_router((endpoint,))
    finally:
        first.close()
    with pytest.raises(ValueError, match="listen '7447'"):
        open_router(("7447",))


def test_importing_the_transports_and_the_cli_does_not_import_zenoh() -> None:
    code = (
        "import sys, temoto.transport, temoto.cli, temoto.cli.router;"
        " temoto.cli._parser();"
        " assert 'zenoh' not in sys.modules, 'zenoh imported'"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr


def test_subscribing_while_a_flood_arrives_is_safe(
    pair: tuple[ZenohTransport, ZenohTransport],
) -> None:
    # LCM's binding can crash here (temoto/transport/lcm.py): a Zenoh transport's subscriptions
    # are our own lists, changed under the lock its receive thread dispatches under, and its one
    # Zenoh subscriber is declared before that thread reads from it; nothing can race.
    a, b = pair
    until_routed(a, b)
    stop, current, got = threading.Event(), [0], [0]

    def flood() -> None:
        while not stop.is_set():
            n = current[0]
            a.publish(f"S{n}", b"x")
            a.publish(f"S{n + 1}", b"x")

    def count(channel: str, data: bytes) -> None:
        got[0] += 1

    flooder = threading.Thread(target=flood, name="temoto-test-flood")
    flooder.start()
    subs = []
    try:
        deadline = time.monotonic() + 1.5
        while time.monotonic() < deadline:
            subs.append(b.subscribe(f"S{current[0] + 1}", count))
            current[0] += 1
            if len(subs) > 16:
                subs.pop(0).unsubscribe()
    finally:
        stop.set()
        flooder.join()
    assert current[0] > 50
    assert b.handler_errors == 0
    assert got[0] > 0
