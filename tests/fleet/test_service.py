"""ServiceCore (what the parts of a fleet service share) and the shape of temoto.fleet."""

from __future__ import annotations

import ast
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

import temoto.fleet
from temoto.clock import ManualClock, MonotonicClock
from temoto.errors import TransportError
from temoto.fleet import common
from temoto.fleet.service import ServiceCore
from temoto.lcm_types import ris_request_t
from temoto.transport import FleetAuth, FleetLink, InProcessTransport, Opened, codec

KEY = bytes(range(32))
COUNTERS = ("sent", "send_errors", "decode_errors", "unexpected")


@pytest.fixture
def link(request: pytest.FixtureRequest) -> Iterator[FleetLink]:
    with InProcessTransport(f"service-{request.node.name}") as transport:
        yield FleetLink(transport, FleetAuth("fleet", "A", KEY))


def ask() -> Any:
    msg = common.new(ris_request_t)
    msg.requester, msg.manager = "A", ""
    return msg


def test_send_counts_what_was_sent_and_what_failed(link: FleetLink) -> None:
    core = ServiceCore(link, COUNTERS)
    core.send("TEST", ask(), "sent")
    assert core.stats() == {"sent": 1, "send_errors": 0, "decode_errors": 0, "unexpected": 0}
    link.transport.close()
    with pytest.raises(TransportError):
        core.send("TEST", ask(), "sent")
    assert core.stats()["send_errors"] == 1
    assert core.stats()["sent"] == 1


def test_decode_counts_what_it_drops(link: FleetLink) -> None:
    core = ServiceCore(link, COUNTERS)
    name, payload = codec.encode(ask())
    opened = Opened("TEST", "B", name, payload, 1, 0)
    assert core.decode(opened, ("ris_request_t",)).requester == "A"
    assert core.decode(opened, ("ris_advert_t",)) is None
    assert core.decode(Opened("TEST", "B", name, b"garbage", 2, 0), ("ris_request_t",)) is None
    assert core.stats() == {"sent": 0, "send_errors": 0, "decode_errors": 1, "unexpected": 1}


def test_stats_is_a_copy_and_count_needs_a_known_name(link: FleetLink) -> None:
    core = ServiceCore(link, COUNTERS)
    with core.lock:
        core.count("unexpected", 3)
    stats = core.stats()
    stats["unexpected"] = 0
    assert core.stats()["unexpected"] == 3
    with core.lock, pytest.raises(KeyError):
        core.count("nonsense")


def test_time_and_waits_are_the_clocks(link: FleetLink) -> None:
    assert isinstance(ServiceCore(link, COUNTERS).clock, MonotonicClock)
    clock = ManualClock(start=5.0, epoch=1_000.0)
    core = ServiceCore(link, COUNTERS, clock)
    assert (core.now(), core.wall()) == (5.0, 1_000.0)
    cond = core.condition()
    woke = threading.Event()

    def waiter() -> None:
        with cond:
            core.wait(cond, 10.0)  # ten seconds of the clock, however long in real time
        woke.set()

    thread = threading.Thread(target=waiter, name="test-waiter")
    thread.start()
    assert not woke.wait(0.3)
    while not woke.is_set():  # the waiter may not be waiting yet: advance until it wakes
        clock.advance(10.0)
        woke.wait(0.05)
    thread.join()


def test_a_function_is_refused_as_a_clock_with_a_hint(link: FleetLink) -> None:
    with pytest.raises(TypeError, match=r"a function is no longer accepted.*MonotonicClock"):
        ServiceCore(link, COUNTERS, time.monotonic)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match=r"temoto\.clock\.Clock, got 3$"):
        common.check_clock("clock", 3)


# --- the shape of the package --------------------------------------------------------------

FLEET = Path(temoto.fleet.__file__).parent


def _fleet_imports(path: Path) -> set[str]:
    """The temoto.fleet modules a module imports, at run time or for type checking."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("temoto.fleet."):
            found.add(node.module or "")
    return found


def test_no_import_circles_in_the_fleet_package() -> None:
    graph = {f"temoto.fleet.{p.stem}": _fleet_imports(p) for p in FLEET.glob("*.py")}
    done: set[str] = set()

    def visit(module: str, path: tuple[str, ...]) -> None:
        assert module not in path, "import circle: " + " -> ".join((*path, module))
        if module in done:
            return
        for dep in sorted(graph.get(module, ())):
            visit(dep, (*path, module))
        done.add(module)

    for module in sorted(graph):
        visit(module, ())


def test_every_fleet_module_says_what_it_is() -> None:
    paths = [
        *FLEET.glob("*.py"),
        FLEET.parent / "cli" / "fleet.py",
        FLEET.parent / "cli" / "signals.py",
    ]
    for path in paths:
        text = path.read_text()
        assert ast.get_docstring(ast.parse(text)), f"{path.name} has no docstring"
