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
from temoto.transport.auth import _MAX_FIRST_LINES, DROP_SUMMARY_S

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


def replayed(clock: FakeClock, bob: FleetAuth) -> bytes:
    data = FleetAuth("fleet", "alice", KEY, clock=clock).seal(CHANNEL, "t", b"x")
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
        lambda c, b: FleetAuth("fleet", "alice", OTHER_KEY, clock=c).seal(CHANNEL, "t", b"x"),
        "alice",
        "wrong mac; sealed with another fleet key",
    ),
    "stale": (
        lambda c, b: FleetAuth("fleet", "alice", KEY, clock=FakeClock(c.t - 45)).seal(
            CHANNEL, "t", b"x"
        ),
        "alice",
        "(-45.0 s from our clock, window ±30 s); are the clocks synchronised",
    ),
    "replayed": (replayed, "alice", "already seen or too old"),
}


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
    quiet = {"self", "fleet", "unexpected_mac"}  # the last one has its own test above
    assert set(CASES) == set(DROP_REASONS) - quiet


def test_repeats_are_summarised_with_counts_at_most_once_per_interval(
    clock: FakeClock, bob: FleetAuth, caplog: pytest.LogCaptureFixture
) -> None:
    mallory = FleetAuth("fleet", "mallory", OTHER_KEY, clock=clock)

    def drops(n: int, step: float) -> None:
        for _ in range(n):
            bob.open(CHANNEL, mallory.seal(CHANNEL, "t", b"x"))
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
    carol = FleetAuth("fleet", "carol", OTHER_KEY, clock=clock)
    dave = FleetAuth("fleet", "dave", OTHER_KEY, clock=clock)
    old = FleetAuth("fleet", "carol", KEY, clock=FakeClock(clock.t - 100))
    with caplog.at_level(logging.WARNING, logger="temoto.transport"):
        for auth in (carol, dave, carol, dave, old, old):
            bob.open(CHANNEL, auth.seal(CHANNEL, "t", b"x"))
    lines = warnings(caplog)
    assert len(lines) == 3, lines
    assert "from 'carol': wrong mac" in lines[0]
    assert "from 'dave': wrong mac" in lines[1]
    assert "from 'carol': time stamp outside the window" in lines[2]


def test_invented_sender_names_cannot_flood_the_log(
    clock: FakeClock, bob: FleetAuth, caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.WARNING, logger="temoto.transport"):
        for i in range(_MAX_FIRST_LINES + 100):
            fake = FleetAuth("fleet", f"stranger-{i}", OTHER_KEY, clock=clock)
            bob.open(CHANNEL, fake.seal(CHANNEL, "t", b"x"))
        assert len(warnings(caplog)) == _MAX_FIRST_LINES
        clock.t += DROP_SUMMARY_S
        bob.open(CHANNEL, fake.seal(CHANNEL, "t", b"x"))
    lines = warnings(caplog)
    assert len(lines) == _MAX_FIRST_LINES + 1
    assert "dropped 101 more messages" in lines[-1]
    assert "other senders/reasons" in lines[-1]


def test_a_long_claimed_name_is_cut_and_escaped(
    clock: FakeClock, bob: FleetAuth, caplog: pytest.LogCaptureFixture
) -> None:
    name = "evil\n" + "x" * 500
    fake = FleetAuth("fleet", name, OTHER_KEY, clock=clock)
    with caplog.at_level(logging.WARNING, logger="temoto.transport"):
        bob.open(CHANNEL, fake.seal(CHANNEL, "t", b"x"))
    (line,) = warnings(caplog)
    assert "\n" not in line
    assert "'evil\\nxxx" in line
    assert "x" * 100 not in line


def test_the_summary_of_the_last_drops_can_be_logged_at_the_end(
    clock: FakeClock, bob: FleetAuth, caplog: pytest.LogCaptureFixture
) -> None:
    mallory = FleetAuth("fleet", "mallory", OTHER_KEY, clock=clock)
    with caplog.at_level(logging.WARNING, logger="temoto.transport"):
        bob.log_drop_summary()  # nothing held back: nothing logged
        for _ in range(5):
            bob.open(CHANNEL, mallory.seal(CHANNEL, "t", b"x"))
        clock.t += 2
        bob.log_drop_summary()
        bob.log_drop_summary()  # said once
    lines = warnings(caplog)
    assert len(lines) == 2, lines
    assert lines[1] == (
        "fleet 'fleet': dropped 4 more messages in the last 2 s: 4 from 'mallory' (wrong mac)"
    )
