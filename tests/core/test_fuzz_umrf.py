"""Property tests: broken UMRF documents only ever raise ConfigError.

Every test starts from the real upstream documents of the conformance folder, mutates them at
random places (wrong types, odd strings, huge and non-finite numbers, deep nesting, deleted,
inserted, renamed and duplicated members) and feeds the result to the parsers. Whatever
parses must also validate, render as DOT and survive a serialise-and-parse round trip.
"""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any, TypeVar

import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from temoto.core.documents import dump_umrf, graph_to_dict, load_umrf, parse_graph_text
from temoto.core.dot import graph_to_dot
from temoto.core.graph import UmrfGraph, parse_graph
from temoto.core.params import Parameter
from temoto.core.states import NodeState, Result
from temoto.core.umrf import Umrf, parse_umrf
from temoto.core.validation import validate_graph
from temoto.errors import ConfigError, GraphDefinitionError

SHARED = Path(__file__).resolve().parents[2].parent / "shared"
UPSTREAM = SHARED / "conformance" / "umrf" / "upstream"
if not UPSTREAM.is_dir():  # the seeds are upstream's documents: nothing to mutate without them
    pytest.skip(f"upstream conformance data not found at {UPSTREAM}", allow_module_level=True)

GRAPH_FILES = sorted(UPSTREAM.glob("actionengine_*graph.json"))
UMRF_FILES = sorted(UPSTREAM.glob("actionengine_*.umrf.json"))
LEGACY_GRAPH_FILES = [
    *sorted(UPSTREAM.glob("legacy_*.umrfg.json")),
    UPSTREAM / "legacy_gptparser_prompt_example_move_1.json",
]
LEGACY_UMRF_FILES = sorted(UPSTREAM.glob("legacy_*.umrf.json"))

TEXTS = {p.name: p.read_text(encoding="utf-8") for p in GRAPH_FILES + LEGACY_GRAPH_FILES}
GRAPHS = [json.loads(p.read_text(encoding="utf-8")) for p in GRAPH_FILES]
UMRFS = [json.loads(p.read_text(encoding="utf-8")) for p in UMRF_FILES]
LEGACY_GRAPHS = [json.loads(p.read_text(encoding="utf-8")) for p in LEGACY_GRAPH_FILES]
LEGACY_UMRFS = [json.loads(p.read_text(encoding="utf-8")) for p in LEGACY_UMRF_FILES]

# The whole module runs in well under a minute on two cores. For a long soak run, scale the
# number of examples: TEMOTO_FUZZ_SCALE=50 python3 -m pytest tests/core/test_fuzz_umrf.py
SCALE = float(os.environ.get("TEMOTO_FUZZ_SCALE", "1"))
FUZZ = settings(
    max_examples=max(1, int(1000 * SCALE)),
    deadline=None,
    database=None,  # no .hypothesis/ directory in the work tree
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
HANG_S = 20.0  # one example taking longer than this is treated as a hang
ACTION_RESULTS = (Result.TRUE, Result.FALSE, Result.STOPPED, Result.ERROR)

T = TypeVar("T")


# --- vocabulary --------------------------------------------------------------------------------


def _harvest(doc: Any, out: set[str]) -> None:
    todo = [doc]
    while todo:
        node = todo.pop()
        if isinstance(node, dict):
            out.update(node)
            todo.extend(node.values())
        elif isinstance(node, list):
            todo.extend(node)
        elif isinstance(node, str):
            out.add(node)


_WORDS: set[str] = set()
for _doc in GRAPHS + UMRFS + LEGACY_GRAPHS + LEGACY_UMRFS:
    _harvest(_doc, _WORDS)

#: Strings with a meaning somewhere in the format, plus every string of the seed documents.
# fmt: off
VOCAB = sorted(
    _WORDS
    | {
        "", " ", "::", "a::b", ":", "_", "_0", "x_1", "graph_entry", "graph_exit", "umrf_actions",
        "id", "effect", "synchronous", "asynchronous", "execute_first", "stop_when_received",
        "package_name", "pvf_example", "sync", "async", "spontaneous", "weird",
        "string", "strings", "number", "numbers", "bool", "bools", "cir_pointer",
        "on_true -> run", "on_false -> stop", "on_stopped -> restart", "on_error -> ignore",
        "on_true -> pause", "on_false->bypass", "on_halted -> run", "on_true -> fly", "->",
        "on_true -> run -> stop", "RUNNING", "FINISHED", "ERROR", "UNINITIALIZED", "HALTED",
        "\x00", "\ud800", "\u202e", "ü✓ 名前", "a\nb", 'quo"te', "back\\slash", "x" * 300,
    }
)
KEYS = st.sampled_from(VOCAB) | st.text(max_size=8)

SPECIAL_NUMBERS = [
    0, 1, -1, 2, 3, 2**31, 2**32 - 1, 2**32, 2**53 + 1, 2**63, 2**64, 10**400, -(10**400),
    1e308, -1e308, 1.7976931348623157e308, 5e-324, -0.0, 0.5, 1.0, 3.0, 1e15, 1e16,
    float("inf"), float("-inf"), float("nan"),
]
# fmt: on

SCALARS = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(),
    st.sampled_from(SPECIAL_NUMBERS),
    st.floats(),
    st.text(max_size=12),
    st.sampled_from(VOCAB),
)


def nest(depth: int, kind: str) -> Any:
    """A value nested ``depth`` levels deep, built without recursion."""
    value: Any = "bottom"
    for level in range(depth):
        if kind == "list":
            value = [value]
        elif kind == "dict":
            value = {"k": value}
        else:  # parameter namespaces, the shape the parser recurses into
            value = {f"ns{level}": value} if level else {"p": {"pvf_type": "string"}}
    return value


DEEP = st.builds(nest, st.integers(200, 300), st.sampled_from(["list", "dict", "tree"]))

# Fragments in the shape of the format, so that mutated documents often still parse and reach
# the validator with odd but well-typed content.
NAME = st.sampled_from(VOCAB)
SMALL_ID = st.sampled_from([0, 1, 2, 3, 4, 5, 7, 2**32 - 1])
RELATION = st.fixed_dictionaries(
    {"name": NAME},
    optional={
        "instance_id": SMALL_ID,
        "required": st.booleans(),
        "conditions": st.lists(st.sampled_from(VOCAB), max_size=3),
        "remap": st.lists(st.fixed_dictionaries({"from": NAME, "to": NAME}), max_size=2),
    },
)
LEAF = st.fixed_dictionaries(
    {
        "pvf_type": st.sampled_from(
            ["string", "strings", "number", "numbers", "bool", "bools", "cir_pointer", ""]
        )
    },
    optional={
        "pvf_value": SCALARS | st.lists(SCALARS, max_size=3),
        "pvf_required": st.booleans(),
        "pvf_updatable": st.booleans(),
        "pvf_allowed_values": st.lists(SCALARS, max_size=3),
    },
)

WILD = st.one_of(
    st.recursive(
        SCALARS,
        lambda kids: st.lists(kids, max_size=4) | st.dictionaries(KEYS, kids, max_size=4),
        max_leaves=10,
    ),
    DEEP,
)
# Well-typed replacements: the document usually still parses and the validator sees odd
# relations, parameters and names.
GENTLE = st.one_of(
    NAME,
    SMALL_ID,
    st.booleans(),
    RELATION,
    st.lists(RELATION, max_size=3),
    LEAF,
    st.dictionaries(NAME, LEAF, max_size=3),
    st.lists(st.sampled_from(VOCAB), max_size=3),
)
VALUES = WILD | GENTLE


# --- mutation ----------------------------------------------------------------------------------

Key = str | int


def locate(data: st.DataObject, doc: Any, max_depth: int = 12) -> list[Key]:
    """A random path into ``doc`` (possibly empty: the root)."""
    path: list[Key] = []
    node = doc
    while isinstance(node, dict | list) and node and len(path) < max_depth:
        if data.draw(st.integers(0, 3), label="stop here") == 0:
            break
        key: Key
        if isinstance(node, dict):
            key = data.draw(st.sampled_from(list(node)), label="key")
        else:
            key = data.draw(st.integers(0, len(node) - 1), label="index")
        path.append(key)
        node = node[key]
    return path


def update(doc: Any, path: list[Key], change: Callable[[Any], Any]) -> Any:
    """``doc`` with ``change`` applied at ``path``; containers on the path are copied."""
    if not path:
        return change(doc)
    head, rest = path[0], path[1:]
    out = dict(doc) if isinstance(doc, dict) else list(doc)
    out[head] = update(doc[head], rest, change)  # type: ignore[index]
    return out


def mutate(data: st.DataObject, doc: Any) -> Any:
    """Apply 1 to 3 random mutations (the seed document itself is never modified)."""
    for _ in range(data.draw(st.integers(1, 3), label="mutations")):
        path = locate(data, doc)
        op = data.draw(
            st.sampled_from(["replace", "delete", "insert", "duplicate", "rename"]), label="op"
        )
        if op == "replace":
            value = data.draw(VALUES, label="value")
            doc = update(doc, path, lambda _old, v=value: v)
        elif op == "delete" and path:
            key = path[-1]

            def delete(parent: Any, key: Key = key) -> Any:
                out = dict(parent) if isinstance(parent, dict) else list(parent)
                del out[key]  # type: ignore[arg-type]
                return out

            doc = update(doc, path[:-1], delete)
        elif op in ("insert", "duplicate", "rename"):
            doc = update(doc, path, lambda node, op=op: change_container(data, node, op))
    return doc


def change_container(data: st.DataObject, node: Any, op: str) -> Any:
    if isinstance(node, list):
        out = list(node)
        pos = data.draw(st.integers(0, len(out)), label="position")
        if op == "duplicate" and out:
            out.insert(pos, out[data.draw(st.integers(0, len(out) - 1), label="copied")])
        else:
            out.insert(pos, data.draw(VALUES, label="inserted"))
        return out
    if isinstance(node, dict):
        dout = dict(node)
        if op == "rename" and dout:
            old = data.draw(st.sampled_from(list(dout)), label="renamed")
            dout[data.draw(KEYS, label="new name")] = dout.pop(old)
        elif op == "duplicate" and dout:
            old = data.draw(st.sampled_from(list(dout)), label="copied")
            dout[data.draw(KEYS, label="copy name")] = dout[old]
        else:
            dout[data.draw(KEYS, label="new key")] = data.draw(VALUES, label="inserted")
        return dout
    return data.draw(VALUES, label="value")


# --- guards ------------------------------------------------------------------------------------


class ExampleHangError(AssertionError):
    """One example ran for longer than :data:`HANG_S`."""


def _hang(signum: int, frame: object) -> None:
    raise ExampleHangError(f"example still running after {HANG_S:g} s (a hang?)")


@contextmanager
def hang_guard(seconds: float = HANG_S) -> Iterator[None]:
    """Interrupt one example that hangs, so Hypothesis reports (and shrinks) it.

    Uses SIGALRM in the main thread; any timer already armed (pytest-timeout's signal method)
    is saved and re-armed with its remaining time afterwards.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    start = time.monotonic()
    old_handler = signal.signal(signal.SIGALRM, _hang)
    old_delay, old_interval = signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old_handler)
        if old_delay:
            left = max(old_delay - (time.monotonic() - start), 0.001)
            signal.setitimer(signal.ITIMER_REAL, left, old_interval)


def config_error_or(call: Callable[[], T]) -> T | None:
    """Run ``call``; a ConfigError means "rejected" (None), anything else propagates."""
    try:
        return call()
    except ConfigError:
        return None


# --- checks of a parsed graph ------------------------------------------------------------------


def params_key(params: Mapping[str, Parameter]) -> list[Any]:
    return [
        (n, p.type, repr(p.value), p.required, p.updatable, p.allowed_values)
        for n, p in params.items()
    ]


def action_key(act: Umrf) -> tuple[Any, ...]:
    return (
        act.full_name,
        act.type,
        act.actor,
        act.description,
        act.state,
        [(r.full_name, r.required, [r.response(x) for x in ACTION_RESULTS]) for r in act.parents],
        [(r.full_name, r.remap) for r in act.children],
        params_key(act.input_parameters),
        params_key(act.output_parameters),
        act.gui_attributes,
        act.runtime_messages,
    )


def graph_key(graph: UmrfGraph) -> tuple[Any, ...]:
    """What a serialise-and-parse round trip must keep (actions get sorted by full name)."""
    return (
        graph.name,
        graph.description,
        graph.state,
        graph.entry,
        [(r.full_name, r.required, [r.response(x) for x in ACTION_RESULTS]) for r in graph.exit],
        sorted((action_key(a) for a in graph.actions), key=lambda k: str(k[0])),
    )


def check_parsed_graph(data: st.DataObject, graph: UmrfGraph) -> None:
    names = sorted(graph.signature().inputs)
    supplied = data.draw(
        st.none() | st.sets(st.sampled_from(names) | st.sampled_from(VOCAB), max_size=4)
        if names
        else st.none() | st.sets(st.sampled_from(VOCAB), max_size=2),
        label="supplied",
    )
    report = validate_graph(graph, supplied=supplied)  # never raises
    event("validated: " + ("ok" if report.ok else "errors"))
    assert report.graph == graph.name
    for issue in report.errors + report.warnings:
        assert isinstance(issue.path, str)
        assert isinstance(issue.message, str)
        assert issue.message
        str(issue)
    if report.ok:
        report.raise_for_errors("fuzz.graph.json")
    else:
        with pytest.raises(GraphDefinitionError) as info:
            report.raise_for_errors("fuzz.graph.json")
        assert info.value.path == report.errors[0].path

    # The canonical form parses back, and serialising again changes nothing.
    canonical = graph_to_dict(graph)
    again = parse_graph(canonical)
    assert graph_to_dict(again) == canonical
    assert graph_key(again) == graph_key(graph)
    json.dumps(canonical, allow_nan=True)

    states = {
        a.full_name: data.draw(st.sampled_from(VOCAB), label="state") for a in graph.actions[:3]
    }
    text = graph_to_dot(graph, states=states)
    assert text.startswith("digraph ")
    assert text.endswith("}\n")
    text.encode("utf-8")  # no lone surrogates left


def parse_text(text: str) -> UmrfGraph | None:
    return config_error_or(lambda: parse_graph_text(text, file="fuzz.json"))


# --- tests -------------------------------------------------------------------------------------


@pytest.mark.timeout(120)
@FUZZ
@given(st.data())
def test_mutated_graphs_parse_validate_and_round_trip_or_raise_config_error(
    data: st.DataObject,
) -> None:
    seed = data.draw(st.sampled_from(GRAPHS), label="seed")
    doc = mutate(data, seed)
    with hang_guard():
        graph = config_error_or(lambda: parse_graph(doc, file="fuzz.graph.json"))
        event("parsed" if graph is not None else "rejected")
        if graph is not None:
            check_parsed_graph(data, graph)
        # The same document as text goes through the format detection (and, when the mutation
        # made it look legacy, through the legacy converter).
        text = json.dumps(doc)
        from_text = parse_text(text)
        if from_text is not None:
            check_parsed_graph(data, from_text)


@pytest.mark.timeout(120)
@FUZZ
@given(st.data())
def test_mutated_legacy_graphs_convert_or_raise_config_error(data: st.DataObject) -> None:
    seed = data.draw(st.sampled_from(LEGACY_GRAPHS), label="seed")
    doc = mutate(data, seed)
    with hang_guard():
        graph = parse_text(json.dumps(doc))
        if graph is not None:
            check_parsed_graph(data, graph)


@pytest.fixture(scope="module")
def scratch() -> Iterator[Path]:
    with tempfile.TemporaryDirectory(prefix="temoto-fuzz-") as name:
        yield Path(name)


@pytest.mark.timeout(120)
@FUZZ
@given(data=st.data())
def test_mutated_action_descriptions_parse_or_raise_config_error(
    data: st.DataObject, scratch: Path
) -> None:
    seed = data.draw(st.sampled_from(UMRFS + LEGACY_UMRFS), label="seed")
    doc = mutate(data, seed)
    with hang_guard():
        umrf = config_error_or(lambda: parse_umrf(doc, file="fuzz.umrf.json", warnings=[]))
        if umrf is not None:
            again = parse_umrf(dump_umrf(umrf))
            # The canonical form always writes a state (UNINITIALIZED when none was given).
            written = dataclasses.replace(umrf, state=umrf.state or NodeState.UNINITIALIZED)
            assert action_key(again) == action_key(written)
        # Through the file loader, which also converts legacy descriptions.
        path = scratch / "fuzz.umrf.json"
        path.write_text(json.dumps(doc), encoding="utf-8")
        config_error_or(lambda: load_umrf(path, warnings=[]))


JSONISH = st.lists(
    st.sampled_from(list('{}[]",:0123456789-+.eE \n\\tfalsenul')) | st.sampled_from(VOCAB),
    max_size=40,
).map("".join)


@pytest.mark.timeout(120)
@FUZZ
@given(
    st.one_of(
        st.text(),
        JSONISH,
        st.binary(max_size=64).map(lambda b: b.decode("latin-1")),
        st.integers(1, 200_000).map(lambda n: "[" * n),
        st.integers(1, 200_000).map(lambda n: '{"a":' * n),
        st.integers(4000, 10_000).map(lambda n: "9" * n),
        st.sampled_from(["NaN", "Infinity", "-Infinity", "null", "[]", "{}", '""', "1e999"]),
    )
)
def test_random_text_is_rejected_with_config_error(text: str) -> None:
    with hang_guard():
        graph = parse_text(text)
    assert graph is None or isinstance(graph, UmrfGraph)


@pytest.mark.timeout(120)
@FUZZ
@given(st.sampled_from(sorted(TEXTS)), st.data())
def test_truncated_and_spliced_files_are_rejected_with_config_error(
    name: str, data: st.DataObject
) -> None:
    text = TEXTS[name]
    cut = data.draw(st.integers(0, len(text)), label="cut")
    end = data.draw(st.integers(cut, len(text)), label="end")
    insert = data.draw(st.sampled_from(["", "}", "]", ",", '"', "\\", "\x00", "null"]))
    with hang_guard():
        parse_text(text[:cut])
        parse_text(text[:cut] + insert + text[end:])


@pytest.mark.timeout(120)
def test_every_prefix_of_every_file_is_rejected_with_config_error() -> None:
    # A sweep rather than a sample: every 13th prefix of every file, plus its last 20 ones.
    for text in TEXTS.values():
        cuts = set(range(0, len(text), 13)) | set(range(max(len(text) - 20, 0), len(text)))
        for cut in sorted(cuts):
            prefix = text[:cut]
            with hang_guard():
                graph = parse_text(prefix)
            # Only the whole document (perhaps without its final newline) parses.
            assert graph is None or prefix.strip() == text.strip(), (cut, prefix[-40:])
