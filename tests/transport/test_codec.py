"""temoto.transport.codec: every inner message round-trips; anything else is a DecodeError."""

from __future__ import annotations

import struct
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from temoto.errors import DecodeError, TemotoError, TransportError
from temoto.lcm_types import (
    action_ack_t,
    envelope_t,
    graph_feedback_t,
    handshake_t,
    node_state_t,
    resource_status_t,
    ris_withdraw_t,
)
from temoto.transport import codec

#: The inner types of docs/fleet.md's table.
INNER = {
    "handshake_t",
    "action_notification_t",
    "action_ack_t",
    "graph_command_t",
    "graph_command_reply_t",
    "graph_feedback_t",
    "ris_advert_t",
    "ris_request_t",
    "ris_withdraw_t",
    "resource_request_t",
    "resource_reply_t",
    "resource_release_t",
    "resource_status_t",
    "context_update_t",
    "context_request_t",
    "context_digest_t",
}

_INTS = {"int8_t": 3, "int16_t": 300, "int32_t": 70_000, "int64_t": 1 << 40, "double": 1.5}


def sample(cls: type[Any], salt: int = 0) -> Any:
    """An instance with a non-default value in every field; arrays hold two elements.

    Size fields stay 0: ``encode`` must fill them.
    """
    msg = cls()
    sizes = {dims[0] for dims in cls.__dimensions__ if dims is not None}
    for field, typename, dims in zip(
        cls.__slots__, cls.__typenames__, cls.__dimensions__, strict=True
    ):
        if field in sizes or field == "version":
            continue
        if dims is not None:
            if typename == "string":
                value: Any = [f"{field}-{salt}-{i}-ü" for i in range(2)]
            elif typename == "byte":
                value = bytes([salt % 7 + 1, 0, 255, salt % 5 + 2])
            else:
                nested = _class_of(typename)
                value = [sample(nested, salt * 10 + i + 1) for i in range(2)]
        elif typename == "string":
            value = f"{field}-{salt}-é✓"
        elif typename == "boolean":
            value = True
        else:
            value = _INTS[typename] + salt
        setattr(msg, field, value)
    return msg


def _class_of(typename: str) -> type[Any]:
    import temoto.lcm_types

    cls: type[Any] = getattr(temoto.lcm_types, typename.rsplit(".", 1)[-1])
    return cls


def as_plain(msg: Any) -> Any:
    """A message as nested dicts and lists, for comparison."""
    if isinstance(msg, list):
        return [as_plain(item) for item in msg]
    if hasattr(msg, "__slots__"):
        return {field: as_plain(getattr(msg, field)) for field in msg.__slots__}
    return msg


def encoded_samples() -> list[tuple[str, bytes]]:
    return [codec.encode(sample(cls)) for cls in codec.TYPES.values()]


# ================================================================ registry


def test_registry_holds_exactly_the_inner_types() -> None:
    assert set(codec.TYPES) == INNER
    for name, cls in codec.TYPES.items():
        assert cls.__name__ == name
        assert cls.__slots__[0] == "version"
        assert cls.__typenames__[0] == "int16_t"
    assert codec.VERSION == 1
    versions = dict.fromkeys(INNER, 1) | {"handshake_t": 2}
    assert versions == codec.VERSIONS


def test_decode_error_is_a_transport_error() -> None:
    assert issubclass(DecodeError, TransportError)
    assert issubclass(DecodeError, TemotoError)


# ================================================================ round trips


@pytest.mark.parametrize("name", sorted(INNER))
def test_every_type_round_trips_with_every_field_set(name: str) -> None:
    msg = sample(codec.TYPES[name], salt=7)
    type_name, payload = codec.encode(msg)
    assert type_name == name
    assert msg.version == codec.VERSIONS[name]
    decoded = codec.decode(type_name, payload)
    assert type(decoded) is codec.TYPES[name]
    assert as_plain(decoded) == as_plain(msg)
    # Every field really differs from a fresh instance, so the round trip proves something.
    fresh = as_plain(codec.TYPES[name]())
    for field, value in as_plain(decoded).items():
        assert value != fresh[field], field


def test_encode_fills_version_and_array_sizes_in_nested_structs_too() -> None:
    msg = graph_feedback_t()
    node = node_state_t()
    node.name, node.state = "Go_0", "RUNNING"
    msg.nodes = [node, node_state_t()]
    msg.nodes_count = 99  # stale counts are corrected, never trusted
    name, payload = codec.encode(msg)
    assert (msg.version, msg.nodes_count) == (1, 2)
    back = codec.decode(name, payload)
    assert [(n.name, n.state) for n in back.nodes] == [("Go_0", "RUNNING"), ("", "")]


def test_a_handshake_carries_its_heard_stamps_as_bytes() -> None:
    msg = handshake_t()
    msg.phase = handshake_t.READY
    msg.graph, msg.session, msg.actor, msg.stamp_us = "patrol", "s-1", "alpha", 1_700_000_000
    msg.actors = '["alpha","beta","gamma"]'
    msg.heard = struct.pack(">3q", 1_700_000_000, 1_699_999_999, 0)
    msg.heard_size = 7  # stale sizes are corrected, never trusted
    name, payload = codec.encode(msg)
    assert (msg.version, msg.heard_size) == (2, 24)
    back = codec.decode(name, payload)
    assert back.actors == '["alpha","beta","gamma"]'
    assert struct.unpack(">3q", back.heard) == (1_700_000_000, 1_699_999_999, 0)
    assert back.phase == handshake_t.READY


def test_empty_arrays_and_empty_strings_round_trip() -> None:
    msg = graph_feedback_t()
    back = codec.decode(*codec.encode(msg))
    assert back.nodes == []
    assert back.nodes_count == 0
    assert back.graph == ""
    msg.nodes = [node_state_t()]
    back = codec.decode(*codec.encode(msg))
    assert [(n.name, n.state, n.result) for n in back.nodes] == [("", "", "")]


def test_constants_are_generated() -> None:
    assert (handshake_t.JOIN, handshake_t.READY, handshake_t.LEAVE) == (1, 2, 3)
    assert (resource_status_t.OK, resource_status_t.FATAL) == (1, 5)


# ================================================================ encode refusals


@pytest.mark.parametrize("msg", [envelope_t(), node_state_t(), object(), "handshake_t"])
def test_encode_refuses_what_is_not_an_inner_message(msg: Any) -> None:
    with pytest.raises(TypeError, match="not an inner fleet message"):
        codec.encode(msg)


def test_encode_refuses_values_that_do_not_fit() -> None:
    msg = handshake_t()
    msg.phase = 1000  # int8_t
    with pytest.raises(ValueError, match="cannot encode handshake_t"):
        codec.encode(msg)
    msg = action_ack_t()
    msg.actor = None
    with pytest.raises(ValueError, match="cannot encode action_ack_t"):
        codec.encode(msg)


# ================================================================ decode refusals


@pytest.mark.parametrize("name", ["nope_t", "envelope_t", "node_state_t", ""])
def test_unknown_type_name(name: str) -> None:
    _, payload = codec.encode(sample(action_ack_t))
    with pytest.raises(DecodeError, match="unknown message type"):
        codec.decode(name, payload)


def test_payload_of_another_type_is_a_fingerprint_mismatch() -> None:
    _, payload = codec.encode(sample(action_ack_t))
    with pytest.raises(DecodeError, match=r"handshake_t: the payload is not a handshake_t.*"):
        codec.decode("handshake_t", payload)


@pytest.mark.parametrize(("name", "payload"), encoded_samples(), ids=sorted(INNER))
def test_every_truncation_is_refused(name: str, payload: bytes) -> None:
    for cut in range(len(payload)):
        with pytest.raises(DecodeError, match=name):
            codec.decode(name, payload[:cut])


def test_truncation_messages_say_what_was_wrong() -> None:
    name, payload = codec.encode(sample(action_ack_t))
    with pytest.raises(DecodeError, match="shorter than a fingerprint"):
        codec.decode(name, payload[:5])
    with pytest.raises(DecodeError, match="truncated payload"):
        codec.decode(name, payload[:-1])


def test_bytes_after_the_end_are_refused() -> None:
    name, payload = codec.encode(sample(action_ack_t))
    with pytest.raises(DecodeError, match="1 unexpected bytes after the end"):
        codec.decode(name, payload + b"\0")


@pytest.mark.parametrize("version", [0, 2, -1, 32767])
def test_unknown_version(version: int) -> None:
    msg = sample(action_ack_t)
    msg.version = version
    with pytest.raises(codec.UnsupportedVersion, match=f"version {version} is not supported"):
        codec.decode("action_ack_t", msg.encode())  # the raw encoder keeps the version


def test_a_handshake_of_the_first_format_names_both_versions() -> None:
    """A version 1 handshake_t (an older release: another definition, so another LCM
    fingerprint, 253b31dc311612e4) is refused as that version, not as an unknown payload."""
    msg = sample(handshake_t)
    _, payload = codec.encode(msg)
    old = bytearray(payload)
    old[:8] = bytes.fromhex("253b31dc311612e4")
    old[8:10] = (1).to_bytes(2, "big")
    with pytest.raises(codec.UnsupportedVersion, match=r"version 1 is not supported.*2") as err:
        codec.decode("handshake_t", bytes(old))
    assert (err.value.version, err.value.supported) == (1, 2)
    assert isinstance(err.value, DecodeError)


def test_negative_array_size_is_refused() -> None:
    msg = ris_withdraw_t()
    msg.version = codec.VERSION
    msg.servers_count = -2  # the raw encoder writes the count and no element
    with pytest.raises(DecodeError, match="negative array size servers_count = -2"):
        codec.decode("ris_withdraw_t", msg.encode())


@settings(max_examples=300, deadline=None)
@given(data=st.data())
def test_corrupted_payloads_decode_or_raise_decode_error_only(data: st.DataObject) -> None:
    name, payload = data.draw(st.sampled_from(encoded_samples()))
    buf = bytearray(payload)
    for _ in range(data.draw(st.integers(1, 4))):
        at = data.draw(st.integers(0, len(buf) - 1))
        buf[at] = data.draw(st.integers(0, 255))
    try:
        msg = codec.decode(name, bytes(buf))
    except DecodeError:
        return
    assert type(msg) is codec.TYPES[name]
