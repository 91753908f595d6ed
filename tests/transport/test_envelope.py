"""The fast envelope reader and writer agree with lcm-gen's ``envelope_t`` byte for byte."""

from __future__ import annotations

from typing import Any

from hypothesis import given, settings
from hypothesis import strategies as st

from temoto.lcm_types import envelope_t
from temoto.transport._envelope import Writer, parse

FIELDS = ("version", "fleet", "sender", "seq", "stamp_us", "type", "payload_size", "payload")
TEXT = st.text(max_size=12)  # any str LCM can encode (no lone surrogates)
INT64 = st.integers(-(2**63), 2**63 - 1)


def lcm(version: int, fleet: str, sender: str, seq: int, stamp: int, type_name: str,
        payload: bytes, mac: bytes) -> bytes:  # fmt: skip
    env: Any = envelope_t()  # type: ignore[no-untyped-call]
    env.version, env.fleet, env.sender, env.seq, env.stamp_us = version, fleet, sender, seq, stamp
    env.type, env.payload_size, env.payload = type_name, len(payload), payload
    env.mac_size, env.mac = len(mac), mac
    data: bytes = env.encode()
    return data


def lcm_canonical(data: bytes) -> Any:
    """What auth accepted before the fast reader: LCM decodes it and re-encodes it unchanged."""
    try:
        env: Any = envelope_t.decode(data)
        ok = (
            len(env.payload) == env.payload_size
            and len(env.mac) == env.mac_size
            and env.encode() == data
        )
    except Exception:
        return None
    return env if ok else None


@settings(max_examples=300)
@given(
    st.integers(-(2**15), 2**15 - 1), TEXT, TEXT, INT64, INT64, TEXT,
    st.binary(max_size=64), st.binary(max_size=80),
)  # fmt: skip
def test_the_writer_writes_what_lcm_writes_and_the_reader_reads_it_back(
    version: int, fleet: str, sender: str, seq: int, stamp: int, type_name: str,
    payload: bytes, mac: bytes,
) -> None:  # fmt: skip
    data = Writer(version, fleet, sender).write(seq, stamp, type_name, payload, mac)
    assert data == lcm(version, fleet, sender, seq, stamp, type_name, payload, mac)
    env: Any = parse(data)
    ref = envelope_t.decode(data)
    assert env is not None
    for name in (*FIELDS, "mac_size", "mac"):
        assert getattr(env, name) == getattr(ref, name), name


GOOD = lcm(2, "fleet", "alice", 7, 99, "action_ack_t", b"payload", b"m" * 16)


@settings(max_examples=500)
@given(st.data())
def test_the_reader_accepts_exactly_the_canonical_envelopes(data: st.DataObject) -> None:
    """Truncations, extensions, changed bytes and size fields: the reader and LCM agree."""
    raw = bytearray(GOOD)
    for _ in range(data.draw(st.integers(0, 3))):
        at = data.draw(st.integers(0, len(raw) - 1))
        raw[at] = data.draw(st.integers(0, 255))
    cut = data.draw(st.integers(0, len(raw) + 4))
    candidate = bytes(raw[:cut]) + (b"\0" * (cut - len(raw)) if cut > len(raw) else b"")
    ours, theirs = parse(candidate), lcm_canonical(candidate)
    assert (ours is None) == (theirs is None), candidate
    if ours is not None:
        for name in (*FIELDS, "mac_size", "mac"):
            assert getattr(ours, name) == getattr(theirs, name), name


def test_bad_utf8_and_a_missing_terminator_are_refused() -> None:
    good = lcm(2, "fleet", "bob", 1, 1, "t", b"", b"")
    assert parse(good) is not None
    assert parse(good.replace(b"bob\0", b"b\xffb\0")) is None  # LCM would read U+FFFD
    assert parse(good.replace(b"bob\0", b"bobX")) is None
    assert parse(good[:-1]) is None
    assert parse(good + b"\0") is None
    assert parse("not bytes") is None  # type: ignore[arg-type]
