"""RefBook (temoto.core._fast): the registrar's reference counts and dependency lists.

Every test runs against both builds (docs/development.md §7): the pure-Python ``_refbook_py`` and
the compiled ``_refbook_c``. The compiled parameter skips when the extension is not built, unless
``TEMOTO_REQUIRE_EXTENSIONS=1`` (then it fails). A Hypothesis test drives each build and a
dict-based model with the same random operations and compares every result and exception.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from types import ModuleType
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from temoto.core import _fast
from temoto.core.registrar import LoadContext, Registrar, ResourceServer
from temoto.errors import ResourceLoadError

PURE = "temoto.core._fast._refbook_py"
COMPILED = "temoto.core._fast._refbook_c"


@pytest.fixture(scope="session")
def impl(refbook_impl: ModuleType) -> ModuleType:
    """The book, once per build (the ``refbook_impl`` fixture of tests/conftest.py)."""
    return refbook_impl


# ----------------------------------------------------------------------------------- semantics


def test_slots_are_dense_and_reused_last_freed_first(impl: ModuleType) -> None:
    book = impl.RefBook()
    assert [book.new_resource() for _ in range(4)] == [0, 1, 2, 3]
    book.free_resource(1)
    book.free_resource(3)
    assert book.live_resources() == 2
    assert [book.new_resource(), book.new_resource(), book.new_resource()] == [3, 1, 4]
    a = book.add_ref(0, -1)
    b = book.add_ref(0, -1)
    assert (a, b) == (0, 1)
    book.release(a)
    assert book.add_ref(2, -1) == a
    assert book.live_refs() == 2


def test_counts_and_the_last_release(impl: ModuleType) -> None:
    book = impl.RefBook()
    res = book.new_resource()
    assert book.count(res) == 0
    refs = [book.add_ref(res, -1) for _ in range(3)]
    assert book.count(res) == 3
    assert [book.resource_of(r) for r in refs] == [res] * 3
    assert [book.holder_of(r) for r in refs] == [-1] * 3
    assert book.release(refs[1]) == 2
    assert book.release(refs[0]) == 1
    assert book.release(refs[2]) == 0
    assert book.count(res) == 0
    book.free_resource(res)
    assert (book.live_resources(), book.live_refs()) == (0, 0)


def test_dependencies_in_acquisition_order_and_unlinked_on_release(impl: ModuleType) -> None:
    book = impl.RefBook()
    top, a, b, c = (book.new_resource() for _ in range(4))
    deps = [book.add_ref(x, top) for x in (a, b, c, a)]
    consumer = book.add_ref(top, -1)
    assert book.dependencies(top) == deps
    assert book.dependencies(a) == []
    assert [book.holder_of(d) for d in deps] == [top] * 4
    assert book.count(a) == 2
    assert book.release(deps[1]) == 0  # the middle one
    assert book.dependencies(top) == [deps[0], deps[2], deps[3]]
    book.release(deps[0])  # the head
    book.release(deps[3])  # the tail
    assert book.dependencies(top) == [deps[2]]
    again = book.add_ref(b, top)  # appended after the survivor
    assert book.dependencies(top) == [deps[2], again]
    assert book.release(consumer) == 0
    for d in reversed(book.dependencies(top)):
        book.release(d)
    assert book.dependencies(top) == []
    for res in (top, a, b, c):
        book.free_resource(res)


def test_detach_takes_a_reference_off_its_holders_list_but_keeps_it_counted(
    impl: ModuleType,
) -> None:
    book = impl.RefBook()
    holder, res = book.new_resource(), book.new_resource()
    one, two = book.add_ref(res, holder), book.add_ref(res, holder)
    book.detach(one)
    assert book.dependencies(holder) == [two]
    assert (book.holder_of(one), book.count(res)) == (-1, 2)
    book.detach(one)  # already detached: nothing to do
    book.detach(two)
    book.free_resource(holder)  # no dependencies left
    assert book.release(one) == 1
    assert book.release(two) == 0


def test_a_resource_may_hold_a_reference_to_itself(impl: ModuleType) -> None:
    book = impl.RefBook()
    res = book.new_resource()
    ref = book.add_ref(res, res)
    assert (book.dependencies(res), book.count(res)) == ([ref], 1)
    assert book.release(ref) == 0
    book.free_resource(res)


def test_arrays_grow_and_keep_their_contents(impl: ModuleType) -> None:
    book = impl.RefBook()
    resources = [book.new_resource() for _ in range(1000)]
    held: dict[int, list[int]] = {r: [] for r in resources[:50]}
    for i in range(5000):
        res = resources[(i * 7) % 1000]
        holder = resources[i % 50]
        if holder != res:
            held[holder].append(book.add_ref(res, holder))
    for holder, refs in held.items():
        assert book.dependencies(holder) == refs
    assert book.live_refs() == sum(len(r) for r in held.values())
    for refs in held.values():
        for ref in reversed(refs):
            book.release(ref)
    assert all(book.count(r) == 0 for r in resources)


@pytest.mark.parametrize("bad", [-1, -2, 0, 5, 10**6])
def test_unknown_or_free_reference_slots_raise_key_error(impl: ModuleType, bad: int) -> None:
    book = impl.RefBook()
    res = book.new_resource()
    book.release(book.add_ref(res, -1))  # slot 0 is free again
    for method in (book.release, book.detach, book.resource_of, book.holder_of):
        with pytest.raises(KeyError, match=f"no live reference slot {bad}"):
            method(bad)


@pytest.mark.parametrize("bad", [-1, -2, 1, 5, 10**6])
def test_unknown_or_free_resource_slots_raise_key_error(impl: ModuleType, bad: int) -> None:
    book = impl.RefBook()
    live = book.new_resource()
    book.free_resource(book.new_resource())  # slot 1 is free again
    for method in (book.count, book.dependencies, book.free_resource):
        with pytest.raises(KeyError, match=f"no live resource slot {bad}"):
            method(bad)
    with pytest.raises(KeyError, match=f"no live resource slot {bad}"):
        book.add_ref(bad, -1)
    if bad != -1:  # -1 is "no holder"
        with pytest.raises(KeyError, match=f"no live resource slot {bad}"):
            book.add_ref(live, bad)
    assert (book.live_resources(), book.live_refs()) == (1, 0)  # nothing changed


def test_double_release_raises_and_changes_nothing(impl: ModuleType) -> None:
    book = impl.RefBook()
    res = book.new_resource()
    keep, ref = book.add_ref(res, -1), book.add_ref(res, -1)
    assert book.release(ref) == 1
    with pytest.raises(KeyError, match=f"no live reference slot {ref}"):
        book.release(ref)
    assert book.count(res) == 1
    assert book.release(keep) == 0


def test_freeing_a_resource_in_use_raises_value_error(impl: ModuleType) -> None:
    book = impl.RefBook()
    holder, res = book.new_resource(), book.new_resource()
    ref = book.add_ref(res, holder)
    with pytest.raises(ValueError, match=rf"resource slot {res} still has 1 reference\(s\)"):
        book.free_resource(res)
    with pytest.raises(ValueError, match=f"resource slot {holder} still holds dependencies"):
        book.free_resource(holder)
    book.release(ref)
    book.free_resource(holder)
    book.free_resource(res)


def test_compiled_refbook_is_a_cdef_class_with_typed_attributes(impl: ModuleType) -> None:
    if impl.__name__ == PURE:
        pytest.skip("a property of the compiled build")
    compiled = impl
    assert compiled.__file__ is not None
    assert not compiled.__file__.endswith(".py")
    book = compiled.RefBook()
    assert not hasattr(book, "__dict__")
    with pytest.raises(AttributeError):
        book.undeclared = 1
    with pytest.raises(AttributeError):
        _ = book._rs  # a typed memoryview (cdef attribute), invisible from Python
    if not os.environ.get("TEMOTO_NO_EXTENSIONS"):
        assert _fast.RefBook is compiled.RefBook  # the selector prefers the compiled build


# ------------------------------------------------------------------------------ property test


@dataclass
class Model:
    """The RefBook's contract with dicts and lists (slots handed out the same way)."""

    counts: dict[int, int] = field(default_factory=dict)
    deps: dict[int, list[int]] = field(default_factory=dict)
    refs: dict[int, tuple[int, int]] = field(default_factory=dict)  # ref -> (res, holder)
    free_res: list[int] = field(default_factory=list)
    free_refs: list[int] = field(default_factory=list)
    used_res: int = 0
    used_refs: int = 0

    def _res(self, res: int) -> int:
        if res not in self.counts:
            raise KeyError(f"no live resource slot {res}")
        return self.counts[res]

    def _ref(self, ref: int) -> tuple[int, int]:
        if ref not in self.refs:
            raise KeyError(f"no live reference slot {ref}")
        return self.refs[ref]

    def new_resource(self) -> int:
        if self.free_res:
            res = self.free_res.pop()
        else:
            res, self.used_res = self.used_res, self.used_res + 1
        self.counts[res] = 0
        self.deps[res] = []
        return res

    def free_resource(self, res: int) -> None:
        count = self._res(res)
        if count:
            raise ValueError(f"resource slot {res} still has {count} reference(s)")
        if self.deps[res]:
            raise ValueError(f"resource slot {res} still holds dependencies")
        del self.counts[res], self.deps[res]
        self.free_res.append(res)

    def add_ref(self, res: int, holder: int) -> int:
        self._res(res)
        if holder != -1:
            self._res(holder)
        if self.free_refs:
            ref = self.free_refs.pop()
        else:
            ref, self.used_refs = self.used_refs, self.used_refs + 1
        self.refs[ref] = (res, holder)
        self.counts[res] += 1
        if holder != -1:
            self.deps[holder].append(ref)
        return ref

    def detach(self, ref: int) -> None:
        res, holder = self._ref(ref)
        if holder != -1:
            self.deps[holder].remove(ref)
            self.refs[ref] = (res, -1)

    def release(self, ref: int) -> int:
        self.detach(ref)
        res, _ = self.refs.pop(ref)
        self.free_refs.append(ref)
        self.counts[res] -= 1
        return self.counts[res]

    def count(self, res: int) -> int:
        return self._res(res)

    def dependencies(self, res: int) -> list[int]:
        self._res(res)
        return list(self.deps[res])

    def resource_of(self, ref: int) -> int:
        return self._ref(ref)[0]

    def holder_of(self, ref: int) -> int:
        return self._ref(ref)[1]

    def live_resources(self) -> int:
        return len(self.counts)

    def live_refs(self) -> int:
        return len(self.refs)


RES_OPS = ("free_resource", "count", "dependencies")
REF_OPS = ("release", "detach", "resource_of", "holder_of")
# An argument picks a live slot (mostly), one of the three most recently allocated live slots
# (so that a fresh resource gets dependencies and is freed again), any slot handed out so far
# (freed ones included, and one past the last), or a raw value; a holder may also be -1 (none).
KINDS = ["live"] * 5 + ["recent"] * 4 + ["any"] * 2 + ["raw"]
arg = st.tuples(st.sampled_from(KINDS), st.integers(0, 10**6))
holder_arg = st.one_of(arg, st.just(("none", -1)))
ops = st.lists(
    st.one_of(
        st.tuples(st.just("new_resource")),
        st.tuples(st.just("add_ref"), arg, holder_arg),
        st.tuples(st.just("add_ref"), arg, holder_arg),
        st.tuples(st.sampled_from(REF_OPS), arg),
        st.tuples(st.sampled_from(RES_OPS), arg),
    ),
    min_size=10,
    max_size=200,
)
RAW = (-2, -1, 10**6)


def _slot(choice: tuple[str, int], live: list[int], used: int) -> int:
    kind, value = choice
    if kind == "none":
        return -1
    if kind == "raw":
        return RAW[value % len(RAW)]
    if kind == "live" and live:
        return live[value % len(live)]
    if kind == "recent" and live:
        return live[-1 - value % min(3, len(live))]
    return value % (used + 1)


def _outcome(method: Any, *args: int) -> tuple[Any, ...]:
    try:
        return ("ok", method(*args))
    except (KeyError, ValueError) as err:
        return (type(err).__name__, str(err))


def _args(model: Model, name: str, choices: list[tuple[str, int]]) -> list[int]:
    resources = list(model.counts)  # allocation order
    if name == "new_resource":
        return []
    if name == "add_ref":
        return [_slot(c, resources, model.used_res) for c in choices]
    if name in RES_OPS:
        return [_slot(choices[0], resources, model.used_res)]
    return [_slot(choices[0], list(model.refs), model.used_refs)]


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(prefill=st.integers(0, 40), program=ops)
def test_random_operations_match_the_model(
    impl: ModuleType, prefill: int, program: list[tuple[Any, ...]]
) -> None:
    book = impl.RefBook()
    model = Model()
    # Start from a populated book (past the first growth of the arrays): resource i holds a
    # reference to resource 2i+1 and 2i+2 (a binary tree), and each has one consumer.
    start: list[tuple[Any, ...]] = [("new_resource",)] * prefill
    start += [("add_ref", ("raw", i), ("raw", (i - 1) // 2 if i else -1)) for i in range(prefill)]
    start += [("add_ref", ("raw", i), ("none", -1)) for i in range(prefill)]
    for name, *raw in start:
        args = [value for _, value in raw]
        assert _outcome(getattr(book, name), *args) == _outcome(getattr(model, name), *args)
    for step, (name, *choices) in enumerate(program):
        args = _args(model, name, choices)
        expected = _outcome(getattr(model, name), *args)
        got = _outcome(getattr(book, name), *args)
        assert got == expected, f"step {step}: {name}{tuple(args)}"
        assert (book.live_resources(), book.live_refs()) == (
            model.live_resources(),
            model.live_refs(),
        )
    for res in model.counts:
        assert book.count(res) == model.count(res)
        assert book.dependencies(res) == model.dependencies(res)
    for ref, (res, holder) in model.refs.items():
        assert (book.resource_of(ref), book.holder_of(ref)) == (res, holder)


# ---------------------------------------------------------------------------- in the registrar


@dataclass(frozen=True)
class Req:
    name: str
    subs: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "subs", tuple(self.subs))


@dataclass(frozen=True)
class Resp:
    value: str = ""


class Tree(ResourceServer[Req, Resp]):
    name = "tree"
    request_type = Req
    response_type = Resp

    def __init__(self, registrar: Registrar) -> None:
        self.registrar = registrar

    def on_load(self, request: Req, ctx: LoadContext) -> Resp:
        for sub in request.subs:
            self.registrar.call("tree", Req(sub))
        return Resp(request.name)

    def on_unload(self, request: Req, response: Resp) -> None:
        pass


def test_registrar_book_matches_its_tables_and_empties() -> None:
    reg = Registrar("rb")
    reg.register(Tree(reg))
    a = reg.call("tree", Req("a", ("b", "c")), client="x")
    d = reg.call("tree", Req("d", ("c", "b", "e")), client="y")
    book = reg._ledger.book
    assert (book.live_resources(), book.live_refs()) == (5, 7)
    assert [i.request.name for i in reg.dependencies(d.id)] == ["c", "b", "e"]
    assert [reg.info(r).request.name for r in reg.info(d.resource_id).dependencies] == [
        "c",
        "b",
        "e",
    ]
    assert reg.release(a.id) is True
    assert (book.live_resources(), book.live_refs()) == (4, 4)
    assert reg.release(d.id) is True
    assert reg.resources() == []
    assert (book.live_resources(), book.live_refs()) == (0, 0)
    reg.close()


class ClosesWhileLoading(ResourceServer[Req, Resp]):
    """Takes a dependency, closes the registrar, fails: the rollback cannot release it."""

    name = "closer"
    request_type = Req
    response_type = Resp

    def __init__(self, registrar: Registrar) -> None:
        self.registrar = registrar

    def on_load(self, request: Req, ctx: LoadContext) -> Resp:
        self.registrar.call("tree", Req("inner"))
        self.registrar.close()
        raise RuntimeError("gave up")

    def on_unload(self, request: Req, response: Resp) -> None:
        raise AssertionError("never loaded")


def test_a_forgotten_resource_detaches_the_dependencies_it_could_not_release(
    caplog: pytest.LogCaptureFixture,
) -> None:
    reg = Registrar("rb")
    reg.register(Tree(reg))
    reg.register(ClosesWhileLoading(reg))
    with pytest.raises(ResourceLoadError, match="gave up"):
        reg.call("closer", Req("outer"))
    assert "releasing" in caplog.text  # the rollback logged the failed release
    book = reg._ledger.book
    (inner,) = reg.resources()
    (ref,) = inner.references
    assert (book.live_resources(), book.live_refs()) == (1, 1)
    assert book.holder_of(reg._ledger.refs[ref.id].slot) == -1  # still counted, nobody's dependency
    assert reg.dependencies(inner.id) == []
