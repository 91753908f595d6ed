"""Fleet security in one process: replays across restarts, a key per member, permissions,
revocation, and what a passive listener sees (docs/security.md).

Every member is a whole :class:`~temoto.instance.Instance` or a commander on an in-process bus;
an attacker transport on the same bus captures and re-publishes bytes.
"""

from __future__ import annotations

import itertools
import logging
import sys
import time
from collections.abc import Iterator
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import pytest

from temoto.errors import ResourceLoadError
from temoto.fleet.control import COMMAND_CHANNEL, GraphCommander
from temoto.instance import Instance
from temoto.lcm_types import envelope_t
from temoto.managers.process import ProcessRequest
from temoto.testing.fleet import settle
from temoto.transport.auth import HELLO_CHANNEL, FleetAuth
from temoto.transport.identity import Credentials, Identity, Policy, Roster
from temoto.transport.inprocess import InProcessTransport
from temoto.transport.link import FleetLink

ROOT = Path(__file__).resolve().parents[2]
ACTIONS = ROOT / "examples" / "actions" / "conformance"
KEY = bytes(range(32))
WAIT = 10.0
_buses = itertools.count()


def relay_graph(name: str = "relay", value: str = "x") -> dict[str, Any]:
    return {
        "graph_name": name,
        "graph_entry": [{"name": "TaRelayString", "instance_id": 0}],
        "graph_exit": [{"name": "TaRelayString", "instance_id": 0}],
        "actions": [
            {
                "name": "TaRelayString",
                "instance_id": 0,
                "type": "sync",
                "input_parameters": {"string_in": {"pvf_type": "string", "pvf_value": value}},
                "output_parameters": {"string_out": {"pvf_type": "string"}},
            }
        ],
    }


class Capture:
    """A passive listener: every byte published on the bus's channels, in order."""

    def __init__(self, transport: InProcessTransport, channels: set[str]) -> None:
        self.transport = transport
        self.frames: list[tuple[str, bytes]] = []
        for channel in sorted(channels):
            transport.subscribe(channel, self._take)

    def _take(self, channel: str, data: bytes) -> None:
        self.frames.append((channel, data))

    def of(self, channel: str) -> list[bytes]:
        return [data for ch, data in self.frames if ch == channel]


class Bus:
    def __init__(self, stack: ExitStack) -> None:
        self.stack = stack
        self.name = f"trust-{next(_buses)}"

    def transport(self) -> InProcessTransport:
        return self.stack.enter_context(InProcessTransport(self.name))

    def instance(
        self, actor: str, key: bytes | Credentials, stack: ExitStack | None = None
    ) -> Instance:
        where = stack or self.stack
        return where.enter_context(
            Instance(actor, transport=InProcessTransport(self.name), key=key, actions=[ACTIONS])
        )

    def commander(self, name: str, key: bytes | Credentials) -> GraphCommander:
        link = FleetLink(self.transport(), FleetAuth("temoto", name, key))
        return self.stack.enter_context(GraphCommander(link, resend_s=0.05))


@pytest.fixture
def bus() -> Iterator[Bus]:
    with ExitStack() as stack:
        yield Bus(stack)


ALL_CHANNELS = {
    HELLO_CHANNEL,
    COMMAND_CHANNEL,
    "TEMOTO_GRAPH_REPLY",
    "TEMOTO_GRAPH_FEEDBACK",
    "TEMOTO_HANDSHAKE",
    "TEMOTO_NOTIFY",
    "TEMOTO_RIS",
    "TEMOTO_RESOURCE",
    "TEMOTO_CONTEXT",
}


# --- replays across restarts --------------------------------------------------------------------


def test_a_captured_start_replayed_to_a_restarted_instance_is_refused(bus: Bus) -> None:
    spy = Capture(bus.transport(), {COMMAND_CHANNEL})
    commander = bus.commander("operator", KEY)
    with ExitStack() as first_boot:
        a = bus.instance("A", KEY, first_boot)
        out = commander.command("start", ["A"], graph_json=relay_graph(), timeout=WAIT)
        assert out.ok, out
        assert a.engine.wait("relay", WAIT).value == "on_true"
    captured = spy.of(COMMAND_CHANNEL)
    assert captured  # the start (and its re-sends)
    restarted = bus.instance("A", KEY)
    attacker = bus.transport()
    for data in captured:
        attacker.publish(COMMAND_CHANNEL, data)
    # the commander, still running, and the new boot agree on keys: the captured bytes are at
    # or below the floor of the commander's grant to the new boot, whatever they carry
    assert restarted.link.wait_for_peers(["operator"], WAIT)
    for data in captured:
        attacker.publish(COMMAND_CHANNEL, data)
    assert attacker.flush(WAIT)
    assert restarted.link.transport.flush(WAIT)  # type: ignore[attr-defined]
    assert restarted.control.stats["commands"] == 0
    assert "relay" not in restarted.engine.running_graphs()
    drops = restarted.link.stats
    assert drops["no_session"] + drops["replayed"] >= 2 * len(captured)
    assert drops["accepted"] == 0 or restarted.control.stats["commands"] == 0
    # and the commander is heard by the new boot as by the old one
    out = commander.command("start", ["A"], graph_json=relay_graph(), timeout=WAIT)
    assert out.ok, out


@pytest.mark.parametrize("later_s", [0.0, 11.0, 45.0, 3600.0])
@pytest.mark.parametrize("skew_s", [-3600.0, -31.0, 0.0, 31.0, 3600.0])
def test_replays_to_a_restarted_receiver_are_refused_whatever_the_clocks(
    later_s: float, skew_s: float
) -> None:
    now = [1_750_000_000.0]

    def receiver_clock() -> float:
        return now[0]

    def sender_clock() -> float:
        return now[0] + skew_s

    sender = FleetAuth("temoto", "operator", KEY, clock=sender_clock)
    receiver = FleetAuth("temoto", "A", KEY, clock=receiver_clock)
    settle(sender, receiver)
    captured = sender.seal(COMMAND_CHANNEL, "graph_command_t", b"start")
    assert receiver.open(COMMAND_CHANNEL, captured) is not None
    now[0] += later_s  # inside or past a clock window of 30 s: no matter
    restarted = FleetAuth("temoto", "A", KEY, clock=receiver_clock)
    assert restarted.open(COMMAND_CHANNEL, captured) is None  # no session granted yet
    settle(sender, restarted)
    assert restarted.open(COMMAND_CHANNEL, captured) is None  # at or below the floor
    assert restarted.stats["accepted"] == 0
    assert restarted.stats["replayed"] == 1
    fresh = sender.seal(COMMAND_CHANNEL, "graph_command_t", b"start")
    assert restarted.open(COMMAND_CHANNEL, fresh) is not None


def test_a_restarted_sender_s_old_messages_never_open_again(bus: Bus) -> None:
    receiver = FleetAuth("temoto", "A", KEY)
    old = FleetAuth("temoto", "operator", KEY)
    settle(old, receiver)
    captured = old.seal(COMMAND_CHANNEL, "graph_command_t", b"start")
    assert receiver.open(COMMAND_CHANNEL, captured) is not None
    new = FleetAuth("temoto", "operator", KEY)  # the same member after a restart
    settle(new, receiver)
    assert receiver.open(COMMAND_CHANNEL, captured) is None
    assert receiver.stats["replayed"] == 1


# --- a key per member ---------------------------------------------------------------------------


class Keys:
    """Identities A (a robot), operator and mallory (members), and a roster file."""

    def __init__(self, tmp_path: Path, policy: Policy | None = None) -> None:
        self.ids = {name: Identity.generate(name) for name in ("A", "operator", "mallory")}
        self.path = tmp_path / "roster.yaml"
        roster = Roster({}, policy=policy)
        for name, identity in self.ids.items():
            roster.add(name, identity.public_key)
        roster.save(self.path)

    def creds(self, name: str) -> Credentials:
        return Credentials(self.ids[name], Roster.load(self.path))


OPERATOR_ONLY = Policy.from_data([{"who": ["operator"], "may": ["graph.*"], "targets": ["A"]}])


def test_members_with_their_own_keys_work_together(bus: Bus, tmp_path: Path) -> None:
    keys = Keys(tmp_path)
    a = bus.instance("A", keys.creds("A"))
    out = bus.commander("operator", keys.creds("operator")).command(
        "start", ["A"], graph_json=relay_graph(), timeout=WAIT
    )
    assert out.ok, out
    assert a.engine.wait("relay", WAIT).value == "on_true"


def test_a_member_speaking_as_another_is_refused(bus: Bus, tmp_path: Path) -> None:
    keys = Keys(tmp_path)
    a = bus.instance("A", keys.creds("A"))
    spy = Capture(bus.transport(), {COMMAND_CHANNEL, HELLO_CHANNEL})
    operator = bus.commander("operator", keys.creds("operator"))
    mallory_link = FleetLink(bus.transport(), FleetAuth("temoto", "mallory", keys.creds("mallory")))
    assert mallory_link.wait_for_peers(["operator", "A"], WAIT)
    assert operator.command("start", ["A"], graph_json=relay_graph(), timeout=WAIT).ok
    assert a.engine.wait("relay", WAIT).value == "on_true"
    before = a.link.stats
    # 1. mallory signs a hello as the operator: the signature is not the operator's
    forged_hello = _resign_hello(spy.of(HELLO_CHANNEL), "operator", keys.ids["mallory"])
    bus.transport().publish(HELLO_CHANNEL, forged_hello)
    # 2. mallory holds the operator's sending key (every member does, to decrypt) and rewrites
    # one of its commands: the operator's MAC for A, which mallory cannot make, no longer fits
    captured = decode(spy.of(COMMAND_CHANNEL)[-1])  # sealed with an entry for A
    secure = mallory_link.auth._secure
    assert secure is not None
    rx = secure.rx["operator", captured.stamp_us]
    from temoto.transport._secure import _ad

    tags = b"".join(captured.mac[16 + i : 16 + i + 4] for i in range(0, len(captured.mac) - 16, 20))
    ad = _ad(
        COMMAND_CHANNEL, "temoto", "operator", captured.type, captured.seq, captured.stamp_us, tags
    )
    plain = rx.aead.decrypt(
        captured.seq.to_bytes(12, "big"), bytes(captured.payload) + captured.mac[:16], ad
    )
    assert b"relay" in plain  # mallory reads it: it is a member
    captured.seq += 1000  # a new number, so that it is not a mere replay
    ad = _ad(
        COMMAND_CHANNEL, "temoto", "operator", captured.type, captured.seq, captured.stamp_us, tags
    )
    sealed = rx.aead.encrypt(
        captured.seq.to_bytes(12, "big"), plain.replace(b"relay", b"evil!"), ad
    )
    captured.payload, captured.mac = sealed[:-16], sealed[-16:] + captured.mac[16:]
    bus.transport().publish(COMMAND_CHANNEL, captured.encode())
    assert bus.transport().flush(WAIT)
    assert a.link.transport.flush(WAIT)  # type: ignore[attr-defined]
    after = a.link.stats
    assert after["forged"] - before["forged"] == 2
    assert after["accepted"] == before["accepted"] or a.control.stats["commands"] == 1
    assert a.control.stats["commands"] == 1  # only the operator's own start
    assert "evil!" not in a.engine.running_graphs()


def decode(data: bytes) -> Any:
    return envelope_t.decode(data)


def _resign_hello(hellos: list[bytes], claimed: str, signer: Identity) -> bytes:
    """A hello as ``claimed`` announcing an ephemeral key of the signer's choice, signed with
    the signer's own key: what a member would send to take another's place."""
    from cryptography.hazmat.primitives.asymmetric.x25519 import X25519PrivateKey
    from cryptography.hazmat.primitives.serialization import Encoding, PublicFormat

    env = next(e for e in map(decode, hellos) if e.sender == claimed)
    mine = X25519PrivateKey.generate().public_key().public_bytes(Encoding.Raw, PublicFormat.Raw)
    env.payload = mine + bytes(env.payload)[32:]
    env.mac_size, env.mac = 0, b""
    env.mac = signer.sign(HELLO_CHANNEL.encode() + b"\0" + env.encode())
    env.mac_size = len(env.mac)
    data: bytes = env.encode()
    return data


def test_an_identity_without_permission_gets_a_reason(
    bus: Bus, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    keys = Keys(tmp_path, OPERATOR_ONLY)
    a = bus.instance("A", keys.creds("A"))
    mallory = bus.commander("mallory", keys.creds("mallory"))
    with caplog.at_level(logging.WARNING, logger="temoto.fleet.control"):
        out = mallory.command("start", ["A"], graph_json=relay_graph(), timeout=WAIT)
    assert not out.ok
    reply = out.replies["A"]
    assert "permission denied: 'mallory' may not graph.start on 'A'" in reply.message
    assert "relay" not in a.engine.running_graphs()
    assert a.control.stats["refused"] == 1
    assert any(
        "refused graph command start from 'mallory'" in r.getMessage() for r in caplog.records
    )
    # the operator may
    operator = bus.commander("operator", keys.creds("operator"))
    assert operator.command("start", ["A"], graph_json=relay_graph(), timeout=WAIT).ok
    assert mallory.command("stop", ["A"], graph="relay", timeout=WAIT).replies["A"].ok is False


def eventually(check: Any, what: str) -> None:
    deadline = time.monotonic() + WAIT
    while not check():
        assert time.monotonic() < deadline, what
        time.sleep(0.01)


RESOURCES_AND_WORLD = Policy.from_data(
    [
        {"who": ["operator"], "may": ["resource.request", "world.publish"], "targets": ["*"]},
        {"who": ["*"], "may": ["world.publish"], "targets": ["nobody"]},
    ]
)


def test_a_resource_request_without_permission_gets_a_reason(
    bus: Bus, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    keys = Keys(tmp_path, RESOURCES_AND_WORLD)
    a = bus.instance("A", keys.creds("A"))
    mallory = bus.instance("mallory", keys.creds("mallory"))
    operator = bus.instance("operator", keys.creds("operator"))
    for member in (mallory, operator):  # every instance serves "process": A among them
        eventually(lambda m=member: "A" in m.ris.providers("process"), "A's servers not heard")
    request = ProcessRequest(sys.executable, ("-c", "import time; time.sleep(60)"))
    with (
        caplog.at_level(logging.WARNING, logger="temoto.fleet"),
        pytest.raises(ResourceLoadError, match="permission denied: 'mallory' may not"),
    ):
        mallory.resources.request("process", request, robot="A")
    assert a.processes.running() == []  # nothing was started for mallory
    assert any("refused" in r.getMessage() and "mallory" in r.getMessage() for r in caplog.records)
    # the operator may: the same request loads on A
    held = operator.resources.request("process", request, robot="A")
    operator.registrar.release(held.id)


def test_world_model_changes_without_permission_are_ignored(
    bus: Bus, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    keys = Keys(tmp_path, RESOURCES_AND_WORLD)
    a = bus.instance("A", keys.creds("A"))
    mallory = bus.instance("mallory", keys.creds("mallory"))
    operator = bus.instance("operator", keys.creds("operator"))
    with caplog.at_level(logging.WARNING, logger="temoto.managers.context"):
        mallory.context.add("crate", "object")
        eventually(lambda: a.context.stats["updates_refused"] >= 1, "mallory's change taken")
        operator.context.add("dock", "object")
        eventually(lambda: any(i.name == "dock" for i in a.context.items()), "no dock on A")
    assert not any(i.name == "crate" for i in a.context.items())
    assert any("changes from 'mallory' ignored" in r.getMessage() for r in caplog.records)


def test_a_revoked_key_is_refused_at_once(bus: Bus, tmp_path: Path) -> None:
    keys = Keys(tmp_path)
    a = bus.instance("A", keys.creds("A"))
    operator = bus.commander("operator", keys.creds("operator"))
    assert operator.command("start", ["A"], graph_json=relay_graph(), timeout=WAIT).ok
    assert a.engine.wait("relay", WAIT).value == "on_true"
    roster = Roster.load(keys.path)
    roster.revoke("operator")
    roster.save()
    out = operator.command("start", ["A"], graph_json=relay_graph("again"), timeout=1.0)
    assert out.missing == ("A",)
    assert "again" not in a.engine.running_graphs()
    assert a.link.stats["unknown_member"] >= 1
    assert a.control.stats["commands"] == 1


# --- what a passive listener sees ---------------------------------------------------------------


@pytest.mark.parametrize("mode", ["fleet key", "roster", "insecure"])
def test_a_passive_capture_shows_no_graph_parameter_or_item(
    bus: Bus, tmp_path: Path, mode: str
) -> None:
    spy = Capture(bus.transport(), ALL_CHANNELS | {"TEMOTO_ACK_A", "TEMOTO_ACK_operator"})
    keys = Keys(tmp_path)
    if mode == "insecure":  # the control: the same run, seen in clear
        a = bus.stack.enter_context(
            Instance(
                "A",
                transport=InProcessTransport(bus.name),
                key=None,
                insecure=True,
                actions=[ACTIONS],
            )
        )
        link = FleetLink(bus.transport(), FleetAuth("temoto", "operator", None, insecure=True))
        operator = bus.stack.enter_context(GraphCommander(link, resend_s=0.05))
    else:
        a = bus.instance("A", KEY if mode == "fleet key" else keys.creds("A"))
        operator = bus.commander("operator", KEY if mode == "fleet key" else keys.creds("operator"))
    a.context.add("secret_crate_item", "object")
    out = operator.command(
        "start",
        ["A"],
        graph_json=relay_graph("classified_graph", "SECRET-PARAMETER-VALUE"),
        timeout=WAIT,
    )
    assert out.ok, out
    assert a.engine.wait("classified_graph", WAIT).value == "on_true"
    assert a.link.transport.flush(WAIT)  # type: ignore[attr-defined]
    assert spy.transport.flush(WAIT)
    # the feedback thread publishes the run's end on its own time (loaded machine: later)
    eventually(lambda: "TEMOTO_GRAPH_FEEDBACK" in {ch for ch, _ in spy.frames}, "no feedback")
    blob = b"".join(data for _, data in spy.frames)
    assert {ch for ch, _ in spy.frames} >= {
        COMMAND_CHANNEL,
        "TEMOTO_GRAPH_FEEDBACK",
        "TEMOTO_CONTEXT",
    }
    secrets = (b"classified_graph", b"SECRET-PARAMETER", b"secret_crate_item", b"TaRelayString")
    for secret in secrets:
        assert (secret in blob) is (mode == "insecure"), secret


def test_a_member_cannot_answer_or_report_feedback_in_another_s_name(
    bus: Bus, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # mallory (a member, its own key) answers a command and sends feedback naming A
    from temoto.fleet.common import new
    from temoto.fleet.control import FEEDBACK_CHANNEL, REPLY_CHANNEL
    from temoto.lcm_types import graph_command_reply_t, graph_feedback_t
    from temoto.transport import codec

    keys = Keys(tmp_path)
    operator = bus.commander("operator", keys.creds("operator"))
    mallory = FleetLink(bus.transport(), FleetAuth("temoto", "mallory", keys.creds("mallory")))
    assert mallory.wait_for_peers(["operator"], WAIT)
    seen: list[Any] = []
    operator.watch(seen.append)

    def answer(opened: Any) -> None:
        msg = codec.decode(opened.type, opened.payload)
        reply = new(graph_command_reply_t)
        reply.request_id, reply.actor, reply.graph, reply.session = msg.request_id, "A", "g", "g"
        reply.code, reply.message = 1, "started"
        mallory.send(REPLY_CHANNEL, *codec.encode(reply))
        feedback = new(graph_feedback_t)
        feedback.actor, feedback.graph, feedback.session = "A", "g", "g"
        feedback.state, feedback.result = "finished", "on_true"
        mallory.send(FEEDBACK_CHANNEL, *codec.encode(feedback))

    mallory.listen(COMMAND_CHANNEL, answer)
    with caplog.at_level(logging.WARNING, logger="temoto.fleet.common"):
        out = operator.command("start", ["A"], graph_json=relay_graph(), timeout=1.0)
        eventually(lambda: operator.stats["impostor"] >= 2, "mallory's messages not dropped")
    assert not out.ok
    assert "A" not in out.replies
    assert seen == []  # no feedback in A's name reached the watcher
    lines = [r.getMessage() for r in caplog.records]
    assert any("sent by 'mallory' whose actor names 'A'" in line for line in lines), lines
