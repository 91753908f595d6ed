"""Attacks on every channel a fleet member listens on: all dropped, all counted, no crash.

The members are a whole instance (every fleet service it runs) and a commander (the CLI's
side). Each channel they subscribe to gets garbage, a message sealed with another key, a
captured message replayed, a tampered copy, and an authentic envelope whose inner message is
garbage; afterwards the instance still does its work.
"""

from __future__ import annotations

import itertools
import json
from collections.abc import Iterator
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from temoto.fleet.control import GraphCommander
from temoto.instance import Instance
from temoto.transport.auth import DROP_REASONS, HELLO_CHANNEL, FleetAuth
from temoto.transport.inprocess import InProcessTransport
from temoto.transport.link import FleetLink

ROOT = Path(__file__).resolve().parents[2]
ACTIONS = ROOT / "examples" / "actions" / "conformance"
KEY = bytes(range(32))
OTHER_KEY = bytes(range(1, 33))
WAIT = 10.0
_buses = itertools.count()


class Fleet:
    def __init__(self, stack: ExitStack) -> None:
        self.bus = f"security-{next(_buses)}"
        self.instance_transport = InProcessTransport(self.bus)
        self.instance = stack.enter_context(
            Instance("A", transport=self.instance_transport, key=KEY, actions=[ACTIONS])
        )
        self.cli_transport = stack.enter_context(InProcessTransport(self.bus))
        self.cli_link = FleetLink(self.cli_transport, FleetAuth("temoto", "cli", KEY))
        self.commander = stack.enter_context(GraphCommander(self.cli_link, resend_s=0.05))
        self.attacker = stack.enter_context(InProcessTransport(self.bus))

    @property
    def channels(self) -> list[str]:
        """The data channels the members listen to (not the hellos')."""
        both = self.instance_transport.channels | self.cli_transport.channels
        return sorted(c for c in both if not c.startswith(HELLO_CHANNEL))

    def member(self, stack: ExitStack, name: str = "B") -> FleetAuth:
        """An authentic member on its own transport whose hellos crossed with both members'."""
        link = FleetLink(
            stack.enter_context(InProcessTransport(self.bus)), FleetAuth("temoto", name, KEY)
        )
        assert link.wait_for_peers(["A", "cli"], WAIT)
        assert self.instance.link.wait_for_peers([name], WAIT)
        assert self.cli_link.wait_for_peers([name], WAIT)
        return link.auth

    def links(self) -> list[FleetLink]:
        return [self.instance.link, self.cli_link]

    def drops(self) -> dict[str, int]:
        """The drop counters of every member, summed."""
        total = dict.fromkeys((*DROP_REASONS, "handler_error"), 0)
        for link in self.links():
            for name, value in link.stats.items():
                if name in total:
                    total[name] += value
        return total

    def quiet(self) -> None:
        """Wait until every member handled everything published so far."""
        for transport in (self.instance_transport, self.cli_transport):
            assert transport.flush(WAIT)


@pytest.fixture
def fleet() -> Iterator[Fleet]:
    with ExitStack() as stack:
        yield Fleet(stack)


def relay_graph() -> dict[str, Any]:
    return {
        "graph_name": "relay",
        "graph_entry": [{"name": "TaRelayString", "instance_id": 0}],
        "graph_exit": [{"name": "TaRelayString", "instance_id": 0}],
        "actions": [
            {
                "name": "TaRelayString",
                "instance_id": 0,
                "type": "sync",
                "input_parameters": {"string_in": {"pvf_type": "string", "pvf_value": "x"}},
                "output_parameters": {"string_out": {"pvf_type": "string"}},
            }
        ],
    }


def decode_errors(fleet: Fleet) -> int:
    """What the services dropped as undecodable inner messages."""
    services = (
        fleet.instance.actors,
        fleet.instance.control,
        fleet.instance.ris,
        fleet.instance.resources,
        fleet.instance.context,
        fleet.commander,
    )
    return sum(service.stats["decode_errors"] for service in services)


def test_every_attack_on_every_channel_is_dropped_and_counted(fleet: Fleet) -> None:
    channels = fleet.channels
    # the instance's services and the commander's: all of them are attacked
    assert {"TEMOTO_HANDSHAKE", "TEMOTO_NOTIFY", "TEMOTO_GRAPH_CMD"} <= set(channels)
    assert {"TEMOTO_GRAPH_REPLY", "TEMOTO_GRAPH_FEEDBACK"} <= set(channels)
    assert {"TEMOTO_RIS", "TEMOTO_RESOURCE", "TEMOTO_CONTEXT"} <= set(channels)
    with ExitStack() as stack:
        member = fleet.member(stack)  # an authentic member whose messages we capture
        stranger = FleetAuth("temoto", "B", OTHER_KEY)
        fleet.quiet()
        before = fleet.drops()
        inner_before = decode_errors(fleet)
        for channel in channels:
            fleet.attacker.publish(channel, b"\x00" * 7 + b"garbage that is no envelope")
            fleet.attacker.publish(channel, stranger.seal(channel, "graph_command_t", b"\x01"))
            captured = member.seal(channel, "graph_command_t", b"\x00\x01 not lcm")
            fleet.attacker.publish(channel, captured)  # authentic: its inner message is garbage
            fleet.attacker.publish(channel, captured)  # the same bytes again
            tampered = bytearray(member.seal(channel, "graph_command_t", b"\x00\x01 not lcm"))
            tampered[len(tampered) // 2] ^= 0x01
            fleet.attacker.publish(channel, bytes(tampered))
        # the hello channel, which both members listen to
        ((_, stranger_hello),) = stranger.take_outgoing()
        fleet.attacker.publish(HELLO_CHANNEL, b"\x00" * 7 + b"garbage that is no envelope")
        fleet.attacker.publish(HELLO_CHANNEL, stranger_hello)
        fleet.quiet()
    after = fleet.drops()
    n = len(channels)  # one member listens on each channel
    assert after["garbage"] - before["garbage"] == n + 2
    assert after["forged"] - before["forged"] == n + 2  # a flipped bit; the stranger's hello
    assert after["no_session"] - before["no_session"] >= n  # the stranger's data: no key for it
    assert after["replayed"] - before["replayed"] == n
    assert after["handler_error"] == 0
    assert decode_errors(fleet) - inner_before == n
    # and the instance still does what an authentic commander asks
    out = fleet.commander.command("start", ["A"], graph_json=relay_graph(), timeout=WAIT)
    assert out.ok, out
    assert fleet.instance.engine.wait("relay", WAIT).value == "on_true"


@settings(max_examples=30, deadline=None)
@given(data=st.binary(max_size=400), pick=st.integers(min_value=0))
def test_random_bytes_on_any_channel_never_crash_a_handler(data: bytes, pick: int) -> None:
    with ExitStack() as stack:
        fleet = Fleet(stack)
        channel = fleet.channels[pick % len(fleet.channels)]
        fleet.attacker.publish(channel, data)
        fleet.quiet()
        assert fleet.drops()["handler_error"] == 0
        assert sum(fleet.drops()[r] for r in DROP_REASONS) >= 1


def test_authentic_members_sending_nonsense_inner_messages_are_counted(fleet: Fleet) -> None:
    member = FleetLink(fleet.attacker, FleetAuth("temoto", "B", KEY))
    assert fleet.instance.link.wait_for_peers(["B"], WAIT)
    assert fleet.cli_link.wait_for_peers(["B"], WAIT)
    fleet.quiet()
    before = decode_errors(fleet)
    for channel in fleet.channels:
        member.send(channel, "no_such_type_t", b"")
        member.send(channel, "handshake_t", json.dumps({"not": "lcm"}).encode())
    fleet.quiet()
    assert decode_errors(fleet) - before == 2 * len(fleet.channels)
    assert fleet.drops()["handler_error"] == 0
