"""Authentication drops are visible: WARNING lines naming the claimed sender and the reason.

The first drop of each sender and reason is logged at once; later ones are summarised, with
counts, at most once per ``DROP_SUMMARY_S`` seconds of the member's (injected) clock.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

import pytest

from temoto.lcm_types import envelope_t
from temoto.testing.fleet import settle
from temoto.transport import DROP_REASONS, FleetAuth
from temoto.transport._drops import _MAX_FIRST_LINES, DROP_SUMMARY_S

KEY = bytes(range(32))
OTHER_KEY = bytes(range(1, 33))
T0 = 1_750_000_000.0
CHANNEL = "TEMOTO_NOTIFY"


class FakeClock:
    def __init__(self, t: float = T0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


@pytest.fixture
def clock() -> FakeClock:
    return FakeClock()


@pytest.fixture
def bob(clock: FakeClock) -> FleetAuth:
    return FleetAuth("fleet", "bob", KEY, clock=clock)


def warnings(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]


def wrong_version(clock: FakeClock) -> bytes:
    env = envelope_t()  # type: ignore[no-untyped-call]
    env.version = 7
    env.fleet = "fleet"
    env.sender = "alice"
    env.seq = 1
    env.stamp_us = round(clock() * 1e6)
    env.type = "t"
    env.payload = b""
    env.payload_size = 0
    env.mac = b""
    env.mac_size = 0
    data: bytes = env.encode()  # type: ignore[no-untyped-call]
    return data


def member(name: str, clock: FakeClock, bob: FleetAuth) -> FleetAuth:
    """A member with the fleet key whose hellos crossed with bob's."""
    auth = FleetAuth("fleet", name, KEY, clock=clock)
    for _ in range(4):
        for sender, receiver in ((auth, bob), (bob, auth)):
            for channel, data in sender.take_outgoing():
                receiver.open(channel, data)
    return auth


def tampered(auth: FleetAuth) -> bytes:
    """A message of ``auth`` with its last byte (of the Poly1305 tag) changed."""
    data = auth.seal(CHANNEL, "t", b"x")
    return data[:-1] + bytes([data[-1] ^ 0x01])


def replayed(clock: FakeClock, bob: FleetAuth) -> bytes:
    data = member("alice", clock, bob).seal(CHANNEL, "t", b"x")
    assert bob.open(CHANNEL, data) is not None  # the first copy passes
    return data


#: reason -> (a message that is dropped for it, the claimed sender, words the line must hold)
CASES: dict[str, tuple[Callable[[FakeClock, FleetAuth], bytes], str | None, str]] = {
    "garbage": (lambda c, b: b"\x00junk", None, "not a well-formed envelope"),
    "version": (lambda c, b: wrong_version(c), "alice", "unknown envelope version (version 7)"),
    "unsigned": (
        lambda c, b: FleetAuth("fleet", "alice", None, insecure=True, clock=c).seal(
            CHANNEL, "t", b"x"
        ),
        "alice",
        "does the sender run --insecure?",
    ),
    "forged": (
        lambda c, b: tampered(member("alice", c, b)),
        "alice",
        "wrong mac; sealed with another fleet key",
    ),
    "replayed": (replayed, "alice", "already seen or too old"),
}


def test_a_stale_stamp_into_an_insecure_member_is_a_warning(
    clock: FakeClock, caplog: pytest.LogCaptureFixture
) -> None:
    insecure = FleetAuth("fleet", "bob", None, insecure=True, clock=clock)
    old = FleetAuth("fleet", "alice", None, insecure=True, clock=FakeClock(clock.t - 45))
    data = old.seal(CHANNEL, "t", b"x")
    with caplog.at_level(logging.WARNING, logger="temoto.transport"):
        caplog.clear()
        assert insecure.open(CHANNEL, data) is None
    (line,) = warnings(caplog)
    assert "from 'alice': time stamp outside the window" in line
    assert "(-45.0 s from our clock, window ±30 s); are the clocks synchronised" in line


def test_a_hello_with_another_fleet_key_is_a_warning(
    clock: FakeClock, bob: FleetAuth, caplog: pytest.LogCaptureFixture
) -> None:
    stranger = FleetAuth("fleet", "alice", OTHER_KEY, clock=clock)
    ((channel, hello),) = stranger.take_outgoing()
    with caplog.at_level(logging.WARNING, logger="temoto.transport"):
        assert bob.open(channel, hello) is None
    (line,) = warnings(caplog)
    assert "on 'TEMOTO_KEYS' from 'alice': wrong mac; sealed with another fleet key" in line


@pytest.mark.parametrize("reason", sorted(CASES))
def test_each_authentication_failure_is_a_warning_naming_sender_and_reason(
    reason: str, clock: FakeClock, bob: FleetAuth, caplog: pytest.LogCaptureFixture
) -> None:
    make, sender, words = CASES[reason]
    data = make(clock, bob)
    with caplog.at_level(logging.WARNING, logger="temoto.transport"):
        caplog.clear()  # an insecure sender's own warning at its creation
        assert bob.open(CHANNEL, data) is None
    assert bob.stats[reason] == 1
    (line,) = warnings(caplog)
    assert "fleet 'fleet': dropped a message on 'TEMOTO_NOTIFY' from " in line
    assert ("an unknown sender" if sender is None else f"from '{sender}'") in line
    assert words in line


def test_a_mac_into_an_insecure_member_is_a_warning(
    clock: FakeClock, caplog: pytest.LogCaptureFixture
) -> None:
    insecure = FleetAuth("fleet", "bob", None, insecure=True, clock=clock)
    signed = FleetAuth("fleet", "alice", KEY, clock=clock).seal(CHANNEL, "t", b"x")
    with caplog.at_level(logging.WARNING, logger="temoto.transport"):
        caplog.clear()  # the insecure member's own warning at creation
        assert insecure.open(CHANNEL, signed) is None
    (line,) = warnings(caplog)
    assert "from 'alice': a mac, but this member runs --insecure" in line


def test_the_table_covers_every_reason_that_warns() -> None:
    quiet = {"self", "fleet", "no_session", "not_for_us"}
    own_tests = {"unexpected_mac", "stale", "unknown_member"}  # tests above, tests/security
    assert set(CASES) == set(DROP_REASONS) - quiet - own_tests


def test_repeats_are_summarised_within_a_second_even_without_more_drops(
    clock: FakeClock, bob: FleetAuth, caplog: pytest.LogCaptureFixture
) -> None:
    # The summary is due DROP_SUMMARY_S (1 s) after the first drop it counts, and the link
    # writes it then (drop_summary_due_in, log_drop_summary), more drops or not: it does not
    # wait for the next drop or for the stop.
    mallory = member("mallory", clock, bob)

    def drops(n: int, step: float) -> None:
        for _ in range(n):
            bob.open(CHANNEL, tampered(mallory))
            clock.t += step

    assert DROP_SUMMARY_S == 1.0
    with caplog.at_level(logging.WARNING, logger="temoto.transport"):
        assert bob.drop_summary_due_in() is None
        drops(50, 0.01)  # t = 0 .. 0.49 s: the first at once, 49 held back from t = 0.01 s
        assert len(warnings(caplog)) == 1
        assert bob.drop_summary_due_in() == pytest.approx(0.51)
        clock.t = T0 + 0.01 + DROP_SUMMARY_S  # due, and no drop comes
        assert bob.drop_summary_due_in() == 0.0
        bob.log_drop_summary()  # what the FleetLink's timer does then
        assert len(warnings(caplog)) == 2
        assert bob.drop_summary_due_in() is None
        drops(30, 0.01)  # a new period begins with the first of them: held back
        assert len(warnings(caplog)) == 2
        clock.t += DROP_SUMMARY_S  # a drop after the period also writes the summary
        drops(1, 0.0)
    lines = warnings(caplog)
    assert len(lines) == 3, lines
    assert "from 'mallory': wrong mac" in lines[0]
    assert lines[1] == (
        "fleet 'fleet': dropped 49 more messages in the last 1.0 s: 49 from 'mallory' (wrong mac)"
    )
    assert lines[2].startswith("fleet 'fleet': dropped 31 more messages in the last 1.3 s")
    assert bob.stats["forged"] == 81


def test_a_fleet_link_writes_the_summary_when_it_is_due(caplog: pytest.LogCaptureFixture) -> None:
    # the link's own timer (real time, at most 1 s): no further drop, no stop is needed
    from temoto.transport import FleetLink, InProcessTransport

    with (
        InProcessTransport("drop-summary") as bus,
        InProcessTransport("drop-summary") as noise,
        caplog.at_level(logging.WARNING, logger="temoto.transport"),
    ):
        link = FleetLink(bus, FleetAuth("fleet", "bob", KEY))
        link.listen(CHANNEL, lambda opened: None)
        for _ in range(3):
            noise.publish(CHANNEL, b"not an envelope")
        assert noise.flush(5.0)
        deadline = time.monotonic() + 5.0
        while len(warnings(caplog)) < 2 and time.monotonic() < deadline:
            time.sleep(0.01)
    lines = warnings(caplog)
    assert len(lines) == 2, lines
    assert "dropped 2 more messages" in lines[1]
    assert "2 from an unknown sender (not a well-formed envelope)" in lines[1]


def test_each_sender_and_reason_gets_its_own_first_line(
    clock: FakeClock, bob: FleetAuth, caplog: pytest.LogCaptureFixture
) -> None:
    carol = member("carol", clock, bob)
    dave = member("dave", clock, bob)
    old = carol.seal(CHANNEL, "t", b"x")
    assert bob.open(CHANNEL, old) is not None
    with caplog.at_level(logging.WARNING, logger="temoto.transport"):
        for data in (tampered(carol), tampered(dave), tampered(carol), tampered(dave), old, old):
            bob.open(CHANNEL, data)
    lines = warnings(caplog)
    assert len(lines) == 3, lines
    assert "from 'carol': wrong mac" in lines[0]
    assert "from 'dave': wrong mac" in lines[1]
    assert "from 'carol': sequence number already seen" in lines[2]


def test_invented_sender_names_cannot_flood_the_log(
    clock: FakeClock, bob: FleetAuth, caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.WARNING, logger="temoto.transport"):
        for i in range(_MAX_FIRST_LINES + 100):
            fake = FleetAuth("fleet", f"stranger-{i}", OTHER_KEY, clock=clock)
            ((channel, hello),) = fake.take_outgoing()
            bob.open(channel, hello)
        assert len(warnings(caplog)) == _MAX_FIRST_LINES
        clock.t += DROP_SUMMARY_S
        bob.open(channel, hello)
    lines = warnings(caplog)
    assert len(lines) == _MAX_FIRST_LINES + 1
    assert "dropped 101 more messages" in lines[-1]
    assert "other senders/reasons" in lines[-1]


def test_a_long_claimed_name_is_cut_and_escaped(
    clock: FakeClock, bob: FleetAuth, caplog: pytest.LogCaptureFixture
) -> None:
    name = "evil\n" + "x" * 500
    fake = FleetAuth("fleet", name, OTHER_KEY, clock=clock)
    ((channel, hello),) = fake.take_outgoing()
    with caplog.at_level(logging.WARNING, logger="temoto.transport"):
        bob.open(channel, hello)
    (line,) = warnings(caplog)
    assert "\n" not in line
    assert "'evil\\nxxx" in line
    assert "x" * 100 not in line


def test_the_summary_of_the_last_drops_can_be_logged_at_the_end(
    clock: FakeClock, bob: FleetAuth, caplog: pytest.LogCaptureFixture
) -> None:
    mallory = member("mallory", clock, bob)
    with caplog.at_level(logging.WARNING, logger="temoto.transport"):
        bob.log_drop_summary()  # nothing held back: nothing logged
        for _ in range(5):
            bob.open(CHANNEL, tampered(mallory))
        clock.t += 2
        bob.log_drop_summary()
        bob.log_drop_summary()  # said once
    lines = warnings(caplog)
    assert len(lines) == 2, lines
    assert lines[1] == (
        "fleet 'fleet': dropped 4 more messages in the last 2.0 s: 4 from 'mallory' (wrong mac)"
    )


def test_a_replay_to_a_restarted_member_is_a_warning_once_per_member(
    clock: FakeClock, caplog: pytest.LogCaptureFixture
) -> None:
    # A captured message shown to a member after it restarted: its receiver cannot tell it from
    # a message sent while the hellos crossed (DEBUG only). Its sender can: the restarted
    # member asks for it, and an earlier boot of that member held a grant for it. The sender
    # says so at WARNING, once per member.
    operator = FleetAuth("fleet", "operator", KEY, clock=clock)
    a = FleetAuth("fleet", "A", KEY, clock=clock)
    settle(operator, a)
    captured = operator.seal(CHANNEL, "graph_command_t", b"start")
    assert a.open(CHANNEL, captured) is not None
    with caplog.at_level(logging.WARNING, logger="temoto.transport"):
        for _boot in range(2):  # A restarts twice; the capture is replayed to each boot
            clock.t += 1.0
            a = FleetAuth("fleet", "A", KEY, clock=clock)
            assert a.open(CHANNEL, captured) is None  # no_session: quiet at A
            settle(operator, a)  # A asks operator for it: never sent again
            assert a.stats["accepted"] == 0
    lines = [line for line in warnings(caplog) if "restarted" in line]
    assert len(lines) == 1, warnings(caplog)
    assert lines[0].startswith(
        "fleet 'fleet': 'A', restarted, was shown 1 message(s) of ours that its earlier boot"
    )
