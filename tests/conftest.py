"""Suite-wide fixtures: autouse leak checks that every test gets; the pure pass's selection."""

from __future__ import annotations

import importlib
import os
import signal
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

import pytest

from temoto.testing.reaper import Reaper

# A suite started as a background job of a shell without job control inherits SIGINT ignored
# (POSIX), and so would every command a test starts: Ctrl-C tests then see nothing. The
# suite's own process takes the default handler back, so its children start with SIGINT's
# default action, as under a terminal or CI.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

#: What marks every process this run starts (temoto.testing.reaper ends them if the run is killed).
RUN_MARK = "TEMOTO_TEST_RUN"

THREAD_PREFIX = "temoto-"
#: The test files outside ``tests/core/`` that reach a kernel (``tools/kernel_tests.py``).
KERNEL_TESTS = Path(__file__).with_name("kernel_tests.txt")
THREAD_GRACE_S = 2.0


@pytest.fixture(autouse=True)
def no_leaked_temoto_threads() -> Iterator[None]:
    """Fail a test that leaves a ``temoto-*`` thread running.

    Owners join their threads in ``shutdown()``; a thread that is still alive after the test
    (and a grace period for threads that are already winding down) is a leak.
    """
    before = set(threading.enumerate())
    yield
    leftovers = [
        t for t in threading.enumerate() if t not in before and t.name.startswith(THREAD_PREFIX)
    ]
    deadline = time.monotonic() + THREAD_GRACE_S
    for thread in leftovers:
        thread.join(timeout=max(0.0, deadline - time.monotonic()))
    leaked = sorted(t.name for t in leftovers if t.is_alive())
    if leaked:
        pytest.fail(
            f"test leaked {len(leaked)} thread(s) still alive {THREAD_GRACE_S:g} s after it "
            f"ended: {', '.join(leaked)}",
            pytrace=False,
        )


def fast_kernel(kernel: str, build: str) -> ModuleType:
    """Import one build of a ``temoto.core._fast`` kernel, for tests that compare the two.

    The compiled build is skipped when it is not installed, unless
    ``TEMOTO_REQUIRE_EXTENSIONS=1`` (as in CI), in which case its absence fails the test.

    Args:
        kernel: ``"evolution"`` or ``"refbook"``.
        build: ``"py"`` (the pure-Python source) or ``"c"`` (the Cython extension).

    Returns:
        The module.
    """
    name = f"temoto.core._fast._{kernel}_{build}"
    try:
        return importlib.import_module(name)
    except ImportError as err:
        if build == "py" or os.environ.get("TEMOTO_REQUIRE_EXTENSIONS") == "1":
            raise
        pytest.skip(f"compiled build not installed ({err})")


#: Parameters for a fixture over both builds; the compiled one carries the ``compiled`` marker.
BUILDS = [
    pytest.param("py", id="pure"),
    pytest.param("c", id="compiled", marks=pytest.mark.compiled),
]


@pytest.fixture(scope="session", params=BUILDS)
def evolution_impl(request: pytest.FixtureRequest) -> ModuleType:
    """The evolution kernel, once per build (pure, compiled)."""
    return fast_kernel("evolution", request.param)


@pytest.fixture(scope="session", params=BUILDS)
def refbook_impl(request: pytest.FixtureRequest) -> ModuleType:
    """The registrar's reference book, once per build (pure, compiled)."""
    return fast_kernel("refbook", request.param)


def kernel_test_files() -> set[str]:
    """The test files outside ``tests/core/`` listed in ``tests/kernel_tests.txt``."""
    lines = KERNEL_TESTS.read_text(encoding="utf-8").splitlines()
    return {line.strip() for line in lines if line.strip() and not line.startswith("#")}


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """With ``TEMOTO_KERNEL_TESTS_ONLY=1``, keep only the tests that reach a compiled kernel.

    The Makefile's pure-Python pass sets it: the other tests run the same code in both builds,
    and the compiled pass ran them already. Kept: everything under ``tests/core/`` and the files
    of ``tests/kernel_tests.txt``.
    """
    if os.environ.get("TEMOTO_KERNEL_TESTS_ONLY") != "1":
        return
    files = kernel_test_files()
    keep, drop = [], []
    for item in items:
        path = item.nodeid.split("::", 1)[0]
        (keep if path.startswith("tests/core/") or path in files else drop).append(item)
    if drop:
        config.hook.pytest_deselected(items=drop)
        items[:] = keep


def pytest_configure(config: pytest.Config) -> None:
    """Mark what this run starts; if the run is killed, a watcher ends what it left behind."""
    if os.environ.get(RUN_MARK) is None:  # a suite run by a test of this suite has its own owner
        config.stash[_REAPER] = Reaper(RUN_MARK, f"{os.getpid()}-{time.time_ns()}")


def pytest_unconfigure(config: pytest.Config) -> None:
    """The run ends normally: the watcher goes, having killed nothing."""
    reaper = config.stash.get(_REAPER, None)
    if reaper is not None:
        reaper.close()


_REAPER = pytest.StashKey[Reaper]()
