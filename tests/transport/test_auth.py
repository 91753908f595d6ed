"""The fleet's security test: every way a message can be bad is refused, counted, never raised."""

from __future__ import annotations

import base64
import logging
import struct
import threading
from collections.abc import Iterator
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from temoto.lcm_types import envelope_t
from temoto.transport import (
    KEY_ENV,
    FleetAuth,
    FleetLink,
    InProcessTransport,
    Opened,
    key_from_env,
    key_from_text,
)
from temoto.transport.auth import HELLO_CHANNEL, REPLAY_WINDOW

KEY = bytes(range(32))
OTHER_KEY = bytes(range(1, 33))
T0 = 1_750_000_000.0
CHANNEL = "TEMOTO_NOTIFY"
PAYLOAD = b"<inner message payload>"


class FakeClock:
    def __init__(self, t: float = T0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


@pytest.fixture
def clock() -> FakeClock:
    return FakeClock()


def exchange(*members: FleetAuth, clock: FakeClock | None = None) -> list[tuple[str, bytes]]:
    """Deliver what each member wants published (hellos, re-sent copies) to every other member
    until nothing is left; returns the data messages delivered (not hellos)."""
    data: list[tuple[str, bytes]] = []
    for _ in range(50):
        moved = False
        for member in members:
            due = member.hello_due_in()
            if due and clock is not None:
                clock.t += due
            for channel, out in member.take_outgoing():
                moved = True
                if channel != HELLO_CHANNEL:
                    data.append((channel, out))
                for other in members:
                    if other is not member:
                        other.open(channel, out)
        if not moved:
            return data
    raise AssertionError("the hellos never settled")


@pytest.fixture
def alice(clock: FakeClock) -> FleetAuth:
    return FleetAuth("fleet", "alice", KEY, clock=clock)


@pytest.fixture
def bob(clock: FakeClock, alice: FleetAuth) -> FleetAuth:
    bob = FleetAuth("fleet", "bob", KEY, clock=clock)
    exchange(alice, bob, clock=clock)
    return bob


def drops(auth: FleetAuth) -> dict[str, int]:
    return {reason: n for reason, n in auth.stats.items() if n and reason != "accepted"}


def refused(receiver: FleetAuth, data: bytes, reason: str, channel: str = CHANNEL) -> None:
    before = receiver.stats
    assert receiver.open(channel, data) is None
    after = receiver.stats
    changed = {k: after[k] - before[k] for k in after if after[k] != before[k]}
    assert changed == {reason: 1}, f"expected one {reason!r} drop, counters moved: {changed}"


def flip(data: bytes, index: int, mask: int = 0x01) -> bytes:
    return data[:index] + bytes([data[index] ^ mask]) + data[index + 1 :]


def decoded(data: bytes) -> Any:  # the generated class is untyped
    return envelope_t.decode(data)


# --- the good case ----------------------------------------------------------------------------


def test_a_sealed_message_is_accepted_with_its_content(alice: FleetAuth, bob: FleetAuth) -> None:
    data = alice.seal(CHANNEL, "action_ack_t", PAYLOAD)
    before = bob.stats
    opened = bob.open(CHANNEL, data)
    env = decoded(data)
    assert opened == Opened(
        channel=CHANNEL,
        sender="alice",
        type="action_ack_t",
        payload=PAYLOAD,
        seq=env.seq,
        stamp_us=env.stamp_us,
    )
    assert bob.stats == {**before, "accepted": before["accepted"] + 1}


def test_the_envelope_follows_the_documented_format(alice: FleetAuth, bob: FleetAuth) -> None:
    data = alice.seal(CHANNEL, "handshake_t", PAYLOAD)
    env = decoded(data)
    assert (env.version, env.fleet, env.sender, env.type) == (2, "fleet", "alice", "handshake_t")
    # the payload is encrypted (same size); the mac field holds the 16-byte Poly1305 tag
    assert env.payload_size == len(PAYLOAD)
    assert env.payload != PAYLOAD
    assert PAYLOAD not in data
    assert env.mac_size == 16
    assert env.stamp_us > 0  # the sender's session id
    assert env.seq >= 1


def test_an_insecure_fleet_exchanges_unsigned_envelopes(clock: FakeClock) -> None:
    one = FleetAuth("lab", "one", None, insecure=True, clock=clock)
    two = FleetAuth("lab", "two", None, insecure=True, clock=clock)
    data = one.seal(CHANNEL, "t", PAYLOAD)
    assert decoded(data).mac_size == 0
    opened = two.open(CHANNEL, data)
    assert opened is not None
    assert opened.payload == PAYLOAD
    assert one.insecure
    assert two.open(CHANNEL, data) is None  # replay protection works without a key too


# --- forged and tampered ------------------------------------------------------------------------


def test_a_member_with_another_key_is_never_granted_a_session(
    clock: FakeClock, bob: FleetAuth
) -> None:
    mallory = FleetAuth("fleet", "alice", OTHER_KEY, clock=clock)
    (channel, hello), *_ = mallory.take_outgoing()
    refused(bob, hello, "forged", channel=channel)  # its hello: wrong mac
    refused(bob, mallory.seal(CHANNEL, "t", PAYLOAD), "no_session")  # its data: no key for it


def test_a_flipped_payload_byte_is_forged(alice: FleetAuth, bob: FleetAuth) -> None:
    data = alice.seal(CHANNEL, "t", PAYLOAD)
    start = data.index(decoded(data).payload)
    for index in (start, start + len(PAYLOAD) // 2, start + len(PAYLOAD) - 1):
        refused(bob, flip(data, index), "forged")
    assert bob.open(CHANNEL, data) is not None  # the original still passes


@pytest.mark.parametrize(
    ("field", "reason"),
    [("seq", "forged"), ("stamp_us", "no_session"), ("type", "forged"), ("sender", "no_session")],
)
def test_a_changed_header_field_is_refused(
    alice: FleetAuth, bob: FleetAuth, field: str, reason: str
) -> None:
    data = alice.seal(CHANNEL, "notify_t", PAYLOAD)
    env = decoded(data)
    needle = {
        "seq": struct.pack(">q", env.seq),
        "stamp_us": struct.pack(">q", env.stamp_us),
        "type": b"notify_t\0",
        "sender": b"alice\0",
    }[field]
    # The last byte of a number (1 µs or one sequence number off), the first of a string.
    index = data.index(needle) + (len(needle) - 1 if field in ("seq", "stamp_us") else 0)
    refused(bob, flip(data, index), reason)


def test_a_changed_mac_byte_is_forged(alice: FleetAuth, bob: FleetAuth) -> None:
    data = alice.seal(CHANNEL, "t", PAYLOAD)
    for index in (len(data) - 16, len(data) - 1):
        refused(bob, flip(data, index, 0x80), "forged")


def test_a_mac_of_the_wrong_size_is_forged(alice: FleetAuth, bob: FleetAuth) -> None:
    env = decoded(alice.seal(CHANNEL, "t", PAYLOAD))
    env.mac_size, env.mac = 15, env.mac[:15]
    refused(bob, env.encode(), "forged")


def test_the_wrong_version_is_refused(alice: FleetAuth, bob: FleetAuth) -> None:
    data = alice.seal(CHANNEL, "t", PAYLOAD)
    refused(bob, flip(data, 9), "version")  # the low byte of int16 version after the fingerprint


def test_every_single_bit_flip_is_refused(alice: FleetAuth, bob: FleetAuth) -> None:
    data = alice.seal(CHANNEL, "t", PAYLOAD)
    allowed = {"garbage", "version", "fleet", "forged", "no_session", "not_for_us"}
    for index in range(len(data)):
        for mask in (0x01, 0x80):
            before = bob.stats
            assert bob.open(CHANNEL, flip(data, index, mask)) is None, (index, mask)
            after = bob.stats
            (reason,) = [k for k in after if after[k] != before[k]]
            assert reason in allowed, (index, mask, reason)
    assert bob.stats["accepted"] == 0


def test_the_mac_covers_the_channel(alice: FleetAuth, bob: FleetAuth) -> None:
    data = alice.seal("TEMOTO_GRAPH_CMD", "graph_command_t", PAYLOAD)
    refused(bob, data, "forged", channel="TEMOTO_NOTIFY")
    assert bob.open("TEMOTO_GRAPH_CMD", data) is not None


# --- replays and reordering ---------------------------------------------------------------------


def test_the_same_message_twice_is_replayed(alice: FleetAuth, bob: FleetAuth) -> None:
    data = alice.seal(CHANNEL, "t", PAYLOAD)
    assert bob.open(CHANNEL, data) is not None
    refused(bob, data, "replayed")
    refused(bob, data, "replayed")


def test_reordering_inside_the_window_is_accepted_once(alice: FleetAuth, bob: FleetAuth) -> None:
    sealed = [alice.seal(CHANNEL, "t", bytes([i])) for i in range(REPLAY_WINDOW)]
    order = [REPLAY_WINDOW - 1, 0, 40, 3, 2, 63 - 10, 1]
    order += [i for i in range(REPLAY_WINDOW) if i not in order]
    for i in order:
        opened = bob.open(CHANNEL, sealed[i])
        assert opened is not None, i
        assert opened.payload == bytes([i])
    for i in (0, 31, REPLAY_WINDOW - 1):
        refused(bob, sealed[i], "replayed")
    assert bob.stats["accepted"] == REPLAY_WINDOW


def test_a_message_older_than_the_window_is_replayed(alice: FleetAuth, bob: FleetAuth) -> None:
    sealed = [alice.seal(CHANNEL, "t", b"") for _ in range(REPLAY_WINDOW + 1)]
    assert bob.open(CHANNEL, sealed[-1]) is not None
    refused(bob, sealed[0], "replayed")  # 64 behind the highest: never seen, but too old
    assert bob.open(CHANNEL, sealed[1]) is not None  # 63 behind: still inside


def test_a_big_jump_forward_clears_the_window(alice: FleetAuth, bob: FleetAuth) -> None:
    first = alice.seal(CHANNEL, "t", b"")
    skipped = [alice.seal(CHANNEL, "t", b"") for _ in range(200)]
    assert bob.open(CHANNEL, first) is not None
    assert bob.open(CHANNEL, skipped[-1]) is not None
    refused(bob, skipped[0], "replayed")
    assert bob.open(CHANNEL, skipped[-2]) is not None
    refused(bob, skipped[-2], "replayed")


def test_a_restarted_sender_continues_above_its_old_numbers(clock: FakeClock) -> None:
    bob = FleetAuth("fleet", "bob", None, insecure=True, clock=clock)
    before = FleetAuth("fleet", "alice", None, insecure=True, clock=clock)
    for _ in range(100):
        assert bob.open(CHANNEL, before.seal(CHANNEL, "t", b"")) is not None
    clock.t += 1.0  # the restart takes a second: far more microseconds than messages sent
    after = FleetAuth("fleet", "alice", None, insecure=True, clock=clock)
    opened = bob.open(CHANNEL, after.seal(CHANNEL, "t", b""))
    assert opened is not None
    assert opened.seq == round(clock.t * 1e6)


def test_a_restarted_keyed_sender_gets_a_new_session(clock: FakeClock, bob: FleetAuth) -> None:
    before = FleetAuth("fleet", "alice", KEY, clock=clock)
    exchange(before, bob, clock=clock)
    old = before.seal(CHANNEL, "t", b"")
    assert bob.open(CHANNEL, old) is not None
    after = FleetAuth("fleet", "alice", KEY, clock=clock)
    exchange(after, bob, clock=clock)
    opened = bob.open(CHANNEL, after.seal(CHANNEL, "t", b""))
    assert opened is not None
    assert opened.stamp_us != decoded(old).stamp_us  # another session id
    refused(bob, old, "replayed")


def test_replay_state_is_kept_per_sender(clock: FakeClock, bob: FleetAuth) -> None:
    carol = FleetAuth("fleet", "carol", KEY, clock=clock)
    dave = FleetAuth("fleet", "dave", KEY, clock=clock)
    exchange(carol, dave, bob, clock=clock)
    from_carol, from_dave = carol.seal(CHANNEL, "t", b""), dave.seal(CHANNEL, "t", b"")
    assert decoded(from_carol).seq == decoded(from_dave).seq
    assert bob.open(CHANNEL, from_carol) is not None
    assert bob.open(CHANNEL, from_dave) is not None


def test_senders_not_heard_for_ten_windows_are_forgotten(clock: FakeClock) -> None:
    bob = FleetAuth("fleet", "bob", None, insecure=True, window_s=1.0, clock=clock)
    for i in range(50):
        sender = FleetAuth("fleet", f"robot{i}", None, insecure=True, clock=clock)
        assert bob.open(CHANNEL, sender.seal(CHANNEL, "t", b"")) is not None
    assert len(bob._peers) == 50
    clock.t += 10.5
    late = FleetAuth("fleet", "late", None, insecure=True, clock=clock)
    assert bob.open(CHANNEL, late.seal(CHANNEL, "t", b"")) is not None
    assert set(bob._peers) == {"late"}


def test_a_forgotten_senders_old_message_is_stale_not_accepted(clock: FakeClock) -> None:
    alice = FleetAuth("fleet", "alice", None, insecure=True, clock=clock)
    bob = FleetAuth("fleet", "bob", None, insecure=True, clock=clock)
    data = alice.seal(CHANNEL, "t", b"")
    assert bob.open(CHANNEL, data) is not None
    clock.t += 10 * bob.window_s + 1
    bob._prune(clock.t)
    assert "alice" not in bob._peers
    refused(bob, data, "stale")


# --- garbage ------------------------------------------------------------------------------------


@settings(max_examples=300, deadline=None)
@given(st.binary())
def test_random_bytes_are_garbage_and_never_raise(data: bytes) -> None:
    receiver = FleetAuth("fleet", "bob", KEY, clock=FakeClock())
    assert receiver.open(CHANNEL, data) is None
    assert receiver.stats["garbage"] == 1


@settings(max_examples=300, deadline=None)
@given(st.binary())
def test_random_bytes_after_the_envelope_fingerprint_never_pass(tail: bytes) -> None:
    receiver = FleetAuth("fleet", "bob", KEY, clock=FakeClock())
    fingerprint: bytes = envelope_t._get_packed_fingerprint()  # type: ignore[no-untyped-call]
    assert receiver.open(CHANNEL, fingerprint + tail) is None
    stats = receiver.stats
    assert stats["accepted"] == 0
    assert sum(stats.values()) == 1


def test_every_truncation_and_any_trailing_bytes_are_garbage(
    alice: FleetAuth, bob: FleetAuth
) -> None:
    data = alice.seal(CHANNEL, "t", PAYLOAD)
    for length in range(len(data)):
        refused(bob, data[:length], "garbage")
    for tail in (b"\0", b"x" * 100):
        refused(bob, data + tail, "garbage")
    assert bob.open(CHANNEL, data) is not None


def test_a_non_canonical_string_is_garbage(alice: FleetAuth, bob: FleetAuth) -> None:
    data = alice.seal(CHANNEL, "t", PAYLOAD)
    # Replace the NUL that ends the type string: LCM's decoder would not notice.
    index = data.index(b"t\0") + 1
    refused(bob, flip(data, index, 0x41), "garbage")


# --- other fleets, ourselves, time, signatures -------------------------------------------------


def test_another_fleets_message_is_refused(clock: FakeClock, bob: FleetAuth) -> None:
    stranger = FleetAuth("other-fleet", "carol", KEY, clock=clock)
    refused(bob, stranger.seal(CHANNEL, "t", PAYLOAD), "fleet")


def test_our_own_message_echoed_back_is_refused(alice: FleetAuth) -> None:
    refused(alice, alice.seal(CHANNEL, "t", PAYLOAD), "self")


@pytest.mark.parametrize("skew_s", [-31.0, 31.0, -3600.0, 1e6])
def test_an_insecure_stamp_outside_the_window_is_stale(clock: FakeClock, skew_s: float) -> None:
    bob = FleetAuth("fleet", "bob", None, insecure=True, clock=clock)
    sender_clock = FakeClock(clock.t + skew_s)
    skewed = FleetAuth("fleet", "alice", None, insecure=True, clock=sender_clock)
    refused(bob, skewed.seal(CHANNEL, "t", PAYLOAD), "stale")


@pytest.mark.parametrize("skew_s", [-29.0, 0.0, 29.0])
def test_an_insecure_stamp_inside_the_window_is_accepted(clock: FakeClock, skew_s: float) -> None:
    bob = FleetAuth("fleet", "bob", None, insecure=True, clock=clock)
    skewed = FleetAuth("fleet", "alice", None, insecure=True, clock=FakeClock(clock.t + skew_s))
    assert bob.open(CHANNEL, skewed.seal(CHANNEL, "t", PAYLOAD)) is not None


@pytest.mark.parametrize("skew_s", [-1e6, -31.0, 0.0, 29.0, 1e6])
def test_keyed_fleets_ignore_the_clocks(clock: FakeClock, bob: FleetAuth, skew_s: float) -> None:
    skewed = FleetAuth("fleet", "carol", KEY, clock=FakeClock(clock.t + skew_s))
    exchange(skewed, bob)
    assert bob.open(CHANNEL, skewed.seal(CHANNEL, "t", PAYLOAD)) is not None


def test_a_captured_message_never_opens_at_a_restarted_receiver(
    clock: FakeClock, alice: FleetAuth, bob: FleetAuth
) -> None:
    data = alice.seal(CHANNEL, "t", PAYLOAD)
    assert bob.open(CHANNEL, data) is not None
    restarted = FleetAuth("fleet", "bob", KEY, clock=clock)  # lost its replay state
    refused(restarted, data, "no_session")
    exchange(alice, restarted, clock=clock)  # alice grants its session to the new boot
    refused(restarted, data, "replayed")  # at or below the floor of that grant
    assert restarted.open(CHANNEL, alice.seal(CHANNEL, "t", PAYLOAD)) is not None


def test_an_unsigned_message_into_a_keyed_fleet_is_refused(
    clock: FakeClock, bob: FleetAuth
) -> None:
    insecure = FleetAuth("fleet", "alice", None, insecure=True, clock=clock)
    refused(bob, insecure.seal(CHANNEL, "t", PAYLOAD), "unsigned")


def test_a_signed_message_into_an_insecure_fleet_is_refused(
    clock: FakeClock, alice: FleetAuth
) -> None:
    insecure = FleetAuth("fleet", "bob", None, insecure=True, clock=clock)
    refused(insecure, alice.seal(CHANNEL, "t", PAYLOAD), "unexpected_mac")


def test_checks_run_in_the_documented_order(clock: FakeClock, alice: FleetAuth) -> None:
    # Another fleet's stale, unsigned message is counted as "fleet": the first check that fails.
    stranger = FleetAuth("other", "carol", None, insecure=True, clock=FakeClock(clock.t - 99))
    refused(alice, stranger.seal(CHANNEL, "t", b""), "fleet")
    # Our own name on a forged message: "self" comes before the mac.
    impostor = FleetAuth("fleet", "alice", OTHER_KEY, clock=clock)
    refused(alice, impostor.seal(CHANNEL, "t", b""), "self")


# --- logging --------------------------------------------------------------------------------------


def test_echoes_and_other_fleets_are_debug_logged_at_most_once_per_reason_per_second(
    alice: FleetAuth, clock: FakeClock, caplog: pytest.LogCaptureFixture
) -> None:
    # Normal on a shared network: no warning (tests/transport/test_auth_drop_log.py has those).
    own = alice.seal(CHANNEL, "t", PAYLOAD)
    stranger = FleetAuth("other", "carol", KEY, clock=clock).seal(CHANNEL, "t", PAYLOAD)
    with caplog.at_level(logging.DEBUG, logger="temoto.transport"):
        for _ in range(10):
            alice.open(CHANNEL, own)
        for _ in range(10):
            alice.open(CHANNEL, stranger)
    lines = [r.getMessage() for r in caplog.records if r.levelno == logging.DEBUG]
    assert len(lines) == 2, lines
    assert "'alice'" in lines[0]
    assert "our own message" in lines[0]
    assert "'carol'" in lines[1]
    assert "another fleet" in lines[1]
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert alice.stats["self"] == alice.stats["fleet"] == 10


def test_an_insecure_member_warns_once_when_created(
    clock: FakeClock, caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.WARNING, logger="temoto.transport"):
        auth = FleetAuth("lab", "one", None, insecure=True, clock=clock)
        auth.open(CHANNEL, auth.seal(CHANNEL, "t", b""))
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1
    assert "INSECURE" in warnings[0].getMessage()
    assert KEY_ENV in warnings[0].getMessage()


# --- sequence numbers -----------------------------------------------------------------------------


def test_sequence_numbers_start_at_boot_time_and_strictly_increase_across_threads(
    clock: FakeClock,
) -> None:
    alice = FleetAuth("fleet", "alice", None, insecure=True, clock=clock)
    per_thread: dict[int, list[int]] = {}
    start = threading.Barrier(8)

    def seal_many(n: int) -> None:
        start.wait(5)
        per_thread[n] = [decoded(alice.seal(CHANNEL, "t", b"")).seq for _ in range(300)]

    threads = [threading.Thread(target=seal_many, args=(n,)) for n in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(30)
    seqs = [s for values in per_thread.values() for s in values]
    assert len(seqs) == 8 * 300
    assert sorted(seqs) == list(range(round(T0 * 1e6), round(T0 * 1e6) + len(seqs)))
    for values in per_thread.values():
        assert values == sorted(values)


# --- keys and construction ------------------------------------------------------------------------


def test_keys_are_read_from_hex_or_base64() -> None:
    key = bytes(range(100, 148))
    assert key_from_text(key.hex()) == key
    assert key_from_text(key.hex().upper()) == key
    assert key_from_text(f"  {key.hex()[:40]}\n{key.hex()[40:]}  ") == key
    assert key_from_text(base64.b64encode(key).decode()) == key
    assert key_from_text(base64.urlsafe_b64encode(key).decode()) == key
    odd = bytes(range(33))
    assert key_from_text(base64.b64encode(odd).decode().rstrip("=")) == odd


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("", "empty"),
        ("   \n", "empty"),
        ("not a key!", "neither hex nor base64"),
        ("ab" * 16, "16 bytes long; at least 32"),
        (base64.b64encode(b"x" * 31).decode(), "31 bytes long; at least 32"),
    ],
)
def test_bad_keys_are_refused_clearly(text: str, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        key_from_text(text)


def test_the_key_comes_from_the_environment() -> None:
    assert key_from_env({}) is None
    assert key_from_env({KEY_ENV: "  "}) is None
    assert key_from_env({KEY_ENV: KEY.hex()}) == KEY
    with pytest.raises(ValueError, match=f"^{KEY_ENV}: the fleet key is 3 bytes long"):
        key_from_env({KEY_ENV: "abcdef"})


def test_key_from_env_reads_os_environ(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(KEY_ENV, KEY.hex())
    assert key_from_env() == KEY
    monkeypatch.delenv(KEY_ENV)
    assert key_from_env() is None


def test_a_member_without_a_key_must_be_explicitly_insecure() -> None:
    with pytest.raises(ValueError, match="--insecure"):
        FleetAuth("fleet", "bob", None)


@pytest.mark.parametrize(
    ("kwargs", "error", "message"),
    [
        ({"fleet": ""}, ValueError, "fleet name"),
        ({"sender": ""}, ValueError, "sender name"),
        ({"key": b"short"}, ValueError, "5 bytes long"),
        ({"key": KEY.hex()}, TypeError, "bytes"),
        ({"insecure": True}, ValueError, "exclude each other"),
        ({"window_s": 0.0}, ValueError, "window_s"),
        ({"window_s": float("nan")}, ValueError, "window_s"),
    ],
)
def test_bad_construction_is_refused(
    kwargs: dict[str, object], error: type[Exception], message: str
) -> None:
    args: dict[str, object] = {"fleet": "fleet", "sender": "bob", "key": KEY, **kwargs}
    with pytest.raises(error, match=message):
        FleetAuth(**args)  # type: ignore[arg-type]


def test_seal_refuses_a_payload_that_is_not_bytes(alice: FleetAuth) -> None:
    with pytest.raises(TypeError, match="payload"):
        alice.seal(CHANNEL, "t", "text")  # type: ignore[arg-type]


# --- FleetLink --------------------------------------------------------------------------------


@pytest.fixture
def inproc(request: pytest.FixtureRequest) -> Iterator[InProcessTransport]:
    with InProcessTransport(f"auth-{request.node.name}") as t:
        yield t


def test_a_fleet_link_delivers_good_messages_and_counts_the_rest(
    inproc: InProcessTransport, clock: FakeClock, caplog: pytest.LogCaptureFixture
) -> None:
    alice = FleetLink(inproc, FleetAuth("fleet", "alice", KEY, clock=clock))
    with InProcessTransport(inproc.bus) as other:
        bob = FleetLink(other, FleetAuth("fleet", "bob", KEY, clock=clock))
        got: list[Opened] = []
        done = threading.Event()

        def on_message(opened: Opened) -> None:
            if opened.payload == b"boom":
                raise RuntimeError("handler bug")
            got.append(opened)
            if opened.payload == b"last":
                done.set()

        bob.listen(CHANNEL, on_message, queue_capacity=100)
        with caplog.at_level(logging.ERROR, logger="temoto.transport"):
            alice.send(CHANNEL, "t", b"first")
            inproc.publish(CHANNEL, b"garbage")
            alice.send(CHANNEL, "t", b"boom")
            alice.send(CHANNEL, "t", b"last")
            assert done.wait(5)
        assert [o.payload for o in got] == [b"first", b"last"]
        stats = bob.stats
        assert stats["accepted"] == 3
        assert stats["garbage"] == 1
        assert stats["handler_error"] == 1
        assert other.handler_errors == 0  # contained by the link, not the transport
        assert "handler bug" in caplog.text
        assert "FleetLink" in repr(bob)
