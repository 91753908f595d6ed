"""The Action helpers, directly: sleep, wait_for/wake, wait_until_stopped, inputs, outputs, log.

Most tests bind an action to a ``RunControl`` by hand (what the engine does before a run), so
stop and pause are driven from the test thread without a graph around them; a few go through an
engine to check the same helpers end to end.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from typing import Any, ClassVar

import pytest

from temoto import Action, ActionCatalog, ActionEngine, Result, ScaledClock, parse_graph, parse_umrf
from temoto.clock import Clock, MonotonicClock
from temoto.core.action import LOG_LENGTH, Inputs, Outputs, RunControl
from temoto.core.params import Parameter
from temoto.errors import ActionError, StopRequested

WAIT = 10.0


class Probe(Action):
    def on_run(self) -> bool:
        return True


def bound(
    clock: Clock | None = None,
    inputs: dict[str, Parameter] | None = None,
    outputs: dict[str, Parameter] | None = None,
) -> tuple[Probe, RunControl]:
    """An action bound like the engine binds one, and its control."""
    control = RunControl(clock or MonotonicClock())
    action = Probe()
    action.initialize(control, "Probe_0", "g", inputs or {}, outputs or {})
    return action, control


def later(seconds: float, fn: Callable[[], Any]) -> threading.Thread:
    """Call fn from another thread after `seconds` (joined by the caller)."""

    def body() -> None:
        time.sleep(seconds)
        fn()

    thread = threading.Thread(target=body, name="test-later")
    thread.start()
    return thread


@pytest.fixture
def threads() -> Iterator[list[threading.Thread]]:
    started: list[threading.Thread] = []
    yield started
    for t in started:
        t.join(5)


# ================================================================ sleep


def test_sleep_returns_after_duration() -> None:
    action, _ = bound()
    t0 = time.monotonic()
    action.sleep(0.05)
    assert 0.05 <= time.monotonic() - t0 < 0.5


def test_sleep_uses_the_clock() -> None:
    action, _ = bound(ScaledClock(20))
    t0 = time.monotonic()
    action.sleep(1.0)  # one clock-second = 0.05 s real
    assert time.monotonic() - t0 < 0.5


def test_sleep_raises_stop_requested_on_stop(threads: list[threading.Thread]) -> None:
    action, control = bound()
    threads.append(later(0.05, control.request_stop))
    t0 = time.monotonic()
    with pytest.raises(StopRequested):
        action.sleep(5.0)
    assert time.monotonic() - t0 < 1.0
    assert action.stop_requested


def test_sleep_after_stop_raises_at_once() -> None:
    action, control = bound()
    control.request_stop()
    with pytest.raises(StopRequested):
        action.sleep(0)
    assert not isinstance(StopRequested("x"), Exception)  # `except Exception` does not swallow it


def test_sleep_blocks_while_paused_and_continues_after_resume(
    threads: list[threading.Thread],
) -> None:
    action, control = bound()
    control.set_paused(True)
    assert action.paused
    threads.append(later(0.2, lambda: control.set_paused(False)))
    t0 = time.monotonic()
    action.sleep(0.05)  # its deadline passes during the pause: it waits for the resume
    assert time.monotonic() - t0 >= 0.18
    assert not action.paused


def test_short_pause_does_not_extend_sleep(threads: list[threading.Thread]) -> None:
    # The sleep ends at its deadline or at the resume, whichever is later (like TaTimer,
    # elapsed time counts from the start).
    action, control = bound()
    threads.append(later(0.03, lambda: control.set_paused(True)))
    threads.append(later(0.08, lambda: control.set_paused(False)))
    t0 = time.monotonic()
    action.sleep(0.25)
    assert 0.24 <= time.monotonic() - t0 < 0.33


def test_stop_while_paused_raises_from_sleep(threads: list[threading.Thread]) -> None:
    action, control = bound()
    control.set_paused(True)
    threads.append(later(0.05, control.request_stop))
    with pytest.raises(StopRequested):
        action.sleep(0.01)


# ================================================================ wait_for / wake


def test_wait_for_returns_when_woken(threads: list[threading.Thread]) -> None:
    action, _ = bound()
    box = {"ready": False}

    def produce() -> None:
        box["ready"] = True
        action.wake()

    threads.append(later(0.05, produce))
    t0 = time.monotonic()
    assert action.wait_for(lambda: box["ready"], timeout=5.0) is True
    assert time.monotonic() - t0 < 1.0


def test_wait_for_true_predicate_returns_at_once() -> None:
    action, _ = bound()
    assert action.wait_for(lambda: True, timeout=0) is True


def test_wait_for_times_out() -> None:
    action, _ = bound()
    t0 = time.monotonic()
    assert action.wait_for(lambda: False, timeout=0.05) is False
    assert time.monotonic() - t0 >= 0.05


def test_wait_for_does_not_poll() -> None:
    action, _ = bound()
    calls = [0]

    def predicate() -> bool:
        calls[0] += 1
        return False

    assert action.wait_for(predicate, timeout=0.2) is False
    assert calls[0] <= 3  # checked on entry and on wake-ups only


def test_wait_for_raises_stop_requested(threads: list[threading.Thread]) -> None:
    action, control = bound()
    threads.append(later(0.05, control.request_stop))
    with pytest.raises(StopRequested):
        action.wait_for(lambda: False)


def test_wait_for_holds_while_paused(threads: list[threading.Thread]) -> None:
    action, control = bound()
    control.set_paused(True)
    threads.append(later(0.1, lambda: control.set_paused(False)))
    t0 = time.monotonic()
    assert action.wait_for(lambda: True, timeout=5.0) is True
    assert time.monotonic() - t0 >= 0.09


# ================================================================ wait_until_stopped


def test_wait_until_stopped_true_on_stop(threads: list[threading.Thread]) -> None:
    action, control = bound()
    threads.append(later(0.05, control.request_stop))
    t0 = time.monotonic()
    assert action.wait_until_stopped() is True
    assert time.monotonic() - t0 < 1.0


def test_wait_until_stopped_false_on_timeout() -> None:
    action, _ = bound()
    t0 = time.monotonic()
    assert action.wait_until_stopped(0.05) is False
    assert time.monotonic() - t0 >= 0.05


def test_wait_until_stopped_already_stopped() -> None:
    action, control = bound()
    control.request_stop()
    assert action.wait_until_stopped(0) is True


def test_wait_until_stopped_is_not_ended_by_pause_or_resume(
    threads: list[threading.Thread],
) -> None:
    action, control = bound()
    threads.append(later(0.02, lambda: control.set_paused(True)))
    threads.append(later(0.04, lambda: control.set_paused(False)))
    t0 = time.monotonic()
    assert action.wait_until_stopped(0.15) is False
    assert time.monotonic() - t0 >= 0.15


def test_reset_clears_stop_and_pause() -> None:
    action, control = bound()
    control.request_stop()
    control.set_paused(True)
    control.reset()
    assert not action.stop_requested
    assert not action.paused


# ================================================================ outputs


def _outs() -> Outputs:
    return Outputs(
        {
            "text": Parameter("text", "string"),
            "count": Parameter("count", "number"),
            "flags": Parameter("flags", "bools"),
            "blob": Parameter("blob", "cir_pointer"),
        }
    )


def test_outputs_accept_declared_values() -> None:
    outs = _outs()
    outs["text"] = "hi"
    outs["count"] = 3
    outs["flags"] = (True, False)
    marker = object()
    outs["blob"] = marker  # non-native types carry any Python object
    snap = outs.snapshot()
    assert snap == {"text": "hi", "count": 3.0, "flags": [True, False], "blob": marker}
    assert type(snap["count"]) is float
    assert "text" in outs
    assert outs["text"] == "hi"
    snap["text"] = "changed"
    assert outs["text"] == "hi"  # snapshot is a copy


def test_outputs_reject_unknown_name() -> None:
    outs = _outs()
    with pytest.raises(KeyError) as info:
        outs["nope"] = 1
    message = str(info.value)
    assert "nope" in message
    assert "text" in message  # the known outputs are listed
    assert "count" in message


@pytest.mark.parametrize(
    ("name", "value"),
    [
        ("text", 5),
        ("count", "5"),
        ("count", True),
        ("count", float("nan")),
        ("flags", [1]),
        ("flags", True),
    ],
)
def test_outputs_reject_wrong_types(name: str, value: Any) -> None:
    outs = _outs()
    with pytest.raises(TypeError) as info:
        outs[name] = value
    assert f"output '{name}'" in str(info.value)
    assert name not in outs


# ================================================================ inputs


def _ins(values: dict[str, Any]) -> Inputs:
    params = {
        name: Parameter(name, kind)
        for name, kind in [
            ("s", "string"),
            ("x", "number"),
            ("b", "bool"),
            ("ss", "strings"),
            ("xs", "numbers"),
            ("bs", "bools"),
            ("missing", "string"),
        ]
    }
    return Inputs(values, params)


def test_inputs_typed_getters() -> None:
    ins = _ins({"s": "a", "x": 2.5, "b": False, "ss": ["p"], "xs": [1.0, 2.0], "bs": [True]})
    assert ins.get_string("s") == "a"
    assert ins.get_number("x") == 2.5
    assert ins.get_bool("b") is False
    assert ins.get_strings("ss") == ["p"]
    assert ins.get_numbers("xs") == [1.0, 2.0]
    assert ins.get_bools("bs") == [True]
    assert dict(ins) == {
        "s": "a",
        "x": 2.5,
        "b": False,
        "ss": ["p"],
        "xs": [1.0, 2.0],
        "bs": [True],
    }
    assert len(ins) == 6


def test_inputs_list_getters_return_copies() -> None:
    values = {"ss": ["p"]}
    ins = _ins(values)
    got = ins.get_strings("ss")
    got.append("q")
    assert ins.get_strings("ss") == ["p"]


def test_inputs_int_is_a_number_but_bool_is_not() -> None:
    ins = _ins({"x": 3, "b": True})
    assert ins.get_number("x") == 3.0
    with pytest.raises(TypeError, match="'b' is not a number"):
        ins.get_number("b")


def test_inputs_unknown_name_raises_key_error_listing_inputs() -> None:
    ins = _ins({"s": "a"})
    with pytest.raises(KeyError) as info:
        ins.get_string("nope")
    message = str(info.value)
    assert "unknown input 'nope'" in message
    assert "s, x, b" in message


def test_inputs_declared_but_empty_raises_key_error() -> None:
    ins = _ins({"s": "a"})
    with pytest.raises(KeyError, match="input 'missing' holds no value"):
        ins["missing"]


@pytest.mark.parametrize(
    ("getter", "name", "value", "label"),
    [
        ("get_string", "s", 1, "string"),
        ("get_number", "x", "1", "number"),
        ("get_bool", "b", 1, "bool"),
        ("get_strings", "ss", "abc", "list"),
        ("get_numbers", "xs", 3, "list"),
        ("get_bools", "bs", True, "list"),
    ],
)
def test_inputs_wrong_type_raises_type_error(
    getter: str, name: str, value: Any, label: str
) -> None:
    ins = _ins({name: value})
    with pytest.raises(TypeError) as info:
        getattr(ins, getter)(name)
    message = str(info.value)
    assert f"input '{name}'" in message
    assert label in message
    assert type(value).__name__ in message


def test_inputs_are_read_only() -> None:
    ins = _ins({"s": "a"})
    with pytest.raises(TypeError):
        ins["s"] = "b"  # type: ignore[index]


# ================================================================ log, names, binding


def test_log_keeps_ten_newest_first() -> None:
    action, _ = bound()
    for i in range(15):
        action.log(f"m{i}")
    snap = action.log_snapshot()
    assert LOG_LENGTH == 10
    assert [m.message for m in snap] == [f"m{i}" for i in range(14, 4, -1)]
    stamps = [m.timestamp_ms for m in snap]
    assert all(type(t) is int for t in stamps)
    assert stamps == sorted(stamps, reverse=True)
    assert abs(stamps[0] - time.time() * 1000) < 5000


def test_log_converts_to_text() -> None:
    action, _ = bound()
    action.log(42)  # type: ignore[arg-type]
    assert action.log_snapshot()[0].message == "42"


def test_unbound_action_helpers_raise_clearly() -> None:
    action = Probe()
    assert action.name == "Probe"
    with pytest.raises(RuntimeError, match="not bound"):
        action.sleep(0)
    with pytest.raises(RuntimeError, match="not bound"):
        _ = action.stop_requested
    action.log("no engine")  # logging works without an engine (timestamp 0)
    assert action.log_snapshot()[0].timestamp_ms == 0


def test_bound_names() -> None:
    action, _ = bound()
    assert action.name == "Probe_0"
    assert action.graph_name == "g"


# ================================================================ one run (Action.run_once)


class Scripted(Action):
    """Returns (or raises) what the test sets, after writing an output and reading an input."""

    outcome: Any = True

    def on_run(self) -> bool:
        self.outputs["echo"] = self.inputs.get_string("text")
        if isinstance(self.outcome, BaseException):
            raise self.outcome
        return self.outcome  # type: ignore[no-any-return]


def _scripted(outcome: Any) -> Scripted:
    action = Scripted()
    action.outcome = outcome
    action.initialize(
        RunControl(MonotonicClock()),
        "Scripted_3",
        "g",
        {"text": Parameter("text", "string")},
        {"echo": Parameter("echo", "string")},
    )
    return action


@pytest.mark.parametrize(("outcome", "result"), [(True, Result.TRUE), (False, Result.FALSE)])
def test_run_once_maps_the_return_value(outcome: bool, result: Result) -> None:
    values = {"text": "hi"}
    assert _scripted(outcome).run_once(values) == (result, {"echo": "hi"}, None)


def test_run_once_a_stop_is_the_stopped_result_without_error() -> None:
    result, outputs, error = _scripted(StopRequested("Scripted_3")).run_once({"text": "a"})
    assert (result, outputs, error) == (Result.STOPPED, {"echo": "a"}, None)


@pytest.mark.parametrize(
    ("outcome", "message"),
    [
        (ValueError("bad input"), "Scripted_3 failed: bad input"),
        (1, "Scripted_3 failed: on_run() must return True or False, not int"),
        (None, "Scripted_3 failed: on_run() must return True or False, not NoneType"),
    ],
)
def test_run_once_an_exception_or_a_non_bool_is_an_error_naming_the_node(
    outcome: Any, message: str
) -> None:
    result, outputs, error = _scripted(outcome).run_once({"text": "x"})
    assert result is Result.ERROR
    assert outputs == {"echo": "x"}  # what was written before the failure is kept
    assert isinstance(error, ActionError)
    assert str(error).endswith(message)
    assert (error.graph, error.node) == ("g", "Scripted_3")
    assert type(error.__cause__) is (ValueError if isinstance(outcome, Exception) else TypeError)


def test_run_once_without_outputs_gives_the_shared_empty_values() -> None:
    action, _ = bound()
    first = action.run_once({})
    second = action.run_once({})
    assert first == (Result.TRUE, {}, None)
    assert first[1] is second[1]  # no dict made per run


def test_holds_resources_and_release_resources_without_a_registrar() -> None:
    action, _ = bound()
    assert not action.holds_resources
    assert action.release_resources() == 0


# ================================================================ the helpers inside an engine


class Sleeper(Action):
    seen: ClassVar[list[str]] = []

    def on_run(self) -> bool:
        Sleeper.seen.append(f"{self.graph_name}/{self.name}")
        self.log("going to sleep")
        try:
            self.sleep(30.0)
        except StopRequested:
            self.log("woken by stop")
            raise
        return True


class Chatty(Action):
    def on_run(self) -> bool:
        for i in range(12):
            self.log(f"line {i}")
        return True


@pytest.fixture
def engine() -> Iterator[ActionEngine]:
    catalog = ActionCatalog(use_entry_points=False)
    catalog.register(Sleeper, parse_umrf({"name": "Sleeper", "type": "sync"}))
    catalog.register(Chatty, parse_umrf({"name": "Chatty", "type": "sync"}))
    with ActionEngine("me", actions=catalog, clock=ScaledClock(10), stop_timeout=5) as eng:
        yield eng


def _single(name: str, graph_name: str) -> Any:
    return parse_graph({"graph_name": graph_name, "actions": [{"name": name, "type": "sync"}]})


def test_stop_requested_from_sleep_gives_on_stopped(engine: ActionEngine) -> None:
    Sleeper.seen = []
    run = engine.start(_single("Sleeper", "sleeping"))
    deadline = time.monotonic() + WAIT
    while not Sleeper.seen and time.monotonic() < deadline:
        time.sleep(0.005)
    t0 = time.monotonic()
    assert engine.stop(run, timeout=WAIT) is Result.STOPPED
    assert time.monotonic() - t0 < 0.3  # well under the 0.5 s (5 clock-s) stop timeout
    assert Sleeper.seen == ["sleeping/Sleeper_0"]
    messages = [m["message"] for m in engine.graph_json(run)["actions"][0]["runtime"]["messages"]]
    assert messages == ["woken by stop", "going to sleep"]


def test_engine_keeps_ten_log_lines(engine: ActionEngine) -> None:
    outcome = engine.run(_single("Chatty", "chatty"), timeout=WAIT)
    assert outcome.result is Result.TRUE
    messages = engine.graph_json("chatty")["actions"][0]["runtime"]["messages"]
    assert [m["message"] for m in messages] == [f"line {i}" for i in range(11, 1, -1)]
