"""Importing any temoto module works, warns about nothing and has no side effects.

The rule is in docs/development.md §9.

All modules are imported one by one in a single fresh interpreter run with ``-W error``: a fresh
interpreter, because the test process has already imported most of the package; a single one,
to keep the test fast.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import temoto

# Generated code with its own rules (docs/development.md §8); not walked.
SKIPPED_PACKAGES = ("temoto.lcm_types",)

# Runs in the child. pkgutil.walk_packages cannot prune a subtree (it would import
# temoto.lcm_types to recurse into it) and hides a package's ImportError unless given onerror,
# so the walk is the same iter_modules recursion, done by hand.
_CHILD = """
import importlib, json, pkgutil, sys, threading, traceback

skipped = tuple(sys.argv[2:])
modules, failures = ["temoto"], {}

def walk(package):
    for info in pkgutil.iter_modules(package.__path__, package.__name__ + "."):
        if any(info.name == s or info.name.startswith(s + ".") for s in skipped):
            continue
        modules.append(info.name)
        try:
            module = importlib.import_module(info.name)
        except BaseException:
            failures[info.name] = traceback.format_exc()
        else:
            if info.ispkg:
                walk(module)

try:
    walk(importlib.import_module("temoto"))
except BaseException:
    failures["temoto"] = traceback.format_exc()

result = {
    "file": sys.modules["temoto"].__file__ if "temoto" in sys.modules else None,
    "modules": modules,
    "failures": failures,
    "threads": [t.name for t in threading.enumerate()],
}
with open(sys.argv[1], "w", encoding="utf-8") as f:
    json.dump(result, f)
"""


def test_every_module_imports_cleanly_without_side_effects(tmp_path: Path) -> None:
    result_file = tmp_path / "result.json"
    proc = subprocess.run(
        [sys.executable, "-W", "error", "-c", _CHILD, str(result_file), *SKIPPED_PACKAGES],
        capture_output=True,
        text=True,
        timeout=50,
        check=False,
    )
    assert proc.returncode == 0, f"import walker crashed:\n{proc.stderr}"
    result = json.loads(result_file.read_text(encoding="utf-8"))

    assert result["file"] == temoto.__file__, "the child imported a different temoto"
    problems = [f"{name} failed to import:\n{tb}" for name, tb in result["failures"].items()]
    if result["threads"] != ["MainThread"]:
        problems.append(f"importing started threads: {result['threads']}")
    if proc.stdout or proc.stderr:
        problems.append(f"importing wrote output:\n{proc.stdout}{proc.stderr}")
    assert not problems, f"{len(result['modules'])} modules imported:\n" + "\n".join(problems)


def test_public_names_in_dunder_all_exist() -> None:
    missing = [name for name in temoto.__all__ if not hasattr(temoto, name)]
    assert not missing, f"temoto.__all__ names missing from the package: {missing}"
    assert len(set(temoto.__all__)) == len(temoto.__all__), "temoto.__all__ has duplicates"
