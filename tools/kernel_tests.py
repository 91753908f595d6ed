"""Find the test files that reach the compiled kernels, for the pure-Python pass of ``make test``.

Usage::

    python tools/kernel_tests.py            # run the suite on the pure build, rewrite the list
    python tools/kernel_tests.py -- -k foo  # extra pytest arguments after ``--``
    python tools/kernel_tests.py --add -- tests/new_file.py   # measure some files, keep the rest

``make test`` runs the whole suite on the compiled kernels, then a second pass on the pure-Python
kernels (``TEMOTO_NO_EXTENSIONS=1``). The second pass only needs the tests that reach a kernel:
the others run the same Python code in both passes. With ``--add`` only the test paths given
after ``--`` run, and the files found are added to the list (nothing is removed), for new tests
without a whole pass. This tool measures which tests those are:
it runs the suite on the pure build with itself loaded as a pytest plugin, which wraps the
constructors of the pure ``Evolution`` and ``RefBook`` classes and notes every test during
which one was built in the test's process. The files holding such tests are written to
``tests/kernel_tests.txt``, which ``tests/conftest.py`` reads when ``TEMOTO_KERNEL_TESTS_ONLY=1``
(the Makefile's pure pass). Everything under ``tests/core/`` runs in that pass whatever the list
says. Run the tool again after adding tests that use the engine or the registrar outside
``tests/core/``; it takes as long as one pass of the suite (about 15 minutes on 2 cores).

Exit status: pytest's, when it failed; otherwise 0.
"""

from __future__ import annotations

import functools
import json
import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parent.parent
LIST = ROOT / "tests" / "kernel_tests.txt"
HEADER = """\
# Test files whose tests build an evolution or reference-book kernel in the test process
# (measured by tools/kernel_tests.py on the pure build; do not edit by hand). The pure-Python
# pass of `make test` runs these and everything under tests/core/.
"""
_HITS_ENV = "TEMOTO_KERNEL_TESTS_OUT"

_current: list[str] = []
_hits: set[str] = set()


def _noting(init: Callable[..., None]) -> Callable[..., None]:
    """Wrap a kernel constructor so that the running test's file is noted."""

    @functools.wraps(init)
    def wrapper(self: object, *args: Any, **kwargs: Any) -> None:
        if _current:
            _hits.add(_current[0])
        init(self, *args, **kwargs)

    return wrapper


def pytest_configure(config: object) -> None:
    """Wrap the pure kernels' constructors (the plugin half of this tool)."""
    import temoto.core._fast as fast
    from temoto.core._fast import _evolution_py, _refbook_py

    if fast.COMPILED:
        raise RuntimeError("kernel_tests needs the pure build: set TEMOTO_NO_EXTENSIONS=1")
    for cls in (_evolution_py.Evolution, _refbook_py.RefBook):
        cls.__init__ = _noting(cls.__init__)  # type: ignore[method-assign]


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item: Any) -> None:
    """Remember which test file is running."""
    _current[:] = [item.nodeid.split("::", 1)[0]]


def pytest_unconfigure(config: object) -> None:
    """Hand the files noted to the tool's process."""
    out = os.environ.get(_HITS_ENV)
    if out:
        Path(out).write_text(json.dumps(sorted(_hits)), encoding="utf-8")


def main(argv: list[str]) -> int:
    """Run the suite with this plugin and rewrite ``tests/kernel_tests.txt``."""
    extra = argv[argv.index("--") + 1 :] if "--" in argv else []
    out = ROOT / ".kernel_tests.json"
    env = dict(os.environ, TEMOTO_NO_EXTENSIONS="1", **{_HITS_ENV: str(out)})
    env["PYTHONPATH"] = os.pathsep.join(
        p for p in (str(ROOT / "tools"), str(ROOT), env.get("PYTHONPATH", "")) if p
    )
    print("kernel_tests: running the suite on the pure build (one pass, ~15 min)", flush=True)
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "kernel_tests", *extra]
    code = subprocess.call(cmd, cwd=ROOT, env=env)
    if not out.exists():
        print("kernel_tests: pytest wrote no result; the list is unchanged", file=sys.stderr)
        return code or 1
    files = [f for f in json.loads(out.read_text(encoding="utf-8")) if f.startswith("tests/")]
    out.unlink()
    outside = sorted(f for f in files if not f.startswith("tests/core/"))
    if "--add" in argv[: argv.index("--") if "--" in argv else len(argv)]:
        kept = [
            line.strip()
            for line in LIST.read_text(encoding="utf-8").splitlines()
            if line.strip() and not line.startswith("#")
        ]
        outside = sorted({*kept, *outside})
    LIST.write_text(HEADER + "".join(f"{f}\n" for f in outside), encoding="utf-8")
    print(f"kernel_tests: {len(files)} files reach a kernel, {len(outside)} outside tests/core/")
    print(f"kernel_tests: wrote {LIST.relative_to(ROOT)}")
    return code


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
