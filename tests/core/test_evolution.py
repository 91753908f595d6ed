"""The evolution kernel (temoto.core._fast): both builds, against each other and a model."""

from __future__ import annotations

import os
import subprocess
import sys
from array import array
from dataclasses import dataclass
from types import ModuleType
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from temoto.core import _fast
from temoto.core._fast import _evolution_py as pure
from temoto.core._runtime import RESPONSES, RESULT_CODES
from temoto.core.states import Response, Result

RUN, PAUSE, RESTART, STOP, BYPASS, IGNORE, LOOP = range(7)
TRUE, FALSE, STOPPED, ERROR = range(4)


@dataclass
class Topo:
    """A graph as plain lists: ``edges`` are (parent, child, responses[4]); slots are unique
    (child, parent) pairs with a required flag."""

    n: int
    edges: list[tuple[int, int, list[int]]]
    required: dict[tuple[int, int], bool]
    exit_node: int = -1

    def arrays(self) -> dict[str, Any]:
        slots = sorted(self.required)  # by child, then parent
        slot_of = {key: i for i, key in enumerate(slots)}
        slot_start = [0] * (self.n + 1)
        for child, _ in slots:
            slot_start[child + 1] += 1
        for i in range(self.n):
            slot_start[i + 1] += slot_start[i]
        ordered = sorted(range(len(self.edges)), key=lambda e: self.edges[e][0])
        edge_start = [0] * (self.n + 1)
        for parent, _, _ in self.edges:
            edge_start[parent + 1] += 1
        for i in range(self.n):
            edge_start[i + 1] += edge_start[i]
        return {
            "n_nodes": self.n,
            "edge_start": edge_start,
            "edge_child": [self.edges[e][1] for e in ordered],
            "edge_slot": [slot_of[self.edges[e][1], self.edges[e][0]] for e in ordered],
            "edge_response": [r for e in ordered for r in self.edges[e][2]],
            "slot_start": slot_start,
            "slot_required": [1 if self.required[key] else 0 for key in slots],
            "exit_node": self.exit_node,
        }

    def build(self, impl: ModuleType) -> Any:
        return impl.Evolution(**self.arrays())


class Model:
    """The propagation rules written the obvious way (sets and dicts), as the reference."""

    def __init__(self, topo: Topo) -> None:
        arrays = topo.arrays()
        self.topo = topo
        self.by_parent: dict[int, list[tuple[int, int, list[int]]]] = {}
        edge = 0
        for parent in range(topo.n):
            for _ in range(arrays["edge_start"][parent], arrays["edge_start"][parent + 1]):
                child = arrays["edge_child"][edge]
                row = arrays["edge_response"][edge * 4 : edge * 4 + 4]
                self.by_parent.setdefault(parent, []).append((edge, child, row))
                edge += 1
        self.received: set[tuple[int, int]] = set()

    def ready(self, child: int) -> bool:
        return all(
            (c, p) in self.received
            for (c, p), req in self.topo.required.items()
            if c == child and req
        )

    def propagate(self, parent: int, result: int) -> list[tuple[int, int, bool]]:
        default = {TRUE: RUN, FALSE: RUN, STOPPED: IGNORE, ERROR: BYPASS}[result]
        out: list[tuple[int, int, bool]] = []
        bypassed: set[int] = set()
        work = [parent]
        while work:
            node = work.pop(0)
            for edge, child, row in self.by_parent.get(node, []):
                self.received.add((child, node))
                response = row[result] if row[result] != -1 else default
                ready = self.ready(child)
                if response == BYPASS and child != self.topo.exit_node:
                    if child in bypassed:
                        response = LOOP
                    else:
                        bypassed.add(child)
                        work.append(child)
                out.append((edge, response, ready))
                if child == self.topo.exit_node and (
                    response == BYPASS or (ready and response != IGNORE)
                ):
                    return out
        return out


def unpack(steps: list[int]) -> list[tuple[int, int, bool]]:
    return [(s >> pure.SHIFT, (s >> 1) & 7, bool(s & 1)) for s in steps]


def chain(n: int, exit_node: int = -1) -> Topo:
    return Topo(
        n,
        [(i, i + 1, [-1, -1, -1, -1]) for i in range(n - 1)],
        {(i + 1, i): True for i in range(n - 1)},
        exit_node,
    )


# ----------------------------------------------------------------------------- rules


def test_defaults_follow_eq_6_1(evolution_impl: ModuleType) -> None:
    impl = evolution_impl
    assert [impl.default_response(r) for r in range(4)] == [RUN, RUN, IGNORE, BYPASS]
    with pytest.raises(ValueError, match="unknown result"):
        impl.default_response(7)


@pytest.mark.parametrize(
    ("states", "verdict"),
    [
        ([], pure.V_NONE),
        ([pure.S_IDLE_TRUE], pure.V_RUN),
        ([pure.S_IDLE_FALSE, pure.S_OTHER], pure.V_RUN),
        ([pure.S_IDLE_TRUE, pure.S_ERROR], pure.V_ERROR),
        ([pure.S_ERROR], pure.V_ERROR),
        ([pure.S_STOPPED, pure.S_OTHER], pure.V_NONE),
    ],
)
def test_default_evolution_over_one_hot_rows(
    evolution_impl: ModuleType, states: list[int], verdict: int
) -> None:
    rows = array("b", bytes(len(states) * pure.N_STATES))
    for i, state in enumerate(states):
        rows[i * pure.N_STATES + state] = 1
    assert evolution_impl.default_evolution(rows, len(states)) == verdict


def test_default_evolution_rejects_short_rows(evolution_impl: ModuleType) -> None:
    with pytest.raises(ValueError, match="rows"):
        evolution_impl.default_evolution(array("b", bytes(4)), 1)


def test_chain_runs_one_child_at_a_time(evolution_impl: ModuleType) -> None:
    evo = chain(4).build(evolution_impl)
    assert evo.missing_parents(1) == 1
    assert not evo.received_any(1)
    assert unpack(evo.propagate(0, TRUE)) == [(0, RUN, True)]
    assert evo.missing_parents(1) == 0
    assert evo.received_any(1)
    assert unpack(evo.propagate(1, FALSE)) == [(1, RUN, True)]
    assert unpack(evo.propagate(2, STOPPED)) == [(2, IGNORE, True)]
    assert unpack(evo.propagate(3, TRUE)) == []


def test_required_and_optional_parents(evolution_impl: ModuleType) -> None:
    # 0 -> 2 (required), 1 -> 2 (optional)
    topo = Topo(3, [(0, 2, [-1] * 4), (1, 2, [-1] * 4)], {(2, 0): True, (2, 1): False})
    evo = topo.build(evolution_impl)
    assert unpack(evo.propagate(1, TRUE)) == [(1, RUN, False)]
    assert unpack(evo.propagate(0, TRUE)) == [(0, RUN, True)]


def test_written_conditions_win(evolution_impl: ModuleType) -> None:
    topo = Topo(2, [(0, 1, [STOP, PAUSE, RESTART, RUN])], {(1, 0): True})
    evo = topo.build(evolution_impl)
    assert [unpack(evo.propagate(0, r))[0][1] for r in range(4)] == [STOP, PAUSE, RESTART, RUN]


def test_bypass_wave_travels_and_stops_at_a_loop(evolution_impl: ModuleType) -> None:
    # 0 -> 1 -> 2 -> 1 (a cycle), errors bypass by default
    topo = Topo(
        3,
        [(0, 1, [-1] * 4), (1, 2, [-1] * 4), (2, 1, [-1] * 4)],
        {(1, 0): True, (2, 1): True, (1, 2): False},
    )
    evo = topo.build(evolution_impl)
    assert unpack(evo.propagate(0, ERROR)) == [
        (0, BYPASS, True),
        (1, BYPASS, True),
        (2, LOOP, True),
    ]
    # a new wave starts afresh
    assert unpack(evo.propagate(0, ERROR))[:2] == [(0, BYPASS, True), (1, BYPASS, True)]


def test_wave_ends_at_the_exit(evolution_impl: ModuleType) -> None:
    # 0 -> 1 (exit), 0 -> 2; the exit is reached first, so 2 is never told
    topo = Topo(3, [(0, 1, [-1] * 4), (0, 2, [-1] * 4)], {(1, 0): True, (2, 0): True}, 1)
    evo = topo.build(evolution_impl)
    assert unpack(evo.propagate(0, TRUE)) == [(0, RUN, True)]
    assert not evo.received_any(2)
    evo = topo.build(evolution_impl)
    assert unpack(evo.propagate(0, ERROR)) == [(0, BYPASS, True)]


def test_received_flags_carry_over(evolution_impl: ModuleType) -> None:
    topo = chain(3)
    evo = topo.build(evolution_impl)
    evo.propagate(0, TRUE)
    flags = evo.received_flags()
    assert flags == b"\x01\x00"
    again = evolution_impl.Evolution(**{**topo.arrays(), "received": flags})
    assert again.missing_parents(1) == 0
    assert again.missing_parents(2) == 1


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"edge_start": [0, 1, 1]}, "offsets"),
        ({"edge_child": [9, 2]}, "out of range"),
        ({"edge_slot": [1, 0]}, "not a slot"),
        ({"edge_response": [9] * 8}, "response code"),
        ({"exit_node": 5}, "exit node"),
        ({"received": [1]}, "one flag per slot"),
        ({"n_nodes": -1}, "n_nodes"),
    ],
)
def test_bad_topology_is_refused(
    evolution_impl: ModuleType, change: dict[str, Any], message: str
) -> None:
    arrays = {**chain(3).arrays(), **change}
    with pytest.raises(ValueError, match=message):
        evolution_impl.Evolution(**arrays)


def test_bad_calls_are_refused(evolution_impl: ModuleType) -> None:
    evo = chain(3).build(evolution_impl)
    with pytest.raises(IndexError):
        evo.propagate(3, TRUE)
    with pytest.raises(ValueError, match="result"):
        evo.propagate(0, 4)
    with pytest.raises(IndexError):
        evo.missing_parents(-1)
    with pytest.raises(IndexError):
        evo.received_any(3)


def test_engine_codes_match_the_kernel() -> None:
    assert [RESULT_CODES[r] for r in (Result.TRUE, Result.FALSE, Result.STOPPED, Result.ERROR)] == [
        pure.R_TRUE,
        pure.R_FALSE,
        pure.R_STOPPED,
        pure.R_ERROR,
    ]
    assert RESPONSES.index(Response.RUN) == pure.P_RUN
    assert RESPONSES.index(Response.PAUSE) == pure.P_PAUSE
    assert RESPONSES.index(Response.RESTART) == pure.P_RESTART
    assert RESPONSES.index(Response.STOP) == pure.P_STOP
    assert RESPONSES.index(Response.BYPASS) == pure.P_BYPASS
    assert RESPONSES.index(Response.IGNORE) == pure.P_IGNORE
    # the engine takes the codes from the kernel in use (temoto.core._fast), never a copy
    names = ("SHIFT", "P_RUN", "P_PAUSE", "P_RESTART", "P_STOP", "P_BYPASS", "P_IGNORE", "P_LOOP")
    names += ("R_TRUE", "R_FALSE", "R_STOPPED", "R_ERROR")
    assert {n: getattr(_fast, n) for n in names} == {n: getattr(pure, n) for n in names}
    kernel = sys.modules[_fast.Evolution.__module__]
    assert {n: getattr(kernel, n) for n in names} == {n: getattr(pure, n) for n in names}


# ----------------------------------------------------------------------------- properties


@st.composite
def topologies(draw: st.DrawFn) -> tuple[Topo, list[tuple[int, int]]]:
    n = draw(st.integers(1, 12))
    pairs = draw(
        st.lists(st.tuples(st.integers(0, n - 1), st.integers(0, n - 1)), max_size=30, unique=True)
    )
    response = st.integers(-1, 5)
    edges = [(p, c, draw(st.lists(response, min_size=4, max_size=4))) for p, c in pairs]
    required = {(c, p): draw(st.booleans()) for p, c in pairs}
    exit_node = draw(st.integers(-1, n - 1))
    calls = draw(st.lists(st.tuples(st.integers(0, n - 1), st.integers(0, 3)), max_size=25))
    return Topo(n, edges, required, exit_node), calls


@settings(max_examples=300, deadline=None, database=None)
@given(topologies())
def test_both_builds_match_the_model(case: tuple[Topo, list[tuple[int, int]]]) -> None:
    topo, calls = case
    model = Model(topo)
    builds = _builds(topo)
    for parent, result in calls:
        expected = model.propagate(parent, result)
        for evo in builds:
            assert unpack(evo.propagate(parent, result)) == expected
    for evo in builds:
        for node in range(topo.n):
            assert (evo.missing_parents(node) == 0) == model.ready(node)
            assert evo.received_any(node) == any(c == node for c, _ in model.received)
        assert evo.received_flags() == builds[0].received_flags()


@settings(max_examples=300, deadline=None, database=None)
@given(topologies())
def test_advance_is_propagate_for_one_run_step(
    case: tuple[Topo, list[tuple[int, int]]],
) -> None:
    """``advance`` takes a wave that is one `run` step to a non-exit child, and nothing else:
    where it declines, it changed nothing and ``propagate`` gives the model's wave."""
    topo, calls = case
    model = Model(topo)
    builds = _builds(topo)
    for parent, result in calls:
        expected = model.propagate(parent, result)
        one_step = (
            len(expected) == 1
            and expected[0][1] == RUN
            and topo.arrays()["edge_child"][expected[0][0]] != topo.exit_node
            and sum(1 for p, _, _ in topo.edges if p == parent) == 1
        )
        for evo in builds:
            edge = evo.advance(parent, result)
            if one_step:
                assert edge == expected[0][0] << 1 | expected[0][2]
            else:
                assert edge == -1
                assert unpack(evo.propagate(parent, result)) == expected
    for evo in builds:
        for node in range(topo.n):
            assert (evo.missing_parents(node) == 0) == model.ready(node)
        assert evo.received_flags() == builds[0].received_flags()


@settings(max_examples=200, deadline=None, database=None)
@given(topologies(), topologies())
def test_fresh_is_a_new_kernel_of_the_same_graph(
    case: tuple[Topo, list[tuple[int, int]]], other: tuple[Topo, list[tuple[int, int]]]
) -> None:
    """``fresh()`` of a used kernel (a repeated run's) behaves as a newly built one, and the
    two do not disturb each other (they share only the arrays no kernel writes)."""
    topo, calls = case
    later = [(p % topo.n, r) for p, r in other[1]]  # the new run's calls
    impls = [pure]
    compiled = _compiled()
    if compiled is not None:
        impls.append(compiled)
    for impl in impls:
        used = topo.build(impl)
        for parent, result in calls:
            used.propagate(parent, result)
        flags = used.received_flags()
        fresh = used.fresh()
        assert type(fresh) is type(used)
        assert fresh.n_nodes == used.n_nodes
        assert fresh.exit_node == used.exit_node
        new = topo.build(impl)
        assert fresh.received_flags() == new.received_flags()
        for parent, result in later:
            assert fresh.propagate(parent, result) == new.propagate(parent, result)
            assert fresh.advance(parent, result) == new.advance(parent, result)
        for node in range(topo.n):
            assert fresh.missing_parents(node) == new.missing_parents(node)
            assert fresh.received_any(node) == new.received_any(node)
        assert used.received_flags() == flags  # the used kernel's run state is its own


def test_advance_refuses_bad_calls(evolution_impl: ModuleType) -> None:
    evo = chain(3).build(evolution_impl)
    with pytest.raises(IndexError):
        evo.advance(3, TRUE)
    with pytest.raises(ValueError, match="result"):
        evo.advance(0, 4)
    assert evo.advance(0, TRUE) == 0 << 1 | 1  # the chain's first link: its child is ready
    assert evo.advance(0, TRUE) == 0 << 1 | 1  # again: the parent stays received
    assert evo.advance(1, STOPPED) == -1  # the response `ignore`: propagate's business
    assert evo.advance(2, TRUE) == -1  # the last node has no relation


def _builds(topo: Topo) -> list[Any]:
    """The topology's kernel in the pure build, and in the compiled one where it exists."""
    compiled = _compiled()
    return [topo.build(pure)] + ([topo.build(compiled)] if compiled is not None else [])


def _compiled() -> ModuleType | None:
    try:
        from temoto.core._fast import _evolution_c  # type: ignore[attr-defined]
    except ImportError:
        if os.environ.get("TEMOTO_REQUIRE_EXTENSIONS") == "1":
            raise
        return None
    return _evolution_c  # type: ignore[no-any-return]


# ----------------------------------------------------------------------------- selector


def _selector(env: dict[str, str]) -> str:
    code = "from temoto.core import _fast; print(_fast.BUILD, sorted(_fast.kernels()))"
    full = {k: v for k, v in os.environ.items() if not k.startswith("TEMOTO_")}
    proc = subprocess.run(
        [sys.executable, "-c", code],
        env={**full, **env},
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    )
    return proc.stdout.strip()


def test_selector_prefers_the_compiled_build_when_installed() -> None:
    import importlib.util

    built = all(
        importlib.util.find_spec(f"temoto.core._fast._{kernel}_c") is not None
        for kernel in ("evolution", "refbook")
    )
    assert _selector({}).startswith("compiled" if built else "pure")


def test_selector_honours_no_extensions() -> None:
    assert _selector({"TEMOTO_NO_EXTENSIONS": "1"}) == "pure ['evolution', 'refbook']"
    assert _selector({"TEMOTO_NO_EXTENSIONS": "1", "TEMOTO_REQUIRE_EXTENSIONS": "1"}).startswith(
        "pure"
    )
