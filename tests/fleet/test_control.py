"""Remote graph control: instances take start/stop/pause/resume/modify and publish feedback."""

from __future__ import annotations

import itertools
import json
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import pytest

from temoto.clock import ManualClock
from temoto.fleet.control import (
    COMMAND_CHANNEL,
    FEEDBACK_CHANNEL,
    GraphCommander,
    GraphFeedback,
)
from temoto.instance import Instance
from temoto.lcm_types import graph_command_t, graph_feedback_t
from temoto.transport import codec
from temoto.transport.auth import FleetAuth, Opened
from temoto.transport.inprocess import InProcessTransport
from temoto.transport.link import FleetLink

ROOT = Path(__file__).resolve().parents[2]
ACTIONS = ROOT / "examples" / "actions" / "conformance"
UPSTREAM = ROOT.parent / "shared" / "conformance" / "umrf" / "upstream"
MULTI = UPSTREAM / "actionengine_test_engine_test_multi_actor.graph.json"
KEY = bytes(range(32))
WAIT = 10.0
_buses = itertools.count()


def action(name: str, iid: int, inputs: dict[str, Any], **extra: Any) -> dict[str, Any]:
    params = {k: {"pvf_type": _type(v), "pvf_value": v} for k, v in inputs.items()}
    return {"name": name, "instance_id": iid, "type": "sync", "input_parameters": params, **extra}


def _type(value: Any) -> str:
    return "number" if isinstance(value, int | float) else "string"


def timer_graph(name: str = "ticking", count_until: float = 0, actor: str = "") -> dict[str, Any]:
    """One TaTimer (0 = runs until stopped)."""
    timer = action("TaTimer", 0, {"count_until": count_until})
    timer["output_parameters"] = {"final_count": {"pvf_type": "number"}}
    if actor:
        timer["actor"] = actor
    return {
        "graph_name": name,
        "graph_entry": [{"name": "TaTimer", "instance_id": 0}],
        "graph_exit": [{"name": "TaTimer", "instance_id": 0}],
        "actions": [timer],
    }


def relay_graph(name: str = "relay", text: str = "hello") -> dict[str, Any]:
    relay = action("TaRelayString", 0, {"string_in": text})
    relay["output_parameters"] = {"string_out": {"pvf_type": "string"}}
    return {
        "graph_name": name,
        "graph_entry": [{"name": "TaRelayString", "instance_id": 0}],
        "graph_exit": [{"name": "TaRelayString", "instance_id": 0}],
        "actions": [relay],
    }


class Net:
    """Instances and commanders on one in-process bus; all closed at the end."""

    def __init__(self, bus: str, stack: ExitStack, graphs: Path) -> None:
        self.bus = bus
        self.stack = stack
        self.graphs = graphs

    def instance(self, actor: str, **kwargs: Any) -> Instance:
        kwargs.setdefault("feedback_period_s", 0.2)
        return self.stack.enter_context(
            Instance(
                actor,
                transport=InProcessTransport(self.bus),
                key=KEY,
                actions=[ACTIONS],
                graphs=[self.graphs],
                **kwargs,
            )
        )

    def link(self, sender: str, key: bytes = KEY) -> FleetLink:
        transport = self.stack.enter_context(InProcessTransport(self.bus))
        return FleetLink(transport, FleetAuth("temoto", sender, key))

    def commander(self, sender: str = "operator", key: bytes = KEY) -> GraphCommander:
        return self.stack.enter_context(GraphCommander(self.link(sender, key), resend_s=0.05))


@pytest.fixture
def net(tmp_path: Path) -> Iterator[Net]:
    (tmp_path / "indexed.graph.json").write_text(json.dumps(relay_graph("indexed")))
    with ExitStack() as stack:
        yield Net(f"control-{next(_buses)}", stack, tmp_path)


class Feedbacks:
    """Collects feedback and waits for a condition on it."""

    def __init__(self, commander: GraphCommander) -> None:
        self.got: list[GraphFeedback] = []
        self._cond = threading.Condition()
        commander.watch(self._add)

    def _add(self, feedback: GraphFeedback) -> None:
        with self._cond:
            self.got.append(feedback)
            self._cond.notify_all()

    def wait(
        self, pred: Callable[[GraphFeedback], bool], timeout: float = WAIT, since: int = 0
    ) -> GraphFeedback:
        """The first feedback from index ``since`` on that satisfies ``pred``."""
        with self._cond:
            found: list[GraphFeedback] = []

            def seen() -> bool:
                found[:] = [f for f in self.got[since:] if pred(f)]
                return bool(found)

            assert self._cond.wait_for(seen, timeout), f"not seen; got {self.got[-5:]}"
            return found[0]


def test_start_a_graph_sent_as_json_and_see_it_finish(net: Net) -> None:
    a = net.instance("A")
    cmd = net.commander()
    feedback = Feedbacks(cmd)
    out = cmd.command("start", ["A"], graph_json=relay_graph(), timeout=WAIT)
    assert out.ok, out
    assert out.replies["A"].session == "relay"
    assert a.engine.wait("relay", WAIT).value == "on_true"
    done = feedback.wait(lambda f: f.graph == "relay" and f.state == "FINISHED")
    assert done.actor == "A"
    assert done.result == "on_true"
    assert done.nodes == (("TaRelayString_0", "FINISHED"),)


def test_start_an_indexed_graph_by_name_under_a_session_name(net: Net) -> None:
    a = net.instance("A")
    out = net.commander().command("start", ["A"], graph="indexed", session="run-7")
    assert out.ok, out
    assert a.engine.wait("run-7", WAIT).value == "on_true"
    assert out.replies["A"].graph == "indexed"


def test_start_passes_graph_inputs_converted_by_declared_type(net: Net) -> None:
    graph = timer_graph("timed")
    graph["actions"][0]["input_parameters"] = {"count_until": {"pvf_type": "number"}}
    a = net.instance("A")
    out = net.commander().command(
        "start", ["A"], graph_json=graph, params={"count_until": "0.1"}, timeout=WAIT
    )
    assert out.ok, out
    assert a.engine.wait("timed", WAIT).value == "on_true"
    bad = net.commander("op2").command(
        "start", ["A"], graph_json=graph, session="t2", params={"count_until": "soon"}
    )
    assert not bad.ok
    assert "not a JSON number" in bad.replies["A"].message


def test_stop_pause_and_resume_a_running_graph(net: Net) -> None:
    a = net.instance("A")
    cmd = net.commander()
    feedback = Feedbacks(cmd)
    assert cmd.command("start", ["A"], graph_json=timer_graph()).ok
    feedback.wait(lambda f: f.state == "RUNNING" and ("TaTimer_0", "RUNNING") in f.nodes)
    assert cmd.command("pause", ["A"], graph="ticking").ok
    feedback.wait(lambda f: f.state == "PAUSED")
    paused_at = len(feedback.got)
    assert cmd.command("resume", ["A"], graph="ticking").ok
    feedback.wait(lambda f: f.state == "RUNNING", since=paused_at)
    stop = cmd.command("stop", ["A"], graph="ticking", timeout=WAIT)
    assert stop.ok, stop
    assert stop.replies["A"].result == "on_stopped"
    assert a.engine.outcome("ticking").state.value == "STOPPED"


def test_modify_a_running_graph(net: Net) -> None:
    a = net.instance("A")
    cmd = net.commander()
    feedback = Feedbacks(cmd)
    assert cmd.command("start", ["A"], graph_json=timer_graph()).ok
    feedback.wait(lambda f: ("TaTimer_0", "RUNNING") in f.nodes)
    assert cmd.command("pause", ["A"], graph="ticking").ok
    changed = timer_graph()
    changed["actions"].append(relay_graph()["actions"][0])
    out = cmd.command("modify", ["A"], graph_json=changed, continue_from="TaRelayString_0")
    assert out.ok, out
    feedback.wait(lambda f: ("TaRelayString_0", "FINISHED") in f.nodes)
    wrong = cmd.command("modify", ["A"], graph_json=changed, continue_from="Nope_0")
    assert not wrong.ok
    assert wrong.replies["A"].message == "the new graph has no action 'Nope_0'"
    assert cmd.command("stop", ["A"], graph="ticking").ok
    assert a.engine.outcome("ticking").state.value == "STOPPED"


def test_commands_that_fail_are_answered_with_the_engines_message(net: Net) -> None:
    net.instance("A")
    cmd = net.commander()
    missing = cmd.command("start", ["A"], graph="no_such_graph")
    assert not missing.ok
    assert "no_such_graph" in missing.replies["A"].message
    assert "GraphNotFoundError" in missing.replies["A"].errors[0]
    stop = cmd.command("stop", ["A"], graph="never_started")
    assert not stop.ok
    assert "never_started" in stop.replies["A"].message
    assert cmd.command("start", ["A"], graph_json=timer_graph()).ok
    again = cmd.command("start", ["A"], graph_json=timer_graph())
    assert not again.ok
    assert "already active" in again.replies["A"].message
    invalid = cmd.command("start", ["A"], graph_json={"graph_name": "x", "actions": "no"})
    assert not invalid.ok
    assert invalid.replies["A"].message
    assert cmd.command("stop", ["A"], graph="ticking").ok


def test_only_the_targets_act_and_each_answers(net: Net) -> None:
    a, b, c = net.instance("A"), net.instance("B"), net.instance("C")
    out = net.commander().command("start", ["A", "C"], graph_json=relay_graph())
    assert out.ok
    assert sorted(out.replies) == ["A", "C"]
    assert a.engine.wait("relay", WAIT).value == "on_true"
    assert c.engine.wait("relay", WAIT).value == "on_true"
    assert "relay" not in b.engine.running_graphs()
    # B opens the command once the hellos crossed (a keyed fleet), maybe after A and C answered;
    # it may see it more than once: the commander re-sends it every 0.25 s until A and C answer
    deadline = time.monotonic() + WAIT
    while b.control.stats["ignored"] < 1:
        assert time.monotonic() < deadline, b.control.stats
        time.sleep(0.01)
    assert b.control.stats["commands"] == 0
    assert "relay" not in b.engine.running_graphs()


def test_a_target_that_does_not_answer_is_reported_missing(net: Net) -> None:
    net.instance("A")
    out = net.commander().command("start", ["A", "Ghost"], graph_json=relay_graph(), timeout=0.5)
    assert not out.ok
    assert out.missing == ("Ghost",)
    assert out.replies["A"].ok


def test_the_commanders_resends_and_timeout_run_on_its_clock(net: Net) -> None:
    """On a ManualClock nothing is re-sent and nobody gives up until virtual time moves."""
    clock = ManualClock()
    sent: list[int] = []
    listener = net.stack.enter_context(InProcessTransport(net.bus))
    listener.subscribe(COMMAND_CHANNEL, lambda _ch, data: sent.append(len(data)))
    commander = net.stack.enter_context(
        GraphCommander(net.link("operator"), resend_s=1.0, clock=clock)
    )
    outcome: list[Any] = []
    thread = threading.Thread(
        target=lambda: outcome.append(commander.command("stop", ["Ghost"], graph="g", timeout=10)),
        daemon=True,
    )
    thread.start()
    deadline = time.monotonic() + WAIT
    while not sent and time.monotonic() < deadline:
        time.sleep(0.01)
    assert len(sent) == 1
    thread.join(0.3)  # real time passes; virtual time does not
    assert thread.is_alive()
    assert len(sent) == 1
    for step in range(1, 10):
        clock.advance(1.0)
        while len(sent) < step + 1 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert len(sent) == step + 1, f"no resend after {step} virtual seconds"
    clock.advance(1.0)
    thread.join(WAIT)
    assert not thread.is_alive()
    assert outcome[0].missing == ("Ghost",)
    with pytest.raises(TypeError, match="Clock"):
        GraphCommander(net.link("other"), clock=time.monotonic)  # type: ignore[arg-type]


def test_a_shared_graph_started_remotely_on_every_actor_ends_on_true(net: Net) -> None:
    if not MULTI.is_file():
        pytest.skip(f"upstream data not found at {MULTI}")
    names = ["Actor A", "Actor B", "Actor C"]
    instances = [net.instance(n) for n in names]
    cmd = net.commander()
    feedback = Feedbacks(cmd)
    graph = json.loads(MULTI.read_text())
    out = cmd.command("start", names, graph_json=graph, timeout=WAIT)
    assert out.ok, out
    for inst in instances:
        assert inst.engine.wait(graph["graph_name"], WAIT).value == "on_true"
    for name in names:
        feedback.wait(lambda f, n=name: f.actor == n and f.result == "on_true")  # type: ignore[misc]


def test_a_resent_command_is_answered_again_but_carried_out_once(net: Net) -> None:
    a = net.instance("A")
    raw = net.link("operator")
    replies: list[Opened] = []
    got = threading.Condition()

    def on_reply(opened: Opened) -> None:
        with got:
            replies.append(opened)
            got.notify_all()

    raw.listen("TEMOTO_GRAPH_REPLY", on_reply)
    msg = graph_command_t()
    msg.request_id, msg.command, msg.targets, msg.targets_count = "r1", 1, ["A"], 1
    msg.graph, msg.session, msg.graph_json = "", "", json.dumps(relay_graph())
    msg.continue_from, msg.params = "", ""
    for sent in range(1, 4):
        raw.send(COMMAND_CHANNEL, *codec.encode(msg))
        with got:
            assert got.wait_for(lambda n=sent: len(replies) >= n, WAIT)  # type: ignore[misc]
    decoded = [codec.decode(o.type, o.payload) for o in replies]
    assert [r.code for r in decoded] == [1, 1, 1]
    assert a.control.stats["commands"] == 1
    assert a.control.stats["resent"] == 2
    assert a.engine.wait("relay", WAIT).value == "on_true"


def test_without_the_fleet_key_nothing_starts(net: Net) -> None:
    a = net.instance("A")
    stranger = net.commander("stranger", key=bytes(32))
    out = stranger.command("start", ["A"], graph_json=relay_graph(), timeout=0.5)
    assert out.missing == ("A",)
    assert "relay" not in a.engine.running_graphs()
    assert a.link.stats["forged"] >= 1
    assert a.control.stats["commands"] == 0


def test_garbage_and_meaningless_commands_are_counted_not_raised(net: Net) -> None:
    a = net.instance("A")
    raw = net.link("operator")
    raw.send(COMMAND_CHANNEL, "graph_command_t", b"\x00garbage")
    raw.send(COMMAND_CHANNEL, *codec.encode(_feedback_msg()))  # wrong type on the channel
    empty = graph_command_t()
    empty.request_id, empty.command, empty.targets, empty.targets_count = "r2", 1, [], 0
    raw.send(COMMAND_CHANNEL, *codec.encode(empty))
    unknown = graph_command_t()
    unknown.request_id, unknown.command, unknown.targets, unknown.targets_count = "r3", 9, ["A"], 1
    raw.send(COMMAND_CHANNEL, *codec.encode(unknown))
    # the instance still works, and what it dropped is counted (in a keyed fleet the raw
    # messages may open only once the hellos crossed, after the commander's start: waited for)
    assert net.commander().command("start", ["A"], graph_json=relay_graph()).ok
    deadline = time.monotonic() + WAIT
    while a.control.stats["decode_errors"] + a.control.stats["unexpected"] < 4:
        assert time.monotonic() < deadline, a.control.stats
        time.sleep(0.01)
    stats = a.control.stats
    assert stats["decode_errors"] == 1
    assert stats["unexpected"] == 3
    assert a.link.stats["handler_error"] == 0


def _feedback_msg() -> Any:
    msg = graph_feedback_t()
    msg.actor, msg.graph, msg.session, msg.state, msg.result = "X", "g", "g", "RUNNING", ""
    msg.nodes, msg.nodes_count = [], 0
    return msg


def test_feedback_of_a_busy_graph_is_rate_limited_and_a_late_watcher_sees_the_state(
    net: Net,
) -> None:
    a = net.instance("A", feedback_period_s=0.2)
    seen: list[Opened] = []
    net.link("counter").listen(FEEDBACK_CHANNEL, seen.append)
    assert net.commander().command("start", ["A"], graph_json=timer_graph()).ok
    late = Feedbacks(net.commander("late"))
    first = late.wait(lambda f: f.graph == "ticking")
    assert first.state == "RUNNING"
    assert a.control.stats["feedback_sent"] >= 1
    assert net.commander().command("stop", ["A"], graph="ticking").ok
    late.wait(lambda f: f.state == "STOPPED")
    assert len(seen) <= a.control.stats["feedback_sent"]


def test_the_instance_needs_an_actor_name() -> None:
    with pytest.raises(ValueError, match="actor name"):
        Instance("", transport=InProcessTransport("x"), key=KEY)
