"""What the browser tests here share: a page in headless Chromium, and a registrar's managers.

* :func:`open_page`: ``with open_page(url, live=True) as browser`` opens the page, waits until
  its event stream is connected (``live``), and closes the browser at the block's end (before
  the live view it shows is closed, as an operator's tab would be). Without Chromium the test
  is skipped (fails under ``CI=true``: ``require_chromium``).
* :func:`managers`: a registrar for the test and the managers added to it, all shut down after
  the test, its references released first.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager
from pathlib import Path
from typing import Any, TypeVar

import pytest
from _cdp import Browser
from test_live_view_browser import require_chromium

from temoto.core.registrar import Registrar

#: The page's event stream is connected.
LIVE = "document.getElementById('conn').textContent === 'live'"

M = TypeVar("M")


@pytest.fixture
def open_page(tmp_path: Path) -> Callable[..., AbstractContextManager[Browser]]:
    """Opens pages in headless Chromium, each closed at the end of its ``with`` block."""
    binary = require_chromium()

    @contextmanager
    def page(url: str, *, live: bool = False) -> Iterator[Browser]:
        browser = Browser(binary, url, tmp_path / "profile", tmp_path / "chromium.log")
        try:
            if live:
                browser.wait_for(LIVE)
            yield browser
        finally:
            browser.close()

    return page


class Managers:
    """A registrar and the managers on it, shut down together.

    Args:
        name: The registrar's name.
    """

    def __init__(self, name: str) -> None:
        self.registrar = Registrar(name)
        self._stops: list[Callable[[], Any]] = []

    def add(self, manager: M, stop: Callable[[], Any] | None = None) -> M:
        """Shut ``manager`` down after the test (``stop``, else its ``shutdown()``), before
        the managers added earlier."""
        self._stops.append(stop if stop is not None else manager.shutdown)  # type: ignore[attr-defined]
        return manager

    def close(self) -> None:
        for ref in self.registrar.references():
            self.registrar.release(ref.id)
        for stop in reversed(self._stops):
            stop()
        self.registrar.close()


@pytest.fixture
def managers(request: pytest.FixtureRequest) -> Iterator[Managers]:
    """A registrar named after the test, with the managers it adds; all closed after it."""
    held = Managers(request.node.name)
    try:
        yield held
    finally:
        held.close()
