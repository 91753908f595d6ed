from __future__ import annotations

from collections.abc import Iterator

import pytest

from temoto.testing import ProcessLeakCheck


@pytest.fixture(autouse=True)
def no_leaked_processes(monkeypatch: pytest.MonkeyPatch) -> Iterator[ProcessLeakCheck]:
    """Every process a test here starts must be gone when it ends (stragglers are killed)."""
    check = ProcessLeakCheck()
    monkeypatch.setenv(check.variable, check.mark)
    yield check
    leaked = check.kill_leftovers()
    if leaked:
        pytest.fail(f"test left processes running: {leaked}", pytrace=False)
