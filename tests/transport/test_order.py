"""A new member's first messages reach the handlers in the order they were sent (docs/fleet.md).

What a new member sends before a receiver holds its grant is refused and asked for again; the
copies, sealed anew, come a round trip later than what it sent meanwhile. The receiver holds
the sender's other messages back until the copies came (``HOLD_S`` at most). Every step is
driven by hand here: which message reaches whom, and when, is the test's choice.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from temoto.testing.fleet import settle
from temoto.transport import FleetAuth, FleetLink
from temoto.transport._secure import BACKLOG_S, HOLD_S
from temoto.transport.auth import HELLO_CHANNEL
from temoto.transport.base import Handler, Subscription, Transport
from temoto.transport.identity import Credentials, Identity, Roster

KEY = bytes(range(32))
CHANNEL = "TEMOTO_RIS"
OTHER = "TEMOTO_NOTIFY"
N = 12


class FakeClock:
    def __init__(self) -> None:
        self.t = 1_750_000_000.0

    def __call__(self) -> float:
        return self.t


Make = Callable[[str], FleetAuth]


@pytest.fixture
def clock() -> FakeClock:
    return FakeClock()


@pytest.fixture(params=["fleet key", "roster"])
def make(request: pytest.FixtureRequest, tmp_path: Path, clock: FakeClock) -> Make:
    """Members with one fleet key, or a roster of exactly the two (a message to the receiver
    alone then carries the receiver's entry only, as a copy did before copies were marked)."""
    if request.param == "fleet key":
        return lambda name: FleetAuth("fleet", name, KEY, clock=clock)
    ids = {name: Identity.generate(name) for name in ("alice", "bob")}
    roster = Roster({})
    for name, identity in ids.items():
        roster.add(name, identity.public_key)
    roster.save(tmp_path / "roster.yaml")
    return lambda name: FleetAuth(
        "fleet", name, Credentials(ids[name], Roster.load(tmp_path / "roster.yaml")), clock=clock
    )


class Receiver:
    """The receiver's side of a FleetLink: released messages first, then the one opened."""

    def __init__(self, auth: FleetAuth) -> None:
        self.auth = auth
        self.got: list[bytes] = []

    def deliver(self, channel: str, data: bytes) -> None:
        opened = self.auth.open(channel, data)
        self.got += [o.payload for o in self.auth.take_released()]
        if opened is not None:
            self.got.append(opened.payload)


def hellos(member: FleetAuth) -> list[tuple[str, bytes]]:
    out = member.take_outgoing()
    assert all(channel == HELLO_CHANNEL for channel, _ in out)
    return out


def copies(member: FleetAuth) -> list[tuple[str, bytes]]:
    """What ``member`` publishes now but hellos: the copies it re-sends."""
    return [(c, d) for c, d in member.take_outgoing() if c != HELLO_CHANNEL]


def numbered(i: int) -> bytes:
    return f"message {i}".encode()


def new_member(make: Make) -> tuple[FleetAuth, FleetAuth, Receiver]:
    """alice listens; bob boots and his hello reaches alice, whose grant reaches bob."""
    alice, bob = make("alice"), make("bob")
    alice.take_outgoing()  # alice's first hello: bob was not there yet
    handler = Receiver(alice)
    for channel, data in hellos(bob):  # bob's first hello: alice grants him her session
        alice.open(channel, data)
    for channel, data in alice.take_outgoing():
        bob.open(channel, data)
    return alice, bob, handler


def test_a_new_members_burst_before_the_grant_is_handled_in_order(make: Make) -> None:
    alice, bob, handler = new_member(make)
    k = N // 3
    early = [(CHANNEL, bob.seal(CHANNEL, "t", numbered(i))) for i in range(1, k + 1)]
    grant = hellos(bob)  # bob's grant for alice: its floor counts the early ones
    for channel, data in early:  # before the grant: refused, asked for again
        handler.deliver(channel, data)
    assert handler.got == []
    assert alice.stats["no_session"] == k
    for channel, data in grant:
        handler.deliver(channel, data)
    ask = alice.take_outgoing()  # alice's hello asks for the early ones
    later = [(CHANNEL, bob.seal(CHANNEL, "t", numbered(i))) for i in range(k + 1, N + 1)]
    for channel, data in later:  # alice holds bob's grant: these open at once
        handler.deliver(channel, data)
    for channel, data in ask:
        bob.open(channel, data)
    resent = copies(bob)
    assert len(resent) == k
    for channel, data in resent:
        handler.deliver(channel, data)
    assert handler.got == [numbered(i) for i in range(1, N + 1)]
    # and from now on at once
    handler.deliver(CHANNEL, bob.seal(CHANNEL, "t", b"after"))
    assert handler.got[-1] == b"after"


def test_copies_asked_for_in_two_hellos_are_handled_in_the_order_sent(make: Make) -> None:
    """A message that its grant overtook is asked for in a hello of its own; the two batches
    of copies cross on the way back (two threads of bob publish them), and a message of
    another channel comes between."""
    alice, bob, handler = new_member(make)
    first = (CHANNEL, bob.seal(CHANNEL, "t", numbered(1)))
    second = (OTHER, bob.seal(OTHER, "t", numbered(2)))  # sealed, not yet published...
    grant = hellos(bob)  # ... when bob's grant (its floor counts both) goes out
    handler.deliver(*first)
    for channel, data in grant:
        handler.deliver(channel, data)
    ask_first = alice.take_outgoing()
    handler.deliver(*second)  # after the grant, at or below its floor: asked for alone
    ask_second = alice.take_outgoing()
    third = (CHANNEL, bob.seal(CHANNEL, "t", numbered(3)))
    for channel, data in ask_first:
        bob.open(channel, data)
    batch_one = copies(bob)
    for channel, data in ask_second:
        bob.open(channel, data)
    batch_two = copies(bob)
    assert len(batch_one) == len(batch_two) == 1
    for channel, data in [third, *batch_two, *batch_one]:
        handler.deliver(channel, data)
    assert handler.got == [numbered(1), numbered(2), numbered(3)]


def test_a_lost_copy_holds_its_sender_back_hold_s_at_most(make: Make, clock: FakeClock) -> None:
    alice, bob, handler = new_member(make)
    early = [(CHANNEL, bob.seal(CHANNEL, "t", numbered(i))) for i in (1, 2)]
    grant = hellos(bob)
    for channel, data in [*early, *grant]:
        handler.deliver(channel, data)
    for channel, data in alice.take_outgoing():
        bob.open(channel, data)
    lost, kept = copies(bob)
    handler.deliver(*kept)
    handler.deliver(CHANNEL, bob.seal(CHANNEL, "t", numbered(3)))
    assert handler.got == []  # waiting for the lost copy
    assert alice.hold_due_in() == pytest.approx(HOLD_S)
    clock.t += HOLD_S
    assert alice.hold_due_in() == 0.0
    handler.deliver(OTHER, b"garbage")  # whatever comes next ends the hold
    assert handler.got == [numbered(2), numbered(3)]  # what came, in order; 1 is lost
    assert alice.hold_due_in() is None
    handler.deliver(*lost)  # a copy later than the hold: handed on when it comes
    assert handler.got[-1] == numbered(1)
    handler.deliver(CHANNEL, bob.seal(CHANNEL, "t", numbered(4)))
    assert handler.got[-1] == numbered(4)


# --- through a FleetLink ----------------------------------------------------------------------


class HandSub(Subscription):
    def _on_unsubscribe(self) -> None:
        pass


class HandBus(Transport):
    """A transport whose messages wait in this member's inbox until the test delivers them
    (on the test's thread): the order in which each member hears the others is the test's."""

    def __init__(self, members: list[HandBus]) -> None:
        super().__init__()
        self.members = members
        members.append(self)
        self.inbox: deque[tuple[str, bytes]] = deque()
        self.subs: list[HandSub] = []
        self.lock = threading.Lock()  # a hello timer of the link may publish meanwhile

    def _publish(self, channel: str, data: bytes) -> None:
        for member in self.members:  # our own messages too, as over multicast
            with member.lock:
                member.inbox.append((channel, data))

    def _subscribe(self, channel: str, handler: Handler, queue_capacity: int | None) -> HandSub:
        sub = HandSub(channel, handler)
        self.subs.append(sub)
        return sub

    def _close(self) -> None:
        self.subs.clear()

    def pump(self) -> None:
        """Deliver everything in the inbox, and what comes meanwhile."""
        while True:
            with self.lock:
                if not self.inbox:
                    return
                channel, data = self.inbox.popleft()
            for sub in self.subs:
                if sub.channel == channel:
                    self._deliver(sub, channel, data)


@contextlib.contextmanager
def alice_and_bob() -> Iterator[tuple[HandBus, HandBus, FleetLink, FleetLink, list[bytes]]]:
    """alice's and bob's FleetLinks on hand-pumped buses; alice's handler on CHANNEL keeps the
    payloads in the list yielded last."""
    members: list[HandBus] = []
    with HandBus(members) as a_bus, HandBus(members) as b_bus:
        alice = FleetLink(a_bus, FleetAuth("fleet", "alice", KEY))
        got: list[bytes] = []
        alice.listen(CHANNEL, lambda opened: got.append(opened.payload))
        bob = FleetLink(b_bus, FleetAuth("fleet", "bob", KEY))
        yield a_bus, b_bus, alice, bob, got


def test_a_fleet_links_handler_sees_a_new_members_burst_in_order() -> None:
    """Over a FleetLink: bob joins and sends N numbered messages, the first third before alice
    holds his grant; alice's handler gets them in order, whatever reaches her when."""
    with alice_and_bob() as (a_bus, b_bus, alice, bob, got):
        k = N // 3
        for i in range(1, k + 1):  # before anyone heard anyone
            bob.send(CHANNEL, "t", numbered(i))
        a_bus.pump()  # bob's hello, then his messages: refused; alice grants bob her session
        assert got == []
        b_bus.pump()  # alice's grant: bob answers with his
        a_bus.pump()  # bob's grant: alice asks for what she could not open
        for i in range(k + 1, N + 1):  # these alice can open at once
            bob.send(CHANNEL, "t", numbered(i))
        a_bus.pump()
        b_bus.pump()  # alice's ask: bob re-sends the first ones
        a_bus.pump()
        assert got == [numbered(i) for i in range(1, N + 1)]
        assert alice.stats["handler_error"] == 0


def test_a_link_lets_go_of_what_waits_for_lost_copies_when_nothing_else_comes() -> None:
    """The copies are lost and bob says nothing more: alice's link ends the hold itself, HOLD_S
    (1 s) later (its hello's echo comes back on the receive thread, where handlers run)."""
    with alice_and_bob() as (a_bus, b_bus, _alice, bob, got):
        bob.send(CHANNEL, "t", numbered(1))
        a_bus.pump()
        b_bus.pump()
        a_bus.pump()  # alice asks for message 1
        bob.send(CHANNEL, "t", numbered(2))
        a_bus.pump()  # held back
        b_bus.pump()  # the copy of 1 ...
        with a_bus.lock:
            a_bus.inbox.clear()  # ... is lost
        assert got == []
        deadline = time.monotonic() + 10 * HOLD_S
        while not got and time.monotonic() < deadline:
            a_bus.pump()
            time.sleep(0.01)
        assert got == [numbered(2)]


def test_a_replay_long_after_the_key_exchange_holds_nothing_back(clock: FakeClock) -> None:
    """A message at or below the grant's floor that comes BACKLOG_S after the grant is asked
    for (a copy would be too old to come) but holds nothing back: a replay of captured traffic
    to a restarted member cannot delay the sender's messages again and again."""
    alice = FleetAuth("fleet", "alice", KEY, clock=clock)
    bob = FleetAuth("fleet", "bob", KEY, clock=clock)
    settle(alice, bob)
    captured = alice.seal(CHANNEL, "t", b"captured")
    assert bob.open(CHANNEL, captured) is not None
    restarted = FleetAuth("fleet", "bob", KEY, clock=clock)
    settle(alice, restarted)
    clock.t += BACKLOG_S
    assert restarted.open(CHANNEL, captured) is None  # at or below the floor
    for channel, data in restarted.take_outgoing():  # its hello asks for it
        alice.open(channel, data)
    assert [c for c, _ in alice.take_outgoing() if c != HELLO_CHANNEL] == []  # too old: refused
    opened = restarted.open(CHANNEL, alice.seal(CHANNEL, "t", b"fresh"))
    assert opened is not None
    assert opened.payload == b"fresh"
    assert restarted.hold_due_in() is None
