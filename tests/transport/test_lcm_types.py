"""The generated LCM types are up to date with their .lcm sources (tools/gen_lcm_types.py)."""

from __future__ import annotations

import importlib.util
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
TOOL = ROOT / "tools" / "gen_lcm_types.py"
PACKAGE = Path("temoto") / "lcm_types"
GENERATED = ROOT / PACKAGE


def run_tool(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, str(TOOL), *args],
        capture_output=True,
        text=True,
        timeout=30,
        check=False,
    )


@pytest.fixture
def tree(tmp_path: Path) -> Path:
    """A copy of the generated package (sources included) and the tool."""
    shutil.copytree(GENERATED, tmp_path / PACKAGE, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copytree(
        ROOT / "tools", tmp_path / "tools", ignore=shutil.ignore_patterns("__pycache__")
    )
    return tmp_path


def test_every_definition_is_generated_and_one_struct_per_file() -> None:
    sources = {path.stem for path in (GENERATED / "defs").glob("*.lcm")}
    modules = {path.stem for path in GENERATED.glob("*.py")} - {"__init__"}
    assert sources == modules
    for stem in sources:
        text = (GENERATED / "defs" / f"{stem}.lcm").read_text(encoding="utf-8")
        assert "package temoto.lcm_types;" in text
        assert text.count("struct ") == 1
        assert f"struct {stem}\n" in text


def test_check_passes_on_the_committed_tree() -> None:
    proc = run_tool("--check")
    assert proc.returncode == 0, proc.stderr


def test_check_passes_on_a_copy(tree: Path) -> None:
    proc = run_tool("--check", "--root", str(tree))
    assert proc.returncode == 0, proc.stderr


def test_check_fails_after_a_generated_file_is_modified(tree: Path) -> None:
    target = tree / PACKAGE / "handshake_t.py"
    target.write_text(target.read_text(encoding="utf-8") + "# edited\n", encoding="utf-8")
    proc = run_tool("--check", "--root", str(tree))
    assert proc.returncode == 1
    assert "changed: temoto/lcm_types/handshake_t.py" in proc.stderr
    assert "+# edited" not in proc.stderr
    assert "-# edited" in proc.stderr
    # Regenerating repairs it, and --check passes again.
    assert run_tool("--root", str(tree)).returncode == 0
    assert target.read_bytes() == (GENERATED / "handshake_t.py").read_bytes()
    assert run_tool("--check", "--root", str(tree)).returncode == 0


def test_check_fails_on_a_missing_or_extra_file_and_regeneration_fixes_both(tree: Path) -> None:
    package = tree / PACKAGE
    (package / "action_ack_t.py").unlink()
    (package / "defs" / "ris_withdraw_t.lcm").unlink()
    proc = run_tool("--check", "--root", str(tree))
    assert proc.returncode == 1
    assert "missing: temoto/lcm_types/action_ack_t.py" in proc.stderr
    assert "extra:   temoto/lcm_types/ris_withdraw_t.py" in proc.stderr
    assert "changed: temoto/lcm_types/__init__.py" in proc.stderr
    proc = run_tool("--root", str(tree))
    assert proc.returncode == 0, proc.stderr
    assert (package / "action_ack_t.py").is_file()
    assert not (package / "ris_withdraw_t.py").exists()
    assert "ris_withdraw_t" not in (package / "__init__.py").read_text(encoding="utf-8")
    assert run_tool("--check", "--root", str(tree)).returncode == 0


def test_regeneration_writes_only_inside_the_generated_package(tree: Path) -> None:
    (tree / "temoto" / "__init__.py").write_text("# hand-written\n", encoding="utf-8")
    (tree / PACKAGE / "graph_command_t.py").unlink()
    assert run_tool("--root", str(tree)).returncode == 0
    assert (tree / "temoto" / "__init__.py").read_text(encoding="utf-8") == "# hand-written\n"
    files = {p.relative_to(tree).as_posix() for p in tree.rglob("*") if p.is_file()}
    assert all(
        f.startswith(("temoto/lcm_types/", "tools/")) or f == "temoto/__init__.py" for f in files
    )


def test_hand_written_files_in_the_package_are_refused(tree: Path) -> None:
    (tree / PACKAGE / "helpers.py").write_text("def f():\n    pass\n", encoding="utf-8")
    proc = run_tool("--root", str(tree))
    assert proc.returncode == 2
    assert "helpers.py" in proc.stderr
    assert "lcm-gen did not write" in proc.stderr
    assert (tree / PACKAGE / "helpers.py").exists()


def test_missing_sources_are_an_error(tree: Path) -> None:
    shutil.rmtree(tree / PACKAGE / "defs")
    proc = run_tool("--check", "--root", str(tree))
    assert proc.returncode == 2
    assert "no .lcm files" in proc.stderr


def test_a_missing_lcm_gen_is_reported_clearly(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    spec = importlib.util.spec_from_file_location("gen_lcm_types", TOOL)
    assert spec is not None
    assert spec.loader is not None
    tool = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, "gen_lcm_types", tool)  # dataclasses look their module up
    spec.loader.exec_module(tool)
    monkeypatch.setattr(sys, "executable", str(tmp_path / "python"))
    monkeypatch.setenv("PATH", str(tmp_path))
    assert tool.main(["--check"]) == 2
    assert "lcm-gen not found" in capsys.readouterr().err


def test_check_ignores_only_the_lcm_gen_version_line(tree: Path) -> None:
    init = tree / PACKAGE / "__init__.py"
    text = re.sub(r"(?m)^lcm-gen \S+$", "lcm-gen 1.5.99", init.read_text(encoding="utf-8"))
    init.write_text(text, encoding="utf-8")
    assert run_tool("--check", "--root", str(tree)).returncode == 0  # same code, other patch
    init.write_text(text + "# edited by hand\n", encoding="utf-8")
    proc = run_tool("--check", "--root", str(tree))
    assert proc.returncode == 1
    assert "the committed files come from lcm-gen 1.5.99" in proc.stderr
