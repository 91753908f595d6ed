"""How keyed members agree their sessions: few hellos, nothing lost while they cross.

Sans-IO: :class:`~temoto.transport.auth.FleetAuth` members on a fake clock, each hello and
message handed over by the test in the order it chooses (docs/security.md, "Sessions").
"""

from __future__ import annotations

from typing import Any

from temoto.testing.fleet import settle
from temoto.transport.auth import HELLO_CHANNEL, FleetAuth
from temoto.transport.inprocess import InProcessTransport
from temoto.transport.link import HELLO_QUEUE, FleetLink

KEY = bytes(range(32))
T0 = 1_750_000_000.0
CHANNEL = "TEMOTO_NOTIFY"
GRANT_WAIT_S = 0.25  # temoto.transport._secure.GRANT_WAIT_S, as documented
ASK_S = 0.5  # temoto.transport._secure.ASK_S


class Clock:
    def __init__(self) -> None:
        self.t = T0

    def __call__(self) -> float:
        return self.t


def member(name: str, clock: Clock) -> FleetAuth:
    return FleetAuth("fleet", name, KEY, clock=clock)


def hellos(auth: FleetAuth) -> list[bytes]:
    return [data for channel, data in auth.take_outgoing() if channel == HELLO_CHANNEL]


def one_hello(auth: FleetAuth) -> bytes:
    out = hellos(auth)
    assert len(out) == 1, f"expected one hello, got {len(out)}"
    return out[0]


def test_a_grant_asked_for_while_ours_is_on_its_way_is_not_sent_again() -> None:
    clock = Clock()
    a, b = member("a", clock), member("b", clock)
    ha0 = one_hello(a)
    one_hello(b)
    b.open(HELLO_CHANNEL, ha0)
    hb1 = one_hello(b)  # b's grant for a, on its way
    data = b.seal(CHANNEL, "t", b"x")
    assert a.open(CHANNEL, data) is None  # before the grant: a asks b for it
    clock.t += (a.hello_due_in() or 0.0) + 1e-6  # hellos are paced
    ha1 = one_hello(a)
    b.open(HELLO_CHANNEL, ha1)
    assert hellos(b) == [], "b sent its grant again while the first one was on its way"
    clock.t += GRANT_WAIT_S
    b.open(HELLO_CHANNEL, ha1)  # a still asks (the first grant was lost): b answers now
    assert len(hellos(b)) == 1
    a.open(HELLO_CHANNEL, hb1)
    settle(a, b, clock=clock, rounds=100)
    assert a.open(CHANNEL, b.seal(CHANNEL, "t", b"y")) is not None


def test_data_before_a_grant_that_is_on_its_way_asks_for_it_only_if_it_does_not_come() -> None:
    clock = Clock()
    a, b = member("a", clock), member("b", clock)
    one_hello(a)
    hb0 = one_hello(b)
    a.open(HELLO_CHANNEL, hb0)
    ha1 = one_hello(a)  # a's key and grant for b: b answers it with its grant
    assert a.open(CHANNEL, b.seal(CHANNEL, "t", b"x")) is None  # b's grant is not here yet
    assert hellos(a) == []
    due = a.hello_due_in()
    assert due is not None
    assert due > GRANT_WAIT_S - 0.01, due
    b.open(HELLO_CHANNEL, ha1)
    a.open(HELLO_CHANNEL, one_hello(b))  # the grant came in time
    assert a.peers == {"b"}


def test_a_large_fleet_answers_members_that_start_together_in_few_hellos() -> None:
    clock = Clock()
    x = member("x", clock)
    one_hello(x)
    others = [member(f"m{i:02d}", clock) for i in range(30)]
    sent = []
    for other in others:
        x.open(HELLO_CHANNEL, one_hello(other))
        sent += hellos(x)  # what x's link publishes after every hello it takes in
    assert len(sent) <= 11, f"x answered 30 members starting together with {len(sent)} hellos"
    for hello in sent:
        for other in others:
            other.open(HELLO_CHANNEL, hello)
    settle(x, *others, clock=clock, rounds=100)
    data = x.seal(CHANNEL, "t", b"x")
    assert all(o.open(CHANNEL, data) is not None for o in others)


def test_a_message_its_grant_overtook_is_asked_for_and_sent_again() -> None:
    clock = Clock()
    a, b = member("a", clock), member("b", clock)
    ha0, hb0 = one_hello(a), one_hello(b)
    b.open(HELLO_CHANNEL, ha0)
    hb1 = one_hello(b)
    a.open(HELLO_CHANNEL, hb0)
    early = a.seal(CHANNEL, "t", b"sealed before the grant")  # published after it, below
    a.open(HELLO_CHANNEL, hb1)
    b.open(HELLO_CHANNEL, one_hello(a))  # a's grant; its floor counts `early`
    before = b.stats
    assert b.open(CHANNEL, early) is None
    after = b.stats
    assert after["replayed"] == before["replayed"]
    assert after["no_session"] == before["no_session"] + 1
    for channel, data in b.take_outgoing():  # b asks for it again
        a.open(channel, data)
    copies = [(c, d) for c, d in a.take_outgoing() if c == CHANNEL]
    assert len(copies) == 1
    opened = b.open(*copies[0])
    assert opened is not None
    assert opened.payload == b"sealed before the grant"
    before = b.stats
    assert b.open(CHANNEL, early) is None  # asked for once: now it is a replay
    assert b.stats["replayed"] == before["replayed"] + 1


def test_a_link_keeps_the_hellos_of_a_fleet_starting_together() -> None:
    transport = InProcessTransport()
    try:
        link = FleetLink(transport, member("a", Clock()))
        assert link._hellos is not None
        assert link._hellos.queue_capacity == HELLO_QUEUE >= 1024
    finally:
        transport.close()


def test_members_whose_first_hellos_were_lost_still_agree_keys() -> None:
    """Over Zenoh a hello published before the router knew a subscriber is lost; a member
    that waits for its peers without sending anything must say hello again."""
    transports = [InProcessTransport(bus="lost-hellos"), InProcessTransport(bus="lost-hellos")]
    try:
        for transport in transports:
            publish = transport.publish
            dropped: list[int] = []

            def lossy(channel: str, data: bytes, publish: Any = publish, dropped: Any = dropped
                      ) -> None:  # fmt: skip
                if channel == HELLO_CHANNEL and not dropped:
                    dropped.append(1)  # the first hello of each member is lost
                    return
                publish(channel, data)

            transport.publish = lossy  # type: ignore[method-assign]
        a = FleetLink(transports[0], FleetAuth("fleet", "a", KEY))
        b = FleetLink(transports[1], FleetAuth("fleet", "b", KEY))
        assert b.wait_for_peers(["a"], 10.0)
        assert a.wait_for_peers(["b"], 10.0)
    finally:
        for transport in transports:
            transport.close()


def test_a_lost_grant_is_asked_for_again_though_its_peer_sends_nothing() -> None:
    clock = Clock()
    a, b = member("a", clock), member("b", clock)
    ha0, hb0 = one_hello(a), one_hello(b)
    b.open(HELLO_CHANNEL, ha0)
    one_hello(b)  # b's grant for a: lost
    a.open(HELLO_CHANNEL, hb0)
    b.open(HELLO_CHANNEL, one_hello(a))  # a's grant for b
    assert (a.peers, b.peers) == (frozenset(), {"a"})
    assert hellos(b) == []  # b has nothing more to say, and sends a nothing it cannot open
    clock.t += ASK_S - 0.1  # b's answer to a's grant may still be on its way: not asked for
    a.want_hello()  # as FleetLink.wait_for_peers does, again and again
    b.open(HELLO_CHANNEL, one_hello(a))
    assert hellos(b) == []
    for attempt in range(3):  # asked for in every hello of a's until it comes
        clock.t += 0.1
        a.want_hello()
        b.open(HELLO_CHANNEL, one_hello(a))
        again = one_hello(b)  # b grants its session again
        if attempt == 2:
            a.open(HELLO_CHANNEL, again)  # the first two were lost too
        clock.t += GRANT_WAIT_S
    assert a.peers == {"b"}
    a.want_hello()
    b.open(HELLO_CHANNEL, one_hello(a))
    assert hellos(b) == []  # nothing is missing: nothing asked


def test_a_member_whose_grant_was_lost_agrees_keys_while_its_peer_is_quiet() -> None:
    """The peer's grant was lost and the peer has nothing to send: waiting for it must not
    wait forever (under 25 % loss, 6 tries of 6 did not agree keys within 15 s)."""
    transports = [InProcessTransport(bus="lost-grant"), InProcessTransport(bus="lost-grant")]
    try:
        publish = transports[1].publish
        hellos_of_b: list[bytes] = []

        def lossy(channel: str, data: bytes) -> None:
            if channel == HELLO_CHANNEL:
                hellos_of_b.append(data)
                if len(hellos_of_b) == 2:
                    return  # b's second hello, its answer to a's grant, carries b's: lost
            publish(channel, data)

        transports[1].publish = lossy  # type: ignore[method-assign]
        a = FleetLink(transports[0], FleetAuth("fleet", "a", KEY))
        b = FleetLink(transports[1], FleetAuth("fleet", "b", KEY))
        assert b.wait_for_peers(["a"], 10.0)
        assert a.wait_for_peers(["b"], 10.0)
        assert len(hellos_of_b) >= 3  # b granted its session again, asked by a
    finally:
        for transport in transports:
            transport.close()
