"""External tools a test drives (MAVProxy, socat, ...): found, or the test skips — or fails in CI.

`make test` installs every tool the suite drives (the Python ones through the ``dev`` extra,
the system ones through the Makefile's ``sysdeps``), so under CI (``CI=true``) a missing tool is
a broken set-up and the test fails, naming what is missing; on a developer's machine the test
skips with the same message. Use it at the top of a test or in a fixture::

    mavproxy = require_tool("mavproxy.py", hint="pip install MAVProxy")

Importing this module does not import pytest; :func:`require_tool` does when it must skip or
fail.
"""

from __future__ import annotations

import os
import shutil
import sys
from pathlib import Path
from typing import NoReturn

__all__ = ["find_tool", "in_ci", "missing_tool", "require_tool"]


def in_ci() -> bool:
    """Whether the suite runs under CI (``CI`` set to ``true`` or ``1``)."""
    return os.environ.get("CI", "").lower() in ("true", "1")


def find_tool(name: str) -> str | None:
    """The path of a command: next to this interpreter first (a venv's scripts), then ``PATH``.

    Args:
        name: The command's name (``mavproxy.py``, ``socat``).

    Returns:
        Its path, or None when it is nowhere.
    """
    local = Path(sys.executable).with_name(name)
    if local.is_file() and os.access(local, os.X_OK):
        return str(local)
    return shutil.which(name, path=os.environ.get("PATH", "") + ":/usr/sbin:/sbin")


def missing_tool(message: str) -> NoReturn:
    """Skip the running test with ``message``, or fail it under CI.

    Args:
        message: What is missing and how to get it.
    """
    import pytest  # here: only tests reach this

    if in_ci():
        pytest.fail(f"CI: {message}", pytrace=False)
    pytest.skip(message)


def require_tool(name: str, *, hint: str) -> str:
    """The path of a command a test needs; skip the test without it (fail it under CI).

    Args:
        name: The command's name.
        hint: How to install it (``pip install MAVProxy``, ``apt-get install socat``).

    Returns:
        The command's path.
    """
    path = find_tool(name)
    if path is None:
        missing_tool(f"needs {name} ({hint}; `make test` installs it)")
    return path
