"""Suite-wide fixtures: autouse leak checks that every test gets."""

from __future__ import annotations

import importlib
import os
import threading
import time
from collections.abc import Iterator
from types import ModuleType

import pytest

THREAD_PREFIX = "temoto-"
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
