"""The main job, exactly as ``make run`` starts it, ends on_true at its default realism."""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def run_command() -> list[str]:
    """The Makefile's ``RUN_CMD``, with the venv's python replaced by this interpreter."""
    text = (ROOT / "Makefile").read_text(encoding="utf-8")
    found = re.search(r"^RUN_CMD = (.*?)(?<!\\)\n", text, re.M | re.S)
    assert found, "the Makefile defines no RUN_CMD"
    words = shlex.split(found.group(1).replace("\\\n", " "))
    assert words[0] == "$(BIN)/python", words
    return [sys.executable, *words[1:]]


def test_make_run_s_mission_ends_on_true_at_typical_realism_with_its_seed_printed() -> None:
    command = run_command()
    assert "--realism" not in command  # the default level is the one users see
    proc = subprocess.run(
        command, cwd=ROOT, capture_output=True, text=True, timeout=240, check=False
    )
    seed = re.search(r"^realism typical, seed (\d+)$", proc.stderr, re.M)
    assert seed, proc.stderr  # printed, so that a failure can be replayed with --seed
    assert proc.returncode == 0, f"seed {seed.group(1)}:\n{proc.stdout}\n{proc.stderr}"
    assert "mobile_manipulation: on_true in" in proc.stdout, proc.stdout
    assert "Traceback" not in proc.stderr
