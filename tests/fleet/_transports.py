"""The two fleet transports for the process tests, and a `temoto router` for the Zenoh one.

Every process test runs in a network namespace of its own (``unshare -n``), so both URLs are
fixed: LCM multicast on loopback, or Zenoh clients of a router on ``127.0.0.1:7447`` that the
test's runner starts in the namespace first (:data:`ROUTER_CODE`, :func:`start_router`).
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

LCM_URL = "udpm://239.255.76.67:7667?ttl=0"
ROUTER_ENDPOINT = "tcp/127.0.0.1:7447"
ZENOH_URL = f"zenoh:{ROUTER_ENDPOINT}"

needs_zenoh = pytest.mark.skipif(
    importlib.util.find_spec("zenoh") is None, reason="the zenoh extra is not installed"
)

#: Parameters of a test that runs over both transports (ids ``lcm`` and ``zenoh``).
TRANSPORTS = [
    pytest.param(LCM_URL, id="lcm"),
    pytest.param(ZENOH_URL, id="zenoh", marks=needs_zenoh),
]

#: Python source defining ``start_router(url)`` and ``stop_router(router)`` for a runner script
#: run as ``python -c``: for a ``zenoh:`` URL, ``temoto router`` on its endpoint, announced
#: before ``start_router`` returns; nothing for LCM.
ROUTER_CODE = (Path(__file__).resolve().parent / "_router.py").read_text()

__all__ = ["LCM_URL", "ROUTER_CODE", "TRANSPORTS", "ZENOH_URL", "needs_zenoh"]
