"""Authentication drops are visible: WARNING lines naming the claimed sender and the reason.

The first drop of each sender and reason is logged at once; later ones are summarised, with
counts, at most once per ``DROP_SUMMARY_S`` seconds of the member's (injected) clock.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import pytest

from temoto.lcm_types import envelope_t
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


def test_repeats_are_summarised_with_counts_at_most_once_per_interval(
    clock: FakeClock, bob: FleetAuth, caplog: pytest.LogCaptureFixture
) -> None:
    mallory = member("mallory", clock, bob)

    def drops(n: int, step: float) -> None:
        for _ in range(n):
            bob.open(CHANNEL, tampered(mallory))
            clock.t += step

    with caplog.at_level(logging.WARNING, logger="temoto.transport"):
        drops(50, DROP_SUMMARY_S / 100)  # t = 0 .. 0.49 intervals
        assert len(warnings(caplog)) == 1  # the first, at once; 49 held back
        clock.t = T0 + DROP_SUMMARY_S
        drops(1, 0.0)  # one interval after the first line: the summary
        assert len(warnings(caplog)) == 2
        drops(30, DROP_SUMMARY_S / 100)  # inside the next interval: held back
        assert len(warnings(caplog)) == 2
        clock.t = T0 + 2 * DROP_SUMMARY_S
        drops(1, 0.0)
    lines = warnings(caplog)
    assert len(lines) == 3, lines
    assert "from 'mallory': wrong mac" in lines[0]
    assert lines[1] == (
        "fleet 'fleet': dropped 50 more messages in the last 10 s: 50 from 'mallory' (wrong mac)"
    )
    assert lines[2].startswith("fleet 'fleet': dropped 31 more messages in the last 10 s")
    assert bob.stats["forged"] == 82


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
        "fleet 'fleet': dropped 4 more messages in the last 2 s: 4 from 'mallory' (wrong mac)"
    )
