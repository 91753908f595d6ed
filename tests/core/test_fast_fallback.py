"""The pure fallback: a missing compiled kernel, and a machine without a C compiler.

A machine without a compiler still gets a working pure install (with a warning);
``TEMOTO_REQUIRE_EXTENSIONS=1`` turns the fallback into an error.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]

# Blocks the compiled evolution kernel, as if its build had failed, then imports the selector.
_BLOCKED = """
import importlib.abc, sys
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name == "temoto.core._fast._evolution_c":
            raise ImportError("blocked by the test")
        return None
sys.meta_path.insert(0, Block())
from temoto.core import _fast
print(_fast.BUILD, _fast.COMPILED, _fast.Evolution.__module__, _fast.RefBook.__module__)
"""


def _python(
    code: str, env: dict[str, str], cwd: Path | None = None
) -> subprocess.CompletedProcess[str]:
    clean = {k: v for k, v in os.environ.items() if not k.startswith("TEMOTO_")}
    return subprocess.run(
        [sys.executable, "-c", code],
        env={**clean, **env},
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_a_missing_kernel_falls_back_to_the_pure_build_with_a_warning() -> None:
    proc = _python(_BLOCKED, {})
    assert proc.returncode == 0, proc.stderr
    # all kernels pure together, never a mix
    assert proc.stdout.split() == [
        "pure",
        "False",
        "temoto.core._fast._evolution_py",
        "temoto.core._fast._refbook_py",
    ]
    assert "compiled kernels not available" in proc.stderr
    assert "blocked by the test" in proc.stderr


def test_required_extensions_turn_the_fallback_into_an_import_error() -> None:
    proc = _python(_BLOCKED, {"TEMOTO_REQUIRE_EXTENSIONS": "1"})
    assert proc.returncode != 0
    assert "ImportError: TEMOTO_REQUIRE_EXTENSIONS is set" in proc.stderr


@pytest.mark.skipif(shutil.which("gcc") is None, reason="needs the toolchain to break it")
def test_a_build_without_a_c_compiler_succeeds_and_runs_pure(tmp_path: Path) -> None:
    try:
        import Cython  # noqa: F401  # the dev extra has it
    except ImportError:
        if os.environ.get("CI"):
            raise  # `make test` installs the dev extra: under CI this test must run
        pytest.skip("Cython is not installed (pip install -e '.[dev]')")
    tree = tmp_path / "src"
    tree.mkdir()
    shutil.copy(REPO / "setup.py", tree / "setup.py")
    shutil.copytree(
        REPO / "temoto",
        tree / "temoto",
        ignore=shutil.ignore_patterns("*.so", "*.c", "__pycache__"),
    )
    # CC and LDSHARED name a compiler that always fails: the build of each extension fails
    proc = subprocess.run(
        [sys.executable, "setup.py", "-q", "build_ext", "--inplace"],
        cwd=tree,
        env={**os.environ, "CC": "false", "LDSHARED": "false", "TEMOTO_NO_EXTENSIONS": ""},
        capture_output=True,
        text=True,
        timeout=300,
    )
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out
    # setuptools warns about each optional extension it could not build, and goes on
    for kernel in ("evolution", "refbook"):
        assert f'building extension "temoto.core._fast._{kernel}_c" failed' in out, out
    assert not list((tree / "temoto" / "core" / "_fast").glob("*.so"))
    code = "import temoto\nfrom temoto.core import _fast\nprint(_fast.BUILD, temoto.__file__)\n"
    run = _python(code, {"PYTHONPATH": str(tree)}, cwd=tree)
    assert run.returncode == 0, run.stderr
    build, where = run.stdout.split()
    assert build == "pure"
    assert where.startswith(str(tree))
    assert "compiled kernels not available" in run.stderr


def test_the_pure_pass_list_names_existing_test_files_outside_core() -> None:
    """``tests/kernel_tests.txt`` (made by ``tools/kernel_tests.py``) names real test files."""
    listed = [
        line
        for line in (REPO / "tests" / "kernel_tests.txt").read_text().splitlines()
        if line and not line.startswith("#")
    ]
    assert listed == sorted(set(listed))
    for path in listed:
        assert (REPO / path).is_file(), f"{path} is listed but gone: run tools/kernel_tests.py"
        assert path.startswith("tests/"), path
        assert not path.startswith("tests/core/"), path


def test_the_pure_pass_keeps_core_and_the_listed_files_only() -> None:
    """``TEMOTO_KERNEL_TESTS_ONLY=1`` deselects a test file that reaches no kernel."""
    clean = {k: v for k, v in os.environ.items() if k != "TEMOTO_KERNEL_TESTS_ONLY"}
    args = [sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider"]
    files = ["tests/test_clock.py", "tests/core/test_states.py"]

    def collected(only: str) -> list[str]:
        done = subprocess.run(
            [*args, *files],
            env={**clean, "TEMOTO_KERNEL_TESTS_ONLY": only},
            cwd=REPO,
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert done.returncode == 0, done.stdout + done.stderr
        return sorted({line.split("::")[0] for line in done.stdout.splitlines() if "::" in line})

    assert collected("0") == sorted(files)
    assert collected("1") == ["tests/core/test_states.py"]
